"""CPU target: the paper's eight stages as numba njit/prange drivers.

Each stage is one parallel loop; the formulas come from physics.py compiled
with ``numba.njit(inline="always")``. ``run_steps`` loops over steps inside
compiled code, so a frame of hundreds of steps costs one Python call.

Determinism: every parallel loop writes only its own index (gather, no
scatter, no atomics); the sorts of a rebuild are serial and stable; each body sums
its spheres in index order. The output is bit-identical for any thread count.
"""

from __future__ import annotations

import types

import numba
import numpy as np
from numba import prange

from . import contacts, neighbours
from .compile import (compile_chain, compile_formulas, compile_pairing, compile_slot_store,
                      compile_walk, invalidate_stale_cache, specialize)
from ..state import CONTACT_SLOTS
# UNPAIRED: read by contacts.sphere_forces, which is compiled with this module's globals
from .contacts import (CONTACT_CHUNK, LIST_PER_SPHERE, PAIR_COLS, PAIRS_PER_SPHERE,  # noqa: F401
                       UNPAIRED, WALL_SLACK)
from .contacts import CLOSE_REACH2  # noqa: F401 (read by contacts.pair_forces, sphere_forces)
from .layout import (BUCKETS_PER_SPHERE, CPU_LAYOUT, FLAGS, GENERAL,  # noqa: F401
                     chunk_spans, cpu_scratch, fit_grid, grid_table, kernel_flags,
                     scene_features, static_extent)
from .neighbours import NEIGHBOURS, SKIN, SKIN_MAX, SKIN_SHRINK_ABOVE, cell_size

invalidate_stale_cache(__file__)
invalidate_stale_cache(contacts.__file__)   # pair_forces, sphere_forces: cached under its name
F = compile_formulas(numba.njit(inline="always", cache=False))
quat_rotate = F.quat_rotate
angular_velocity = F.angular_velocity
sphere_kinematics = F.sphere_kinematics
sphere_pair_force = F.sphere_pair_force
sphere_wall_force = F.sphere_wall_force
body_step = F.body_step
history_recall = F.history_recall
history_store = F.history_store
rest_steps = F.rest_steps
contact_coefficients = F.contact_coefficients
closing = F.closing
static_body = F.static_body
sqrt = np.sqrt
P = compile_pairing(numba.njit(inline="always", cache=False), F)
entry_range = P.entry_range
wall_reach = P.wall_reach
owns = P.owns
pair_count = P.pair_count
pair_slots = P.pair_slots
pair_mirror = P.pair_mirror
rows_to_pairs = P.rows_to_pairs
pairs_to_rows = P.pairs_to_rows
# contacts.py's data layout on this target (layout.CPU_LAYOUT says what each means)
HIST_BY_SLOT = CPU_LAYOUT["HIST_BY_SLOT"]
PAIR_ROWS = CPU_LAYOUT["PAIR_ROWS"]
WALL_ROWS = CPU_LAYOUT["WALL_ROWS"]
LIST_ROWS = CPU_LAYOUT["LIST_ROWS"]
# Cell coordinates are packed into one int64 key, 21 bits per axis, so the world
# spans ±2^20 cells per axis (cells of (1 + SKIN) d: ±12 km at 1 cm spheres,
# ±1.2 km at 1 mm; stability.FAR_CELLS counts in diameters, conservatively). Beyond that
# a sphere is clamped into the outermost cell but one: still correct (distances
# are exact), only slow; `dempipe check` warns (stability.py, "far-from-origin").
_CELL_BITS = 21

_CELL_OFF = 1 << (_CELL_BITS - 1)
_CELL_MAX = (1 << _CELL_BITS) - 1


@numba.njit(inline="always", cache=True)
def cell_coord(x, inv_cell):
    # Clamped one cell inside the key range, so that a row's neighbours c ± 1
    # are still valid keys: a sphere beyond ±2^20 cells lands in the outermost
    # cell with everything else out there, found by the neighbour search (slow
    # but correct), not lost through a key overflowing into the next axis.
    c = np.int64(np.floor(x * inv_cell)) + _CELL_OFF
    if c < 1:
        c = 1
    elif c > _CELL_MAX - 1:
        c = _CELL_MAX - 1
    return c


@numba.njit(inline="always", cache=True)
def cell_key(cx, cy, cz):
    return (cx << 42) | (cy << 21) | cz


@numba.njit(inline="always", cache=True)
def cell_hash(cx, cy, cz, grid):
    """Bucket of a cell: its coordinates wrapped into a 2^bx × 2^by × 2^bz table.

    A wrapped grid, not a scrambling hash: cells next to each other in x land in
    consecutive buckets, so a row of three neighbour cells is one contiguous run
    of grid positions (cache friendly). Far-apart cells that wrap onto the same bucket are told apart by
    their keys. grid = (bx, by, mask_x, mask_y, mask_z).
    """
    return ((cz & grid[4]) << (grid[0] + grid[1])) | ((cy & grid[3]) << grid[0]) | (cx & grid[2])


@numba.njit(inline="always", cache=True)
def spread_bits(v):
    """The 21 low bits of v spread to every third bit (bit k to bit 3k)."""
    v &= 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


@numba.njit(inline="always", cache=True)
def morton_key(cx, cy, cz):
    """A cell's place on the Z-order curve (21 bits per axis interleaved): cells
    near each other in all three axes get keys near each other."""
    return (spread_bits(cz) << 2) | (spread_bits(cy) << 1) | spread_bits(cx)


slot_store = compile_slot_store(numba.njit(inline="always", cache=False))
adapt_skin = compile_chain(neighbours, ("adapt_skin",), numba.njit(inline="always", cache=False),
                           {}).adapt_skin
neighbour_list = compile_walk(numba.njit(inline="always", cache=False), F, cell_coord, cell_key,
                              cell_hash, True)


