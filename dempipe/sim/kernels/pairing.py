"""The rebuild's pairing, for both targets: what the contact passes
(kernels/contacts.py) find ready at each step.

At each rebuild of the neighbour lists: each list entry's pair index (the owner's
row of ``pair_f``, or its partner's, negated: ``pair_slots``, ``pair_mirror``), the
walls each slot can reach before the next rebuild (``wall_reach``), and the
contact histories moved between the State's rows and the pairs' rows
(``rows_to_pairs``, ``pairs_to_rows``, ``walls_to_front``, ``wall_column``); the
per-step passes then read and write a contact's stretch with no search.
Ownership (``owns``): the lower sphere index, or the dynamic sphere against a
static one (contacts.py's docstring says why a contact is computed once).

Plain functions, compiled with each target's formulas by compile.compile_pairing;
they read no feature flag, so they need no variants.
"""

from dempipe.spheres.inscribed import COVERED

#: ``pidx`` of a list entry whose partner's list does not hold it back. Cannot
#: happen (lists are symmetric: the same distance, cells and keys from either
#: side), but a pair that was found from one side only is at the lists' reach,
#: (1 + SKIN) d, and cannot touch before the next rebuild anyway.
UNPAIRED = -(1 << 30)

#: Columns of a row of pair_f: the force on the owner (0-2) [N], the torque about
#: its centre (3-5) [N m], the contact's tangential stretch (6-8) [m], and 1 + the
#: parity of the step when it touched at the last step that computed it, else 0 (9).
PAIR_COLS = 10

#: Rows of pair_f per sphere the CPU allocates to start with (a dense pile of cubes
#: owns 0.9 listed pairs per sphere); grown when a rebuild finds more.
PAIRS_PER_SPHERE = 2

#: Packed list entries per sphere the CPU allocates to start with (the dense pile
#: lists 1.8); grown when a rebuild finds more.
LIST_PER_SPHERE = 4

#: Columns of a packed list entry (list_e, the CPU's): the partner slot, the pair
#: index (as pidx), and 1 when the pair touches this step or is in the step after
#: (pair_ended), else 0: written by patches.body_patches, read by pair_forces
#: (through pair_e) and sphere_forces.
LIST_COLS = 3

#: Walls a slot's bit mask can name (wall_reach); with more, every slot checks every wall.
WALL_BITS = 63

#: How far past its reach a wall is still marked, in units of the distance a sphere
#: may move between rebuilds (SKIN/2 d): room for the rounding of the dot products.
WALL_SLACK = 1.25
#: When a ring's axis is along a wall's normal, every point of the ring is as low:
#: contacts.inscribed_wall then takes the point under the sphere, by adding this much
#: of its direction [1] to the ring's lowest direction (a tie-break: elsewhere it moves
#: the point by about 1e-6 rad and its height by 1e-12 of the ring's radius).
RING_TIE = 1e-6
#: The same for a rim's ring (a tube of radius 0: spheres/inscribed.py rims), which many
#: spheres round it hold: with RING_TIE a rim lying a hair off flat on a wall (a cap
#: landing flat) moved every holder's point to its lowest one, and the rim's whole share
#: of the face's force went to one side and tipped the body. This much [1] turns a
#: holder's point from the lowest towards its own by about RIM_TIE sin ψ / sin(tilt)
#: rad (ψ its angle round the rim from the lowest point): under its own while the rim
#: is within RIM_TIE rad of flat; on a rim on edge (a piece on its side) 7e-4 rad at
#: the nearest holder (ψ ≤ 4°), whose point is then 2.5e-7 of the rim's radius higher.
#: A band (two rims closer than d, one ring swept along its axis) takes its lower
#: edge, and within RIM_TIE of lying flat on the wall slides its point between its
#: edges (contacts.inscribed_wall), so the contact does not jump from edge to edge.
RIM_TIE = 0.01


