"""Bodies that start wholly behind a wall: a plane collider, or one wall of a box
collider, predicted before the bake.

Every wall is a bounded half-space (model.Model, "Walls"): it pushes out a sphere
whose centre is inside its box [wall_lo, wall_hi] up to its wall_depth behind its
surface, and ignores one deeper, taken to be elsewhere. A plane's wall is unbounded
on every axis and PLANE_DEPTH_DIAMETERS deep; a box's walls face inward, each
bounded on the two axes along its surface (a radius past the box's inner corners,
the side walls of an open top reaching on up) and as deep as the box's thickness.

A body that starts entirely beyond that depth therefore never touches the wall: a
body placed under the floor falls on for ever, through a plane or past a tray's
floor, and one placed just outside a box's side wall is not held by it (should it
come within the depth, the wall pushes it in through itself). A body partly through
a wall has spheres within the depth, deep in contact, and the frame-0 overlap check
already reports it; these functions find the bodies wholly behind, which nothing
else notices. A body inside another box, behind a wall that faces away from it, is
where it is meant to be and is not named (behind_boxes). NumPy only.
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


def box_walls(model) -> list[np.ndarray]:
    """The wall indices of each of the Model's boxes (model.boxes order, the scene's
    box colliders in file order): the walls that are not a plane's, in the order the
    builder added them, five to a box with an open top and six to a closed one."""
    walls = np.setdiff1d(np.arange(model.n_walls), plane_walls(model))
    counts = [5 if b.open_top else 6 for b in model.boxes]
    if sum(counts) != len(walls):
        raise ValueError(f"{len(walls)} box walls for boxes of {sum(counts)}")
    return np.split(walls, np.cumsum(counts)[:-1]) if counts else []


def wall_name(model, w: int) -> str:
    """Box wall w in words, from its inward normal and the Model's up axis: "floor"
    and "lid" along the up axis, else "-x wall" for the one at the box's min on x
    (its normal +x), "+x wall" at its max, and so on."""
    nrm = np.asarray(model.wall_normal[w])
    axis = int(np.argmax(np.abs(nrm)))
    if axis == (2 if model.up_axis == "Z" else 1):
        return "floor" if nrm[axis] > 0 else "lid"
    return f"{'-' if nrm[axis] > 0 else '+'}{'xyz'[axis]} wall"


def behind_walls(model, walls) -> list[tuple[int, np.ndarray]]:
    """[(w, bodies)]: for each wall index w of ``walls``, in that order, the dynamic
    bodies (int indices, ascending) every one of whose contact spheres starts with
    its centre inside the wall's box [wall_lo, wall_hi] and farther behind its
    surface than its depth, wall_depth [m]. Walls with none are left out.

    A sphere outside the wall's box is one the contact stage never tests against
    that wall (kernels.contacts.wall_gap), at any depth: a body one of whose spheres
    is beside the wall (under a box's floor but partly beside the box) is not wholly
    behind it. Emitted bodies are taken where they start, at their start_time, and a
    moving wall where its motion has it at that time, in its anchor frame (as the
    contact stage sees it). Kinematic bodies are left out: walls never push them.
    """
    behind, _ = _sides(model, walls)
    return [(int(w), np.flatnonzero(row)) for w, row in zip(walls, behind) if row.any()]


def behind_planes(model) -> list[tuple[int, np.ndarray]]:
    """[(k, bodies)]: for the k-th plane (plane_walls order), the dynamic bodies
    (int indices, ascending) that start wholly behind it (behind_walls). Planes with
    none are left out."""
    walls = plane_walls(model)
    k_of = {int(w): k for k, w in enumerate(walls)}
    return [(k_of[w], bodies) for w, bodies in behind_walls(model, walls)]


def behind_boxes(model) -> list[tuple[int, int, np.ndarray]]:
    """[(k, w, bodies)]: for the k-th box (model.boxes order) and its wall w (a wall
    index; wall_name names it), the dynamic bodies (int indices, ascending) that
    start wholly behind that wall (behind_walls), outside the box where the wall
    never touches them. Walls with none are left out; by box, then wall.

    A wall's extent runs on without end along its normal, so a body in a second box
    beside the first is behind the first's wall facing it; it is held where it is
    meant to be, and left out: bodies that start inside any box, no sphere deeper
    than a wall's depth behind any of its walls (above an open top included), are
    never named. Nor is a body farther behind a wall than the box is deep along the
    wall's normal (its inner size on that axis, past the wall's depth): a body on the
    ground under a shelf, or a pile beside a tray, is placed there, where a body just
    under a floor or just outside a wall is most often one meant to be inside (an
    origin or an up axis mistaken).
    """
    per_box = box_walls(model)
    if not per_box:
        return []
    walls = np.concatenate(per_box)
    # each wall's box's inner size along the wall's normal [m]
    spans = np.array([float((np.asarray(box.hi) - np.asarray(box.lo))[
        int(np.argmax(np.abs(model.wall_normal[w])))])
        for box, ws in zip(model.boxes, per_box) for w in ws])
    behind, front = _sides(model, walls, spans)
    if behind.shape[1] == 0:
        return []
    row = {int(w): i for i, w in enumerate(walls)}
    held = np.zeros(behind.shape[1], dtype=bool)
    for ws in per_box:
        held |= front[[row[int(w)] for w in ws]].all(axis=0)
    return [(k, int(w), np.flatnonzero(behind[row[int(w)]] & ~held))
            for k, ws in enumerate(per_box) for w in ws
            if (behind[row[int(w)]] & ~held).any()]


def _sides(model, walls, spans=None) -> tuple[np.ndarray, np.ndarray]:
    """(behind, front), each (len(walls), n_bodies) bool: whether a dynamic body
    starts wholly behind wall walls[i] (behind_walls; with ``spans``, (len(walls),)
    [m], no sphere more than spans[i] farther behind it than its depth), and whether
    none of its contact spheres is farther behind the wall's surface than its depth,
    whatever the wall's box (in front of it or within its reach). Kinematic bodies
    are False in both."""
    n = model.n_bodies
    walls = np.asarray(walls, dtype=np.int64)
    behind = np.zeros((len(walls), n), dtype=bool)
    front = np.zeros((len(walls), n), dtype=bool)
    if n == 0 or len(walls) == 0:
        return behind, front
    X = sphere_positions(model)
    body = np.asarray(model.sphere_body)
    pushed = ~np.asarray(model.body_static[:n])          # dynamic, not kinematic
    sel = np.flatnonzero((body < n) & pushed[np.minimum(body, n - 1)])
    if len(sel) == 0:
        return behind, front
    Xs, bs = X[sel], body[sel]
    has = pushed & (np.bincount(bs, minlength=n) > 0)
    start = (np.zeros(n) if model.body_start_time is None
             else np.asarray(model.body_start_time, dtype=np.float64))
    for i, w in enumerate(walls):
        mw = -1 if model.wall_motion is None else int(model.wall_motion[w])
        if mw < 0:
            L = Xs
        else:
            # a moving wall is given in its anchor frame: the spheres go there, at the
            # time each body starts
            L = np.empty_like(Xs)
            t_s = start[bs]
            for t in np.unique(t_s):
                at = t_s == t
                P, Q, _, _ = model.motions[mw].anchor(float(t))
                L[at] = (Xs[at] - P) @ quat_to_matrix(Q)
        dist = L @ np.asarray(model.wall_normal[w]) - model.wall_offset[w]
        inside = ((L >= np.asarray(model.wall_lo[w])).all(axis=1)
                  & (L <= np.asarray(model.wall_hi[w])).all(axis=1))
        # a sphere touches the wall while inside its box and dist > -depth (wall_gap)
        deep = dist <= -float(model.wall_depth[w])
        near = True if spans is None else dist >= -float(model.wall_depth[w]) - spans[i]
        behind[i] = has & (np.bincount(bs, weights=~(inside & deep & near),
                                       minlength=n) == 0)
        front[i] = has & (np.bincount(bs, weights=deep, minlength=n) == 0)
    return behind, front
