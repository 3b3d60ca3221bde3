"""Scene file: parsing, defaults, validation messages, body expansion."""

import textwrap
import types

import numpy as np
import pytest

from dempipe.scene import toml_reader as sc
from dempipe.errors import SceneError
from dempipe.sim.motion import Key, Motion
from dempipe.scene.load import load_scene, parse_scene
from dempipe.scene.placement import random_quaternions
from dempipe.scene.data import DEFAULT_RESOLUTION, OutputSettings, SleepSettings
from dempipe.scene.placement import collider_frame, expand_bodies, group_frame

# A stand-in for dempipe.mesh.shapes.SHAPES, so these tests do not depend on the
# exact parameter list of the real built-in shapes.
FAKE_SHAPES = {
    "pawn": types.SimpleNamespace(params={"height": None, "base_diameter": None}),
    "torus": types.SimpleNamespace(params={"major_radius": None, "minor_radius": None}),
    "box": types.SimpleNamespace(params={"size": None}),
}


@pytest.fixture(autouse=True)
def fake_registry(monkeypatch):
    monkeypatch.setattr(sc, "_load_shape_registry", lambda: FAKE_SHAPES)


@pytest.fixture
def obj_file(tmp_path):
    """A small closed mesh written with trimesh to tmp_path/meshes/rock.obj."""
    trimesh = pytest.importorskip("trimesh")
    (tmp_path / "meshes").mkdir()
    path = tmp_path / "meshes" / "rock.obj"
    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(path)
    return path


FULL = """\
[output]
fps = 30
duration = 2.0
up_axis = "Z"
meters_per_unit = 0.01
start_frame = 101

[simulation]
sphere_diameter = 0.01
gravity = [0.0, 0.0, -5.0]
dt = 1e-4
device = "cpu"
seed = 7
stiffness_target_overlap = 0.05
dt_safety = 0.5
sleeping = false

[simulation.sleep]
linear_speed = 0.01
angular_speed = 0.1
time = 0.5

[materials.wood]
density = 700.0
restitution = 0.3
friction = 0.4
stiffness = 2e5

[materials.rubber]
density = 1100
restitution = 0.8

[shapes.pawn]
builtin = "pawn"
height = 0.05

[shapes.rock]
mesh = "meshes/rock.obj"
scale = 2.0

[[bodies]]
name = "pawns"
shape = "pawn"
material = "wood"
count = 10
layout = "grid"
origin = [0.0, 0.0, 0.5]
dims = [2, 3, 4]
spacing = 0.06
rotation = "random"
velocity = [1.0, 0.0, 0.0]
angular_velocity = [0.0, 0.0, 3.0]

[[bodies]]
name = "ball"
shape = "rock"
layout = "single"
position = [0.0, 0.0, 2.0]
rotation = [2.0, 0.0, 0.0, 0.0]

[[bodies]]
name = "rain"
shape = "rock"
material = "rubber"
layout = "random"
count = 50
region_min = [-1.0, -1.0, 1.0]
region_max = [1.0, 1.0, 3.0]

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 2.0]

[[colliders]]
type = "box"
min = [-1.0, -1.0, 0.0]
max = [1.0, 1.0, 1.0]
open_top = false
thickness = 0.05
material = "wood"

[[colliders]]
type = "mesh"
name = "ring"
builtin = "torus"
major_radius = 0.5
minor_radius = 0.1
scale = 1.5
position = [0.0, 0.0, 0.2]
rotation = [1.0, 0.0, 0.0, 0.0]

[[colliders]]
type = "mesh"
mesh = "meshes/rock.obj"
"""

MINIMAL_SHAPES = """\
[shapes.pawn]
builtin = "pawn"
"""


def parse(text, tmp_path=None, name="scene.toml"):
    base = tmp_path if tmp_path is not None else "/nonexistent"
    return parse_scene(textwrap.dedent(text), f"{base}/{name}")


def minimal(body="", extra="", head=""):
    return (head + MINIMAL_SHAPES + extra
            + '\n[[bodies]]\nname = "p"\nshape = "pawn"\n' + body)


def error_of(text, tmp_path=None):
    with pytest.raises(SceneError) as info:
        parse(text, tmp_path)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith("scene.toml: ")
    return msg


# ----------------------------------------------------------------- valid scenes