def wall_reach(s, i, radius, margin, sorted_x, wall_normal, wall_offset, wall_lo, wall_hi,
               wall_depth, wall_motion, sphere_inscribed, wall_mask):
    """At a rebuild: wall_mask[s] gets bit w for each wall w that slot s (sphere i) may
    touch before the next rebuild (-1: every wall, when there are more than WALL_BITS;
    0 for a sphere its neighbours cover, row i of ``sphere_inscribed`` saying so in
    column COVERED: spheres/inscribed.py wall_cover).

    A sphere whose row is a torus (spheres/inscribed.py: offset from the sphere or a
    ring) may touch a wall up to its reach (column 11) deeper than its own sphere
    (contacts.inscribed_wall), so it marks walls that much further; a row that is a
    ball at the sphere's centre, of radius at most r, reaches no deeper than the sphere.

    A sphere moves less than SKIN/2 d between rebuilds, so a wall farther than
    that (``margin`` [m], with slack) beyond the contact test of sphere_forces
    cannot pass it; only the marked walls are tested at each step. In a box most
    spheres are far from every wall: their step skips the walls altogether.
    A moving wall (wall_motion ≥ 0) may come to any sphere: always marked."""
    n_walls = wall_normal.shape[0]
    if sphere_inscribed.shape[0] > 0:
        if sphere_inscribed[i, COVERED] != 0.0:
            wall_mask[s] = 0
            return
        if (sphere_inscribed[i, 0] != 0.0 or sphere_inscribed[i, 1] != 0.0
                or sphere_inscribed[i, 2] != 0.0 or sphere_inscribed[i, 9] != 0.0):
            margin += sphere_inscribed[i, 11]
    if n_walls > WALL_BITS:
        wall_mask[s] = -1
        return
    xi = sorted_x[s, 0]
    yi = sorted_x[s, 1]
    zi = sorted_x[s, 2]
    mask = 0
    for w in range(n_walls):
        if wall_motion[w] >= 0:
            mask |= 1 << w
            continue
        dist = wall_normal[w, 0] * xi + wall_normal[w, 1] * yi + wall_normal[w, 2] * zi \
            - wall_offset[w]
        if dist >= radius + margin or dist <= -wall_depth[w] - margin:
            continue
        if (xi < wall_lo[w, 0] - margin or xi > wall_hi[w, 0] + margin
                or yi < wall_lo[w, 1] - margin or yi > wall_hi[w, 1] + margin
                or zi < wall_lo[w, 2] - margin or zi > wall_hi[w, 2] + margin):
            continue
        mask |= 1 << w
    wall_mask[s] = mask


def entry_range(packed, starts, nbr_n, s):
    """The entries slot s walks: its packed rows starts[s] .. starts[s + 1] - 1
    (``packed``: PAIR_ROWS, LIST_ROWS), or its list's 0 .. nbr_n[s] - 1."""
    if packed:
        return starts[s], starts[s + 1]
    return 0, nbr_n[s]


def owns(s, t, sorted_idx, sorted_body, body_inv_mass):
    """Whether slot s computes its contact with slot t (s has a list: dynamic)."""
    return static_body(body_inv_mass[sorted_body[t]]) or sorted_idx[s] < sorted_idx[t]  # noqa: F821


def pair_count(s, nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass):
    """How many of slot s's list entries it owns (at a rebuild)."""
    n = 0
    for e in range(nbr_n[s]):
        if owns(s, nbr[s, e], sorted_idx, sorted_body, body_inv_mass):
            n += 1
    return n


def pair_slots(s, base, nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx):
    """At a rebuild: the rows base, base + 1, ... of pair_f to slot s's owned
    entries, in list order. The other entries are left for pair_mirror."""
    p = base
    for e in range(nbr_n[s]):
        if owns(s, nbr[s, e], sorted_idx, sorted_body, body_inv_mass):
            pidx[s, e] = p
            p += 1


