"""Contact patches: the sphere pairs between two bodies act as ONE contact.

A body touches a partner (another body, a static collider or a wall) on as many
sphere pairs as the geometry gives: one at a corner, a line of them on an edge,
n ≈ (face width / d)² on a face landing flat. Were each pair a spring-dashpot
with the material's constants, the face would be n springs in parallel: a
stiffness n k and, the dashpots growing with √(k m), a damping ratio √n ζ. A
box would land overdamped (no bounce at e = 0.5 from n ≈ 16 up) and its
frequency, hence the step, would grow with the resolution.

So each pair of a patch takes the share 1/n_eff of the patch's spring, dashpot,
tangential dashpot and tangential spring (physics.contact_force is linear in the
four together, and the tangential stretch it keeps is the same at any share),
where n_eff is the patch's participation ratio

    n_eff = (Σ δ_j)² / Σ δ_j²      over the patch's pairs, δ_j their overlaps [m]:

n for n equal overlaps (a face landing flat: the patch has the material's
stiffness and damping ratio, and bounces with its restitution, whatever n and
the resolution), 1 for one pair, and in between for a tilted face, whose force
K Σδ²/Σδ lies between K × the mean and K × the largest overlap. A pair that
begins at δ = 0 changes neither sum: the shares, hence the forces, are
continuous as pairs come and go (a count would halve a patch's force the step a
second pair touched, and jolt a resting face at every flicker). A pair in the
step after it ends counts with its overlap of the step before (δ + u_n dt), so
a face that leaves together shares its last dashpot impulse as it shared the
contact. docs/physics.md, "Contact patches", has the equations and the limits.

One pass before the contact passes, ``body_patches``, per body (gather, no
atomics; float sums in one fixed order, the body's spheres in index order and
each sphere's pairs in its list's order, then its walls: the same bits on either
target and for any thread count): the sums Σδ, Σδ² of the body's contacts this
step per partner, by the very tests pair_forces makes (a pair touching or in the
step after it ends, a wall likewise; pairs the sleeping rule skips are not
counted), into its row of ``body_patch``. pair_forces then scales each contact
by ``patch_share``, from its owner's body (a body owns every pair with a body of
higher index, and with a static partner), so a pair between two bodies takes
the share of the sums its owner made.

``body_patch[b]`` (BODY_PATCHES + 1, 3) float64: (partner code + 1, Σδ, Σδ²) per
partner (0: empty), then (overflowed, Σδ, Σδ² over every partner). A partner
code is the body's index, or the number of bodies + the wall's index for a
wall. A body with more partners than its row holds is marked overflowed: a pair
it owns with a dynamic body whose row is whole takes that body's share for it
(pair_share: the same patch, summed from the other side); its other contacts take
the share of all its contacts taken as one patch (softer than their own patch,
never stiffer, and the same whatever the order the row was filled in).
"""

# body_patches calls pair_ended, wall_gap and entry_range (and the law's closing): each
# target compiles it with its own compiled versions of them (compile.compile_contacts,
# cpu/stages.py kernels()), which replace these names.
from dempipe.sim.kernels.contacts import pair_ended, wall_gap  # noqa: F401
from dempipe.sim.kernels.pairing import entry_range  # noqa: F401

#: Partners a body's row holds: a one-sphere ball in a dense pile touches up to 12
#: others and three walls in a corner; a piece of a pile, about 6-10 bodies.
BODY_PATCHES = 16


def patch_add(row, slots, code, s1, s2):
    """Add a run of contacts with partner ``code``, their Σδ = ``s1`` [m] and Σδ² =
    ``s2`` [m²], to ``row`` (``slots`` rows of (code + 1, Σδ, Σδ²), then (overflowed,
    Σδ, Σδ²) of all); a partner with no room marks the row overflowed."""
    row[slots, 1] += s1
    row[slots, 2] += s2
    for c in range(slots):
        if row[c, 0] == code + 1:
            row[c, 1] += s1
            row[c, 2] += s2
            return
        if row[c, 0] == 0.0:
            row[c, 0] = code + 1
            row[c, 1] = s1
            row[c, 2] = s2
            return
    row[slots, 0] = 1.0