def test_full_scene(tmp_path, obj_file):
    s = parse(FULL, tmp_path)
    assert s.path == (tmp_path / "scene.toml").resolve()
    o = s.output
    assert (o.fps, o.duration, o.up_axis, o.meters_per_unit, o.start_frame) == (30, 2.0, "Z", 0.01, 101)
    assert o.n_frames == 61
    sim = s.simulation
    assert sim.sphere_diameter == 0.01 and sim.resolution is None
    assert sim.gravity == (0.0, 0.0, -5.0)
    assert sim.dt == 1e-4 and sim.device == "cpu" and sim.seed == 7
    assert sim.stiffness_target_overlap == 0.05 and sim.dt_safety == 0.5
    assert sim.sleeping is False
    assert sim.sleep == SleepSettings(0.01, 0.1, 0.5)

    assert set(s.materials) == {"default", "wood", "rubber"}
    assert s.materials["default"] == sc.MaterialSpec("default", 1000.0, 0.5, 0.5, "auto")
    assert s.materials["wood"] == sc.MaterialSpec("wood", 700.0, 0.3, 0.4, 2e5)
    rubber = s.materials["rubber"]
    assert rubber.density == 1100.0 and isinstance(rubber.density, float)
    assert rubber.friction == 0.5 and rubber.stiffness == "auto"
    assert rubber.to_material().stiffness is None

    pawn = s.shapes["pawn"]
    assert pawn.builtin == "pawn" and pawn.params == {"height": 0.05} and pawn.mesh_path is None
    rock = s.shapes["rock"]
    assert rock.builtin is None and rock.mesh_path == obj_file.resolve() and rock.scale == 2.0

    pawns, ball, rain = s.bodies
    assert pawns.count == 10 and pawns.dims == (2, 3, 4) and pawns.spacing == (0.06,) * 3
    assert pawns.rotation == "random" and pawns.velocity == (1.0, 0.0, 0.0)
    assert pawns.angular_velocity == (0.0, 0.0, 3.0) and pawns.material == "wood"
    assert ball.count == 1 and ball.position == (0.0, 0.0, 2.0) and ball.material == "default"
    assert ball.rotation == (1.0, 0.0, 0.0, 0.0)
    assert rain.count == 50 and rain.region_min == (-1.0, -1.0, 1.0)
    assert s.n_bodies == 61

    plane, box, ring, bowl = s.colliders
    assert isinstance(plane, sc.PlaneCollider) and plane.normal == (0.0, 0.0, 1.0)
    assert plane.material == "default"
    assert isinstance(box, sc.BoxCollider) and box.open_top is False and box.thickness == 0.05
    assert box.material == "wood"
    assert isinstance(ring, sc.MeshCollider) and ring.builtin == "torus" and ring.name == "ring"
    assert ring.params == {"major_radius": 0.5, "minor_radius": 0.1} and ring.scale == 1.5
    assert ring.position == (0.0, 0.0, 0.2)
    assert isinstance(bowl, sc.MeshCollider) and bowl.mesh_path == obj_file.resolve()
    assert bowl.builtin is None

    with pytest.raises(Exception):  # frozen
        s.output.fps = 12


def test_defaults():
    s = parse(minimal())
    assert s.output == OutputSettings(24, 4.0, "Z", 1.0, 0)
    assert s.output.n_frames == 97
    sim = s.simulation
    assert sim.sphere_diameter is None and sim.resolution == DEFAULT_RESOLUTION == 12
    assert sim.gravity == (0.0, 0.0, -9.81)
    assert sim.dt == "auto" and sim.device == "auto" and sim.seed == 0
    assert sim.stiffness_target_overlap is None and sim.dt_safety is None
    assert sim.sleeping is True and sim.sleep == SleepSettings()
    assert list(s.materials) == ["default"]
    (g,) = s.bodies
    assert (g.layout, g.count, g.material, g.rotation) == ("single", 1, "default", "identity")
    assert g.position == (0.0, 0.0, 0.0) and g.velocity == (0.0, 0.0, 0.0)
    assert s.colliders == ()


def test_gravity_follows_up_axis():
    s = parse(minimal(head='[output]\nup_axis = "Y"\n'))
    assert s.output.up_axis == "Y"
    assert s.simulation.gravity == (0.0, -9.81, 0.0)
    s = parse(minimal(head='[output]\nup_axis = "Y"\n[simulation]\ngravity = [0, 0, -1]\n'))
    assert s.simulation.gravity == (0.0, 0.0, -1.0)


def test_plane_normal_default_follows_up_axis():
    s = parse(minimal(head='[output]\nup_axis = "Y"\n', body='[[colliders]]\ntype = "plane"\n'))
    assert s.colliders[0].normal == (0.0, 1.0, 0.0)


def test_resolution_only():
    s = parse(minimal(head="[simulation]\nresolution = 20\n"))
    assert s.simulation.resolution == 20 and s.simulation.sphere_diameter is None


def test_user_may_redefine_default_material():
    s = parse(minimal(extra="[materials.default]\ndensity = 500.0\n"))
    assert s.materials["default"].density == 500.0
    assert s.materials["default"].restitution == 0.5


def test_relative_mesh_path(tmp_path, obj_file):
    sub = tmp_path / "scenes"
    sub.mkdir()
    text = '[shapes.rock]\nmesh = "../meshes/rock.obj"\n[[bodies]]\nname = "r"\nshape = "rock"\n'
    (sub / "scene.toml").write_text(text)
    s = load_scene(sub / "scene.toml")
    assert s.shapes["rock"].mesh_path == obj_file.resolve()
    assert s.shapes["rock"].mesh_path.is_absolute()
    assert s.base_dir == sub.resolve()


