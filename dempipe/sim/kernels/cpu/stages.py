"""CPU target: the paper's eight stages as numba njit/prange drivers.

Each stage is one parallel loop; the formulas come from physics.py compiled
with ``numba.njit(inline="always")``. ``run_steps`` loops over steps inside
compiled code, so a frame of hundreds of steps costs one Python call.

Determinism: every parallel loop writes only its own index (gather, no
scatter, no atomics); the sorts of a rebuild are stable (integer counts, each
bucket filled in sphere order); each body sums its spheres in index order. The
output is bit-identical for any thread count.
"""

from __future__ import annotations

import types

import numba
from numba import prange

from dempipe.sim.kernels import contacts, glue, patches
from dempipe.sim.kernels.bodies import body_update
from dempipe.sim.kernels.prescribed import driven_row, motion_row
from dempipe.sim.kernels.compile import compile_formulas, invalidate_stale_cache, specialize
from dempipe.sim.kernels.layout import (
    FLAGS, BodyModel, BodyScratch, ContactModel, ContactScratch)
from dempipe.sim.kernels.contacts import CONTACT_CHUNK
from dempipe.sim.kernels.neighbours import REST_STEPS, SKIN_GROW_BELOW, SKIN_SHRINK_ABOVE
from dempipe.sim.kernels.cpu.broadphase import stage_near_others
from dempipe.sim.kernels.cpu.device import adapt_skin, shrink_skin, static_body
from dempipe.sim.kernels.cpu.spheres import (
    listed_end, sphere_state, stage_body_velocities, stage_driven, stage_listed_from,
    stage_motion, stage_note_built, stage_spheres, stage_spheres_busy, stage_spheres_sorted)
from dempipe.sim.kernels.cpu.grid import (
    slot_busy, stage_grid_gather, stage_grid_keep, stage_grid_sort, stage_history_in,
    stage_history_out, stage_history_to_slots, stage_history_to_spheres, stage_mark_partners,
    stage_neighbours, stage_neighbours_marked, stage_pairs, stage_pairs_to_rows_busy,
    stage_rest_count, stage_rest_half, stage_rows_to_pairs, stage_rows_to_pairs_busy,
    stage_slot_marks, stage_unsort, stage_wall_reach)
# Read by the functions of spheres.py, contacts.py, bodies.py and prescribed.py, which
# kernels() compiles with this module's globals (compile.specialize):
from dempipe.sim.kernels.cpu.spheres import body_moved  # noqa: F401
from dempipe.sim.kernels.cpu.device import (  # noqa: F401
    angular_velocity, cell_coord, cell_hash, cell_key, quat_rotate, slot_place, slot_store,
    sphere_kinematics)
from dempipe.sim.kernels.contacts import CLOSE_REACH2, RIM_TIE, RING_TIE  # noqa: F401
from dempipe.sim.kernels.pairing import UNPAIRED  # noqa: F401
from dempipe.sim.kernels.cpu.device import (  # noqa: F401
    HIST_BY_SLOT, LIST_ROWS, PAIR_ROWS, WALL_ROWS, anchor_local, anchor_state,
    anchor_surface, body_step, carried_state, chord_velocity, contact_coefficients, entry_range,
    history_recall, history_store, rest_steps, rolling_scale, rolling_torque,
    sphere_pair_force, sphere_wall_force, sqrt, closing, glue_force)

invalidate_stale_cache(__file__)
invalidate_stale_cache(contacts.__file__)   # pair_forces, sphere_forces: cached under its name
invalidate_stale_cache(patches.__file__)
invalidate_stale_cache(glue.__file__)

# ---------------------------------------------------------------------------
# Specialization. The stage drivers below are plain functions reading the flags
# FRICTION, ROTATION, SLEEPING, WALLS as globals; ``kernels(flags)`` compiles
# one variant per flag set (compile.specialize), each with its own numba disk
# cache file. The values here (all on) are the general kernel's. Features off
# are compiled out; features on still check their runtime data (``friction``,
# ``sleep_steps`` > 0, per-pair mu, the wall count), so the general kernel on
# a scene that does not use a feature gives the specialized kernel's frames bit
# for bit (tests/sim/test_specialize.py).
#
# TORQUE_NOTE: a contact without friction pushes along the line of centres and
# has no torque about the sphere's centre; physics.sphere_pair_force's
# (dist/2) n × f rounds to ±1 ulp instead of 0 for a third of the contacts, which
# would spin a one-sphere ball. The kernels add a contact's own torque only
# when its mu > 0, so a frictionless ball keeps L = 0 exactly whichever variant
# runs it; the variants without friction never read sphere_t, and write it only
# as the zeros of a slot with nothing in reach (stage_busy).
# ---------------------------------------------------------------------------

# Feature flags the stage drivers are compiled for: layout.FLAGS, in ``kernels()``'s order.
FRICTION = True
ROTATION = True
SLEEPING = True
WALLS = True
# Glue bonds (kernels/glue.py): not one of FLAGS but its own axis, as the law is
# (kernels(flags, law, glue)): only a scene with bonds compiles their passes.
GLUE = False
# Inscribed tori (contacts.inscribed_wall): likewise, only a model with them.
INSCRIBED = False



#: A sleeping pile's contact passes visit only the slots with work left in them
#: (stage_active) once at least this share of the bodies is quiet; below it
#: finding them would cost about what it saves.
QUIET_SHARE = 0.5

