"""A heavy body on a light material's auto spring that no sharing of the load saves.

``stability.soft_contact`` takes one contact stopping the heaviest corner-contact
mass m_c at the closing speed v: it sinks v √(m_c / k). Under auto stiffness it is a
warning only, since several contacts share the load of a body landing flat. But
sharing has a bound: at most every sphere of the body touches at once, N springs in
parallel, which sink v √(m_c / (N k)). When even that passes the bake's overlap guard,
the bake stops (a density ratio of 1e6 under auto stiffness: "sinks 1414 %", a warning,
then the guard). ``sinking`` is that bound; `dempipe check` and the bake make it an
error. NumPy only.
"""

from __future__ import annotations

import math

import numpy as np

from dempipe.check.stability import OVERLAP_ERROR, shape_rotational_factors


def sinking(model, closing: float) -> tuple[float, int, int, int]:
    """(the shallowest depth the worst pair can reach with every sphere of its heavy
    body sharing the load, as a fraction of the diameter; that body; its material; the
    partner material). (0, -1, -1, -1) when nothing sinks."""
    n = model.n_bodies
    if n == 0 or closing <= 0.0:
        return 0.0, -1, -1, -1
    d = float(model.diameter)
    factors = shape_rotational_factors(model)
    mass = np.asarray(model.body_mass[:n]) / (1.0 + factors[np.asarray(model.body_shape)])
    starts = np.asarray(model.body_sphere_start)
    spheres = np.maximum(1, starts[1:n + 1] - starts[:n])
    moving = np.ones(n, bool)
    if model.body_kinematic is not None:
        moving &= ~np.asarray(model.body_kinematic[:n], bool)
    dyn_mat = np.asarray(model.body_material[:n])
    partners = set(np.asarray(model.wall_material).tolist()) | set(
        np.asarray(model.body_material[n:]).tolist()) | set(dyn_mat[moving].tolist())
    best = (0.0, -1, -1, -1)
    shared = mass / spheres                     # the load each sphere takes at best
    for b in np.flatnonzero(moving):
        mi = int(dyn_mat[b])
        for mj in partners:
            k = float(model.pair_k[mi, mj])
            depth = closing * math.sqrt(shared[b] / k) / d if k > 0 else math.inf
            if depth > best[0]:
                best = (depth, int(b), mi, int(mj))
    return best


def sinks_through(model, closing: float) -> bool:
    """Whether :func:`sinking` passes the overlap guard's limit (OVERLAP_ERROR)."""
    return sinking(model, closing)[0] > OVERLAP_ERROR
