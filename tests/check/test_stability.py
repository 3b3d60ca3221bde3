"""Stability: what dempipe.check.stability predicts, and the extreme cases it is about.

Each physics test states its tolerance and why. Measured figures quoted in the
comments are from NUMBA_NUM_THREADS=1 on the CI machine; docs/stability.md has
the table. Models are tiny lattices (tests/bodies.py) so the suite stays fast.
"""

import json
import math
import re

import numpy as np
import pytest

from bodies import ball_set, box_set
from dempipe.sim import materials as mat
from dempipe.check import stability as st
from dempipe.errors import StabilityError
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.model import rotational_mass_factor
from dempipe.sim.simulator import Simulator, kinetic_energy
from dempipe.sim.overlap import sphere_overlaps
from dempipe.pipeline.check import analyze_scene

D = 0.01
G = 9.81


def ball_on_plane(*, k=None, e=0.5, mu=0.5, density=1000.0, z=D / 2, v=(0, 0, 0),
                  gravity=(0, 0, -G)):
    b = ModelBuilder(D, gravity=gravity)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=density, restitution=e, friction=mu, stiffness=k))
    b.add_bodies("ball", s, m, [[0, 0, z]], velocities=[v])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b


def mixed_cluster(n=14, seed=0, spread=0.033):
    """Two shapes, two materials, turned and thrown, a box container and a tilted
    plane: every kind of pair at once. Small ``spread`` makes it start overlapped."""
    rng = np.random.default_rng(seed)
    b = ModelBuilder(D)
    ssa, ma = box_set(2, 2, 2, D)
    ssb, mb = box_set(4, 1, 1, D)
    shapes = [b.add_shape("a", ma, ssa), b.add_shape("b", mb, ssb)]
    mats = [b.add_material(Material("m1", density=800, restitution=0.4, friction=0.4)),
            b.add_material(Material("m2", density=2000, restitution=0.7, friction=0.2))]
    for i in range(n):
        q = rng.normal(size=4)
        cell = np.array([i % 3, (i // 3) % 3, i // 9]) - [1, 1, 0]
        b.add_bodies(f"g{i}", shapes[i % 2], mats[i % 2], [cell * spread + [0, 0, 0.02]],
                     rotations=[q / np.linalg.norm(q)], velocities=[rng.normal(size=3) * 0.3],
                     angular_velocities=[rng.normal(size=3) * 5])
    b.add_box([-0.05, -0.05, 0], [0.05, 0.05, 0.3], material=mats[0])
    b.add_plane([0, 0, 0.003], [0.1, 0, 1], mats[1])
    return b


def test_the_fastest_body_is_its_speed_at_the_floor_under_it_or_at_the_shot_end():
    # Energy and free fall, exactly: a ball whose bottom is h above the floor under it
    # lands at sqrt(v² + 2 g h) whatever its launch direction, and one with nothing
    # under it falls for the whole shot, |v| + g t by its end (t = (n_frames - 1) / fps).
    # The check's line says this figure; the closing and impact speeds stay finalize's.
    # Tolerance: rounding only (1e-9 relative).

    def fastest(z, *, v=(0.0, 0.0, 0.0), frames=73, collider=None):
        b = ModelBuilder(D)
        ss, mesh = ball_set(D)
        s = b.add_shape("ball", mesh, ss)
        m = b.add_material(Material("m", density=1000.0, restitution=0.5, friction=0.5))
        b.add_bodies("ball", s, m, [[0.0, 0.0, z]], velocities=[v])
        if collider == "plane":
            b.add_plane([0, 0, 0], [0, 0, 1], m)
        elif collider == "box under":
            b.add_box([-0.1, -0.1, 0.0], [0.1, 0.1, 0.3], material=m)
        elif collider == "box beside":
            b.add_box([0.2, 0.2, 0.0], [0.4, 0.4, 0.3], material=m)
        model = b.finalize(fps=24, n_frames=frames)
        speeds = st.expected_speeds(model)
        assert speeds[0] == pytest.approx(float(st.falling_speeds(model).max()), rel=1e-12)
        return speeds[0], model.body_radius[0]

    top = 1.0
    for where in ("plane", "box under"):
        got, radius = fastest(top, collider=where)
        assert got == pytest.approx(math.sqrt(2 * G * (top - radius)), rel=1e-9), where
        got, radius = fastest(top, v=(3.0, 0.0, 0.0), collider=where)   # thrown sideways
        assert got == pytest.approx(math.sqrt(9.0 + 2 * G * (top - radius)), rel=1e-9)
    # nothing under it: a shot of 3 s, and the box beside it holds nothing
    for where in (None, "box beside"):
        assert fastest(top, collider=where)[0] == pytest.approx(G * 3.0, rel=1e-9), where
    # a shot too short to reach the floor: g t, not the landing speed
    assert fastest(top, frames=3, collider="plane")[0] == pytest.approx(G * 2 / 24, rel=1e-9)


# --------------------------------------------------------------------------- the report


def test_report_restates_finalize_exactly():
    # ω_max, the critical step and the impact speed are recomputed from the Model;
    # they must be finalize's own (1e-12: same formulas, same float64 order or close).
    b = mixed_cluster()
    model = b.finalize(fps=60, n_frames=3, target_overlap=0.03)
    r = st.analyze(model)
    assert r.omega_max == pytest.approx(model.omega_max, rel=1e-12)
    # the single contact's critical step is where materials.check_dt starts refusing,
    # and the report's: a face is one contact patch, no stiffer than a corner
    single = st.critical_step(r.omega_max, r.zeta_min)
    mat.check_dt(single * (1 - 1e-9), model.omega_max, r.zeta_min, "x")
    with pytest.raises(StabilityError):
        mat.check_dt(single * (1 + 1e-9), model.omega_max, r.zeta_min, "x")
    assert r.critical_dt == single
    # auto stiffness: finalize's k from the heaviest corner-contact mass and r.impact_speed
    f = np.array([rotational_mass_factor(s.sphere_set.centers,
                                         s.sphere_set.inertia / s.sphere_set.volume)
                  for s in model.shapes])
    n = model.n_bodies
    m_corner = model.body_mass[:n] / (1 + f[model.body_shape])
    assert np.array_equal(model.body_corner_mass, m_corner)
    for name, k in model.stiffness_auto:
        mi = [m.name for m in model.materials].index(name)
        sel = model.body_material[:n] == mi
        assert k == pytest.approx(mat.auto_stiffness(float(m_corner[sel].max()), r.impact_speed,
                                                     G, D, 0.03), rel=1e-12)
    # the per-shape factor in the report is model.rotational_mass_factor of the set
    assert [s["rotational_mass_factor"] for s in r.shapes] == f.tolist()
    # every pair: rotational effective mass never above translational; dt/crit consistent
    for p in r.pairs:
        assert p.mass_rotational <= p.mass_translational
        assert p.critical_dt_rotational <= p.critical_dt_translational
        assert p.dt_ratio == pytest.approx(model.dt / p.critical_dt_rotational)
        by_name = {m.name: m for m in model.materials}
        e_pair = mat.mix(by_name[p.materials[0]], by_name[p.materials[1]])[1]
        assert p.restitution == pytest.approx(e_pair, rel=1e-12)
    kinds = {(p.materials, p.kind) for p in r.pairs}
    assert (("m1", "m2"), "body-body") in kinds and (("m2", "m1"), "body-wall") in kinds
    assert r.ok and r.steps_per_frame == model.steps_per_frame
    d = json.loads(r.to_json())
    assert d["ok"] is True and len(d["pairs"]) == len(r.pairs)


def test_report_takes_the_bakes_masses_with_kinematic_bodies_and_given_inertia():
    # The critical step check reports is the one the bake refuses at, for every kind
    # of body: a kinematic paddle (its motion given: a partner, never a mass) far
    # lighter than the bodies it pushes, and a body whose inertia is given (a
    # UsdPhysics MassAPI's), smaller than its shape's, so its corner contact is
    # lighter. Exact: both read materials.contact_masses over the same numbers.
    from dempipe.sim.motion import Key, Motion

    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    ps, pmesh = box_set(8, 8, 1, D)
    wood = b.add_material(Material("wood", density=700, restitution=0.3, friction=0.5))
    foam = b.add_material(Material("foam", density=5, restitution=0.3, friction=0.5))
    sweep = Motion(keys=(Key(0.0, (0.0, 0.0, 0.0)), Key(1.0, (0.05, 0.0, 0.0))))
    b.add_bodies("paddle", b.add_shape("paddle", pmesh, ps), foam, [[0.0, 0.0, 0.0]],
                 kinematic=True, motion=sweep)
    box = b.add_shape("box", mesh, ss)
    b.add_bodies("boxes", box, wood, [[0.0, 0.0, 0.03], [0.05, 0.0, 0.03]])
    m_box = 700 * ss.volume
    b.add_bodies("thin", box, wood, [[0.1, 0.0, 0.03]], masses=[m_box],
                 inertias=[np.diag([1.0, 1.0, 1.0]) * 1e-3 * m_box * D * D])
    b.add_plane([0, 0, -0.02], [0, 0, 1], wood)
    model = b.finalize(fps=24, n_frames=3)
    r = st.analyze(model)
    assert r.omega_max == model.omega_max
    assert r.critical_dt == st.critical_step(model.omega_max, r.zeta_min)
    # the given inertia's body is the stiffest mode: its corner mass is the least
    n = model.n_bodies
    moving = ~np.asarray(model.body_kinematic)
    lightest = np.argmin(np.where(moving, model.body_corner_mass, np.inf))
    assert model.group_names[model.body_group[lightest]] == "thin"
    assert model.body_corner_mass[lightest] < 0.5 * model.body_corner_mass[n - 2]
    # and the paddle's own (light) mass is in no pair: each pair's masses are the
    # moving bodies', half a box's at the least (two boxes meeting)
    m_paddle = float(model.body_mass[0])
    assert m_paddle < 0.1 * m_box
    assert min(p.mass_translational for p in r.pairs) == pytest.approx(0.5 * m_box,
                                                                       rel=1e-12)
    assert {p.materials for p in r.pairs} >= {("wood", "foam"), ("wood", "wood")}


def test_memory_estimate_matches_cpu_backend():
    # Computed from sizes without allocating; must equal what CpuBackend allocates
    # (exact: any change to the backend's scratch shows up here).
    from dempipe.sim.kernels.cpu.backend import CpuBackend

    model = mixed_cluster().finalize(fps=60, n_frames=5)
    mem = st.memory_estimate(model)
    be = CpuBackend(model)
    real = sum(a.nbytes for a in vars(be).values() if isinstance(a, np.ndarray))
    assert mem["cpu_scratch"] == real
    state = model.initial_state()
    assert mem["state"] == sum(getattr(state, k).nbytes for k in (
        "body_x", "body_q", "body_P", "body_L", "body_rest", "contact_partner",
        "contact_spring"))
    assert mem["total"] == sum(v for k, v in mem.items() if k != "total")


def test_frame0_overlap_numpy_matches_initial_overlap():
    # The NumPy twin (no kernel compiled) against build.initial_overlap (the CPU
    # contact stage itself), on a cluster packed so tight that bodies, the box walls
    # and the tilted plane all overlap. Same rules, different summation: 1e-12 relative.
    from dempipe.scene.build import initial_overlap
    from dempipe.sim.kernels.cpu.backend import CpuBackend

    model = mixed_cluster(n=20, seed=3, spread=0.012).finalize(fps=60, n_frames=2)
    frac, body = st.frame0_overlap(model)
    ref_frac, ref_body = initial_overlap(model)
    assert frac > 0.5
    assert frac == pytest.approx(ref_frac, rel=1e-12) and body == ref_body
    be = CpuBackend(model)
    be.probe(model.initial_state())
    np.testing.assert_allclose(sphere_overlaps(model), be.sphere_overlap, rtol=0,
                               atol=1e-12 * D)
    assert (be.sphere_overlap > 0).sum() > 20


def test_frame0_overlap_is_reported():
    # Two boxes 2x2x2 placed 0.7 diameters into each other: error (bake refuses > 50%);
    # 0.2 diameters: a warning (> 5%); 0.01: nothing.
    for depth, level in [(0.7, "error"), (0.2, "warning"), (0.01, None)]:
        b = ModelBuilder(D)
        ss, mesh = box_set(2, 2, 2, D)
        s = b.add_shape("box", mesh, ss)
        m = b.add_material(Material("m"))
        b.add_bodies("pair", s, m, [[0, 0, 0.05], [0, 0, 0.05 + 2 * D - depth * D]])
        r = st.analyze(b.finalize(fps=24, n_frames=2))
        assert r.overlap == pytest.approx(depth, rel=1e-9)
        found = [f for f in r.findings if f.code == "frame0-overlap"]
        if level is None:
            assert not found and r.ok
        else:
            assert found[0].level == level and "pair[0]" in found[0].message
            assert found[0].fix
            assert r.ok == (level != "error")


def test_mass_ratio_and_small_bodies_are_flagged():
    b = ModelBuilder(D)
    ssb, mb = box_set(3, 3, 3, D)
    ssp, mp = box_set(1, 1, 2, D)                     # 2 spheres: "a ball"
    sb, sp = b.add_shape("crate", mb, ssb), b.add_shape("pebble", mp, ssp)
    lead = b.add_material(Material("lead", density=11000))
    cork = b.add_material(Material("cork", density=100))
    b.add_bodies("crate", sb, lead, [[0, 0, 0.1]])
    b.add_bodies("pebble", sp, cork, [[0.1, 0, 0.1]])
    b.add_plane([0, 0, 0], [0, 0, 1], cork)
    model = b.finalize(fps=24, n_frames=2)
    r = st.analyze(model)
    codes = {f.code: f for f in r.findings}
    ratio = model.body_mass[0] / model.body_mass[1]
    assert ratio > 1000
    assert codes["mass-ratio"].level == "warning" and f"{ratio:.3g}×" in codes["mass-ratio"].message
    assert codes["small-body"].level == "warning" and "'pebble'" in codes["small-body"].message
    assert r.ok                                        # warnings only
    assert [s["small"] for s in r.shapes] == [False, True]


# --------------------------------------------------------------------------- dt auto


STIFFNESSES = [1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9]


@pytest.mark.parametrize("k", STIFFNESSES)
def test_dt_auto_is_stable_from_soft_to_stiff(k):
    # A ball dropped 1 mm at 0.1 m/s (impact 0.17 m/s) onto a plane, 0.05 s. The
    # overlap cannot exceed the undamped bound v √(m/k) + m g / k (impact plus
    # weight; the dashpot only shortens it); it must also stay under the guard's 50%.
    b = ball_on_plane(k=k, z=D / 2 + 1e-3, v=(0, 0, -0.1))
    model = b.finalize(fps=100, n_frames=6)
    sim = Simulator(model)
    frames = sim.advance(model.initial_state())          # raises BakeFailure on a guard
    assert np.isfinite(frames.x).all()
    m = model.body_mass[0]
    v_in = math.sqrt(0.1**2 + 2 * G * 1e-3)
    bound = v_in * math.sqrt(m / k) + m * G / k
    assert 0 < sim.stats.max_overlap <= bound
    assert sim.stats.max_overlap < 0.5 * D
    assert model.dt <= mat.contact_time(k, m, model.pair_zeta[0, 0]) / mat.STEPS_PER_CONTACT


@pytest.mark.parametrize("k", [1e2, 1e5, 1e8])
def test_dt_auto_is_stable_for_a_box(k):
    # A 2x2x2 box, four spheres land at once; rotation is on. Bound as above with the
    # whole mass on one sphere (conservative: four springs in parallel share it).
    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.5, stiffness=k))
    b.add_bodies("box", s, m, [[0, 0, D + 1e-3]], velocities=[[0, 0, -0.1]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=100, n_frames=6)
    sim = Simulator(model)
    frames = sim.advance(model.initial_state())
    mass = model.body_mass[0]
    v_in = math.sqrt(0.1**2 + 2 * G * 1e-3)
    assert np.isfinite(frames.x).all() and np.isfinite(frames.q).all()
    assert 0 < sim.stats.max_overlap <= v_in * math.sqrt(mass / k) + mass * G / k


def test_steps_per_frame_grow_with_sqrt_k():
    # dt auto = tc / 16 with tc ∝ 1/√k, rounded up to whole steps per frame: the
    # steps per frame scale with √k. 1e6 and 1e8 N/m give ~2,200 and ~22,000 steps,
    # so rounding is < 0.05%; 10% is the asked tolerance.
    spf = {}
    for k in (1e6, 1e8):
        spf[k] = ball_on_plane(k=k).finalize(fps=100, n_frames=2).steps_per_frame
    assert spf[1e6] > 100
    assert spf[1e8] / spf[1e6] == pytest.approx(math.sqrt(1e8 / 1e6), rel=0.10)


def test_user_dt_above_critical_is_refused_with_the_key_and_the_fix():
    b = ball_on_plane(k=1e6)
    auto = b.finalize(fps=100, n_frames=2)
    crit = st.analyze(auto).critical_dt
    with pytest.raises(StabilityError, match=r"simulation\.dt: dt = .* above the critical step"
                       r".*use dt = \"auto\""):
        b.finalize(fps=100, n_frames=2, dt=1.0 / 100 / math.floor(1.0 / 100 / (1.5 * crit)))
    ok = b.finalize(fps=100, n_frames=2, dt=1.0 / 100 / math.ceil(1.0 / 100 / (0.5 * crit)))
    assert st.analyze(ok).dt_ratio < 0.51


# --------------------------------------------------------------------------- energy


def total_energy(model, frames):
    """Kinetic (translation + rotation) plus m g h above the plane z = 0 [J]."""
    n = model.n_bodies
    return kinetic_energy(model, frames) + G * np.einsum("b,fb->f", model.body_mass[:n],
                                                          frames.x[:, :, 2])


@pytest.mark.parametrize("e", [0.5, 0.9])
def test_energy_never_grows_without_a_source(e):
    # A 3x2x2 box dropped 5 cm, tilted, spinning and sliding, onto a plane with
    # friction; frames at 1 kHz catch it mid-contact too. The dashpot and friction
    # only remove energy; the spring's elastic energy (not counted) is ≥ 0. The
    # integrator's own error: gravity under symplectic Euler loses ½ m g² dt² per
    # step (never gains); at 16 steps per contact the discrete bounce changes e by
    # at most 2 ζ ω0 dt (≤ 1.3% measured for e = 0.9, so e² ≤ 0.84 < 1): a bounce
    # can never return more than it took. What remains is float64 rounding of KE +
    # PE (~1e-15), so 1e-6 relative is a hard bound, not a fit.
    # (Measured: max E(t)/E0 - 1 = 0 exactly, i.e. frame 0; for e = 1, μ = 0 --
    # no loss at all -- the discretization gains 0.2% over 0.6 s: see below.)
    b = ModelBuilder(D)
    ss, mesh = box_set(3, 2, 2, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("m", density=700, restitution=e, friction=0.5))
    a = 0.3
    q = [math.cos(a / 2), 0.6 * math.sin(a / 2), 0.8 * math.sin(a / 2), 0]
    b.add_bodies("box", s, m, [[0, 0, 0.05]], rotations=[q], velocities=[[0.3, 0, 0]],
                 angular_velocities=[[1, 2, 3]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=1000, n_frames=401)
    frames = Simulator(model).advance(model.initial_state())
    E = total_energy(model, frames)
    assert (E <= E[0] * (1 + 1e-6)).all()
    assert E[-1] < 0.9 * E[0]                           # and it did bounce and lose


def test_energy_gain_of_a_lossless_contact_is_bounded():
    # The discretization's own energy error, with nothing to hide it: e = 1 (ζ = 0),
    # no friction, a ball dropped 2 cm and bouncing for 0.3 s (3 bounces). In flight
    # symplectic Euler loses exactly ½ m g² dt² per step; a contact starts and ends
    # mid-step, so a lossless bounce returns slightly more or less than it took.
    # Tolerance 5e-3 of E0 (measured before the onset was resolved within the step:
    # +0.24%; since: no frame above E0). Any e ≤ 0.9 removes 1 - e² ≥ 19% per bounce,
    # which is why the test above can ask 1e-6. (Frames inside a contact read lower:
    # the spring's energy is not counted.)
    b = ball_on_plane(e=1.0, mu=0.0, z=0.02 + D / 2)
    model = b.finalize(fps=500, n_frames=151)
    frames = Simulator(model).advance(model.initial_state())
    E = total_energy(model, frames)
    assert (E / E[0] - 1).max() < 5e-3
    # and a lossless bounce loses little either: in flight (the frames with the ball
    # clear of the plane) E stays within 3% of E0 (measured 1.7% at the end; symplectic
    # Euler's ½ m g² dt² per step in flight, and what each contact's steps give back)
    flying = frames.x[:, 0, 2] > D / 2
    assert flying.sum() > 100 and (E[flying] / E[0] - 1).min() > -0.03


# --------------------------------------------------------------------------- extreme cases


def test_heavy_box_on_light_box_does_not_sink():
    # Density ratio 100: a 10,000 kg/m³ box resting on a 100 kg/m³ box on a plane of
    # the light material. Auto stiffness is per material from its heaviest corner
    # mass, so the light material is 100x softer; the pair takes the series mix
    # 2 k_l k_h / (k_l + k_h) ≈ 2 k_l. The impact rule (v ≥ √(2 g d)) still makes it
    # stiff enough: measured largest overlap 0.2% of a diameter; asked < 10%.
    b = ModelBuilder(D)
    ss, mesh = box_set(4, 4, 2, D)
    s = b.add_shape("box", mesh, ss)
    light = b.add_material(Material("light", density=100, restitution=0.3, friction=0.5))
    heavy = b.add_material(Material("heavy", density=10000, restitution=0.3, friction=0.5))
    b.add_bodies("light", s, light, [[0, 0, D]])
    b.add_bodies("heavy", s, heavy, [[0, 0, 3 * D]])
    b.add_plane([0, 0, 0], [0, 0, 1], light)
    model = b.finalize(fps=50, n_frames=26)              # 0.5 s: it settles
    k = dict(model.stiffness_auto)
    assert k["heavy"] / k["light"] == pytest.approx(100, rel=1e-9)
    sim = Simulator(model)
    frames = sim.advance(model.initial_state())
    assert sim.stats.max_overlap < 0.10 * D             # every sphere, every step
    assert np.isfinite(frames.x).all()
    # a ratio of exactly 100 is at the warning's edge (it warns above 100)
    assert "mass-ratio" not in {f.code for f in st.analyze(model).findings}
    assert abs(frames.x[-1, 1, 2] - frames.x[-1, 0, 2] - 2 * D) < 0.10 * D


def _bounce_ratio(e, phase):
    """Rebound/impact speed of one sphere hitting a plane at 1 m/s, no gravity, dt
    auto; ``phase`` ∈ [0, 1) shifts where in a step the contact starts."""
    b = ball_on_plane(e=e, mu=0.0, gravity=(0, 0, 0), v=(0, 0, -1.0))
    dt = b.finalize(fps=100, n_frames=2).dt
    b = ball_on_plane(e=e, mu=0.0, gravity=(0, 0, 0), v=(0, 0, -1.0),
                      z=D / 2 + 1e-4 + phase * dt * 1.0)
    model = b.finalize(fps=100, n_frames=2)
    sim = Simulator(model)
    state = model.initial_state()
    for _ in range(10_000):
        sim.backend.step(state, 1)
        if state.body_P[0, 2] > 0 and state.body_x[0, 2] >= D / 2:
            break
    sim.backend.step(state, 1)   # the step after the contact ends takes its last dashpot impulse
    assert np.isfinite(state.body_x).all()
    return state.body_P[0, 2] / model.body_mass[0], model


PHASES = np.linspace(0, 1, 8, endpoint=False)


@pytest.mark.parametrize("e", [0.2, 0.5, 0.9, 1.0])
def test_one_sphere_body_does_not_explode(e):
    # A one-sphere body: no rotational softening, m_eff = m. Over 8 contact phases the
    # rebound never exceeds the impact when there is a dashpot (e < 1: no energy from
    # nowhere; for e = 1 within 1e-3, measured 6.6e-5), and exceeds e by at most
    # 2 ζ ω0 dt, the error the dashpot's jump within a step made before the contact's
    # onset and end were resolved within the step (laws/linear.py). Measured at 16
    # steps per contact since: within 0.2% of e for e = 0.2, 0.5, 0.9.
    ratios = []
    for ph in PHASES:
        r, model = _bounce_ratio(e, ph)
        ratios.append(r)
    ratios = np.array(ratios)
    z = mat.damping_ratio(e)
    w0dt = math.sqrt(model.pair_k[0, 0] / model.body_mass[0]) * model.dt
    assert (ratios <= (1.0 if e < 1 else 1.0 + 1e-3)).all()
    assert (ratios / e - 1).max() <= 2 * z * w0dt + 1e-3


def test_one_sphere_rebound_within_one_percent_of_e():
    e = 0.5
    worst = max(_bounce_ratio(e, ph)[0] for ph in PHASES)
    assert worst <= e * 1.0 + 0.01


def test_thin_rod_dropped_tilted_stays_bounded():
    # A 12x1x1 rod dropped from 6 cm at 29° onto a plane with friction: one end hits
    # first and the rod slaps down. Its rotational effective mass m/(1 + 2.5) sets
    # dt auto. Bound on |w|: the rotational energy ½ wᵀ I w cannot exceed the energy
    # available, m g (h - d/2), so |w| ≤ √(2 E0 / I_min). Measured max 11.6 rad/s
    # against the bound 254 (and 30 for spins about a short axis).
    b = ModelBuilder(D)
    ss, mesh = box_set(12, 1, 1, D)
    s = b.add_shape("rod", mesh, ss)
    m = b.add_material(Material("m", density=700, restitution=0.5, friction=0.5))
    a = 0.5
    h = 0.06
    b.add_bodies("rod", s, m, [[0, 0, h]], rotations=[[math.cos(a / 2), 0, math.sin(a / 2), 0]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=100, n_frames=41)
    r = st.analyze(model)
    assert r.shapes[0]["rotational_mass_factor"] > 2.0
    p = r.pairs[0]
    assert model.dt <= p.contact_time_rotational / mat.STEPS_PER_CONTACT * (1 + 1e-9)
    sim = Simulator(model)
    frames = sim.advance(model.initial_state())
    assert np.isfinite(frames.x).all() and np.isfinite(frames.w).all()
    I_min = 1.0 / model.body_inv_inertia[0, :3].max()
    E0 = model.body_mass[0] * G * (h - D / 2)
    assert np.linalg.norm(frames.w, axis=-1).max() <= math.sqrt(2 * E0 / I_min)
    assert frames.x[-1, 0, 2] < 0.01                   # it came to lie on the plane


def test_fast_ball_does_not_tunnel_with_dt_auto():
    # 20 m/s at a plane 1.5 diameters away: auto stiffness counts the launch speed,
    # so the step is ~1 µs (0.2% of a diameter). Checked every step, not per frame.
    b = ball_on_plane(z=0.02, v=(0, 0, -20.0))
    model = b.finalize(fps=100, n_frames=2)
    r = st.analyze(model)
    assert r.step_travel < st.TUNNEL_WARN and r.ok
    sim = Simulator(model)
    state = model.initial_state()
    lowest = math.inf
    for _ in range(2000):                                # 2 ms: hit and rebound
        sim.backend.step(state, 1)
        lowest = min(lowest, state.body_x[0, 2])
    assert lowest > 0.0                                  # the centre never crossed
    assert lowest > 0.25 * D                             # nor got anywhere near it
    assert state.body_P[0, 2] > 0                        # on its way back up


def test_analyze_flags_tunnelling_with_a_long_user_dt():
    # Same ball, a soft explicit stiffness (so a long dt passes the critical-step
    # check) and dt = 0.5 ms: 20 m/s × 0.5 ms = 1 cm = one diameter per step.
    b = ball_on_plane(k=100.0, z=0.02, v=(0, 0, -20.0))
    r = st.analyze(b.finalize(fps=100, n_frames=2, dt=5e-4))
    f = [f for f in r.findings if f.code == "tunnelling"]
    # closing speed: launch plus a fall from the centre's height to the plane
    assert r.step_travel == pytest.approx((20 + math.sqrt(2 * G * 0.02)) * 5e-4 / D, rel=1e-9)
    assert f and f[0].level == "error" and not r.ok
    assert "dt below" in f[0].fix and "dt = \"auto\"" in f[0].fix
    # 3 m/s: 15% of a diameter, a warning only (k = 2,000 N/m: stiff enough that the
    # ball sinks only ~0.2 d, a soft-contact warning, and soft enough for dt = 0.5 ms)
    b = ball_on_plane(k=2000.0, z=0.02, v=(0, 0, -3.0))
    r = st.analyze(b.finalize(fps=100, n_frames=2, dt=5e-4))
    assert [f.level for f in r.findings if f.code == "tunnelling"] == ["warning"] and r.ok
    # dt auto follows the launch speed (a quarter diameter per step, materials.AUTO_TRAVEL)
    # but cannot save a user stiffness too soft for 20 m/s: the spring lets the ball
    # sink v √(m/k) = 4.5 diameters deep. The check calls that an error, and the bake
    # does fail (the overlap guard trips)
    from dempipe.sim.simulator import BakeFailure

    model = ball_on_plane(k=100.0, z=0.02, v=(0, 0, -20.0)).finalize(fps=100, n_frames=3)
    assert 20.0 * model.dt / D <= 0.25 + 1e-12
    r = st.analyze(model, dt_setting="auto")
    f = [f for f in r.findings if f.code == "soft-contact"][0]
    closing = 20 + math.sqrt(2 * G * 0.02)
    depth = closing * math.sqrt(model.body_mass[0] / 100.0) / D
    assert depth > 4 and f"{depth:.0%}" in f.message
    assert f.level == "error" and not r.ok and "stiffness" in f.fix
    with pytest.raises(BakeFailure):
        Simulator(model).advance(model.initial_state())


# --------------------------------------------------------------------------- scenes

SCENE = """
[output]
fps = 24
duration = 0.5

[simulation]
sphere_diameter = 0.01
{dt}

[materials.wood]
density = 700.0
restitution = 0.3
friction = 0.5

[shapes.crate]
builtin = "box"
size = [0.03, 0.03, 0.03]

[[bodies]]
name = "crates"
shape = "crate"
material = "wood"
layout = "grid"
origin = [0.0, 0.0, 0.02]
dims = [2, 1, 1]
spacing = {spacing}

[[colliders]]
type = "plane"
material = "wood"
"""


def test_analyze_scene_ok_refused_dt_and_overlap(tmp_path):
    from dempipe.spheres.cache import SphereCache

    cache = SphereCache(tmp_path / "cache")
    path = tmp_path / "ok.toml"
    path.write_text(SCENE.format(dt="", spacing=0.05))
    r = analyze_scene(path, cache=cache)
    assert r.ok and r.dt_setting == "auto" and r.bodies == 2 and r.scene == str(path)
    # a user dt far above the critical step: finalize refuses, the check reports it
    path.write_text(SCENE.format(dt="dt = 0.005", spacing=0.05))
    r = analyze_scene(path, cache=cache)
    f = r.errors[0]
    assert not r.ok and f.code == "dt-above-critical" and "simulation.dt" in f.message
    assert "dt = \"auto\"" in f.fix and r.dt == 0.005 and r.dt_ratio > 1
    assert r.steps_per_frame is None
    # overlapping crates (spacing 1.5 diameters less than their size)
    path.write_text(SCENE.format(dt="", spacing=0.015))
    r = analyze_scene(path, cache=cache)
    assert not r.ok and r.errors[0].code == "frame0-overlap" and r.overlap > 0.5
    json.loads(r.to_json())


def test_a_shape_whose_mesh_reaches_past_its_spheres_is_flagged():
    # at 6 spheres across the pawn's height (d = 8.33 mm) the rook's battlements are
    # thinner than the lattice can hold: its mesh reaches 1.26 d beyond its spheres
    # (10.5 mm, measured with 2,000 samples; the sampling can only underestimate), and
    # a rook resting on a floor looks sunk into it by up to that. The pawn's reach is
    # 0.68 d, a box's tiled exactly (r (√3 - 1) at its corners) 0.37 d: no warning
    from dempipe.mesh.shapes import build_shape
    from dempipe.spheres.sphere_set import build_sphere_set

    d = 0.05 / 6
    b = ModelBuilder(d)
    wood = b.add_material(Material("wood", density=700))
    for i, name in enumerate(("rook", "pawn")):
        mesh = build_shape(name)
        s = b.add_shape(name, mesh, build_sphere_set(mesh, d, name=name))
        b.add_bodies(name, s, wood, [[0.1 * i, 0, 0.1]])
    b.add_plane([0, 0, 0], [0, 0, 1], wood)
    r = st.analyze(b.finalize(fps=24, n_frames=2))
    coarse = [f for f in r.findings if f.code == "coarse-shape"]
    assert len(coarse) == 1 and "'rook'" in coarse[0].message and coarse[0].level == "warning"
    reach = {s["name"]: s["mesh_beyond_spheres_diameters"] for s in r.shapes}
    assert 1.1 < reach["rook"] < 1.4 and reach["pawn"] < st.COARSE_DIAMETERS
    assert r.ok


def test_round_shapes_on_a_lattice_are_named_in_one_warning():
    # A lattice follows a curved surface in terraces, so a lattice ball too coarse for
    # its mesh's inscribed tori does not roll (docs/spheres.md, "Rolling"). The ball and
    # the cylinder on lattices at 3 across are named, with their off-axis shares; the
    # box (faces along the lattice's axes), the ball built as a surface set and the
    # ball 7.5 across, whose lattice meets walls through its mesh's tori, are not.
    from dempipe.mesh.shapes import build_shape
    from dempipe.spheres.options import BuildOptions
    from dempipe.spheres.sphere_set import build_sphere_set

    d = 0.04 / 3                        # 3 across the built-in ball, box, can's height
    b = ModelBuilder(d)
    wood = b.add_material(Material("wood", density=700))
    shapes = (("ball", "sphere", "lattice", {}), ("can", "cylinder", "lattice", {}),
              ("crate", "box", "lattice", {}), ("smooth", "sphere", "surface", {}),
              ("boulder", "sphere", "lattice", {"diameter": 0.1}))
    for i, (name, builtin, mode, params) in enumerate(shapes):
        mesh = build_shape(builtin, **params)
        s = b.add_shape(name, mesh, build_sphere_set(mesh, d, name=name,
                                                     options=BuildOptions(mode=mode)))
        b.add_bodies(name, s, wood, [[0.1 * i, 0, 0.05]])
    b.add_plane([0, 0, 0], [0, 0, 1], wood)
    r = st.analyze(b.finalize(fps=24, n_frames=2))
    found = [f for f in r.findings if f.code == "round-lattice"]
    assert len(found) == 1 and found[0].level == "warning" and r.ok
    assert "'ball' (99%), 'can' (65%)" in found[0].message, found[0].message
    assert "'crate'" not in found[0].message and "'smooth'" not in found[0].message
    assert "'boulder'" not in found[0].message
    assert 'spheres = "surface"' in found[0].fix
    rows = {s["name"]: s for s in r.shapes}
    assert rows["crate"]["off_axis_share"] == 0.0 and rows["smooth"]["mode"] == "surface"


def test_off_axis_share_of_a_box_turned_about_its_axis():
    # A box turned 45° about z: its four sides (2/3 of a cube's area) face away from
    # the lattice's axes, its top and bottom do not; turned 3° it still lies along them.
    import trimesh

    from dempipe.spheres.fidelity import off_axis_share

    for degrees, share in ((45.0, 2 / 3), (3.0, 0.0)):
        box = trimesh.creation.box((1.0, 1.0, 1.0))
        box.apply_transform(trimesh.transformations.rotation_matrix(math.radians(degrees),
                                                                    [0, 0, 1]))
        assert off_axis_share(box.vertices, box.faces) == pytest.approx(share, abs=1e-12)


def test_contact_table_columns_line_up_for_long_material_names():
    # "rubber / rubber (wall)" is longer than the pair column's 18 characters: the
    # header and every row still start k at the same column.
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("rubber", density=1000, restitution=0.5))
    b.add_bodies("balls", s, m, [[0, 0, D], [0, 0, 3 * D]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    lines = st.analyze(b.finalize(fps=24, n_frames=2)).format().splitlines()
    head = next(i for i, line in enumerate(lines) if "k [N/m]" in line)
    rows = lines[head + 1:head + 3]
    assert rows[1].lstrip().startswith("rubber / rubber (wall)")
    col = lines[head].index("k [N/m]")
    for row in rows:
        assert row[col - 1] == " " and row[col] != " ", (lines[head], row)


def _advised(text):
    """The "a dt below X s" of a refusal's fix [s]."""
    found = re.search(r"a dt below ([0-9.e+-]+) s", text)
    assert found, text
    return float(found.group(1))


@pytest.mark.parametrize("law", ["linear", "hertz"])
@pytest.mark.parametrize("e", [0.0, 0.3, 0.9])
def test_refused_dt_advice_is_one_figure_between_auto_and_critical(law, e):
    # The bake's refusal (finalize → materials.check_dt) and the check's finding name
    # the same dt to stay below: at least the automatic step (advice never asks for a
    # shorter step than "auto" takes) and below the critical step. At e = 0 the
    # linear law's auto step is past half the critical step: the advice is the auto step.
    b = ball_on_plane(e=e)
    auto = b.finalize(fps=100, n_frames=2, contact_law=law)
    crit = st.analyze(auto).critical_dt
    with pytest.raises(StabilityError) as info:
        b.finalize(fps=100, n_frames=2, dt=2.0 * crit, contact_law=law)
    said = str(info.value)
    r = st.analyze(auto, dt=2.0 * crit, dt_setting=2.0 * crit, refused=said)
    f = [f for f in r.findings if f.code == "dt-above-critical"][0]
    advised = mat.advised_dt(crit, auto.dt)
    assert _advised(said) == _advised(f.fix) == float(f"{advised:.3g}")
    assert auto.dt <= advised < crit
    assert f"({auto.dt:.3g} s here" in said and f"({auto.dt:.3g} s here" in f.fix


BOX_ON_PLANE = """
[output]
fps = 24
duration = 2.0
[simulation]
resolution = 4
dt = {dt}
[shapes.box]
builtin = "box"
[[bodies]]
name = "b"
shape = "box"
layout = "single"
position = [0.0, 0.0, 0.1]
[[colliders]]
type = "plane"
"""


def test_bake_and_check_advise_the_same_dt_for_a_box_on_a_plane(tmp_path):
    # dt = 0.1 s over a plane: `dempipe bake` refuses and `dempipe check` reports it,
    # with one advised dt, half the critical step here (above the auto step)
    import dempipe
    from dempipe.scene.build import Overrides, build_model
    from dempipe.scene.load import load_scene
    from dempipe.spheres.cache import SphereCache

    cache = SphereCache(tmp_path / "cache")
    path = tmp_path / "box.toml"
    path.write_text(BOX_ON_PLANE.format(dt="0.1"))
    r = analyze_scene(path, cache=cache)
    f = [f for f in r.findings if f.code == "dt-above-critical"][0]
    with pytest.raises(StabilityError) as info:
        dempipe.bake(path, tmp_path / "box.usdc", device="cpu", cache=cache)
    advised = _advised(str(info.value))
    assert advised == _advised(f.fix)
    auto = build_model(load_scene(path), cache=cache, overrides=Overrides(dt="auto"))
    assert auto.dt <= advised < r.critical_dt
    assert advised == float(f"{r.critical_dt * mat.SAFE_SHARE:.3g}")
    # a dt just below the advice passes both
    path.write_text(BOX_ON_PLANE.format(dt=f"{1.0 / 24 / math.ceil(1 / 24 / advised):.9g}"))
    assert not [f for f in analyze_scene(path, cache=cache).findings if f.level == "error"]
    build_model(load_scene(path), cache=cache)


def test_memory_is_shown_in_a_unit_that_fits():
    # a duration of 1e12 s once printed "≈ 2746582031.3 MiB"
    from dempipe.check.stability import _size
    assert _size(512) == "0.5 KiB" and _size(3 * 2**20) == "3.0 MiB"
    assert _size(5 * 2**30) == "5.0 GiB" and _size(2.6 * 2**40) == "2.6 TiB"
    assert _size(2**55) == "32.0 PiB"
