"""Frame-0 overlaps: how deep the spheres start in each other and in the walls.

    depth, body = frame0_overlap(model)          # fraction of a diameter, body or -1
    depth, body = emission_overlap(model, state) # the bodies an emitter starts now

The contact stage's exact rules, recomputed in NumPy so that `dempipe check`
(stability.analyze) and the bake's emitters (simulator.py) can ask without
compiling a kernel; it agrees with :func:`dempipe.scene.build.initial_overlap`, which
compiles the CPU kernels; and the limits the answers are held against. No numba,
no pxr.
"""

from __future__ import annotations

import numpy as np

from dempipe.sim.model import Model, quat_to_matrix


def sphere_positions(model: Model, state=None) -> np.ndarray:
    """World positions of every sphere (dynamic and static) [m]."""
    x = model.initial_x if state is None else state.body_x
    q = model.initial_q if state is None else state.body_q
    R = np.stack([quat_to_matrix(qq) for qq in q]) if len(q) else np.zeros((0, 3, 3))
    b = np.asarray(model.sphere_body)
    return np.asarray(x)[b] + np.einsum("sij,sj->si", R[b], np.asarray(model.sphere_offset))


def sphere_overlaps(model: Model, state=None) -> np.ndarray:
    """Largest overlap of each sphere at ``state`` (default frame 0) [m].

    The contact stage's rules in NumPy: spheres of different bodies closer than a
    diameter (two static spheres never touch); a dynamic sphere within a radius of a
    wall's surface and at most wall_depth behind it, inside the wall's box (a
    moving wall where its motion has it at the State's time). Bodies not yet
    emitted at that time touch nothing.
    """
    ns = model.n_spheres
    d = model.diameter
    ov = np.zeros(ns)
    if ns == 0:
        return ov
    t = 0.0 if state is None else float(state.time)
    step = 0 if state is None else int(state.step)
    X = sphere_positions(model, state)
    body = np.asarray(model.sphere_body)
    dynamic = ~model.body_static[body]
    # a body not yet emitted at this step touches nothing (as in the kernels)
    present = np.asarray(model.body_start)[body] <= step
    dynamic &= present
    cell = np.floor(X / d).astype(np.int64)
    cell -= cell.min(axis=0)
    span = cell.max(axis=0) + 3                      # room for the -1..+1 neighbours
    cell += 1

    def key(c):
        return (c[:, 0] * span[1] + c[:, 1]) * span[2] + c[:, 2]

    k = key(cell)
    order = np.argsort(k, kind="stable")
    ks = k[order]
    d2 = d * d
    for off in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")
                        ).reshape(3, -1).T:
        kn = key(cell + off)
        lo = np.searchsorted(ks, kn, "left")
        hi = np.searchsorted(ks, kn, "right")
        cnt = hi - lo
        total = int(cnt.sum())
        if total == 0:
            continue
        i = np.repeat(np.arange(ns), cnt)
        first = np.repeat(lo - np.concatenate([[0], np.cumsum(cnt)[:-1]]), cnt)
        j = order[first + np.arange(total)]
        keep = body[i] != body[j]
        keep &= (dynamic[i] | dynamic[j]) & present[i] & present[j]
        i, j = i[keep], j[keep]
        r = X[j] - X[i]
        dist2 = np.einsum("ij,ij->i", r, r)
        close = dist2 < d2
        np.maximum.at(ov, i[close], d - np.sqrt(dist2[close]))
    radius = 0.5 * d
    for w in range(model.n_walls):
        nrm = model.wall_normal[w]
        Xw = X
        mw = -1 if model.wall_motion is None else int(model.wall_motion[w])
        if mw >= 0:                     # a moving wall: the spheres in its frame
            P, Q, _, _ = model.motions[mw].anchor(t)
            Xw = (X - P) @ quat_to_matrix(Q)
        dist = Xw @ nrm - model.wall_offset[w]
        inside = ((Xw >= model.wall_lo[w]) & (Xw <= model.wall_hi[w])).all(axis=1)
        hit = dynamic & inside & (dist < radius) & (dist > -model.wall_depth[w])
        np.maximum.at(ov, np.flatnonzero(hit), radius - dist[hit])
    return ov


def emission_overlap(model: Model, state) -> tuple[float, int]:
    """Largest overlap of the bodies emitted at ``state``'s step (body_start), as a
    fraction of the diameter, and the body (-1: none): the frame-0 check of an
    emitter, at its start."""
    if model.n_spheres == 0:
        return 0.0, -1
    ov = sphere_overlaps(model, state)
    body = np.asarray(model.sphere_body)
    mine = np.asarray(model.body_start)[body] == int(state.step)
    mine &= np.asarray(model.body_start)[body] > 0
    if not mine.any():
        return 0.0, -1
    i = int(np.flatnonzero(mine)[np.argmax(ov[mine])])
    return float(ov[i] / model.diameter), (int(body[i]) if ov[i] > 0 else -1)


def frame0_overlap(model: Model, state=None) -> tuple[float, int]:
    """Largest overlap at frame 0 as (fraction of the diameter, body index or -1);
    the NumPy twin of build.initial_overlap (no kernel compiled)."""
    if model.n_spheres == 0:
        return 0.0, -1
    ov = sphere_overlaps(model, state)
    i = int(np.argmax(ov))
    return float(ov[i] / model.diameter), (int(model.sphere_body[i]) if ov[i] > 0 else -1)


#: Frame-0 overlap limits as fractions of the diameter, for `check` and the bake
#: (the bake, `dempipe check` and the emitters): above REFUSE_OVERLAP the first step would fling the
#: bodies apart (the same limit the guard uses), refused unless --force; above
#: WARN_OVERLAP a warning.
REFUSE_OVERLAP = 0.5
WARN_OVERLAP = 0.05
