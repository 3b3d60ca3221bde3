"""Restitution at the automatic step, against the closed forms of the contact law.

A contact begins and ends anywhere inside a step. laws/linear.py resolves both
within the step (the dashpot acts for the part of the step spent in contact, and
its last impulse lands in the step after the contact ends) and sizes the dashpot
so that the *stepped* oscillator loses what the closed form loses. These tests
sweep the moment of impact across a step (8 phases) and compare with e², the
contact time and momentum, at dt = "auto" (laws.linear.STEPS_PER_CONTACT: 10 steps
per contact). A pile of cubes resting side by side checks that resolving the onset
leaves resting contacts alone (laws.linear.normal_force, Model.onset_speed).

Scenes are one or two one-sphere balls: m_eff is the body mass, so the closed
forms hold exactly (docs/physics.md, "Which effective mass").
"""


import numpy as np
import pytest

from bodies import ball_set, box_set
from dempipe.sim import laws
from dempipe.sim.laws import linear
from dempipe.sim.materials import ROLLING_FRICTION, Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.simulator import Simulator

D = 0.01
G = 9.81
PHASES = np.arange(8) / 8.0
#: The issue's bound on the error of e² over the phases: mean and worst.
MEAN_TOL, WORST_TOL = 0.02, 0.04


def _ball(e, z, vz, gravity=(0, 0, -G)):
    b = ModelBuilder(D, gravity=gravity)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000.0, restitution=e, friction=0.0))
    b.add_bodies("ball", s, m, [[0, 0, z]], velocities=[[0, 0, vz]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=100, n_frames=2)


def bounce(e, phase, v0=1.0):
    """((rebound speed / impact speed)², model, steps in contact) of a one-sphere
    ball thrown at v0 [m/s] onto a plane, no gravity (gravity during the contact
    would take g t_c from the rebound: 20% of it for e = 0.1 at 2 cm drops, a
    physical effect the closed form e leaves out). It starts ``phase`` of a step's
    travel further up, so the impact falls at that phase of a step."""
    dt = _ball(e, D / 2, -v0, gravity=(0, 0, 0)).dt     # the step the scene will get
    model = _ball(e, D / 2 + 1e-6 + phase * v0 * dt, -v0, gravity=(0, 0, 0))
    sim = Simulator(model)
    st = model.initial_state()
    inside = 0
    for _ in range(100_000):
        sim.backend.step(st, 1)
        z = st.body_x[0, 2]
        inside += z < D / 2
        if st.body_P[0, 2] > 0 and z >= D / 2:
            break
    sim.backend.step(st, 1)   # the step after the contact ends takes its last dashpot impulse
    return (st.body_P[0, 2] / model.body_mass[0] / v0) ** 2, model, inside


@pytest.mark.parametrize("e", [0.1, 0.2, 0.5, 0.8, 0.9])
def test_rebound_is_e_at_every_contact_phase(e):
    # The bound is the issue's, 2% mean / 4% worst of e². Measured at 10 steps per
    # contact (16 phases, benchmarks/restitution_vs_dt.py): e = 0.1: +0.2% / 3.0%;
    # 0.2: 0.0% / 1.7%; 0.5: +0.1% / 2.5%; 0.8: 0.0% / 1.1%; 0.9: 0.0% / 0.2%
    # (docs/physics.md). Before the onset was resolved, e = 0.2 was -17% / 39% off.
    assert linear.STEPS_PER_CONTACT == 10.0
    err = np.array([bounce(e, ph)[0] / e ** 2 - 1 for ph in PHASES])
    assert abs(err.mean()) <= MEAN_TOL, err
    assert np.abs(err).max() <= WORST_TOL, err


def test_contact_lasts_the_damped_half_period():
    # tc = π/ωd of the linear law. The stepped contact lasts a whole number of
    # steps, and the stepped oscillator turns a little faster than ωd (2-4% at
    # 16 steps per contact, more for low e), so: within 6% + one step.
    for e in (0.2, 0.5, 0.9):
        for ph in PHASES[::3]:
            _, model, inside = bounce(e, ph)
            tc = linear.contact_time(model.pair_k[0, 0], model.body_mass[0],
                                     model.pair_zeta[0, 0])
            assert abs(inside * model.dt - tc) <= 0.06 * tc + model.dt, (e, ph, inside)


@pytest.mark.parametrize("e", [0.2, 0.9, 1.0])
def test_bounce_never_gains_energy(e):
    # No gravity: the rebound speed over the impact speed at 8 phases. A dashpot only
    # takes energy (e < 1: ratio < 1); without one, symplectic Euler's spring returns
    # the impact speed to 1e-3 (measured 1e-4).
    for ph in PHASES:
        v0 = 1.0
        dt = _ball(e, D / 2, -v0, gravity=(0, 0, 0)).dt
        model = _ball(e, D / 2 + 1e-6 + ph * v0 * dt, -v0, gravity=(0, 0, 0))
        sim = Simulator(model)
        st = model.initial_state()
        sim.backend.step(st, int(3 * model.contact_time / model.dt) + 10)
        ratio = st.body_P[0, 2] / model.body_mass[0] / v0
        assert 0 < ratio <= (1.0 if e < 1 else 1.0 + 1e-3), (e, ph, ratio)
        assert abs(ratio / e - 1) <= WORST_TOL / 2, (e, ph, ratio)


@pytest.mark.slow
def test_head_on_pair_bounces_with_e_and_keeps_momentum():
    # Two balls of different masses (m_eff = m1 m2 / (m1 + m2)) meet head-on: the pair
    # path of the contact kernel, its onset and its last step. Relative speed after /
    # before = e at every phase; momentum exact to rounding (each contact is computed
    # once and read back negated).
    e = 0.3
    ratios = []
    for ph in PHASES:
        b = ModelBuilder(D, gravity=(0, 0, 0))
        ss, mesh = ball_set(D)
        s = b.add_shape("ball", mesh, ss)
        light = b.add_material(Material("a", density=1000.0, restitution=e, friction=0.0))
        heavy = b.add_material(Material("b", density=3000.0, restitution=e, friction=0.0))
        probe = ModelBuilder(D, gravity=(0, 0, 0))
        s2 = probe.add_shape("ball", mesh, ss)
        ma = probe.add_material(Material("a", density=1000.0, restitution=e, friction=0.0))
        mb = probe.add_material(Material("b", density=3000.0, restitution=e, friction=0.0))
        probe.add_bodies("ball", s2, ma, [[0, 0, 0]], velocities=[[1.0, 0, 0]])
        probe.add_bodies("ball", s2, mb, [[D, 0, 0]], velocities=[[-1.0, 0, 0]])
        dt = probe.finalize(fps=100, n_frames=2).dt
        gap = 1e-6 + ph * 2.0 * dt
        b.add_bodies("ball", s, light, [[0, 0, 0]], velocities=[[1.0, 0, 0]])
        b.add_bodies("ball", s, heavy, [[D + gap, 0, 0]], velocities=[[-1.0, 0, 0]])
        model = b.finalize(fps=100, n_frames=2)
        sim = Simulator(model)
        st = model.initial_state()
        p0 = st.body_P[:2].sum(axis=0)
        sim.backend.step(st, int(3 * model.contact_time / model.dt) + 10)
        v = st.body_P[:2, 0] / model.body_mass[:2]
        ratios.append((v[1] - v[0]) / 2.0)
        np.testing.assert_allclose(st.body_P[:2].sum(axis=0), p0, atol=1e-15)
    err = np.array(ratios) ** 2 / e ** 2 - 1
    assert abs(err.mean()) <= MEAN_TOL and np.abs(err).max() <= WORST_TOL, err


def _touching_cubes(rolling_friction=ROLLING_FRICTION):
    """72 cubes of 3×3×3 spheres packed face to face in a box, at rest: every face
    between neighbours is a set of contacts at exactly zero overlap, lightly loaded
    or not at all (benchmarks/cpu_bench.py's dense pile, smaller)."""
    ss, mesh = box_set(3, 3, 3, D)
    b = ModelBuilder(D)
    s = b.add_shape("cube", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.3, friction=0.5,
                                rolling_friction=rolling_friction))
    pitch = 3 * D
    n = (3, 3, 8)
    ix, iy, iz = np.meshgrid(*(np.arange(k) for k in n), indexing="ij")
    pos = np.stack([ix, iy, iz], -1).reshape(-1, 3) * pitch + pitch / 2
    b.add_bodies("cubes", s, m, pos)
    b.add_box([0, 0, 0], [n[0] * pitch, n[1] * pitch, n[2] * pitch + 1.0], material=m)
    return b.finalize(fps=60, n_frames=2)


