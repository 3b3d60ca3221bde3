"""Static and sliding friction on a slope: the tangential spring holds,
Coulomb's cap lets go.

A box of 4 × 4 × 2 spheres rests on the plane z = 0 and gravity is tilted by θ
about y, which is the same as a slope of angle θ under vertical gravity, with
no plane clipping at the box's edges to worry about.
"""

import math

import numpy as np
import pytest

from bodies import box_set
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.simulator import Simulator

D = 0.01
THETA = math.radians(20.0)
G = 9.81


def box_on_slope(mu, seconds):
    gravity = (G * math.sin(THETA), 0.0, -G * math.cos(THETA))   # down the slope = +x
    b = ModelBuilder(D, gravity=gravity)
    ss, mesh = box_set(4, 4, 2, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("wood", density=700, restitution=0.3, friction=mu))
    # bottom spheres just touching: centre of mass one diameter above the plane
    b.add_bodies("box", s, m, [[0.0, 0.0, D]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    fps = 100
    return b.finalize(fps=fps, n_frames=int(seconds * fps) + 1)


def test_box_holds_on_a_20_degree_slope_with_mu_0_6():
    # tan 20° = 0.36 < 0.6: static friction must hold. The bound: less
    # than 0.5% of the box's size (4 d = 4 cm) per simulated second. The spring
    # stretches once to carry the slope's share of the weight (μ-independent,
    # m g sin θ / (16 contacts · ks) ≈ a few µm) and then holds; measured after
    # the first 0.2 s so the landing transient is not counted.
    model = box_on_slope(0.6, 2.0)
    frames = Simulator(model).advance(model.initial_state())
    x = frames.x[:, 0, 0]
    t = frames.times
    later = t >= 0.2
    creep = abs(x[later][-1] - x[later][0]) / (t[later][-1] - t[later][0])
    assert creep < 0.005 * 4 * D, f"creeps {creep * 1e3:.3f} mm/s"
    assert np.isfinite(frames.x).all()


def test_box_slides_at_g_sin_minus_mu_cos_with_mu_0_2():
    # tan 20° = 0.36 > 0.2: it slides with a = g (sin θ − μ cos θ) = 1.51 m/s².
    # Tolerance 5% (the issue's); a is fitted to x(t) over 0.1..0.6 s, after the
    # contact has settled and before the box has travelled far.
    model = box_on_slope(0.2, 0.6)
    frames = Simulator(model).advance(model.initial_state())
    t = frames.times
    sel = t >= 0.1
    a = 2.0 * np.polyfit(t[sel], frames.x[sel, 0, 0], 2)[0]
    expect = G * (math.sin(THETA) - 0.2 * math.cos(THETA))
    assert a == pytest.approx(expect, rel=0.05)
    # it slides flat: no tumbling, stays on the plane
    assert abs(frames.x[-1, 0, 2] - D) < 0.1 * D