def body_patches(b, k0, k1, work, listed, cm, cs, motion_now, body_sphere_start, slot_of):
    """The pass for body b: the sums (Σδ [m], Σδ² [m²]) of its contacts this step per
    partner, by pair_forces' tests, into body_patch[b] (a static body: left as it
    is, never read). Every body, every step: a sleeper's sums must hold for the
    pairs it computes with a moving partner (the CPU target's stage_patches leaves
    out only bodies whose row would be empty: quiet among quiet partners, or
    nothing in reach). Over the body's spheres in index order: its slots
    work[k0 .. k1-1] when ``listed`` (the CPU: those of its slots with a neighbour
    or a wall, stage_busy's, in slot order, which is the body's sphere order:
    stage_grid_sort), else every one (``work`` unread; CUDA).
    cm, cs, motion_now: as pair_forces; body_sphere_start: the body's spheres;
    slot_of: each sphere's sorted slot.

    With LIST_ROWS (the CPU) each list entry tested is marked in list_e[e, 2]: 1 when
    the pair touches or is in the step after it ends, else 0 (pairing.LIST_COLS). The
    test is pair_forces' and sphere_forces' own, on the same positions from the same
    side, so their passes over the same slots read the mark instead of the partner's
    position. An entry the sleeping rule skips keeps its old mark: its slot is
    asleep, sphere_forces does not walk a sleeping slot's list, and pair_forces
    applies the same rule before it reads the mark. And each slot's slot_touch[s] is
    1 when any of its pairs or walls is so counted, else 0 (contacts.engaged)."""
    diameter = cm.diameter
    dt = cm.dt
    onset_speed = cm.onset_speed
    body_inv_mass = cm.body_inv_mass
    sleep_steps = cm.sleep_steps
    wall_normal = cm.wall_normal
    wall_offset = cm.wall_offset
    wall_lo = cm.wall_lo
    wall_hi = cm.wall_hi
    wall_depth = cm.wall_depth
    wall_motion = cm.wall_motion
    nbr = cs.nbr
    nbr_n = cs.nbr_n
    list_start = cs.list_start
    list_e = cs.list_e
    sorted_x = cs.sorted_x
    sorted_v = cs.sorted_v
    sorted_body = cs.sorted_body
    body_rest = cs.body_rest
    wall_mask = cs.wall_mask
    body_patch = cs.body_patch
    body_q = cs.body_q
    body_w = cs.body_w
    sphere_inscribed = cm.sphere_inscribed
    sorted_idx = cs.sorted_idx
    slot_touch = cs.slot_touch
    if static_body(body_inv_mass[b]):  # noqa: F821
        return
    row = body_patch[b]
    slots = body_patch.shape[1] - 1
    for c in range(slots + 1):
        row[c, 0] = 0.0
        row[c, 1] = 0.0
        row[c, 2] = 0.0
    d2 = diameter * diameter
    radius = 0.5 * diameter
    n_walls = wall_normal.shape[0]
    n_bodies = body_inv_mass.shape[0]
    asleep = SLEEPING and sleep_steps > 0 and body_rest[b] >= sleep_steps  # noqa: F821
    i0 = body_sphere_start[b]
    for j in range(k1 - k0 if listed else body_sphere_start[b + 1] - i0):
        s = work[k0 + j] if listed else slot_of[i0 + j]
        xi = sorted_x[s, 0]
        yi = sorted_x[s, 1]
        zi = sorted_x[s, 2]
        vxi = sorted_v[s, 0]
        vyi = sorted_v[s, 1]
        vzi = sorted_v[s, 2]
        last = -1                           # a run of entries of one partner: one add
        r1 = 0.0
        r2 = 0.0
        touch = 0
        e0, e1 = entry_range(LIST_ROWS, list_start, nbr_n, s)  # noqa: F821
        for e in range(e0, e1):
            t = list_e[e, 0] if LIST_ROWS else nbr[s, e]  # noqa: F821
            bj = sorted_body[t]
            if SLEEPING and sleep_steps > 0:  # noqa: F821 (pair_forces' sleeping rule)
                if asleep and body_rest[bj] >= 0 and (
                        static_body(body_inv_mass[bj]) or body_rest[bj] >= sleep_steps):  # noqa: F821
                    continue
            rx = sorted_x[t, 0] - xi
            ry = sorted_x[t, 1] - yi
            rz = sorted_x[t, 2] - zi
            dvx = sorted_v[t, 0] - vxi
            dvy = sorted_v[t, 1] - vyi
            dvz = sorted_v[t, 2] - vzi
            dist2 = rx * rx + ry * ry + rz * rz
            if dist2 < d2:
                ov = diameter - sqrt(dist2)  # noqa: F821
            elif pair_ended(dist2, d2, diameter, rx, ry, rz, dvx, dvy, dvz, dt,  # noqa: F821
                            onset_speed):
                dist = sqrt(dist2)  # noqa: F821 (the overlap of the step before)
                ov = diameter - dist + (dvx * rx + dvy * ry + dvz * rz) / dist * dt
            else:
                if LIST_ROWS:  # noqa: F821
                    list_e[e, 2] = 0
                continue
            if LIST_ROWS:  # noqa: F821
                list_e[e, 2] = 1            # touching, or in the step after (LIST_COLS)
            touch = 1
            if bj != last:
                if last >= 0:
                    patch_add(row, slots, last, r1, r2)  # noqa: F821
                last = bj
                r1 = 0.0
                r2 = 0.0
            r1 += ov
            r2 += ov * ov
        if last >= 0:
            patch_add(row, slots, last, r1, r2)  # noqa: F821
        walls = wall_mask[s]
        if WALLS and walls != 0 and not asleep:  # noqa: F821 (as pair_forces' wall loop)
            for w in range(n_walls):
                if walls != -1 and (walls >> w) & 1 == 0:
                    continue
                nx = wall_normal[w, 0]
                ny = wall_normal[w, 1]
                nz = wall_normal[w, 2]
                m = wall_motion[w]
                dist, inside = wall_gap(w, xi, yi, zi, wall_normal, wall_offset,  # noqa: F821
                                        wall_lo, wall_hi, wall_motion, motion_now)
                uxi = vxi
                uyi = vyi
                uzi = vzi
                if m >= 0 and inside:
                    nx, ny, nz, sux, suy, suz = anchor_surface(  # noqa: F821
                        motion_now, m, nx, ny, nz, xi, yi, zi, dist, dt)
                    uxi -= sux
                    uyi -= suy
                    uzi -= suz
                if INSCRIBED:  # noqa: F821 (as pair_forces)
                    ov, da, ax, ay, az, uxi, uyi, uzi = inscribed_wall(  # noqa: F821
                        sphere_inscribed, body_q, sorted_idx[s], b, dist, radius,
                        nx, ny, nz, uxi, uyi, uzi,
                        body_w[b, 0], body_w[b, 1], body_w[b, 2])
                else:
                    ov = radius - dist
                away = uxi * nx + uyi * ny + uzi * nz
                if not inside or dist <= -wall_depth[w]:
                    continue
                if ov <= 0.0:
                    if not (away > onset_speed and closing(ov, away, dt)):  # noqa: F821
                        continue
                    ov += away * dt                 # the overlap of the step before
                patch_add(row, slots, n_bodies + w, ov, ov * ov)  # noqa: F821
                touch = 1
        if LIST_ROWS:  # noqa: F821
            slot_touch[s] = touch


