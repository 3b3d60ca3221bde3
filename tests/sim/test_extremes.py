"""The extreme-case suite, part 2: where the explicit contact model is pushed.

Each test asserts a physical bound (a conservation law, a closed form, a similarity
law, float64 rounding) with its tolerance and why, next to it. Figures quoted as
"measured" are from NUMBA_NUM_THREADS=1 on the 2-core CI machine; docs/stability.md
("The extreme-case suite") has the table. Where the library misses a bound, the test
keeps the bound and carries a strict xfail whose reason says what goes wrong and
where; the mark goes when the library is fixed (a strict xfail that passes fails the
run). Five limits found this way are fixed (docs/stability.md, "Limits found").

Sizes are shrunk for CI (counts, not coverage): a 27-ball gas, a 150-ball pile, 27 cubes,
128 chess pieces; each test says what the issue asked for and what it runs instead.
"""

import math

import numpy as np
import pytest

from bodies import ball_set, box_set
from dempipe.sim import materials as mat
from dempipe.check import stability as st
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.model import world_inertia, quat_to_matrix
from dempipe.sim.simulator import Simulator, kinetic_energy

D = 0.01
G = 9.81
EPS = np.finfo(np.float64).eps


def user_dt(builder, steps_per_contact=16.0, **finalize):
    """A user dt of ``steps_per_contact`` steps per π/ω_max (the undamped contact time),
    rounded down to whole steps per frame: what dt="auto" gives when ζ is not ~1."""
    probe = builder.finalize(**finalize)
    frame = 1.0 / probe.fps
    spf = math.ceil(frame / (math.pi / probe.omega_max / steps_per_contact))
    return builder.finalize(dt=frame / spf, **finalize)


# --------------------------------------------------------------------------- 2. restitution 1


def elastic_gas(seed, steps_per_contact=mat.STEPS_PER_CONTACT, n=3, box=0.05, speed=0.1,
                seconds=10.0, fps=200):
    """n³ one-sphere bodies on a lattice in a closed box (6 walls), random directions at
    ``speed``; e = 1, μ = 0, no gravity. Returns (E, collision events, model), E the
    kinetic energy of the frames in which nothing touches: there it is all the energy.
    (Mid-collision, KE + ½ k δ² is not what symplectic Euler conserves: its positions and
    velocities are half a step apart, which reads as an O(ω0 dt) wobble of the pair's
    energy, up to 1% of the total here, that is gone once the contact ends.)"""
    rng = np.random.default_rng(seed)
    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=1.0, friction=0.0))
    lattice = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    v = rng.normal(size=(n**3, 3))
    v *= speed / np.linalg.norm(v, axis=1, keepdims=True)
    b.add_bodies("gas", s, m, (lattice + 0.5) / n * box, velocities=v)
    b.add_box([0, 0, 0], [box] * 3, open_top=False, material=m)
    model = b.finalize(fps=fps, n_frames=int(seconds * fps) + 1,
                       steps_per_contact=steps_per_contact)
    frames = Simulator(model).advance(model.initial_state())
    x = frames.x
    dist = np.linalg.norm(x[:, :, None] - x[:, None], axis=-1) + np.eye(n**3) * D
    free = (dist.min(axis=(1, 2)) >= D) & (np.minimum(x, box - x).min(axis=(1, 2)) >= D / 2)
    assert free.sum() > 0.2 * len(free)                 # ~38% of the frames
    E = kinetic_energy(model, frames)[free]
    # a collision changes a velocity; a ball-ball collision counts for both balls, and one
    # lasting across two frames twice (frames 5 ms apart, contacts ~2 ms)
    dv = np.linalg.norm(np.diff(frames.v, axis=0), axis=-1)
    events = int((dv > 0.01 * speed).sum())
    return E, events, model


def test_elastic_gas_keeps_its_energy():
    # 27 balls in a 5 cm box for 10 s at 0.1 m/s: ~3,500 collisions at every angle
    # (1,900 ball-ball and 1,600 ball-wall, counted from frames at 4 kHz; the test counts
    # ~7,400 velocity changes at 200 fps). Nothing dissipates (ζ = 0, μ = 0); what
    # remains is the step: a contact starts and ends mid-step, so each collision returns
    # slightly more or less than it took (measured per collision at dt auto: +1e-4 to
    # +5e-4 of the pair's energy head-on, -9e-4 to +1.4e-3 oblique), and over thousands
    # of collisions that is a random walk. Asked: within 1% over 10 s. At 32 steps per
    # contact: measured ≤ 0.27% for six seeds. At dt auto (16 steps per contact) the
    # same walk reaches 0.6-1.9% depending on the seed (one of six above 1%), so this
    # test resolves the contact (docs/stability.md, "The extreme-case suite").
    E, events, model = elastic_gas(seed=1, steps_per_contact=32.0)
    assert events > 5000                                # many collisions, really
    assert np.abs(E / E[0] - 1).max() < 0.01


