"""Each contact computed once, by its owner (kernels/contacts.py), on the CPU target.

The claim is exact: the force law is antisymmetric in IEEE arithmetic, so the
sphere that reads its partner's result back, negated, gets the very bits it
would have computed itself. Asserted here bit for bit against plain Python
(physics.py's formulas, uncompiled) summing each sphere's own contacts in the
kernels' order, on scenes with friction springs, walls, a static mesh and
sleeping bodies; and the bookkeeping behind it (pair indices, the stretches'
trip from the history rows into the pairs and back) exactly.
"""

import numpy as np
import pytest

from bodies import ball_set, box_set
from dempipe.sim import physics
from dempipe.sim.laws import law
from dempipe.sim.kernels.cpu import grid
from dempipe.sim.kernels.cpu import stages as cpu
from dempipe.sim.kernels.pairing import LIST_COLS
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.simulator import Simulator
from dempipe.sim.kernels.pairing import WALL_BITS
from dempipe.sim.kernels.cpu.device import pairs_to_rows, rows_to_pairs
from reference import owner_share, pair_closing, patch_share, patch_sums, wall_closing
from test_cuda import falling_model
from test_neighbours import loose_balls
from test_sleeping import pile

D = 0.01


def slab_and_box():
    """(builder, box shape, material): a static mesh slab of 8×8×1 spheres (top face
    at z = D/2) and a 2×2×2-sphere box shape, both wood."""
    b = ModelBuilder(D)
    slab_set, slab_mesh = box_set(8, 8, 1, D)
    ss, mesh = box_set(2, 2, 2, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("wood", density=700, restitution=0.3, friction=0.5))
    b.add_static_mesh("slab", slab_mesh, slab_set, m)
    return b, s, m


def boxes_on_static_slab():
    """Four 2×2×2-sphere boxes dropped 1 mm onto a static mesh slab (8×8 spheres),
    spinning: friction springs against static spheres."""
    b, s, m = slab_and_box()
    pos = [[x, y, 1.6 * D] for x in (-0.02, 0.015) for y in (-0.015, 0.02)]
    b.add_bodies("boxes", s, m, pos, angular_velocities=[[0.0, 0.0, 3.0]] * 4)
    return b.finalize(fps=24, n_frames=2)


def pressed_boxes_woken():
    """Three 2×2×2-sphere boxes pressed side by side in a tight box, asleep within a
    few steps, and a fourth dropped spinning onto two of them: pairs whose owner
    sleeps while the partner moves, pairs of two sleepers, and sleepers woken."""
    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("wood", density=700, restitution=0.3, friction=0.5))
    b.add_bodies("boxes", s, m, [[(i - 1) * 1.999 * D, 0.0, 0.0100 + 0.00002 * i]
                                 for i in range(3)])
    b.add_bodies("drop", s, m, [[-1.0 * D, 0.0, 0.06]], angular_velocities=[[0, 0, 4.0]])
    b.add_box([-3.0 * D + 0.0003 * D, -2 * D, 0], [3.0 * D - 0.0003 * D, 2 * D, 0.1],
              material=m)
    return b.finalize(fps=24, n_frames=6, sleep=(0.05, 1.0, 0.003))


def scenes():
    """(name, model, steps): friction springs against spheres, walls, planes; a
    static slab; a pile part asleep; sleeping pairs."""
    return [("loose balls in a box", loose_balls(), 40),
            ("box onto slab", falling_model(), 30),
            ("pile, part asleep", pile(sleep=(0.05, 1.0, 0.02), n_frames=6), 1000),
            ("boxes on a static slab", boxes_on_static_slab(), 600),
            ("pressed boxes asleep, one dropped on them", pressed_boxes_woken(), 3000)]


def owner_stretch(state, i, j):
    """The remembered stretch of the contact of sphere i with sphere or wall code j
    (a wall: number of spheres + its index) seen from i: from its owner's row (the
    State's form), negated when the owner is sphere j; 0 if none."""
    pairs = ((i, j, 1.0), (j, i, -1.0)) if j < state.contact_partner.shape[0] else \
        ((i, j, 1.0),)
    for a, b, sign in pairs:
        hit = np.nonzero((state.contact_partner[a] >> 1) == b + 1)[0]
        if hit.size:
            return sign * state.contact_spring[a, hit[0]]
    return np.zeros(3)


