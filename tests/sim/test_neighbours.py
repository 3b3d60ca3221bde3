"""Verlet neighbour lists (kernels/neighbours.py) on the CPU target.

The lists are an optimisation of stages 2-3, never of the physics: each list must
hold every partner within its reach, and the frames must not depend on when the
lists are rebuilt (a list is summed in its partners' index order, and a listed
pair farther apart than d adds nothing). Both are asserted exactly here.
"""

import numpy as np

from bodies import ball_set, box_set, slider_past_drifting_row
from dempipe.sim.kernels.neighbours import SKIN, SKIN_MAX, adapt_skin, cell_size
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.simulator import Simulator
from dempipe.sim.kernels.cpu.backend import CpuBackend
from test_simulation import cluster_model

D = 0.01


def loose_balls(n=300, seed=3, box=0.06):
    """One-sphere bodies scattered at random (some touching, many just outside reach)
    in a box, thrown in every direction, no gravity: pairs at every distance."""
    rng = np.random.default_rng(seed)
    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.8, friction=0.3))
    pos = rng.uniform(D, box - D, size=(n, 3))
    keep = [0]
    for i in range(1, n):      # no deep overlaps at the start (they would explode)
        if np.min(np.linalg.norm(pos[keep] - pos[i], axis=1)) > 0.9 * D:
            keep.append(i)
    pos = pos[keep]
    b.add_bodies("balls", s, m, pos, velocities=rng.normal(size=pos.shape) * 0.3)
    b.add_box([0, 0, 0], [box, box, box], material=m)
    return b.finalize(fps=60, n_frames=6)


def ball_lattice(n=5, pitch=1.05, seed=4):
    """n³ one-sphere bodies on a cubic lattice pitch d apart (inside every list's reach,
    not touching), jostled: each ball starts with up to 6 listed partners."""
    rng = np.random.default_rng(seed)
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.5))
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pos = (g + 1.0) * pitch * D
    b.add_bodies("balls", s, m, pos, velocities=rng.normal(size=pos.shape) * 0.2)
    b.add_box([0, 0, 0], [(n + 1) * pitch * D] * 2 + [0.2], material=m)
    return b.finalize(fps=60, n_frames=6)


def dense_blocks(n=4, pitch=0.3, seed=6):
    """n bodies whose spheres are packed 0.3 d apart (as a surface set's shell is),
    7 x 7 x 3 each, a little turned and thrown at each other in a box, no gravity:
    rows of cells holding dozens of one body's spheres, next to another body's."""
    import types
    rng = np.random.default_rng(seed)
    b = ModelBuilder(D, gravity=(0, 0, 0))
    g = np.stack(np.meshgrid(*[np.arange(k) for k in (7, 7, 3)], indexing="ij"), -1)
    c = (g.reshape(-1, 3) - [3.0, 3.0, 1.0]) * pitch * D
    a, bb, cc = 6 * pitch * D + D, 6 * pitch * D + D, 2 * pitch * D + D
    ss = types.SimpleNamespace(centers=c, com=np.zeros(3), volume=a * bb * cc,
                               inertia=a * bb * cc / 12 * np.diag([bb * bb + cc * cc,
                                                                   a * a + cc * cc,
                                                                   a * a + bb * bb]),
                               diameter=D)
    _, mesh = box_set(3, 3, 1, D)
    s = b.add_shape("block", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.3))
    # facing layers 1.1 d apart (in reach, not touching), closing at 0.6 m/s
    pos = np.array([[0.0, 0.0, 0.0], [2.9 * D, 0.2 * D, 0.1 * D], [0.1 * D, 2.9 * D, -0.2 * D],
                    [0.3 * D, 0.2 * D, 1.7 * D]])[:n]
    turn = rng.normal(size=(n, 3)) * 0.01
    q = np.c_[np.ones(n), turn]
    b.add_bodies("blocks", s, m, pos + 0.04, rotations=q / np.linalg.norm(q, axis=1)[:, None],
                 velocities=-(pos - pos.mean(0)) / np.linalg.norm(pos - pos.mean(0), axis=1,
                                                                  keepdims=True) * 0.3,
                 angular_velocities=rng.normal(size=(n, 3)) * 5.0)
    b.add_box([0, 0, 0], [0.08, 0.08, 0.08], material=m)
    return b.finalize(fps=60, n_frames=6)