def pair_mirror(s, nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx):
    """At a rebuild, after every slot's pair_slots: each entry of slot s that its
    partner owns gets -(p + 1), p the row its partner writes."""
    for e in range(nbr_n[s]):
        t = nbr[s, e]
        if owns(s, t, sorted_idx, sorted_body, body_inv_mass):
            continue
        pidx[s, e] = UNPAIRED
        for f in range(nbr_n[t]):
            if nbr[t, f] == s:
                pidx[s, e] = -(pidx[t, f] + 1)
                break


def rows_to_pairs(s, h, n_spheres, nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass,
                  wall_mask, hist_partner, hist_spring, pair_f):
    """At a rebuild, with friction: the stretch of each pair slot s owns from its
    history row h (the State's form: partner code, stretch) into pair_f[p, 6:9],
    with pair_f[p, 9] = 1 + the parity it was touched at when it was remembered
    (touching at the last step that computed it) and 0 when not. The row then
    keeps only the walls within reach (wall_mask[s]), each at its column
    (wall_column): during the steps a pair's stretch is read and written at its
    pair index and a wall's at its column, with no search (with more walls than
    a mask names, the steps search the row: history_recall, history_store).
    Entries for partners out of the list are forgotten: they are out of reach,
    not touching."""
    for e in range(nbr_n[s]):
        p = pidx[s, e]
        if p < 0:
            continue
        slot, sx, sy, sz = history_recall(hist_partner, hist_spring, h,  # noqa: F821
                                          sorted_idx[nbr[s, e]] + 1)
        pair_f[p, 6] = sx
        pair_f[p, 7] = sy
        pair_f[p, 8] = sz
        pair_f[p, 9] = 1.0 + (hist_partner[h, slot] & 1) if slot >= 0 else 0.0
    walls = wall_mask[s]
    for c in range(hist_partner.shape[1]):
        code = (hist_partner[h, c] >> 1) - 1 - n_spheres     # the wall, or < 0: a sphere
        if hist_partner[h, c] != 0 and (code < 0 or (walls != -1 and (walls >> code) & 1 == 0)):
            hist_partner[h, c] = 0          # an empty slot holds no stretch: the
            hist_spring[h, c, 0] = 0.0      # State's rows do not depend on when
            hist_spring[h, c, 1] = 0.0      # the lists were rebuilt
            hist_spring[h, c, 2] = 0.0
    if walls == -1:
        return                              # too many walls for a mask: pair_forces searches
    # each marked wall's stretch to its column (wall_column): the j-th marked wall in
    # column j, so pair_forces reads and writes it with no search. Sorted, the k-th
    # entry's column is at least k: moved from the last, none overwrites another.
    cap = hist_partner.shape[1]
    for c in range(walls_to_front(hist_partner, hist_spring, h) - 1, -1, -1):
        j = wall_column(walls, (hist_partner[h, c] >> 1) - 1 - n_spheres)
        if j == c:
            continue
        if j < cap:
            hist_partner[h, j] = hist_partner[h, c]
            hist_spring[h, j, 0] = hist_spring[h, c, 0]
            hist_spring[h, j, 1] = hist_spring[h, c, 1]
            hist_spring[h, j, 2] = hist_spring[h, c, 2]
        hist_partner[h, c] = 0
        hist_spring[h, c, 0] = 0.0
        hist_spring[h, c, 1] = 0.0
        hist_spring[h, c, 2] = 0.0