def own_forces(model, state, be):
    """(force, torque) on each sphere [N], [N m], each sphere computing every one of
    its contacts itself, in the kernels' order: partners by index, then the
    walls' sum; positions and velocities as the backend's stage 1 left them."""
    ns = model.n_spheres
    x = np.empty((ns, 3))
    v = np.empty((ns, 3))
    x[be.sorted_idx] = be.sorted_x
    v[be.sorted_idx] = be.sorted_v
    W = be.body_w
    d = model.diameter
    rest = state.body_rest
    asleep = (rest >= model.sleep_steps) if model.sleep_steps > 0 else np.zeros_like(rest, bool)
    f = np.zeros((ns, 3))
    t = np.zeros((ns, 3))
    tr = np.zeros((ns, 3))
    patches = patch_sums(model, x, v, rest)      # a pair takes its owner body's share
    nb_all = model.body_mass.shape[0]
    for i in range(ns):
        bi = model.sphere_body[i]
        if model.body_inv_mass[bi] == 0.0 or asleep[bi]:
            continue
        fx = fy = fz = tx = ty = tz = qx = qy = qz = 0.0
        for j in range(ns):
            bj = model.sphere_body[j]
            if bj == bi:
                continue
            r = x[j] - x[i]
            dist2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
            if dist2 >= d * d and not pair_closing(r, dist2, v[j] - v[i], d, model.dt,
                                                        model.onset_speed):
                continue
            mi, mj = model.body_material[bi], model.body_material[bj]
            k, eta, kt, ks = law(model.contact_law).contact_coefficients(
                model.pair_k[mi, mj], model.pair_damp, mi, mj,
                model.body_inv_mass[bi] + model.body_inv_mass[bj], model.kt_ratio,
                model.ks_ratio, model.dt, d - np.sqrt(dist2))
            share = owner_share(model, patches, i, j)
            k, eta, kt, ks = k * share, eta * share, kt * share, ks * share
            mu = model.pair_mu[mi, mj]
            s0 = owner_stretch(state, i, j)
            out = physics.sphere_pair_force(
                r[0], r[1], r[2], np.sqrt(dist2), d, *(v[j] - v[i]), *(W[bi] + W[bj]),
                k, eta, kt, ks, mu, *s0, model.dt, model.onset_speed)
            fx += out[0]
            fy += out[1]
            fz += out[2]
            if mu > 0.0:
                tx += out[3]
                ty += out[4]
                tz += out[5]
            mu_r = model.pair_rolling[mi, mj]
            if model.features.rolling and mu_r > 0.0:     # its own side of the couple
                n, n2 = (r, dist2) if dist2 > 0 else (np.array([0.0, 0.0, 1.0]), 1.0)
                rt = physics.rolling_torque(
                    *(W[bi] - W[bj]), *n, n2, out[0] * n[0] + out[1] * n[1] + out[2] * n[2],
                    mu_r, model.body_inv_radius[bi] + model.body_inv_radius[bj],
                    model.onset_speed)
                qx += rt[0]
                qy += rt[1]
                qz += rt[2]
        wf = [0.0] * 6
        wq = [0.0] * 3
        for w in range(model.n_walls):
            n = model.wall_normal[w]
            dist = n[0] * x[i, 0] + n[1] * x[i, 1] + n[2] * x[i, 2] - model.wall_offset[w]
            if ((dist >= d / 2 and not wall_closing(n, dist, v[i], d, model.dt, model.onset_speed))
                    or dist <= -model.wall_depth[w]):
                continue
            if np.any(x[i] < model.wall_lo[w]) or np.any(x[i] > model.wall_hi[w]):
                continue
            mi, mj = model.body_material[bi], model.wall_material[w]
            k, eta, kt, ks = law(model.contact_law).contact_coefficients(
                model.pair_k[mi, mj], model.pair_damp, mi, mj, model.body_inv_mass[bi],
                model.kt_ratio, model.ks_ratio, model.dt, d / 2 - dist)
            share = patch_share(patches, bi, nb_all + w)
            k, eta, kt, ks = k * share, eta * share, kt * share, ks * share
            mu = model.pair_mu[mi, mj]
            s0 = owner_stretch(state, i, ns + w)
            out = physics.sphere_wall_force(*(-n), d / 2 - dist, d / 2, *v[i], *W[bi],
                                            0.0, 0.0, 0.0, k, eta, kt, ks, mu, *s0, model.dt,
                                            model.onset_speed)
            for c in range(3):
                wf[c] += out[c]
                if mu > 0.0:
                    wf[3 + c] += out[3 + c]
            if model.features.rolling and model.pair_rolling[mi, mj] > 0.0:
                rt = physics.rolling_torque(
                    *W[bi], *n, 1.0, out[0] * n[0] + out[1] * n[1] + out[2] * n[2],
                    model.pair_rolling[mi, mj], model.body_inv_radius[bi], model.onset_speed)
                for c in range(3):
                    wq[c] += rt[c]
        f[i] = (fx + wf[0], fy + wf[1], fz + wf[2])
        t[i] = (tx + wf[3], ty + wf[4], tz + wf[5])
        if model.features.rolling:
            tr[i] = (qx + wq[0], qy + wq[1], qz + wq[2])
    return f, t, tr