# ---------------------------------------------------------------------------
# Specialization. The stage drivers below are plain functions reading the flags
# FRICTION, ROTATION, SLEEPING, WALLS as globals; ``kernels(flags)`` compiles
# one variant per flag set (compile.specialize), each with its own numba disk
# cache file. The values here (all on) are the general kernel's. Features off
# are compiled out; features on still check their runtime data (``friction``,
# ``sleep_steps`` > 0, per-pair mu, the wall count), so the general kernel on
# a scene that does not use a feature gives the specialized kernel's frames bit
# for bit (tests/test_specialize.py).
#
# TORQUE_NOTE: a contact without friction pushes along the line of centres and
# has no torque about the sphere's centre; physics.sphere_pair_force's
# radius (n × f) rounds to ±1 ulp instead of 0 for a third of the contacts, which
# would spin a one-sphere ball. The kernels add a contact's own torque only
# when its mu > 0, so a frictionless ball keeps L = 0 exactly whichever variant
# runs it, and the variants without friction never read or write sphere_t.
# ---------------------------------------------------------------------------

# Feature flags the stage drivers are compiled for: layout.FLAGS, in ``kernels()``'s order.
FRICTION = True
ROTATION = True
SLEEPING = True
WALLS = True



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


def sphere_state(i, sphere_body, sphere_offset, body_x, body_q, body_v, body_w):
    """Stage 1 for sphere i (eq. 19-21): (x, v, R r') [m, m/s, m], world frame."""
    b = sphere_body[i]
    q = body_q[b]
    if ROTATION:
        return sphere_kinematics(
            body_x[b, 0], body_x[b, 1], body_x[b, 2], q[0], q[1], q[2], q[3],
            body_v[b, 0], body_v[b, 1], body_v[b, 2],
            body_w[b, 0], body_w[b, 1], body_w[b, 2],
            sphere_offset[i, 0], sphere_offset[i, 1], sphere_offset[i, 2])
    # W = 0: sphere_kinematics with the W × r' term dropped
    rx, ry, rz = quat_rotate(q[0], q[1], q[2], q[3], sphere_offset[i, 0],
                             sphere_offset[i, 1], sphere_offset[i, 2])
    return (body_x[b, 0] + rx, body_x[b, 1] + ry, body_x[b, 2] + rz,
            body_v[b, 0], body_v[b, 1], body_v[b, 2], rx, ry, rz)


def stage_spheres(sphere_body, sphere_offset, body_x, body_q, body_v, body_w, inv_cell, grid,
                  sphere_x, sphere_v, sphere_r, sphere_key, sphere_hash):
    """Stage 1 (eq. 19-21) in sphere order, and each sphere's grid cell (stage 2's input)."""
    for i in prange(sphere_body.shape[0]):
        x, y, z, vx, vy, vz, rx, ry, rz = sphere_state(i, sphere_body, sphere_offset, body_x,
                                                       body_q, body_v, body_w)
        sphere_x[i, 0] = x
        sphere_x[i, 1] = y
        sphere_x[i, 2] = z
        sphere_v[i, 0] = vx
        sphere_v[i, 1] = vy
        sphere_v[i, 2] = vz
        sphere_r[i, 0] = rx
        sphere_r[i, 1] = ry
        sphere_r[i, 2] = rz
        cx = cell_coord(x, inv_cell)
        cy = cell_coord(y, inv_cell)
        cz = cell_coord(z, inv_cell)
        sphere_key[i] = cell_key(cx, cy, cz)
        sphere_hash[i] = cell_hash(cx, cy, cz, grid)


def stage_spheres_sorted(slot_of, sphere_body, sphere_offset, body_x, body_q, body_v,
                         body_w, body_still, built_x, rebuild_at2, sorted_x, sorted_v, sphere_r):
    """Stage 1 (eq. 19-21) between rebuilds: straight into the sorted slots of the
    last rebuild (no grid, no sort; slot_of[i] is sphere i's). Returns how many
    spheres have moved sqrt(rebuild_at2) [m] or more since (then the lists must
    be rebuilt). Spheres of a body that slept through the last step, or of a
    static collider (body_still), keep the values computed before: the body has
    not moved since.

    In sphere order, not slot order: a body's spheres are contiguous, so their
    offsets are read and sphere_r written in order and the body's state is read
    once per run of its spheres (1.04-1.06x on the 25 k dense pile than the
    other way round, the same at 275 k, when the slots were sorted by cell); and
    a body's slots are consecutive too (stage_grid_sort), so the stores run in
    order as well.
    CUDA (k_spheres_sorted) runs a thread per slot."""
    moved = 0
    for i in prange(slot_of.shape[0]):
        s = slot_of[i]
        if body_still[sphere_body[i]] != 0:
            continue
        x, y, z, vx, vy, vz, rx, ry, rz = sphere_state(i, sphere_body, sphere_offset, body_x,
                                                       body_q, body_v, body_w)
        moved += slot_store(s, i, x, y, z, vx, vy, vz, rx, ry, rz, sorted_x, sorted_v, sphere_r,
                            built_x, rebuild_at2)
    return moved


@numba.njit(cache=True)
def stage_grid_sort(sphere_hash, body_x, inv_cell, grid, body_sphere_start, bucket_start,
                    bucket_fill, body_key, sorted_idx, slot_of, grid_idx, grid_slot):
    """Stage 2 at a rebuild: the slots, and the grid (serial, stable).

    Slots in body order: the bodies sorted by the bucket of the cell their
    centre is in (stable: ties in body order), each body's spheres in
    consecutive slots in their own order; sorted_idx[s] is the sphere at slot s,
    slot_of[i] the slot of sphere i. Bodies near each other in space get slots
    near each other, and a body's spheres are one run of slots, so stage 1
    stores, the second contact pass writes and the body stage reads each body's
    spheres in order (docs/performance.md: "Bodies in slot order").

    The grid: a counting sort of the spheres by bucket, as CUDA's (k_scatter,
    k_bucket_sort). bucket_start[h]:bucket_start[h+1] are the grid positions of
    bucket h, grid_idx[g] the sphere at position g and grid_slot[g] its slot; within a bucket
    the spheres stay in index order, which keeps everything downstream
    independent of the thread count. Only the first grid[5] buckets are in use.
    """
    nb = body_sphere_start.shape[0] - 1
    for b in range(nb):
        body_key[b] = morton_key(cell_coord(body_x[b, 0], inv_cell),
                                 cell_coord(body_x[b, 1], inv_cell),
                                 cell_coord(body_x[b, 2], inv_cell))
    order = np.argsort(body_key[:nb], kind="mergesort")
    s = 0
    for k in range(nb):
        b = order[k]
        for i in range(body_sphere_start[b], body_sphere_start[b + 1]):
            sorted_idx[s] = i
            slot_of[i] = s
            s += 1
    nbk = grid[5]
    for h in range(nbk + 1):
        bucket_start[h] = 0
    for i in range(sphere_hash.shape[0]):
        bucket_start[sphere_hash[i] + 1] += 1
    for h in range(nbk):
        bucket_start[h + 1] += bucket_start[h]
    for h in range(nbk):
        bucket_fill[h] = bucket_start[h]
    for i in range(sphere_hash.shape[0]):
        h = sphere_hash[i]
        grid_idx[bucket_fill[h]] = i
        grid_slot[bucket_fill[h]] = slot_of[i]
        bucket_fill[h] += 1


