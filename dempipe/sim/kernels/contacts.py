"""Stage 4 once per contact: each touching pair's force computed by one of its spheres.

Newton's third law, taken literally. physics.contact_force is antisymmetric in
IEEE arithmetic: seen from the other sphere, every input is negated (the line of
centres, the relative velocity, the tangential stretch) or the same (the
distance, the spins' sum, the material pair), and so the force comes out exactly
negated and the torque about each sphere's own centre exactly equal. So one
sphere of each listed pair, its *owner*, computes the contact, and the other
reads it back, negated: half the arithmetic, and the same force as if each
sphere computed its own. (One exception: two centres exactly coincident, where
physics.sphere_pair_force picks +z as the normal from either side, so each sphere
alone would push both the same way; computed once, the pair is pushed apart along
±z and momentum is kept.)

Owner: the sphere of lower index, or the dynamic one when the other is static
(a static sphere has no list). Ownership follows the sphere indices, not the
sorted slots, so it does not change when the lists are rebuilt.

Static friction: a contact's tangential stretch is kept once, for the pair.
Between ``step`` calls it lives in its owner's history row (the State's
contact_partner / contact_spring, the form a checkpoint keeps); at each rebuild
it moves into the pair's row of ``pair_f`` (rows_to_pairs), where the owner
reads and writes it with no search at every step, and back into the row
before the next re-sort and at the end of the call (pairs_to_rows). The rows
hold only the walls' contacts in between, each marked wall at a fixed column
(wall_column), also read and written with no search. A pair's stretch is forgotten at the
first step it does not touch (unless both bodies sleep: then nothing changes).
Before this, each sphere kept its own copy, searched for in its row every
step; the two copies were exact opposites except where they could drift apart
(one side's 12 slots full, or one side asleep while the other moved).

Two passes over the sorted slots per step, each writing only its own slot's
data (gather, deterministic):

1. ``pair_forces``: the owner computes each contact it owns (if either sphere
   is awake) into ``pair_f`` at its pair index, and each awake sphere its
   walls into ``wall_f``. Touching a sleeper from a moving body flags the
   sleeper to wake.
2. ``sphere_forces``: each awake dynamic sphere sums its list in its partners'
   index order (its own pairs as stored, its partners' negated), then its
   walls' sum.

Pair indices (``pidx[s, e]`` for list entry e of slot s) are set at each
rebuild (kernels/pairing.py): the owner's entry holds the row p of ``pair_f`` it writes; the other
side's holds -(p + 1). The CPU packs the rows (a prefix sum over the owners'
counts); CUDA gives every list entry its own row (s * cap + e), which needs no
scan. The passes do not care which. Walls: at each rebuild a sphere marks the
walls it can reach before the next (wall_reach); a step tests only those.

Written once, compiled for each target with that target's formulas and flags
(compile.specialize on the CPU, compile.compile_contacts on CUDA): FRICTION,
ROTATION, SLEEPING, WALLS as in kernels/cpu/stages.py, HIST_BY_SLOT: the history
rows are in sorted-slot order (the CPU, within a call) or in sphere order (CUDA),
PAIR_ROWS: the first pass walks each slot's own rows pair_start[s] ..
pair_start[s + 1] - 1, row p's entry of the packed list (partner slot, touch
mark) at ``pair_e[p]`` (the CPU's packed rows), rather than the whole list, skipping the entries the partner owns (CUDA), and
WALL_ROWS: while stepping, the stretch of the wall at column j of slot s's
history row lives in row wall_start[s] + j of ``wall_s`` (the CPU's packed wall
rows, filled and emptied at each rebuild by kernels/cpu/stages.py), rather than in the
history row itself (CUDA). The same numbers either way: packed, the few slots
that touch walls read consecutive rows instead of one scattered history row
each, which cost a fifth of the first pass on a pile in a box. And LIST_ROWS:
the second pass walks slot s's list entries as packed (partner slot, pair
index) rows list_start[s] .. list_start[s + 1] - 1 of ``list_e`` (the CPU's,
filled at each rebuild) rather than its list and pair-index rows (CUDA): the
same entries in the same order, 8 bytes an entry read instead of two 64-byte
rows a sphere.
"""

# The rebuild's bookkeeping (pair indices, walls in reach, histories into pair rows)
# lives in kernels/pairing.py; its names are imported from here too, and read by the
# passes below (compiled with this module's globals on CUDA).
from dempipe.sim.kernels.pairing import RIM_TIE, RING_TIE, UNPAIRED, entry_range

#: (reach / d)² within which a pair apart is tested for ``closing``: touching one
#: step ago, so that its dashpot's last impulse lands (laws.linear.normal_force).
#: 1% of d: at dt auto a contact's overlap (near 2% of d at the fastest impact)
#: changes by about a fifth of that per step; a contact that opens by more than 1%
#: of d in one step (a user's much softer stiffness, or dt) keeps the old end, its
#: last impulse missed. Kept small: in a dense pile every pair within the reach
#: costs a test (measured: 5% of d cost the 25 k pile 15% of its step).
CLOSE_REACH2 = 1.01 * 1.01


