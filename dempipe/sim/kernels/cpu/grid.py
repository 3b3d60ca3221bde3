"""The CPU target's rebuild stages (stages 2-3 and the pairing): the grid's
counting sort and gather, the 27-cell neighbour lists, pair rows, walls in reach,
and the contact histories between sphere order and sorted-slot order. They run
only at a neighbour-list rebuild (kernels/cpu/stages.py run_steps); each is compiled
once (they read no feature flag). The CUDA target's twins: kernels/cuda/grid.py,
kernels/cuda/stages.py.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from dempipe.sim.kernels.compile import invalidate_stale_cache
from dempipe.sim.kernels.contacts import CONTACT_CHUNK
from dempipe.sim.kernels.cpu.device import (
    WALL_ROWS,
    cell_coord,
    cell_hash,
    cell_key,
    morton_key,
    neighbour_list,
    pair_count,
    pair_mirror,
    pair_slots,
    pairs_to_rows,
    rows_to_pairs,
    sqrt,
    static_body,
    wall_reach,
)
from dempipe.sim.kernels.layout import BUCKET_BLOCK
from dempipe.sim.kernels.pairing import WALL_SLACK

invalidate_stale_cache(__file__)


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_grid_sort(sphere_hash, body_x, inv_cell, grid, body_sphere_start, bucket_start,
                    bucket_blocks, body_key, sorted_idx, slot_of, grid_idx, grid_slot):
    """Stage 2 at a rebuild: the slots, and the grid (stable).

    Slots in body order: the bodies sorted by the bucket of the cell their
    centre is in (stable: ties in body order), each body's spheres in
    consecutive slots in their own order; sorted_idx[s] is the sphere at slot s,
    slot_of[i] the slot of sphere i. Bodies near each other in space get slots
    near each other, and a body's spheres are one run of slots, so stage 1
    stores, the second contact pass writes and the body stage reads each body's
    spheres in order (docs/performance.md, "Where a step goes").

    The grid: bucket_sort.
    """
    nb = body_sphere_start.shape[0] - 1
    for b in prange(nb):
        body_key[b] = morton_key(cell_coord(body_x[b, 0], inv_cell),
                                 cell_coord(body_x[b, 1], inv_cell),
                                 cell_coord(body_x[b, 2], inv_cell))
    order = np.argsort(body_key[:nb], kind="mergesort")
    first = np.empty(nb, np.int64)          # each body's first slot, in slot order
    s = 0
    for k in range(nb):
        first[k] = s
        b = order[k]
        s += body_sphere_start[b + 1] - body_sphere_start[b]
    for k in prange(nb):
        b = order[k]
        i0 = body_sphere_start[b]
        for i in range(i0, body_sphere_start[b + 1]):
            sorted_idx[first[k] + i - i0] = i
            slot_of[i] = first[k] + i - i0
    bucket_sort(sphere_hash, slot_of, grid, bucket_start, bucket_blocks, grid_idx, grid_slot)


@numba.njit(error_model="numpy", parallel=True, cache=True)
def bucket_sort(sphere_hash, slot_of, grid, bucket_start, bucket_blocks, grid_idx, grid_slot):
    """The grid's counting sort of the spheres by bucket (sphere_hash, in sphere
    order), with each position's slot (slot_of), as CUDA's (k_scatter,
    k_bucket_sort): bucket_start[h]:bucket_start[h+1] are the grid positions of
    bucket h, grid_idx[g] the sphere at position g and grid_slot[g] its slot. Only
    the first grid[5] buckets are in use. A sphere whose hash is -1
    (broadphase.stage_near_others) goes into none.

    Stable: within a bucket the spheres stay in index order, which keeps
    everything downstream independent of the thread count. The table has
    BUCKETS_PER_SPHERE buckets a sphere however few are in the grid, so its
    passes are what costs: the counts go into bucket_start[h] and, per block of
    BUCKET_BLOCK buckets, into bucket_blocks (serial, one read per sphere); the
    blocks' starts are summed serially, and each block's running sum is done in
    parallel, leaving bucket_start[h] = the end of bucket h; the spheres are
    then placed from the last to the first, each at its bucket's end less one,
    which leaves bucket_start[h] = the start of bucket h. Integer sums: the same
    table whatever the thread count."""
    nbk = grid[5]
    n_blocks = (nbk + BUCKET_BLOCK - 1) // BUCKET_BLOCK
    for c in prange(n_blocks):
        bucket_blocks[c] = 0
        for h in range(c * BUCKET_BLOCK, min(nbk, (c + 1) * BUCKET_BLOCK)):
            bucket_start[h] = 0
    for i in range(sphere_hash.shape[0]):
        h = sphere_hash[i]
        if h >= 0:
            bucket_start[h] += 1
            bucket_blocks[h // BUCKET_BLOCK] += 1
    total = 0
    for c in range(n_blocks):               # each block's first position
        n = bucket_blocks[c]
        bucket_blocks[c] = total
        total += n
    for c in prange(n_blocks):
        run = bucket_blocks[c]
        for h in range(c * BUCKET_BLOCK, min(nbk, (c + 1) * BUCKET_BLOCK)):
            run += bucket_start[h]
            bucket_start[h] = run
    bucket_start[nbk] = total
    for i in range(sphere_hash.shape[0] - 1, -1, -1):
        h = sphere_hash[i]
        if h < 0:
            continue
        g = bucket_start[h] - 1
        bucket_start[h] = g
        grid_idx[g] = i
        grid_slot[g] = slot_of[i]


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_grid_gather(sorted_idx, grid_idx, n_grid, sphere_x, sphere_v, sphere_key,
                      sphere_body, sorted_x, sorted_v, sorted_body, grid_x, grid_key,
                      grid_body):
    """Copy sphere data into slot order (what each step reads: a body's spheres,
    and bodies near each other, from contiguous memory), and what the neighbour
    search reads into grid order (a row of three cells from contiguous memory) for
    the n_grid spheres in the grid."""
    for s in prange(sorted_idx.shape[0]):
        i = sorted_idx[s]
        sorted_x[s, 0] = sphere_x[i, 0]
        sorted_x[s, 1] = sphere_x[i, 1]
        sorted_x[s, 2] = sphere_x[i, 2]
        sorted_v[s, 0] = sphere_v[i, 0]
        sorted_v[s, 1] = sphere_v[i, 1]
        sorted_v[s, 2] = sphere_v[i, 2]
        sorted_body[s] = sphere_body[i]
    for g in prange(n_grid):
        i = grid_idx[g]
        grid_x[g, 0] = sphere_x[i, 0]
        grid_x[g, 1] = sphere_x[i, 1]
        grid_x[g, 2] = sphere_x[i, 2]
        grid_key[g] = sphere_key[i]
        grid_body[g] = sphere_body[i]


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_slot_marks(body_sphere_start, slot_of, sorted_x, built_x, body_inv_mass, nbr, nbr_n,
                     moved2, body_half, slot_mark):
    """At a rebuild that may keep the slots (run_steps): slot_mark[s] = 1 for each
    slot of a body one of whose spheres is farther than sqrt(moved2) [m], or than
    its body's rebuild distance (body_half, stage_rest_half) if that is less, from
    where its list was built (built_x; moved2 = 0, and for a static body always: not
    where it was, bit for bit), whose built_x becomes where it is now: its lists
    are searched again from there. Else 2 when the slot's list holds one marked 1,
    else 0. A body below that distance keeps its lists and where they were built,
    so each sphere keeps its own build position and the next rebuild still comes
    when one of them is half the skin from it. Returns (dynamic spheres marked 1,
    static ones: a carried collider's)."""
    cap = nbr.shape[1]
    moved = 0
    moved_static = 0
    for b in prange(body_sphere_start.shape[0] - 1):
        i0 = body_sphere_start[b]
        i1 = body_sphere_start[b + 1]
        if i1 == i0:
            continue
        s0 = slot_of[i0]                # a body's slots are one run (stage_grid_sort)
        s1 = s0 + i1 - i0
        static = static_body(body_inv_mass[b])
        limit = 0.0 if static else min(moved2, body_half[b] * body_half[b])
        far = False
        for s in range(s0, s1):
            ex = sorted_x[s, 0] - built_x[s, 0]
            ey = sorted_x[s, 1] - built_x[s, 1]
            ez = sorted_x[s, 2] - built_x[s, 2]
            if (ex != 0.0 or ey != 0.0 or ez != 0.0) and ex * ex + ey * ey + ez * ez >= limit:
                far = True
                break
        for s in range(s0, s1):
            if far:
                slot_mark[s] = 1
                built_x[s, 0] = sorted_x[s, 0]
                built_x[s, 1] = sorted_x[s, 1]
                built_x[s, 2] = sorted_x[s, 2]
            else:
                slot_mark[s] = 0
        if far:
            if static:
                moved_static += s1 - s0
            else:
                moved += s1 - s0
    for s in prange(slot_mark.shape[0]):    # (only 0 becomes 2 here: the 1s read are final)
        if slot_mark[s] == 0:
            for e in range(min(nbr_n[s], cap)):
                if slot_mark[nbr[s, e]] == 1:
                    slot_mark[s] = 2
                    break
    return moved, moved_static


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_grid_keep(built_x, sorted_body, slot_of, inv_cell, grid, sphere_key, sphere_hash,
                    bucket_start, bucket_blocks, grid_idx, grid_slot, grid_x, grid_key,
                    grid_body):
    """At a rebuild that keeps the slots: the grid of where each slot's list is
    built (built_x, after stage_slot_marks), as stage_grid_sort and stage_grid_gather
    make it (the same counting sort), the slots left as they are. A list then holds
    each sphere whose build position is within its reach of its own: a pair neither
    lists is apart by the reach less what each moved since, more than d."""
    ns = slot_of.shape[0]
    for i in prange(ns):
        s = slot_of[i]
        cx = cell_coord(built_x[s, 0], inv_cell)
        cy = cell_coord(built_x[s, 1], inv_cell)
        cz = cell_coord(built_x[s, 2], inv_cell)
        sphere_key[i] = cell_key(cx, cy, cz)
        sphere_hash[i] = cell_hash(cx, cy, cz, grid)
    bucket_sort(sphere_hash, slot_of, grid, bucket_start, bucket_blocks, grid_idx, grid_slot)
    for g in prange(ns):
        s = grid_slot[g]
        grid_x[g, 0] = built_x[s, 0]
        grid_x[g, 1] = built_x[s, 1]
        grid_x[g, 2] = built_x[s, 2]
        grid_key[g] = sphere_key[grid_idx[g]]
        grid_body[g] = sorted_body[s]


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_neighbours_marked(lo, hi, slot_mark, diameter, skin, grid, bucket_start, grid_idx,
                            grid_x, grid_key, grid_body, grid_slot, sorted_idx, sorted_x,
                            sorted_body, body_inv_mass, built_x, nbr, nbr_n, body_start,
                            step):
    """stage_neighbours for the slots whose mark (stage_slot_marks) is lo .. hi only,
    each searched from ``sorted_x`` (run_steps passes built_x: where its list is
    built); the others keep their lists. Returns how many lists overflowed."""
    n = sorted_idx.shape[0]
    n_chunks = (n + CONTACT_CHUNK - 1) // CONTACT_CHUNK
    cutoff = (1.0 + skin) * diameter
    cap = nbr.shape[1]
    over = 0
    for c in prange(n_chunks):
        for s in range(c * CONTACT_CHUNK, min(n, (c + 1) * CONTACT_CHUNK)):
            if lo <= slot_mark[s] <= hi and neighbour_list(
                    s, cutoff * cutoff, 1.0 / cutoff, grid, bucket_start, grid_idx, grid_x,
                    grid_key, grid_body, grid_slot, sorted_idx, sorted_x, sorted_body,
                    body_inv_mass, built_x, nbr, nbr_n, body_start, step) > cap:
                over += 1
    return over


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_mark_partners(nbr, nbr_n, slot_mark):
    """After the new lists of the slots marked 1 (moved): each partner in them with
    no mark kept a list without that sphere, which is now within reach: marked 3, to
    be searched again (a scatter of one value: the same marks for any thread count)."""
    cap = nbr.shape[1]
    for s in prange(nbr_n.shape[0]):
        if slot_mark[s] == 1:
            for e in range(min(nbr_n[s], cap)):
                t = nbr[s, e]
                if slot_mark[t] == 0:
                    slot_mark[t] = 3


@numba.njit(error_model="numpy", cache=True)
def sphere_neighbours(s0, s1, cutoff2, inv_cell, grid, bucket_start, grid_idx, grid_x,
                      grid_key, grid_body, grid_slot, sorted_idx, sorted_x, sorted_body,
                      body_inv_mass, built_x, nbr, nbr_n, body_start, step, sphere_hash):
    """Stages 2-3 for sorted slots s0 .. s1-1: each slot's neighbour list
    (neighbours.neighbour_list), empty without a search for a sphere the
    broadphase left out of the grid (sphere_hash -1); returns how many lists
    overflowed."""
    cap = nbr.shape[1]
    over = 0
    for s in range(s0, s1):
        if sphere_hash[sorted_idx[s]] < 0:
            built_x[s, 0] = sorted_x[s, 0]
            built_x[s, 1] = sorted_x[s, 1]
            built_x[s, 2] = sorted_x[s, 2]
            nbr_n[s] = 0
        elif neighbour_list(s, cutoff2, inv_cell, grid, bucket_start, grid_idx, grid_x,
                          grid_key, grid_body, grid_slot, sorted_idx, sorted_x, sorted_body,
                          body_inv_mass, built_x, nbr, nbr_n, body_start, step) > cap:
            over += 1
    return over


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_neighbours(diameter, skin, grid, bucket_start, grid_idx, grid_x, grid_key, grid_body,
                     grid_slot, sorted_idx, sorted_x, sorted_body, body_inv_mass, built_x,
                     nbr, nbr_n, body_start, step, sphere_hash):
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
                                  body_inv_mass, built_x, nbr, nbr_n, body_start, step,
                                  sphere_hash)
    return over


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_pairs(nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pair_start, pidx, pair_e,
                rows, list_start, list_e):
    """At a rebuild, after stage_neighbours: each list entry's pair index
    (contacts.py). The pairs a slot owns get consecutive rows of pair_f, slot
    after slot: pair_start[s] is slot s's first (a prefix sum of the owners'
    counts, serial: a fixed order), and pair_e[p] is row p's entry of its owner's
    packed list (below), which holds its partner slot.
    Returns 0, or the rows needed when that is more than ``rows`` (pair_start
    has the counts; the caller grows pair_f and pair_e). Then each slot's list
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
    list_start[0] = 0
    for s in range(n):
        list_start[s + 1] = list_start[s] + nbr_n[s]
    if list_start[n] > list_e.shape[0]:
        return list_start[n]
    for s in prange(n):
        pair_mirror(s, nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx)
        for e in range(nbr_n[s]):        # (pair_mirror has set every entry of s's row)
            if pidx[s, e] >= 0:
                pair_e[pidx[s, e]] = list_start[s] + e
    for s in prange(n):
        q = list_start[s]
        for e in range(nbr_n[s]):
            list_e[q + e, 0] = nbr[s, e]
            list_e[q + e, 1] = pidx[s, e]
    return 0


@numba.njit(inline="always", cache=True)
def body_at_rest(b, body_v, body_w, body_reach, rest_half, rest_time):
    """Whether body b's spheres would take more than rest_time [s] to move rest_half
    [m] at their speed bound |v| + |ω| R (R its farthest sphere, body_reach)."""
    v = sqrt(body_v[b, 0] * body_v[b, 0] + body_v[b, 1] * body_v[b, 1]
             + body_v[b, 2] * body_v[b, 2])
    w = sqrt(body_w[b, 0] * body_w[b, 0] + body_w[b, 1] * body_w[b, 1]
             + body_w[b, 2] * body_w[b, 2])
    return (v + w * body_reach[b]) * rest_time < rest_half


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_rest_half(body_v, body_w, body_reach, body_inv_mass, body_sphere_start, slot_of,
                    slot_mark, kept, half_skin, rest_half, rest_time, body_half):
    """At a rebuild: each body's rebuild distance body_half[b] [m], how far its spheres
    may move from where their lists were built before the next (stage 1,
    stage_slot_marks) and how far past its spheres' reach walls are marked
    (stage_wall_reach): half the skin, ``half_skin``, or ``rest_half`` for a dynamic
    body at rest (body_at_rest, over ``rest_time`` [s]; neighbours.REST_SKIN). A
    body whose lists a rebuild that keeps the slots (``kept``) leaves where they
    were built (not marked 1 by stage_slot_marks) keeps its distance: its spheres
    are measured from there."""
    for b in prange(body_half.shape[0]):
        i0 = body_sphere_start[b]
        if kept and body_sphere_start[b + 1] > i0 and slot_mark[slot_of[i0]] != 1:
            continue
        body_half[b] = half_skin
        if not static_body(body_inv_mass[b]):
            if body_at_rest(b, body_v, body_w, body_reach, rest_half, rest_time):
                body_half[b] = min(rest_half, half_skin)


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_rest_count(body_v, body_w, body_reach, body_inv_mass, body_start, step, rest_half,
                     rest_time, body_half):
    """How many dynamic bodies in the simulation are at rest now (body_at_rest) but keep a wider rebuild distance than ``rest_half`` from a rebuild that
    found them moving: the bodies a rebuild would narrow (run_steps)."""
    n = 0
    for b in prange(body_half.shape[0]):
        if static_body(body_inv_mass[b]) or body_start[b] > step or body_half[b] <= rest_half:
            continue
        if body_at_rest(b, body_v, body_w, body_reach, rest_half, rest_time):
            n += 1
    return n


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_wall_reach(diameter, body_half, sorted_x, wall_normal, wall_offset, wall_lo, wall_hi,
                     wall_depth, wall_mask, wall_start, cap, rows, wall_motion, sorted_body,
                     body_start, step, sorted_idx, sphere_inscribed):
    """At a rebuild: each slot's walls within reach until the next (contacts.wall_reach),
    its sphere moving less than its body's rebuild distance (body_half [m],
    stage_rest_half) from sorted_x, and its packed wall rows (contacts.py WALL_ROWS):
    wall_start[s] .. wall_start[s + 1] - 1, one per marked wall up to the ``cap``
    columns of a history row (none for a mask of -1: those search the row). A
    prefix sum, serial: a fixed order. Returns 0, or the rows needed when that is
    more than ``rows`` (the caller grows wall_s)."""
    n = sorted_x.shape[0]
    for s in prange(n):
        b = sorted_body[s]
        wall_reach(s, sorted_idx[s], 0.5 * diameter, WALL_SLACK * body_half[b], sorted_x,
                   wall_normal, wall_offset, wall_lo, wall_hi, wall_depth, wall_motion,
                   sphere_inscribed, wall_mask)
        if body_start[b] > step:
            wall_mask[s] = 0                # not emitted yet: no wall either
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


@numba.njit(inline="always", cache=True)
def slot_busy(s, nbr_n, wall_mask, sorted_body, body_inv_mass):
    """Whether slot s is busy (stage_busy): a dynamic body's, with a neighbour listed
    or a wall in reach."""
    return (nbr_n[s] > 0 or wall_mask[s] != 0) and \
        not static_body(body_inv_mass[sorted_body[s]])


@numba.njit(inline="always", cache=True)
def history_row_clear(partner, spring, r):
    """Empty row r of a contact history (partner 0 and a zero stretch in every column)."""
    for c in range(partner.shape[1]):
        if partner[r, c] != 0:
            partner[r, c] = 0
            spring[r, c, 0] = 0.0
            spring[r, c, 1] = 0.0
            spring[r, c, 2] = 0.0


@numba.njit(inline="always", cache=True)
def slot_rows_to_pairs(s, nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass, wall_mask,
                       hist_partner, hist_spring, pair_f, wall_start, wall_s):
    """stage_rows_to_pairs for slot s."""
    rows_to_pairs(s, s, sorted_idx.shape[0], nbr, nbr_n, pidx, sorted_idx, sorted_body,
                  body_inv_mass, wall_mask, hist_partner, hist_spring, pair_f)
    q = wall_start[s]
    for j in range(wall_start[s + 1] - q if WALL_ROWS else 0):
        code = hist_partner[s, j]
        wall_s[q + j, 0] = hist_spring[s, j, 0]
        wall_s[q + j, 1] = hist_spring[s, j, 1]
        wall_s[q + j, 2] = hist_spring[s, j, 2]
        wall_s[q + j, 3] = 1.0 + (code & 1) if code != 0 else 0.0


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_rows_to_pairs(nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass, wall_mask,
                        hist_partner, hist_spring, pair_f, wall_start, wall_s):
    """At a rebuild, with friction: the owned pairs' stretches from the history rows
    (sorted-slot order) into pair_f; the rows keep the walls in reach
    (contacts.rows_to_pairs), whose columns are then copied into the packed wall
    rows wall_s (stretch, 1 + parity or 0), where the steps keep them: the rows'
    copies go stale until stage_pairs_to_rows_busy puts the packed ones back. Every
    slot's row: a call's first rebuild, whose rows come from the State."""
    for s in prange(sorted_idx.shape[0]):
        slot_rows_to_pairs(s, nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass,
                           wall_mask, hist_partner, hist_spring, pair_f, wall_start, wall_s)


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_rows_to_pairs_busy(busy, n_busy, held, n_held, nbr, nbr_n, pidx, sorted_idx,
                             sorted_body, body_inv_mass, wall_mask, hist_partner, hist_spring,
                             pair_f, wall_start, wall_s):
    """stage_rows_to_pairs at a later rebuild of a call, for the rows that can hold
    anything: the busy slots' (busy[:n_busy], stage_busy's), and the slots whose
    rows were busy at the last rebuild (held[:n_held], where the rows moved to),
    emptied when they are not busy now (rows_to_pairs would forget every entry of
    a slot with no list and no wall in reach). Every other row is already empty:
    rows_to_pairs emptied it at the rebuild it was left out of, and only busy
    slots write their rows in between. The same rows and pair_f as a pass over
    every slot."""
    for k in prange(n_busy):
        slot_rows_to_pairs(busy[k], nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass,
                           wall_mask, hist_partner, hist_spring, pair_f, wall_start, wall_s)
    for k in prange(n_held):
        s = held[k]
        if not slot_busy(s, nbr_n, wall_mask, sorted_body, body_inv_mass):  # (busy: above)
            history_row_clear(hist_partner, hist_spring, s)


@numba.njit(inline="always", cache=True)
def slot_pairs_to_rows(s, nbr, nbr_n, pidx, sorted_idx, hist_partner, hist_spring, pair_f,
                       wall_mask, wall_start, wall_s):
    """stage_pairs_to_rows_busy for slot s."""
    n = sorted_idx.shape[0]
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


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_pairs_to_rows_busy(busy, n_busy, nbr, nbr_n, pidx, sorted_idx, hist_partner,
                             hist_spring, pair_f, wall_mask, wall_start, wall_s):
    """Before a re-sort and at the end of a call, with friction: the packed wall rows
    back into their columns of the history rows (the inverse of stage_rows_to_pairs'
    copy), then the touching pairs' stretches (contacts.pairs_to_rows), for the busy
    slots (busy[:n_busy]) only: a slot with no list and no wall has an empty row
    (the rebuild that left it out emptied it) and nothing to put back."""
    for k in prange(n_busy):
        slot_pairs_to_rows(busy[k], nbr, nbr_n, pidx, sorted_idx, hist_partner, hist_spring,
                           pair_f, wall_mask, wall_start, wall_s)


@numba.njit(inline="always", cache=True)
def history_row_copy(src_partner, src_spring, a, dst_partner, dst_spring, b):
    """Row a of a contact history (partners and stretches) into row b of another.

    An empty column (partner 0) holds a zero stretch in every history row, so a
    column empty on both sides is left alone: most spheres touch nothing, and their
    stretches are most of the bytes a rebuild would otherwise move."""
    for h in range(src_partner.shape[1]):
        code = src_partner[a, h]
        if code == 0 and dst_partner[b, h] == 0:
            continue
        dst_partner[b, h] = code
        dst_spring[b, h, 0] = src_spring[a, h, 0]
        dst_spring[b, h, 1] = src_spring[a, h, 1]
        dst_spring[b, h, 2] = src_spring[a, h, 2]


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_history_to_slots(sorted_idx, contact_partner, contact_spring, hist_partner,
                           hist_spring):
    """Contact histories from sphere order (the State's) into sorted-slot order.

    Between rebuilds the contact stage reads and writes sphere s's history at row
    s, next to its position, so that friction walks memory in order instead of
    jumping to each sphere's own index (measured: docs/performance.md)."""
    for s in prange(sorted_idx.shape[0]):
        history_row_copy(contact_partner, contact_spring, sorted_idx[s], hist_partner,
                         hist_spring, s)


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_history_to_spheres(sorted_idx, hist_partner, hist_spring, contact_partner,
                             contact_spring):
    """The inverse of stage_history_to_slots (before a re-sort, and at the end of a call)."""
    for s in prange(sorted_idx.shape[0]):
        history_row_copy(hist_partner, hist_spring, s, contact_partner, contact_spring,
                         sorted_idx[s])


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_history_out(busy, n_busy, prev, n_prev, slot_of, sorted_idx, nbr_n, wall_mask,
                      sorted_body, body_inv_mass, hist_partner, hist_spring, contact_partner,
                      contact_spring):
    """stage_history_to_spheres at a re-sort within a call, for the rows that can hold
    anything, and the slot rows emptied behind them (for stage_history_in).

    A slot row holds anything only when its slot is busy (busy[:n_busy]: every other
    row was emptied at the rebuild that left it out, stage_rows_to_pairs_busy), and a
    sphere row of the State's only when its sphere is one of prev[:n_prev] (the busy
    spheres of the last re-sort, whose rows it wrote; a call's first re-sort copies
    every row). So: each busy slot's row goes to its sphere's row and is emptied; each
    of prev's spheres whose slot is no longer busy gets its (empty) row. The same
    State rows as stage_history_to_spheres; afterwards every slot row is empty."""
    for k in prange(n_prev):
        i = prev[k]
        if not slot_busy(slot_of[i], nbr_n, wall_mask, sorted_body, body_inv_mass):
            history_row_clear(contact_partner, contact_spring, i)    # (busy: below)
    for k in prange(n_busy):
        s = busy[k]
        history_row_copy(hist_partner, hist_spring, s, contact_partner, contact_spring,
                         sorted_idx[s])
        history_row_clear(hist_partner, hist_spring, s)


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_history_in(rows, n_rows, slot_of, contact_partner, contact_spring, hist_partner,
                     hist_spring):
    """stage_history_to_slots after stage_history_out's re-sort: the rows of the
    spheres rows[:n_rows] (the only State rows that hold anything) into their new
    slots' rows, every other slot row being empty already."""
    for k in prange(n_rows):
        i = rows[k]
        history_row_copy(contact_partner, contact_spring, i, hist_partner, hist_spring,
                         slot_of[i])


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_unsort(sorted_idx, sorted_x, sphere_x):
    """sphere_x in sphere order from the sorted slots (where the spheres were at
    the last step's contact search), for callers that look at them."""
    for s in prange(sorted_idx.shape[0]):
        i = sorted_idx[s]
        sphere_x[i, 0] = sorted_x[s, 0]
        sphere_x[i, 1] = sorted_x[s, 1]
        sphere_x[i, 2] = sorted_x[s, 2]
