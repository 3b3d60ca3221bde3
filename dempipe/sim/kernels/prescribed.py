"""The prescribed inputs inside a step, for both targets: each motion evaluated at
the step's time (``motion_row``) and each carried body put where its motion says
(``driven_row``). Plain functions (no numba here), compiled per target with its
formulas (motion.anchor_state, motion.carried_state): kernels/cpu/stages.py loops over
them serially (a scene has a few), kernels/cuda/stages.py runs a thread each.
The Drive they read is control.Drive; the walls a motion carries are read in the
contact pass (contacts.pair_forces) through motion_now.
"""


def motion_row(m, t, motion_kind, motion_v, motion_w, motion_pivot, key_start, key_t, key_p,
               key_q, motion_now):
    """Motion m at time t [s] (motion.anchor_state): its anchor's position,
    orientation, velocity and angular velocity into motion_now[m, :13], and in
    motion_now[m, 13] whether it moves (1) or holds still (0)."""
    (px, py, pz, qw, qx, qy, qz, vx, vy, vz, wx, wy, wz) = anchor_state(  # noqa: F821
        t, motion_kind[m], motion_v[m], motion_w[m], motion_pivot[m], key_t, key_p, key_q,
        key_start[m], key_start[m + 1])
    motion_now[m, 0] = px
    motion_now[m, 1] = py
    motion_now[m, 2] = pz
    motion_now[m, 3] = qw
    motion_now[m, 4] = qx
    motion_now[m, 5] = qy
    motion_now[m, 6] = qz
    motion_now[m, 7] = vx
    motion_now[m, 8] = vy
    motion_now[m, 9] = vz
    motion_now[m, 10] = wx
    motion_now[m, 11] = wy
    motion_now[m, 12] = wz
    moving = (vx != 0.0 or vy != 0.0 or vz != 0.0 or wx != 0.0 or wy != 0.0 or wz != 0.0)
    motion_now[m, 13] = 1.0 if moving else 0.0


def driven_row(k, driven_body, body_motion, body_anchor_c, body_anchor_q, motion_now, body_x,
               body_q, body_v, body_w, body_rest, body_still, h):
    """The k-th carried body (a kinematic body, a moving mesh collider) where its
    motion puts it (motion.carried_state), with its velocities, so that stage 1
    gives its spheres the surface velocity. Its centre's velocity is the chord of
    the step h [s] (motion.chord_velocity), as a dynamic body's is; h = 0 gives
    the tangent, what a frame records. Its rest count is -1 while it moves
    (the contact pass then wakes what it touches) and 0 when it holds still;
    stage 1 recomputes its spheres at every step (body_still = 0)."""
    b = driven_body[k]
    m = body_motion[b]
    (x, y, z, qw, qx, qy, qz, vx, vy, vz) = carried_state(  # noqa: F821
        motion_now[m, 0], motion_now[m, 1], motion_now[m, 2], motion_now[m, 3],
        motion_now[m, 4], motion_now[m, 5], motion_now[m, 6], motion_now[m, 7],
        motion_now[m, 8], motion_now[m, 9], motion_now[m, 10], motion_now[m, 11],
        motion_now[m, 12], body_anchor_c[b, 0], body_anchor_c[b, 1], body_anchor_c[b, 2],
        body_anchor_q[b, 0], body_anchor_q[b, 1], body_anchor_q[b, 2], body_anchor_q[b, 3])
    body_x[b, 0] = x
    body_x[b, 1] = y
    body_x[b, 2] = z
    body_q[b, 0] = qw
    body_q[b, 1] = qx
    body_q[b, 2] = qy
    body_q[b, 3] = qz
    if h > 0.0:
        vx, vy, vz = chord_velocity(  # noqa: F821
            motion_now[m, 7], motion_now[m, 8], motion_now[m, 9], motion_now[m, 10],
            motion_now[m, 11], motion_now[m, 12], x - motion_now[m, 0], y - motion_now[m, 1],
            z - motion_now[m, 2], h)
    body_v[b, 0] = vx
    body_v[b, 1] = vy
    body_v[b, 2] = vz
    body_w[b, 0] = motion_now[m, 10]
    body_w[b, 1] = motion_now[m, 11]
    body_w[b, 2] = motion_now[m, 12]
    body_rest[b] = -1 if motion_now[m, 13] != 0.0 else 0
    body_still[b] = 0