def test_contact_force_is_k_times_overlap_in_any_grid_cell():
    # Two balls 10% of d into each other along x, no gravity, k = 100 N/m: the spring is
    # k δ = 0.1 N whichever cells the two centres fall in (exact to rounding: 1e-9).
    from dempipe.sim.kernels.cpu.backend import CpuBackend

    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", restitution=1.0, friction=0.0, stiffness=100.0))
    b.add_bodies("pair", s, m, [[0.0, 0, 0], [0.9 * D, 0, 0]])
    model = b.finalize(fps=24, n_frames=2)
    be = CpuBackend(model)
    state = model.initial_state()
    for x0 in (0.0001, 0.0005, 0.0012, 0.0051):        # same cell, then x-adjacent cells
        state.body_x[:, 0] = [x0, x0 + 0.9 * D]
        be.probe(state)
        assert be.sphere_f[:, 0] == pytest.approx([-100 * 0.1 * D, 100 * 0.1 * D], rel=1e-9), x0


# --------------------------------------------------------------------------- 2. restitution 0


def drop(shape, e, h=0.02, mu=0.5, fps=1000, n_frames=2, dt="auto"):
    b = ModelBuilder(D)
    ss, mesh = ball_set(D) if shape == (1, 1, 1) else box_set(*shape, D)
    s = b.add_shape("body", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=e, friction=mu))
    rest = shape[2] * D / 2                             # centre height when just touching
    b.add_bodies("body", s, m, [[0, 0, rest + h]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    kw = dict(fps=fps, n_frames=n_frames)
    return (user_dt(b, **kw) if dt == "user" else b.finalize(**kw)), rest


def run_drop(model, rest, seconds):
    """Step one at a time; after the first contact record the highest centre and the
    largest upward velocity [m, m/s]."""
    sim = Simulator(model)
    state = model.initial_state()
    touched = False
    z_max = v_max = -math.inf
    for _ in range(int(round(seconds / model.dt))):
        sim.backend.step(state, 1)
        z = state.body_x[0, 2]
        touched = touched or z < rest
        if touched:
            z_max = max(z_max, z)
            v_max = max(v_max, state.body_P[0, 2] / model.body_mass[0])
    assert touched and np.isfinite(state.body_x).all()
    return z_max, v_max, state


@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 2, 2)], ids=["ball", "box2x2x2"])
def test_restitution_zero_does_not_rebound(shape):
    # e = 0 is ζ = 1: critical damping. The exact contact x(t) = v t e^(-ω t) never
    # separates, and its way back out of the deepest overlap is at most v e^-2 = 0.135 v
    # (at t = 2/ω). So after the first contact the centre never rises above the
    # just-touching height (tolerance 0: gravity keeps it m g / k below; measured 8e-5 d
    # below for the ball, 3.5e-5 d for the box) and the upward speed stays near 0.135 v:
    # measured every step, 0.145 v for the ball (the stepped contact, its onset resolved
    # within the step: laws.linear.normal_force; before, the first step's full dashpot
    # took more and it was 0.094 v), 0.079 v for the box (four dashpots at once);
    # bounded at 0.135 v + 25%, the discretization (at 16 steps per π/ω here, 10 at dt
    # auto: 0.166 v, the next test). dt is given; the next test runs it at dt auto.
    model, rest = drop(shape, 0.0, dt="user")
    v_imp = math.sqrt(2 * G * 0.02)
    z_max, v_max, state = run_drop(model, rest, 0.15)
    assert z_max <= rest
    assert v_max <= 1.25 * math.exp(-2) * v_imp
    assert abs(state.body_P[0, 2] / model.body_mass[0]) < 1e-3 * v_imp     # at rest


def test_restitution_zero_does_not_rebound_at_dt_auto():
    model, rest = drop((1, 1, 1), 0.0)
    v_imp = math.sqrt(2 * G * 0.02)
    z_max, v_max, _ = run_drop(model, rest, 0.15)
    # measured 0.172 v at the auto step (10 steps per contact, the contact's own bound
    # now that a face is one patch; 0.166 v under the flat-face bound it replaced):
    # bound 0.135 v + 30%
    assert z_max <= rest and v_max <= 1.3 * math.exp(-2) * v_imp