#: Steps at least between two searches for the active slots (stage_active): the
#: search is a pass over the busy slots, about what a step with few sleepers spends
#: on them. Between searches the list stays valid while bodies only fall quiet (it
#: holds more than needed); a body that wakes sends the passes back to every busy
#: slot until the next search. (Searching at every change cost 0.91x on a pile
#: waking and settling, half of it quiet; benchmarks/sleeping_pile.py --wake 1800.)
SEARCH_GAP = 8

#: A rebuild forced by spheres moving keeps the slots, and searches again only the
#: lists that can have changed, when at most this share of the spheres moved since
#: the lists were built (and no static sphere moved, and the skin need not narrow:
#: run_steps): a pile settling but for a few bodies then pays for their lists, not
#: for every sphere's (stage_slot_marks). Above it the slots are sorted again as at
#: any rebuild.
KEEP_SLOTS_SHARE = 0.25

#: At a rebuild that keeps the slots, a body's lists are searched again when one of
#: its spheres has moved this share of half the skin since they were built; the
#: others keep theirs, and where they were built (stage_slot_marks). So a pile with
#: a few bodies still rolling across it re-lists those bodies and their partners,
#: not the pile, each time one of them forces a rebuild.
KEEP_MOVE = 0.5

#: With this share of the dynamic bodies at rest but rebuilt while they moved (a pile
#: come to rest between rebuilds), a rebuild comes once SKIN_SHRINK_ABOVE steps have
#: gone without one, to narrow their rebuild distances (stage_rest_half).
REST_SHARE = 0.25

#: Rebuilds in a row that may keep the slots: then one sorts them again, so bodies
#: that moved far get slots next to their new neighbours (memory order).
KEEP_SLOTS_RUN = 8


@numba.njit(error_model="numpy", cache=True)
def pack_blocks(work, block_n, n_blocks):
    """Move each block's entries (block c's block_n[c] first entries of work[c *
    CONTACT_CHUNK ..]) down into one run at the front of ``work``, in block order;
    returns its length. Serial: the same list for any thread count."""
    n = 0
    for c in range(n_blocks):
        k0 = c * CONTACT_CHUNK
        for k in range(k0, k0 + block_n[c]):
            work[n] = work[k]               # (n <= k: in place, front to back)
            n += 1
    return n


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_busy(nbr_n, wall_mask, sorted_idx, sorted_body, body_inv_mass, chunk_n, busy,
               sphere_f, sphere_t, sphere_tr):
    """After a rebuild: busy[:n] (n returned) = the sorted slots of dynamic bodies with
    a neighbour in their list or a wall in reach, in slot order; every other sphere's
    force, torque and rolling torque set to zero. Until the next rebuild those others
    have nothing to sum (contacts.sphere_forces would write the same zeros) and nothing
    to compute, so the contact passes visit ``busy`` only: a falling or loosely
    packed pile, where most lists are empty, pays for its contacts, not for its
    spheres. The same State bit for bit (the CUDA simulator's, which visits every
    slot: tests/sim/test_cuda.py)."""
    n_slots = nbr_n.shape[0]
    n_blocks = (n_slots + CONTACT_CHUNK - 1) // CONTACT_CHUNK
    for c in prange(n_blocks):
        n = 0
        for s in range(c * CONTACT_CHUNK, min(n_slots, (c + 1) * CONTACT_CHUNK)):
            if slot_busy(s, nbr_n, wall_mask, sorted_body, body_inv_mass):
                busy[c * CONTACT_CHUNK + n] = s
                n += 1
            else:
                i = sorted_idx[s]
                for a in range(3):
                    sphere_f[i, a] = 0.0
                    sphere_t[i, a] = 0.0
                    sphere_tr[i, a] = 0.0
        chunk_n[c] = n
    return pack_blocks(busy, chunk_n, n_blocks)


@numba.njit(inline="always", cache=True)
def body_quiet(b, body_inv_mass, body_rest, body_still, sleep_steps):
    """Whether body b will do nothing in the contact passes of the next step: a
    static collider (not a carried one moving: rest count -1), or a body asleep
    that also slept through the step just done (body_still), so that its pass-1
    and pass-2 results are those already stored."""
    return (static_body(body_inv_mass[b]) and body_rest[b] >= 0) or (
        body_rest[b] >= sleep_steps and body_still[b] != 0)


@numba.njit(error_model="numpy", parallel=True, cache=True)
def stage_active(busy, n_busy, sorted_body, nbr, nbr_n, body_inv_mass, body_rest, body_still,
                 sleep_steps, chunk_n, active, wall_mask, moving_walls):
    """After the body stage: active[:n] (n returned) = the busy slots (stage_busy's
    busy[:n_busy]) the next step's contact passes must visit, in slot order.

    A busy slot must be visited unless its body is quiet (body_quiet) and so is the
    body of every partner in its list, and no moving wall may reach it. Such a
    slot's visit writes nothing: pass 1 at a sleeper computes only pairs with a
    moving partner (and its walls not at all; its trim of the pairs it remembers was
    done when it was last visited, asleep among the same sleepers), pass 2 writes
    the zero force it wrote at its last visit. So the active slots give the same
    State bit for bit as the busy ones (tests/sim/test_sleeping.py), and a pile
    where most bodies sleep costs what its moving part costs, not its size. Valid
    for the steps after it until a rebuild (new lists) or a quiet body wakes; bodies
    that fall quiet meanwhile only make the list longer than needed (run_steps)."""
    n_blocks = (n_busy + CONTACT_CHUNK - 1) // CONTACT_CHUNK
    for c in prange(n_blocks):
        n = 0
        for k in range(c * CONTACT_CHUNK, min(n_busy, (c + 1) * CONTACT_CHUNK)):
            s = busy[k]
            bi = sorted_body[s]
            visit = not body_quiet(bi, body_inv_mass, body_rest, body_still, sleep_steps) \
                or (wall_mask[s] & moving_walls) != 0   # a moving wall may reach it
            e = 0
            while not visit and e < nbr_n[s]:
                visit = not body_quiet(sorted_body[nbr[s, e]], body_inv_mass, body_rest,
                                       body_still, sleep_steps)
                e += 1
            if visit:
                active[c * CONTACT_CHUNK + n] = s
                n += 1
        chunk_n[c] = n
    return pack_blocks(active, chunk_n, n_blocks)


