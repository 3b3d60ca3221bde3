"""Stages 4-8 on the device, the twin of cpu/stages.py: the contact kernels (the pairs
at a rebuild: pair rows, walls in reach, the histories in and out; the two contact
passes, contacts.py compiled by cuda/device.py and specialized per feature set by
cuda/backend.py's kernels; the glue passes of a scene with bonds), then the body kernels (the step's control: begin, idle;
body velocities, the body update with rest counts, small reductions).

Launched by cuda/backend.py; see docs/cuda.md.
"""

from __future__ import annotations

from numba import cuda

from dempipe.sim.kernels.cuda.device import (
    CTL_AWAKE,
    CTL_DONE,
    CTL_FORCE,
    CTL_IDLE,
    CTL_IDLE_STEPS,
    CTL_MOVED,
    CTL_OVER,
    CTL_REBUILDS,
    CTL_STEP,
    angular_velocity,
    body_glue_sum,
    body_patches,
    body_update,
    bond_contacts,
    bond_forces,
    driven_row,
    motion_row,
    pair_forces,
    pair_mirror,
    pair_slots,
    pairs_to_rows,
    rebuilding,
    rows_to_pairs,
    sphere_forces,
    wall_reach,
)


@cuda.jit
def k_save_pairs(at_end, friction, nbr, nbr_n, pidx, sorted_idx, contact_partner,
                 contact_spring, pair_f, ctl):
    """With friction: the touching pairs' stretches back into their owners' history
    rows (contacts.pairs_to_rows), while
    the lists they were read from still stand: at a rebuild that is not a
    call's first step (before the re-sort), and (``at_end``, launched by the
    host) after a call's last step."""
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0] or not friction:
        return
    if not at_end and (ctl[CTL_FORCE] != 0 or ctl[CTL_MOVED] == 0 or ctl[CTL_OVER] != 0):
        return
    pairs_to_rows(s, sorted_idx[s], nbr, nbr_n, pidx, sorted_idx, contact_partner,
                  contact_spring, pair_f)


@cuda.jit
def k_pair_slots(nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx, ctl):
    """Rebuild: the pair index of each list entry a slot owns: row s * cap + k of
    pair_f for its k-th (no scan: every list entry has a row)."""
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0] or not rebuilding(ctl) or ctl[CTL_OVER] != 0:
        return
    pair_slots(s, s * nbr.shape[1], nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx)


@cuda.jit
def k_pair_mirror(radius, margin, nbr, nbr_n, sorted_idx, sorted_x, sorted_body,
                  body_inv_mass, wall_normal, wall_offset, wall_lo, wall_hi, wall_depth,
                  wall_motion, body_start, sphere_inscribed, wall_mask, pidx, ctl):
    """Rebuild, after k_pair_slots: the entries the partner owns
    (contacts.pair_mirror) and the walls in reach (contacts.wall_reach)."""
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0] or not rebuilding(ctl) or ctl[CTL_OVER] != 0:
        return
    pair_mirror(s, nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx)
    wall_reach(s, sorted_idx[s], radius, margin, sorted_x, wall_normal, wall_offset,
               wall_lo, wall_hi, wall_depth, wall_motion, sphere_inscribed, wall_mask)
    if body_start[sorted_body[s]] > ctl[CTL_STEP]:
        wall_mask[s] = 0                    # not emitted yet: no wall either


@cuda.jit
def k_load_pairs(friction, nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass,
                 wall_mask, contact_partner, contact_spring, pair_f, ctl):
    """Rebuild, with friction, after k_pair_mirror: the owned pairs' stretches from the
    history rows into pair_f; the rows keep the walls in reach (contacts.rows_to_pairs)."""
    s = cuda.grid(1)
    n = sorted_idx.shape[0]
    if s >= n or not friction or not rebuilding(ctl) or ctl[CTL_OVER] != 0:
        return
    rows_to_pairs(s, sorted_idx[s], n, nbr, nbr_n, pidx, sorted_idx, sorted_body,
                  body_inv_mass, wall_mask, contact_partner, contact_spring, pair_f)


@cuda.jit
def k_body_patches(cm, cs, motion_now, body_sphere_start, slot_of, ctl):
    """The contact patches (patches.body_patches, one thread per body): each body's
    contacts this step per partner, summed over its spheres in index order."""
    b = cuda.grid(1)
    if b >= cs.body_patch.shape[0] or ctl[CTL_OVER] != 0 or ctl[CTL_IDLE] != 0:
        return
    body_patches(b, 0, 0, cs.nbr_n, False, cm, cs, motion_now, body_sphere_start,
                 slot_of)                                   # (nbr_n: unread)


@cuda.jit
def k_pair_forces(cm, cs, motion_now, parity, ctl):
    """Stages 3-4, first pass (contacts.pair_forces, one thread per sorted slot): each
    contact computed once, by its owner, and each sphere's walls. After an overflow
    in this call (ctl[CTL_OVER]) or once every body sleeps it returns at once.
    cm, cs: layout.ContactModel, ContactScratch (the CPU's packed rows in cs are
    stand-ins here: PAIR_ROWS, WALL_ROWS, LIST_ROWS are off)."""
    s = cuda.grid(1)
    if s >= cs.sorted_idx.shape[0] or ctl[CTL_OVER] != 0 or ctl[CTL_IDLE] != 0:
        return
    pair_forces(s, s + 1, cs.nbr_n, False, cm, cs, motion_now, parity)  # (nbr_n: unread)


