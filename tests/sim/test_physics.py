"""physics.py's formulas in plain Python against closed forms."""

import math

import numpy as np
import pytest

from dempipe.sim import materials, physics


def rotmat(q):
    from dempipe.sim.model import quat_to_matrix
    return quat_to_matrix(q)


def test_quat_rotate_matches_matrix():
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.normal(size=4); q /= np.linalg.norm(q)
        v = rng.normal(size=3)
        assert np.allclose(physics.quat_rotate(*q, *v), rotmat(q) @ v, atol=1e-12)
        assert np.allclose(physics.quat_rotate_inv(*q, *v), rotmat(q).T @ v, atol=1e-12)


def test_quat_integrate_constant_spin_is_exact():
    # eq. 7-10 compose exact axis-angle increments: N steps of w dt about a fixed
    # axis give exactly the rotation by N|w|dt (to rounding, 1e-12).
    q = (1.0, 0.0, 0.0, 0.0)
    w = np.array([0.0, 0.0, 2.0])
    for _ in range(1000):
        q = physics.quat_integrate(*q, *w, 1e-3)
    angle = 2.0
    assert np.allclose(q, [math.cos(angle / 2), 0, 0, math.sin(angle / 2)], atol=1e-12)
    assert physics.quat_integrate(*q, 0.0, 0.0, 0.0, 1e-3) == pytest.approx(q, abs=1e-15)


def test_angular_velocity_is_world_inverse_inertia_times_L():
    rng = np.random.default_rng(2)
    q = rng.normal(size=4); q /= np.linalg.norm(q)
    I0 = np.diag([1.0, 2.0, 3.0]) + 0.1
    inv = np.linalg.inv(I0)
    L = rng.normal(size=3)
    R = rotmat(q)
    expect = R @ inv @ R.T @ L                                      # eq. 5-6
    six = (inv[0, 0], inv[1, 1], inv[2, 2], inv[0, 1], inv[0, 2], inv[1, 2])
    assert np.allclose(physics.angular_velocity(*q, *six, *L), expect, rtol=1e-12)


def test_pair_force_is_exactly_antisymmetric():
    # gathered sums conserve momentum only if f_ji == -f_ij bit for bit
    rng = np.random.default_rng(3)
    for _ in range(50):
        r = rng.normal(size=3) * 0.003
        dist = float(np.sqrt(r @ r))
        dv = rng.normal(size=3); ws = rng.normal(size=3) * 10
        s = rng.normal(size=3) * 1e-4
        a = physics.sphere_pair_force(*r, dist, 0.01, *dv, *ws, 1e4, 3.0, 2.0, 2e3, 0.5,
                                      *s, 1e-5)
        b = physics.sphere_pair_force(*(-r), dist, 0.01, *(-dv), *ws, 1e4, 3.0, 2.0, 2e3, 0.5,
                                      *(-s), 1e-5)
        assert a[:3] == tuple(-x for x in b[:3])
        assert a[3:6] == b[3:6]  # equal torques about each centre: the force acts at the contact
        assert a[6:] == tuple(-x for x in b[6:])  # the two histories stay exact opposites


def test_spring_and_coulomb_cap():
    # pure overlap, no motion: f = -k δ n (eq. 11)
    f = physics.contact_force(1.0, 0.0, 0.0, 1e-4, 0, 0, 0, 1e4, 5.0, 3.0, 0.0, 0.5,
                              0, 0, 0, 0.0, 1e-5)
    assert f[:3] == pytest.approx((-1.0, 0.0, 0.0))
    # fast sliding: tangential force is capped at μ |f_n|
    f = physics.contact_force(0.0, 0.0, 1.0, 1e-4, 5.0, 0.0, 0.0, 1e4, 0.0, 100.0, 0.0, 0.3,
                              0, 0, 0, 0.0, 1e-5)
    assert f[2] == pytest.approx(-1.0)
    assert f[0] == pytest.approx(0.3)        # along the partner's relative motion
    # slow sliding: viscous kt v_t (eq. 13) below the cap
    f = physics.contact_force(0.0, 0.0, 1.0, 1e-4, 1e-3, 0.0, 0.0, 1e4, 0.0, 100.0, 0.0, 0.3,
                              0, 0, 0, 0.0, 1e-5)
    assert f[0] == pytest.approx(0.1)