@pytest.mark.slow
@pytest.mark.parametrize("case", range(5))
def test_each_contact_once_gives_the_forces_of_each_sphere_computing_its_own(case):
    name, model, steps = scenes()[case]
    be = Simulator(model).backend
    st = model.initial_state()
    be.step(st, steps)
    assert (st.contact_partner != 0).sum() >= 4, name        # stretches in use
    be.probe(st)
    f, t, tr = own_forces(model, st, be)
    assert np.abs(f).max() > 0, name
    np.testing.assert_array_equal(be.sphere_f, f, err_msg=name)     # bit for bit
    np.testing.assert_array_equal(be.sphere_t, t, err_msg=name)
    if model.features.rolling:                      # rolling torques, limited per body later
        np.testing.assert_array_equal(be.sphere_tr, tr, err_msg=name)
    if case in (2, 4):
        asleep = st.asleep(model.sleep_steps)[: model.n_bodies]
        assert 0 < asleep.sum(), "no body asleep: the sleeping paths were not exercised"
    if case == 4:                                   # a sleeper owns a pair with a mover
        assert be.pair_start[-1] > 0
        assert not asleep.all()


@pytest.mark.parametrize("case", range(5))
def test_pair_indices_pair_each_entry_with_its_owner(case):
    name, model, steps = scenes()[case]
    be = Simulator(model).backend
    st = model.initial_state()
    be.step(st, steps)
    be.probe(st)
    idx, body, inv = be.sorted_idx, be.sorted_body, model.body_inv_mass
    rows = []
    for s in range(model.n_spheres):
        for e in range(be.nbr_n[s]):
            t, p = be.nbr[s, e], be.pidx[s, e]
            if inv[body[t]] == 0.0 or idx[s] < idx[t]:      # s owns the pair
                assert be.pair_start[s] <= p < be.pair_start[s + 1], name
                assert be.list_e[be.pair_e[p], 0] == t, name  # the row knows its partner
                assert be.list_start[s] <= be.pair_e[p] < be.list_start[s + 1], name
                rows.append(p)
            else:                                            # t owns it: t lists s
                back = list(be.nbr[t, : be.nbr_n[t]]).index(s)
                assert p == -(be.pidx[t, back] + 1), name
    assert sorted(rows) == list(range(be.pair_start[-1])), name     # each row once
    for s in range(model.n_spheres):             # the lists packed for the second pass
        q, n = be.list_start[s], be.nbr_n[s]
        assert be.list_start[s + 1] == q + n, name
        np.testing.assert_array_equal(be.list_e[q:q + n, 0], be.nbr[s, :n], err_msg=name)
        np.testing.assert_array_equal(be.list_e[q:q + n, 1], be.pidx[s, :n], err_msg=name)
    if case == 3:                                            # pairs with static spheres
        assert any(inv[body[t]] == 0.0 for s in range(model.n_spheres)
                   for t in be.nbr[s, : be.nbr_n[s]])
    static = inv[body] == 0.0
    assert np.all(be.nbr_n[static] == 0)                     # a static sphere owns nothing


