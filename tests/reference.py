"""A slow, obvious reference for one step: all sphere pairs, no grid, plain Python.

It calls physics.py's formulas uncompiled, in the simplest possible loops, and
is the oracle the fast kernels (CPU and CUDA) are compared against.
"""

import numpy as np

from dempipe.sim import physics
from dempipe.sim.kernels.contacts import CLOSE_REACH2
from dempipe.sim.kernels.patches import BODY_PATCHES
from dempipe.sim.laws import law, linear


def pair_closing(r, dist2, dv, d, dt, vc):
    """Whether two spheres apart (|r|² = dist2 ≥ d²) touched a step ago and separate
    faster than the onset speed vc: the step in which the law applies the end of
    its dashpot (kernels/contacts.py: pair_ended)."""
    if dist2 >= d * d * CLOSE_REACH2:
        return False
    un = (dv[0] * r[0] + dv[1] * r[1] + dv[2] * r[2]) / np.sqrt(dist2)
    return un > vc and linear.closing(d - np.sqrt(dist2), un, dt)


def wall_closing(n, dist, v, d, dt, vc):
    """Whether a sphere at ``dist`` ≥ d/2 from a wall of normal n touched it a step
    ago and leaves faster than vc."""
    un = v[0] * n[0] + v[1] * n[1] + v[2] * n[2]
    return un > vc and linear.closing(0.5 * d - dist, un, dt)


def rolling(model, w_rel, n, out, mi, mj, inv_radius):
    """The rolling-resistance torque on a sphere of a contact (physics.rolling_torque),
    from the contact's force ``out[0:3]`` and normal ``n`` (any length); zero without it."""
    mu_r = model.pair_rolling[mi, mj]
    if not (model.features.rolling and mu_r > 0.0):
        return np.zeros(3)
    fn = out[0] * n[0] + out[1] * n[1] + out[2] * n[2]
    return np.array(physics.rolling_torque(*w_rel, *n, float(n @ n), fn, mu_r, inv_radius,
                                           model.onset_speed))


def patch_sums(model, x, v, rest):
    """Each dynamic body's contact patches this step (kernels/patches.py): body ->
    (partner code -> [Σδ, Σδ²], [Σδ, Σδ²] of all, overflowed), summed in the kernels'
    order (the body's spheres by index, each sphere's partners by index, a run of one
    partner body's spheres summed first, then its walls), so that the shares come out
    bit for bit. x, v: every sphere's position and velocity; rest: the rest counts."""
    nb_all = model.body_mass.shape[0]
    S = model.n_spheres
    d = model.diameter
    radius = 0.5 * d
    sleep = model.sleep_steps
    inv = model.body_inv_mass
    out = {}
    for b in range(nb_all):
        if inv[b] == 0.0:
            continue
        row, total = {}, [0.0, 0.0]

        def add(code, s1, s2):
            total[0] += s1
            total[1] += s2
            if code in row:
                row[code][0] += s1
                row[code][1] += s2
            else:
                row[code] = [s1, s2]
        asleep = sleep > 0 and rest[b] >= sleep
        for i in range(model.body_sphere_start[b], model.body_sphere_start[b + 1]):
            last, r1, r2 = -1, 0.0, 0.0
            for j in range(S):
                bj = int(model.sphere_body[j])
                if bj == b:
                    continue
                if sleep > 0 and asleep and rest[bj] >= 0 and (
                        inv[bj] == 0.0 or rest[bj] >= sleep):
                    continue
                rx, ry, rz = (float(c) for c in x[j] - x[i])
                dvx, dvy, dvz = (float(c) for c in v[j] - v[i])
                dist2 = rx * rx + ry * ry + rz * rz
                if dist2 < d * d:
                    ov = d - float(np.sqrt(dist2))
                elif pair_closing(np.array([rx, ry, rz]), dist2, np.array([dvx, dvy, dvz]), d,
                                  model.dt, model.onset_speed):
                    dist = float(np.sqrt(dist2))
                    ov = d - dist + (dvx * rx + dvy * ry + dvz * rz) / dist * model.dt
                else:
                    continue
                if bj != last:
                    if last >= 0:
                        add(last, r1, r2)
                    last, r1, r2 = bj, 0.0, 0.0
                r1 += ov
                r2 += ov * ov
            if last >= 0:
                add(last, r1, r2)
            if asleep:
                continue
            for w in range(model.n_walls):
                n = model.wall_normal[w]
                dist = float(n[0] * x[i, 0] + n[1] * x[i, 1] + n[2] * x[i, 2]
                             - model.wall_offset[w])
                if np.any(x[i] < model.wall_lo[w]) or np.any(x[i] > model.wall_hi[w]) \
                        or dist <= -model.wall_depth[w]:
                    continue
                ov = radius - dist
                if dist >= radius:
                    away = float(v[i, 0] * n[0] + v[i, 1] * n[1] + v[i, 2] * n[2])
                    if not wall_closing(n, dist, v[i], d, model.dt, model.onset_speed):
                        continue
                    ov += away * model.dt
                add(nb_all + w, ov, ov * ov)
        out[b] = (row, total, len(row) > BODY_PATCHES)
    return out


