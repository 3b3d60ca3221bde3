"""Stages 1-3 on the device: spheres from their bodies, the grid (cells, buckets,
prefix sum, scatter, per-bucket sort, gather) and the neighbour lists; the
CPU's kernels/cpu/stages.py stage_spheres*, stage_grid_sort, stage_neighbours.

Imported by kernels/cuda/backend.py (the backend launches them); see docs/cuda.md.
"""

from __future__ import annotations

from numba import cuda, int64

from dempipe.sim.kernels.cuda.device import (
    CTL_FORCE,
    CTL_IDLE,
    CTL_MAXN,
    CTL_MOVED,
    CTL_OVER,
    CTL_STEP,
    SCAN_B,
    SCAN_CHUNK,
    SCAN_ITEMS,
    cell_coord,
    cell_hash,
    cell_key,
    neighbour_list,
    rebuilding,
    slot_place,
    slot_store,
    sphere_kinematics,
)


@cuda.jit
def k_spheres_sorted(sorted_idx, sphere_body, sphere_offset, body_x, body_q, body_v, body_w,
                     h, built_x, rebuild_at2, sorted_x, sorted_v, sphere_r, ctl):
    """Stage 1 (eq. 19-21) between rebuilds: straight into the sorted slots of the
    last rebuild (kernels.cpu.stages.stage_spheres_sorted). Counts the spheres that moved
    sqrt(rebuild_at2) [m] or more since (integer atomic add into ctl[CTL_MOVED]):
    then this step rebuilds. Returns at once when the step rebuilds anyway
    (CTL_FORCE: the first step of a call), as the CPU skips it then."""
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0] or ctl[CTL_FORCE] != 0 or ctl[CTL_IDLE] != 0:
        return
    i = sorted_idx[s]
    b = sphere_body[i]
    x, y, z, vx, vy, vz, rx, ry, rz = sphere_kinematics(
        body_x[b, 0], body_x[b, 1], body_x[b, 2],
        body_q[b, 0], body_q[b, 1], body_q[b, 2], body_q[b, 3],
        body_v[b, 0], body_v[b, 1], body_v[b, 2], body_w[b, 0], body_w[b, 1], body_w[b, 2],
        sphere_offset[i, 0], sphere_offset[i, 1], sphere_offset[i, 2], h)
    if slot_store(s, i, x, y, z, vx, vy, vz, rx, ry, rz, sorted_x, sorted_v, sphere_r, built_x,
                  rebuild_at2):
        cuda.atomic.add(ctl, CTL_MOVED, 1)       # integer: order-independent


@cuda.jit
def k_zero_buckets(bucket_start, bucket_fill, ctl):
    if not rebuilding(ctl):
        return
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for h in range(start, bucket_start.shape[0], stride):
        bucket_start[h] = 0
    for h in range(start, bucket_fill.shape[0], stride):
        bucket_fill[h] = 0


@cuda.jit
def k_spheres(sphere_body, sphere_offset, body_x, body_q, body_v, body_w, h, inv_cell, grid,
              sphere_x, sphere_v, sphere_r, sphere_key, sphere_hash, bucket_start, ctl):
    """Stage 1 (eq. 19-21) in sphere order at a rebuild, each sphere's grid cell,
    and the bucket counts."""
    i = cuda.grid(1)
    if i >= sphere_body.shape[0] or not rebuilding(ctl):
        return
    b = sphere_body[i]
    x, y, z, vx, vy, vz, rx, ry, rz = sphere_kinematics(
        body_x[b, 0], body_x[b, 1], body_x[b, 2],
        body_q[b, 0], body_q[b, 1], body_q[b, 2], body_q[b, 3],
        body_v[b, 0], body_v[b, 1], body_v[b, 2], body_w[b, 0], body_w[b, 1], body_w[b, 2],
        sphere_offset[i, 0], sphere_offset[i, 1], sphere_offset[i, 2], h)
    slot_place(i, i, x, y, z, vx, vy, vz, rx, ry, rz, sphere_x, sphere_v, sphere_r)
    cx = cell_coord(x, inv_cell)
    cy = cell_coord(y, inv_cell)
    cz = cell_coord(z, inv_cell)
    sphere_key[i] = cell_key(cx, cy, cz)
    h = cell_hash(cx, cy, cz, grid)
    sphere_hash[i] = h
    cuda.atomic.add(bucket_start, h + 1, 1)      # integer: order-independent


@cuda.jit
def k_scan_blocks(data, block_sums, ctl):
    """Inclusive prefix sum of each SCAN_CHUNK-element chunk of ``data`` in place;
    each chunk's total goes to block_sums. Each thread scans SCAN_ITEMS
    consecutive elements serially, the block scans the threads' totals
    (Hillis-Steele in shared memory), then each thread adds its offset.
    The whole grid returns (before any barrier) when ``ctl`` says no rebuild."""
    if not rebuilding(ctl):
        return
    tmp = cuda.shared.array(SCAN_B, int64)
    tid = cuda.threadIdx.x
    n = data.shape[0]
    first = cuda.blockIdx.x * SCAN_CHUNK + tid * SCAN_ITEMS
    total = int64(0)
    for j in range(first, min(first + SCAN_ITEMS, n)):
        total += data[j]
        data[j] = total
    tmp[tid] = total
    cuda.syncthreads()
    off = 1
    while off < SCAN_B:
        add = int64(0)
        if tid >= off:
            add = tmp[tid - off]
        cuda.syncthreads()
        tmp[tid] += add
        cuda.syncthreads()
        off *= 2
    before = tmp[tid] - total
    for j in range(first, min(first + SCAN_ITEMS, n)):
        data[j] += before
    if tid == SCAN_B - 1:
        block_sums[cuda.blockIdx.x] = tmp[tid]