def stage_patches(cm, cs, motion_now, body_sphere_start, slot_of, work, n_work, work_from):
    """The contact patches (patches.body_patches): each body's contacts this step
    per partner, summed over its spheres in index order, for every body with a slot
    in work[:n_work] (run_steps': the busy or the active slots; body b's run of them
    starts at work_from[b]: stage_listed_from).

    A slot left out either has nothing in reach (not busy: stage_busy) or is of a
    quiet body among quiet partners (not active: stage_active): body_patches would
    skip each of its pairs and walls. So the pass goes over the body's listed slots
    only, and the row of a body with none is emptied without it. The rows are the
    same bit for bit (a body's slots are consecutive, in its spheres' order:
    stage_grid_sort)."""
    body_patch = cs.body_patch
    last = body_patch.shape[1] - 1
    for b in prange(body_patch.shape[0]):
        i0 = body_sphere_start[b]
        k0 = k1 = 0
        if i0 < body_sphere_start[b + 1]:
            k0 = work_from[b]
            k1 = listed_end(k0, slot_of[i0] + body_sphere_start[b + 1] - i0, work, n_work)
        if k0 == k1:
            if body_patch[b, 0, 0] != 0.0 or body_patch[b, last, 0] != 0.0:
                for c in range(last + 1):   # (a row nothing was added to is empty)
                    body_patch[b, c, 0] = 0.0
                    body_patch[b, c, 1] = 0.0
                    body_patch[b, c, 2] = 0.0
            continue
        body_patches(b, k0, k1, work, True, cm, cs, motion_now, body_sphere_start,
                     slot_of)