def test_rows_into_pairs_over_the_busy_and_held_slots_as_over_every_slot():
    # Within a call the rebuild reads only the rows that can hold anything: the busy
    # slots' and those the last rebuild left busy (held). A held row whose slot has
    # nothing in reach now is emptied, as the pass over every slot empties it.
    name, model, steps = scenes()[2]
    be = Simulator(model).backend
    st = model.initial_state()
    be.step(st, steps)
    be.probe(st)
    n_busy = cpu.stage_busy(be.nbr_n, be.wall_mask, be.sorted_idx, be.sorted_body,
                            model.body_inv_mass, be.chunk_n, be.busy, be.sphere_f, be.sphere_t,
                            be.sphere_tr)
    idle = np.setdiff1d(np.arange(model.n_spheres), be.busy[:n_busy])
    assert idle.size, name
    hp = st.contact_partner[be.sorted_idx]
    hs = st.contact_spring[be.sorted_idx]
    hp[idle[0], 0] = (1 << 1) | 1          # a stale entry in a row left out now
    hs[idle[0], 0] = (1e-4, 2e-4, 3e-4)
    held = np.r_[idle[:1], be.busy[:n_busy]].astype(np.int32)
    runs = []
    for listed in (False, True):
        p, s_ = hp.copy(), hs.copy()
        pair_f = np.zeros_like(be.pair_f)
        wall_s = np.zeros_like(be.wall_s)
        if listed:
            grid.stage_rows_to_pairs_busy(be.busy, n_busy, held, held.shape[0], be.nbr,
                                          be.nbr_n, be.pidx, be.sorted_idx, be.sorted_body,
                                          model.body_inv_mass, be.wall_mask, p, s_, pair_f,
                                          be.wall_start, wall_s)
        else:
            grid.stage_rows_to_pairs(be.nbr, be.nbr_n, be.pidx, be.sorted_idx, be.sorted_body,
                                     model.body_inv_mass, be.wall_mask, p, s_, pair_f,
                                     be.wall_start, wall_s)
        runs.append((p, s_, pair_f, wall_s))
    assert not runs[1][0][idle[0]].any() and not runs[1][1][idle[0]].any()
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("case", range(5))
def test_stretches_go_into_the_pairs_and_back_unchanged(case):
    # The State's history rows (canonical: pairs by partner index, then walls) into
    # the pairs of a fresh build and back give the same rows, bit for bit.
    name, model, steps = scenes()[case]
    be = Simulator(model).backend
    st = model.initial_state()
    be.step(st, steps)
    assert (st.contact_partner != 0).any()
    be.probe(st)                       # lists, pair indices and wall reach at these positions
    hp = st.contact_partner[be.sorted_idx]
    hs = st.contact_spring[be.sorted_idx]
    pair_f = np.zeros_like(be.pair_f)
    grid.stage_rows_to_pairs(be.nbr, be.nbr_n, be.pidx, be.sorted_idx, be.sorted_body,
                             model.body_inv_mass, be.wall_mask, hp, hs, pair_f, be.wall_start,
                             be.wall_s)
    assert np.all(hp[hp != 0] >> 1 > model.n_spheres), name   # the rows keep the walls only
    # back over the busy slots only, as within a call: the others' rows are empty now
    n_busy = cpu.stage_busy(be.nbr_n, be.wall_mask, be.sorted_idx, be.sorted_body,
                            model.body_inv_mass, be.chunk_n, be.busy, be.sphere_f, be.sphere_t,
                            be.sphere_tr)
    assert n_busy > 0, name
    grid.stage_pairs_to_rows_busy(be.busy, n_busy, be.nbr, be.nbr_n, be.pidx, be.sorted_idx,
                                  hp, hs, pair_f, be.wall_mask, be.wall_start, be.wall_s)
    partner = np.empty_like(hp)
    spring = np.empty_like(hs)
    partner[be.sorted_idx] = hp
    spring[be.sorted_idx] = hs
    np.testing.assert_array_equal(partner, st.contact_partner, err_msg=name)
    np.testing.assert_array_equal(spring, st.contact_spring, err_msg=name)


