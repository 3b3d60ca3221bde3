"""Control: prescribed poses of static bodies, beside Model and State.

Physics asserted: a ball resting on a static mesh slab stays at rest while the
slab stays (the contact holds its weight: |v_z| small), and falls freely, at g,
once a Control moves the slab away. "Static" is one test: Model.body_static and
the kernels' physics.static_body agree with the bodies the body stage leaves alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from bodies import ball_set, box_set
from dempipe.sim import physics
from dempipe.sim.control import Control
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.simulator import Simulator

D = 0.01
G = 9.81


def ball_on_slab():
    b = ModelBuilder(D, gravity=(0.0, 0.0, -G))
    slab_set, slab_mesh = box_set(4, 4, 1, D)
    ss, mesh = ball_set(D)
    m = b.add_material(Material("m", density=1000, restitution=0.3, friction=0.0))
    b.add_static_mesh("slab", slab_mesh, slab_set, m)
    # resting: the ball's centre one diameter above the slab's spheres' centres
    b.add_bodies("ball", b.add_shape("ball", mesh, ss), m, [[0.5 * D, 0.5 * D, 0.995 * D]])
    return b.finalize(fps=60, n_frames=2)


def test_static_is_one_test():
    model = ball_on_slab()
    assert model.body_static.tolist() == [False, True]
    assert [physics.static_body(im) for im in model.body_inv_mass] == [False, True]


@pytest.mark.slow
def test_empty_control_changes_nothing():
    model = ball_on_slab()
    a, b = model.initial_state(), model.initial_state()
    sim_a, sim_b = Simulator(model), Simulator(model)
    sim_a.backend.step(a, model.steps_per_frame)
    sim_b.backend.step(b, model.steps_per_frame, Control())
    for k in ("body_x", "body_q", "body_P", "body_L"):
        assert getattr(a, k).tobytes() == getattr(b, k).tobytes(), k


def test_moving_the_slab_away_drops_the_ball():
    model = ball_on_slab()
    sim = Simulator(model)
    state = model.initial_state()
    n = model.steps_per_frame
    sim.backend.step(state, n)
    # held: after a frame the ball moves at well under what a frame of free fall gives
    vz_held = state.body_P[0, 2] / model.body_mass[0]
    assert abs(vz_held) < 0.1 * G / model.fps
    slab = model.n_bodies
    away = Control(body=np.array([slab], dtype=np.int32),
                   x=state.body_x[[slab]] - [0.0, 0.0, 1.0], q=state.body_q[[slab]].copy(),
                   v=np.zeros((1, 3)), w=np.zeros((1, 3)))
    away.check(model)
    sim.backend.step(state, n, away)
    assert state.body_x[slab, 2] == pytest.approx(model.initial_x[slab, 2] - 1.0)
    # free fall for a frame: Δv = g/fps exactly up to the integrator's rounding
    vz = state.body_P[0, 2] / model.body_mass[0]
    assert vz - vz_held == pytest.approx(-G * n * model.dt, rel=1e-9)


def test_control_refuses_a_dynamic_body_and_bad_shapes():
    model = ball_on_slab()
    one = dict(x=np.zeros((1, 3)), q=np.array([[1.0, 0, 0, 0]]), v=np.zeros((1, 3)),
               w=np.zeros((1, 3)))
    with pytest.raises(ValueError, match="dynamic"):
        Control(body=np.array([0], dtype=np.int32), **one).check(model)
    with pytest.raises(ValueError, match="shape"):
        Control(body=np.array([1], dtype=np.int32), x=np.zeros((2, 3)), q=one["q"],
                v=one["v"], w=one["w"]).check(model)
    with pytest.raises(ValueError, match="unit"):
        Control(body=np.array([1], dtype=np.int32), **dict(one, q=np.array([[2.0, 0, 0, 0]]))
                ).check(model)
