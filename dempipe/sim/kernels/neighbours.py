"""Verlet neighbour lists: the contact search of stages 2-3, done once per many steps.

The paper builds the grid and searches the 27 neighbour cells at every step. Both
targets instead keep, for each sphere, the list of spheres of other bodies closer
than (1 + skin) d when the list was built, and walk only that list at each step.
The lists are rebuilt (grid, counting sort, 27-cell search) at the first step of
each ``step`` call and whenever some sphere has moved skin/2 d or more since the
last build. Between rebuilds no pair outside the lists can touch: each of its two
spheres has moved less than skin/2 d, so their distance is still above d. The skin
is SKIN on CUDA; the CPU adapts it at each rebuild (``adapt_skin``).

The grid of the rebuild has cells of edge (1 + skin) d (``cell_size``), not d: its 27
cells must hold every sphere within the list's reach, (1 + skin) d.

A list is kept in its partners' sphere-index order. The force on a sphere is the
sum over the list of the partners that touch it (a listed pair farther apart than d
adds nothing), in that order, then the walls: so the forces, and the frames, do not
depend on the skin, on when the lists were rebuilt, on the grid's layout or on how the
steps were split into calls. CPU and CUDA sum in the same order.

This module holds what both targets share: the constants, the list build of one
slot (``neighbour_list``, compiled for each by ``compile.compile_walk``) and the
store of one slot between rebuilds (``slot_place``, ``slot_store``); it imports no numba.
"""

import numpy as np

#: Verlet skin [diameters]: a list holds the partners within (1 + SKIN) d; rebuilt
#: when a sphere has moved SKIN/2 d. Larger: longer lists walked every step, fewer
#: rebuilds. Measured: docs/performance.md, "Where a step goes". The CPU adapts its skin
#: between SKIN and SKIN_MAX to how often the lists are rebuilt (adapt_skin); CUDA
#: keeps SKIN.
SKIN = 0.2

#: The CPU's skin grows by SKIN_STEP [diameters] at a rebuild that a sphere's move
#: forced fewer than SKIN_GROW_BELOW steps after the last one (bodies flying and
#: landing: the rebuilds cost more than walking longer lists), up to SKIN_MAX; and
#: shrinks by SKIN_STEP, down to SKIN, at any rebuild more than SKIN_SHRINK_ABOVE
#: steps after the last (a pile coming to rest: walking the lists is the cost; a
#: wide skin that no move forces a rebuild of is rebuilt then, to shrink), and at a
#: rebuild that few bodies force SKIN_GROW_BELOW steps or more after the last
#: (shrink_skin; kernels/cpu/stages.py run_steps: a pile where a few pieces still
#: roll, whose rebuilds keep the slots). Measured on the quickstart, the dense pile
#: and the chess scene: docs/performance.md.
SKIN_MAX = 0.6
SKIN_STEP = 0.1
SKIN_GROW_BELOW = 20
SKIN_SHRINK_ABOVE = 100

#: The CPU's skin range [diameters] where the bodies' spheres are packed closer than
#: DENSE_SPACING d (surface sets: 0.3 d). Ten times a lattice's spheres come within a
#: list's reach of another body's face, and each is placed and tested at every step,
#: so the skin starts narrower than a lattice's; but a rebuild places and sorts every
#: sphere, eight times a lattice's, so it may grow past a lattice's smallest to keep
#: rebuilds rare (``skin_range``; measured: docs/performance.md, "Surface sphere sets").
SKIN_MIN_DENSE = 0.1
SKIN_MAX_DENSE = 0.3
DENSE_SPACING = 0.9

#: A dynamic body at rest at a rebuild, whose spheres move slower than REST_SKIN/2 d
#: in REST_STEPS steps (|v| + |ω| R, R its farthest sphere), is rebuilt when one of
#: them has moved REST_SKIN/2 d instead of half the skin, and so marks only the walls
#: within that of its spheres, with slack (the CPU's; kernels/cpu/grid.py
#: stage_rest_half). A surface set's flat face rounds into its edges: a chess piece
#: standing on a board has a ring of spheres round its foot's 0.02 d above the floor,
#: within a skin's wall margin but not this one, so while it stands the contact
#: passes and stage 1 leave that ring out. A body that starts moving forces a rebuild
#: sooner, which gives it half the skin again.
REST_SKIN = 0.02
REST_STEPS = 500

#: A row of three cells holding more spheres than this is searched bucket by bucket,
#: each bucket that holds only the searching sphere's own body skipped whole (a
#: surface set's shell fills the cells round most of its spheres); a shorter row is
#: walked in one run, where the two extra reads per bucket would cost more than the
#: few spheres they skip. Measured: docs/performance.md, "Where a step goes".
LONG_ROW = 8