def test_a_pair_keeps_one_stretch_in_its_owners_row():
    # Each remembered sphere-sphere contact appears once in the State, in the row of
    # its owner (the lower index, or the dynamic sphere against a static one).
    n_pairs = 0
    for name, model, steps in scenes():
        st = model.initial_state()
        Simulator(model).backend.step(st, steps)
        ns = model.n_spheres
        seen = set()
        for i, h in zip(*np.nonzero(st.contact_partner)):
            j = (int(st.contact_partner[i, h]) >> 1) - 1
            if j >= ns:
                continue                                    # a wall
            n_pairs += 1
            key = (min(i, j), max(i, j))
            assert key not in seen, name                    # not also in the partner's row
            seen.add(key)
            static_j = model.body_inv_mass[model.sphere_body[j]] == 0.0
            assert i < j or static_j, name
    assert n_pairs > 20


def many_walls_model(n_floors, far_boxes=0):
    """Two spinning balls pushed (gravity along -x and -z) into a corner made of
    ``n_floors`` copies of the floor plane and one side wall: the first ball touches
    n_floors + 1 walls and its partner, more than its 12-slot row holds when
    n_floors is 11. ``far_boxes`` closed boxes (six walls each) far above and
    aside, which nothing ever touches."""
    b = ModelBuilder(D, gravity=(-9.81, 0, -9.81))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    # (no rolling resistance: the rattle below was timed without it)
    m = b.add_material(Material("m", density=1000, restitution=0.3, friction=0.5,
                                rolling_friction=0.0))
    b.add_bodies("balls", s, m, [[0, 0, 0.5 * D], [1.0 * D, 0, 0.5 * D]],
                 angular_velocities=[[0, 0, 5.0], [0, 0, 5.0]])
    for _ in range(n_floors):
        b.add_plane([0, 0, 0], [0, 0, 1], m)
    b.add_plane([-0.5 * D, 0, 0], [1, 0, 0], m)
    for k in range(far_boxes):
        b.add_box([1.0 + k, 1.0, 1.0], [1.5 + k, 1.5, 1.5], open_top=False, material=m)
    return b.finalize(fps=60, n_frames=2)


@pytest.mark.parametrize("n_floors", [10, 11])
def test_a_full_history_row_does_not_depend_on_how_steps_are_split(n_floors):
    # With 11 floors the first ball remembers 12 walls and its pair: one more than its
    # row holds. The pair's stretch is then forgotten at every step (walls first),
    # in one call of 150 steps as in three of 50 (found by review: it was kept within
    # a call and dropped at each call's end). (The ball rattles in its corner of 12
    # coincident walls: 150 steps end with it touching.)
    model = many_walls_model(n_floors)
    ref = model.initial_state()
    Simulator(model).backend.step(ref, 150)
    assert (ref.contact_partner[0] != 0).sum() == 12
    be = Simulator(model).backend
    st = model.initial_state()
    for _ in range(3):
        be.step(st, 50)
    for name in ("body_x", "body_q", "body_P", "body_L", "contact_partner", "contact_spring"):
        assert np.array_equal(getattr(st, name), getattr(ref, name)), name