# --------------------------------------------------------------------- expansion


def test_grid_expansion_z_up():
    s = parse(minimal(body='layout = "grid"\norigin = [1, 2, 3]\ndims = [2, 3, 2]\n'
                           'spacing = [0.1, 0.2, 0.5]\ncount = 8\n'))
    (p,) = expand_bodies(s)
    assert p.positions.shape == (8, 3) and p.positions.dtype == np.float64
    expected = [(1 + 0.1 * i, 2 + 0.2 * j, 3 + 0.5 * k)
                for k in range(2) for j in range(3) for i in range(2)][:8]
    np.testing.assert_allclose(p.positions, expected)
    np.testing.assert_array_equal(p.rotations, np.tile([1.0, 0, 0, 0], (8, 1)))
    assert p.velocities.shape == (8, 3) and p.angular_velocities.shape == (8, 3)


def test_grid_count_defaults_to_dims_product():
    s = parse(minimal(body='layout = "grid"\ndims = [2, 3, 4]\nspacing = 0.1\n'))
    assert s.bodies[0].count == 24
    assert expand_bodies(s)[0].positions.shape == (24, 3)


def test_grid_expansion_y_up():
    s = parse(minimal(head='[output]\nup_axis = "Y"\n',
                      body='layout = "grid"\ndims = [2, 2, 3]\nspacing = [1.0, 2.0, 10.0]\n'))
    (p,) = expand_bodies(s)
    # x fastest, then z (second horizontal), then y (up)
    expected = [(1.0 * i, 10.0 * k, 2.0 * j) for k in range(3) for j in range(2) for i in range(2)]
    np.testing.assert_allclose(p.positions, expected)


def _random_rot_scene(seed):
    return parse(minimal(head=f"[simulation]\nseed = {seed}\n",
                         body='layout = "grid"\ndims = [10, 10, 2]\nspacing = 0.1\n'
                              'rotation = "random"\nvelocity = [0, 0, -1]\n'))