@numba.njit(parallel=True, cache=True)
def stage_grid_gather(sorted_idx, grid_idx, sphere_x, sphere_v, sphere_key, sphere_body,
                      sorted_x, sorted_v, sorted_body, grid_x, grid_key, grid_body):
    """Copy sphere data into slot order (what each step reads: a body's spheres,
    and bodies near each other, from contiguous memory), and what the neighbour
    search reads into grid order (a row of three cells from contiguous memory)."""
    for s in prange(sorted_idx.shape[0]):
        i = sorted_idx[s]
        sorted_x[s, 0] = sphere_x[i, 0]
        sorted_x[s, 1] = sphere_x[i, 1]
        sorted_x[s, 2] = sphere_x[i, 2]
        sorted_v[s, 0] = sphere_v[i, 0]
        sorted_v[s, 1] = sphere_v[i, 1]
        sorted_v[s, 2] = sphere_v[i, 2]
        sorted_body[s] = sphere_body[i]
    for g in prange(grid_idx.shape[0]):
        i = grid_idx[g]
        grid_x[g, 0] = sphere_x[i, 0]
        grid_x[g, 1] = sphere_x[i, 1]
        grid_x[g, 2] = sphere_x[i, 2]
        grid_key[g] = sphere_key[i]
        grid_body[g] = sphere_body[i]


@numba.njit(cache=True)
def sphere_neighbours(s0, s1, cutoff2, inv_cell, grid, bucket_start, grid_idx, grid_x,
                      grid_key, grid_body, grid_slot, sorted_idx, sorted_x, sorted_body,
                      body_inv_mass, built_x, nbr, nbr_n):
    """Stages 2-3 for sorted slots s0 .. s1-1: each slot's neighbour list
    (neighbours.neighbour_list); returns how many lists overflowed."""
    cap = nbr.shape[1]
    over = 0
    for s in range(s0, s1):
        if neighbour_list(s, cutoff2, inv_cell, grid, bucket_start, grid_idx, grid_x,
                          grid_key, grid_body, grid_slot, sorted_idx, sorted_x, sorted_body,
                          body_inv_mass, built_x, nbr, nbr_n) > cap:
            over += 1
    return over


@numba.njit(parallel=True, cache=True)
def stage_neighbours(diameter, skin, grid, bucket_start, grid_idx, grid_x, grid_key, grid_body,
                     grid_slot, sorted_idx, sorted_x, sorted_body, body_inv_mass, built_x,
                     nbr, nbr_n):
    """Stages 2-3 at a rebuild: every sorted slot's neighbour list (sphere_neighbours)
    of reach (1 + skin) d, from the grid just sorted (cells of that edge). Returns how
    many lists overflowed (0: all fit)."""
    n = sorted_idx.shape[0]
    n_chunks = (n + CONTACT_CHUNK - 1) // CONTACT_CHUNK
    cutoff = (1.0 + skin) * diameter
    over = 0
    for c in prange(n_chunks):
        over += sphere_neighbours(c * CONTACT_CHUNK, min(n, (c + 1) * CONTACT_CHUNK),
                                  cutoff * cutoff, 1.0 / cutoff, grid, bucket_start,
                                  grid_idx, grid_x, grid_key, grid_body, grid_slot,
                                  sorted_idx, sorted_x, sorted_body,
                                  body_inv_mass, built_x, nbr, nbr_n)
    return over


@numba.njit(parallel=True, cache=True)
def stage_pairs(nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pair_start, pidx, pair_t,
                rows, list_start, list_e):
    """At a rebuild, after stage_neighbours: each list entry's pair index
    (contacts.py). The pairs a slot owns get consecutive rows of pair_f, slot
    after slot: pair_start[s] is slot s's first (a prefix sum of the owners'
    counts, serial: a fixed order), and pair_t[p] is row p's partner slot.
    Returns 0, or the rows needed when that is more than ``rows`` (pair_start
    has the counts; the caller grows pair_f and pair_t). Then each slot's list
    entries packed, (partner slot, pair index), into list_e[list_start[s] ..]
    (contacts.py LIST_ROWS; a serial prefix sum), or a return of the rows needed
    when list_e is too short."""
    n = sorted_idx.shape[0]
    for s in prange(n):
        pair_start[s + 1] = pair_count(s, nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass)
    pair_start[0] = 0
    for s in range(n):
        pair_start[s + 1] += pair_start[s]
    if pair_start[n] > rows:
        return pair_start[n]
    for s in prange(n):
        pair_slots(s, pair_start[s], nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx)
    for s in prange(n):
        pair_mirror(s, nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx)
        for e in range(nbr_n[s]):        # (pair_mirror has set every entry of s's row)
            if pidx[s, e] >= 0:
                pair_t[pidx[s, e]] = nbr[s, e]
    list_start[0] = 0
    for s in range(n):
        list_start[s + 1] = list_start[s] + nbr_n[s]
    if list_start[n] > list_e.shape[0]:
        return list_start[n]
    for s in prange(n):
        q = list_start[s]
        for e in range(nbr_n[s]):
            list_e[q + e, 0] = nbr[s, e]
            list_e[q + e, 1] = pidx[s, e]
    return 0