def test_rows_to_pairs_puts_each_marked_wall_at_its_column():
    # While stepping, the j-th wall a slot's mask marks keeps its stretch at column j
    # of the slot's history row (contacts.wall_column), found with no search; walls
    # not marked, and spheres, leave the row. pairs_to_rows sorts them back.
    n_spheres, cap = 2, 12
    walls = (1 << 1) | (1 << 3) | (1 << 4)         # columns: wall 1 -> 0, 3 -> 1, 4 -> 2
    hp = np.zeros((1, cap), dtype=np.int32)
    hs = np.zeros((1, cap, 3))
    code = lambda w: ((n_spheres + w + 1) << 1) | 1     # noqa: E731 (touched at parity 1)
    for col, c, s in ((0, code(4), 4.0), (1, code(0), 9.0), (2, (2 << 1) | 1, 7.0),
                      (5, code(1), 1.0)):
        hp[0, col] = c
        hs[0, col] = (s, -s, 2 * s)
    empty = np.zeros((1, 4), dtype=np.int32)
    args = (empty, np.zeros(1, dtype=np.int32), empty, np.arange(n_spheres, dtype=np.int32),
            np.zeros(n_spheres, dtype=np.int32), np.ones(1))
    rows_to_pairs(0, 0, n_spheres, *args, np.array([walls], dtype=np.int64), hp, hs,
                      np.zeros((1, 10)))
    want_p = np.zeros(cap, dtype=np.int32)
    want_p[0], want_p[2] = code(1), code(4)
    np.testing.assert_array_equal(hp[0], want_p)
    np.testing.assert_array_equal(hs[0, 0], (1.0, -1.0, 2.0))
    np.testing.assert_array_equal(hs[0, 2], (4.0, -4.0, 8.0))
    assert not hs[0, [1] + list(range(3, cap))].any()
    nbr, nbr_n, pidx = empty, np.zeros(1, dtype=np.int32), empty
    pairs_to_rows(0, 0, nbr, nbr_n, pidx, args[3], hp, hs, np.zeros((1, 10)))
    want_p[:] = 0
    want_p[0], want_p[1] = code(1), code(4)
    np.testing.assert_array_equal(hp[0], want_p)
    np.testing.assert_array_equal(hs[0, 1], (4.0, -4.0, 8.0))


def test_walls_beyond_a_mask_give_the_same_motion():
    # With more walls than a mask names (WALL_BITS), every slot tests every wall and
    # finds its walls' stretches by a search of its row instead of at their columns.
    # Eleven closed boxes far away (66 walls that never touch) must change nothing.
    near, far = many_walls_model(1), many_walls_model(1, far_boxes=11)
    assert far.n_walls > WALL_BITS >= near.n_walls
    assert far.dt == near.dt
    states = []
    for model in (near, far):
        st = model.initial_state()
        be = Simulator(model).backend
        be.step(st, 150)
        be.probe(st)
        assert (be.wall_mask == -1).all() == (model is far)
        be.step(st, 150)
        states.append(st)
    assert (states[0].contact_partner != 0).sum() >= 3          # both walls and the pair
    for name in ("body_x", "body_q", "body_P", "body_L"):
        assert np.array_equal(getattr(states[0], name), getattr(states[1], name)), name


def balls_on_the_floor(n_side):
    """n_side² one-sphere balls side by side on a floor with friction, sliding and
    spinning: every sphere rests on the floor and bumps into its neighbours."""
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.3, friction=0.5))
    ix, iy = np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="ij")
    pos = np.stack([ix.ravel() * 1.0001 * D, iy.ravel() * 1.0001 * D,
                    np.full(n_side * n_side, 0.5 * D)], -1)
    rng = np.random.default_rng(3)
    b.add_bodies("balls", s, m, pos, velocities=rng.normal(0, 0.05, (len(pos), 3)) * [1, 1, 0],
                 angular_velocities=rng.normal(0, 5.0, (len(pos), 3)))
    b.add_box([-D, -D, 0], [n_side * D, n_side * D, 1.0], material=m)
    return b.finalize(fps=60, n_frames=2)


def three_ways(model, steps, give_room):
    """The States after ``steps`` steps of ``model`` from a backend that grows its
    packed rows when a rebuild needs more (returned too, with the room its
    ``give_room`` array had to start with), from one that give_room(backend) gave
    room first, and from calls of one step; (states, grown backend, first room)."""
    states = []
    for mode in ("grow", "room", "one step per call"):
        be = Simulator(model).backend
        if mode == "grow":
            grown, room0 = be, give_room(be, False)
        else:
            give_room(be, mode == "room")
        st = model.initial_state()
        for _ in range(steps if mode == "one step per call" else 1):
            be.step(st, 1 if mode == "one step per call" else steps)
        states.append(st)
    for st in states[1:]:
        for name in ("body_x", "body_q", "body_P", "body_L", "contact_partner",
                     "contact_spring"):
            assert np.array_equal(getattr(st, name), getattr(states[0], name)), name
    return states, grown, room0