def test_flat_tile_does_not_bounce_back_faster_than_e():
    # A flat landing of 64 spheres at once is one contact patch (docs/physics.md,
    # "Contact patches"): the rebound must stay below e v (+5%: the one-sphere
    # discretization excess at 16 steps per contact is +4.9%, docs/stability.md).
    model, rest = drop((8, 8, 1), 0.5, fps=1000, n_frames=101)
    frames = Simulator(model).advance(model.initial_state())
    v_imp = math.sqrt(2 * G * 0.02)
    assert frames.v[:, 0, 2].max() <= 0.5 * 1.05 * v_imp


# --------------------------------------------------------------------------- 3. 100 m/s


def step_in_chunks(sim, state, n_steps, chunk=50):
    """Step, returning the largest overlap of any step [m] (the contact stage records it
    every step) and the lowest centre of each body seen between chunks."""
    low = np.full(sim.model.n_bodies, np.inf)
    sim.backend.take_max_overlap()
    for _ in range(0, n_steps, chunk):
        sim.backend.step(state, chunk)
        low = np.minimum(low, state.body_x[: sim.model.n_bodies, 2])
    return sim.backend.take_max_overlap(), low


def test_100_m_per_s_into_a_plane_does_not_pass_through():
    # Auto stiffness counts the launch speed twice (the fastest body against a partner
    # launched at it): k = m v²/δ² with v ≥ 200 m/s, so an undamped spring stops 100 m/s
    # within δ/2 = 1% of d. Tolerance: the target overlap δ = 2% of d, every step
    # (measured 0.73%); dt auto moves the ball 0.2% of d per step (asked: < 10%).
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.5))
    b.add_bodies("ball", s, m, [[0, 0, 2 * D]], velocities=[[0, 0, -100.0]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=100, n_frames=2)
    r = st.analyze(model)
    assert r.ok and r.step_travel < 0.005
    sim = Simulator(model)
    state = model.initial_state()
    n = int(4 * D / 100.0 / model.dt)                   # down 1.5 d, contact, back up 2 d
    overlap, low = step_in_chunks(sim, state, n)
    assert overlap < 0.02 * D
    assert low[0] > 0.49 * D
    v = state.body_P[0, 2] / model.body_mass[0]
    assert state.body_x[0, 2] > D / 2 and v > 0.45 * 100   # it bounced: e = 0.5 (-10%)


@pytest.mark.parametrize("target", ["ball", "box3x3x2"])
def test_100_m_per_s_into_a_resting_body_does_not_pass_through(target):
    # A ball at 100 m/s onto a body resting on a plane, off centre. Body-body the closing
    # speed meets m/2 (or the box's corner mass), still ≤ the 200 m/s auto stiffness was
    # made for, so no overlap of any pair, any step, exceeds δ = 2% of d (measured 0.62%
    # ball, 0.21% box); the target is driven into the plane and must not go through it;
    # the projectile must end above the target, moving up.
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    if target == "ball":
        ts, top = s, D
    else:
        tss, tmesh = box_set(3, 3, 2, D)
        ts, top = b.add_shape("box", tmesh, tss), 2 * D
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.5))
    b.add_bodies("target", ts, m, [[0, 0, top / 2]])
    b.add_bodies("ball", s, m, [[0.2 * D, 0.1 * D, top + 1.5 * D]], velocities=[[0, 0, -100.0]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=100, n_frames=2)
    assert st.analyze(model).ok
    sim = Simulator(model)
    state = model.initial_state()
    n = int(6 * D / 100.0 / model.dt) + 2000
    overlap, low = step_in_chunks(sim, state, n)
    assert overlap < 0.02 * D
    assert low[0] > top / 2 - 0.02 * D                  # the target did not go through
    bs = model.body_sphere_start
    target_spheres = sim.backend.sphere_x[bs[0]:bs[1]]
    ball_x, ball_v = state.body_x[1], state.body_P[1] / model.body_mass[1]
    assert ball_v[2] > 0 and ball_x[2] > target_spheres[:, 2].max()


# --------------------------------------------------------------------------- 5. scale


def scaled_scene(d, stiffness_at_1cm=None):
    """One scene in units of its diameter d. Similarity law, gravity and density kept:
    lengths × s (s = d / 1 cm) → masses × s³, times × √s, velocities × √s, angular
    velocities × 1/√s, forces × s³, stiffness × s² (force per length); e, μ, ζ unchanged.
    Three bodies in an open box: a tilted, spinning box that lands on an edge and falls
    flat, a ball thrown sliding and spinning that ends up rolling, a tile sliding to rest
    (static friction holds it)."""
    s = d / 0.01
    rs = math.sqrt(s)
    b = ModelBuilder(d)
    sa, ma = box_set(3, 2, 2, d)
    sb, mb = ball_set(d)
    sc, mc = box_set(2, 2, 1, d)
    A, B, C = b.add_shape("a", ma, sa), b.add_shape("b", mb, sb), b.add_shape("c", mc, sc)
    k = None if stiffness_at_1cm is None else stiffness_at_1cm * s * s
    m = b.add_material(Material("m", density=700, restitution=0.5, friction=0.5, stiffness=k))
    a = 0.4
    q = [math.cos(a / 2), 0.6 * math.sin(a / 2), 0.8 * math.sin(a / 2), 0]
    b.add_bodies("a", A, m, [[0, 0, 4 * d]], rotations=[q], velocities=[[0.05 * rs, 0, 0]],
                 angular_velocities=[[1 / rs, 5 / rs, 2 / rs]])
    b.add_bodies("b", B, m, [[3 * d, 3 * d, 6 * d]], velocities=[[-0.1 * rs, 0, 0]],
                 angular_velocities=[[0, 0, 10 / rs]])
    b.add_bodies("c", C, m, [[-3 * d, -3 * d, 2 * d]], velocities=[[0.1 * rs, 0, 0]])
    b.add_box([-5 * d, -5 * d, 0], [5 * d, 5 * d, 20 * d], material=m)
    return b.finalize(fps=100 / rs, n_frames=61)      # 0.6 s at 1 cm: landed, rolled, rests


@pytest.mark.parametrize("stiffness", [None, 2e3], ids=["auto", "explicit"])
def test_same_scene_at_1_mm_and_10_m_moves_the_same(stiffness):
    # The scene at d = 1 mm and at d = 10 m (s = 1e4 apart), with k × s² when given
    # (auto stiffness, m v²/δ² ∝ s³ s / s², does it by itself; dt auto ∝ √(m/k) ∝ √s, so
    # both take the same steps per frame). In scaled units (x/d, v/√(g d), w √(d/g), q)
    # the two runs are the same discrete map; only rounding differs (1 mm and 10 m are
    # not a power of 2 apart), amplified where a contact is sensitive. Asked: positions
    # and orientations within 1% (of d; of 1), velocities within 3% and spins within 5% of
    # their largest value in the run. Measured, explicit: 1.3e-9 at most. Auto: positions
    # 5.6e-4 d, but velocities 1.2% and spins 3.1% for a frame or two at 0.21 s, where the
    # tilted box rebounds off an edge (with the asked e = 0.5 now that a face is one
    # contact patch) and one run's contact begins a step before the other's; 1e-4 again
    # ten frames later. A ball landing on the tile's edge was left out: that
    # landing is chaotic enough (at auto stiffness, with static friction) to turn
    # rounding into 5% of d within 0.6 s, which says nothing about the similarity law.
    runs = []
    for d in (1e-3, 10.0):
        model = scaled_scene(d, stiffness)
        frames = Simulator(model).advance(model.initial_state())
        runs.append((model, frames.x / d, frames.v / math.sqrt(G * d),
                     frames.w * math.sqrt(d / G), frames.q))
    (m1, *a), (m2, *b) = runs
    assert m1.steps_per_frame == m2.steps_per_frame
    assert m2.pair_k[0, 0] / m1.pair_k[0, 0] == pytest.approx(1e4**2, rel=1e-9)
    for u, v, unit in zip(a, b, (0.01, 0.03 * np.abs(a[1]).max(), 0.05 * np.abs(a[2]).max(),
                                 0.01)):
        assert np.isfinite(u).all() and np.abs(u - v).max() < unit
    assert np.abs(a[0][-1] - a[0][0]).max() > 2          # it moved: 5.5 d


# --------------------------------------------------------------------------- 6. needle


def spinning_needle(dt="auto", fps=24, seconds=10.0, angle=0.5):
    """A 1×1×30 needle of steel in free space (no gravity, nothing to touch), spinning at
    100 rad/s about an axis `angle` from its long axis (and off both short axes), its body
    frame turned arbitrarily in the world."""
    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = box_set(1, 1, 30, D)
    s = b.add_shape("needle", mesh, ss)
    m = b.add_material(Material("steel", density=7800))
    w_body = 100.0 * np.array([0.8 * math.sin(angle), 0.6 * math.sin(angle), math.cos(angle)])
    q0 = np.array([0.9, 0.2, -0.3, 0.25])
    q0 /= np.linalg.norm(q0)
    b.add_bodies("needle", s, m, [[0, 0, 0]], rotations=[q0],
                 angular_velocities=[quat_to_matrix(q0) @ w_body])
    model = b.finalize(fps=fps, n_frames=int(seconds * fps) + 1, dt=dt)
    frames = Simulator(model).advance(model.initial_state())
    return model, frames


def needle_checks(model, frames):
    """|q| - 1, |L| drift, KE drift, |w| drift, and the needle axis against the closed form:
    a torque-free axisymmetric body's axis turns about the fixed L at |L| / I_transverse."""
    inv6 = model.body_inv_inertia[0]
    L = np.array([world_inertia(q, inv6) @ w for q, w in zip(frames.q[:, 0], frames.w[:, 0])])
    ke = kinetic_energy(model, frames)
    w = np.linalg.norm(frames.w[:, 0], axis=1)
    I1 = 1.0 / inv6[0]
    Lhat = L[0] / np.linalg.norm(L[0])
    rate = np.linalg.norm(L[0]) / I1
    axis0 = quat_to_matrix(frames.q[0, 0])[:, 2]
    err = 0.0
    for f in range(frames.n_frames):
        th = rate * frames.times[f]
        expect = (axis0 * math.cos(th) + np.cross(Lhat, axis0) * math.sin(th)
                  + Lhat * (Lhat @ axis0) * (1 - math.cos(th)))
        err = max(err, np.linalg.norm(quat_to_matrix(frames.q[f, 0])[:, 2] - expect))
    return dict(q=np.abs(np.linalg.norm(frames.q[:, 0], axis=1) - 1).max(),
                L=np.abs(np.linalg.norm(L, axis=1) / np.linalg.norm(L[0]) - 1).max(),
                ke=np.abs(ke / ke[0] - 1).max(), w=np.abs(w / w[0] - 1).max(), axis=err)


def test_spinning_needle_with_a_resolved_dt():
    # dt = 50 µs (|w| dt = 0.005), 2 s = 32 turns. Bounds: |q| = 1 to 1e-12 (renormalized
    # every step: rounding only); |L| to 1e-12 (no torque: L is integrated directly and
    # read back through I(q) w, so rounding only); KE and |w|, both constant for a
    # torque-free axisymmetric body, within 1e-3: the midpoint orientation update drifts
    # them secularly at a rate ∝ dt³ (|w|: measured 9.5e-5 per second at 50 µs, 7.7e-4
    # at 100 µs); the needle's axis within 1e-3 of the closed-form precession (measured
    # 4e-4). Resolved, the update is accurate to 1e-3; dt auto is coarser (next test).
    model, frames = spinning_needle(dt=5e-5, fps=100, seconds=2.0)
    c = needle_checks(model, frames)
    assert np.isfinite(frames.q).all()
    assert c["q"] < 1e-12 and c["L"] < 1e-12
    assert c["ke"] < 1e-3 and c["w"] < 1e-3
    assert c["axis"] < 1e-3


def test_spinning_needle_at_dt_auto():
    # dt auto bounds |w| dt (materials.MAX_SPIN_STEP) and the tip's travel per step
    # (materials.AUTO_TRAVEL): here dt = 1.7e-4 s, |w| dt = 0.017, 60,000 steps in 10 s.
    # No blow-up: |q| and |L| exact, KE within 0.1% (measured 7.5e-4). The precession
    # is a trade of accuracy for speed, bounded at 5% (measured |w| 3.8%, axis 2.2%);
    # the resolved test above holds it to 1e-3.
    model, frames = spinning_needle()
    c = needle_checks(model, frames)
    assert c["q"] < 1e-12 and c["L"] < 1e-12
    assert c["ke"] < 1e-3 and c["w"] < 0.05 and c["axis"] < 0.05


# --------------------------------------------------------------------------- 7. held pile


def settled(model, settle, hold):
    """Run ``model``; the largest speed of any body in each frame of the hold [m/s]."""
    sim = Simulator(model)
    frames = sim.advance(model.initial_state())
    speed = np.linalg.norm(frames.v, axis=-1).max(axis=1)
    assert frames.n_frames == round((settle + hold) * model.fps) + 1
    return speed[round(settle * model.fps):], frames, sim


@pytest.mark.slow
def test_frictionless_settled_ball_pile_is_held_for_10_s():
    # 150 balls dropped a few mm onto each other in a 6 d × 6 d box (5 × 5 a layer, 6
    # layers), settled 2 s, then held 10 s. The issue asked for 5,000 bodies; 150 give the
    # same contact network (every ball carries the column above it) at CI cost. Stiffness
    # 300 N/m: the bottom ball carries ~6 m g at 1% of d. Without friction the settled
    # pile is a jammed set of normal contacts only; a creeping explosion (energy from the
    # integrator in a long-held dense network) would show as speeds that do not decay.
    # Asked: the largest speed of any ball in any frame of the hold under 1 mm/s
    # (measured 4.5e-4 m/s at its start), and every ball at rest at its end but one
    # that may be left loose on the floor: without friction nothing stops it, and it
    # glides on at constant speed (at 10 steps per contact one ball does, at 8.9e-5
    # m/s, 0.37 d from its nearest neighbour; the others are below 1e-12 m/s).
    # (With friction, balls are a poor probe: nothing resists rolling, so a ball left
    # loose on the floor rolls on at constant speed, 0.2 mm/s here, which is right.)
    n = 150
    rng = np.random.default_rng(0)
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.3, friction=0.0,
                                stiffness=300.0))
    i = np.arange(n)
    pos = np.stack([(i % 5 - 2) * 1.2 * D, (i // 5 % 5 - 2) * 1.2 * D, D + i // 25 * 1.3 * D], -1)
    b.add_bodies("pile", s, m, pos + rng.uniform(-0.05, 0.05, (n, 3)) * D)
    b.add_box([-3 * D, -3 * D, 0], [3 * D, 3 * D, 40 * D], material=m)
    speed, frames, sim = settled(b.finalize(fps=20, n_frames=241), 2.0, 10.0)
    assert np.isfinite(frames.x).all()
    assert speed.max() < 1e-3
    last = np.sort(np.linalg.norm(frames.v[-1], axis=-1))
    assert last[-2] < 1e-6                              # at rest, not just slow
    glide = np.linalg.norm(frames.v[-40:], axis=-1)[:, np.argmax(np.linalg.norm(frames.v[-1], axis=-1))]
    assert glide.max() - glide.min() <= 1e-3 * glide.max() + 1e-12     # a loose glider
    assert sim.stats.max_overlap < 0.10 * D


@pytest.mark.slow
def test_settled_pile_of_cubes_with_friction_is_held_for_10_s():
    # 27 cubes (2 × 2 × 2 spheres) tilted at random up to 0.6 rad, dropped in three
    # layers of 3 × 3, 3 d apart, into a box 9 d wide, μ = 0.5: they land askew on
    # each other and on the walls, and only friction holds them so. Settled 4 s, held
    # 10 s. Stiffness 2,000 N/m: the 1-2 d drops stay under 7% of d; the bottom cubes'
    # contacts carry three cubes at 0.3% of d. Asked: the largest speed of any cube in any
    # frame of the hold under 1 mm/s (measured 8.4e-5 m/s, decaying to 3.5e-10 at the
    # end; seeds 0-4 give 3e-7 to 8.4e-5). The pile needs the 4 s: after 2 s cubes still
    # slip and topple at up to 1.2 mm/s, for a second or two. Before the tangential spring
    # (viscous friction only) such piles crept without end.
    rng = np.random.default_rng(0)
    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    s = b.add_shape("cube", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.3, friction=0.5,
                                stiffness=2000.0))
    i = np.arange(27)
    pos = np.stack([i % 3 - 1, i // 3 % 3 - 1, i // 9], -1) * 3 * D + [0, 0, 2 * D]
    axis = rng.normal(size=(27, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, 0.6, 27)
    q = np.concatenate([np.cos(angle / 2)[:, None], axis * np.sin(angle / 2)[:, None]], 1)
    b.add_bodies("pile", s, m, pos, rotations=q)
    b.add_box([-4.5 * D, -4.5 * D, 0], [4.5 * D, 4.5 * D, 60 * D], material=m)
    speed, frames, sim = settled(b.finalize(fps=20, n_frames=281), 4.0, 10.0)
    assert np.isfinite(frames.x).all()
    assert speed.max() < 1e-3
    assert sim.stats.max_overlap < 0.10 * D
    assert frames.x[-1, :, 2].max() > 4 * D             # still a pile, three layers deep


# --------------------------------------------------------------------------- 8. far away


FAR = np.array([1e4, -1e4, 1e4])                        # 10 km out on every axis


def far_scene(offset, d=D):
    """Everything placed relative to ``offset``, in an open box with friction: a ball
    thrown sliding and spinning (it falls 5.5 d, bounces once on the floor and is in
    the air again at the end, 0.2 s) and a tile sliding on the floor until static
    friction holds it."""
    off = np.asarray(offset, dtype=np.float64)
    b = ModelBuilder(d)
    ss, mesh = ball_set(d)
    ts, tmesh = box_set(2, 2, 1, d)
    s, t = b.add_shape("ball", mesh, ss), b.add_shape("tile", tmesh, ts)
    m = b.add_material(Material("m", density=700, restitution=0.5, friction=0.5))
    b.add_bodies("ball", s, m, [off + [2 * d, 2 * d, 6 * d]], velocities=[[0.1, 0.05, 0]],
                 angular_velocities=[[0, 0, 20]])
    b.add_bodies("tile", t, m, [off + [-3 * d, -3 * d, d / 2]], velocities=[[0.3, 0, 0]])
    b.add_box(off + [-5 * d, -5 * d, 0], off + [5 * d, 5 * d, 20 * d], material=m)
    return b.finalize(fps=100, n_frames=21)


def test_bounce_10_km_from_the_origin_matches_the_origin():
    # dempipe is float64 everywhere. At 1e4 m a position rounds by at most eps × 1e4 m / 2
    # ≈ 1e-12 m. Placing a body and every step round X once (X += V dt): before the
    # ball's first contact the far run can differ by at most (N + 1) eps 1e4 m after N
    # steps. A contact onset amplifies that: where in a step a contact starts moves the
    # rebound by up to 2 ζ ω0 v dt per step of shift (docs/physics.md, "Restitution
    # against dt"), so a shift δ gives a velocity error ≤ 2 ζ ω0 δ and a position error
    # ≤ δ (1 + 2 ζ ω0 T) over the time T left; the run has one onset (more would
    # compound this bound into nothing: each bounce multiplies it). The tile slides in
    # contact from the start and sticks; it is held to the same bound. Measured: 5.3e-9 m
    # at the frame before the onset (bound 2.4e-8 m), at most 5.6e-9 m over the run
    # (bound 6.4e-5 m; even (N + 1) eps 1e4 m = 4.8e-8 m holds). Both bounds catch a
    # float32 anywhere (its rounding at 1e4 m is 1e-3 m).
    runs = []
    for off in (np.zeros(3), FAR):
        model = far_scene(off)
        sim = Simulator(model)
        frames = sim.advance(model.initial_state())
        runs.append((frames.x - off, frames, sim))
    (x0, f0, s0), (x1, f1, s1) = runs
    err = np.abs(x1 - x0).max(axis=2)                   # (frames, bodies) [m]
    bound = (np.arange(f0.n_frames) * model.steps_per_frame + 1) * EPS * 1e4
    vz = f0.v[:, 0, 2]
    bounce = int(np.argmax(np.diff(vz) > 0)) + 1        # first frame after the ball's onset
    assert 5 < bounce < f0.n_frames - 5 and (np.diff(vz[bounce:]) < 0).all()   # one bounce
    assert (err[:bounce, 0] <= bound[:bounce]).all()
    zeta = mat.damping_ratio(0.5)
    w0 = math.sqrt(model.pair_k[0, 0] / model.body_mass[0])
    T = f0.times[-1]
    assert err.max() <= bound[-1] * (1 + 2 * zeta * w0 * T)
    assert s1.stats.max_overlap == pytest.approx(s0.stats.max_overlap, rel=1e-6)
    assert np.abs(f0.v[-1, 1]).max() < 1e-6             # the tile stopped (and stuck)


def test_contacts_beyond_the_grid_key_range_are_kept():
    # Two balls stacked (0.3 d off centre) on a plane at x = +11 km, d = 1 cm: the upper
    # one must roll off the lower, never through it (centres ≥ 0.9 d apart in every frame:
    # the contact overlap stays ~2%).
    off = np.array([1.1e4, 0, 0])
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=700, restitution=0.5, friction=0.5))
    b.add_bodies("b", s, m, [off + [0, 0, 3 * D], off + [0.3 * D, 0, 5 * D]])
    b.add_plane(off, [0, 0, 1], m)
    model = b.finalize(fps=100, n_frames=21)
    frames = Simulator(model).advance(model.initial_state())
    sep = np.linalg.norm(frames.x[:, 0] - frames.x[:, 1], axis=-1)
    assert sep.min() >= 0.9 * D


# --------------------------------------------------------------------------- the pile test

CHESS = """
[output]
fps = 50
duration = {duration}

[simulation]
resolution = {resolution}          # spheres across the pawn's height
stiffness_target_overlap = 0.05
seed = 7

[materials.boxwood]
density = 900.0
restitution = 0.35
friction = 0.5

[materials.felt]
density = 500.0
restitution = 0.2
friction = 0.7

[shapes.pawn]
builtin = "pawn"
[shapes.rook]
builtin = "rook"
[shapes.knight]
builtin = "knight"
[shapes.bishop]
builtin = "bishop"
[shapes.queen]
builtin = "queen"
[shapes.king]
builtin = "king"

[[bodies]]
name = "pieces"
shape = ["rook", "knight", "bishop", "queen", "king", "bishop", "knight", "rook",
         "pawn", "pawn", "pawn", "pawn", "pawn", "pawn", "pawn", "pawn"]
material = "boxwood"
count = {count}
layout = "grid"
origin = [-0.175, -0.175, 0.01]
dims = [8, 8, 2]
spacing = [0.05, 0.05, 0.11]

[[colliders]]
type = "box"
min = [-0.22, -0.22, 0.0]
max = [0.22, 0.22, 0.6]
material = "felt"
"""


@pytest.mark.slow
def test_a_thousand_chess_pieces_dropped_into_a_box_settle(tmp_path):
    # The paper's scene at the size: 1,000 pieces (the paper's smallest run is
    # 1,024) in four upright layers of up to 16 × 16, dropped 1 to 34 cm into a felt
    # box: the upper layers land on the lower and topple them. Resolution 4 (d = 12.5
    # mm, 8-15 spheres a piece, about 10,000 in all), 1.5 s. Bounds: finite; no overlap
    # of any sphere in any step above 10 % of d (auto stiffness aims at 5 %); total
    # energy KE + m g z never above its start (no energy from the contacts; 1e-6 for
    # rounding; elastic energy not counted only lowers it); the kinetic energy at the
    # end below 1e-3 of the energy the drop released; at the end the median piece
    # slower than 1 mm/s and 80 % slower than 1 cm/s (measured: 0.14 mm/s; 91 %; the
    # last few still roll off the pile's edge). 58 s on the 2-core CI machine.
    from dempipe.scene.build import build_model
    from dempipe.spheres.cache import SphereCache
    from dempipe.scene.load import parse_scene

    text = CHESS.format(count=1000, duration=1.5, resolution=4)
    text = text.replace("origin = [-0.175, -0.175, 0.01]", "origin = [-0.375, -0.375, 0.01]")
    text = text.replace("dims = [8, 8, 2]", "dims = [16, 16, 4]")
    text = text.replace("min = [-0.22, -0.22, 0.0]", "min = [-0.42, -0.42, 0.0]")
    text = text.replace("max = [0.22, 0.22, 0.6]", "max = [0.42, 0.42, 0.8]")
    model = build_model(parse_scene(text), cache=SphereCache(tmp_path / "cache"))
    assert model.n_bodies == 1000 and model.diameter == pytest.approx(0.0125, rel=1e-9)
    sim = Simulator(model)
    state = model.initial_state()
    frames = sim.advance(state)
    assert np.isfinite(frames.x).all() and np.isfinite(frames.q).all()
    assert sim.stats.max_overlap < 0.10 * model.diameter
    n = model.n_bodies
    pe = G * np.einsum("b,fb->f", model.body_mass[:n], frames.x[:, :, 2])
    ke = kinetic_energy(model, frames)
    E = ke + pe
    assert (E <= E[0] + 1e-6 * abs(E[0])).all()
    released = pe[0] - pe[-1]
    assert released > 0 and ke[-1] < 1e-3 * released
    speed = np.linalg.norm(frames.v[-1], axis=1)
    assert np.median(speed) < 1e-3 and (speed < 0.01).mean() > 0.8, \
        np.percentile(speed, [50, 90, 95, 99, 100])