#: Entries per sphere a backend allocates to start with. A rebuild that finds a
#: longer list (a sphere deep in others, a dense pile of small bodies) makes the
#: backend grow the lists and carry on from that step (the CPU returns before the
#: step's contacts; on CUDA nothing of the State changes from that step on and the
#: host relaunches the remaining steps): contacts are never dropped.
NEIGHBOURS = 16


def cell_size(diameter: float) -> float:
    """Edge of the rebuild grid's cells [m] at SKIN: the lists' reach, (1 + SKIN) d,
    so the 27 cells round a sphere hold every partner a list may need. CUDA's cells
    always; the CPU's grid table is sized for them, and its cells follow its skin
    (adapt_skin, run_steps): larger, or down to (1 + SKIN_MIN_DENSE) d for dense
    sets, whose few more cells across the extent may share buckets (still correct:
    the cells' keys tell them apart)."""
    return (1.0 + SKIN) * diameter


def shrink_skin(skin, skin_min):
    """The skin one SKIN_STEP narrower, down to exactly skin_min (0.2 + 0.1 - 0.1 is
    0.20000000000000004 in floating point, which would keep asking run_steps for a
    rebuild to shrink)."""
    return skin_min if skin - SKIN_STEP < skin_min + 0.5 * SKIN_STEP else skin - SKIN_STEP


def adapt_skin(skin, since, skin_min, skin_max, moved):
    """The skin [diameters] for a rebuild ``since`` steps after the last one, forced
    by a sphere's move (``moved``) or not (a call's first step, or to shrink; see
    SKIN_MAX), between skin_min and skin_max (``skin_range``). The frames do not
    depend on it: a list holds every pair that can touch before the next rebuild,
    whatever its reach."""
    if since > SKIN_SHRINK_ABOVE:
        return shrink_skin(skin, skin_min)
    if moved and since < SKIN_GROW_BELOW:
        return min(skin_max, skin + SKIN_STEP)
    return skin


def skin_range(model) -> tuple[float, float]:
    """The CPU's (smallest, largest) skin for ``model`` [diameters]: (SKIN_MIN_DENSE,
    SKIN_MAX_DENSE) when most of the dynamic bodies' contact spheres (by count) are
    closer than DENSE_SPACING d to the nearest other sphere of their shape, else (SKIN,
    SKIN_MAX). Called once per backend; scipy is imported here so that the kernels,
    which import this module, do not load it."""
    from scipy.spatial import cKDTree

    nb = model.n_bodies
    counts = np.bincount(model.body_shape[:nb][model.body_inv_mass[:nb] > 0],
                         minlength=len(model.shapes))
    dense = 0
    total = 0
    for shape, n in zip(model.shapes, counts):
        c = np.asarray(shape.contact_centers if shape.contact_centers is not None
                       else shape.sphere_set.centers)
        if n == 0 or len(c) < 2:
            continue
        gap = cKDTree(c).query(c, k=2)[0][:, 1]
        dense += n * int(np.count_nonzero(gap < DENSE_SPACING * model.diameter))
        total += n * len(c)
    if 2 * dense > total:
        return SKIN_MIN_DENSE, SKIN_MAX_DENSE
    return SKIN, SKIN_MAX


def slot_place(s, i, x, y, z, vx, vy, vz, rx, ry, rz, sorted_x, sorted_v, sphere_r):
    """Stage 1 for sorted slot s (sphere i): its position and velocity [m, m/s] into
    the slot, its offset R r' [m] into sphere_r[i]."""
    sorted_x[s, 0] = x
    sorted_x[s, 1] = y
    sorted_x[s, 2] = z
    sorted_v[s, 0] = vx
    sorted_v[s, 1] = vy
    sorted_v[s, 2] = vz
    sphere_r[i, 0] = rx
    sphere_r[i, 1] = ry
    sphere_r[i, 2] = rz


def slot_store(s, i, x, y, z, vx, vy, vz, rx, ry, rz, sorted_x, sorted_v, sphere_r, built_x,
               rebuild_at2):
    """Stage 1 between rebuilds, for sorted slot s (sphere i): slot_place into the
    slot of the last build. Returns 1 when it has moved sqrt(rebuild_at2) [m] or more
    since that build (then the lists must be rebuilt), else 0. Written once, compiled
    for each target (kernels.cpu.spheres.stage_spheres_busy,
    kernels.cuda.grid.k_spheres_sorted)."""
    slot_place(s, i, x, y, z, vx, vy, vz, rx, ry, rz, sorted_x, sorted_v, sphere_r)
    ex = x - built_x[s, 0]
    ey = y - built_x[s, 1]
    ez = z - built_x[s, 2]
    return 1 if ex * ex + ey * ey + ez * ez >= rebuild_at2 else 0