def test_packed_wall_rows_grow_and_change_nothing():
    # While stepping, the CPU keeps the walls' stretches in packed rows (contacts.py
    # WALL_ROWS), one per marked wall, allocated for an eighth of the spheres. Here
    # every sphere touches the floor, so the first rebuild finds too few rows: the
    # step stops, the backend grows them and redoes it. Against a backend that had
    # room from the start, and against calls of one step (each rebuilds, copying
    # the stretches out of the history rows and back), the State is the same.
    model = balls_on_the_floor(12)

    def room(be, give):
        if give:
            be.wall_s = np.zeros((4 * model.n_spheres, 4))
        return be.wall_s.shape[0]

    runs, be, rows0 = three_ways(model, 120, room)
    assert be.wall_start[-1] >= model.n_spheres               # a row per sphere at least
    assert rows0 < model.n_spheres < be.wall_s.shape[0]        # so they grew
    walls = runs[0].contact_partner >> 1 > model.n_spheres
    assert walls.sum() >= 0.9 * model.n_spheres                # the floor's stretches kept
    assert np.abs(runs[0].contact_spring[walls]).max() > 0.0
    # a wall entry not touched at a step is forgotten (nothing sleeps here), so each
    # one left was touched at the last, step 119: its parity bit says so
    assert np.all(runs[0].contact_partner[walls] & 1 == 119 & 1)


def test_packed_lists_grow_and_change_nothing():
    # The second pass reads each slot's list packed (contacts.py LIST_ROWS), with room
    # for LIST_PER_SPHERE entries a sphere to start with. A cubic lattice of balls
    # lists six neighbours inside: the first rebuild finds too little room, the step
    # stops, the backend grows it and redoes the step. Against a backend with room
    # from the start and calls of one step, the State is the same.
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.3, friction=0.5))
    g = np.arange(6) * 1.0001 * D
    pos = np.stack(np.meshgrid(g, g, g + 0.5 * D, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(5)
    b.add_bodies("balls", s, m, pos, velocities=rng.normal(0, 0.05, (len(pos), 3)))
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=60, n_frames=2)

    def room(be, give):
        if give:
            be.list_e = np.zeros((16 * model.n_spheres, LIST_COLS), dtype=np.int32)
        return be.list_e.shape[0]

    runs, be, rows0 = three_ways(model, 100, room)
    assert rows0 < be.list_start[-1] <= be.list_e.shape[0]     # the lists' room grew
    assert (runs[0].contact_partner != 0).sum() >= 50          # stretches to compare


def test_a_body_lifted_off_its_contacts_between_calls_falls_freely():
    # The CPU's contact passes visit only the slots with a neighbour or a wall in reach
    # (stages.stage_busy), and set every other sphere's force to zero at the rebuild.
    # A State edited between calls (a box lifted off the static slab it rests on,
    # another off the floor) leaves spheres whose last force was their share of the
    # resting load and whose lists are now empty: they must feel nothing, so both
    # boxes fall freely, as the integrator's closed form (semi-implicit Euler: a drop
    # of g dt² n (n + 1) / 2 after n steps) says to the last few bits.
    b, s, m = slab_and_box()
    b.add_plane([0.0, 0.0, -0.5], [0.0, 0.0, 1.0], material=m)
    b.add_bodies("boxes", s, m, [[0.0, 0.0, 1.5 * D], [0.3, 0.0, -0.5 + D]])
    model = b.finalize(fps=24, n_frames=2)              # sleeping off: they keep resting
    be = Simulator(model).backend
    state = model.initial_state()
    be.step(state, int(0.2 / model.dt))
    mass = model.body_mass[: model.n_bodies].max()
    assert np.abs(state.body_P).max() < 1e-3 * mass      # resting: P [kg m/s]
    assert np.abs(be.sphere_f[:, 2]).max() > 0.1 * 9.81 * mass   # spheres hold them up [N]
    boxes = slice(0, model.n_bodies)                    # (the slab stays)
    state.body_x[boxes, 2] += 0.05
    state.body_P[boxes] = 0.0
    state.body_L[boxes] = 0.0
    lifted = state.body_x[boxes, 2].copy()
    n = int(0.03 / model.dt)                            # 30 ms: 4.4 mm, inside the lift
    be.step(state, n)
    drop = 9.81 * model.dt ** 2 * n * (n + 1) / 2
    np.testing.assert_allclose(lifted - state.body_x[boxes, 2], drop, rtol=1e-6)