def patch_share(patches, b, code):
    """1/n_eff of body b's patch with partner ``code`` (kernels/patches.patch_share)."""
    row, total, over = patches[b]
    s1, s2 = total if over else row.get(code, total)
    n = s1 * s1
    return s2 / n if n > s2 and s2 > 0.0 else 1.0


def owner_share(model, patches, i, j):
    """The share a sphere pair (i, j) takes (kernels/patches.pair_share): its owner's
    body's (the sphere of lower index, or the dynamic one when the other is static),
    or the partner's when the owner's row overflowed and the partner's did not."""
    bi, bj = int(model.sphere_body[i]), int(model.sphere_body[j])
    if not (model.body_inv_mass[bj] == 0.0 or i < j):
        bi, bj = bj, bi                             # bi owns the pair
    if patches[bi][2] and model.body_inv_mass[bj] > 0.0 and not patches[bj][2]:
        return patch_share(patches, bj, bi)         # its row overflowed, bj's did not
    return patch_share(patches, bi, bj)


def reference_step(model, state):
    """Advance a copy of ``state`` by one step of ``model``; returns the new State."""
    st = state.copy()
    nb_all = model.body_mass.shape[0]
    V = np.zeros((nb_all, 3))
    W = np.zeros((nb_all, 3))
    for b in range(model.n_bodies):
        V[b] = st.body_P[b] * model.body_inv_mass[b]
        W[b] = physics.angular_velocity(*st.body_q[b], *model.body_inv_inertia[b], *st.body_L[b])
    S = model.n_spheres
    x = np.zeros((S, 3)); v = np.zeros((S, 3)); r = np.zeros((S, 3))
    for i in range(S):
        b = model.sphere_body[i]
        out = physics.sphere_kinematics(*st.body_x[b], *st.body_q[b], *V[b], *W[b],
                                        *model.sphere_offset[i], model.dt)
        x[i], v[i], r[i] = out[0:3], out[3:6], out[6:9]
    d = model.diameter
    # remembered tangential springs: (sphere, partner code) -> stretch; codes as in State.
    # A pair's stretch is kept once, in its owner's row (kernels/contacts.py); seen
    # from the other sphere it is the opposite (the force law is antisymmetric).
    spring = {}
    if model.features.friction and st.contact_partner is not None:
        for i, h in zip(*np.nonzero(st.contact_partner)):
            spring[(int(i), int(st.contact_partner[i, h]) >> 1)] = st.contact_spring[i, h]
    f = np.zeros((S, 3)); t = np.zeros((S, 3)); tr = np.zeros((S, 3))
    patches = patch_sums(model, x, v, st.body_rest)
    for i in range(S):
        bi = model.sphere_body[i]
        if model.body_inv_mass[bi] == 0.0:
            continue                       # static spheres feel no force
        for j in range(S):
            bj = model.sphere_body[j]
            if bi == bj:
                continue
            im = model.body_inv_mass[bi] + model.body_inv_mass[bj]
            if im == 0.0:
                continue
            rij = x[j] - x[i]
            dist = float(np.sqrt(rij @ rij))
            if dist >= d and not pair_closing(rij, rij @ rij, v[j] - v[i], d, model.dt,
                                                    model.onset_speed):
                continue
            mi, mj = model.body_material[bi], model.body_material[bj]
            k, eta, kt, ks = law(model.contact_law).contact_coefficients(model.pair_k[mi, mj],
                                                         model.pair_damp, mi, mj, im,
                                                         model.kt_ratio, model.ks_ratio, model.dt,
                                                         d - dist)
            share = owner_share(model, patches, i, j)
            k, eta, kt, ks = k * share, eta * share, kt * share, ks * share
            mu = model.pair_mu[mi, mj] if model.features.friction else 0.0
            if (i, j + 1) in spring:
                s0 = spring[(i, j + 1)]
            else:
                s0 = -spring.get((j, i + 1), np.zeros(3))
            out = physics.sphere_pair_force(*rij, dist, d, *(v[j] - v[i]), *(W[bi] + W[bj]),
                                            k, eta, kt, ks, mu, *s0, model.dt,
                                            model.onset_speed)
            f[i] += out[0:3]; t[i] += out[3:6]
            n = rij if dist > 0 else np.array([0.0, 0.0, 1.0])
            tr[i] += rolling(model, W[bi] - W[bj], n, out, mi, mj,
                             model.body_inv_radius[bi] + model.body_inv_radius[bj])
        if model.body_inv_mass[bi] > 0:
            for w in range(model.n_walls):
                n = model.wall_normal[w]
                dist = float(n @ x[i] - model.wall_offset[w])
                if not (-model.wall_depth[w] < dist < d / 2
                        or (dist >= d / 2
                            and wall_closing(n, dist, v[i], d, model.dt, model.onset_speed))):
                    continue
                if np.any(x[i] < model.wall_lo[w]) or np.any(x[i] > model.wall_hi[w]):
                    continue
                mi, mj = model.body_material[bi], model.wall_material[w]
                k, eta, kt, ks = law(model.contact_law).contact_coefficients(
                    model.pair_k[mi, mj], model.pair_damp, mi, mj, model.body_inv_mass[bi],
                    model.kt_ratio, model.ks_ratio, model.dt, d / 2 - dist)
                share = patch_share(patches, bi, nb_all + w)
                k, eta, kt, ks = k * share, eta * share, kt * share, ks * share
                mu = model.pair_mu[mi, mj] if model.features.friction else 0.0
                s0 = spring.get((i, S + w + 1), np.zeros(3))
                out = physics.sphere_wall_force(*(-n), d / 2 - dist, d / 2, *v[i], *W[bi],
                                                0.0, 0.0, 0.0, k, eta, kt, ks, mu, *s0,
                                                model.dt, model.onset_speed)
                f[i] += out[0:3]; t[i] += out[3:6]
                tr[i] += rolling(model, W[bi], n, out, mi, mj, model.body_inv_radius[bi])
    for b in range(model.n_bodies):
        sl = slice(model.body_sphere_start[b], model.body_sphere_start[b + 1])
        F = model.body_mass[b] * model.gravity + f[sl].sum(axis=0)
        T = (np.cross(r[sl], f[sl]) + t[sl]).sum(axis=0)
        TR = tr[sl].sum(axis=0)
        if np.any(TR != 0):             # limited per body (physics.rolling_scale),
            ii, q, L = model.body_inv_inertia[b], st.body_q[b], st.body_L[b]
            w = physics.angular_velocity(*q, *ii, *(L + T * model.dt))   # after T
            dw = physics.angular_velocity(*q, *ii, *(TR * model.dt))
            T = T + physics.rolling_scale(*w, *dw, *TR) * TR
        out = physics.body_step(*st.body_x[b], *st.body_q[b], *st.body_P[b], *st.body_L[b], *F, *T,
                                model.body_inv_mass[b], *model.body_inv_inertia[b], model.dt)
        st.body_x[b], st.body_q[b], st.body_P[b], st.body_L[b] = out[0:3], out[3:7], out[7:10], out[10:13]
    return st
