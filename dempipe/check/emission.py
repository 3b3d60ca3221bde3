"""Emitted bodies that start inside each other: predicted before the bake.

An emitter starts body *i* of a group at ``start_time + i / rate``, at a random place
in its region (docs/scene-format.md, "Emitters"). At a high rate several bodies start
within a few steps of each other; the bake's emission check (simulator.py) then finds
one deep in another and stops. Those bodies have not moved apart yet, so their
overlap is known from the Model alone: the overlap of their spheres at their start
places, less the most either could have fallen or flown in the time between their
starts. ``emission_overlap`` is that lower bound; `dempipe check` and the bake hold it
against the frame-0 limits (sim.overlap.REFUSE_OVERLAP, WARN_OVERLAP). NumPy and
scipy only.
"""

from __future__ import annotations

import numpy as np

from dempipe.sim.overlap import sphere_positions


def emission_overlap(model) -> tuple[float, int, int]:
    """(overlap as a fraction of the diameter, body, the body it starts in) for the
    worst pair of bodies of which at least one is emitted after frame 0; (0, -1, -1)
    when none can overlap. A static mesh collider's spheres count (they stay where
    they are); planes and boxes are the frame-0 check's.

    A pair started Δt apart is credited with the most the earlier body can have
    moved meanwhile, |v0| Δt + |g| Δt² / 2 (contacts may push it further; the bound
    is then low, never high)."""
    if model.n_spheres == 0 or model.body_start_time is None:
        return 0.0, -1, -1
    nb = model.n_bodies
    start = np.zeros(len(model.body_static))
    start[:nb] = np.asarray(model.body_start_time, dtype=np.float64)[:nb]
    if not (start[:nb] > 0).any():
        return 0.0, -1, -1
    from scipy.spatial import cKDTree

    d = float(model.diameter)
    g = float(np.linalg.norm(model.gravity))
    v0 = np.zeros(len(start))
    v0[:nb] = np.linalg.norm(np.asarray(model.initial_v, dtype=np.float64)[:nb], axis=1)
    body = np.asarray(model.sphere_body)
    static = np.asarray(model.body_static)[body]
    X = sphere_positions(model)
    pairs = cKDTree(X).query_pairs(d, output_type="ndarray")
    if not len(pairs):
        return 0.0, -1, -1
    i, j = pairs[:, 0], pairs[:, 1]
    bi, bj = body[i], body[j]
    keep = (bi != bj) & ~(static[i] & static[j])
    keep &= (start[bi] > 0) | (start[bj] > 0)         # frame 0's pairs: the frame-0 check
    i, j, bi, bj = i[keep], j[keep], bi[keep], bj[keep]
    if not len(i):
        return 0.0, -1, -1
    gap = np.abs(start[bi] - start[bj])
    earlier = np.where(start[bi] <= start[bj], bi, bj)
    moved = np.where(static[i] | static[j], 0.0, v0[earlier] * gap + 0.5 * g * gap * gap)
    dist = np.linalg.norm(X[i] - X[j], axis=1)
    depth = d - dist - moved
    k = int(np.argmax(depth))
    if depth[k] <= 0:
        return 0.0, -1, -1
    later = int(bi[k] if start[bi[k]] >= start[bj[k]] else bj[k])
    other = int(bj[k] if later == bi[k] else bi[k])
    return float(depth[k] / d), later, other