#: Sorted slots per call of pair_forces / sphere_forces in the CPU's parallel loops
#: (kernels/cpu/stages.py): small enough to balance two to a few dozen threads on piles of
#: a few thousand spheres, large enough that a call's cost is spread over many
#: spheres. Each sphere's result does not depend on it (gather: determinism is kept).
CONTACT_CHUNK = 64


def wall_gap(w, xi, yi, zi, wall_normal, wall_offset, wall_lo, wall_hi, wall_motion,
             motion_now):
    """Wall w at the sphere centred at (xi, yi, zi) [m]: (dist, inside): its signed
    distance from the wall's surface along the wall's normal [m], and whether it is
    inside the wall's box; a moving wall (wall_motion[w] = m ≥ 0) is tested in its
    anchor frame (motion_now[m]). The sphere touches the wall when inside, dist <
    its radius and dist > -wall_depth[w]."""
    lx = xi
    ly = yi
    lz = zi
    m = wall_motion[w]
    if m >= 0:
        lx, ly, lz = anchor_local(motion_now, m, xi, yi, zi)  # noqa: F821
    dist = wall_normal[w, 0] * lx + wall_normal[w, 1] * ly + wall_normal[w, 2] * lz \
        - wall_offset[w]
    inside = (lx >= wall_lo[w, 0] and lx <= wall_hi[w, 0] and ly >= wall_lo[w, 1]
              and ly <= wall_hi[w, 1] and lz >= wall_lo[w, 2] and lz <= wall_hi[w, 2])
    return dist, inside


def inscribed_wall(sphere_inscribed, body_q, i, bi, dist, radius, nx, ny, nz,
                   ux, uy, uz, wx, wy, wz):
    """Sphere i (of body bi, at signed distance ``dist`` [m] from a wall of normal n,
    pointing into the free side) meets the wall through its inscribed torus
    (spheres/inscribed.py; a ball when its circle's radius is 0): row i of
    ``sphere_inscribed`` holds, body frame, the vector from the sphere's centre to the
    torus's centre, the circle's axis, the direction from that centre to the tube's
    centre under the sphere [m, 1, 1], the circle's radius a and the tube's b, and the
    reach [m], turned by body_q[bi]. The tube's centre at the circle's point lowest towards the
    wall is the contact's centre: returns (overlap [m], that centre's distance from the
    wall [m], its offset from the sphere's centre (world) [m], its velocity u + w × that
    offset [m/s]), from u, the sphere centre's velocity relative to the wall, and w, its
    body's angular velocity.

    The overlap is the tube's, b − its centre's distance, but at most the reach more
    than the sphere's own, radius − dist: a round body's contact follows its surface
    across the dips between its spheres (a surface set's, REACH d; a lattice's
    terraces, deeper: spheres/inscribed.py lattice_tori), so a ball rolls as a ball and
    a cylinder on its side along its bottom line, while a torus far from the contact
    (on the body's other side) adds nothing. Without inscribed tori (an empty table:
    lattice sets with no round surface) it is the sphere's own contact, bit for bit.
    A rim is a ring whose tube is 0 (spheres/inscribed.py rims): the spheres along it
    each hold it, so where it lies flat on the wall each takes the point under itself
    (pairing.RIM_TIE), and on edge they all take its lowest point. A band (column 12:
    a rim swept H along its axis) takes the lowest point of its lower edge."""
    if sphere_inscribed.shape[0] == 0:          # every sphere is its own
        return radius - dist, dist, 0.0, 0.0, 0.0, ux, uy, uz
    ax = sphere_inscribed[i, 0]
    ay = sphere_inscribed[i, 1]
    az = sphere_inscribed[i, 2]
    ring = sphere_inscribed[i, 9]
    rho = sphere_inscribed[i, 10]
    if ax != 0.0 or ay != 0.0 or az != 0.0:
        qw = body_q[bi, 0]
        qx = body_q[bi, 1]
        qy = body_q[bi, 2]
        qz = body_q[bi, 3]
        ax, ay, az = quat_rotate(qw, qx, qy, qz, ax, ay, az)  # noqa: F821
        if ring > 0.0:
            # the circle's point lowest towards the wall: along -n's part across the
            # axis, or (the axis along n: every point as low) the one under the sphere
            tx, ty, tz = quat_rotate(qw, qx, qy, qz, sphere_inscribed[i, 3],  # noqa: F821
                                     sphere_inscribed[i, 4], sphere_inscribed[i, 5])
            sx, sy, sz = quat_rotate(qw, qx, qy, qz, sphere_inscribed[i, 6],  # noqa: F821
                                     sphere_inscribed[i, 7], sphere_inscribed[i, 8])
            nt = nx * tx + ny * ty + nz * tz
            tie = RING_TIE if rho > 0.0 else RIM_TIE
            px = nt * tx - nx + tie * sx
            py = nt * ty - ny + tie * sy
            pz = nt * tz - nz + tie * sz
            s = ring / sqrt(px * px + py * py + pz * pz)  # noqa: F821
            ax += s * px
            ay += s * py
            az += s * pz
            band = sphere_inscribed[i, 12]
            if band > 0.0:
                # a band's lower edge: its far one where the axis leans towards the
                # wall, the near one where away; across the tie (the band flat on the
                # wall, nt = 0) the point slides between them
                h = 0.5 - 0.5 * nt / RIM_TIE
                if h > 1.0:
                    h = 1.0
                elif h < 0.0:
                    h = 0.0
                ax += h * band * tx
                ay += h * band * ty
                az += h * band * tz
    da = dist + nx * ax + ny * ay + nz * az
    ov = rho - da
    gate = radius + sphere_inscribed[i, 11] - dist
    if gate < ov:
        ov = gate
    return (ov, da, ax, ay, az, ux + (wy * az - wz * ay), uy + (wz * ax - wx * az),
            uz + (wx * ay - wy * ax))