@numba.njit(parallel=True, cache=True)
def stage_wall_reach(diameter, skin, sorted_x, wall_normal, wall_offset, wall_lo, wall_hi,
                     wall_depth, wall_mask, wall_start, cap, rows):
    """At a rebuild: each slot's walls within reach until the next (contacts.wall_reach),
    for lists of reach (1 + skin) d, and its packed wall rows (contacts.py WALL_ROWS):
    wall_start[s] .. wall_start[s + 1] - 1, one per marked wall up to the ``cap``
    columns of a history row (none for a mask of -1: those search the row). A
    prefix sum, serial: a fixed order. Returns 0, or the rows needed when that is
    more than ``rows`` (the caller grows wall_s)."""
    margin = WALL_SLACK * 0.5 * skin * diameter
    n = sorted_x.shape[0]
    for s in prange(n):
        wall_reach(s, 0.5 * diameter, margin, sorted_x, wall_normal, wall_offset, wall_lo,
                   wall_hi, wall_depth, wall_mask)
    wall_start[0] = 0
    for s in range(n):
        m = wall_mask[s]
        c = 0
        if m != -1:
            while m != 0 and c < cap:
                m &= m - 1                  # one marked wall fewer
                c += 1
        wall_start[s + 1] = wall_start[s] + c
    return wall_start[n] if wall_start[n] > rows else 0


@numba.njit(inline="always", cache=True)
def nth_wall(walls, j):
    """The wall whose bit is the j-th set one of the mask ``walls`` (the inverse of
    contacts.wall_column)."""
    w = 0
    while True:
        if (walls >> w) & 1:
            if j == 0:
                return w
            j -= 1
        w += 1


@numba.njit(parallel=True, cache=True)
def stage_rows_to_pairs(nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass, wall_mask,
                        hist_partner, hist_spring, pair_f, wall_start, wall_s):
    """At a rebuild, with friction: the owned pairs' stretches from the history rows
    (sorted-slot order) into pair_f; the rows keep the walls in reach
    (contacts.rows_to_pairs), whose columns are then copied into the packed wall
    rows wall_s (stretch, 1 + parity or 0), where the steps keep them: the rows'
    copies go stale until stage_pairs_to_rows puts the packed ones back."""
    n = sorted_idx.shape[0]
    for s in prange(n):
        rows_to_pairs(s, s, n, nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass,
                      wall_mask, hist_partner, hist_spring, pair_f)
        q = wall_start[s]
        for j in range(wall_start[s + 1] - q if WALL_ROWS else 0):
            code = hist_partner[s, j]
            wall_s[q + j, 0] = hist_spring[s, j, 0]
            wall_s[q + j, 1] = hist_spring[s, j, 1]
            wall_s[q + j, 2] = hist_spring[s, j, 2]
            wall_s[q + j, 3] = 1.0 + (code & 1) if code != 0 else 0.0


@numba.njit(parallel=True, cache=True)
def stage_pairs_to_rows(nbr, nbr_n, pidx, sorted_idx, hist_partner, hist_spring, pair_f,
                        wall_mask, wall_start, wall_s):
    """Before a re-sort and at the end of a call, with friction: the packed wall rows
    back into their columns of the history rows (the inverse of stage_rows_to_pairs'
    copy), then the touching pairs' stretches (contacts.pairs_to_rows)."""
    n = sorted_idx.shape[0]
    for s in prange(n):
        q = wall_start[s]
        for j in range(wall_start[s + 1] - q if WALL_ROWS else 0):
            if wall_s[q + j, 3] != 0.0:
                code = n + nth_wall(wall_mask[s], j) + 1
                hist_partner[s, j] = (code << 1) | (int(wall_s[q + j, 3]) - 1)
                hist_spring[s, j, 0] = wall_s[q + j, 0]
                hist_spring[s, j, 1] = wall_s[q + j, 1]
                hist_spring[s, j, 2] = wall_s[q + j, 2]
            else:
                hist_partner[s, j] = 0
                hist_spring[s, j, 0] = 0.0
                hist_spring[s, j, 1] = 0.0
                hist_spring[s, j, 2] = 0.0
        pairs_to_rows(s, s, nbr, nbr_n, pidx, sorted_idx, hist_partner, hist_spring, pair_f)


#: A sleeping pile's contact passes run over only the chunks with work left in
#: them (stage_active) once at least this share of the bodies is quiet; below it
#: finding the chunks would cost about what it saves.
QUIET_SHARE = 0.5

#: Steps at least between two searches for the spans (stage_active): the search is
#: a pass over every slot, about what a step with few sleepers spends on them.
#: Between searches the spans stay valid while bodies only fall quiet (they cover
#: more than needed); a body that wakes sends the passes back to every chunk
#: until the next search. (Searching at every change cost 0.91x on a pile waking
#: and settling, half of it quiet; benchmarks/sleeping_pile.py --wake 1800.)
SEARCH_GAP = 8


@numba.njit(inline="always", cache=True)
def body_quiet(b, body_inv_mass, body_rest, body_still, sleep_steps):
    """Whether body b will do nothing in the contact passes of the next step: a
    static collider, or a body asleep that also slept through the step just done
    (body_still), so that its pass-1 and pass-2 results are those already stored."""
    return static_body(body_inv_mass[b]) or (body_rest[b] >= sleep_steps and body_still[b] != 0)


