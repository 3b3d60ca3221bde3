"""What `dempipe check` said was safe and the bake then stopped on, predicted now:
an emitter whose bodies start inside each other, a kinematic body spinning about its
own centre. The check (analyze_scene) and the bake's refusal before simulating; no
kernel is compiled."""

import pytest

from dempipe.check.prescribed import surface_speed
from dempipe.errors import StabilityError
from dempipe.pipeline.bake import bake
from dempipe.pipeline.check import analyze_scene
from dempipe.scene.build import build_model
from dempipe.scene.load import load_scene
from dempipe.spheres.cache import SphereCache

SCENE = """
[output]
fps = 24
duration = 0.5

[simulation]
resolution = 2

[shapes.ball]
builtin = "sphere"
diameter = 0.1

[shapes.paddle]
builtin = "box"
size = [0.3, 0.04, 0.04]

[[bodies]]
name = "rain"
shape = "ball"
layout = "emit"
region_min = [-0.3, -0.3, 0.5]
region_max = [0.3, 0.3, 0.6]
rate = {rate}
count = 50
start_time = 0.1

[[bodies]]
name = "paddle"
shape = "paddle"
position = [0.0, 0.6, 0.1]
kinematic = true
[bodies.motion]
angular_velocity = [0.0, 0.0, {spin}]

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
"""


@pytest.fixture
def scene(tmp_path):
    def write(rate=10.0, spin=2.0):
        p = tmp_path / "s.toml"
        p.write_text(SCENE.format(rate=rate, spin=spin))
        return p
    return write


def _errors(report):
    return {f.code: f.message for f in report.errors}


def test_emitter_whose_bodies_start_inside_each_other_is_an_error(scene, tmp_path):
    cache = SphereCache(tmp_path / "cache")
    assert "emission-overlap" not in _errors(analyze_scene(scene(rate=10.0), cache=cache))
    errors = _errors(analyze_scene(scene(rate=1e9), cache=cache))
    assert "emission-overlap" in errors and "rain[" in errors["emission-overlap"], errors
    with pytest.raises(StabilityError, match="deep in rain"):
        bake(scene(rate=1e9), tmp_path / "o.usda", device="cpu", cache=cache)
    assert not (tmp_path / "o.usda").exists()


def test_a_body_spinning_about_its_centre_has_a_surface_speed(scene, tmp_path):
    # |w| times the paddle's reach: 2 rad/s x 0.15 m = 0.3 m/s at least, never 0
    cache = SphereCache(tmp_path / "cache")
    model = build_model(load_scene(scene(spin=2.0)), cache=cache)
    v, b = surface_speed(model)
    assert v >= 2.0 * 0.15 and model.body_name(b) == "paddle[0]"
    errors = _errors(analyze_scene(scene(spin=1e6), cache=cache))
    assert "prescribed-speed" in errors and "paddle[0]" in errors["prescribed-speed"], errors
    with pytest.raises(StabilityError, match="paddle"):
        bake(scene(spin=1e6), tmp_path / "o.usda", device="cpu", cache=cache)


HEAVY = """
[output]
fps = 24
duration = 0.3

[simulation]
resolution = 3

[materials.light]
density = 1000.0

[materials.heavy]
density = {density}

[shapes.ball]
builtin = "sphere"
diameter = 0.1

[shapes.box]
builtin = "box"
size = [0.08, 0.06, 0.05]

[[bodies]]
name = "balls"
shape = "ball"
material = "light"
layout = "grid"
origin = [-0.1, -0.1, 0.06]
dims = [2, 2, 1]
spacing = 0.12

[[bodies]]
name = "boxes"
shape = "box"
material = "heavy"
position = [0.0, 0.0, 0.3]

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "light"
"""


def test_a_body_no_load_sharing_saves_is_an_error_under_auto_stiffness(tmp_path):
    # a density ratio of 1e6: soft-contact alone says "a warning" (several contacts
    # share the load, it says); the box's face is one patch, and it sinks past the guard
    cache = SphereCache(tmp_path / "cache")
    p = tmp_path / "h.toml"
    p.write_text(HEAVY.format(density=10000.0))
    assert "sinking" not in _errors(analyze_scene(p, cache=cache))
    p.write_text(HEAVY.format(density=1e9))
    errors = _errors(analyze_scene(p, cache=cache))
    assert "sinking" in errors and "boxes[0]" in errors["sinking"], errors
    with pytest.raises(StabilityError, match="one patch"):
        bake(p, tmp_path / "o.usda", device="cpu", cache=cache, warn=[].append)
