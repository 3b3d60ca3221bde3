"""CPU target, stage 1 (eq. 5-6, 19-21): the bodies' velocities, the carried bodies
where their prescriptions put them, and the spheres from their bodies.

The plain functions here are compiled by kernels/cpu/stages.py with its globals (the
feature flags, the formulas of kernels/cpu/device.py: compile.specialize), as the
functions of contacts.py are; the ones with a numba decorator read no flag.

Between rebuilds only the spheres a contact reads are placed (stage_spheres_busy):
a sphere with nothing in reach has a zero force until the next rebuild, which
places every sphere again, and so does the end of a call (stage_spheres_sorted).
Whether a rebuild is due is decided per body first: a bound on how far its spheres
can be from where the lists were built (body_moved), the test of every sphere
only for a body whose bound reaches half the skin. So the rebuilds come at the
steps they came at when every sphere was placed and tested.
"""

from __future__ import annotations

import numba
from numba import prange

from dempipe.sim.kernels.compile import invalidate_stale_cache
from dempipe.sim.kernels.cpu.device import sqrt

invalidate_stale_cache(__file__)

def stage_body_velocities(n_bodies, body_P, body_L, body_q, body_inv_mass, body_inv_inertia,
                          body_v, body_w):
    """V = P/M and W = I(t)⁻¹ L (eq. 5-6) for each dynamic body (W = 0 without ROTATION)."""
    for b in prange(n_bodies):
        im = body_inv_mass[b]
        body_v[b, 0] = body_P[b, 0] * im
        body_v[b, 1] = body_P[b, 1] * im
        body_v[b, 2] = body_P[b, 2] * im
        if not ROTATION:
            body_w[b, 0] = 0.0
            body_w[b, 1] = 0.0
            body_w[b, 2] = 0.0
            continue
        ii = body_inv_inertia[b]
        q = body_q[b]
        wx, wy, wz = angular_velocity(q[0], q[1], q[2], q[3], ii[0], ii[1], ii[2], ii[3],
                                      ii[4], ii[5], body_L[b, 0], body_L[b, 1], body_L[b, 2])
        body_w[b, 0] = wx
        body_w[b, 1] = wy
        body_w[b, 2] = wz


def stage_motion(t, motion_kind, motion_v, motion_w, motion_pivot, key_start, key_t, key_p,
                 key_q, motion_now):
    """The prescribed motions at time t [s] into motion_now (prescribed.motion_row);
    serial: a scene has a few."""
    for m in range(motion_now.shape[0]):
        motion_row(m, t, motion_kind, motion_v, motion_w, motion_pivot, key_start, key_t,
                   key_p, key_q, motion_now)


def stage_driven(driven_body, body_motion, body_anchor_c, body_anchor_q, motion_now, body_x,
                 body_q, body_v, body_w, body_rest, body_still, h):
    """The carried bodies where their motions put them (prescribed.driven_row; h [s]:
    their velocities as chords of that step, 0 for the tangent). Returns how many
    started moving (rest count 0 to -1): a sleeping pile's active slots, searched
    while they held still and so counted them quiet, no longer hold (run_steps)."""
    started = 0
    for k in range(driven_body.shape[0]):
        b = driven_body[k]
        held = body_rest[b] >= 0
        driven_row(k, driven_body, body_motion, body_anchor_c, body_anchor_q, motion_now,
                   body_x, body_q, body_v, body_w, body_rest, body_still, h)
        if held and body_rest[b] < 0:
            started += 1
    return started


def sphere_state(i, sphere_body, sphere_offset, body_x, body_q, body_v, body_w, h):
    """Stage 1 for sphere i (eq. 19-21): (x, v, R r') [m, m/s, m], world frame; v
    the chord of the step h [s] (physics.sphere_kinematics)."""
    b = sphere_body[i]
    q = body_q[b]
    if ROTATION:
        return sphere_kinematics(
            body_x[b, 0], body_x[b, 1], body_x[b, 2], q[0], q[1], q[2], q[3],
            body_v[b, 0], body_v[b, 1], body_v[b, 2],
            body_w[b, 0], body_w[b, 1], body_w[b, 2],
            sphere_offset[i, 0], sphere_offset[i, 1], sphere_offset[i, 2], h)
    # W = 0: sphere_kinematics with the W × r' term dropped
    rx, ry, rz = quat_rotate(q[0], q[1], q[2], q[3], sphere_offset[i, 0],
                             sphere_offset[i, 1], sphere_offset[i, 2])
    return (body_x[b, 0] + rx, body_x[b, 1] + ry, body_x[b, 2] + rz,
            body_v[b, 0], body_v[b, 1], body_v[b, 2], rx, ry, rz)