@numba.njit(parallel=True, cache=True)
def stage_active(sorted_body, nbr, nbr_n, body_inv_mass, body_rest, body_still, sleep_steps,
                 chunks, spans):
    """After the body stage: spans[:n] (returned) = for each chunk of sorted slots
    (chunks) with a slot the next step's contact passes must visit, the first and
    one past the last such slot; the rest of the chunk's slots are left out.

    A slot must be visited unless it is static or its body is quiet (body_quiet)
    and so is the body of every partner in its list. Such a slot's visit writes
    nothing: pass 1 at a sleeper computes only pairs with a moving partner (and
    its walls not at all; its trim of the pairs it remembers was done when it
    was last visited, asleep among the same sleepers), pass 2 writes the zero
    force it wrote at its last visit. So the spans give the same State bit for
    bit as every chunk (tests/test_sleeping.py), and a pile where most bodies
    sleep costs what its moving part costs, not its size. Valid for the steps
    after it until a rebuild (new slots) or a quiet body wakes; bodies that fall
    quiet meanwhile only make the spans cover more than needed (run_steps)."""
    n_chunks = chunks.shape[0]
    for c in prange(n_chunks):
        lo = -1
        hi = -1
        for s in range(chunks[c, 0], chunks[c, 1]):
            bi = sorted_body[s]
            if static_body(body_inv_mass[bi]):
                continue
            visit = not body_quiet(bi, body_inv_mass, body_rest, body_still, sleep_steps)
            e = 0
            while not visit and e < nbr_n[s]:
                visit = not body_quiet(sorted_body[nbr[s, e]], body_inv_mass, body_rest,
                                       body_still, sleep_steps)
                e += 1
            if visit:
                if lo < 0:
                    lo = s
                hi = s + 1
        spans[c, 0] = lo
        spans[c, 1] = hi
    n = 0
    for c in range(n_chunks):        # serial, in chunk order: the same spans for any threads
        if spans[c, 0] >= 0:
            spans[n, 0] = spans[c, 0]
            spans[n, 1] = spans[c, 1]
            n += 1
    return n


def stage_contacts(diameter, nbr, nbr_n, pidx, pair_start, pair_t, sorted_idx, sorted_x,
                   sorted_v,
                   sorted_body, body_w, body_inv_mass, body_material,
                   pair_k, pair_zeta, pair_mu, kt_ratio, ks_ratio, friction, dt, parity,
                   hist_partner, hist_spring, sleep_steps, body_rest, body_wake,
                   wall_normal, wall_offset, wall_lo, wall_hi, wall_depth, wall_material,
                   wall_mask, pair_f, wall_f, wall_start, wall_s, spans, n_spans):
    """Stages 3-4, first pass: the force of each contact, computed once, by the
    sphere that owns it (kernels/contacts.py: pair_forces), and each sphere's
    walls, in parallel over the spans of sorted slots spans[:n_spans] (every
    chunk of CONTACT_CHUNK slots, or only those a sleeping pile leaves to do:
    stage_active).

    With friction, each contact's tangential spring lives in its owner's history
    row (hist_partner, hist_spring: the State's contact_partner, contact_spring
    with rows in sorted-slot order, see stage_history_to_slots): a contact found
    again keeps its stretch, a new one starts at zero, and one not touched this
    step (``parity``) is forgotten. Only a slot's own rows are written: gather.
    A sphere of a moving body (rest count 0) that touches a sleeping body flags
    it to wake (body_wake).
    """
    for c in prange(n_spans):
        pair_forces(spans[c, 0], spans[c, 1],
                    diameter, nbr, nbr_n, pidx, pair_start, pair_t, wall_start, wall_s,
                    sorted_idx, sorted_x, sorted_v,
                    sorted_body, body_w, body_inv_mass, body_material,
                    pair_k, pair_zeta, pair_mu, kt_ratio, ks_ratio, friction, dt, parity,
                    hist_partner, hist_spring, sleep_steps, body_rest, body_wake,
                    wall_normal, wall_offset, wall_lo, wall_hi, wall_depth, wall_material,
                    wall_mask, pair_f, wall_f)


def stage_sums(diameter, nbr, nbr_n, pidx, list_start, list_e, sorted_idx, sorted_x,
               sorted_body, body_inv_mass, sleep_steps, body_rest, wall_mask, pair_f, wall_f,
               sphere_f, sphere_t, sphere_overlap, spans, n_spans):
    """Stage 4, second pass (contacts.sphere_forces): each sphere gathers the
    forces on itself, in its list's order (its partners' index order), then its
    walls'; writes sphere_f, sphere_t (torque about the sphere's centre) and
    sphere_overlap (largest overlap this step, [m]). Static and sleeping spheres
    feel no force. Over spans[:n_spans], as stage_contacts."""
    for c in prange(n_spans):
        sphere_forces(spans[c, 0], spans[c, 1],
                      diameter, nbr, nbr_n, pidx, list_start, list_e, sorted_idx, sorted_x,
                      sorted_body,
                      body_inv_mass, sleep_steps, body_rest, wall_mask, pair_f, wall_f,
                      sphere_f, sphere_t, sphere_overlap)


@numba.njit(inline="always", cache=True)
def history_row_copy(src_partner, src_spring, a, dst_partner, dst_spring, b):
    """Row a of a contact history (partners and stretches) into row b of another."""
    for h in range(src_partner.shape[1]):
        dst_partner[b, h] = src_partner[a, h]
        dst_spring[b, h, 0] = src_spring[a, h, 0]
        dst_spring[b, h, 1] = src_spring[a, h, 1]
        dst_spring[b, h, 2] = src_spring[a, h, 2]


@numba.njit(parallel=True, cache=True)
def stage_history_to_slots(sorted_idx, contact_partner, contact_spring, hist_partner,
                           hist_spring):
    """Contact histories from sphere order (the State's) into sorted-slot order.

    Between rebuilds the contact stage reads and writes sphere s's history at row
    s, next to its position, so that friction walks memory in order instead of
    jumping to each sphere's own index (measured: docs/performance.md)."""
    for s in prange(sorted_idx.shape[0]):
        history_row_copy(contact_partner, contact_spring, sorted_idx[s], hist_partner,
                         hist_spring, s)


@numba.njit(parallel=True, cache=True)
def stage_history_to_spheres(sorted_idx, hist_partner, hist_spring, contact_partner,
                             contact_spring):
    """The inverse of stage_history_to_slots (before a re-sort, and at the end of a call)."""
    for s in prange(sorted_idx.shape[0]):
        history_row_copy(hist_partner, hist_spring, s, contact_partner, contact_spring,
                         sorted_idx[s])


