"""`dempipe scene export`: the stage and, beside it, the settings a stage cannot hold,
so that baking the export gives the TOML scene's own settings (docs/usd-input.md)."""

from dataclasses import replace

import pytest

pytest.importorskip("pxr")

from dempipe.pipeline.export import export_scene, settings_path  # noqa: E402
from dempipe.scene.build import build_model  # noqa: E402
from dempipe.scene.load import load_scene  # noqa: E402

SCENE = """
[output]
fps = 12
duration = 0.25

[simulation]
{simulation}

[materials.wood]
density = 700.0

[shapes.box]
builtin = "box"

[[bodies]]
name = "box"
shape = "box"
material = "wood"
position = [0.0, 0.0, 1.0]

[[colliders]]
type = "plane"
material = "wood"
"""


def test_the_settings_a_stage_cannot_hold_are_written_beside_it(tmp_path):
    scene = tmp_path / "shot.toml"
    scene.write_text(SCENE.format(simulation="resolution = 5\nseed = 7\n"
                                  "stiffness_target_overlap = 0.09\nspheres = \"surface\"\n"
                                  "[simulation.sleep]\ntime = 0.5"))
    stage, settings = export_scene(scene, tmp_path / "out" / "shot.usda")
    assert settings == settings_path(stage) == tmp_path / "out" / "shot.settings.toml"
    want = load_scene(scene).simulation
    got = load_scene(settings)          # the stage, with the settings over it
    # gravity stays the stage's (a DCC may change it there), as a float attribute
    assert got.simulation.gravity == pytest.approx(want.gravity, rel=1e-7)
    assert replace(got.simulation, gravity=want.gravity) == want
    assert got.usd is not None and got.usd.stage_path == stage.resolve()
    # the same model as the TOML's (the stage alone takes the default resolution)
    a, b = build_model(load_scene(scene)), build_model(got)
    # (a stage's sizes are float attributes: the same to float32)
    assert a.n_spheres == b.n_spheres and b.diameter == pytest.approx(a.diameter, rel=1e-6)
    assert b.pair_k[0, 0] == pytest.approx(a.pair_k[0, 0], rel=1e-5)
    assert build_model(load_scene(stage)).diameter != pytest.approx(a.diameter, rel=0.1)


def test_a_scene_at_the_default_settings_gets_no_settings_file(tmp_path):
    scene = tmp_path / "plain.toml"
    scene.write_text(SCENE.format(simulation=""))
    stage, settings = export_scene(scene, tmp_path / "plain.usdc")
    assert settings is None and not settings_path(stage).exists()
