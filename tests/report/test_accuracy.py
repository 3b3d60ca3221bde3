"""The report's closed-form cases (dempipe/report/accuracy.py) against their closed forms.

`dempipe report` prints these errors per run; a closed form that leaves out physics
the simulator has (rolling resistance, on by default) makes every run look wrong
by the same bias, and a user tunes the wrong knob.
"""

import math

import pytest

from dempipe.report import accuracy as acc
from dempipe.sim.materials import Material

D = 0.01
G = 9.81


def material(mu_r):
    return Material("m", density=1000, restitution=0.5, friction=0.5, rolling_friction=mu_r)


def test_sliding_ball_closed_form():
    # without rolling friction: rolls at 5/7 v0 after t_r = 2 v0 / (7 μ g), for ever
    v0, mu = 1.0, 0.5
    t_r = 2.0 * v0 / (7.0 * mu * G)
    v, x = acc.sliding_ball(v0, mu, 0.0, 3.0 * t_r)
    assert v == pytest.approx(5.0 / 7.0 * v0, rel=1e-12)
    assert x == pytest.approx(v0 * t_r - 0.5 * mu * G * t_r ** 2 + v * 2.0 * t_r, rel=1e-12)
    # with it: it stops, after 7 v_r² / (10 μ_r g) of rolling
    mu_r = 0.05
    t_r = v0 / (G * (mu + 2.5 * (mu - mu_r)))
    v_r = v0 - mu * G * t_r
    v, x = acc.sliding_ball(v0, mu, mu_r, 100.0)
    assert v == 0.0
    slide = v0 * t_r - 0.5 * mu * G * t_r ** 2
    assert x == pytest.approx(slide + 7.0 * v_r ** 2 / (10.0 * mu_r * G), rel=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("law", ["linear", "hertz"])
def test_rolling_case_matches_its_closed_form_with_rolling_friction(law):
    """The sliding-ball case of the report, with the default rolling friction and
    five times it: within 1e-3 of the closed form (measured 3e-5 to 8e-5: the
    tangential spring's creep and the first contact's settling). The bias the
    rolling friction puts on the old closed form (5/7 v0 for ever) is at least
    ten times that bound at μ_r = 0.05, so the test tells the two apart."""
    b, s, m = acc._ball_scene(material(0.0), D, None)
    b.add_bodies("ball", s, m, [[0.0, 0.0, D]], velocities=[[1.0, 0.0, 0.0]])
    b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    k = float(b.finalize(fps=100, n_frames=2, contact_law=law).pair_k[0, 0])
    for mu_r in (0.01, 0.05):
        assert acc.rolling_error(material(mu_r), D, k, acc.DtRule(law=law)) < 1e-3
    # the case's own v0 and length (accuracy.rolling_error)
    v0 = math.sqrt(2.0 * G * acc.BOUNCE_HEIGHT * D)
    t_end = 3.0 * 2.0 * v0 / (7.0 * 0.5 * G) + 0.02
    with_r, without = acc.sliding_ball(v0, 0.5, 0.05, t_end), acc.sliding_ball(v0, 0.5, 0.0, t_end)
    assert abs(with_r[0] / without[0] - 1.0) > 1e-2


def test_incline_cylinder_lies_on_its_side_and_slides_below_its_grip():
    """The incline case's cylinder (accuracy.INCLINE_SHAPES): on its side it rolls
    when μ ≥ κ tan θ / (1 + κ) with κ = 1/2 (0.121 at 20°), the ball's κ = 2/5 needing
    only 0.104. At μ = 0.11, between the two, it slides at g (sin θ − μ cos θ): within
    2 % (measured 0.9 % as a surface set, 4 across), where the rolling closed form
    (2/3 g sin θ = 2.24 m/s² against 2.34) would be off by 4 %."""
    mu = 0.11
    m = Material("m", density=700, restitution=0.5, friction=mu, rolling_friction=0.0)
    run = acc.incline_run(m, 4, "surface", acc.DtRule(), shape="cylinder")
    theta = math.radians(acc.INCLINE_DEGREES)
    assert run.closed == pytest.approx(G * (math.sin(theta) - mu * math.cos(theta)))
    assert run.accel / run.closed == pytest.approx(1.0, abs=0.02)
    # On its side the friction μ m g cos θ, a radius R = 0.05 m under the centre,
    # spins it up about its axis (+y) at μ g cos θ / (κ R); stood on its base it
    # would not spin. At 0.1 s within 5 % (measured 3.4 % slow: the contact is a
    # radius less the overlap from the centre, and the first 5 ms are the landing).
    # Later, from about 0.5 m/s of slip, the envelope's bumps set it rocking
    # (docs/spheres.md, "Rolling"), so the check stops at 0.1 s.
    fr = run.frames
    i = int(abs(fr.times - 0.1).argmin())
    assert fr.times[i] == pytest.approx(0.1, abs=0.005)
    spin = mu * G * math.cos(theta) / (0.5 * 0.05) * fr.times[i]
    assert fr.w[i, 0, 1] == pytest.approx(spin, rel=0.05)
