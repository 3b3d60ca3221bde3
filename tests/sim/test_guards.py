"""Guards during a bake: an unstable or unforeseen run stops
at the step it goes wrong, with a message naming the frame, the time, the body
and the likely cause, and keeps every frame before it."""

import math

import numpy as np
import pytest
from click.testing import CliRunner

from bodies import ball_set, box_set
from dempipe.errors import StabilityError
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.simulator import BakeFailure, Simulator
from dempipe_cli.main import app

D = 0.01


def bouncing_boxes(dt, e=1.0, n_frames=40):
    """Lossless boxes dropped onto a plane with a user dt (forced past the check)."""
    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=e, friction=0.3,
                                stiffness=1e4))
    b.add_bodies("boxes", s, m, [[0.0, 0.0, 0.012], [0.03, 0.0, 0.02]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=24, n_frames=n_frames, dt=dt, force=True)


def test_energy_growth_stops_the_bake_and_keeps_the_frames():
    # Past the critical step the explicit spring gains energy every contact: the
    # guard must stop it as energy growth (before it becomes NaN), name the body,
    # and hand back the frames recorded so far.
    auto = bouncing_boxes("auto")
    crit = 2.0 / auto.omega_max           # undamped critical step (e = 1)
    model = bouncing_boxes(1.0 / 24 / math.floor(1.0 / 24 / (1.3 * crit)))
    with pytest.raises(BakeFailure) as info:
        Simulator(model).advance(model.initial_state())
    msg = str(info.value)
    assert "energy grew" in msg and "boxes[" in msg and "t = " in msg and "dt" in msg
    kept = info.value.frames
    assert 1 <= kept.n_frames < model.n_frames
    assert np.isfinite(kept.x).all()


def test_stable_run_is_not_stopped():
    # the same scene at dt auto: lossless bounces keep their energy, no guard trips
    model = bouncing_boxes("auto")
    frames = Simulator(model).advance(model.initial_state())
    assert frames.n_frames == model.n_frames


def test_unforeseen_speed_stops_the_bake():
    # A ball launched far faster than dt was chosen for (dt given, forced): it
    # would cross the plane in one step. The guard stops it at frame 1, still in
    # flight, before it reaches the plane.
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.0))
    b.add_bodies("ball", s, m, [[0.0, 0.0, 20.0]], velocities=[[0.0, 0.0, -200.0]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=24, n_frames=10, dt=1.0 / 2400, force=True)
    with pytest.raises(BakeFailure) as info:
        Simulator(model).advance(model.initial_state())
    msg = str(info.value)
    assert "ball[0]" in msg and "per step" in msg and "frame 1 " in msg


def test_user_dt_above_critical_is_refused_without_force():
    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", stiffness=1e6))
    b.add_bodies("ball", s, m, [[0.0, 0.0, 0.02]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    with pytest.raises(StabilityError, match="critical step"):
        b.finalize(fps=24, n_frames=5, dt=1.0 / 240)


TUNNEL = """
[output]
fps = 24
duration = 0.2
[simulation]
sphere_diameter = 0.01
dt = {dt}
[materials.m]
restitution = 0.5
friction = 0.3
stiffness = 1000.0
[shapes.ball]
builtin = "sphere"
diameter = 0.01
[[bodies]]
name = "ball"
shape = "ball"
material = "m"
layout = "single"
position = [0.0, 0.0, 0.5]
velocity = [0.0, 0.0, -60.0]
[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "m"
"""


def test_bake_refuses_tunnelling_and_names_the_fix(tmp_path):
    # soft user stiffness + dt auto: the step is long for a 60 m/s ball; bake
    # refuses with the check's message (one line, exit 1, nothing written)
    scene = tmp_path / "tunnel.toml"
    scene.write_text(TUNNEL.format(dt='"auto"'))
    out = tmp_path / "o.usdc"
    res = CliRunner().invoke(app, ["bake", str(scene), "-o", str(out), "--quiet",
                                   "--cache-dir", str(tmp_path / "c")])
    assert res.exit_code != 0
    msg = str(res.exception) + res.output
    assert "diameter per step" in msg and "stiffness" in msg and "--force" in msg
    assert not out.exists()


@pytest.mark.parametrize("partner", [None, "kinematic", "emitted"])
def test_travel_guard_only_where_a_contact_is_possible(partner):
    # A ball at 200 m/s with a forced dt that moves it 8 diameters per step. Alone,
    # nothing can touch it (dt "auto" would be the free-flight step): the guard and
    # the check's closing-pair finding leave it alone and it flies the whole run. A
    # kinematic body or a body emitted later far off makes a contact possible: both
    # stop it, as the plane of test_unforeseen_speed_stops_the_bake does.
    from dempipe.check.stability import analyze
    from dempipe.sim.motion import Motion

    b = ModelBuilder(D)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.0))
    b.add_bodies("ball", s, m, [[0.0, 0.0, 20.0]], velocities=[[0.0, 0.0, -200.0]])
    if partner == "kinematic":
        b.add_bodies("post", s, m, [[5.0, 0.0, 0.0]], kinematic=True,
                     motion=Motion(velocity=(0.0, 0.0, 0.0)))
    elif partner == "emitted":
        b.add_bodies("late", s, m, [[5.0, 0.0, 0.0]], start_time=0.2)
    model = b.finalize(fps=24, n_frames=10, dt=1.0 / 2400, force=True)
    assert model.contact_possible == (partner is not None)
    tunnel = [f for f in analyze(model).findings if f.code == "tunnelling"]
    if partner is None:
        frames = Simulator(model).advance(model.initial_state())
        assert frames.n_frames == model.n_frames and not tunnel
        # free flight: the velocity is exact under symplectic Euler
        assert frames.v[-1, 0, 2] == pytest.approx(-200.0 - 9.81 * frames.times[-1], rel=1e-9)
    else:
        assert tunnel and tunnel[0].level == "error"
        with pytest.raises(BakeFailure, match=r"ball\[0\].*per step"):
            Simulator(model).advance(model.initial_state())


FREE_FALL = """
[output]
fps = 24
duration = 2.0
[simulation]
resolution = 4
[shapes.box]
builtin = "box"
[[bodies]]
name = "b"
shape = "box"
layout = "single"
position = [0.0, 0.0, 0.1]
"""


def test_a_long_free_fall_with_nothing_to_hit_bakes_whole(tmp_path):
    # One box and no colliders: dt "auto" is the free-flight step (1/240 s) whatever the
    # speed, and there is nothing to pass through. The check says so (no closing-pair
    # finding; only that the box falls for the whole shot, nothing being under it) and
    # the bake agrees: 2 s of fall, to 19.6 m/s (8 diameters per step), with no
    # refusal, no per-step warning and no guard tripping.
    import dempipe
    from dempipe.pipeline.check import analyze_scene
    from dempipe.spheres.cache import SphereCache

    scene = tmp_path / "fall.toml"
    scene.write_text(FREE_FALL)
    cache = SphereCache(tmp_path / "c")
    report = analyze_scene(scene, cache=cache)
    assert report.ok and report.dt == pytest.approx(1.0 / 240.0)
    assert not report.pairs, report.format()
    assert [f.code for f in report.findings] == ["nothing-below"], report.format()
    assert "19.6 m in 2 s" in report.findings[0].message
    said = []
    result = dempipe.bake(scene, tmp_path / "fall.usdc", device="cpu", cache=cache,
                          warn=said.append, checkpoints=False)
    assert not result.partial and result.path.exists()
    assert not [w for w in said if "per step" in w], said
    model = dempipe.build_model(dempipe.load_scene(scene), cache=cache)
    frames = Simulator(model).advance(model.initial_state())
    assert frames.n_frames == 49 and frames.times[-1] == pytest.approx(2.0)
    assert frames.v[-1, 0, 2] == pytest.approx(-9.81 * 2.0, rel=1e-9)