def test_random_rotations_unit_and_reproducible():
    a = expand_bodies(_random_rot_scene(3))[0]
    b = expand_bodies(_random_rot_scene(3))[0]
    c = expand_bodies(_random_rot_scene(4))[0]
    assert a.rotations.shape == (200, 4)
    np.testing.assert_allclose(np.linalg.norm(a.rotations, axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(a.rotations, b.rotations)
    assert not np.allclose(a.rotations, c.rotations)
    assert len({tuple(q) for q in a.rotations}) == 200
    np.testing.assert_array_equal(a.velocities, np.tile([0.0, 0.0, -1.0], (200, 1)))


def test_random_rotations_are_uniform():
    q = random_quaternions(np.random.default_rng(0), 20000)
    # uniform on SO(3): every component has mean 0 and E[c²] = 1/4
    np.testing.assert_allclose(q.mean(axis=0), 0.0, atol=0.02)
    np.testing.assert_allclose((q**2).mean(axis=0), 0.25, atol=0.01)


def test_groups_are_independent():
    one = minimal(body='layout = "random"\ncount = 5\nregion_min = [0, 0, 0]\n'
                       'region_max = [1, 1, 1]\nrotation = "random"\n')
    two = one + '[[bodies]]\nname = "q"\nshape = "pawn"\nrotation = "random"\n'
    a = expand_bodies(parse(one))[0]
    b = expand_bodies(parse(two))
    np.testing.assert_array_equal(a.positions, b[0].positions)
    np.testing.assert_array_equal(a.rotations, b[0].rotations)
    assert not np.allclose(b[1].rotations[0], a.rotations[0])


def test_random_layout_within_region():
    s = parse(minimal(body='layout = "random"\ncount = 500\nregion_min = [-1, 2, 0]\n'
                           'region_max = [1, 3, 0.5]\n'))
    (p,) = expand_bodies(s)
    assert p.positions.shape == (500, 3)
    assert (p.positions >= [-1, 2, 0]).all() and (p.positions <= [1, 3, 0.5]).all()
    assert p.positions[:, 0].std() > 0.3  # spread over the box, not piled up
    np.testing.assert_array_equal(p.positions, expand_bodies(s)[0].positions)


def test_fixed_rotation_normalized():
    s = parse(minimal(body="rotation = [0, 0, 0, 3]\n"))
    (p,) = expand_bodies(s)
    np.testing.assert_allclose(p.rotations, [[0, 0, 0, 1.0]])


# ------------------------------------------------------------------------- errors


def test_file_not_found(tmp_path):
    with pytest.raises(SceneError, match=r"^scene\.toml: file not found$"):
        load_scene(tmp_path / "scene.toml")


def test_a_mesh_given_as_the_scene(tmp_path):
    # `dempipe bake rock.obj`: not a TOML syntax error at line 1, but what to give
    (tmp_path / "rock.obj").write_text("v 0 0 0\n")
    with pytest.raises(SceneError, match=r"^rock\.obj: a mesh, not a scene: give a scene "
                                         r"file .*mesh = \"rock\.obj\""):
        load_scene(tmp_path / "rock.obj")


def test_toml_syntax_error_names_line():
    text = minimal() + 'count = \n'
    line = text.splitlines().index("count = ") + 1
    msg = error_of(text)
    assert msg.startswith(f"scene.toml: line {line}: ")
    assert "Invalid value" in msg


def test_toml_syntax_error_at_end_of_document():
    text = minimal() + 'velocity = "abc\n'
    msg = error_of(text)
    assert f"scene.toml: line {len(text.splitlines())}:" in msg


def test_unknown_top_level_key():
    msg = error_of(minimal() + '[outptu]\nfps = 24\n')
    assert "scene.toml: outptu: unknown section" in msg
    assert "did you mean 'output'?" in msg


@pytest.mark.parametrize("text, key, hint", [
    (minimal(head="[output]\nfsp = 24\n"), "output.fsp", "'fps'"),
    (minimal(head="[simulation]\nsphere_diam = 0.01\n"), "simulation.sphere_diam",
     "'sphere_diameter'"),
    (minimal(head="[simulation.sleep]\nlinear = 0.1\n"), "simulation.sleep.linear",
     "'linear_speed'"),
    (minimal(extra="[materials.wood]\ndensty = 1.0\n"), "materials.wood.densty", "'density'"),
    (minimal(body="cont = 3\n"), "bodies[0].cont", "'count'"),
    (minimal(body='[[colliders]]\ntype = "plane"\nnormall = [0, 0, 1]\n'),
     "colliders[0].normall", "'normal'"),
])
def test_unknown_nested_key(text, key, hint):
    msg = error_of(text)
    assert f"scene.toml: {key}: unknown key" in msg
    assert f"did you mean {hint}?" in msg


def test_layout_key_on_wrong_layout():
    msg = error_of(minimal(body="dims = [2, 2, 2]\n"))
    assert "bodies[0].dims: only used with layout = 'grid'" in msg


@pytest.mark.parametrize("text, key, expect", [
    (minimal(head='[output]\nfps = "24"\n'), "output.fps", "expected a positive integer, got string '24'"),
    (minimal(head="[output]\nfps = 24.5\n"), "output.fps", "expected a positive integer"),
    (minimal(head="[output]\nduration = true\n"), "output.duration", "got boolean true"),
    (minimal(head="[output]\nduration = nan\n"), "output.duration", "finite"),
    (minimal(head="[simulation]\ngravity = [0, -9.81]\n"), "simulation.gravity",
     "expected an array of 3 numbers, got array of length 2"),
    # the example is a gravity, not zeros
    (minimal(head="[simulation]\ngravity = -9.81\n"), "simulation.gravity",
     "e.g. gravity = [0.0, 0.0, -9.81]"),
    (minimal(head="[simulation]\ngravity = [0, 0, inf]\n"), "simulation.gravity[2]", "finite"),
    (minimal(head='[simulation]\ndevice = "gpu"\n'), "simulation.device", "known: auto, cpu, cuda"),
    (minimal(head='[simulation]\ndt = "fast"\n'), "simulation.dt",
     "known: auto; or a step in seconds"),
    (minimal(extra='[materials.wood]\nstiffness = "hard"\n'), "materials.wood.stiffness",
     "known: auto; or a stiffness in N/m"),
    (minimal(head="[simulation]\nsleeping = 1\n"), "simulation.sleeping", "expected a boolean"),
    (minimal(body='velocity = [0, "1", 0]\n'), "bodies[0].velocity[1]", "got string '1'"),
    (minimal(body="rotation = 5\n"), "bodies[0].rotation", "expected"),
    # the example is a turn a scene accepts (not the zero quaternion it refuses)
    (minimal(body="rotation = [0.7, 0.7, 0.0]\n"), "bodies[0].rotation",
     "e.g. rotation = [1.0, 0.0, 0.0, 0.0]"),
    (minimal(body='layout = "grid"\ndims = [2, 2.5, 2]\nspacing = 0.1\n'), "bodies[0].dims[1]",
     "expected a positive integer"),
    (minimal(body='layout = "hex"\n'), "bodies[0].layout", "known: single, grid, random"),
    ("[output]\nfps = 24\n" + MINIMAL_SHAPES + "[bodies]\nname = 'p'\nshape = 'pawn'\n",
     "bodies", "expected an array of tables"),
])
def test_bad_types(text, key, expect):
    msg = error_of(text)
    assert f"scene.toml: {key}: " in msg
    assert expect in msg


@pytest.mark.parametrize("text, key", [
    (minimal(head="[output]\nfps = -24\n"), "output.fps"),
    (minimal(head="[output]\nfps = 0\n"), "output.fps"),
    (minimal(head="[output]\nduration = 0\n"), "output.duration"),
    (minimal(extra="[materials.wood]\nrestitution = 1.5\n"), "materials.wood.restitution"),
    (minimal(extra="[materials.wood]\ndensity = -1\n"), "materials.wood.density"),
    (minimal(extra="[materials.wood]\nfriction = -0.1\n"), "materials.wood.friction"),
    (minimal(extra="[materials.wood]\nstiffness = 0\n"), "materials.wood.stiffness"),
    (minimal(head="[simulation]\nsphere_diameter = 0\n"), "simulation.sphere_diameter"),
    (minimal(head="[simulation]\nstiffness_target_overlap = 0.6\n"),
     "simulation.stiffness_target_overlap"),
    (minimal(head="[simulation]\ndt_safety = 0\n"), "simulation.dt_safety"),
    (minimal(head="[simulation]\nseed = -1\n"), "simulation.seed"),
    (minimal(body="count = 0\n"), "bodies[0].count"),
])
def test_out_of_range(text, key):
    msg = error_of(text)
    assert f"scene.toml: {key}: " in msg
    assert "out of range" in msg


def test_restitution_message():
    msg = error_of(minimal(extra="[materials.wood]\nrestitution = 1.5\n"))
    assert msg == ("scene.toml: materials.wood.restitution: 1.5 is out of range "
                   "(expected a number in [0, 1])")


def test_missing_mesh_file(tmp_path):
    text = '[shapes.rock]\nmesh = "meshes/rok.obj"\n[[bodies]]\nname = "r"\nshape = "rock"\n'
    msg = error_of(text, tmp_path)
    assert "scene.toml: shapes.rock.mesh: mesh file not found" in msg
    assert str((tmp_path / "meshes" / "rok.obj").resolve()) in msg


def test_missing_collider_mesh_file(tmp_path):
    msg = error_of(minimal(body='[[colliders]]\ntype = "mesh"\nmesh = "bowl.obj"\n'), tmp_path)
    assert "scene.toml: colliders[0].mesh: mesh file not found" in msg
    assert str((tmp_path / "bowl.obj").resolve()) in msg


def test_unknown_shape(tmp_path, obj_file):
    text = (MINIMAL_SHAPES + '[shapes.rock]\nmesh = "meshes/rock.obj"\n'
            '[[bodies]]\nname = "a"\nshape = "pawn"\n[[bodies]]\nname = "b"\nshape = "rok"\n')
    msg = error_of(text, tmp_path)
    assert msg.startswith("scene.toml: bodies[1].shape: unknown shape 'rok' (")
    assert "did you mean 'rock'?" in msg and "known: pawn, rock" in msg


def test_unknown_builtin_and_parameter():
    msg = error_of('[shapes.pawn]\nbuiltin = "pwn"\n[[bodies]]\nname = "p"\nshape = "pawn"\n')
    assert "scene.toml: shapes.pawn.builtin: unknown built-in shape 'pwn'" in msg
    assert "did you mean 'pawn'?" in msg
    msg = error_of('[shapes.pawn]\nbuiltin = "pawn"\nheigth = 0.05\n'
                   '[[bodies]]\nname = "p"\nshape = "pawn"\n')
    assert msg == ("scene.toml: shapes.pawn.heigth: unknown parameter for 'pawn' "
                   "(did you mean 'height'? known: height, base_diameter)")


def test_scale_on_builtin_is_an_error():
    msg = error_of('[shapes.pawn]\nbuiltin = "pawn"\nscale = 2.0\n'
                   '[[bodies]]\nname = "p"\nshape = "pawn"\n')
    assert "scene.toml: shapes.pawn.scale: scale applies to mesh files only" in msg


def test_shape_needs_builtin_or_mesh():
    assert "scene.toml: shapes.pawn: needs builtin or mesh" in error_of(
        '[shapes.pawn]\nheight = 1.0\n[[bodies]]\nname = "p"\nshape = "pawn"\n')


def test_unknown_material():
    msg = error_of(minimal(extra="[materials.wood]\n", body='material = "wod"\n'))
    assert "scene.toml: bodies[0].material: unknown material 'wod'" in msg
    assert "did you mean 'wood'?" in msg and "known: default, wood" in msg
    msg = error_of(minimal(body='[[colliders]]\ntype = "plane"\nmaterial = "steel"\n'))
    assert "scene.toml: colliders[0].material: unknown material 'steel'" in msg


def test_count_larger_than_dims():
    msg = error_of(minimal(body='layout = "grid"\ncount = 30\ndims = [2, 3, 4]\nspacing = 0.1\n'))
    assert "scene.toml: bodies[0].count: count = 30 is larger than dims = [2, 3, 4]" in msg
    assert "(24)" in msg


def test_single_layout_count():
    msg = error_of(minimal(body="count = 3\n"))
    assert "scene.toml: bodies[0].count: layout 'single' places one body" in msg


def test_both_diameter_and_resolution():
    msg = error_of(minimal(head="[simulation]\nsphere_diameter = 0.01\nresolution = 10\n"))
    assert "scene.toml: simulation.resolution: both sphere_diameter and resolution" in msg


def test_zero_normal():
    msg = error_of(minimal(body='[[colliders]]\ntype = "plane"\nnormal = [0, 0, 0]\n'))
    assert "scene.toml: colliders[0].normal: zero normal" in msg


def test_zero_quaternion():
    msg = error_of(minimal(body="rotation = [0, 0, 0, 0]\n"))
    assert "scene.toml: bodies[0].rotation: zero quaternion" in msg


def test_box_min_above_max():
    msg = error_of(minimal(body='[[colliders]]\ntype = "box"\nmin = [0, 0, 0]\nmax = [1, -1, 1]\n'))
    assert "scene.toml: colliders[0].max[1]:" in msg


def test_unknown_collider_type():
    msg = error_of(minimal(body='[[colliders]]\ntype = "sphere"\n'))
    assert "scene.toml: colliders[0].type: unknown value 'sphere'" in msg
    assert "known: plane, box, mesh" in msg


def test_duplicate_group_names():
    msg = error_of(minimal() + '[[bodies]]\nname = "p"\nshape = "pawn"\n')
    assert "scene.toml: bodies[1].name: duplicate group name 'p'" in msg
    assert "bodies[0]" in msg


@pytest.mark.parametrize("name", ["2pawns", "my pawns", "pawns-1", ""])
def test_bad_usd_name(name):
    msg = error_of(MINIMAL_SHAPES + f'[[bodies]]\nname = "{name}"\nshape = "pawn"\n')
    assert f"scene.toml: bodies[0].name: {name!r} is not a valid USD prim name" in msg


def test_missing_required_keys():
    assert "scene.toml: bodies[0].shape: missing required key" in error_of(
        MINIMAL_SHAPES + '[[bodies]]\nname = "p"\n')
    assert "scene.toml: bodies[0].name: missing required key" in error_of(
        MINIMAL_SHAPES + '[[bodies]]\nshape = "pawn"\n')
    assert "scene.toml: bodies[0].region_min: missing required key" in error_of(
        minimal(body='layout = "random"\ncount = 3\n'))
    assert "scene.toml: bodies[0].dims: missing required key" in error_of(
        minimal(body='layout = "grid"\nspacing = 0.1\n'))
    assert "scene.toml: colliders[0].type: missing required key" in error_of(
        minimal(body='[[colliders]]\npoint = [0, 0, 0]\n'))
    assert "scene.toml: bodies: no body groups" in error_of(MINIMAL_SHAPES)


def test_load_scene_uses_file_name(tmp_path):
    path = tmp_path / "drop.toml"
    path.write_text(minimal(body="cont = 1\n"))
    with pytest.raises(SceneError, match=r"^drop\.toml: bodies\[0\]\.cont: unknown key"):
        load_scene(path)


# ------------------------------------------------- against the real shape registry


def test_real_shape_registry(monkeypatch):
    """When dempipe.mesh.shapes exists, builtin names and parameters are checked against it."""
    monkeypatch.undo()  # use the real registry
    registry = sc._load_shape_registry()
    if registry is None:
        pytest.skip("dempipe.mesh.shapes is not there yet")
    name, spec = next(iter(registry.items()))
    params = list(spec.params)
    ok = f'[shapes.s]\nbuiltin = "{name}"\n[[bodies]]\nname = "b"\nshape = "s"\n'
    assert parse_scene(ok, "scene.toml").shapes["s"].builtin == name
    bad = f'[shapes.s]\nbuiltin = "{name}"\nnot_a_param = 1.0\n[[bodies]]\nname = "b"\nshape = "s"\n'
    with pytest.raises(SceneError) as info:
        parse_scene(bad, "scene.toml")
    msg = str(info.value)
    assert f"scene.toml: shapes.s.not_a_param: unknown parameter for {name!r}" in msg
    for p in params:
        assert p in msg


@pytest.fixture
def real_registry(monkeypatch):
    monkeypatch.undo()
    registry = sc._load_shape_registry()
    if registry is None:
        pytest.skip("dempipe.mesh.shapes is not there yet")
    return registry


def test_real_pawn_parameters(real_registry):
    if "pawn" not in real_registry:
        pytest.skip("no built-in pawn")
    s = parse_scene('[shapes.pawn]\nbuiltin = "pawn"\nheight = 1\n'
                       '[[bodies]]\nname = "p"\nshape = "pawn"\n', "scene.toml")
    assert s.shapes["pawn"].params == {"height": 1.0}
    with pytest.raises(SceneError) as info:
        parse_scene('[shapes.pawn]\nbuiltin = "pawn"\nheigth = 0.05\n'
                       '[[bodies]]\nname = "p"\nshape = "pawn"\n', "scene.toml")
    msg = str(info.value)
    assert msg.startswith("scene.toml: shapes.pawn.heigth: unknown parameter for 'pawn' (")
    assert "did you mean 'height'?" in msg and "base_diameter" in msg
    with pytest.raises(SceneError, match=r"^scene\.toml: shapes\.pawn\.height: -1 is out of range"):
        parse_scene('[shapes.pawn]\nbuiltin = "pawn"\nheight = -1\n'
                       '[[bodies]]\nname = "p"\nshape = "pawn"\n', "scene.toml")


def test_real_builtin_collider_parameters(real_registry):
    if "torus" not in real_registry:
        pytest.skip("no built-in torus")
    text = minimal(body='[[colliders]]\ntype = "mesh"\nbuiltin = "torus"\nmajor_radius = "big"\n')
    with pytest.raises(SceneError, match=r"^scene\.toml: colliders\[0\]\.major_radius: expected"):
        parse_scene(text, "scene.toml")


# ------------------------------------------------ motion, kinematic groups, emitters

MOVING = """\
[output]
duration = 2.0

[shapes.pawn]
builtin = "pawn"

[[bodies]]
name = "ball"
shape = "pawn"
position = [0.0, 0.0, 1.0]
rotation = [2.0, 0.0, 0.0, 0.0]
kinematic = true
start_time = 0.5
[bodies.motion]
interpolation = "smooth"
keys = [{ time = 0.0 },
        { time = 1.0, position = [1.0, 0.0, 1.0], rotation = [0.0, 0.0, 0.0, 3.0] }]

[[bodies]]
name = "turntable"
shape = "pawn"
layout = "grid"
origin = [1.0, 2.0, 0.0]
dims = [2, 2, 1]
spacing = 0.3
kinematic = true
[bodies.motion]
angular_velocity = [0.0, 0.0, 1.0]

[[bodies]]
name = "late"
shape = "pawn"
start_time = 2.0
velocity = [0.0, 0.0, -1.0]

[[colliders]]
type = "plane"
name = "belt"
point = [0.0, 0.0, 0.5]
[colliders.motion]
velocity = [1.0, 0.0, 0.0]

[[colliders]]
type = "box"
min = [-1.0, -1.0, 0.0]
max = [1.0, 3.0, 1.0]
[colliders.motion]
angular_velocity = [0.0, 0.0, 0.5]
pivot = [0.0, 0.0, 0.0]

[[colliders]]
type = "mesh"
builtin = "torus"
position = [1.0, 2.0, 3.0]
rotation = [0.0, 1.0, 0.0, 0.0]
[colliders.motion]
[[colliders.motion.keys]]
time = 0.0
[[colliders.motion.keys]]
time = 1.5
position = [1.0, 2.0, 4.0]
"""


def test_motion_keys_rates_and_emitters():
    s = parse(MOVING)
    ball, table, late = s.bodies
    assert ball.kinematic and ball.start_time == 0.5
    m = ball.motion
    assert m.interpolation == "smooth" and m.keyed
    # a key without position/rotation stands at the body's own pose; rotations normalized
    assert m.keys[0] == Key(0.0, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    assert m.keys[1] == Key(1.0, (1.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0))
    # rates: the pivot is left to the builder (the owner's point)
    assert table.kinematic and table.motion == Motion(angular_velocity=(0.0, 0.0, 1.0))
    assert table.motion.pivot is None
    assert not late.kinematic and late.motion is None and late.start_time == 2.0
    belt, box, ring = s.colliders
    assert belt.motion == Motion(velocity=(1.0, 0.0, 0.0))
    assert box.motion.pivot == (0.0, 0.0, 0.0)
    assert ring.motion.interpolation == "linear"
    assert [k.position for k in ring.motion.keys] == [(1.0, 2.0, 3.0), (1.0, 2.0, 4.0)]
    assert all(k.rotation == (0.0, 1.0, 0.0, 0.0) for k in ring.motion.keys)
    # the frames motions move (what the builder anchors them at)
    frames = [collider_frame(c) for c in s.colliders]
    assert [f[0].tolist() for f in frames] == [[0.0, 0.0, 0.5], [0.0, 1.0, 0.5], [1.0, 2.0, 3.0]]
    assert frames[2][1].tolist() == [0.0, 1.0, 0.0, 0.0]
    placements = expand_bodies(s)
    o, r = group_frame(ball, placements[0])
    assert o.tolist() == [0.0, 0.0, 1.0] and r.tolist() == [1.0, 0.0, 0.0, 0.0]
    assert group_frame(table, placements[1])[0].tolist() == [1.0, 2.0, 0.0]
    # static by default
    p = parse(minimal(body='[[colliders]]\ntype = "plane"\n'))
    assert p.colliders[0].motion is None and not p.bodies[0].kinematic
    assert p.bodies[0].start_time == 0.0


def test_kinematic_group_keys_default_to_its_origin():
    s = parse(minimal(body='layout = "random"\ncount = 3\nregion_min = [0, 0, 0]\n'
                           'region_max = [2, 4, 6]\nkinematic = true\n'
                           '[bodies.motion]\nkeys = [{ time = 0.0 }, '
                           '{ time = 1.0, rotation = [0, 0, 0, 1] }]\n'))
    assert [k.position for k in s.bodies[0].motion.keys] == [(1.0, 2.0, 3.0)] * 2


KIN = 'kinematic = true\n'


@pytest.mark.parametrize("body, key, expect", [
    (KIN + "velocity = [1, 0, 0]\n[bodies.motion]\nvelocity = [1, 0, 0]\n",
     "bodies[0].velocity", "given on a kinematic group"),
    (KIN + "angular_velocity = [1, 0, 0]\n[bodies.motion]\nvelocity = [1, 0, 0]\n",
     "bodies[0].angular_velocity", "given on a kinematic group"),
    (KIN, "bodies[0].motion", "a kinematic group needs a motion"),
    ("[bodies.motion]\nvelocity = [1, 0, 0]\n", "bodies[0].motion",
     "add kinematic = true"),
    ('kinematic = "yes"\n', "bodies[0].kinematic", "expected a boolean"),
    ("start_time = -1.0\n", "bodies[0].start_time", "out of range"),
    ("start_time = 5.0\n", "bodies[0].start_time", "after the end of the animation"),
    (KIN + "[bodies.motion]\n", "bodies[0].motion", "no motion given"),
    (KIN + "[bodies.motion]\nvelocity = [1, 0, 0]\nkeys = [{ time = 0.0 }]\n",
     "bodies[0].motion.velocity", "not both"),
    (KIN + "[bodies.motion]\nvelocity = [1, 0, 0]\ninterpolation = 'smooth'\n",
     "bodies[0].motion.interpolation", "applies to keys only"),
    (KIN + "[bodies.motion]\nkeys = []\n", "bodies[0].motion.keys", "got an empty array"),
    (KIN + "[bodies.motion]\nkeys = [{ time = 0.0 }]\ninterpolation = 'cubic'\n",
     "bodies[0].motion.interpolation", "known: linear, smooth"),
    (KIN + "[bodies.motion]\nkeys = [{ time = 1.0 }, { time = 0.5 }]\n",
     "bodies[0].motion.keys[1].time", "is before keys[0].time = 1"),
    (KIN + "[bodies.motion]\nkeys = [{ time = 1.0 }, { time = 1.0 }]\n",
     "bodies[0].motion.keys[1].time", "repeats keys[0]"),
    (KIN + "[bodies.motion]\nkeys = [{ position = [0, 0, 0] }]\n",
     "bodies[0].motion.keys[0].time", "missing required key"),
    (KIN + "[bodies.motion]\nkeys = [{ time = 0.0, rotation = [0, 0, 0, 0] }]\n",
     "bodies[0].motion.keys[0].rotation", "zero quaternion"),
    (KIN + "[bodies.motion]\nkeys = [{ time = 0.0, postion = [0, 0, 0] }]\n",
     "bodies[0].motion.keys[0].postion", "did you mean 'position'?"),
    (KIN + "[bodies.motion]\nkeys = [1.0]\n", "bodies[0].motion.keys[0]", "expected a table"),
    (KIN + 'rotation = "random"\n[bodies.motion]\nkeys = [{ time = 0.0 }]\n',
     "bodies[0].motion.keys[0]", 'bodies[0] has rotation = "random"'),
    (KIN + "[bodies.motion]\nvelocty = [1, 0, 0]\n", "bodies[0].motion.velocty",
     "did you mean 'velocity'?"),
    ('[[colliders]]\ntype = "plane"\n[colliders.motion]\npivot = [0, 0, 0]\n',
     "colliders[0].motion", "no motion given"),
    ('[[colliders]]\ntype = "box"\nmin = [0, 0, 0]\nmax = [1, 1, 1]\n[colliders.motion]\n'
     'keys = [{ time = 0.0 }]\nangular_velocity = [0, 0, 1]\n',
     "colliders[0].motion.angular_velocity", "not both"),
    ('[[colliders]]\ntype = "plane"\nmotion = [1, 0, 0]\n', "colliders[0].motion",
     "expected a table"),
])
def test_motion_errors(body, key, expect):
    msg = error_of(minimal(head="[output]\nduration = 2.0\n", body=body))
    assert f"scene.toml: {key}: " in msg
    assert expect in msg