@cuda.jit
def k_scan_add(data, block_sums, ctl):
    """Second pass of the multi-level scan: add the scanned totals of the chunks before."""
    if not rebuilding(ctl):
        return
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for i in range(start + SCAN_CHUNK, data.shape[0], stride):
        data[i] += block_sums[i // SCAN_CHUNK - 1]


@cuda.jit
def k_scatter(sphere_hash, bucket_start, bucket_fill, sorted_idx, ctl):
    """Stage 2: each sphere claims a slot of its bucket (integer atomic add)."""
    i = cuda.grid(1)
    if i >= sphere_hash.shape[0] or not rebuilding(ctl):
        return
    h = sphere_hash[i]
    slot = bucket_start[h] + cuda.atomic.add(bucket_fill, h, 1)
    sorted_idx[slot] = i


@cuda.jit
def k_bucket_sort(bucket_start, sorted_idx, ctl):
    """Sort each bucket's slots by sphere index (insertion sort: buckets hold 1-few
    spheres), making the order that of the CPU's stable counting sort."""
    if not rebuilding(ctl):
        return
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for h in range(start, bucket_start.shape[0] - 1, stride):
        t0 = bucket_start[h]
        t1 = bucket_start[h + 1]
        for a in range(t0 + 1, t1):
            v = sorted_idx[a]
            c = a - 1
            while c >= t0 and sorted_idx[c] > v:
                sorted_idx[c + 1] = sorted_idx[c]
                c -= 1
            sorted_idx[c + 1] = v


@cuda.jit
def k_gather(sorted_idx, sphere_x, sphere_v, sphere_key, sphere_body,
             sorted_x, sorted_v, sorted_key, sorted_body, slot_of, ctl):
    """Copy sphere data into sorted order, so neighbours are read from contiguous
    memory, and note each sphere's slot (slot_of: the contact patches' pass)."""
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0] or not rebuilding(ctl):
        return
    i = sorted_idx[s]
    sorted_x[s, 0] = sphere_x[i, 0]
    sorted_x[s, 1] = sphere_x[i, 1]
    sorted_x[s, 2] = sphere_x[i, 2]
    sorted_v[s, 0] = sphere_v[i, 0]
    sorted_v[s, 1] = sphere_v[i, 1]
    sorted_v[s, 2] = sphere_v[i, 2]
    sorted_key[s] = sphere_key[i]
    sorted_body[s] = sphere_body[i]
    slot_of[i] = s


@cuda.jit
def k_neighbours(cutoff2, inv_cell, grid, bucket_start, sorted_idx, sorted_x, sorted_key,
                 sorted_body, body_inv_mass, built_x, nbr, nbr_n, body_start, ctl):
    """Stages 2-3 at a rebuild: each sorted slot's neighbour list, from the grid
    just sorted (kernels.cpu.grid.sphere_neighbours, one thread per slot).

    nbr[s, :nbr_n[s]] are the slots of the spheres of other bodies closer than
    sqrt(cutoff2) [m], found over the 27 cells in the CPU's order and inserted
    in the order of their sphere index; static spheres get none. built_x[s] is
    the slot's position at the build. A list longer than nbr.shape[1] keeps its
    true count in nbr_n and stores what fits; the overflow is counted in
    ctl[CTL_OVER] and its length maxed into ctl[CTL_MAXN] (integer atomics),
    for the host to grow nbr and carry on from this step.
    """
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0] or not rebuilding(ctl):
        return
    cap = nbr.shape[1]
    # the slots are sorted by bucket: they are the grid, and a grid position is a
    # slot (grid_slot, the tenth argument, is not read; the CPU's slots are in
    # body order instead)
    n = neighbour_list(s, cutoff2, inv_cell, grid, bucket_start, sorted_idx, sorted_x,
                       sorted_key, sorted_body, sorted_idx, sorted_idx, sorted_x, sorted_body,
                       body_inv_mass, built_x, nbr, nbr_n, body_start, ctl[CTL_STEP])
    if n > cap:
        cuda.atomic.add(ctl, CTL_OVER, 1)        # integer atomics: order-independent
        cuda.atomic.max(ctl, CTL_MAXN, n)


@cuda.jit
def k_unsort(sorted_idx, sorted_x, sphere_x):
    """sphere_x in sphere order from the sorted slots (where the spheres were at
    the last step's contact search; kernels.cpu.grid.stage_unsort)."""
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0]:
        return
    i = sorted_idx[s]
    sphere_x[i, 0] = sorted_x[s, 0]
    sphere_x[i, 1] = sorted_x[s, 1]
    sphere_x[i, 2] = sorted_x[s, 2]