def pair_ended(dist2, d2, diameter, rx, ry, rz, dvx, dvy, dvz, dt, vc):
    """Whether a pair apart (``dist2`` ≥ ``d2``: the squared distance of its centres
    and the diameter's, [m²]) was still touching one step ago, by the law's
    ``closing`` from its relative position r and velocity dv (partner minus self,
    [m], [m/s]): the step in which normal_force applies the end of its dashpot.
    Only pairs within CLOSE_REACH2 and separating faster than ``vc`` [m/s] (the
    onset speed: slower, the law ends a contact at once) are asked (cheap tests
    first).
    The same bits from either side of the pair (r and dv only change sign), so
    pair_forces, which writes the force, and sphere_forces, which reads it,
    agree on every pair."""
    if dist2 >= d2 * CLOSE_REACH2:
        return False
    dvr = dvx * rx + dvy * ry + dvz * rz
    if dvr <= 0.0 or dvr * dvr <= vc * vc * dist2:
        return False                # only a pair separating faster than vc
    dist = sqrt(dist2)  # noqa: F821
    return closing(diameter - dist, dvr / dist, dt)  # noqa: F821 (the law's)


def engaged(s, i, slot_touch, sphere_engaged):
    """Whether the contact passes visit slot s (sphere i) of their work this step (the
    CPU, LIST_ROWS): it touches something (slot_touch: body_patches' tests, pairs and
    walls), or touched anything at its last visit (sphere_engaged: its force, its
    pairs' and walls' stretches are to be cleared).

    Any other slot's visit would write what it holds already: pass 1 finds each pair
    and wall apart and has no stretch to forget (none was kept: it touched nothing at
    its last visit), and writes zero wall forces that pass 2 reads only where pass 1
    visited too; pass 2 writes the zero force it wrote at its last visit (or
    stage_busy at the rebuild). So the State is the same bit for bit, and a piece
    standing on a floor costs what its spheres on the floor cost, not every sphere a
    wall is in reach of (a chess piece's foot ring 0.02 d above the floor:
    docs/performance.md, "Surface sphere sets"). The first step of each ``step`` call
    visits every slot of its work (run_steps: the State may be another than the last
    call's, whose stretches the scratch knows nothing of)."""
    return slot_touch[s] != 0 or sphere_engaged[i] != 0


