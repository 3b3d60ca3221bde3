"""Stages 5-8 for one body, for both targets: the sum of its spheres' forces and
torques (eq. 15-16), its momenta, position and orientation (eq. 2-10,
physics.body_step), and sleeping. A plain function (no numba here) compiled with
each target's formulas and feature flags: kernels/cpu/stages.py's stage_bodies loops
over it, kernels/cuda/stages.py's k_bodies runs a thread per body, so the two
targets run the one body stage and stay bit-identical.
"""

# The names this module reads but does not define (static_body, body_step,
# angular_velocity, rest_steps, rolling_scale, ROTATION, FRICTION, SLEEPING,
# GLUE) are the
# target's:
# its compiled formulas and feature flags, given when it is compiled.


def body_update(b, k0, k1, s0, work, listed, bm, bs, step):
    """Stages 5-8 for body b (the body of stage_bodies' loop), with sleeping.

    The sums run over the body's spheres in index order: when ``listed`` (the CPU)
    only those at the slots work[k0 .. k1-1] (stage_busy's, in slot order, which is
    the body's sphere order from its first slot s0: stage_grid_sort), the others'
    forces and torques being zero until the next rebuild, and of those only the
    spheres that touched anything at this step's contact passes (sphere_engaged:
    contacts.engaged; the others' sums are +0.0); else every one (``work``, s0 and
    sphere_engaged unread; CUDA). The same sums bit for bit: a sum that starts at
    +0.0, as each of them does, is left as it is by adding +0.0.

    Returns awake + 2 woke + 4 quiet + 8 calmed: awake (1) when the body will
    integrate at the next step; quiet (4) when it is asleep and slept through
    this step (stage_active's body_quiet); woke (2) when it was quiet before this
    step and is not now; calmed (8) the other way round. body_still[b] = 1 when the body slept
    through this step (did not move): stage 1 may keep its spheres' positions
    from the last step. A kinematic body (static: its motion carries it,
    stage_driven) and a body not yet emitted (body_start) are left alone; a
    kinematic body that moves counts as awake. A body flagged by the contact pass
    while awake (it touches a moving surface) keeps a rest count of 0.
    bm: layout.BodyModel, bs: layout.BodyScratch (unpacked below under the names
    the stage reads); step: this step's number."""
    (dt, gravity, body_sphere_start, body_mass, body_inv_mass, body_inv_inertia, sleep_steps,
     v_sleep, w_sleep, body_start, rolling) = bm
    (sphere_f, sphere_t, sphere_tr, sphere_r, body_x, body_q, body_P, body_L, body_rest,
     body_wake, body_still, body_glue, sphere_engaged) = bs
    if static_body(body_inv_mass[b]):
        return 1 if body_rest[b] < 0 else 0
    if body_start[b] > step:
        body_still[b] = 1           # parked where it will start
        return 0
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
    FX = m * gravity[0] + 0.0       # + 0.0: never -0.0, which adding +0.0 would change
    FY = m * gravity[1] + 0.0
    FZ = m * gravity[2] + 0.0
    TX = 0.0
    TY = 0.0
    TZ = 0.0
    RX = 0.0                        # the rolling torques, limited below (rolling_scale)
    RY = 0.0
    RZ = 0.0
    i0 = body_sphere_start[b]
    for j in range(k1 - k0 if listed else body_sphere_start[b + 1] - i0):
        i = i0 + work[k0 + j] - s0 if listed else i0 + j
        if listed and sphere_engaged[i] == 0:
            continue                # touched nothing at this step's passes: +0.0 each
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
            # torques about the spheres' centres (TORQUE_NOTE), and without friction
            # those of the inscribed tori's contacts, whose force is off the centre
            if FRICTION or INSCRIBED:  # noqa: F821
                TX += (ry * fz - rz * fy) + sphere_t[i, 0]
                TY += (rz * fx - rx * fz) + sphere_t[i, 1]
                TZ += (rx * fy - ry * fx) + sphere_t[i, 2]
                if FRICTION and rolling:
                    RX += sphere_tr[i, 0]
                    RY += sphere_tr[i, 1]
                    RZ += sphere_tr[i, 2]
            else:
                TX += ry * fz - rz * fy
                TY += rz * fx - rx * fz
                TZ += rx * fy - ry * fx
    if GLUE:  # noqa: F821 (its bonds' sum: kernels/glue.py)
        FX += body_glue[b, 0]
        FY += body_glue[b, 1]
        FZ += body_glue[b, 2]
        if ROTATION:
            TX += body_glue[b, 3]
            TY += body_glue[b, 4]
            TZ += body_glue[b, 5]
    ii = body_inv_inertia[b]
    x = body_x[b]
    q = body_q[b]
    P = body_P[b]
    L = body_L[b]
    im = body_inv_mass[b]
    if ROTATION and FRICTION and rolling and (RX != 0.0 or RY != 0.0 or RZ != 0.0):
        # rolling resistance may at most stop the spin the body would have after
        # this step's other torques, never reverse it, however many contacts it has
        # (physics.rolling_scale)
        wx, wy, wz = angular_velocity(q[0], q[1], q[2], q[3], ii[0], ii[1], ii[2], ii[3],
                                      ii[4], ii[5], L[0] + TX * dt, L[1] + TY * dt,
                                      L[2] + TZ * dt)
        dwx, dwy, dwz = angular_velocity(q[0], q[1], q[2], q[3], ii[0], ii[1], ii[2], ii[3],
                                         ii[4], ii[5], RX * dt, RY * dt, RZ * dt)
        sr = rolling_scale(wx, wy, wz, dwx, dwy, dwz, RX, RY, RZ)
        TX += sr * RX
        TY += sr * RY
        TZ += sr * RZ
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
        if body_wake[b] != 0:
            r = 0                   # on a moving surface: never falls asleep
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
    body_still[b] = 0               # it moves: stage 1 places its spheres (parked until now)
    return 1