def stage_spheres(sphere_body, sphere_offset, body_x, body_q, body_v, body_w, h, inv_cell,
                  grid, sphere_x, sphere_v, sphere_r, sphere_key, sphere_hash):
    """Stage 1 (eq. 19-21) in sphere order (velocities: chords of the step h [s]), and
    each sphere's grid cell (stage 2's input)."""
    for i in prange(sphere_body.shape[0]):
        x, y, z, vx, vy, vz, rx, ry, rz = sphere_state(i, sphere_body, sphere_offset, body_x,
                                                       body_q, body_v, body_w, h)
        slot_place(i, i, x, y, z, vx, vy, vz, rx, ry, rz, sphere_x, sphere_v, sphere_r)
        cx = cell_coord(x, inv_cell)
        cy = cell_coord(y, inv_cell)
        cz = cell_coord(z, inv_cell)
        sphere_key[i] = cell_key(cx, cy, cz)
        sphere_hash[i] = cell_hash(cx, cy, cz, grid)


def stage_spheres_sorted(slot_of, sphere_body, sphere_offset, body_x, body_q, body_v,
                         body_w, h, sorted_x, sorted_v, sphere_r):
    """Stage 1 (eq. 19-21) for every sphere, straight into the sorted slots of the
    last rebuild (no grid, no sort; slot_of[i] is sphere i's), from the poses
    body_x, body_q: before a rebuild that may keep the slots (stage_slot_marks
    compares every slot), and at the end of a call (stage_unsort), where
    stage_spheres_busy has left the others where the last rebuild put them.

    In sphere order, not slot order: a body's spheres are contiguous, so their
    offsets are read and sphere_r written in order and the body's state is read
    once per run of its spheres (1.04-1.06x on the 25 k dense pile than the
    other way round, the same at 275 k, when the slots were sorted by cell); and
    a body's slots are consecutive too (stage_grid_sort), so the stores run in
    order as well."""
    for i in prange(slot_of.shape[0]):
        x, y, z, vx, vy, vz, rx, ry, rz = sphere_state(i, sphere_body, sphere_offset, body_x,
                                                       body_q, body_v, body_w, h)
        slot_place(slot_of[i], i, x, y, z, vx, vy, vz, rx, ry, rz, sorted_x, sorted_v,
                   sphere_r)


@numba.njit(inline="always", cache=True)
def body_moved(b, body_x, body_q, built_bx, built_bq, body_reach):
    """A bound [m] on how far any sphere of body b is from where the last rebuild
    placed it: |x - x0| + 2 R |q -+ q0| (R its farthest sphere from the centre; the
    sign that makes the difference the smaller), since a rotation by angle a moves
    a point at distance R by 2 R sin(a/2) <= 2 R |q -+ q0| for unit quaternions.
    Plus 1e-9 of the coordinates, far more than the spheres' placement rounds by."""
    ex = body_x[b, 0] - built_bx[b, 0]
    ey = body_x[b, 1] - built_bx[b, 1]
    ez = body_x[b, 2] - built_bx[b, 2]
    dm = 0.0
    dp = 0.0
    for a in range(4):
        u = body_q[b, a] - built_bq[b, a]
        w = body_q[b, a] + built_bq[b, a]
        dm += u * u
        dp += w * w
    r = body_reach[b]
    return (sqrt(ex * ex + ey * ey + ez * ez) + 2.0 * r * sqrt(min(dm, dp))
            + 1e-9 * (abs(body_x[b, 0]) + abs(body_x[b, 1]) + abs(body_x[b, 2]) + r))


