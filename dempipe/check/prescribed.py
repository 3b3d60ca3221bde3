"""How fast the surfaces of kinematic bodies move: their whole extent, not its centre.

The Model's ``surface_speed`` takes each kinematic body's points out from its motion's
anchor along the line through its centre; a body spinning about its own centre has
its centre on the axis, the line has no direction, and the speed comes out 0 m/s
however fast it spins (``dempipe check`` said "fastest surface 0 m/s" at 1e6 rad/s,
and the bake then stopped). ``surface_speed`` here takes the points at the body's
radius around its centre along each axis as well, so the spin counts; `dempipe check`
and the bake add what the Model left out to the closing speed of the tunnelling check.
"""

from __future__ import annotations

import numpy as np

_AXES = np.concatenate([np.eye(3), -np.eye(3)])


def surface_speed(model) -> tuple[float, int]:
    """(fastest surface speed of a kinematic body over the bake [m/s], that body or -1)."""
    if model.body_motion is None or not model.motions:
        return 0.0, -1
    kin = (np.asarray(model.body_kinematic, bool) if model.body_kinematic is not None
           else np.zeros(model.n_bodies, bool))
    t_end = max(0.0, (model.n_frames - 1) / float(model.fps))
    best, who = 0.0, -1
    for b in np.flatnonzero(kin[:model.n_bodies]):
        k = int(model.body_motion[b])
        if k < 0:
            continue
        c = np.asarray(model.body_anchor_c[b], dtype=np.float64)
        r = float(model.body_radius[b])
        dist = float(np.linalg.norm(c))
        pts = c + r * _AXES
        if dist > 0:
            pts = np.vstack([pts, c * (1.0 + r / dist)])
        v = float(model.motions[k].max_speed(pts, 0.0, t_end))
        if v > best:
            best, who = v, int(b)
    return best, who


def missing_surface_speed(model) -> tuple[float, int]:
    """(what ``surface_speed`` finds beyond the Model's own ``surface_speed`` [m/s],
    the body): 0 when the Model counted it."""
    v, b = surface_speed(model)
    extra = v - float(model.surface_speed)
    return (extra, b) if extra > 1e-9 * max(1.0, v) else (0.0, -1)