def test_tangential_spring_holds_and_slides():
    k, ks, kt, mu, dt = 1e4, 2e3, 10.0, 0.5, 1e-4
    # at rest with a stretch below the cap: the spring alone pulls back, the
    # stretch is kept (static friction: no velocity needed)
    f = physics.contact_force(0.0, 0.0, 1.0, 1e-4, 0, 0, 0, k, 0.0, kt, ks, mu,
                              1e-4, 0.0, 0.0, 0.0, dt)
    assert f[0] == pytest.approx(ks * 1e-4) and f[3] == pytest.approx(1e-4)
    # slip grows the stretch by u_t dt
    f = physics.contact_force(0.0, 0.0, 1.0, 1e-4, 1e-3, 0, 0, k, 0.0, kt, ks, mu,
                              0.0, 0.0, 0.0, 0.0, dt)
    assert f[3] == pytest.approx(1e-3 * dt)
    # a stretch with a normal part is turned into the tangent plane, length kept
    f = physics.contact_force(0.0, 0.0, 1.0, 1e-4, 0, 0, 0, k, 0.0, kt, ks, mu,
                              3e-5, 0.0, 4e-5, 0.0, dt)
    assert f[3:] == pytest.approx((5e-5, 0.0, 0.0))
    # beyond the cap it slides: |f_t| = μ|f_n| and the stretch is what that force needs
    f = physics.contact_force(0.0, 0.0, 1.0, 1e-4, 0, 0, 0, k, 0.0, kt, ks, mu,
                              1e-2, 0.0, 0.0, 0.0, dt)
    assert f[0] == pytest.approx(mu * k * 1e-4)
    assert f[3] == pytest.approx(mu * k * 1e-4 / ks)
    # no normal load: no friction and no stored stretch
    f = physics.contact_force(0.0, 0.0, 1.0, 1e-4, 0, 0, 1.0, k, 1e3, kt, ks, mu,
                              1e-4, 0.0, 0.0, 0.0, dt)
    assert f[0] == 0.0 and f[3:] == (0.0, 0.0, 0.0)


def test_tangential_spring_turns_with_a_contact_spinning_about_its_normal():
    """A contact turning at ω about its normal with no slip (a box carried on a
    turntable) carries its stretch round with it: after N steps of dt it is the
    first stretch turned by ω N dt, length kept. Each step turns by atan(ω dt)
    instead of ω dt, a third of (ω dt)² short: over 1000 steps of ω dt = 2e-3,
    2.7e-6 rad in all, hence the 1e-5 rad allowed."""
    k, ks, kt, mu, dt, omega = 1e4, 2e3, 10.0, 0.5, 1e-3, 2.0
    s = (1e-4, 0.0, 0.0)
    for _ in range(1000):
        s = physics.contact_force(0.0, 0.0, 1.0, 1e-4, 0, 0, 0, k, 0.0, kt, ks, mu,
                                  *s, omega, dt)[3:]
    angle = omega * 1000 * dt
    assert math.hypot(*s) == pytest.approx(1e-4, rel=1e-12)
    assert s[2] == 0.0
    assert abs(math.atan2(s[1], s[0]) - angle) < 1e-5


def test_bond_shear_turns_with_a_pair_spinning_about_its_normal():
    """A glue bond whose two sides spin together at ω about its normal (ws = 2ω n:
    the bond point does not slip, u = 0) carries its shear stretch round with it,
    as a contact does: after N steps of dt it is the first stretch turned by
    ω N dt, length kept, still in the tangent plane, and its load the same. The
    1e-5 rad allowed is the carry's atan(ω dt) per step, as for a contact (2.7e-6
    rad in all here). Before the carry turned it, the stretch stayed at angle 0."""
    k, eta, dt, omega, rest = 1e4, 5.0, 1e-3, 2.0, 0.01
    s = (1e-4, 0.0, 0.0)
    for _ in range(1000):
        out = physics.glue_force(0.0, 0.0, rest, rest, rest, 0.0, 0.0, 0.0,
                                 0.0, 0.0, 2.0 * omega, k, eta, *s, dt)
        s = out[6:9]
    angle = omega * 1000 * dt
    assert math.hypot(*s) == pytest.approx(1e-4, rel=1e-12)
    assert s[2] == 0.0
    assert abs(math.atan2(s[1], s[0]) - angle) < 1e-5
    assert out[9] == pytest.approx(k * 1e-4, rel=1e-12)
    # seen from the other sphere (r, s negated; ws the same) it is the exact negation
    back = physics.glue_force(0.0, 0.0, -rest, rest, rest, 0.0, 0.0, 0.0,
                              0.0, 0.0, 2.0 * omega, k, eta, *(-c for c in s), dt)
    assert back[6:9] == tuple(-c for c in physics.glue_force(
        0.0, 0.0, rest, rest, rest, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0 * omega, k, eta, *s, dt)[6:9])


@pytest.mark.parametrize("e", [0.05, 0.2, 0.5, 0.9, 0.99])
def test_damping_ratio_inverts_restitution(e):
    z = materials.damping_ratio(e)
    assert 0 < z < 1
    assert materials.restitution_from_damping(z) == pytest.approx(e, rel=1e-12)


def test_auto_dt_whole_steps_per_frame():
    dt, spf = materials.auto_dt(omega_max=5000.0, fps=24)
    assert spf * dt == pytest.approx(1 / 24, rel=1e-12)
    assert dt <= math.pi / 5000.0 / materials.STEPS_PER_CONTACT