def brute_force_lists(backend, model):
    """For each sorted slot: the set of slots of spheres of other bodies within the
    lists' reach, by testing every pair (the oracle for the 27-cell search)."""
    x = backend.sorted_x
    body = backend.sorted_body
    reach2 = cell_size(model.diameter) ** 2
    d2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    near = (d2 < reach2) & (body[:, None] != body[None, :])
    static = model.body_inv_mass[body] == 0
    near[static, :] = False
    return near


def test_lists_hold_every_partner_within_reach_in_index_order():
    # the cells of the rebuild grid are (1 + SKIN) d: with cells of d, partners
    # between d and (1 + SKIN) d two cells away were missed (energy grew in the
    # elastic gas of test_extremes)
    # (with the broadphase on whatever the bodies' size: test_broadphase)
    for model in (loose_balls(), ball_lattice(), cluster_model(n=20), dense_blocks()):
        be = CpuBackend(model)
        be.broadphase_spheres = 0
        st = model.initial_state()
        for k in range(4):
            if k:
                be.step(st, max(1, model.steps_per_frame // 3))
            be.probe(st)                     # rebuilds the lists from this state
            near = brute_force_lists(be, model)
            for s in range(model.n_spheres):
                lst = be.nbr[s, : be.nbr_n[s]]
                assert set(lst.tolist()) == set(np.flatnonzero(near[s]).tolist()), s
                idx = be.sorted_idx[lst]
                assert np.all(np.diff(idx) > 0), s       # partners' index order


def z_order(c):
    """Place on the Z-order curve of integer cell coordinates (x, y, z): bit k of
    x, y, z to bits 3k, 3k+1, 3k+2 (the reference for kernels.cpu.device.morton_key)."""
    key = 0
    for bit in range(21):
        for axis in range(3):
            key |= ((int(c[axis]) >> bit) & 1) << (3 * bit + axis)
    return key


def test_slots_follow_the_bodies_and_the_grid_holds_every_sphere_once():
    # The CPU's slots (stage_grid_sort): bodies in Z-order of the cell their centre is
    # in (ties in body order), each body's spheres in consecutive slots in their own
    # order; the grid beside them holds once every sphere the broadphase kept (the
    # others have the hash -1: test_broadphase), by bucket, in index order within a
    # bucket, with its slot, position, cell key and body.
    from test_contacts import boxes_on_static_slab      # (test_contacts imports this module)

    for model in (cluster_model(n=20), loose_balls(), boxes_on_static_slab()):
        be = CpuBackend(model)
        be.broadphase_spheres = 0
        st = model.initial_state()
        be.step(st, model.steps_per_frame)
        be.probe(st)
        ns = model.n_spheres
        idx, slot = be.sorted_idx, be.slot_of
        assert np.array_equal(np.sort(idx), np.arange(ns))
        assert np.array_equal(slot[idx], np.arange(ns))
        start = model.body_sphere_start
        nb = len(start) - 1
        first = np.array([slot[start[b]] for b in range(nb)])
        for b in range(nb):
            assert np.array_equal(slot[start[b]:start[b + 1]],
                                  first[b] + np.arange(start[b + 1] - start[b])), b
        cells = np.floor(st.body_x * (1.0 / cell_size(model.diameter))).astype(np.int64)
        keys = [z_order(c + (1 << 20)) for c in cells]          # cpu._CELL_OFF
        order = sorted(range(nb), key=lambda b: (keys[b], b))
        assert np.array_equal(np.argsort(first), order)
        g = be.grid
        kept = np.flatnonzero(be.sphere_hash >= 0)
        n = int(be.bucket_start[g[5]])
        assert n == len(kept)
        grid_idx = be.grid_idx[:n]
        assert np.array_equal(np.sort(grid_idx), kept)
        assert np.array_equal(be.grid_slot[:n], slot[grid_idx])
        assert np.array_equal(be.grid_x[:n], be.sphere_x[grid_idx])
        assert np.array_equal(be.grid_key[:n], be.sphere_key[grid_idx])
        assert np.array_equal(be.grid_body[:n], model.sphere_body[grid_idx])
        bucket = be.sphere_hash[grid_idx]
        assert np.all((np.diff(bucket) > 0) | ((np.diff(bucket) == 0)
                                               & (np.diff(grid_idx) > 0)))
        counts = np.bincount(bucket, minlength=int(g[5]))
        assert np.array_equal(np.diff(be.bucket_start[: g[5] + 1]), counts)


def test_frames_do_not_depend_on_when_lists_are_rebuilt():
    # one call of many steps (rebuilds only when a sphere moved SKIN/2 d) against one
    # step per call (a rebuild at every step, as the paper's loop): bit for bit
    for model in (loose_balls(), ball_lattice(), cluster_model(n=20)):
        a = model.initial_state()
        b = model.initial_state()
        sa = Simulator(model).backend
        sb = Simulator(model).backend
        n = 3 * model.steps_per_frame
        sa.step(a, n)
        for _ in range(n):
            sb.step(b, 1)
        for name in ("body_x", "body_q", "body_P", "body_L", "contact_partner",
                     "contact_spring"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name


def spinning_bar(omega=200.0):
    """A bar of 9 spheres in a row along x, its centre held in place (no gravity),
    spinning about z at ``omega`` [rad/s]; a ball 4 d from that centre along y,
    which only the bar's tip reaches: its centre does not move, only the spin
    brings its spheres within the lists' reach."""
    b = ModelBuilder(D, gravity=(0, 0, 0))
    bar_set, bar_mesh = box_set(9, 1, 1, D)
    ball, ball_mesh = ball_set(D)
    m = b.add_material(Material("m", density=1000, restitution=0.8, friction=0.3))
    b.add_bodies("bar", b.add_shape("bar", bar_mesh, bar_set), m, [[0.0, 0.0, 0.0]],
                 angular_velocities=[[0.0, 0.0, omega]])
    b.add_bodies("ball", b.add_shape("ball", ball_mesh, ball), m, [[0.0, 4.0 * D, 0.0]])
    return b.finalize(fps=60, n_frames=2)


def test_a_spinning_body_rebuilds_the_lists_as_its_tips_move():
    # Between rebuilds the CPU places only the spheres with something in reach and
    # decides per body whether one may have moved half the skin (spheres.body_moved:
    # its centre's move plus its turn). The bar's centre stays put: only the turn
    # brings its tip to the ball. One call of many steps must hit the ball exactly
    # as a rebuild at every step does.
    model = spinning_bar()
    n = int(round(0.5 * np.pi / 200.0 / model.dt)) + 40      # a quarter turn, and on
    a = model.initial_state()
    b = model.initial_state()
    sa = Simulator(model).backend
    sb = Simulator(model).backend
    sa.step(a, n)
    for _ in range(n):
        sb.step(b, 1)
    assert sa.skin_ctl[3] > 5                          # rebuilt within the one call
    assert np.linalg.norm(a.body_P[1]) > 0            # the tip hit the ball
    for name in ("body_x", "body_q", "body_P", "body_L", "contact_partner", "contact_spring"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(sa.sphere_x, sb.sphere_x)   # every sphere placed at the end


def test_a_body_bound_holds_every_sphere_move():
    # spheres.body_moved against every sphere's move, for turns from 1e-9 rad to a
    # half turn, with the quaternion's sign flipped (the same rotation)
    from dempipe.sim.kernels.cpu.spheres import body_moved
    from dempipe.sim.physics import quat_rotate
    rng = np.random.default_rng(7)
    offsets = rng.normal(size=(20, 3)) * 0.05
    reach = np.array([np.linalg.norm(offsets, axis=1).max()])
    for angle in (1e-9, 1e-6, 1e-3, 0.1, 1.0, 3.1):
        for _ in range(20):
            q0 = rng.normal(size=4)
            q0 /= np.linalg.norm(q0)
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            turn = np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]
            w0, v0 = turn[0], turn[1:]
            q1 = np.r_[w0 * q0[0] - v0 @ q0[1:],
                       w0 * q0[1:] + q0[0] * v0 + np.cross(v0, q0[1:])]
            q1 *= rng.choice([-1.0, 1.0])
            x0 = rng.normal(size=3)
            x1 = x0 + rng.normal(size=3) * rng.choice([0.0, 1e-6, 0.01])
            moves = [np.linalg.norm((x1 + quat_rotate(*q1, *o)) - (x0 + quat_rotate(*q0, *o)))
                     for o in offsets]
            bound = body_moved(0, x1[None], q1[None], x0[None], q0[None], reach)
            assert max(moves) <= bound, (angle, max(moves), bound)
            assert bound <= max(moves) + 2.0 * reach[0] * angle + 1e-6, (angle, bound)


def test_the_skin_grows_while_bodies_fly_and_the_frames_do_not_change():
    # Balls thrown about force a rebuild every few steps at the smallest skin: the CPU
    # widens the lists' reach (neighbours.adapt_skin) and rebuilds less often. A list
    # still holds every pair that can touch before the next rebuild, so the State is
    # the same bit for bit as with the skin held at SKIN (skin_ctl[2]).
    model = loose_balls()
    runs = []
    for skin_max in (SKIN_MAX, SKIN):
        st = model.initial_state()
        be = Simulator(model).backend
        be.skin_ctl[2] = skin_max
        skins = []
        for _ in range(3):
            be.step(st, model.steps_per_frame)
            skins.append(be.skin_ctl[0])
        runs.append((st, be.skin_ctl[3], max(skins)))
    (adaptive, rebuilds, widest), (fixed, rebuilds_fixed, widest_fixed) = runs
    assert widest_fixed == SKIN and SKIN < widest <= SKIN_MAX
    assert rebuilds < 0.6 * rebuilds_fixed
    for name in ("body_x", "body_q", "body_P", "body_L", "contact_partner", "contact_spring"):
        assert np.array_equal(getattr(adaptive, name), getattr(fixed, name)), name


def test_rebuilds_a_few_fast_bodies_force_narrow_the_skin_and_then_keep_the_slots():
    # A box slides at 2 m/s past a row of boxes drifting at millimetres a second: a
    # pile where few bodies move. Their rebuilds keep the other lists (a kept
    # rebuild costs a few steps' work), so the skin a landing widened is only extra
    # pairs walked at every step: such a rebuild, when it comes a while after the
    # last, narrows the skin by a step, down to the smallest, and from there keeps
    # the slots. Started at the widest skin, it ends at the smallest with most
    # rebuilds kept, and the State is the same bit for bit as with the skin held.
    model = slider_past_drifting_row(D, 20, 0.1, 2.0, 6)
    wide, held = Simulator(model).backend, Simulator(model).backend
    wide.skin_ctl[0] = SKIN_MAX
    held.skin_ctl[2] = SKIN
    a, c = model.initial_state(), model.initial_state()
    skins = []
    for _ in range(5):
        wide.step(a, model.steps_per_frame)
        held.step(c, model.steps_per_frame)
        skins.append(wide.skin_ctl[0])
    for name in ("body_x", "body_q", "body_P", "body_L", "contact_partner", "contact_spring"):
        assert np.array_equal(getattr(a, name), getattr(c, name)), name
    assert skins[-1] == SKIN, skins
    assert wide.span_ctl[2] > 0.5 * wide.skin_ctl[3], (wide.span_ctl[2], wide.skin_ctl[3])
    assert a.body_x[20, 0] > 0.022 * 15                      # it passed most of the row


def test_the_skin_shrinks_back_when_rebuilds_are_rare():
    # the rule itself: grow by a step when rebuilds come fast, shrink back when slow
    from dempipe.sim.kernels.neighbours import SKIN_GROW_BELOW, SKIN_SHRINK_ABOVE, SKIN_STEP
    assert adapt_skin(SKIN, SKIN_GROW_BELOW - 1, SKIN, SKIN_MAX, True) == SKIN + SKIN_STEP
    assert adapt_skin(SKIN, SKIN_GROW_BELOW - 1, SKIN, SKIN_MAX, False) == SKIN  # a call's start
    assert adapt_skin(SKIN_MAX, 1, SKIN, SKIN_MAX, True) == SKIN_MAX
    for moved in (True, False):
        assert adapt_skin(SKIN_MAX, SKIN_SHRINK_ABOVE + 1, SKIN, SKIN_MAX, moved) == \
            SKIN_MAX - SKIN_STEP
        assert adapt_skin(SKIN, SKIN_SHRINK_ABOVE + 1, SKIN, SKIN_MAX, moved) == SKIN
    assert adapt_skin(0.4, (SKIN_GROW_BELOW + SKIN_SHRINK_ABOVE) // 2, SKIN, SKIN_MAX,
                      True) == 0.4
    assert adapt_skin(SKIN, 1, SKIN, SKIN, True) == SKIN            # held: a fixed skin
    up = adapt_skin(SKIN, 1, SKIN, SKIN_MAX, True)                  # 0.30000000000000004
    assert adapt_skin(up, SKIN_SHRINK_ABOVE + 1, SKIN, SKIN_MAX, False) == SKIN   # exactly
    # a dense set's range starts below SKIN and ends there exactly too
    from dempipe.sim.kernels.neighbours import SKIN_MAX_DENSE, SKIN_MIN_DENSE
    up = SKIN_MIN_DENSE
    for _ in range(round((SKIN_MAX_DENSE - SKIN_MIN_DENSE) / SKIN_STEP)):
        up = adapt_skin(up, 1, SKIN_MIN_DENSE, SKIN_MAX_DENSE, True)
    assert up == SKIN_MAX_DENSE or abs(up - SKIN_MAX_DENSE) < 1e-12
    assert adapt_skin(up, 1, SKIN_MIN_DENSE, SKIN_MAX_DENSE, True) == up         # held
    for _ in range(round((SKIN_MAX_DENSE - SKIN_MIN_DENSE) / SKIN_STEP)):
        up = adapt_skin(up, SKIN_SHRINK_ABOVE + 1, SKIN_MIN_DENSE, SKIN_MAX_DENSE, False)
    assert up == SKIN_MIN_DENSE


def test_spheres_packed_closer_than_a_lattice_keep_the_skin_narrower():
    # a surface set's shell (0.3 d apart) puts ten times a lattice's spheres within a
    # list's reach of a face: its skin stays between SKIN_MIN_DENSE and SKIN_MAX_DENSE
    # (neighbours.skin_range), and the frames are those of the lattice's range
    from dempipe.sim.kernels.neighbours import SKIN_MAX_DENSE, SKIN_MIN_DENSE, skin_range
    assert SKIN_MIN_DENSE < SKIN and SKIN_MIN_DENSE < SKIN_MAX_DENSE < SKIN_MAX
    assert skin_range(cluster_model(n=6)) == (SKIN, SKIN_MAX)
    assert skin_range(loose_balls(n=20)) == (SKIN, SKIN_MAX)          # one sphere per body
    model = dense_blocks()
    assert skin_range(model) == (SKIN_MIN_DENSE, SKIN_MAX_DENSE)
    runs = []
    for lo, hi in ((SKIN_MIN_DENSE, SKIN_MAX_DENSE), (SKIN, SKIN_MAX)):
        st = model.initial_state()
        be = Simulator(model).backend
        if lo == SKIN_MIN_DENSE:
            assert be.skin_ctl[2] == SKIN_MAX_DENSE and be.skin_ctl[4] == SKIN_MIN_DENSE
            assert be.skin_ctl[0] == SKIN_MIN_DENSE
        be.skin_ctl[0], be.skin_ctl[2], be.skin_ctl[4] = lo, hi, lo
        skins = []
        for _ in range(3):
            be.step(st, model.steps_per_frame)
            skins.append(be.skin_ctl[0])
        assert lo <= min(skins) and max(skins) <= hi
        runs.append(st)
    for name in ("body_x", "body_q", "body_P", "body_L", "contact_partner", "contact_spring"):
        assert np.array_equal(getattr(runs[0], name), getattr(runs[1], name)), name


def test_rebuilds_happen_mid_call_and_lists_grow_without_losing_contacts():
    # lists of room 1 overflow at the first rebuild: the backend grows them and
    # redoes the step; the result is the one with room to spare
    for model in (ball_lattice(), ball_lattice(n=4, pitch=1.15, seed=5)):
        ref = model.initial_state()
        full = Simulator(model).backend
        full.probe(ref)
        assert full.nbr_n.max() > 1            # room 1 overflows at the first rebuild
        full.step(ref, 2 * model.steps_per_frame)
        be = Simulator(model).backend
        be.nbr = np.zeros((model.n_spheres, 1), dtype=np.int32)
        st = model.initial_state()
        be.step(st, 2 * model.steps_per_frame)
        assert be.nbr.shape[1] > 1
        assert st.step == ref.step
        for name in ("body_x", "body_q", "body_P", "body_L"):
            assert np.array_equal(getattr(st, name), getattr(ref, name)), name
        # the bodies move far enough that the lists are rebuilt inside one call
        moved = np.linalg.norm(st.body_x - model.initial_state().body_x, axis=1).max()
        assert moved > SKIN * model.diameter


def test_an_overflow_in_the_middle_of_a_call_keeps_the_histories():
    # A box falls onto a slab: no partner at the first build, so lists of room 1
    # overflow at a rebuild in the middle of the call, with friction histories in
    # sorted-slot order at that moment; the State's histories must be current when
    # run_steps returns early, and the rest of the call must go on from there.
    from test_cuda import falling_model

    model = falling_model()
    ref = model.initial_state()
    Simulator(model).backend.step(ref, 30)
    assert (ref.contact_partner != 0).any()              # friction histories in use
    for split in (30, 13, 19):
        be = Simulator(model).backend
        be.probe(model.initial_state())
        assert be.nbr_n.max() == 0                       # nothing to overflow at the start
        be.nbr = np.zeros((model.n_spheres, 1), dtype=np.int32)
        st = model.initial_state()
        be.step(st, split)
        be.step(st, 30 - split)
        assert be.nbr.shape[1] > 1                       # it overflowed, and grew
        for name in ("body_x", "body_q", "body_P", "body_L", "body_rest",
                     "contact_partner", "contact_spring"):
            assert np.array_equal(getattr(st, name), getattr(ref, name)), (split, name)


def test_an_empty_history_column_holds_no_stretch():
    # A rebuild moves and clears only the filled columns of the contact histories
    # (kernels/cpu/grid.py history_row_copy, pairing.walls_to_front): that is exact
    # only while every empty column (partner 0) holds a zero stretch, in the State's
    # rows and in the backend's rows in slot order, and while the State's rows keep
    # their filled columns first (the copy itself is held to the State of other
    # rebuild times by the two tests above). Balls thrown about a box rebuild every
    # few steps and touch each other and the walls.
    model = loose_balls()
    st = model.initial_state()
    be = Simulator(model).backend
    touched = 0
    for n in (1, 7, model.steps_per_frame, 2 * model.steps_per_frame):
        be.step(st, n)
        for partner, spring in ((st.contact_partner, st.contact_spring),
                                (be.hist_partner, be.hist_spring)):
            empty = partner == 0
            assert not spring[empty].any()
            touched += int((~empty).sum())
        filled = st.contact_partner != 0
        assert not (filled[:, 1:] & ~filled[:, :-1]).any()   # no gap before a filled column
    assert touched > 0 and be.skin_ctl[3] > 10


def test_bucket_sort_is_a_stable_counting_sort_across_blocks():
    # The CPU's counting sort sums the table in blocks of BUCKET_BLOCK buckets; with a
    # table of several blocks, spheres in none (-1), empty blocks and a bucket in the
    # last block, it is numpy's stable sort by bucket, and bucket_start the counts'
    # running sum, whatever the thread count.
    import numba

    from dempipe.sim.kernels.cpu.grid import bucket_sort
    from dempipe.sim.kernels.layout import BUCKET_BLOCK

    rng = np.random.default_rng(5)
    nbk = 5 * BUCKET_BLOCK + 17
    grid = np.array([0, 0, 0, 0, 0, nbk], np.int64)
    h = rng.integers(-1, 3 * BUCKET_BLOCK, 4000)
    h[rng.integers(0, 4000, 300)] = nbk - 1
    h[:50] = 7                                      # a crowded bucket
    slot_of = rng.permutation(4000).astype(np.int32)
    results = []
    for threads in (1, numba.config.NUMBA_NUM_THREADS):
        numba.set_num_threads(threads)
        start = np.full(nbk + 1, 99, np.int64)     # stale values from a last sort
        blocks = np.full(nbk // BUCKET_BLOCK + 1, 99, np.int64)
        idx = np.full(4000, -5, np.int32)
        slots = np.full(4000, -5, np.int32)
        bucket_sort(h, slot_of, grid, start, blocks, idx, slots)
        results.append((start.copy(), idx.copy(), slots.copy()))
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    kept = np.flatnonzero(h >= 0)
    order = kept[np.argsort(h[kept], kind="stable")]
    start, idx, slots = results[0]
    assert np.array_equal(idx[: len(kept)], order)
    assert np.array_equal(slots[: len(kept)], slot_of[order])
    assert np.array_equal(np.diff(start), np.bincount(h[kept], minlength=nbk))
    assert start[0] == 0 and start[nbk] == len(kept)
    for other in results[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(results[0], other))