@numba.njit(parallel=True, cache=True)
def stage_unsort(sorted_idx, sorted_x, sphere_x):
    """sphere_x in sphere order from the sorted slots (where the spheres were at
    the last step's contact search), for callers that look at them."""
    for s in prange(sorted_idx.shape[0]):
        i = sorted_idx[s]
        sphere_x[i, 0] = sorted_x[s, 0]
        sphere_x[i, 1] = sorted_x[s, 1]
        sphere_x[i, 2] = sorted_x[s, 2]


def body_update(b, dt, gx, gy, gz, body_sphere_start, sphere_f, sphere_t, sphere_r,
                body_mass, body_inv_mass, body_inv_inertia, body_x, body_q, body_P, body_L,
                sleep_steps, v_sleep, w_sleep, body_rest, body_wake, body_still):
    """Stages 5-8 for body b (the body of stage_bodies' loop), with sleeping.

    Returns awake + 2 woke + 4 quiet + 8 calmed: awake (1) when the body will
    integrate at the next step; quiet (4) when it is asleep and slept through
    this step (stage_active's body_quiet); woke (2) when it was quiet before this
    step and is not now; calmed (8) the other way round. body_still[b] = 1 when the body slept
    through this step (did not move): stage 1 may keep its spheres' positions
    from the last step."""
    if SLEEPING and sleep_steps > 0 and body_rest[b] >= sleep_steps:
        was_quiet = body_still[b] != 0
        if body_wake[b] != 0:      # touched by a moving body: integrates from next step
            body_rest[b] = 1
            body_wake[b] = 0
            body_still[b] = 0
            return 1 + (2 if was_quiet else 0)
        body_still[b] = 1
        return 4 + (0 if was_quiet else 8)
    m = body_mass[b]
    FX = m * gx
    FY = m * gy
    FZ = m * gz
    TX = 0.0
    TY = 0.0
    TZ = 0.0
    for i in range(body_sphere_start[b], body_sphere_start[b + 1]):
        fx = sphere_f[i, 0]
        fy = sphere_f[i, 1]
        fz = sphere_f[i, 2]
        FX += fx
        FY += fy
        FZ += fz
        if ROTATION:
            rx = sphere_r[i, 0]
            ry = sphere_r[i, 1]
            rz = sphere_r[i, 2]
            if FRICTION:           # torques about the spheres' centres (TORQUE_NOTE)
                TX += (ry * fz - rz * fy) + sphere_t[i, 0]
                TY += (rz * fx - rx * fz) + sphere_t[i, 1]
                TZ += (rx * fy - ry * fx) + sphere_t[i, 2]
            else:
                TX += ry * fz - rz * fy
                TY += rz * fx - rx * fz
                TZ += rx * fy - ry * fx
    ii = body_inv_inertia[b]
    x = body_x[b]
    q = body_q[b]
    P = body_P[b]
    L = body_L[b]
    im = body_inv_mass[b]
    if ROTATION:
        (x[0], x[1], x[2], q[0], q[1], q[2], q[3], P[0], P[1], P[2], L[0], L[1], L[2]) = \
            body_step(x[0], x[1], x[2], q[0], q[1], q[2], q[3], P[0], P[1], P[2],
                      L[0], L[1], L[2], FX, FY, FZ, TX, TY, TZ, im,
                      ii[0], ii[1], ii[2], ii[3], ii[4], ii[5], dt)
    else:   # body_step's translation, in its arithmetic order; L = 0 and q stay put
        P[0] += FX * dt
        P[1] += FY * dt
        P[2] += FZ * dt
        x[0] += P[0] * im * dt
        x[1] += P[1] * im * dt
        x[2] += P[2] * im * dt
    if SLEEPING and sleep_steps > 0:
        wx = 0.0
        wy = 0.0
        wz = 0.0
        if ROTATION:
            wx, wy, wz = angular_velocity(q[0], q[1], q[2], q[3], ii[0], ii[1], ii[2], ii[3],
                                          ii[4], ii[5], L[0], L[1], L[2])
        r = rest_steps(body_rest[b], P[0] * im, P[1] * im, P[2] * im, wx, wy, wz,
                       v_sleep, w_sleep)
        if r >= sleep_steps:       # falls asleep: at rest exactly
            P[0] = 0.0
            P[1] = 0.0
            P[2] = 0.0
            L[0] = 0.0
            L[1] = 0.0
            L[2] = 0.0
        body_rest[b] = r
        body_wake[b] = 0
        body_still[b] = 0
        return 1 if r < sleep_steps else 0
    return 1


def stage_bodies(n_bodies, dt, gx, gy, gz, body_sphere_start, sphere_f, sphere_t, sphere_r,
                 body_mass, body_inv_mass, body_inv_inertia, body_x, body_q, body_P, body_L,
                 sleep_steps, v_sleep, w_sleep, body_rest, body_wake, body_still):
    """Stages 5-8: sum forces and torques (eq. 15-16), update P, L, X, q (eq. 2-10).

    With sleeping (sleep_steps > 0): a body slower than (v_sleep, w_sleep) for
    sleep_steps steps in a row falls asleep (P = L = 0, no integration) until a
    moving body touches it (body_wake, set by the contact stage). Returns (bodies
    awake for the next step, bodies that woke from quiet, bodies quiet, bodies
    that became quiet: body_update), integer sums: the same for any thread count.
    """
    awake = 0
    woke = 0
    quiet = 0
    calmed = 0
    for b in prange(n_bodies):
        r = body_update(b, dt, gx, gy, gz, body_sphere_start, sphere_f, sphere_t,
                        sphere_r, body_mass, body_inv_mass, body_inv_inertia, body_x,
                        body_q, body_P, body_L, sleep_steps, v_sleep, w_sleep, body_rest,
                        body_wake, body_still)
        awake += r & 1
        woke += (r >> 1) & 1
        quiet += (r >> 2) & 1
        calmed += r >> 3
    return awake, woke, quiet, calmed


