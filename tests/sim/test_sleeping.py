"""Sleeping: bodies at rest leave the integration, and wake when a
moving body touches them."""

import numpy as np
import pytest

from bodies import ball_set, box_set, slider_past_drifting_row
from dempipe.sim.materials import Material
from dempipe.sim.motion import Key, Motion
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.simulator import Simulator

D = 0.01


def pile(sleep, ball_height=None, n_frames=24, fps=24, slab=False):
    """Nine 2×2×2-sphere boxes dropped side by side onto a plane; optionally a
    ball dropped onto the middle one from ``ball_height``, and a static mesh slab
    (one sphere thick, under the plane's surface level + 1 d) under them."""
    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("wood", density=700, restitution=0.3, friction=0.5))
    pos = [[(i % 3 - 1) * 0.025, (i // 3 - 1) * 0.025, 0.012 + 0.002 * i] for i in range(9)]
    b.add_bodies("boxes", s, m, pos)
    if ball_height is not None:
        bs, bm = ball_set(2 * D)
        ball = b.add_shape("ball", bm, _scaled(bs))
        b.add_bodies("ball", ball, b.add_material(Material("steel", density=7800,
                                                           restitution=0.3, friction=0.5)),
                     [[0.0, 0.0, ball_height]])
    if slab:
        slab_set, slab_mesh = box_set(8, 8, 1, D)
        centre = np.array([0.0, 0.0, -0.3 * D])      # its top 0.2 d above the plane
        slab_set.com = centre          # the builder places the set's centres about its com
        slab_mesh.vertices = slab_mesh.vertices + centre
        b.add_static_mesh("slab", slab_mesh, slab_set, m)
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=fps, n_frames=n_frames, sleep=sleep)


def _scaled(bs):
    # a ball of diameter 2D made of one sphere of diameter D would not touch
    # right; use 8 spheres in a cube instead, with the ball's mass properties
    ss, _ = box_set(2, 2, 2, D)
    return ss


#: The State's arrays two runs must agree on, bit for bit.
STATE = ("body_x", "body_q", "body_P", "body_L", "body_rest", "contact_partner",
         "contact_spring")


def assert_same_state(a, b, where=None):
    """States a and b equal bit for bit in every array of STATE."""
    for name in STATE:
        assert np.array_equal(getattr(a, name), getattr(b, name)), (where, name)


def lists(be):
    """Each sphere's neighbour list as its partners' sphere indices, in list order."""
    return [tuple(be.sorted_idx[be.nbr[s, :be.nbr_n[s]]]) for s in be.slot_of]


def test_a_settled_pile_falls_asleep_and_stays_put():
    model = pile(sleep=(None, None, 0.2), n_frames=25)
    sim = Simulator(model)
    state = model.initial_state()
    frames = sim.advance(state)
    asleep = state.asleep(model.sleep_steps)[: model.n_bodies]
    assert asleep.all(), f"{asleep.sum()} of {model.n_bodies} asleep after 1 s"
    # once all sleep, the CPU target skips the steps (and says how many it skipped)
    assert 0 < sim.stats.steps_skipped < sim.stats.steps
    # asleep means exactly still: the last frames are identical
    assert np.array_equal(frames.x[-1], frames.x[-2])
    assert np.all(frames.v[-1] == 0.0)


def test_sleeping_that_never_triggers_gives_the_same_frames():
    # the general path (sleeping off) and the sleeping path with thresholds no
    # body meets are bit-identical: the feature costs nothing in the physics
    a = pile(sleep=None, n_frames=10)
    b = pile(sleep=(1e-12, 1e-12, 10.0), n_frames=10)
    fa = Simulator(a).advance(a.initial_state())
    fb = Simulator(b).advance(b.initial_state())
    for name in ("x", "q", "v", "w"):
        assert np.array_equal(getattr(fa, name), getattr(fb, name)), name


def test_a_sleeping_pile_wakes_when_hit():
    # The boxes sleep after 0.2 s at rest (settled by ~0.3 s); the ball dropped
    # from 1.5 m reaches them at ~0.55 s and must wake the middle box and push it.
    model = pile(sleep=(None, None, 0.2), ball_height=1.5, n_frames=36)
    sim = Simulator(model)
    state = model.initial_state()
    sim.advance(state, n_frames=13)                     # to t = 0.5 s: pile asleep
    asleep = state.asleep(model.sleep_steps)[:9]
    assert asleep.sum() >= 8
    before = state.body_x[:9].copy()
    frames = sim.advance(state, n_frames=24)            # the ball lands
    moved = np.linalg.norm(frames.x[:, :9] - before, axis=2).max(axis=0)
    assert moved[4] > 0.05 * D, "the hit box never moved"
    assert np.isfinite(frames.x).all()


def test_sleeping_adds_little_error_to_a_settled_pile():
    # With sleeping, bodies freeze once slower than ~1.6 cm/s for 0.2 s: the
    # final pile differs from the one without sleeping by less than a tenth of a
    # diameter per body (a viewer sees no difference).
    a = pile(sleep=None, n_frames=25)
    b = pile(sleep=(None, None, 0.2), n_frames=25)
    fa = Simulator(a).advance(a.initial_state())
    fb = Simulator(b).advance(b.initial_state())
    err = np.linalg.norm(fa.x[-1] - fb.x[-1], axis=1).max()
    assert err < 0.1 * D, f"{err / D:.3f} d"


@pytest.mark.parametrize("ball_height,slab", [(0.3, False), (None, True)])
def test_skipping_what_sleeps_changes_nothing(ball_height, slab):
    # Three shortcuts of the CPU kernels: once every body sleeps, run_steps skips the
    # rest of its steps (nothing can move any more), stage 1 keeps the spheres of
    # bodies that slept through the last step and of static colliders, and the
    # contact passes leave out the slots of sleepers among sleepers. All must be
    # exact: one call of 2 s against calls of one step each (each a rebuild,
    # with stage 1 and the contact passes for every sphere and no skipping), bit
    # for bit. The ball lands on
    # the boxes as they settle, so some fall asleep while touching a moving body.
    model = pile(sleep=(None, None, 0.2), ball_height=ball_height, n_frames=49, slab=slab)
    n = 48 * model.steps_per_frame                       # 2 s; all asleep before
    a = model.initial_state()
    fast = Simulator(model).backend
    fast.step(a, n)
    assert fast.steps_skipped > 0                       # the shortcut was taken
    # and the third: once half the bodies are quiet, the contact passes visit
    # only the slots with work in them (kernels.cpu.stages.stage_active); the
    # calls of one step below never do (a call's first step visits every busy slot)
    assert fast.span_ctl[0] > 0
    b = model.initial_state()
    be = Simulator(model).backend
    be.skip_idle = False        # (each call steps, also once all sleep: below)
    for _ in range(n):
        be.step(b, 1)
    assert a.asleep(model.sleep_steps)[: model.n_bodies].all()
    assert a.step == b.step == n
    assert_same_state(a, b)


@pytest.mark.parametrize("starts_asleep", [False, True])
def test_a_call_with_everything_asleep_is_skipped_and_changes_nothing(starts_asleep):
    # A call that begins with every body asleep and nothing moving changes nothing
    # (sim.backend.nothing_moves): the backend skips it outright, counted as skipped,
    # where run_steps would rebuild every sphere's list for one step first. Frame by
    # frame against the kernels finding it (skip_idle off): the same State bit for bit,
    # rest counts and contact histories included; and every step of the frames after
    # the pile sleeps is skipped. Starting asleep, the pile never steps at all.
    model = pile(sleep=(None, None, 0.2), n_frames=25)
    skip, find = Simulator(model).backend, Simulator(model).backend
    find.skip_idle = False
    a, b = model.initial_state(), model.initial_state()
    if starts_asleep:
        for st in (a, b):
            st.ensure_rest(model.body_mass.shape[0])
            st.body_rest[: model.n_bodies] = model.sleep_steps
    from dempipe.sim.backend import nothing_moves
    idle_frames = 0
    for frame in range(24):
        idle = nothing_moves(model, True, skip.drive, a.body_rest, int(a.step))
        before = skip.steps_skipped
        skip.step(a, model.steps_per_frame)
        find.step(b, model.steps_per_frame)
        assert_same_state(a, b, frame)
        if idle:
            idle_frames += 1
            assert skip.steps_skipped - before == model.steps_per_frame
    assert a.asleep(model.sleep_steps)[: model.n_bodies].all()
    assert idle_frames >= (24 if starts_asleep else 4)
    assert skip.steps_skipped > find.steps_skipped
    assert a.step == b.step == 24 * model.steps_per_frame


def test_nothing_moves_only_when_nothing_can():
    # a body awake, a moving collider, glue, sleeping off or compiled out: never idle
    from dempipe.sim.backend import nothing_moves
    model = pile(sleep=(None, None, 0.2), n_frames=3)
    be = Simulator(model).backend
    st = model.initial_state()
    st.ensure_rest(model.body_mass.shape[0])
    st.body_rest[: model.n_bodies] = model.sleep_steps
    assert nothing_moves(model, True, be.drive, st.body_rest, 0)
    assert not nothing_moves(model, False, be.drive, st.body_rest, 0)
    st.body_rest[3] = model.sleep_steps - 1
    assert not nothing_moves(model, True, be.drive, st.body_rest, 0)
    off = pile(sleep=None, n_frames=3)
    assert not nothing_moves(off, True, be.drive, st.body_rest, 0)
    # a kinematic platform that will lift the boxes asleep on it
    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    ps, pmesh = box_set(8, 8, 1, D)
    m = b.add_material(Material("wood", density=700, restitution=0.3, friction=0.5))
    lift = Motion(keys=(Key(0.0, (0.0, 0.0, 0.0)), Key(0.4, (0.0, 0.0, 0.0)),
                        Key(0.6, (0.0, 0.0, 0.02))))
    b.add_bodies("platform", b.add_shape("platform", pmesh, ps), m, [[0.0, 0.0, 0.0]],
                 kinematic=True, motion=lift)
    b.add_bodies("boxes", b.add_shape("box", mesh, ss), m, [[0.0, 0.0, 0.0151]])
    lifted = b.finalize(fps=24, n_frames=3, sleep=(None, None, 0.1))
    rest = np.full(lifted.body_mass.shape[0], lifted.sleep_steps, dtype=np.int32)
    assert not nothing_moves(lifted, True, Simulator(lifted).backend.drive, rest, 0)


def test_contact_passes_over_the_active_slots_change_nothing_frame_by_frame():
    # kernels.cpu.stages.stage_active at its most eager (quiet_share 0: the active
    # slots, which the contact passes and the patch pass keep to, are used whenever any
    # body is quiet, so also while most still move, through wakes and bodies falling
    # quiet between searches) against never (quiet_share above 1):
    # the same State bit for bit at every frame, not only at the end. The ball
    # lands on the boxes as they settle and wakes some of them.
    model = pile(sleep=(None, None, 0.2), ball_height=0.3, n_frames=37)
    eager, never = Simulator(model).backend, Simulator(model).backend
    eager.quiet_share, never.quiet_share = 0.0, 2.0
    a, b = model.initial_state(), model.initial_state()
    for frame in range(36):
        eager.step(a, model.steps_per_frame)
        never.step(b, model.steps_per_frame)
        assert_same_state(a, b, frame)
    assert eager.span_ctl[0] > 0 and eager.span_ctl[1] > 0   # the active slots were used
    assert never.span_ctl[0] == 0


@pytest.mark.parametrize("slab", [False, True])
def test_rebuilds_that_keep_the_slots_change_nothing_frame_by_frame(slab):
    # A rebuild forced by a few moving bodies among sleepers keeps the slots and
    # searches again only the lists that can change (kernels.cpu.stages.run_steps,
    # stage_slot_marks): against rebuilds that always sort the slots again
    # (keep_share 0), the same State bit for bit at every frame, and each sphere's
    # list the same partners in the same order. The ball lands on the boxes as
    # they settle, so lists change next to sleepers that do not move; with the
    # slab, a static mesh's spheres are in the lists too.
    model = pile(sleep=(None, None, 0.2), ball_height=0.3, n_frames=37, slab=slab)
    keep, never = Simulator(model).backend, Simulator(model).backend
    never.keep_share = 0.0
    a, b = model.initial_state(), model.initial_state()
    for frame in range(36):
        keep.step(a, model.steps_per_frame)
        never.step(b, model.steps_per_frame)
        assert_same_state(a, b, frame)
        assert lists(keep) == lists(never), frame
    assert keep.span_ctl[2] > 0 and never.span_ctl[2] == 0   # the slots were kept


def test_a_body_sliding_past_sleepers_enters_and_leaves_their_kept_lists():
    # A frictionless box slides along a row of boxes asleep on the floor, a tenth of a
    # diameter clear of them: inside their lists' reach, never touching. Each rebuild
    # keeps the slots (one body moves), so the sleepers' lists must gain the slider
    # as it comes (stage_mark_partners) and lose it as it goes (stage_slot_marks'
    # mark 2); against rebuilds that sort the slots again, the same lists and State
    # at every frame, and the row stays asleep.
    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    s = b.add_shape("box", mesh, ss)
    wood = b.add_material(Material("wood", density=700, restitution=0.3, friction=0.5))
    ice = b.add_material(Material("ice", density=700, restitution=0.3, friction=0.0))
    row = [[0.025 * i, 0.0, D] for i in range(8)]
    b.add_bodies("row", s, wood, row, asleep=np.ones(8, dtype=bool))
    b.add_bodies("slider", s, ice, [[-0.05, 2.1 * D, D]], velocities=[[0.5, 0.0, 0.0]])
    b.add_plane([0, 0, 0], [0, 0, 1], ice)
    model = b.finalize(fps=24, n_frames=17, sleep=(None, None, 0.2))
    keep, never = Simulator(model).backend, Simulator(model).backend
    never.keep_share = 0.0
    a, c = model.initial_state(), model.initial_state()
    marks = np.zeros(4, dtype=int)
    for frame in range(16):
        keep.step(a, model.steps_per_frame)
        never.step(c, model.steps_per_frame)
        marks += np.bincount(keep.slot_mark, minlength=4)
        assert_same_state(a, c, frame)
        assert lists(keep) == lists(never), frame
    assert a.asleep(model.sleep_steps)[:8].all()
    assert a.body_x[8, 0] > 0.025 * 7 + 0.03                # it passed the whole row
    assert keep.span_ctl[2] > 0 and marks[2] > 0     # slots kept, a list lost the slider


def lists_hold_what_reaches(be, model):
    """Each slot's list is exactly the spheres of other bodies whose build position
    (built_x) is within the lists' reach (1 + skin) d of its own, and every pair of
    spheres closer than d where they are now (sorted_x) is listed."""
    reach = (1.0 + be.skin_ctl[0]) * model.diameter
    body = be.sorted_body
    other = body[:, None] != body[None, :]
    built = np.linalg.norm(be.built_x[:, None, :] - be.built_x[None, :, :], axis=2)
    now = np.linalg.norm(be.sorted_x[:, None, :] - be.sorted_x[None, :, :], axis=2)
    for s in range(body.shape[0]):
        listed = set(be.nbr[s, :be.nbr_n[s]].tolist())
        assert listed == set(np.nonzero(other[s] & (built[s] < reach))[0].tolist()), s
        assert set(np.nonzero(other[s] & (now[s] < model.diameter))[0].tolist()) <= listed, s


@pytest.mark.parametrize("gap", [0.1, -0.05])
def test_rebuilds_that_keep_most_lists_where_they_were_built_change_nothing(gap):
    # A box slides at 0.5 m/s past a row of boxes drifting at 1-3 mm/s on a
    # frictionless floor, a tenth of a diameter clear of them or scraping them: no
    # body is ever still, so keeping the slots only for bodies that moved at all
    # (keep_move 0) never keeps them; with the default keep_move only the bodies
    # that moved that share of half the skin are listed again, from where they
    # are, and the others keep their lists and where they built them. Against
    # rebuilds that sort every slot again (keep_share 0), the same State bit for
    # bit at every frame, and every touching pair listed.
    model = slider_past_drifting_row(D, 8, gap, 0.5, 17)
    keep, anymove, never = (Simulator(model).backend for _ in range(3))
    anymove.keep_move = 0.0
    never.keep_share = 0.0
    for be in (keep, anymove, never):   # the row's facing spheres drift across the reach
        be.skin_ctl[0] = be.skin_ctl[2] = be.skin_ctl[4] = 0.2
    a, c, e = model.initial_state(), model.initial_state(), model.initial_state()
    for frame in range(16):
        keep.step(a, model.steps_per_frame)
        anymove.step(c, model.steps_per_frame)
        never.step(e, model.steps_per_frame)
        assert_same_state(a, e, frame)
        assert_same_state(c, e, frame)
        lists_hold_what_reaches(keep, model)
    assert keep.span_ctl[2] > 0 and anymove.span_ctl[2] == 0
    assert a.body_x[8, 0] > 0.022 * 7 + 0.03                # it passed the whole row


def test_a_carried_platform_that_starts_moving_wakes_what_sleeps_on_it():
    # Boxes fall asleep on a keyed platform holding still, while a box far off keeps
    # sliding; then the platform lifts them. The active slots searched while it held
    # still leave theirs out, so the step it starts moving must drop them
    # (kernels.cpu.stages.stage_driven): with the active slots at their most eager
    # against none, the same State at every frame, and the boxes are lifted with it.
    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    s = b.add_shape("box", mesh, ss)
    ps, pmesh = box_set(8, 8, 1, D)
    p = b.add_shape("platform", pmesh, ps)
    m = b.add_material(Material("wood", density=700, restitution=0.3, friction=0.5))
    lift = Motion(keys=(Key(0.0, (0.0, 0.0, 0.0)), Key(0.4, (0.0, 0.0, 0.0)),
                        Key(0.6, (0.0, 0.0, 0.02)), Key(2.0, (0.0, 0.0, 0.02))))
    b.add_bodies("platform", p, m, [[0.0, 0.0, 0.0]], kinematic=True, motion=lift)
    b.add_bodies("boxes", s, m, [[-0.02, -0.02, 0.0151], [0.02, 0.02, 0.0151]])
    # far off, a frictionless box slides on and on: the steps are not skipped
    ice = b.add_material(Material("ice", density=700, restitution=0.3, friction=0.0))
    b.add_bodies("slider", s, ice, [[0.5, 0.0, -0.1 + D]], velocities=[[0.1, 0.0, 0.0]])
    b.add_plane([0, 0, -0.1], [0, 0, 1], ice)
    model = b.finalize(fps=24, n_frames=20, sleep=(None, None, 0.1))
    eager, never = Simulator(model).backend, Simulator(model).backend
    eager.quiet_share, never.quiet_share = 0.0, 2.0
    a, c = model.initial_state(), model.initial_state()
    asleep_before = False
    for frame in range(19):
        eager.step(a, model.steps_per_frame)
        never.step(c, model.steps_per_frame)
        assert_same_state(a, c, frame)
        if a.time < 0.4:
            asleep_before |= bool(a.asleep(model.sleep_steps)[1:3].all())
    assert asleep_before and eager.span_ctl[0] > 0      # they slept; the active slots were used
    assert np.all(a.body_x[1:3, 2] > 0.0151 + 0.015)      # and rode up with it


@pytest.mark.parametrize("sleep", [None, (None, None, 0.2)])
def test_bodies_at_rest_rebuilt_at_a_narrower_distance_change_nothing(sleep):
    # A body at rest at a rebuild is rebuilt when a sphere has moved REST_SKIN/2 d
    # rather than half the skin, and marks only the walls that near
    # (kernels.cpu.grid.stage_rest_half); a pile that came to rest between rebuilds
    # gets one to narrow them (run_steps, REST_SHARE). Against a backend that narrows
    # none (rest_skin at the largest skin), the same State bit for bit at every
    # frame while the boxes settle, rest, and are hit by the ball at ~0.55 s, which
    # wakes or shoves them past their narrow distances.
    from dempipe.sim.kernels.neighbours import REST_SKIN

    model = pile(sleep=sleep, ball_height=1.5, n_frames=37)
    narrow, wide = Simulator(model).backend, Simulator(model).backend
    wide.rest_skin = wide.skin_ctl[2]
    a, b = model.initial_state(), model.initial_state()
    narrowed = 0
    for frame in range(36):
        narrow.step(a, model.steps_per_frame)
        wide.step(b, model.steps_per_frame)
        assert_same_state(a, b, frame)
        at_rest = narrow.body_half[:9] == 0.5 * REST_SKIN * D
        narrowed = max(narrowed, int(at_rest.sum()))
        assert np.all(wide.body_half[:9] > 0.5 * REST_SKIN * D), frame
    assert narrowed >= 8                                 # the pile at rest was narrowed
    assert narrow.skin_ctl[3] > wide.skin_ctl[3]        # and its rebuilds came sooner
    moved = np.linalg.norm(a.body_x[:9] - model.initial_x[:9], axis=1)
    assert moved.max() > D                               # the boxes did fall and get hit
