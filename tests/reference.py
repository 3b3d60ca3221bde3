"""A slow, obvious reference for one step: all sphere pairs, no grid, plain Python.

It calls physics.py's formulas uncompiled, in the simplest possible loops, and
is the oracle the fast kernels (CPU and CUDA) are compared against.
"""

import numpy as np

from dempipe import physics


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
                                        *model.sphere_offset[i])
        x[i], v[i], r[i] = out[0:3], out[3:6], out[6:9]
    d = model.diameter
    # remembered tangential springs: (sphere, partner code) -> stretch; codes as in State.
    # A pair's stretch is kept once, in its owner's row (kernels/contacts.py); seen
    # from the other sphere it is the opposite (the force law is antisymmetric).
    spring = {}
    if model.features.friction and st.contact_partner is not None:
        for i, h in zip(*np.nonzero(st.contact_partner)):
            spring[(int(i), int(st.contact_partner[i, h]) >> 1)] = st.contact_spring[i, h]
    f = np.zeros((S, 3)); t = np.zeros((S, 3))
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
            if dist >= d:
                continue
            mi, mj = model.body_material[bi], model.body_material[bj]
            k = model.pair_k[mi, mj]
            root = np.sqrt(k / im)
            mu = model.pair_mu[mi, mj] if model.features.friction else 0.0
            if (i, j + 1) in spring:
                s0 = spring[(i, j + 1)]
            else:
                s0 = -spring.get((j, i + 1), np.zeros(3))
            out = physics.sphere_pair_force(*rij, dist, d, *(v[j] - v[i]), *(W[bi] + W[bj]), k,
                                            2 * model.pair_zeta[mi, mj] * root,
                                            model.kt_ratio * root, model.ks_ratio * k, mu,
                                            *s0, model.dt)
            f[i] += out[0:3]; t[i] += out[3:6]
        if model.body_inv_mass[bi] > 0:
            for w in range(model.n_walls):
                n = model.wall_normal[w]
                dist = float(n @ x[i] - model.wall_offset[w])
                if not (-model.wall_depth[w] < dist < d / 2):
                    continue
                if np.any(x[i] < model.wall_lo[w]) or np.any(x[i] > model.wall_hi[w]):
                    continue
                mi, mj = model.body_material[bi], model.wall_material[w]
                k = model.pair_k[mi, mj]
                root = np.sqrt(k / model.body_inv_mass[bi])
                mu = model.pair_mu[mi, mj] if model.features.friction else 0.0
                s0 = spring.get((i, S + w + 1), np.zeros(3))
                out = physics.sphere_wall_force(*(-n), d / 2 - dist, d / 2, *v[i], *W[bi], k,
                                                2 * model.pair_zeta[mi, mj] * root,
                                                model.kt_ratio * root, model.ks_ratio * k, mu,
                                                *s0, model.dt)
                f[i] += out[0:3]; t[i] += out[3:6]
    for b in range(model.n_bodies):
        sl = slice(model.body_sphere_start[b], model.body_sphere_start[b + 1])
        F = model.body_mass[b] * model.gravity + f[sl].sum(axis=0)
        T = (np.cross(r[sl], f[sl]) + t[sl]).sum(axis=0)
        out = physics.body_step(*st.body_x[b], *st.body_q[b], *st.body_P[b], *st.body_L[b], *F, *T,
                                model.body_inv_mass[b], *model.body_inv_inertia[b], model.dt)
        st.body_x[b], st.body_q[b], st.body_P[b], st.body_L[b] = out[0:3], out[3:7], out[7:10], out[10:13]
    return st