def pair_forces(k0, k1, work, listed, cm, cs, motion_now, parity):
    """Stage 4, first pass, for the sorted slots work[k0 .. k1-1] when ``listed`` (the
    CPU: a block of its parallel loop over the slots with work), else slots k0 ..
    k1-1 (``work`` unread; CUDA: one). For each slot s:

    - each touching contact s owns, when either sphere is awake: the force on s
      (eq. 11-14, physics.sphere_pair_force) and its torque about s's centre into
      pair_f[p] (the torque only with friction and rotation, and 0 for a
      frictionless contact: kernels/cpu/stages.py TORQUE_NOTE);
    - when s is awake and dynamic, the walls marked in wall_mask[s] (wall_reach)
      that it touches, summed in wall order into wall_f[s] = (force, torque,
      largest overlap [m]; 0 when none touches);
    - with friction, each contact's stretch: a pair's in pair_f[p, 6:9] (kept
      while it touches, forgotten when it does not), a wall's at its column of
      s's history row (wall_column; touched at ``parity``; when s is awake, the
      row's walls not touched this step are forgotten).

    A moving body (rest count 0) touching a sleeping one flags it to wake.
    A carried body that moves this step (rest count -1: kernels' stage_driven) and
    a moving wall (wall_motion[w] = m ≥ 0, its anchor in motion_now[m]: position,
    orientation, velocity, angular velocity, moving) flag every body they touch
    (body_wake): a sleeper wakes, an awake body's rest count stays 0. A moving
    wall is given in its anchor frame; its surface velocity V + W × (y − P) at the
    contact point y enters the dashpot and friction.
    pair_start, pair_e: slot s's rows and each row's entry of list_e, whose partner
    slot it reads, and whose mark (patches.body_patches, this step) says whether
    the pair touches (PAIR_ROWS, with LIST_ROWS);
    wall_start, wall_s: its walls' packed rows, (stretch [m], 1 + parity or 0)
    (WALL_ROWS); unread otherwise.

    cm: layout.ContactModel, cs: layout.ContactScratch (unpacked below under the
    names the loop reads); motion_now: control.Drive's (M x 14); parity: the
    step's (step & 1), which marks the histories touched this step."""
    (diameter, dt, onset_speed, body_inv_mass, body_material, pair_k, pair_damp, pair_mu,
     kt_ratio, ks_ratio, friction, sleep_steps, wall_normal, wall_offset, wall_lo, wall_hi,
     wall_depth, wall_material, wall_motion, rolling, pair_rolling, body_inv_radius,
     sphere_inscribed) = cm
    (nbr, nbr_n, pidx, pair_start, pair_e, wall_start, wall_s, _list_start, list_e,
     sorted_idx, sorted_x, sorted_v, sorted_body, body_w, body_rest, body_wake, wall_mask,
     hist_partner, hist_spring, pair_f, wall_f, _sphere_f, _sphere_t, _sphere_tr,
     _sphere_overlap, body_patch, body_q, slot_touch, sphere_engaged) = cs
    d2 = diameter * diameter
    radius = 0.5 * diameter
    n_walls = wall_normal.shape[0]
    n_bodies = body_inv_mass.shape[0]
    n_spheres = sorted_idx.shape[0]
    cap = hist_partner.shape[1]
    for k in range(k0, k1):
        s = work[k] if listed else k
        bi = sorted_body[s]
        imi = body_inv_mass[bi]
        if static_body(imi):  # noqa: F821
            continue
        n_wall_on = -1                      # walls the row remembers (-1: count them)
        h = s if HIST_BY_SLOT else sorted_idx[s]  # noqa: F821 (the target's: compile_contacts)
        asleep_i = SLEEPING and sleep_steps > 0 and body_rest[bi] >= sleep_steps  # noqa: F821
        if LIST_ROWS and not engaged(s, sorted_idx[s], slot_touch,  # noqa: F821
                                     sphere_engaged) and not (
                asleep_i and wall_mask[s] != 0 and motion_now.shape[0] > 0):
            continue                        # (a sleeper a moving wall may wake: visited)
        xi = sorted_x[s, 0]
        yi = sorted_x[s, 1]
        zi = sorted_x[s, 2]
        vxi = sorted_v[s, 0]
        vyi = sorted_v[s, 1]
        vzi = sorted_v[s, 2]
        mi = body_material[bi]
        wxi = 0.0
        wyi = 0.0
        wzi = 0.0
        if ROTATION:  # noqa: F821
            wxi = body_w[bi, 0]
            wyi = body_w[bi, 1]
            wzi = body_w[bi, 2]
        kept = 0                            # pairs that remember a stretch after this step
        e0, e1 = entry_range(PAIR_ROWS, pair_start, nbr_n, s)  # noqa: F821
        for e in range(e0, e1):
            on = True                       # PAIR_ROWS: the mark says
            if PAIR_ROWS:  # noqa: F821
                p = e
                t = list_e[pair_e[e], 0]
                on = list_e[pair_e[e], 2] != 0
            else:
                p = pidx[s, e]
                if p < 0:
                    continue                # the partner's to compute
                t = nbr[s, e]
            bj = sorted_body[t]
            imj = body_inv_mass[bj]
            if SLEEPING and sleep_steps > 0:  # noqa: F821
                if asleep_i and body_rest[bj] >= 0 and (  # (-1: a carried body moving)
                        static_body(imj) or body_rest[bj] >= sleep_steps):  # noqa: F821
                    if FRICTION and friction and pair_f[p, 9] != 0.0:  # noqa: F821
                        kept += 1
                    continue                # neither feels it: both keep their state
            if not on:                      # apart (body_patches' test, this step)
                if FRICTION and friction:  # noqa: F821
                    pair_f[p, 9] = 0.0      # not touching: the contact ends, its stretch goes
                continue
            rx = sorted_x[t, 0] - xi
            ry = sorted_x[t, 1] - yi
            rz = sorted_x[t, 2] - zi
            dist2 = rx * rx + ry * ry + rz * rz
            if not PAIR_ROWS and dist2 >= d2 and not pair_ended(  # noqa: F821
                    dist2, d2, diameter, rx, ry, rz, sorted_v[t, 0] - vxi,
                    sorted_v[t, 1] - vyi, sorted_v[t, 2] - vzi, dt, onset_speed):
                if FRICTION and friction:  # noqa: F821
                    pair_f[p, 9] = 0.0
                continue
            if SLEEPING and sleep_steps > 0:  # noqa: F821
                # a moving body touches a sleeper (the same value from any thread)
                if body_rest[bi] == 0 and body_rest[bj] >= sleep_steps:
                    body_wake[bj] = 1
                if not static_body(imj) and body_rest[bj] == 0 and asleep_i:  # noqa: F821
                    body_wake[bi] = 1
                if body_rest[bj] < 0:
                    body_wake[bi] = 1       # carried and moving: wakes, keeps awake
            mj = body_material[bj]
            dist = sqrt(dist2)  # noqa: F821
            k, eta, kt, ks = contact_coefficients(  # noqa: F821 (the law's)
                pair_k[mi, mj], pair_damp, mi, mj, imi + imj, kt_ratio, ks_ratio, dt,
                diameter - dist)
            share = pair_share(body_patch, body_inv_mass, bi, bj)  # noqa: F821 (its patch's)
            k *= share
            eta *= share
            kt *= share
            ks *= share
            if FRICTION and friction and pair_f[p, 9] != 0.0:  # noqa: F821 (touching last step)
                mu = pair_mu[mi, mj]
                sx = pair_f[p, 6]
                sy = pair_f[p, 7]
                sz = pair_f[p, 8]
            elif FRICTION and friction:  # noqa: F821 (a new contact)
                mu = pair_mu[mi, mj]
                sx = 0.0
                sy = 0.0
                sz = 0.0
            else:
                mu = 0.0
                sx = 0.0
                sy = 0.0
                sz = 0.0
            wsx = wxi
            wsy = wyi
            wsz = wzi
            if ROTATION:  # noqa: F821
                wsx += body_w[bj, 0]
                wsy += body_w[bj, 1]
                wsz += body_w[bj, 2]
            (pfx, pfy, pfz, ptx, pty, ptz, sx, sy, sz) = sphere_pair_force(  # noqa: F821
                rx, ry, rz, dist, diameter,
                sorted_v[t, 0] - vxi, sorted_v[t, 1] - vyi, sorted_v[t, 2] - vzi,
                wsx, wsy, wsz,
                k, eta, kt, ks, mu, sx, sy, sz, dt, onset_speed)
            if FRICTION and friction:  # noqa: F821
                pair_f[p, 6] = sx
                pair_f[p, 7] = sy
                pair_f[p, 8] = sz
                pair_f[p, 9] = 1.0 + parity
                kept += 1
            pair_f[p, 0] = pfx
            pair_f[p, 1] = pfy
            pair_f[p, 2] = pfz
            if ROTATION and FRICTION:  # noqa: F821
                if mu > 0.0:
                    pair_f[p, 3] = ptx
                    pair_f[p, 4] = pty
                    pair_f[p, 5] = ptz
                else:
                    pair_f[p, 3] = 0.0
                    pair_f[p, 4] = 0.0
                    pair_f[p, 5] = 0.0
        walls = wall_mask[s]
        # the walls marked at the rebuild; a sleeper feels nothing, its row stays as it was
        if WALLS and walls != 0 and asleep_i and motion_now.shape[0] > 0:  # noqa: F821
            for w in range(n_walls):        # ... but a moving wall wakes it
                m = wall_motion[w]
                if m < 0 or motion_now[m, 13] == 0.0 or (
                        walls != -1 and (walls >> w) & 1 == 0):
                    continue
                dist, inside = wall_gap(w, xi, yi, zi, wall_normal, wall_offset,  # noqa: F821
                                        wall_lo, wall_hi, wall_motion, motion_now)
                if inside and dist < radius and dist > -wall_depth[w]:
                    body_wake[bi] = 1
        if WALLS and walls != 0 and not asleep_i:  # noqa: F821
            fx = 0.0
            fy = 0.0
            fz = 0.0
            tx = 0.0
            ty = 0.0
            tz = 0.0
            max_ov = 0.0
            qx = 0.0                        # the walls' rolling torques
            qy = 0.0
            qz = 0.0
            col = -1                        # the wall's column in s's history row
            n_wall_on = 0
            qw = wall_start[s] if WALL_ROWS else 0  # noqa: F821 (its packed rows)
            for w in range(n_walls):
                if walls != -1:
                    if (walls >> w) & 1 == 0:
                        continue
                    col += 1                # wall_column(walls, w), counted as we go
                nx = wall_normal[w, 0]
                ny = wall_normal[w, 1]
                nz = wall_normal[w, 2]
                m = wall_motion[w]
                dist, inside = wall_gap(w, xi, yi, zi, wall_normal, wall_offset,  # noqa: F821
                                        wall_lo, wall_hi, wall_motion, motion_now)
                uxi = vxi                   # the sphere's velocity relative to the wall
                uyi = vyi
                uzi = vzi
                Wx = 0.0                    # and the wall's spin
                Wy = 0.0
                Wz = 0.0
                if m >= 0 and inside:       # a moving wall: its surface's velocity
                    nx, ny, nz, sux, suy, suz = anchor_surface(  # noqa: F821
                        motion_now, m, nx, ny, nz, xi, yi, zi, dist, dt)
                    uxi -= sux
                    uyi -= suy
                    uzi -= suz
                    Wx = motion_now[m, 10]
                    Wy = motion_now[m, 11]
                    Wz = motion_now[m, 12]
                if INSCRIBED:  # noqa: F821 (the target's: a model with inscribed tori)
                    ov, da, ax, ay, az, uxi, uyi, uzi = inscribed_wall(
                        sphere_inscribed, body_q, sorted_idx[s], bi, dist, radius,
                        nx, ny, nz, uxi, uyi, uzi, wxi, wyi, wzi)
                else:
                    ov = radius - dist
                    da = dist
                    ax = 0.0
                    ay = 0.0
                    az = 0.0
                away = uxi * nx + uyi * ny + uzi * nz   # its speed away from the wall [m/s]
                if (not inside or dist <= -wall_depth[w]
                        or (ov <= 0.0 and not (away > onset_speed and closing(  # noqa: F821
                            ov, away, dt)))):    # (touching a step ago: pair_ended)
                    if FRICTION and friction and 0 <= col < cap:  # noqa: F821
                        if WALL_ROWS:  # noqa: F821
                            if wall_s[qw + col, 3] != 0.0:
                                wall_s[qw + col, 0] = 0.0   # not touching: forgotten
                                wall_s[qw + col, 1] = 0.0
                                wall_s[qw + col, 2] = 0.0
                                wall_s[qw + col, 3] = 0.0
                        elif hist_partner[h, col] != 0:
                            hist_partner[h, col] = 0        # not touching: forgotten
                            hist_spring[h, col, 0] = 0.0
                            hist_spring[h, col, 1] = 0.0
                            hist_spring[h, col, 2] = 0.0
                    continue
                mj = wall_material[w]
                k, eta, kt, ks = contact_coefficients(  # noqa: F821 (the law's; a wall adds
                    pair_k[mi, mj], pair_damp, mi, mj, imi, kt_ratio, ks_ratio, dt,  # no 1/m)
                    ov)
                share = patch_share(body_patch, bi, n_bodies + w)  # noqa: F821
                k *= share
                eta *= share
                kt *= share
                ks *= share
                if FRICTION and friction:  # noqa: F821
                    mu = pair_mu[mi, mj]
                    code = n_spheres + w + 1
                    if walls == -1:
                        slot, sx, sy, sz = history_recall(hist_partner, hist_spring,  # noqa: F821
                                                          h, code)
                    elif WALL_ROWS and col < cap and wall_s[qw + col, 3] != 0.0:  # noqa: F821
                        slot = col
                        sx = wall_s[qw + col, 0]
                        sy = wall_s[qw + col, 1]
                        sz = wall_s[qw + col, 2]
                    elif not WALL_ROWS and col < cap and hist_partner[h, col] != 0:  # noqa: F821
                        slot = col
                        sx = hist_spring[h, col, 0]
                        sy = hist_spring[h, col, 1]
                        sz = hist_spring[h, col, 2]
                    else:
                        slot = -1
                        sx = 0.0
                        sy = 0.0
                        sz = 0.0
                else:
                    mu = 0.0
                    sx = 0.0
                    sy = 0.0
                    sz = 0.0
                if SLEEPING and m >= 0 and motion_now[m, 13] != 0.0:  # noqa: F821
                    body_wake[bi] = 1       # never asleep on a moving surface
                (pfx, pfy, pfz, ptx, pty, ptz, sx, sy, sz) = sphere_wall_force(  # noqa: F821
                    -nx, -ny, -nz, ov, ov + da, uxi, uyi, uzi, wxi, wyi, wzi,
                    Wx, Wy, Wz, k, eta, kt, ks, mu, sx, sy, sz, dt, onset_speed)
                if INSCRIBED and ROTATION:  # noqa: F821 (about the sphere's centre: a away)
                    ptx += ay * pfz - az * pfy
                    pty += az * pfx - ax * pfz
                    ptz += ax * pfy - ay * pfx
                if FRICTION and friction:  # noqa: F821
                    if walls == -1:
                        history_store(hist_partner, hist_spring, h, slot, code,  # noqa: F821
                                      parity, sx, sy, sz)
                    elif col < cap:
                        if WALL_ROWS:  # noqa: F821
                            wall_s[qw + col, 0] = sx
                            wall_s[qw + col, 1] = sy
                            wall_s[qw + col, 2] = sz
                            wall_s[qw + col, 3] = 1.0 + parity
                        else:
                            hist_partner[h, col] = (code << 1) | parity
                            hist_spring[h, col, 0] = sx
                            hist_spring[h, col, 1] = sy
                            hist_spring[h, col, 2] = sz
                        n_wall_on += 1
                fx += pfx
                fy += pfy
                fz += pfz
                if ROTATION and ((FRICTION and mu > 0.0)  # noqa: F821 (TORQUE_NOTE)
                                 or ax != 0.0 or ay != 0.0 or az != 0.0):
                    tx += ptx
                    ty += pty
                    tz += ptz
                if ROTATION and FRICTION and rolling and pair_rolling[mi, mj] > 0.0:  # noqa: F821
                    rwx = wxi - Wx              # the spin relative to the wall's
                    rwy = wyi - Wy
                    rwz = wzi - Wz
                    rtx, rty, rtz = rolling_torque(  # noqa: F821 (a wall rolls as flat)
                        rwx, rwy, rwz, nx, ny, nz, 1.0, pfx * nx + pfy * ny + pfz * nz,
                        pair_rolling[mi, mj], body_inv_radius[bi], onset_speed)
                    qx += rtx
                    qy += rty
                    qz += rtz
                if ov > max_ov:
                    max_ov = ov
            wall_f[s, 0] = fx
            wall_f[s, 1] = fy
            wall_f[s, 2] = fz
            wall_f[s, 3] = tx
            wall_f[s, 4] = ty
            wall_f[s, 5] = tz
            wall_f[s, 6] = max_ov
            wall_f[s, 7] = qx
            wall_f[s, 8] = qy
            wall_f[s, 9] = qz
            if FRICTION and friction and walls == -1:  # noqa: F821 (forget the walls not
                n_wall_on = -1                              # touched at this parity)
                for c in range(hist_partner.shape[1]):
                    code = hist_partner[h, c]
                    if code != 0 and (code & 1) != parity:
                        hist_partner[h, c] = 0
                        hist_spring[h, c, 0] = 0.0
                        hist_spring[h, c, 1] = 0.0
                        hist_spring[h, c, 2] = 0.0
        if FRICTION and friction and kept > 0:  # noqa: F821
            # Between calls s's row must hold all it remembers (pairs_to_rows): beyond its
            # room, the pairs last in list order forget their stretch, as a full row
            # drops a contact (history_store). So the State does not depend on how
            # the steps were split into calls.
            room = cap
            if walls != 0 and n_wall_on >= 0:
                room -= n_wall_on           # the walls it remembers, counted above
            elif WALL_ROWS and walls != -1:  # noqa: F821 (asleep: the walls it remembers)
                for q in range(wall_start[s], wall_start[s + 1]):
                    if wall_s[q, 3] != 0.0:
                        room -= 1
            elif walls != 0:                # the row holds walls only while stepping
                for c in range(cap):
                    if hist_partner[h, c] != 0:
                        room -= 1
            if kept <= room:
                continue
            for e in range(e0, e1):
                p = e if PAIR_ROWS else pidx[s, e]  # noqa: F821
                if p >= 0 and pair_f[p, 9] != 0.0:
                    if room > 0:
                        room -= 1
                    else:
                        pair_f[p, 9] = 0.0