def _kinetic(model, st):
    return float((st.body_P ** 2 * model.body_inv_mass[:, None]).sum() / 2)


def _pile_energies(rolling_friction=ROLLING_FRICTION):
    """The largest kinetic energy [J] of the pile over steps 6000-6500 and 6500-7000.
    The first 6000 settle it under gravity: each face between two cubes is one contact
    patch with the material's damping ratio (ζ = 0.36 at e = 0.3, kernels/patches.py),
    and the 8 cubes of a column ring as a chain of them, the slowest mode about a sixth
    of a contact's frequency: measured 3e-5 J at step 500, falling by 3.5x every 500
    steps to 2e-11 J at 6000 and 1.5e-12 J at 7000."""
    model = _touching_cubes(rolling_friction)
    sim = Simulator(model)
    st = model.initial_state()
    sim.backend.step(st, 6000)
    peaks = []
    for _ in range(2):
        peak = 0.0
        for _ in range(5):
            sim.backend.step(st, 100)
            peak = max(peak, _kinetic(model, st))
        peaks.append(peak)
    return peaks


def test_cubes_resting_side_by_side_stay_still(monkeypatch):
    # Settled, the pile keeps still and keeps losing what is left: bounded at 1e-10 J
    # over steps 6000-7000 (one cube, 27 g, moving at 0.1 mm/s; measured 2e-11 J), the
    # second half's peak below the first's. Resolved at every speed (onset speed 0),
    # the onset and end of these flickering contacts act as a spring η/dt on both sides
    # of δ = 0: when each of a face's contacts was a whole contact, that made the pile
    # gain energy from nothing (200 J by step 1000, the cubes thrown about), the reason
    # for the gate Model.onset_speed puts on them. As one patch, the face shares that
    # spring among its contacts and stays still without the gate too (measured the
    # same energies); the gate stays, for the contacts a patch does not group.
    # Rolling resistance (on by default) must not keep it moving either.
    for rolling in (ROLLING_FRICTION, 0.0):
        first, second = _pile_energies(rolling)
        assert first <= 1e-10 and second < first, (rolling, first, second)
    monkeypatch.setattr(laws, "ONSET_SPEED_FRACTION", 0.0)
    first, second = _pile_energies(0.0)
    assert first <= 1e-10 and second < first, (first, second)