def stage_spheres_busy(body_sphere_start, slot_of, sphere_body, sphere_offset, body_x, body_q,
                       body_v, body_w, h, body_still, body_inv_mass, built_bx, built_bq,
                       body_reach, seen_bx, seen_bq, busy, n_busy, busy_from, built_x,
                       body_half, sorted_x, sorted_v, sphere_r):
    """Stage 1 (eq. 19-21) between rebuilds, into the sorted slots of the last one,
    for the spheres a contact reads: the busy slots' (stage_busy; a list's partners
    list each other, so their partners are busy too) and a carried static body's
    (in no list, but a partner of busy ones). The others' forces are zero until
    the next rebuild, which places them again. Returns how many spheres have moved
    their body's rebuild distance (body_half [m], grid.stage_rest_half) or more since
    that rebuild (then the lists must be rebuilt), the count of the test on every
    sphere: a body that may hold such a sphere (body_moved) has all its spheres
    placed and tested; a body that slept through the last step, or a static
    collider (body_still), none: it has not moved. Notes each body's pose in seen_bx, seen_bq (the end of a call places every
    sphere where this step saw it). With GLUE every sphere is placed: a bond reads
    its two spheres, busy or not.

    A body's slots are consecutive and in its spheres' order (stage_grid_sort), so
    its busy slots are one run of ``busy``, from busy_from[b] (stage_listed_from)."""
    moved = 0
    for b in prange(body_reach.shape[0]):
        for a in range(3):
            seen_bx[b, a] = body_x[b, a]
        for a in range(4):
            seen_bq[b, a] = body_q[b, a]
        i0 = body_sphere_start[b]
        i1 = body_sphere_start[b + 1]
        if body_still[b] != 0 or i0 == i1:
            continue
        half = body_half[b]
        if GLUE or static_body(body_inv_mass[b]) or \
                body_moved(b, body_x, body_q, built_bx, built_bq, body_reach) >= half:
            rebuild_at2 = half * half
            for i in range(i0, i1):
                x, y, z, vx, vy, vz, rx, ry, rz = sphere_state(i, sphere_body, sphere_offset,
                                                               body_x, body_q, body_v, body_w,
                                                               h)
                moved += slot_store(slot_of[i], i, x, y, z, vx, vy, vz, rx, ry, rz, sorted_x,
                                    sorted_v, sphere_r, built_x, rebuild_at2)
        else:
            s0 = slot_of[i0]
            k0 = busy_from[b]
            for k in range(k0, listed_end(k0, s0 + i1 - i0, busy, n_busy)):
                s = busy[k]
                i = i0 + s - s0
                x, y, z, vx, vy, vz, rx, ry, rz = sphere_state(i, sphere_body, sphere_offset,
                                                               body_x, body_q, body_v, body_w,
                                                               h)
                slot_place(s, i, x, y, z, vx, vy, vz, rx, ry, rz, sorted_x, sorted_v,
                           sphere_r)
    return moved


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_note_built(body_x, body_q, built_bx, built_bq, seen_bx, seen_bq, body_sphere_start,
                     slot_of, slot_mark, kept):
    """At a rebuild: each body's pose where this step sees it, and where its
    spheres' lists were built (stage_spheres_busy's body_moved): here, unless the
    rebuild kept the slots (``kept``) and the body's lists stay where they were
    built (its slots not marked 1 by stage_slot_marks)."""
    for b in prange(body_x.shape[0]):
        i0 = body_sphere_start[b]
        for a in range(3):
            seen_bx[b, a] = body_x[b, a]
        for a in range(4):
            seen_bq[b, a] = body_q[b, a]
        if kept and body_sphere_start[b + 1] > i0 and slot_mark[slot_of[i0]] != 1:
            continue
        for a in range(3):
            built_bx[b, a] = body_x[b, a]
        for a in range(4):
            built_bq[b, a] = body_q[b, a]


@numba.njit(inline="always", cache=True)
def listed_end(k0, s1, work, n_work):
    """The end k1 of a body's run of work[:n_work] (in slot order) that starts at
    entry k0 (its first at or after its first slot): the run is work[k0 .. k1-1],
    the entries below slot s1."""
    k1 = k0
    while k1 < n_work and work[k1] < s1:
        k1 += 1
    return k1


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_listed_from(body_sphere_start, slot_of, work, n_work, work_from):
    """work_from[b] = the first entry of work[:n_work] (slots in slot order) at or
    after body b's first slot (0 for a body without spheres): where its run of work
    starts, found by a binary search once when work is made (a rebuild's busy slots,
    a search's active ones) rather than in each pass of each step. The passes end
    the run with listed_end."""
    for b in prange(work_from.shape[0]):
        i0 = body_sphere_start[b]
        s0 = slot_of[i0] if body_sphere_start[b + 1] > i0 else 0
        lo = 0
        hi = n_work
        while lo < hi:
            mid = (lo + hi) // 2
            if work[mid] < s0:
                lo = mid + 1
            else:
                hi = mid
        work_from[b] = lo