def neighbour_list(s, cutoff2, inv_cell, grid, bucket_start, grid_idx, grid_x, grid_key,
                   grid_body, grid_slot, sorted_idx, sorted_x, sorted_body, body_inv_mass,
                   built_x, nbr, nbr_n, body_start, step):
    """Stages 2-3 for sorted slot s at a rebuild: its neighbour list. Returns its
    true length (more than nbr.shape[1] when it overflowed).

    nbr[s, :nbr_n[s]] are the slots of the spheres of other bodies closer than
    sqrt(cutoff2) [m], found over the 27 cells round s, in the order of their
    sphere index (so the forces are summed in an order that does not depend on
    the grid, the slots or when lists are rebuilt). A static sphere gets none (it
    feels nothing), nor does a sphere of a body not yet in the simulation at
    ``step`` (body_start, an emitter's), which is in no list either. A list that
    would hold more than nbr.shape[1] keeps its true
    count in nbr_n and stores what fits. Notes the slot's position at the build
    (built_x). Written once, compiled for each target (compile.compile_walk) with
    that target's cell_coord, cell_key, cell_hash and GRID_SLOTS.

    The grid: bucket_start[h]:bucket_start[h+1] are the grid positions of bucket
    h; grid_idx, grid_x, grid_key, grid_body are the sphere index, position, cell
    key and body at each position, read in order along a row of cells. On CUDA
    (GRID_SLOTS False) the slots are sorted by bucket: they are the grid (the
    grid_* arrays are the sorted_* ones) and a position is a slot. On the CPU
    the slots are in body order (kernels/cpu/stages.py: stage_grid_sort) and
    grid_slot[g] is the slot of the sphere at position g.
    """
    cap = nbr.shape[1]
    xi = sorted_x[s, 0]
    yi = sorted_x[s, 1]
    zi = sorted_x[s, 2]
    built_x[s, 0] = xi
    built_x[s, 1] = yi
    built_x[s, 2] = zi
    bi = sorted_body[s]
    n = 0
    if static_body(body_inv_mass[bi]) or body_start[bi] > step:  # noqa: F821 (the target's)
        nbr_n[s] = 0
        return 0
    cx0 = cell_coord(xi, inv_cell)  # noqa: F821 (the target's, see compile_walk)
    cy0 = cell_coord(yi, inv_cell)  # noqa: F821
    cz0 = cell_coord(zi, inv_cell)  # noqa: F821
    for dz in range(-1, 2):
        for dy in range(-1, 2):
            cy = cy0 + dy
            cz = cz0 + dz
            # the three cells (cx0-1..cx0+1, cy, cz): keys in [lo, hi]
            key_lo = cell_key(cx0 - 1, cy, cz)  # noqa: F821
            key_hi = cell_key(cx0 + 1, cy, cz)  # noqa: F821
            h_lo = cell_hash(cx0 - 1, cy, cz, grid)  # noqa: F821
            h_hi = cell_hash(cx0 + 1, cy, cz, grid)  # noqa: F821
            wraps = h_hi != h_lo + 2    # round the table: three runs of buckets
            n_runs = 3                  # (or a long row: bucket by bucket)
            if not wraps:
                t0 = bucket_start[h_lo]
                t1 = bucket_start[h_hi + 1]
                if t1 - t0 <= LONG_ROW:
                    n_runs = 1
            for run in range(n_runs):
                if n_runs == 3:
                    h = h_lo + run
                    if wraps:
                        h = cell_hash(cx0 - 1 + run, cy, cz, grid)  # noqa: F821
                    t0 = bucket_start[h]
                    t1 = bucket_start[h + 1]
                    # A bucket lists its spheres in index order and a body's spheres
                    # have consecutive indices, so one whose first and last are
                    # this body's holds nothing else: skipped whole.
                    if t1 == t0 or (grid_body[t0] == bi and grid_body[t1 - 1] == bi):
                        continue
                for g in range(t0, t1):
                    kt = grid_key[g]
                    if kt < key_lo or kt > key_hi:
                        continue        # another cell sharing the buckets
                    if grid_body[g] == bi:
                        continue        # spheres of one body never collide
                    rx = grid_x[g, 0] - xi
                    ry = grid_x[g, 1] - yi
                    rz = grid_x[g, 2] - zi
                    if rx * rx + ry * ry + rz * rz >= cutoff2:
                        continue
                    if body_start[grid_body[g]] > step:
                        continue        # not emitted yet
                    if n < cap:         # insert in sphere-index order
                        it = grid_idx[g]
                        p = n
                        while p > 0 and sorted_idx[nbr[s, p - 1]] > it:
                            nbr[s, p] = nbr[s, p - 1]
                            p -= 1
                        nbr[s, p] = grid_slot[g] if GRID_SLOTS else g  # noqa: F821
                    n += 1
    nbr_n[s] = n
    return n