def walls_to_front(hist_partner, hist_spring, h):
    """History row h, which holds walls only, sorted by wall into its first
    columns (an insertion sort; the codes grow with the wall index), the other
    columns emptied. Returns how many walls it holds."""
    cap = hist_partner.shape[1]
    nw = 0
    for c in range(cap):
        code = hist_partner[h, c]
        if code == 0:
            continue
        sx = hist_spring[h, c, 0]
        sy = hist_spring[h, c, 1]
        sz = hist_spring[h, c, 2]
        j = nw
        while j > 0 and hist_partner[h, j - 1] > code:
            hist_partner[h, j] = hist_partner[h, j - 1]
            hist_spring[h, j, 0] = hist_spring[h, j - 1, 0]
            hist_spring[h, j, 1] = hist_spring[h, j - 1, 1]
            hist_spring[h, j, 2] = hist_spring[h, j - 1, 2]
            j -= 1
        hist_partner[h, j] = code
        hist_spring[h, j, 0] = sx
        hist_spring[h, j, 1] = sy
        hist_spring[h, j, 2] = sz
        nw += 1
    for c in range(nw, cap):
        if hist_partner[h, c] != 0:     # (an empty column's stretch is already 0)
            hist_partner[h, c] = 0
            hist_spring[h, c, 0] = 0.0
            hist_spring[h, c, 1] = 0.0
            hist_spring[h, c, 2] = 0.0
    return nw


def wall_column(walls, w):
    """The column of a history row that wall w's stretch takes while stepping:
    how many walls below w the mask ``walls`` marks (wall_reach).

    Found by a search of the row every step before (history_recall, history_store,
    then a sweep for the walls not touched): 1.10x the step of a dense pile in a
    box without them (docs/performance.md). A sphere within reach of more
    walls than its row has columns (12: never in a box, where at most three
    meet) keeps no stretch for those beyond, touching or not; the search lost
    only the ones beyond the touching 12."""
    j = 0
    for b in range(w):
        if (walls >> b) & 1:
            j += 1
    return j


def pairs_to_rows(s, h, nbr, nbr_n, pidx, sorted_idx, hist_partner, hist_spring, pair_f):
    """The inverse of rows_to_pairs, before a re-sort and at the end of a call: each
    pair slot s owns that touched at the last step that computed it back into its
    history row h, with the parity of that step (a pair of two sleeping bodies
    keeps the one it had when they fell asleep, as a sleeper's row always did).
    The row comes out in one canonical order, whatever the steps did to it: the
    pairs in list order (their partners' index order), then the walls by wall
    index; so the State does not depend on when the lists were rebuilt or how
    the steps were split into calls. They always fit: pair_forces forgets the
    stretches of the pairs beyond the row's room at every step (the walls and
    the first pairs are kept; the guard here keeps the same ones)."""
    cap = hist_partner.shape[1]
    nw = walls_to_front(hist_partner, hist_spring, h)
    n_on = 0
    for e in range(nbr_n[s]):
        p = pidx[s, e]
        if p >= 0 and pair_f[p, 9] != 0.0:
            n_on += 1
    keep = min(n_on, cap - nw)
    for j in range(nw - 1, -1, -1):             # the walls after the pairs
        hist_partner[h, keep + j] = hist_partner[h, j]
        hist_spring[h, keep + j, 0] = hist_spring[h, j, 0]
        hist_spring[h, keep + j, 1] = hist_spring[h, j, 1]
        hist_spring[h, keep + j, 2] = hist_spring[h, j, 2]
    for c in range(keep + nw, cap):
        if hist_partner[h, c] != 0:
            hist_partner[h, c] = 0
            hist_spring[h, c, 0] = 0.0
            hist_spring[h, c, 1] = 0.0
            hist_spring[h, c, 2] = 0.0
    c = 0
    for e in range(nbr_n[s]):
        if c >= keep:
            break
        p = pidx[s, e]
        if p < 0 or pair_f[p, 9] == 0.0:
            continue
        hist_partner[h, c] = ((sorted_idx[nbr[s, e]] + 1) << 1) | (int(pair_f[p, 9]) - 1)
        hist_spring[h, c, 0] = pair_f[p, 6]
        hist_spring[h, c, 1] = pair_f[p, 7]
        hist_spring[h, c, 2] = pair_f[p, 8]
        c += 1
