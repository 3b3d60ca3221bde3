"""`dempipe check` predicts what the bake does: a holdout suite of scenes
at a fixed dt, none of them used to tune the estimate. For each, check says unsafe
exactly when the bake (with --force, so that it runs at all) diverges: a guard
stops it. docs/stability.md has the table of these runs."""

import pytest

from dempipe.pipeline.bake import bake
from dempipe.spheres.cache import SphereCache
from dempipe.errors import StabilityError
from dempipe.pipeline.check import analyze_scene

BOXES = """
[output]
fps = 24
duration = {duration}

[simulation]
resolution = 4
dt = {dt}

[shapes.box]
builtin = "box"

[[bodies]]
name = "boxes"
shape = "box"
layout = "grid"
origin = [0.0, 0.0, 0.0205]
dims = [1, 1, {stack}]
spacing = 0.041

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
"""

# (name, stack height, dt [s], whether the bake diverges): the two-box stack that
# diverged (check said OK at dt / critical 0.52, the bake stopped at frame 1), the same
# stack at a safe dt, a single box resting on the floor on both sides of its
# flat-face limit (16 spheres of a face in parallel)
HOLDOUT = [
    ("stack of two, dt 1e-4", 2, 1e-4, True),
    ("stack of two, dt 2.5e-5", 2, 2.5e-5, False),
    ("one box on the floor, dt 1e-4", 1, 1e-4, False),
    ("one box on the floor, dt 2.5e-4", 1, 2.5e-4, True),
]


@pytest.mark.slow
@pytest.mark.parametrize("name, stack, dt, diverges", HOLDOUT, ids=[h[0] for h in HOLDOUT])
def test_check_says_unsafe_exactly_when_bake_diverges(tmp_path, name, stack, dt, diverges):
    scene = tmp_path / "s.toml"
    scene.write_text(BOXES.format(duration=0.25, dt=dt, stack=stack))
    cache = SphereCache(tmp_path / "cache")
    report = analyze_scene(scene, cache=cache)
    unsafe = not report.ok
    try:
        r = bake(scene, tmp_path / "o.usdc", device="cpu", cache=cache, force=True)
        diverged = False
        assert r.report["completed"]
    except StabilityError as exc:
        diverged = "bake stopped at frame" in str(exc)
        assert diverged, exc
    print(f"{name}: check {'unsafe' if unsafe else 'OK'} (dt / critical "
          f"{report.dt_ratio:.2f}); bake {'diverged' if diverged else 'completed'}")
    assert diverged == diverges
    assert unsafe == diverged, report.format()
