"""Bad input through the Python API (Material, ModelBuilder, finalize, bake): a
DempipeError naming the parameter, before any simulation, as the scene readers give
for the same mistakes in a file. Before, a negative density made a body that hung in
the air, fps = -24 ran backwards in time, and bake(layout="bogus") simulated the whole
shot before refusing."""

import math

import numpy as np
import pytest

from dempipe.errors import DeviceError, ExportError, SceneError
from dempipe.mesh.shapes import build_shape
from dempipe.pipeline.bake import bake, parse_frame_range
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.materials import Material
from dempipe.spheres.sphere_set import build_sphere_set

SCENE = """
[output]
fps = 12
duration = 0.25
[simulation]
resolution = 3
[shapes.box]
builtin = "box"
[[bodies]]
name = "box"
shape = "box"
position = [0.0, 0.0, 1.0]
[[colliders]]
type = "plane"
"""


@pytest.mark.parametrize("kw, key", [
    (dict(density=-700.0), "density"), (dict(density=0.0), "density"),
    (dict(restitution=2.0), "restitution"), (dict(restitution=-0.5), "restitution"),
    (dict(friction=math.nan), "friction"), (dict(friction=-1.0), "friction"),
    (dict(stiffness=0.0), "stiffness"), (dict(glue_damping=-1.0), "glue_damping")])
def test_a_material_out_of_range_is_refused(kw, key):
    with pytest.raises(SceneError, match=f"material 'w': {key} = "):
        Material("w", **kw)


@pytest.fixture(scope="module")
def box():
    mesh = build_shape("box", size=(0.05, 0.05, 0.05))
    return mesh, build_sphere_set(mesh, 0.01)


def builder(box):
    b = ModelBuilder(0.01)
    s = b.add_shape("box", *box)
    m = b.add_material(Material("wood", density=700.0))
    return b, s, m


def test_builder_refuses_what_cannot_be_simulated(box):
    b, s, m = builder(box)
    for call, words in [
            (lambda: b.add_bodies("g", s, m, [[0.0, 0.0, math.nan]]), "g: positions: "),
            (lambda: b.add_bodies("g", s, m, [[0.0, 0.0, 0.2]], rotations=[[0, 0, 0, 0]]),
             "length 0"),
            (lambda: b.add_bodies("g", s, m, [[0.0, 0.0, 0.2]], velocities=[[1.0, 2.0]]),
             "g: velocities: expected 3 numbers"),
            (lambda: b.add_bodies("g", 5, m, [[0.0, 0.0, 0.2]]), "shape index out of range"),
            (lambda: b.add_bodies("g", s, 7, [[0.0, 0.0, 0.2]]), "material index 7"),
            (lambda: b.add_plane((0, 0, 0), (0, 0, 0)), "has length 0")]:
        with pytest.raises(SceneError, match=words):
            call()
    b.add_bodies("g", s, m, [[0.0, 0.0, 0.2]])
    b.add_plane((0, 0, 0), (0, 0, 1), m)
    for kw, words in [(dict(fps=0), "fps: 0"), (dict(fps=-24.0), "fps: -24"),
                      (dict(n_frames=0), "n_frames: 0"),
                      (dict(contact_law="nope"), "unknown law 'nope'")]:
        with pytest.raises(SceneError, match=words):
            b.finalize(**kw)
    with pytest.warns(UserWarning, match="does not point down the stage's up axis Y"):
        b.finalize(fps=10, n_frames=2, up_axis="Y")    # gravity along -z, a Y-up stage
    model = b.finalize(fps=10, n_frames=11)    # what was refused above, given right
    assert model.body_mass[0] == pytest.approx(700.0 * 0.05 ** 3)


def test_bake_refuses_a_bad_layout_or_thread_count_before_any_work(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE)
    out = tmp_path / "o.usdc"
    with pytest.raises(ExportError, match="unknown USD layout 'bogus'"):
        bake(scene, out, layout="bogus")
    with pytest.raises(DeviceError, match="threads: 0 must be"):
        bake(scene, out, threads=0)
    with pytest.raises(SceneError, match="resolution or sphere_diameter, not both"):
        bake(scene, out, simulation=dict(resolution=3, sphere_diameter=0.05))
    with pytest.raises(SceneError, match="expected two paths .* got Scene and PosixPath"):
        from dempipe.scene.load import load_scene

        bake(load_scene(scene), out)
    # nothing was simulated, so nothing was left to resume
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.toml"]


def test_frame_ranges_say_what_is_wrong():
    with pytest.raises(SceneError, match="2:1 ends before it starts"):
        parse_frame_range("2:1", 4, 0)
    with pytest.raises(SceneError, match="0:8 reaches outside the scene's frames 1:36"):
        parse_frame_range("0:8", 36, 1)
    with pytest.raises(SceneError, match="50:60 is outside the scene's frames 1:36"):
        parse_frame_range("50:60", 36, 1)
    assert parse_frame_range("2:3", 36, 1) == (1, 2)
    assert np.array_equal(parse_frame_range(None, 36, 1), (0, 35))