@cuda.jit
def k_sphere_forces(cm, cs, ctl):
    """Stage 4, second pass (contacts.sphere_forces): each sphere's sum over its list
    in its partners' index order, then its walls; the CPU's order and sums."""
    s = cuda.grid(1)
    if s >= cs.sorted_idx.shape[0] or ctl[CTL_OVER] != 0 or ctl[CTL_IDLE] != 0:
        return
    sphere_forces(s, s + 1, cs.nbr_n, False, cm, cs)  # (nbr_n: unread)


@cuda.jit
def k_bond_forces(gm, gs, sphere_body, slot_of, sorted_x, sorted_v, body_w, body_inv_mass,
                  body_rest, body_wake, sleep_steps, dt, ctl):
    """Glue, pass 1 (glue.bond_forces, a thread per bond), after k_pair_forces: each
    bond's pairs' forces into glue_f, its shear stretch into bond_shear, its break
    into bond_broken; each thread writes only its bond's rows (the wake flags it
    sets are the same value from any thread). gm, gs: layout.GlueModel,
    GlueScratch. Nothing after an overflow or once every body sleeps."""
    n = cuda.grid(1)
    if n >= gm.bond_body.shape[0] or ctl[CTL_OVER] != 0 or ctl[CTL_IDLE] != 0:
        return
    bond_forces(n, gm, gs, sphere_body, slot_of, sorted_x, sorted_v, body_w, body_inv_mass,
                body_rest, body_wake, sleep_steps, dt)


@cuda.jit
def k_bond_contacts(gm, gs, slot_of, sorted_body, body_inv_mass, nbr, nbr_n, pidx, pair_f,
                    ctl):
    """Glue, pass 2 (glue.bond_contacts, a thread per bond), after k_bond_forces and
    before k_sphere_forces: a holding bond's sphere pairs' contact rows of pair_f
    zeroed (each pair is one bond's: no two threads write a row)."""
    n = cuda.grid(1)
    if n >= gm.bond_body.shape[0] or ctl[CTL_OVER] != 0 or ctl[CTL_IDLE] != 0:
        return
    # the CPU's packed rows (PAIR_ROWS is off here): nbr_n and nbr stand in, unread
    bond_contacts(n, gm, gs, slot_of, sorted_body, body_inv_mass, nbr_n, nbr_n, nbr, nbr,
                  nbr_n, pidx, pair_f)


@cuda.jit
def k_body_glue(n_bodies, gm, gs, sphere_body, sphere_r, ctl):
    """Glue, pass 3 (glue.body_glue_sum, a thread per body), before k_bodies: each
    body's bonds' force and torque into body_glue, in its bonds' order."""
    b = cuda.grid(1)
    if b >= n_bodies or ctl[CTL_OVER] != 0 or ctl[CTL_IDLE] != 0:
        return
    body_glue_sum(b, gm, gs, sphere_body, sphere_r)


@cuda.jit
def k_begin_call(ctl, first_step):
    """Once per ``step`` call (and per probe): rebuild at the first step, and no
    spheres moved, no overflow, no rebuilds yet; the step count just before
    ``first_step`` (k_idle_check counts each step in)."""
    if cuda.grid(1) == 0:
        for j in range(ctl.shape[0]):
            ctl[j] = 0
        ctl[CTL_FORCE] = 1
        ctl[CTL_AWAKE] = 1
        ctl[CTL_STEP] = first_step - 1


@cuda.jit
def k_idle_check(ctl, sleep_steps):
    """First launch of a step (one thread): counts the step in (CTL_STEP); with
    sleeping on and no body awake after the last step's body stage, nothing can
    move any more, so this and the call's remaining steps are no-ops (CTL_IDLE);
    then reset the awake count for this step."""
    if cuda.grid(1) == 0:
        ctl[CTL_STEP] += 1
        if sleep_steps > 0 and ctl[CTL_AWAKE] == 0:
            ctl[CTL_IDLE] = 1
        ctl[CTL_AWAKE] = 0


@cuda.jit
def k_motion(t, dt, motion_kind, motion_v, motion_w, motion_pivot, key_start, key_t, key_p,
             key_q, motion_now, ctl):
    """The prescribed motions (prescribed.motion_row, a thread each) at time ``t``
    [s], or when t < 0 at the step being run (ctl[CTL_STEP] dt)."""
    m = cuda.grid(1)
    if m >= motion_now.shape[0] or (t < 0.0 and ctl[CTL_IDLE] != 0):
        return
    tm = t if t >= 0.0 else ctl[CTL_STEP] * dt
    motion_row(m, tm, motion_kind, motion_v, motion_w, motion_pivot, key_start, key_t, key_p,
               key_q, motion_now)


@cuda.jit
def k_driven(driven_body, body_motion, body_anchor_c, body_anchor_q, motion_now, body_x,
             body_q, body_v, body_w, body_rest, body_still, h):
    """The carried bodies where their motions put them (prescribed.driven_row, a
    thread each; h [s]: velocities as chords of that step, 0 for the tangent),
    after k_motion."""
    k = cuda.grid(1)
    if k >= driven_body.shape[0]:
        return
    driven_row(k, driven_body, body_motion, body_anchor_c, body_anchor_q, motion_now, body_x,
               body_q, body_v, body_w, body_rest, body_still, h)


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
def k_bodies(n_bodies, bm, bs, ctl):
    """Stages 5-8 with sleeping, a thread per body: kernels/bodies.py's body_update,
    the CPU's own; each body awake for the next step adds 1 to ctl[CTL_AWAKE].

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
    r = body_update(b, 0, 0, 0, ctl, False, bm, bs, ctl[CTL_STEP])     # (ctl: unread)
    if r & 1:
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
