"""Bodies that start wholly behind a plane collider: predicted before the bake.

A plane is a half-space (docs/scene-format.md, ``[[colliders]]``): it pushes out a
sphere up to its wall_depth (model.PLANE_DEPTH_DIAMETERS) behind its surface and
ignores one deeper, taken to be elsewhere. A body that starts entirely beyond that
depth therefore never touches the plane: a box placed under the floor falls on for
ever. A body partly through the plane has spheres within the depth, deep in
contact, and the frame-0 overlap check already reports it; ``behind_planes`` finds
the bodies wholly behind, which nothing else notices. NumPy only.
"""

from __future__ import annotations

import numpy as np

from dempipe.sim.model import quat_to_matrix
from dempipe.sim.overlap import sphere_positions


def plane_walls(model) -> np.ndarray:
    """The wall indices of the Model's planes, in the order they were added (the
    scene's plane colliders in file order): a plane's wall is unbounded on every
    axis, a box wall bounded on two."""
    lo, hi = np.asarray(model.wall_lo), np.asarray(model.wall_hi)
    return np.flatnonzero(np.isinf(lo).all(axis=1) & np.isinf(hi).all(axis=1))


def behind_planes(model) -> list[tuple[int, np.ndarray]]:
    """[(k, bodies)]: for the k-th plane (plane_walls order), the dynamic bodies
    (int indices, ascending) every one of whose contact spheres starts farther behind
    its surface than its depth, wall_depth [m]. Planes with none are left out.

    Emitted bodies are taken where they start, at their start_time, and a moving
    plane where its motion has it at that time (as the contact stage sees it).
    Kinematic bodies are left out: walls never push them.
    """
    n = model.n_bodies
    walls = plane_walls(model)
    if n == 0 or len(walls) == 0:
        return []
    X = sphere_positions(model)
    body = np.asarray(model.sphere_body)
    pushed = ~np.asarray(model.body_static[:n])          # dynamic, not kinematic
    sel = np.flatnonzero((body < n) & pushed[np.minimum(body, n - 1)])
    if len(sel) == 0:
        return []
    Xs, bs = X[sel], body[sel]
    start = (np.zeros(n) if model.body_start_time is None
             else np.asarray(model.body_start_time, dtype=np.float64))
    found = []
    for k, w in enumerate(walls):
        nrm = np.asarray(model.wall_normal[w])
        mw = -1 if model.wall_motion is None else int(model.wall_motion[w])
        if mw < 0:
            dist = Xs @ nrm - model.wall_offset[w]
        else:
            # a moving plane is given in its anchor frame: the spheres go there, at
            # the time each body starts
            dist = np.empty(len(sel))
            t_s = start[bs]
            for t in np.unique(t_s):
                at = t_s == t
                P, Q, _, _ = model.motions[mw].anchor(float(t))
                dist[at] = ((Xs[at] - P) @ quat_to_matrix(Q)) @ nrm - model.wall_offset[w]
        nearest = np.full(n, -np.inf)
        np.maximum.at(nearest, bs, dist)
        # a sphere touches the plane while dist > -depth (overlap.sphere_overlaps)
        behind = np.flatnonzero(pushed & (nearest <= -float(model.wall_depth[w])))
        if len(behind):
            found.append((k, behind))
    return found