def run_steps(n_steps, first_step, dt, diameter, n_bodies, gravity, grid,
              sphere_body, sphere_offset, body_sphere_start, body_mass, body_inv_mass,
              body_inv_inertia, body_material, pair_k, pair_zeta, pair_mu, kt_ratio, ks_ratio,
              friction, contact_partner, contact_spring, hist_partner, hist_spring,
              sleep_steps, v_sleep, w_sleep, body_rest, body_wake, body_still,
              wall_normal, wall_offset, wall_lo, wall_hi, wall_depth, wall_material,
              body_x, body_q, body_P, body_L,
              body_v, body_w, sphere_x, sphere_v, sphere_r, sphere_key, sphere_hash,
              bucket_start, bucket_fill, body_key, grid_slot, sorted_idx, slot_of, sorted_x,
              sorted_v, sorted_body, grid_idx, grid_x, grid_key, grid_body, built_x, nbr,
              nbr_n, pidx, pair_start, pair_t, pair_f, list_start, list_e,
              wall_mask, wall_start, wall_s, wall_f, sphere_f, sphere_t, sphere_overlap, skin_ctl,
              chunks, spans, span_ctl, quiet_share):
    """Advance up to ``n_steps`` steps of the eight stages; everything stays in
    compiled code. Returns (steps done, steps computed). Done is fewer than
    n_steps only when a rebuild found a neighbour list longer than nbr holds
    (nbr_n has the counts), or more pairs than pair_f has rows (pair_start[-1]
    is the count): the caller grows them and calls again, that step not yet
    begun. Computed is fewer than done when every body fell asleep.

    Stages 2-3 (grid, sort, 27-cell search) run only to rebuild the neighbour
    lists: at the first step, when a sphere has moved skin/2 d since, and when a
    wide skin has gone SKIN_SHRINK_ABOVE steps without one (to shrink it). The
    skin (skin_ctl[0], [d]) adapts at each rebuild to how many steps came since
    the last (neighbours.adapt_skin, up to skin_ctl[2]); it changes which pairs
    are listed, never a force (the frames do not depend on it). skin_ctl[1] carries the steps since the last rebuild from call to call,
    skin_ctl[3] counts the rebuilds.

    With sleeping, once every body is asleep the remaining steps are skipped:
    a step then changes nothing (a sleeping body moves only when a moving one
    touches it, and none is left), so skipping them gives the same State bit
    for bit, at no cost. The scratch arrays keep the last step done.
    And once at least quiet_share of the bodies are quiet, the contact passes
    visit only the chunks of slots stage_active finds work in (spans): searched
    at most every SEARCH_GAP steps, after a rebuild (new slots), a wake (a woken
    body's chunks may be missing: every chunk until the next search) or once a
    quarter of the bodies not quiet at the last search have become quiet (the
    spans cover more than needed until then); exact too. span_ctl counts the
    steps run so (0) and the searches (1).
    """
    if n_steps <= 0:
        return 0, 0  # nothing sorted yet: the unsort below would scramble the State's rows
    skin = skin_ctl[0]
    since = skin_ctl[1]
    inv_cell = 1.0 / ((1.0 + skin) * diameter)     # neighbours.cell_size, at this skin
    gx = gravity[0]
    gy = gravity[1]
    gz = gravity[2]
    half_skin = 0.5 * skin * diameter
    rebuild = True
    moved = False
    computed = 0
    n_chunks = chunks.shape[0]
    n_spans = 0
    spans_ok = False        # spans[:n_spans] hold this step's work (stage_active)
    rebuilt = True
    since_search = SEARCH_GAP
    calmed_since = 0        # bodies that became quiet since the last search
    quiet_then = 0          # and how many were quiet at it
    for step in range(first_step, first_step + n_steps):
        computed += 1
        stage_body_velocities(n_bodies, body_P, body_L, body_q, body_inv_mass, body_inv_inertia,
                              body_v, body_w)
        if not rebuild:
            rebuild = stage_spheres_sorted(slot_of, sphere_body, sphere_offset, body_x,
                                           body_q, body_v, body_w, body_still, built_x,
                                           half_skin * half_skin, sorted_x, sorted_v,
                                           sphere_r) > 0
            moved = rebuild
            if not rebuild and skin > SKIN and since > SKIN_SHRINK_ABOVE:
                rebuild = True                  # at rest with a wide skin: shrink it
        if rebuild:
            skin = adapt_skin(skin, since, skin_ctl[2], moved)    # the reach for this build
            inv_cell = 1.0 / ((1.0 + skin) * diameter)
            half_skin = 0.5 * skin * diameter
            since = 0.0
            moved = False
            if FRICTION and friction and step > first_step:   # histories back to sphere order
                stage_pairs_to_rows(nbr, nbr_n, pidx, sorted_idx, hist_partner, hist_spring,
                                    pair_f, wall_mask, wall_start, wall_s)
                stage_history_to_spheres(sorted_idx, hist_partner, hist_spring,
                                         contact_partner, contact_spring)
            stage_spheres(sphere_body, sphere_offset, body_x, body_q, body_v, body_w, inv_cell,
                          grid, sphere_x, sphere_v, sphere_r, sphere_key, sphere_hash)
            stage_grid_sort(sphere_hash, body_x, inv_cell, grid, body_sphere_start,
                            bucket_start, bucket_fill, body_key, sorted_idx, slot_of, grid_idx,
                            grid_slot)
            stage_grid_gather(sorted_idx, grid_idx, sphere_x, sphere_v, sphere_key, sphere_body,
                              sorted_x, sorted_v, sorted_body, grid_x, grid_key, grid_body)
            if FRICTION and friction:
                stage_history_to_slots(sorted_idx, contact_partner, contact_spring,
                                       hist_partner, hist_spring)
            if stage_neighbours(diameter, skin, grid, bucket_start, grid_idx, grid_x, grid_key,
                                grid_body, grid_slot, sorted_idx, sorted_x, sorted_body,
                                body_inv_mass, built_x, nbr, nbr_n) > 0 or \
                    stage_pairs(nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass,
                                pair_start, pidx, pair_t, pair_f.shape[0], list_start,
                                list_e) > 0 or \
                    (WALLS and stage_wall_reach(diameter, skin, sorted_x, wall_normal,
                                                wall_offset, wall_lo, wall_hi, wall_depth,
                                                wall_mask, wall_start,
                                                hist_partner.shape[1] if FRICTION and friction
                                                else 0, wall_s.shape[0]) > 0):
                skin_ctl[0] = skin              # the redo keeps this build's skin
                skin_ctl[1] = since
                return step - first_step, step - first_step   # the histories are current
            skin_ctl[3] += 1.0
            spans_ok = False                    # new slots, new lists
            rebuilt = True
            if FRICTION and friction:
                stage_rows_to_pairs(nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass,
                                    wall_mask, hist_partner, hist_spring, pair_f, wall_start,
                                    wall_s)
            rebuild = False
        work = spans if spans_ok else chunks
        n_work = n_spans if spans_ok else n_chunks
        if spans_ok:
            span_ctl[0] += 1
        stage_contacts(diameter, nbr, nbr_n, pidx, pair_start, pair_t, sorted_idx, sorted_x,
                       sorted_v, sorted_body, body_w, body_inv_mass, body_material,
                       pair_k, pair_zeta, pair_mu, kt_ratio, ks_ratio, friction, dt, step & 1,
                       hist_partner, hist_spring, sleep_steps, body_rest, body_wake,
                       wall_normal, wall_offset, wall_lo, wall_hi, wall_depth, wall_material,
                       wall_mask, pair_f, wall_f, wall_start, wall_s, work, n_work)
        stage_sums(diameter, nbr, nbr_n, pidx, list_start, list_e, sorted_idx, sorted_x,
                   sorted_body, body_inv_mass,
                   sleep_steps, body_rest, wall_mask, pair_f, wall_f, sphere_f, sphere_t,
                   sphere_overlap, work, n_work)
        awake, woke, quiet, calmed = stage_bodies(n_bodies, dt, gx, gy, gz, body_sphere_start,
                                                  sphere_f, sphere_t, sphere_r, body_mass,
                                                  body_inv_mass, body_inv_inertia, body_x,
                                                  body_q, body_P, body_L, sleep_steps, v_sleep,
                                                  w_sleep, body_rest, body_wake, body_still)
        since_search += 1
        calmed_since += calmed
        if rebuilt or woke > 0:
            spans_ok = False    # (at the first step: body_still was stale, rebuilt is set)
        if SLEEPING and sleep_steps > 0 and quiet >= quiet_share * n_bodies and quiet > 0:
            if since_search >= SEARCH_GAP and (
                    not spans_ok or 4 * calmed_since >= n_bodies - quiet_then):
                n_spans = stage_active(sorted_body, nbr, nbr_n, body_inv_mass, body_rest,
                                       body_still, sleep_steps, chunks, spans)
                span_ctl[1] += 1
                spans_ok = True
                since_search = 0
                calmed_since = 0
                quiet_then = quiet
        else:
            spans_ok = False
        rebuilt = False
        since += 1.0
        if SLEEPING and sleep_steps > 0 and awake == 0:
            break                               # all asleep: nothing changes any more
    skin_ctl[0] = skin
    skin_ctl[1] = since
    stage_unsort(sorted_idx, sorted_x, sphere_x)
    if FRICTION and friction:
        stage_pairs_to_rows(nbr, nbr_n, pidx, sorted_idx, hist_partner, hist_spring, pair_f,
                            wall_mask, wall_start, wall_s)
        stage_history_to_spheres(sorted_idx, hist_partner, hist_spring, contact_partner,
                                 contact_spring)
    return n_steps, computed


