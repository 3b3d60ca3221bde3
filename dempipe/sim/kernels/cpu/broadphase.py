"""CPU target, stage 3's first pass at a rebuild: which spheres can have a partner.

A sphere of body A has a neighbour only where some other body B comes within the
list's reach r = (1 + skin) d of it. Bodies first (``body_partners``): B can be in
reach of A only when their centres are closer than R_A + R_B + r (R: the farthest
sphere centre from the body's centre, ``body_reach``), found by a sweep along the
axis where the bodies' intervals overlap least. Then each sphere of A (``stage_near_others``): it
can have a partner in B only when its centre lies within the box of B's sphere
centres (``body_box``, in B's frame) grown by r along B's axes. A sphere that no
partner body passes goes into no grid cell and gets an empty list without a search.

Nothing is lost: a sphere j of B within r of sphere i puts i within r of j's
centre, which is in B's box, so within r of the box along each of its axes; and
it puts the centres of A and B within R_A + R_B + r. So the lists are the ones
the 27-cell search over every sphere finds and the frames do not change
(tests/sim/test_broadphase.py checks both steps against every pair,
tests/sim/test_neighbours.py the lists). The tests are padded by PAD r for the
rounding of the positions.

A surface set's shell, most of a pile's spheres, faces no other body on most of
its side: at 0.42 s of the quickstart with surface sets two thirds of the spheres
are left out, and a rebuild costs half what it did (docs/performance.md, "Where a
step goes").

Static and carried bodies' spheres always go into the grid (they search nothing,
but a sphere of a dynamic body may find them); a body not yet emitted is no
partner (it is in no list).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from dempipe.sim.kernels.compile import invalidate_stale_cache
from dempipe.sim.kernels.cpu.device import quat_rotate, quat_rotate_inv, static_body

invalidate_stale_cache(__file__)

#: Below this many spheres per dynamic body (on average) the broadphase is skipped:
#: for small bodies the body pairs' tests cost more than the search they save (4,096
#: chess pieces of 28 spheres landing: 17 ms per rebuild, one thread, to leave out 24 %
#: of the spheres; the surface quickstart's 255: 0.5 ms to leave out two thirds,
#: half the rebuild; docs/performance.md, "Surface sphere sets").
BROADPHASE_SPHERES = 64

#: The bounds' tests are grown by this share of the reach: positions come from
#: rounded rotations (relative errors ~1e-15), so a pair at the reach is never lost.
PAD = 1e-6


def body_bounds(sphere_offset, body_sphere_start, body_reach, body_box):
    """Each body's bounds in its own frame [m], filled in: body_reach[b] the farthest
    sphere centre from its centre, body_box[b] = (centre, half-extent) of the box of
    its sphere centres. Bodies without spheres keep zeros."""
    start = np.asarray(body_sphere_start)
    held = np.flatnonzero(np.diff(start) > 0)
    if not held.size:
        return
    off = np.asarray(sphere_offset)[: start[-1]]
    at = start[held]
    body_reach[held] = np.maximum.reduceat(np.linalg.norm(off, axis=1), at)
    lo = np.minimum.reduceat(off, at, axis=0)
    hi = np.maximum.reduceat(off, at, axis=0)
    body_box[held, :3] = 0.5 * (lo + hi)
    body_box[held, 3:] = 0.5 * (hi - lo)


@numba.njit(error_model="numpy", cache=True)
def sweep(fill, order, live, lo, axis, half, reach, body_x, body_reach, body_inv_mass, count,
          other):
    """body_partners' sweep: counts each body's partners into count[b + 1] (fill
    False), or writes them at count[b] on (fill True, count the running ends)."""
    n = live.shape[0]
    for k in range(n):
        a = live[order[k]]
        end = body_x[a, axis] + body_reach[a] + half
        sa = static_body(body_inv_mass[a])
        for m in range(k + 1, n):
            if lo[order[m]] > end:
                break
            b = live[order[m]]
            if sa and static_body(body_inv_mass[b]):
                continue
            dx = body_x[a, 0] - body_x[b, 0]
            dy = body_x[a, 1] - body_x[b, 1]
            dz = body_x[a, 2] - body_x[b, 2]
            r = (body_reach[a] + body_reach[b] + reach) * (1.0 + PAD)
            if dx * dx + dy * dy + dz * dz > r * r:
                continue
            if fill:
                other[count[a]] = b
                count[a] += 1
                other[count[b]] = a
                count[b] += 1
            else:
                count[a + 1] += 1
                count[b + 1] += 1


@numba.njit(error_model="numpy", cache=True)
def body_partners(reach, body_x, body_reach, body_sphere_start, body_inv_mass, body_start,
                  step):
    """The pairs of bodies whose centres are closer than R_A + R_B + reach [m], at
    least one of them dynamic, both in the simulation at ``step``: (start, other),
    body b's partners other[start[b]:start[b+1]] (serial; the same for any thread
    count). A sweep: the bodies sorted (stable) by where their bounding interval
    starts on the axis where these intervals overlap least, each compared with the
    ones after it until an interval starts past its end."""
    nb = body_sphere_start.shape[0] - 1
    live = np.empty(nb, np.int64)
    n = 0
    for b in range(nb):
        if body_sphere_start[b + 1] > body_sphere_start[b] and body_start[b] <= step:
            live[n] = b
            n += 1
    live = live[:n]
    half = 0.5 * reach * (1.0 + PAD)
    # the axis whose intervals overlap least (the sweep's work): for each, the
    # intervals starting within each one, counted by a binary search in the sorted starts
    best = -1
    axis = 0
    for ax in range(3):
        lo_ax = np.empty(n)
        hi_ax = np.empty(n)
        for k in range(n):
            b = live[k]
            lo_ax[k] = body_x[b, ax] - body_reach[b] - half
            hi_ax[k] = body_x[b, ax] + body_reach[b] + half
        starts = np.sort(lo_ax)
        work = 0
        for k in range(n):
            work += np.searchsorted(starts, hi_ax[k], side="right")
        if best < 0 or work < best:
            best = work
            axis = ax
    lo = np.empty(n)
    for k in range(n):
        b = live[k]
        lo[k] = body_x[b, axis] - body_reach[b] - half
    order = np.argsort(lo, kind="mergesort")
    start = np.zeros(nb + 1, np.int64)
    sweep(False, order, live, lo, axis, half, reach, body_x, body_reach, body_inv_mass, start,
          live)
    for b in range(nb):
        start[b + 1] += start[b]
    other = np.empty(start[nb], np.int64)
    at = start[:nb].copy()
    sweep(True, order, live, lo, axis, half, reach, body_x, body_reach, body_inv_mass, at,
          other)
    return start, other


@numba.njit(inline="always", cache=True)
def axis_in_frame(qa, qb, j):
    """Body b's axis j (orientation qb) in body a's frame (orientation qa)."""
    wx, wy, wz = quat_rotate(qb[0], qb[1], qb[2], qb[3], 1.0 if j == 0 else 0.0,
                             1.0 if j == 1 else 0.0, 1.0 if j == 2 else 0.0)
    return quat_rotate_inv(qa[0], qa[1], qa[2], qa[3], wx, wy, wz)


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_near_others(min_spheres, reach, offset_t, body_x, body_q, body_sphere_start,
                      body_reach, body_box, body_inv_mass, body_start, step, sphere_hash):
    """At a rebuild, before the grid's sort: each sphere of a dynamic body that no
    other body can be within ``reach`` [m] of gets sphere_hash -1, so the sort
    leaves it out of the grid and the search gives it an empty list (the module's
    docstring). Returns how many are left out: none, without a test, when the
    dynamic bodies in the simulation have fewer than ``min_spheres`` spheres each on
    average (BROADPHASE_SPHERES).

    Each partner body's box of sphere centres is put into the body's own frame
    (centre c, axes u_j, half-extents h_j), and the spheres' offsets p (offset_t:
    the Model's sphere_offset by coordinate, so that the loop over a body's spheres
    runs on contiguous arrays, in SIMD lanes) are tested there without a branch:
    |u_j . (p - c)| <= h_j + reach for j = 1..3."""
    nb = body_sphere_start.shape[0] - 1
    n_dynamic = 0
    n_spheres = 0
    for a in range(nb):
        if not static_body(body_inv_mass[a]) and body_start[a] <= step:
            n_dynamic += 1
            n_spheres += body_sphere_start[a + 1] - body_sphere_start[a]
    if n_spheres < min_spheres * n_dynamic or n_dynamic == 0:
        return 0
    start, other = body_partners(reach, body_x, body_reach, body_sphere_start, body_inv_mass,
                                 body_start, step)
    grown = reach * (1.0 + PAD)
    out = 0
    for a in prange(nb):
        if static_body(body_inv_mass[a]) or body_start[a] > step:
            continue
        s0 = body_sphere_start[a]
        s1 = body_sphere_start[a + 1]
        ox = offset_t[0, s0:s1]
        oy = offset_t[1, s0:s1]
        oz = offset_t[2, s0:s1]
        near = np.zeros(s1 - s0, np.uint8)
        qa = body_q[a]
        for e in range(start[a], start[a + 1]):
            b = other[e]
            qb = body_q[b]
            box = body_box[b]
            wx, wy, wz = quat_rotate(qb[0], qb[1], qb[2], qb[3], box[0], box[1], box[2])
            cx, cy, cz = quat_rotate_inv(qa[0], qa[1], qa[2], qa[3],
                                         body_x[b, 0] + wx - body_x[a, 0],
                                         body_x[b, 1] + wy - body_x[a, 1],
                                         body_x[b, 2] + wz - body_x[a, 2])
            u0x, u0y, u0z = axis_in_frame(qa, qb, 0)
            u1x, u1y, u1z = axis_in_frame(qa, qb, 1)
            u2x, u2y, u2z = axis_in_frame(qa, qb, 2)
            h0 = box[3] + grown
            h1 = box[4] + grown
            h2 = box[5] + grown
            for i in range(s1 - s0):
                dx = ox[i] - cx
                dy = oy[i] - cy
                dz = oz[i] - cz
                near[i] |= ((abs(u0x * dx + u0y * dy + u0z * dz) <= h0)
                            & (abs(u1x * dx + u1y * dy + u1z * dz) <= h1)
                            & (abs(u2x * dx + u2y * dy + u2z * dz) <= h2))
        n = 0
        for i in range(s1 - s0):
            if not near[i]:
                sphere_hash[s0 + i] = -1
                n += 1
        out += n
    return out