def patch_share(body_patch, b, code):
    """1/n_eff for a contact of body b with partner ``code`` (a body index, or the
    number of bodies + a wall's index): n_eff = (Σδ)² / Σδ² of the patch this step
    (body_patches), or of all of b's contacts when b's row overflowed; 1 when the
    sums are 0 (the contact then exerts no force)."""
    row = body_patch[b]
    slots = body_patch.shape[1] - 1
    s1 = row[slots, 1]
    s2 = row[slots, 2]
    if row[slots, 0] == 0.0:
        for c in range(slots):
            if row[c, 0] == code + 1:
                s1 = row[c, 1]
                s2 = row[c, 2]
                break
    n = s1 * s1
    if n > s2 and s2 > 0.0:
        return s2 / n
    return 1.0


def pair_share(body_patch, body_inv_mass, b, partner):
    """The share of a sphere pair that body b owns with body ``partner``: b's row's
    (patch_share), or, when b's row overflowed (a tray carrying more than
    BODY_PATCHES pieces) and the partner is dynamic with a whole row, the partner's
    row's for b: the same patch summed from the other side. So the pieces on a crowded
    body keep their own patches whichever of the two owns the pairs."""
    slots = body_patch.shape[1] - 1
    if (body_patch[b, slots, 0] != 0.0 and not static_body(body_inv_mass[partner])  # noqa: F821
            and body_patch[partner, slots, 0] == 0.0):
        return patch_share(body_patch, partner, b)
    return patch_share(body_patch, b, partner)


#: The functions the targets compile from this module (callees first).
KERNEL = ("patch_add", "body_patches", "patch_share", "pair_share")
