"""Stages 5-8 and sleep on the device: the step's control (begin, idle), body
velocities, the body update with rest counts, and small reductions.

Imported by kernels/cuda.py (the backend launches them); see docs/cuda.md.
"""

from __future__ import annotations

from numba import cuda

from .cuda_device import (CTL_AWAKE, CTL_DONE, CTL_FORCE, CTL_IDLE, CTL_IDLE_STEPS, CTL_MOVED,
                          CTL_OVER, CTL_REBUILDS, SLEEPING, angular_velocity, body_step,
                          rebuilding, rest_steps)


@cuda.jit
def k_begin_call(ctl):
    """Once per ``step`` call (and per probe): rebuild at the first step, and no
    spheres moved, no overflow, no rebuilds yet."""
    if cuda.grid(1) == 0:
        for j in range(ctl.shape[0]):
            ctl[j] = 0
        ctl[CTL_FORCE] = 1
        ctl[CTL_AWAKE] = 1


@cuda.jit
def k_idle_check(ctl, sleep_steps):
    """First launch of a step (one thread): with sleeping on and no body awake after
    the last step's body stage, nothing can move any more, so this and the call's
    remaining steps are no-ops (CTL_IDLE); then reset the awake count for this step."""
    if cuda.grid(1) == 0:
        if sleep_steps > 0 and ctl[CTL_AWAKE] == 0:
            ctl[CTL_IDLE] = 1
        ctl[CTL_AWAKE] = 0


@cuda.jit
def k_body_velocities(n_bodies, body_P, body_L, body_q, body_inv_mass, body_inv_inertia,
                      body_v, body_w):
    """V = P/M and W = I(t)⁻¹ L (eq. 5-6) for each dynamic body."""
    b = cuda.grid(1)
    if b >= n_bodies:
        return
    im = body_inv_mass[b]
    body_v[b, 0] = body_P[b, 0] * im
    body_v[b, 1] = body_P[b, 1] * im
    body_v[b, 2] = body_P[b, 2] * im
    wx, wy, wz = angular_velocity(
        body_q[b, 0], body_q[b, 1], body_q[b, 2], body_q[b, 3],
        body_inv_inertia[b, 0], body_inv_inertia[b, 1], body_inv_inertia[b, 2],
        body_inv_inertia[b, 3], body_inv_inertia[b, 4], body_inv_inertia[b, 5],
        body_L[b, 0], body_L[b, 1], body_L[b, 2])
    body_w[b, 0] = wx
    body_w[b, 1] = wy
    body_w[b, 2] = wz


