"""Glue bonds in the step: each bond's sphere pairs, its break, each body's sum.

Three passes, each writing only its own rows (gather, no atomics; the same bits
for any thread count), run between the contact passes (kernels/contacts.py) and
the body stage (kernels/bodies.py), only in a kernel compiled with GLUE:

1. ``bond_forces`` per bond n (not broken): each of its sphere pairs' force on
   pair_i, torque about pair_i's centre and new shear stretch
   (physics.glue_force) into glue_f; when one pair's elastic load exceeds
   bond_limit[n], the bond breaks (bond_broken[n] = 1, for good) and none of
   its forces act from this step on. Two sleeping bodies' bond is left as it
   is; a moving body (rest count 0) wakes a sleeping partner, as a contact does.
2. ``bond_contacts`` per bond n that holds: its pairs' ordinary contacts are
   cancelled (their rows of pair_f zeroed after the contact stage's first pass,
   their friction history forgotten), so a glued pair is a bond and not also a
   contact; once broken, the contact stage alone acts on them.
3. ``body_glue_sum`` per body b: the force and the torque about its centre of
   mass of all its unbroken bonds, in its bonds' order, each bond's pairs in
   order, into body_glue[b], which the body stage adds to its spheres' sum.

Plain functions: the CPU compiles them with kernels/cpu/stages.py's globals
(compile.specialize), CUDA with compile.compile_glue; the names they read that are
not defined here (glue_force, static_body, entry_range, sqrt, ROTATION, SLEEPING,
PAIR_ROWS) are the target's.
"""


def bond_forces(n, gm, gs, sphere_body, slot_of, sorted_x, sorted_v, body_w, body_inv_mass,
                body_rest, body_wake, sleep_steps, dt):
    """Pass 1 for bond n; returns 1 when it broke this step, else 0. gm, gs:
    layout.GlueModel, GlueScratch; the positions and velocities of sphere i are at
    its sorted slot slot_of[i] (sorted_x [m], sorted_v [m/s])."""
    (pair_i, pair_j, pair_rest, bond_start, bond_body, bond_k, bond_eta, bond_limit,
     _body_bond_start, _body_bond) = gm
    (bond_broken, bond_shear, glue_f, _body_glue) = gs
    if bond_broken[n] != 0:
        return 0
    ba = bond_body[n, 0]
    bb = bond_body[n, 1]
    if SLEEPING and sleep_steps > 0:  # noqa: F821
        sa = body_rest[ba] >= sleep_steps or (static_body(body_inv_mass[ba])  # noqa: F821
                                              and body_rest[ba] >= 0)
        sb = body_rest[bb] >= sleep_steps or (static_body(body_inv_mass[bb])  # noqa: F821
                                              and body_rest[bb] >= 0)
        if sa and sb:
            for p in range(bond_start[n], bond_start[n + 1]):
                for c in range(6):
                    glue_f[p, c] = 0.0
            return 0                    # neither moves: the bond keeps its state
        if body_rest[ba] == 0 and body_rest[bb] >= sleep_steps:
            body_wake[bb] = 1
        if body_rest[bb] == 0 and body_rest[ba] >= sleep_steps:
            body_wake[ba] = 1
    k = bond_k[n]
    eta = bond_eta[n]
    broke = False
    for p in range(bond_start[n], bond_start[n + 1]):
        i = pair_i[p]
        j = pair_j[p]
        si = slot_of[i]
        sj = slot_of[j]
        bi = sphere_body[i]
        bj = sphere_body[j]
        wsx = 0.0
        wsy = 0.0
        wsz = 0.0
        if ROTATION:  # noqa: F821
            wsx = body_w[bi, 0] + body_w[bj, 0]
            wsy = body_w[bi, 1] + body_w[bj, 1]
            wsz = body_w[bi, 2] + body_w[bj, 2]
        rx = sorted_x[sj, 0] - sorted_x[si, 0]
        ry = sorted_x[sj, 1] - sorted_x[si, 1]
        rz = sorted_x[sj, 2] - sorted_x[si, 2]
        dist = sqrt(rx * rx + ry * ry + rz * rz)  # noqa: F821
        (fx, fy, fz, tx, ty, tz, sx, sy, sz, load) = glue_force(  # noqa: F821
            rx, ry, rz, dist, pair_rest[p],
            sorted_v[sj, 0] - sorted_v[si, 0], sorted_v[sj, 1] - sorted_v[si, 1],
            sorted_v[sj, 2] - sorted_v[si, 2], wsx, wsy, wsz, k, eta,
            bond_shear[p, 0], bond_shear[p, 1], bond_shear[p, 2], dt)
        if load > bond_limit[n]:
            broke = True
        glue_f[p, 0] = fx
        glue_f[p, 1] = fy
        glue_f[p, 2] = fz
        glue_f[p, 3] = tx
        glue_f[p, 4] = ty
        glue_f[p, 5] = tz
        glue_f[p, 6] = sx
        glue_f[p, 7] = sy
        glue_f[p, 8] = sz
    if broke:
        bond_broken[n] = 1
        for p in range(bond_start[n], bond_start[n + 1]):
            for c in range(9):
                glue_f[p, c] = 0.0
            bond_shear[p, 0] = 0.0
            bond_shear[p, 1] = 0.0
            bond_shear[p, 2] = 0.0
        return 1
    for p in range(bond_start[n], bond_start[n + 1]):
        bond_shear[p, 0] = glue_f[p, 6]
        bond_shear[p, 1] = glue_f[p, 7]
        bond_shear[p, 2] = glue_f[p, 8]
    return 0