def sphere_forces(k0, k1, work, listed, cm, cs):
    """Stage 4, second pass, for the sorted slots work[k0 .. k1-1] or k0 .. k1-1, as
    pair_forces; for each slot s (sphere i = sorted_idx[s]): the sum of the forces
    on it from its touching partners in its list's order (its partners' index
    order; the pairs its partners own read back negated, their torque as it is),
    then its walls' sum (wall_f), into sphere_f[i], sphere_t[i] (about its centre)
    and sphere_overlap[i] (the largest this step, [m], kept if larger). Static and
    sleeping spheres feel nothing. A pair apart that pair_ended finds touching a
    step ago is summed too (its dashpot's last impulse): the same test, so from
    either side, as the owner's pair_forces made. (A slot with no neighbour and no
    wall writes zeros: the CPU writes them once per rebuild and leaves it out of
    ``work``.) cm, cs: as pair_forces takes them."""
    diameter = cm.diameter
    dt = cm.dt
    onset_speed = cm.onset_speed
    body_inv_mass = cm.body_inv_mass
    sleep_steps = cm.sleep_steps
    rolling = cm.rolling
    body_material = cm.body_material
    pair_rolling = cm.pair_rolling
    body_inv_radius = cm.body_inv_radius
    (nbr, nbr_n, pidx, _pair_start, _pair_e, _wall_start, _wall_s, list_start, list_e,
     sorted_idx, sorted_x, sorted_v, sorted_body, body_w, body_rest, _body_wake, wall_mask,
     _hist_partner, _hist_spring, pair_f, wall_f, sphere_f, sphere_t, sphere_tr,
     sphere_overlap, _body_patch, _body_q, slot_touch, sphere_engaged) = cs
    d2 = diameter * diameter
    for k in range(k0, k1):
        s = work[k] if listed else k
        i = sorted_idx[s]
        bi = sorted_body[s]
        if LIST_ROWS:  # noqa: F821
            if not engaged(s, i, slot_touch, sphere_engaged):  # noqa: F821
                continue
            sphere_engaged[i] = slot_touch[s]
        if static_body(body_inv_mass[bi]) or (SLEEPING and sleep_steps > 0  # noqa: F821
                                              and body_rest[bi] >= sleep_steps):
            # static, or asleep: feels nothing (but is found by its moving neighbours)
            sphere_f[i, 0] = 0.0
            sphere_f[i, 1] = 0.0
            sphere_f[i, 2] = 0.0
            sphere_t[i, 0] = 0.0
            sphere_t[i, 1] = 0.0
            sphere_t[i, 2] = 0.0
            if ROTATION and FRICTION and rolling:  # noqa: F821
                sphere_tr[i, 0] = 0.0
                sphere_tr[i, 1] = 0.0
                sphere_tr[i, 2] = 0.0
            continue
        xi = sorted_x[s, 0]
        yi = sorted_x[s, 1]
        zi = sorted_x[s, 2]
        vxi = sorted_v[s, 0]
        vyi = sorted_v[s, 1]
        vzi = sorted_v[s, 2]
        mi = 0                              # this sphere's side of rolling resistance
        rwx = 0.0
        rwy = 0.0
        rwz = 0.0
        inv_ri = 0.0
        if ROTATION and FRICTION and rolling:  # noqa: F821
            mi = body_material[bi]
            rwx = body_w[bi, 0]
            rwy = body_w[bi, 1]
            rwz = body_w[bi, 2]
            inv_ri = body_inv_radius[bi]
        qx = 0.0                            # its rolling torques (sphere_tr)
        qy = 0.0
        qz = 0.0
        fx = 0.0
        fy = 0.0
        fz = 0.0
        tx = 0.0
        ty = 0.0
        tz = 0.0
        near2 = d2
        e0, e1 = entry_range(LIST_ROWS, list_start, nbr_n, s)  # noqa: F821
        for e in range(e0, e1):
            if LIST_ROWS and list_e[e, 2] == 0:  # noqa: F821 (body_patches' test, this step)
                continue
            t = list_e[e, 0] if LIST_ROWS else nbr[s, e]  # noqa: F821
            rx = sorted_x[t, 0] - xi
            ry = sorted_x[t, 1] - yi
            rz = sorted_x[t, 2] - zi
            dist2 = rx * rx + ry * ry + rz * rz
            # touching, or in the step after (the CPU: body_patches' mark, above)
            if not LIST_ROWS and dist2 >= d2 and not pair_ended(  # noqa: F821
                    dist2, d2, diameter, rx, ry, rz, sorted_v[t, 0] - vxi,
                    sorted_v[t, 1] - vyi, sorted_v[t, 2] - vzi, dt, onset_speed):
                continue
            p = list_e[e, 1] if LIST_ROWS else pidx[s, e]  # noqa: F821
            if p >= 0:
                pfx = pair_f[p, 0]
                pfy = pair_f[p, 1]
                pfz = pair_f[p, 2]
            elif p != UNPAIRED:  # noqa: F821
                p = -(p + 1)
                pfx = -pair_f[p, 0]         # (a - b is a + (-b) exactly: the same sums)
                pfy = -pair_f[p, 1]
                pfz = -pair_f[p, 2]
            else:
                continue
            fx += pfx
            fy += pfy
            fz += pfz
            if ROTATION and FRICTION:  # noqa: F821
                tx += pair_f[p, 3]
                ty += pair_f[p, 4]
                tz += pair_f[p, 5]
                if rolling:
                    # computed from each side, not stored: every input is the same or
                    # negated from the partner's, so its torque is exactly the negation
                    bj = sorted_body[t]
                    mu_r = pair_rolling[mi, body_material[bj]]
                    if mu_r > 0.0:
                        nx = rx                 # the line of centres, as it is; coincident
                        ny = ry                 # centres: +z from either side (as
                        nz = rz                 # physics.sphere_pair_force)
                        n2 = dist2
                        if dist2 == 0.0:
                            nz = 1.0
                            n2 = 1.0
                        rtx, rty, rtz = rolling_torque(  # noqa: F821
                            rwx - body_w[bj, 0], rwy - body_w[bj, 1], rwz - body_w[bj, 2],
                            nx, ny, nz, n2, pfx * nx + pfy * ny + pfz * nz, mu_r,
                            inv_ri + body_inv_radius[bj], onset_speed)
                        qx += rtx
                        qy += rty
                        qz += rtz
            if dist2 < near2:
                near2 = dist2
        max_ov = 0.0
        if near2 < d2:
            max_ov = diameter - sqrt(near2)  # noqa: F821 (sqrt is monotone: the largest)
        if WALLS and wall_mask[s] != 0:  # noqa: F821
            fx += wall_f[s, 0]
            fy += wall_f[s, 1]
            fz += wall_f[s, 2]
            tx += wall_f[s, 3]
            ty += wall_f[s, 4]
            tz += wall_f[s, 5]
            if wall_f[s, 6] > max_ov:
                max_ov = wall_f[s, 6]
            if ROTATION and FRICTION and rolling:  # noqa: F821
                qx += wall_f[s, 7]
                qy += wall_f[s, 8]
                qz += wall_f[s, 9]
        sphere_f[i, 0] = fx
        sphere_f[i, 1] = fy
        sphere_f[i, 2] = fz
        if ROTATION and (FRICTION or INSCRIBED):  # noqa: F821 (a torus's arm: a × F)
            sphere_t[i, 0] = tx
            sphere_t[i, 1] = ty
            sphere_t[i, 2] = tz
        if ROTATION and FRICTION:  # noqa: F821
            if rolling:
                sphere_tr[i, 0] = qx
                sphere_tr[i, 1] = qy
                sphere_tr[i, 2] = qz
        if max_ov > sphere_overlap[i]:
            sphere_overlap[i] = max_ov