@cuda.jit
def k_bodies(n_bodies, dt, gravity, body_sphere_start, sphere_f, sphere_t, sphere_r,
             body_mass, body_inv_mass, body_inv_inertia, body_x, body_q, body_P, body_L,
             sleep_steps, v_sleep, w_sleep, body_rest, body_wake, ctl):
    """Stages 5-8: sum forces and torques (eq. 15-16), update P, L, X, q (eq. 2-10);
    sleeping as kernels.cpu.body_update.

    Thread 0 also closes the step's rebuild decision: counts a rebuild if there
    was one and clears CTL_FORCE and CTL_MOVED for the next step (no kernel of
    this launch reads them), and counts the step done (CTL_DONE) unless a list
    overflowed in this call (CTL_OVER): from then on the bodies are left as they
    are, and the host carries on from the overflowing step with longer lists.
    """
    b = cuda.grid(1)
    if b == 0:
        if rebuilding(ctl):
            ctl[CTL_REBUILDS] += 1
        ctl[CTL_FORCE] = 0
        ctl[CTL_MOVED] = 0
        if ctl[CTL_OVER] == 0:
            ctl[CTL_DONE] += 1
        if ctl[CTL_IDLE] != 0:
            ctl[CTL_IDLE_STEPS] += 1
    if b >= n_bodies or ctl[CTL_OVER] != 0 or ctl[CTL_IDLE] != 0:
        return
    if SLEEPING and sleep_steps > 0 and body_rest[b] >= sleep_steps:
        if body_wake[b] != 0:
            body_rest[b] = 1
            body_wake[b] = 0
            cuda.atomic.add(ctl, CTL_AWAKE, 1)   # integrates from the next step
        return
    m = body_mass[b]
    FX = m * gravity[0]
    FY = m * gravity[1]
    FZ = m * gravity[2]
    TX = 0.0
    TY = 0.0
    TZ = 0.0
    for i in range(body_sphere_start[b], body_sphere_start[b + 1]):
        fx = sphere_f[i, 0]
        fy = sphere_f[i, 1]
        fz = sphere_f[i, 2]
        rx = sphere_r[i, 0]
        ry = sphere_r[i, 1]
        rz = sphere_r[i, 2]
        FX += fx
        FY += fy
        FZ += fz
        TX += (ry * fz - rz * fy) + sphere_t[i, 0]
        TY += (rz * fx - rx * fz) + sphere_t[i, 1]
        TZ += (rx * fy - ry * fx) + sphere_t[i, 2]
    (X, Y, Z, qw, qx, qy, qz, PX, PY, PZ, LX, LY, LZ) = body_step(
        body_x[b, 0], body_x[b, 1], body_x[b, 2],
        body_q[b, 0], body_q[b, 1], body_q[b, 2], body_q[b, 3],
        body_P[b, 0], body_P[b, 1], body_P[b, 2], body_L[b, 0], body_L[b, 1], body_L[b, 2],
        FX, FY, FZ, TX, TY, TZ, body_inv_mass[b],
        body_inv_inertia[b, 0], body_inv_inertia[b, 1], body_inv_inertia[b, 2],
        body_inv_inertia[b, 3], body_inv_inertia[b, 4], body_inv_inertia[b, 5], dt)
    body_x[b, 0] = X
    body_x[b, 1] = Y
    body_x[b, 2] = Z
    body_q[b, 0] = qw
    body_q[b, 1] = qx
    body_q[b, 2] = qy
    body_q[b, 3] = qz
    body_P[b, 0] = PX
    body_P[b, 1] = PY
    body_P[b, 2] = PZ
    body_L[b, 0] = LX
    body_L[b, 1] = LY
    body_L[b, 2] = LZ
    if SLEEPING and sleep_steps > 0:
        im = body_inv_mass[b]
        wx, wy, wz = angular_velocity(qw, qx, qy, qz, body_inv_inertia[b, 0],
                                      body_inv_inertia[b, 1], body_inv_inertia[b, 2],
                                      body_inv_inertia[b, 3], body_inv_inertia[b, 4],
                                      body_inv_inertia[b, 5], LX, LY, LZ)
        r = rest_steps(body_rest[b], PX * im, PY * im, PZ * im, wx, wy, wz, v_sleep, w_sleep)
        if r >= sleep_steps:
            body_P[b, 0] = 0.0
            body_P[b, 1] = 0.0
            body_P[b, 2] = 0.0
            body_L[b, 0] = 0.0
            body_L[b, 1] = 0.0
            body_L[b, 2] = 0.0
        body_rest[b] = r
        body_wake[b] = 0
        if r < sleep_steps:
            cuda.atomic.add(ctl, CTL_AWAKE, 1)
    else:
        cuda.atomic.add(ctl, CTL_AWAKE, 1)


@cuda.jit
def k_take_max(values, out):
    """out[0] = max(out[0], values[...]) and values[...] = 0 (float max: exact, commutative)."""
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    m = 0.0
    for i in range(start, values.shape[0], stride):
        v = values[i]
        if v > m:
            m = v
        values[i] = 0.0
    if m > 0.0:
        cuda.atomic.max(out, 0, m)


@cuda.jit
def k_fill(values, v):
    i = cuda.grid(1)
    if i < values.shape[0]:
        values[i] = v