_STAGES = (stage_body_velocities, sphere_state, stage_spheres, stage_spheres_sorted,
           contacts.pair_forces, contacts.sphere_forces,
           stage_contacts, stage_sums, body_update,
           stage_bodies, run_steps)
_JITS = {
    "stage_body_velocities": numba.njit(parallel=True, cache=True),
    "sphere_state": numba.njit(inline="always", cache=True),
    "stage_spheres": numba.njit(parallel=True, cache=True),
    "stage_spheres_sorted": numba.njit(parallel=True, cache=True),
    "pair_forces": numba.njit(cache=True),
    "sphere_forces": numba.njit(cache=True),
    "stage_contacts": numba.njit(parallel=True, cache=True),
    "stage_sums": numba.njit(parallel=True, cache=True),
    "body_update": numba.njit(cache=True),
    "stage_bodies": numba.njit(parallel=True, cache=True),
    "run_steps": numba.njit(cache=True),
}
_VARIANTS: dict = {}


def kernels(flags, law: str = "linear") -> "types.SimpleNamespace":
    """The stage drivers compiled for ``flags`` (friction, rotation, sleeping, walls)
    and the contact ``law`` (laws.LAWS; the module's formulas are the linear law's,
    another law's are compiled and overlaid), created on first use; numba compiles
    each (or loads it from its disk cache) at its first call."""
    flags = tuple(bool(f) for f in flags)
    key = flags if law == "linear" else (flags, law)
    if key not in _VARIANTS:
        tag = "".join(f"{n[0].upper()}{int(f)}" for n, f in zip(FLAGS, flags))
        consts = {n.upper(): f for n, f in zip(FLAGS, flags)}
        if law != "linear":
            tag += f"_{law}"
            fl = compile_formulas(numba.njit(inline="always", cache=False), law)
            consts.update(sphere_pair_force=fl.sphere_pair_force,
                          sphere_wall_force=fl.sphere_wall_force,
                          contact_coefficients=fl.contact_coefficients, closing=fl.closing)
        _VARIANTS[key] = specialize(_STAGES, _JITS, consts, tag, globals())
    return _VARIANTS[key]


# The backend (host side) lives beside: kernels/cpu_backend.py.
from .cpu_backend import CpuBackend  # noqa: E402,F401  (the name callers import from here)
