"""The Hertz-Mindlin contact law with Tsuji damping (laws/hertz.py) against its
closed forms: the scaled contact, the restitution at every contact phase and at
impact speeds a decade apart, the contact time, and the scene key.

One-sphere balls onto a plane, no gravity, a fixed Hertz constant K (auto
stiffness would rescale K with the impact speed and hide the speed dependence).
"""

import math

import numpy as np
import pytest

from bodies import ball_set
from dempipe.sim.laws import hertz
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.simulator import Simulator
from dempipe.scene.load import parse_scene

D = 0.01
PHASES = np.arange(8) / 8.0
K = 5e6          # N/m^1.5: a 1 m/s impact of a 1 cm water-density ball sinks 1.6% of d


def _ball(e, z, v, k=K):
    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000.0, restitution=e, friction=0.0, stiffness=k))
    b.add_bodies("ball", s, m, [[0, 0, z]], velocities=[[0, 0, -v]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=100, n_frames=2, contact_law="hertz")


def bounce(e, phase, v=1.0):
    """((rebound / impact speed)², model, steps in contact) at dt auto; the impact
    falls ``phase`` of a step late."""
    dt = _ball(e, D / 2, v).dt
    model = _ball(e, D / 2 + 1e-7 + phase * v * dt, v)
    sim = Simulator(model)
    st = model.initial_state()
    inside = 0
    for _ in range(100_000):
        sim.backend.step(st, 1)
        inside += st.body_x[0, 2] < D / 2
        if st.body_P[0, 2] > 0 and st.body_x[0, 2] >= D / 2:
            break
    sim.backend.step(st, 1)   # the step after the contact ends takes its last dashpot impulse
    return (st.body_P[0, 2] / model.body_mass[0] / v) ** 2, model, inside


def test_damping_closed_form_is_the_root_of_the_scaled_contact():
    # c(e) = 2√(5/4)(-ln e)/√(π² + ln² e) (LIGGGHTS' form) against e of the scaled
    # contact ξ'' = -ξ^1.5 - c ξ^0.25 ξ' solved by RK4: measured ≤ 2.5e-6.
    for e in (0.05, 0.1, 0.3, 0.5, 0.9, 0.99):
        assert hertz.restitution(hertz.damping_ratio(e)) == pytest.approx(e, rel=1e-5)
    # the undamped contact time: the Beta-function closed form, and the classical
    # 2.87 (m²/(R E*² v))^(1/5) with K = (4/3) E* √R
    assert hertz.scaled_contact_time(0.0) == pytest.approx(hertz.TAU_UNDAMPED, rel=1e-8)
    assert hertz.TAU_UNDAMPED * (9 / 16) ** 0.2 == pytest.approx(2.868, abs=1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("e", [0.1, 0.2, 0.5, 0.8, 0.9])
def test_rebound_is_e_at_every_contact_phase(e):
    # The bound, 2% mean / 4% worst of e² over 8 phases at dt auto (the law's
    # 12 steps per contact). Measured (16 phases, restitution_vs_dt.py --law hertz):
    # e = 0.1: -1.7% / 2.1%; 0.2: -0.9% / 1.2%; 0.5: -0.2% / 0.4%; 0.9: ≤ 0.3%.
    assert hertz.STEPS_PER_CONTACT == 12.0
    err = np.array([bounce(e, ph)[0] / e ** 2 - 1 for ph in PHASES])
    assert abs(err.mean()) <= 0.02 and np.abs(err).max() <= 0.04, err


def test_restitution_does_not_depend_on_impact_speed():
    # Tsuji's damping ∝ δ^(1/4) makes e independent of the impact speed (the linear
    # dashpot does not, for a Hertz spring). Three speeds over a decade, one K, 4
    # phases each at dt auto (which follows the speed): the mean e² at each speed
    # within 1% of e², and of each other. Measured: within 0.3%.
    e = 0.5
    means = []
    for v in (0.3, 1.0, 3.0):
        means.append(np.mean([bounce(e, ph, v)[0] for ph in PHASES[::2]]) / e ** 2 - 1)
    assert max(abs(m) for m in means) <= 0.01, means
    assert max(means) - min(means) <= 0.01, means


def test_contact_lasts_the_closed_form_time():
    # τ_c(c) (m/K)^(2/5) v^(-1/5): within 6% + two steps (the contact is counted in
    # whole steps with the centre below d/2, which misses up to a step at each end; at
    # 12 steps per contact e = 0.9 measured 13 steps against 15.1).
    for e in (0.3, 0.9):
        for ph in PHASES[::3]:
            _, model, inside = bounce(e, ph)
            tc = hertz.contact_time(K, model.body_mass[0], model.pair_zeta[0, 0], 1.0)
            assert abs(inside * model.dt - tc) <= 0.06 * tc + 2 * model.dt, (e, ph, inside, tc)


def test_no_bounce_gains_energy():
    # Without damping (e = 1, c = 0) the stepped Hertz contact returns the impact
    # speed's square to 0.5% (symplectic Euler on a stiffening spring, at the law's
    # 12 steps per contact: measured at most +0.23%); with damping it never returns
    # more than it took.
    for e in (1.0, 0.7):
        for ph in PHASES[::2]:
            r2, _, _ = bounce(e, ph)
            assert r2 <= 1.0 + (5e-3 if e == 1.0 else 0.0), (e, ph, r2)


def test_auto_stiffness_keeps_the_target_overlap():
    # K = (5/4) m v² / δ^(5/2): the undamped overlap at the fastest impact is δ.
    m, v, d, target = 2.0, 3.0, 0.01, 0.02
    k = hertz.stiffness_for_overlap(m, v, 0.0, d, target)
    assert hertz.max_overlap(k, m, v) == pytest.approx(target * d, rel=1e-12)
    assert hertz.elastic_energy(k, target * d) == pytest.approx(0.5 * m * v * v, rel=1e-12)
    assert math.isfinite(hertz.critical_dt(k, m, hertz.damping_ratio(0.5), v))


def test_scene_key_chooses_the_law():
    # [simulation] contact_law: the default is the paper's law; an unknown name is
    # refused naming the key and the choices.
    from dempipe.errors import SceneError

    base = '[shapes.pawn]\nbuiltin = "pawn"\n[[bodies]]\nname = "p"\nshape = "pawn"\n'
    assert parse_scene(base, "/nonexistent/scene.toml").simulation.contact_law == "linear"
    hz = parse_scene('[simulation]\ncontact_law = "hertz"\n' + base, "/nonexistent/s.toml")
    assert hz.simulation.contact_law == "hertz"
    with pytest.raises(SceneError, match=r"simulation\.contact_law.*hertz"):
        parse_scene('[simulation]\ncontact_law = "hooke"\n' + base, "/nonexistent/s.toml")


@pytest.mark.slow
def test_young_modulus_gives_the_classical_hertz_contact():
    # [materials] young_modulus E, poisson_ratio ν: K = (4/3) E* √R* for two equal
    # spheres (E* = E / (2 (1 - ν²)), R* = d/4). Two such balls meeting head-on at a
    # relative speed v, undamped (e = 1), touch for the classical Hertz time
    # 2.87 (m_eff² / (R* E*² v))^(1/5), m_eff = m/2: within 6% + two whole steps
    # (the contact counted in whole steps with the centres closer than d).
    E, nu, v = 1e8, 0.3, 1.0
    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("rubber", density=1000.0, restitution=1.0, friction=0.0,
                                young_modulus=E, poisson_ratio=nu))
    b.add_bodies("balls", s, m, [[0, 0, 0], [D + 1e-6, 0, 0]],
                 velocities=[[0.5 * v, 0, 0], [-0.5 * v, 0, 0]])
    model = b.finalize(fps=100, n_frames=2, contact_law="hertz")
    e_star = E / (2 * (1 - nu * nu))
    assert model.pair_k[0, 0] == pytest.approx(4 / 3 * e_star * math.sqrt(D / 4), rel=1e-12)
    m_eff = model.body_mass[0] / 2
    tc = 2.868 * (m_eff ** 2 / (D / 4 * e_star ** 2 * v)) ** 0.2
    sim = Simulator(model)
    st = model.initial_state()
    inside = 0
    for _ in range(100_000):
        sim.backend.step(st, 1)
        gap = st.body_x[1, 0] - st.body_x[0, 0]
        inside += gap < D
        if inside and gap >= D:
            break
    assert abs(inside * model.dt - tc) <= 0.06 * tc + 2 * model.dt, (inside, model.dt, tc)
    # lossless: the balls part at the speed they met (symplectic Euler: 0.5%)
    assert (st.body_P[1, 0] - st.body_P[0, 0]) / model.body_mass[0] == pytest.approx(v, rel=5e-3)


def test_young_modulus_scene_keys():
    # Hertz only; not with stiffness; poisson_ratio only with it. Each refusal names
    # the key and the fix.
    from dempipe.errors import SceneError

    base = '[shapes.pawn]\nbuiltin = "pawn"\n[[bodies]]\nname = "p"\nshape = "pawn"\n' \
           'material = "r"\n'
    hz = '[simulation]\ncontact_law = "hertz"\n'
    ok = parse_scene(hz + '[materials.r]\nyoung_modulus = 5e7\npoisson_ratio = 0.4\n'
                        + base, "/nonexistent/s.toml")
    mat = ok.materials["r"].to_material()
    assert (mat.young_modulus, mat.poisson_ratio, mat.stiffness) == (5e7, 0.4, None)
    with pytest.raises(SceneError, match=r"materials\.r\.young_modulus.*Hertz.*contact_law"):
        parse_scene('[materials.r]\nyoung_modulus = 5e7\n' + base, "/nonexistent/s.toml")
    with pytest.raises(SceneError, match=r"materials\.r.*both stiffness and young_modulus"):
        parse_scene(hz + '[materials.r]\nyoung_modulus = 5e7\nstiffness = 1e6\n' + base,
                       "/nonexistent/s.toml")
    with pytest.raises(SceneError, match=r"materials\.r\.poisson_ratio.*without young"):
        parse_scene(hz + '[materials.r]\npoisson_ratio = 0.3\n' + base, "/nonexistent/s.toml")
    with pytest.raises(SceneError, match=r"materials\.r\.young_modulus"):
        parse_scene(hz + '[materials.r]\nyoung_modulus = -1\n' + base, "/nonexistent/s.toml")


def test_stiffness_factor_scales_the_young_modulus():
    # the report's k× axis (build Overrides.stiffness_factor) scales K through E (K ∝ E),
    # as it scales a given stiffness; a Material that gives both is refused
    from dempipe.scene.build import Overrides, build_model
    from dempipe.errors import SceneError
    from dempipe.scene.load import parse_scene

    text = ('[simulation]\ncontact_law = "hertz"\nresolution = 2\n'
            '[materials.r]\nyoung_modulus = 5e7\n[shapes.ball]\nbuiltin = "sphere"\n'
            '[[bodies]]\nname = "b"\nshape = "ball"\nmaterial = "r"\n'
            '[output]\nduration = 0.05\n')
    scene = parse_scene(text, "/nonexistent/s.toml")
    k1 = build_model(scene).pair_k[0, 0]
    k2 = build_model(scene, overrides=Overrides(stiffness_factor=2.0)).pair_k[0, 0]
    assert k2 == pytest.approx(2.0 * k1, rel=1e-12)
    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("r", stiffness=1e6, young_modulus=5e7))
    b.add_bodies("ball", s, m, [[0, 0, D]])
    with pytest.raises(SceneError, match=r"materials\.r: young_modulus"):
        b.finalize(fps=100, n_frames=2, contact_law="hertz")