def stage_contacts(cm, cs, motion_now, parity, work, n_work):
    """Stages 3-4, first pass: the force of each contact, computed once, by the
    sphere that owns it (kernels/contacts.py: pair_forces), and each sphere's
    walls, in parallel over blocks of CONTACT_CHUNK of the slots work[:n_work]
    (run_steps': those with a neighbour or a wall, or only those a sleeping pile
    leaves to do: stage_busy, stage_active).

    With friction, each contact's tangential spring lives in its owner's history
    row (hist_partner, hist_spring: the State's contact_partner, contact_spring
    with rows in sorted-slot order, see stage_history_to_slots): a contact found
    again keeps its stretch, a new one starts at zero, and one not touched this
    step (``parity``) is forgotten. Only a slot's own rows are written: gather.
    A sphere of a moving body (rest count 0) that touches a sleeping body flags
    it to wake (body_wake). cm, cs: layout.ContactModel, ContactScratch;
    motion_now: control.Drive's; parity: step & 1.
    """
    for c in prange((n_work + CONTACT_CHUNK - 1) // CONTACT_CHUNK):
        pair_forces(c * CONTACT_CHUNK, min(n_work, (c + 1) * CONTACT_CHUNK), work, True, cm,
                    cs, motion_now, parity)


def stage_sums(cm, cs, work, n_work):
    """Stage 4, second pass (contacts.sphere_forces): each sphere gathers the
    forces on itself, in its list's order (its partners' index order), then its
    walls'; writes sphere_f, sphere_t (torque about the sphere's centre) and
    sphere_overlap (largest overlap this step, [m]). Static and sleeping spheres
    feel no force. Over work[:n_work], as stage_contacts."""
    for c in prange((n_work + CONTACT_CHUNK - 1) // CONTACT_CHUNK):
        sphere_forces(c * CONTACT_CHUNK, min(n_work, (c + 1) * CONTACT_CHUNK), work, True, cm,
                      cs)


def stage_glue(gm, gs, sphere_body, slot_of, sorted_x, sorted_v, body_w, body_inv_mass,
               body_rest, body_wake, sleep_steps, dt):
    """The bonds' forces, each bond by one thread (kernels/glue.py bond_forces);
    returns how many broke this step (an integer sum: any thread count)."""
    broke = 0
    for n in prange(gm.bond_body.shape[0]):
        broke += bond_forces(n, gm, gs, sphere_body, slot_of, sorted_x, sorted_v,  # noqa: F821
                             body_w,
                             body_inv_mass, body_rest, body_wake, sleep_steps, dt)
    return broke


def stage_glue_contacts(gm, gs, slot_of, sorted_body, body_inv_mass, pair_start, pair_e,
                        list_e, nbr, nbr_n, pidx, pair_f):
    """A holding bond's sphere pairs are not also contacts (glue.bond_contacts)."""
    for n in prange(gm.bond_body.shape[0]):
        bond_contacts(n, gm, gs, slot_of, sorted_body, body_inv_mass, pair_start,  # noqa: F821
                      pair_e, list_e, nbr, nbr_n, pidx, pair_f)


def stage_glue_bodies(n_bodies, gm, gs, sphere_body, sphere_r):
    """Each body's bonds summed into body_glue (glue.body_glue_sum)."""
    for b in prange(n_bodies):
        body_glue_sum(b, gm, gs, sphere_body, sphere_r)  # noqa: F821 (specialize's)


def stage_bodies(n_bodies, bm, bs, step, slot_of, busy, n_busy, busy_from):
    """Stages 5-8: sum forces and torques (eq. 15-16), update P, L, X, q (eq. 2-10).
    Each body sums its busy slots only (busy[:n_busy], stage_busy's; body b's from
    busy_from[b]): every other sphere's force and torques are zero until the next
    rebuild.

    With sleeping (sleep_steps > 0): a body slower than (v_sleep, w_sleep) for
    sleep_steps steps in a row falls asleep (P = L = 0, no integration) until a
    moving body touches it (body_wake, set by the contact stage). Returns (bodies
    awake for the next step, bodies that woke from quiet, bodies quiet, bodies
    that became quiet: body_update), integer sums: the same for any thread count.
    bm, bs: layout.BodyModel, BodyScratch.
    """
    awake = 0
    woke = 0
    quiet = 0
    calmed = 0
    body_sphere_start = bm.body_sphere_start
    for b in prange(n_bodies):
        i0 = body_sphere_start[b]
        s0 = slot_of[i0] if i0 < body_sphere_start[b + 1] else 0
        k0 = busy_from[b]
        k1 = listed_end(k0, s0 + body_sphere_start[b + 1] - i0, busy, n_busy)
        r = body_update(b, k0, k1, s0, busy, True, bm, bs, step)
        awake += r & 1
        woke += (r >> 1) & 1
        quiet += (r >> 2) & 1
        calmed += r >> 3
    return awake, woke, quiet, calmed


@numba.njit(error_model="numpy", parallel=True, cache=True)
def held_rows(src, n, index, keep, dst):
    """dst[:n] = src[:n] when ``keep``, else index[src[:n]] (a slot's sphere before a
    new sort, then that sphere's new slot): at a rebuild within a call, where the
    rows the last rebuild left busy are (stage_rows_to_pairs_busy). dst may be src."""
    for k in prange(n):
        dst[k] = src[k] if keep else index[src[k]]


def run_steps(n_steps, first_step, grid, quiet_share, keep_share, keep_move, rest_skin,
              broadphase_spheres, model, state, scratch, drive, gm, gs):
    """Advance up to ``n_steps`` steps of the eight stages; everything stays in
    compiled code. Returns (steps done, steps computed). Done is fewer than
    n_steps only when a rebuild found a neighbour list longer than nbr holds
    (nbr_n has the counts), or more pairs than pair_f has rows (pair_start[-1]
    is the count): the caller grows them and calls again, that step not yet
    begun. Computed is fewer than done when every body fell asleep.

    Stages 2-3 (grid, sort, 27-cell search) run only to rebuild the neighbour
    lists: at the first step, when a sphere has moved its body's rebuild distance
    since (half the skin, or rest_skin/2 d for a body at rest: stage_rest_half),
    and when a wide skin, or a REST_SHARE of the bodies at rest with wider
    distances than that, has gone SKIN_SHRINK_ABOVE steps without one. The
    skin (skin_ctl[0], [d]) adapts at each rebuild to how many steps came since
    the last (neighbours.adapt_skin, from skin_ctl[4] up to skin_ctl[2]); it
    changes which pairs are listed, never a force (the frames do not depend on
    it). skin_ctl[1]
    carries the steps since the last rebuild from call to call, skin_ctl[3] counts
    the rebuilds. After each rebuild the contact passes visit only the slots with
    a neighbour or a wall in reach (stage_busy): the others' forces are zero until
    the next, written once.

    A rebuild forced by a move keeps the slots (span_ctl[2] counts those) when at
    most keep_share of the spheres belong to bodies that moved keep_move × half the
    skin since their lists were built and no static sphere moved ("few"), and the
    skin is the smallest or the rebuild came fewer than SKIN_GROW_BELOW steps after
    the last; a rebuild that few bodies force later than that, with a wider skin,
    sorts every slot again at a skin one step narrower (neighbours.shrink_skin):
    where few bodies move, kept rebuilds are cheap and a wide skin only adds listed
    pairs to every step. When keeping, only those bodies' lists are searched again,
    from where they are now (stage_slot_marks), then the lists that held one of their spheres, then the
    lists their new lists reach (stage_mark_partners), each from where it was
    built. Every list then holds each sphere whose build position (built_x) is
    within the reach (1 + skin) d of its own, and each sphere is less than half the
    skin from its build position until the next rebuild, so every pair that can
    touch is listed, as after a full rebuild; lists also hold pairs a full rebuild
    would leave out, which exert no force. The forces are summed in each list's
    partner index order, so the frames are a full rebuild's; the slots' order
    never enters a force. At most KEEP_SLOTS_RUN such rebuilds in a row
    (keep_share 0: none; keep_move 0: only the bodies that moved at all re-list).

    With sleeping, once every body is asleep and no wall moves the remaining steps
    are skipped: a step then changes nothing (a sleeping body moves only when a
    moving body or wall touches it, and none is left), so skipping them gives the
    same State bit for bit, at no cost. The scratch arrays keep the last step done.
    And once at least quiet_share of the bodies are quiet, the contact passes
    visit only the busy slots stage_active finds work in (active): searched at
    most every SEARCH_GAP steps, after a rebuild (new lists), a wake (a woken
    body's slots may be missing: every busy slot until the next search) or once a
    quarter of the bodies not quiet at the last search have become quiet (the
    list holds more than needed until then); exact too. span_ctl counts the steps
    run so (0) and the searches (1).

    The arguments: model (layout.StepModel: what the step reads of the Model),
    state (layout.StepState: the State's arrays), scratch (layout.Scratch: the
    backend's), drive (control.Drive): the prescribed motions, evaluated at the start of
    each step (stage_motion, stage_driven) and once more at the end, so the State
    holds the carried bodies where they are at its time; and the emitters' start
    steps (a call never spans one: the backend splits it there). gm, gs
    (layout.GlueModel, GlueScratch): the glue bonds, read only with GLUE.
    """
    # the structured arguments (layout.StepModel, StepState, Scratch; control.Drive),
    # under the names the stages take them by
    (dt, onset_speed, diameter, n_bodies, gravity, sphere_body, sphere_offset, body_sphere_start,
     body_mass, body_inv_mass, body_inv_inertia, body_material, pair_k, pair_damp, pair_mu,
     kt_ratio, ks_ratio, friction, sleep_steps, v_sleep, w_sleep, wall_normal, wall_offset,
     wall_lo, wall_hi, wall_depth, wall_material, rolling, pair_rolling,
     body_inv_radius, sphere_inscribed) = model
    (body_x, body_q, body_P, body_L, body_rest, contact_partner, contact_spring) = state
    (hist_partner, hist_spring, body_wake, body_still, built_bx, built_bq, seen_bx, seen_bq,
     body_reach, body_box, offset_t, body_v, body_w, sphere_x, sphere_v,
     sphere_r, sphere_key, sphere_hash, bucket_start, bucket_blocks, body_key, grid_slot,
     sorted_idx, slot_of, sorted_x, sorted_v, sorted_body, grid_idx, grid_x, grid_key,
     grid_body, built_x, nbr, nbr_n, pidx, pair_start, pair_e, pair_f, list_start, list_e,
     wall_mask, wall_start, wall_s, wall_f, sphere_f, sphere_t, sphere_tr, sphere_overlap,
     body_patch, skin_ctl, chunk_n, busy, active, span_ctl, slot_mark, state_rows, busy_from,
     active_from, slot_touch, sphere_engaged, body_half) = scratch
    # what the contact passes take (layout.ContactModel, ContactScratch): the same arrays
    cm = ContactModel(diameter, dt, onset_speed, body_inv_mass, body_material, pair_k,
                      pair_damp, pair_mu, kt_ratio, ks_ratio, friction, sleep_steps,
                      wall_normal, wall_offset, wall_lo, wall_hi, wall_depth, wall_material,
                      drive.wall_motion, rolling, pair_rolling, body_inv_radius,
                      sphere_inscribed)
    cs = ContactScratch(nbr, nbr_n, pidx, pair_start, pair_e, wall_start, wall_s, list_start,
                        list_e, sorted_idx, sorted_x, sorted_v, sorted_body, body_w, body_rest,
                        body_wake, wall_mask, hist_partner, hist_spring, pair_f, wall_f,
                        sphere_f, sphere_t, sphere_tr, sphere_overlap, body_patch, body_q,
                        slot_touch, sphere_engaged)
    bm = BodyModel(dt, gravity, body_sphere_start, body_mass, body_inv_mass, body_inv_inertia,
                   sleep_steps, v_sleep, w_sleep, drive.body_start, rolling)
    bs = BodyScratch(sphere_f, sphere_t, sphere_tr, sphere_r, body_x, body_q, body_P, body_L,
                     body_rest, body_wake, body_still, gs.body_glue, sphere_engaged)
    if n_steps <= 0:
        return 0, 0  # nothing sorted yet: the unsort below would scramble the State's rows
    sphere_engaged[:] = 1   # the first step visits every slot (contacts.engaged)
    skin = skin_ctl[0]
    since = skin_ctl[1]
    inv_cell = 1.0 / ((1.0 + skin) * diameter)     # neighbours.cell_size, at this skin
    half_skin = 0.5 * skin * diameter
    rest_half = 0.5 * rest_skin * diameter      # a body at rest's (stage_rest_half)
    rebuild = True
    moved = False
    computed = 0
    n_busy = 0              # busy[:n_busy]: the slots with work (stage_busy)
    held = active           # at a rebuild: the rows the last one left busy (held_rows)
    n_held = 0
    n_active = 0
    active_ok = False       # active[:n_active] hold this step's work (stage_active)
    rebuilt = True
    since_search = SEARCH_GAP
    calmed_since = 0        # bodies that became quiet since the last search
    quiet_then = 0          # and how many were quiet at it
    driven = drive.motion_now.shape[0] > 0
    body_start = drive.body_start
    n_slots = slot_of.shape[0]
    kept_run = 0            # rebuilds in a row that kept the slots
    # with friction: after the call's first re-sort, only the State's history rows of
    # state_rows[:n_state_rows] can hold anything (stage_history_out)
    rows_known = False
    n_state_rows = 0
    for step in range(first_step, first_step + n_steps):
        computed += 1
        stage_body_velocities(n_bodies, body_P, body_L, body_q, body_inv_mass, body_inv_inertia,
                              body_v, body_w)
        if driven:
            stage_motion(step * dt, drive.motion_kind, drive.motion_v, drive.motion_w,
                         drive.motion_pivot, drive.key_start, drive.key_t, drive.key_p,
                         drive.key_q, drive.motion_now)
            if stage_driven(drive.driven_body, drive.body_motion, drive.body_anchor_c,
                            drive.body_anchor_q, drive.motion_now, body_x, body_q, body_v,
                            body_w, body_rest, body_still, dt) > 0:
                active_ok = False   # a carried body that held still moves: every busy slot
        if not rebuild:
            rebuild = stage_spheres_busy(body_sphere_start, slot_of, sphere_body,
                                         sphere_offset, body_x, body_q, body_v, body_w, dt,
                                         body_still, body_inv_mass, built_bx, built_bq,
                                         body_reach, seen_bx, seen_bq, busy, n_busy,
                                         busy_from, built_x, body_half, sorted_x, sorted_v,
                                         sphere_r) > 0
            moved = rebuild
            if not rebuild and since > SKIN_SHRINK_ABOVE and (
                    skin > skin_ctl[4] or (
                        int(since) % SKIN_SHRINK_ABOVE == 1 and REST_SHARE * n_bodies <=
                        stage_rest_count(body_v, body_w, body_reach, body_inv_mass,
                                         body_start, step, rest_half, REST_STEPS * dt,
                                         body_half))):
                rebuild = True      # at rest with a wide skin, or wide rebuild distances
        keep = False
        few = False
        if rebuild and moved and keep_share > 0.0 and kept_run < KEEP_SLOTS_RUN:
            stage_spheres_sorted(slot_of, sphere_body, sphere_offset, body_x, body_q, body_v,
                                 body_w, dt, sorted_x, sorted_v, sphere_r)
            n_moved, n_static_moved = stage_slot_marks(
                body_sphere_start, slot_of, sorted_x, built_x, body_inv_mass, nbr, nbr_n,
                (keep_move * half_skin) ** 2, body_half, slot_mark)
            few = n_static_moved == 0 and n_moved <= keep_share * n_slots
            keep = few and (skin <= skin_ctl[4] or since < SKIN_GROW_BELOW)
        if rebuild:
            if keep:
                kept_run += 1
            else:
                kept_run = 0
                if few:
                    skin = shrink_skin(skin, skin_ctl[4])
                else:
                    skin = adapt_skin(skin, since, skin_ctl[4], skin_ctl[2], moved)
                inv_cell = 1.0 / ((1.0 + skin) * diameter)
                half_skin = 0.5 * skin * diameter
            since = 0.0
            moved = False
            if FRICTION and friction and step > first_step:
                # the histories back into their rows (slot order), and to sphere order
                # for a new sort; which rows can hold anything (held: the busy ones, as
                # spheres until the new sort gives their slots)
                stage_pairs_to_rows_busy(busy, n_busy, nbr, nbr_n, pidx, sorted_idx,
                                         hist_partner, hist_spring, pair_f, wall_mask,
                                         wall_start, wall_s)
                n_held = n_busy
                held_rows(busy, n_busy, sorted_idx, keep, held)
                if not keep:
                    if rows_known:          # only the rows that can hold anything
                        stage_history_out(busy, n_busy, state_rows, n_state_rows, slot_of,
                                          sorted_idx, nbr_n, wall_mask, sorted_body,
                                          body_inv_mass, hist_partner, hist_spring,
                                          contact_partner, contact_spring)
                    else:
                        stage_history_to_spheres(sorted_idx, hist_partner, hist_spring,
                                                 contact_partner, contact_spring)
                    for k in range(n_held):
                        state_rows[k] = held[k]
                    n_state_rows = n_held
            if keep:                            # the slots stay: only the marked lists
                stage_grid_keep(built_x, sorted_body, slot_of, inv_cell, grid, sphere_key,
                                sphere_hash, bucket_start, bucket_blocks, grid_idx, grid_slot,
                                grid_x, grid_key, grid_body)
                over = stage_neighbours_marked(1, 2, slot_mark, diameter, skin, grid,
                                               bucket_start, grid_idx, grid_x, grid_key,
                                               grid_body, grid_slot, sorted_idx, built_x,
                                               sorted_body, body_inv_mass, built_x, nbr,
                                               nbr_n, body_start, step)
                if over == 0:
                    stage_mark_partners(nbr, nbr_n, slot_mark)
                    over = stage_neighbours_marked(3, 3, slot_mark, diameter, skin, grid,
                                                   bucket_start, grid_idx, grid_x, grid_key,
                                                   grid_body, grid_slot, sorted_idx, built_x,
                                                   sorted_body, body_inv_mass, built_x, nbr,
                                                   nbr_n, body_start, step)
            else:
                stage_spheres(sphere_body, sphere_offset, body_x, body_q, body_v, body_w, dt,
                              inv_cell, grid, sphere_x, sphere_v, sphere_r, sphere_key,
                              sphere_hash)
                stage_near_others(broadphase_spheres, (1.0 + skin) * diameter, offset_t,
                                  body_x, body_q, body_sphere_start, body_reach, body_box,
                                  body_inv_mass, body_start, step, sphere_hash)
                stage_grid_sort(sphere_hash, body_x, inv_cell, grid, body_sphere_start,
                                bucket_start, bucket_blocks, body_key, sorted_idx, slot_of,
                                grid_idx, grid_slot)
                if FRICTION and friction and step > first_step:
                    held_rows(held, n_held, slot_of, False, held)    # spheres to slots
                stage_grid_gather(sorted_idx, grid_idx, bucket_start[grid[5]], sphere_x,
                                  sphere_v, sphere_key, sphere_body, sorted_x, sorted_v,
                                  sorted_body, grid_x, grid_key, grid_body)
                if FRICTION and friction:
                    if rows_known:
                        stage_history_in(state_rows, n_state_rows, slot_of, contact_partner,
                                         contact_spring, hist_partner, hist_spring)
                    else:
                        stage_history_to_slots(sorted_idx, contact_partner, contact_spring,
                                               hist_partner, hist_spring)
                        rows_known = step > first_step
                over = stage_neighbours(diameter, skin, grid, bucket_start, grid_idx, grid_x,
                                        grid_key, grid_body, grid_slot, sorted_idx, sorted_x,
                                        sorted_body, body_inv_mass, built_x, nbr, nbr_n,
                                        body_start, step, sphere_hash)
            stage_rest_half(body_v, body_w, body_reach, body_inv_mass, body_sphere_start,
                            slot_of, slot_mark, keep, half_skin, rest_half, REST_STEPS * dt,
                            body_half)
            if over > 0 or \
                    stage_pairs(nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass,
                                pair_start, pidx, pair_e, pair_f.shape[0], list_start,
                                list_e) > 0 or \
                    (WALLS and stage_wall_reach(diameter, body_half, built_x, wall_normal,
                                                wall_offset, wall_lo, wall_hi, wall_depth,
                                                wall_mask, wall_start,
                                                hist_partner.shape[1] if FRICTION and friction
                                                else 0, wall_s.shape[0], drive.wall_motion,
                                                sorted_body, body_start, step,
                                                sorted_idx, sphere_inscribed) > 0):
                if keep and FRICTION and friction:  # the State's histories current
                    stage_history_to_spheres(sorted_idx, hist_partner, hist_spring,
                                             contact_partner, contact_spring)
                skin_ctl[0] = skin              # the redo keeps this build's skin
                skin_ctl[1] = since
                return step - first_step, step - first_step
            skin_ctl[3] += 1.0
            if keep:
                span_ctl[2] += 1
            n_busy = stage_busy(nbr_n, wall_mask, sorted_idx, sorted_body, body_inv_mass,
                                chunk_n, busy, sphere_f, sphere_t, sphere_tr)
            stage_listed_from(body_sphere_start, slot_of, busy, n_busy, busy_from)
            stage_note_built(body_x, body_q, built_bx, built_bq, seen_bx, seen_bq,
                             body_sphere_start, slot_of, slot_mark, keep)
            active_ok = False                   # new lists (and slots)
            rebuilt = True
            if FRICTION and friction and step == first_step:     # rows from the State
                stage_rows_to_pairs(nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass,
                                    wall_mask, hist_partner, hist_spring, pair_f, wall_start,
                                    wall_s)
            elif FRICTION and friction:
                stage_rows_to_pairs_busy(busy, n_busy, held, n_held, nbr, nbr_n, pidx,
                                         sorted_idx, sorted_body, body_inv_mass, wall_mask,
                                         hist_partner, hist_spring, pair_f, wall_start,
                                         wall_s)
            rebuild = False
        work = active if active_ok else busy
        n_work = n_active if active_ok else n_busy
        work_from = active_from if active_ok else busy_from
        if active_ok:
            span_ctl[0] += 1
        stage_patches(cm, cs, drive.motion_now, body_sphere_start, slot_of, work, n_work,
                      work_from)
        stage_contacts(cm, cs, drive.motion_now, step & 1, work, n_work)
        if GLUE:
            stage_glue(gm, gs, sphere_body, slot_of, sorted_x, sorted_v, body_w,
                       body_inv_mass, body_rest, body_wake, sleep_steps, dt)
            stage_glue_contacts(gm, gs, slot_of, sorted_body, body_inv_mass, pair_start,
                                pair_e, list_e, nbr, nbr_n, pidx, pair_f)
        stage_sums(cm, cs, work, n_work)
        if GLUE:
            stage_glue_bodies(n_bodies, gm, gs, sphere_body, sphere_r)
        awake, woke, quiet, calmed = stage_bodies(n_bodies, bm, bs, step, slot_of, busy,
                                                  n_busy, busy_from)
        since_search += 1
        calmed_since += calmed
        if rebuilt or woke > 0:
            active_ok = False   # (at the first step: body_still was stale, rebuilt is set)
        if SLEEPING and sleep_steps > 0 and quiet >= quiet_share * n_bodies and quiet > 0:
            if since_search >= SEARCH_GAP and (
                    not active_ok or 4 * calmed_since >= n_bodies - quiet_then):
                n_active = stage_active(busy, n_busy, sorted_body, nbr, nbr_n, body_inv_mass,
                                        body_rest, body_still, sleep_steps, chunk_n, active,
                                        wall_mask, drive.moving_walls)
                stage_listed_from(body_sphere_start, slot_of, active, n_active, active_from)
                span_ctl[1] += 1
                active_ok = True
                since_search = 0
                calmed_since = 0
                quiet_then = quiet
        else:
            active_ok = False
        rebuilt = False
        since += 1.0
        if SLEEPING and sleep_steps > 0 and awake == 0 and drive.moving_walls == 0:
            break                               # all asleep, no wall moving: nothing changes
    skin_ctl[0] = skin
    skin_ctl[1] = since
    if driven:                  # the carried bodies where they are at the State's time
        stage_motion((first_step + n_steps) * dt, drive.motion_kind, drive.motion_v,
                     drive.motion_w, drive.motion_pivot, drive.key_start, drive.key_t,
                     drive.key_p, drive.key_q, drive.motion_now)
        stage_driven(drive.driven_body, drive.body_motion, drive.body_anchor_c,
                     drive.body_anchor_q, drive.motion_now, body_x, body_q, body_v, body_w,
                     body_rest, body_still, 0.0)
    # every sphere where the last step saw it (stage_spheres_busy placed the busy ones)
    stage_spheres_sorted(slot_of, sphere_body, sphere_offset, seen_bx, seen_bq, body_v, body_w,
                         dt, sorted_x, sorted_v, sphere_r)
    stage_unsort(sorted_idx, sorted_x, sphere_x)
    if FRICTION and friction:
        stage_pairs_to_rows_busy(busy, n_busy, nbr, nbr_n, pidx, sorted_idx, hist_partner,
                                 hist_spring, pair_f, wall_mask, wall_start, wall_s)
        stage_history_to_spheres(sorted_idx, hist_partner, hist_spring, contact_partner,
                                 contact_spring)
    return n_steps, computed


_STAGES = (stage_body_velocities, motion_row, driven_row, stage_motion, stage_driven,
           sphere_state, stage_spheres,
           stage_spheres_sorted, stage_spheres_busy,
           contacts.wall_gap, contacts.pair_ended, contacts.inscribed_wall, contacts.engaged,
           patches.patch_add, patches.body_patches,
           patches.patch_share, patches.pair_share, stage_patches,
           contacts.pair_forces, contacts.sphere_forces, stage_contacts, stage_sums,
           glue.bond_forces, glue.bond_contacts, glue.body_glue_sum, stage_glue,
           stage_glue_contacts, stage_glue_bodies, body_update, stage_bodies, run_steps)
# error_model="numpy" (CUDA's): a float division is not checked for a zero divisor
# on every "/" of the passes. The same bits; a division by zero would give inf or
# nan instead of an exception, which the Simulator's check of every frame reports.
_JITS = {
    "stage_body_velocities": numba.njit(error_model="numpy", parallel=True, cache=True),
    "motion_row": numba.njit(inline="always", cache=True),
    "driven_row": numba.njit(inline="always", cache=True),
    "stage_motion": numba.njit(error_model="numpy", cache=True),
    "stage_driven": numba.njit(error_model="numpy", cache=True),
    "sphere_state": numba.njit(inline="always", cache=True),
    "stage_spheres": numba.njit(error_model="numpy", parallel=True, cache=True),
    "stage_spheres_sorted": numba.njit(error_model="numpy", parallel=True, cache=True),
    "stage_spheres_busy": numba.njit(error_model="numpy", parallel=True, cache=True),
    "wall_gap": numba.njit(inline="always", cache=True),
    "pair_ended": numba.njit(inline="always", cache=True),
    "inscribed_wall": numba.njit(inline="always", cache=True),
    "engaged": numba.njit(inline="always", cache=True),
    "patch_add": numba.njit(inline="always", cache=True),
    "body_patches": numba.njit(error_model="numpy", cache=True),
    "patch_share": numba.njit(inline="always", cache=True),
    "pair_share": numba.njit(inline="always", cache=True),
    "stage_patches": numba.njit(error_model="numpy", parallel=True, cache=True),
    "pair_forces": numba.njit(error_model="numpy", cache=True),
    "sphere_forces": numba.njit(error_model="numpy", cache=True),
    "stage_contacts": numba.njit(error_model="numpy", parallel=True, cache=True),
    "stage_sums": numba.njit(error_model="numpy", parallel=True, cache=True),
    "bond_forces": numba.njit(error_model="numpy", cache=True),
    "bond_contacts": numba.njit(inline="always", cache=True),
    "body_glue_sum": numba.njit(error_model="numpy", cache=True),
    "stage_glue": numba.njit(error_model="numpy", parallel=True, cache=True),
    "stage_glue_contacts": numba.njit(error_model="numpy", parallel=True, cache=True),
    "stage_glue_bodies": numba.njit(error_model="numpy", parallel=True, cache=True),
    "body_update": numba.njit(error_model="numpy", cache=True),
    "stage_bodies": numba.njit(error_model="numpy", parallel=True, cache=True),
    "run_steps": numba.njit(error_model="numpy", cache=True),
}
_VARIANTS: dict = {}


def kernels(flags, law: str = "linear", glue: bool = False,
            inscribed: bool = False) -> "types.SimpleNamespace":
    """The stage drivers compiled for ``flags`` (friction, rotation, sleeping, walls)
    and the contact ``law`` (laws.LAWS; the module's formulas are the linear law's,
    another law's are compiled and overlaid), with the glue passes when ``glue``
    (kernels/glue.py) and the wall contacts through inscribed tori when ``inscribed``
    (contacts.inscribed_wall: a model with tori, of surface or lattice sets; without,
    the sphere's own contact is compiled alone), created on first use; numba compiles
    each (or loads it from its disk cache) at its first call."""
    flags = tuple(bool(f) for f in flags)
    key = flags if law == "linear" else (flags, law)
    if glue:
        key = (key, "glue")
    if inscribed:
        key = (key, "inscribed")
    if key not in _VARIANTS:
        tag = "".join(f"{n[0].upper()}{int(f)}" for n, f in zip(FLAGS, flags))
        consts = {n.upper(): f for n, f in zip(FLAGS, flags)}
        consts["GLUE"] = bool(glue)
        consts["INSCRIBED"] = bool(inscribed)
        if law != "linear":
            tag += f"_{law}"
            fl = compile_formulas(numba.njit(inline="always", cache=False), law)
            consts.update(sphere_pair_force=fl.sphere_pair_force,
                          sphere_wall_force=fl.sphere_wall_force,
                          contact_coefficients=fl.contact_coefficients, closing=fl.closing)
        if glue:
            tag += "_glue"
        if inscribed:
            tag += "_ins"
        _VARIANTS[key] = specialize(_STAGES, _JITS, consts, tag, globals())
    return _VARIANTS[key]