def bond_contacts(n, gm, gs, slot_of, sorted_body, body_inv_mass, pair_start,
                  pair_e, list_e, nbr, nbr_n, pidx, pair_f):
    """Pass 2 for bond n: while it holds, the contact rows of its sphere pairs are
    zeroed (force, torque, friction stretch), so that the second contact pass sums
    nothing for them. The owner's rows are found as the first pass walks them
    (contacts.py PAIR_ROWS): the CPU's packed rows pair_start[s] .. with their
    partners in their packed list entries (list_e[pair_e[row], 0]), or (CUDA) the
    owner's list nbr[s, :nbr_n[s]] with its rows in pidx (the partner's entries,
    pidx < 0, skipped)."""
    (pair_i, pair_j, _pair_rest, bond_start, _bond_body, _bond_k, _bond_eta, _bond_limit,
     _body_bond_start, _body_bond) = gm
    bond_broken = gs.bond_broken
    if bond_broken[n] != 0:
        return
    for p in range(bond_start[n], bond_start[n + 1]):
        s = slot_of[pair_i[p]]
        t = slot_of[pair_j[p]]
        if static_body(body_inv_mass[sorted_body[s]]):  # noqa: F821
            s, t = t, s             # the dynamic side owns (pairing.owns; pair_i < pair_j)
        e0, e1 = entry_range(PAIR_ROWS, pair_start, nbr_n, s)  # noqa: F821
        for e in range(e0, e1):
            if PAIR_ROWS:  # noqa: F821
                row = e
                u = list_e[pair_e[e], 0]
            else:
                row = pidx[s, e]
                u = nbr[s, e]
            if u == t and row >= 0:
                for c in range(pair_f.shape[1]):
                    pair_f[row, c] = 0.0
                break


def body_glue_sum(b, gm, gs, sphere_body, sphere_r):
    """Pass 3 for body b: body_glue[b] = (force [N], torque about its centre of mass
    [N m]) of its unbroken bonds (glue_f: the force on pair_i; pair_j takes it
    negated, its torque about its own centre equal), sphere_r the spheres' offsets
    from their bodies' centres of mass, world frame [m]."""
    (pair_i, pair_j, _pair_rest, bond_start, _bond_body, _bond_k, _bond_eta, _bond_limit,
     body_bond_start, body_bond) = gm
    (bond_broken, _bond_shear, glue_f, body_glue) = gs
    fx = 0.0
    fy = 0.0
    fz = 0.0
    tx = 0.0
    ty = 0.0
    tz = 0.0
    for e in range(body_bond_start[b], body_bond_start[b + 1]):
        n = body_bond[e]
        if bond_broken[n] != 0:
            continue
        for p in range(bond_start[n], bond_start[n + 1]):
            i = pair_i[p]
            gx = glue_f[p, 0]
            gy = glue_f[p, 1]
            gz = glue_f[p, 2]
            if sphere_body[i] != b:
                i = pair_j[p]
                gx = -gx
                gy = -gy
                gz = -gz
            fx += gx
            fy += gy
            fz += gz
            if ROTATION:  # noqa: F821
                rx = sphere_r[i, 0]
                ry = sphere_r[i, 1]
                rz = sphere_r[i, 2]
                tx += (ry * gz - rz * gy) + glue_f[p, 3]
                ty += (rz * gx - rx * gz) + glue_f[p, 4]
                tz += (rx * gy - ry * gx) + glue_f[p, 5]
    body_glue[b, 0] = fx
    body_glue[b, 1] = fy
    body_glue[b, 2] = fz
    body_glue[b, 3] = tx
    body_glue[b, 4] = ty
    body_glue[b, 5] = tz
