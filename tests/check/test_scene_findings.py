"""`dempipe check` names by their scene keys what only the scene can name: a mesh
that is not watertight (a body's shape or a mesh collider), bodies that start
wholly behind a plane or a box collider's wall, and bodies dropped with nothing
under them. Each is a counted warning finding with a fix, in the text and in the
JSON; the bake's pre-flight warns of the bodies too. Real scene files and real OBJ
meshes written by trimesh."""

import json
import re

import pytest
import trimesh
from click.testing import CliRunner

from dempipe.pipeline.check import analyze_scene
from dempipe.spheres.cache import SphereCache

HEAD = """
[output]
fps = 24
duration = 0.5

[simulation]
resolution = 6
"""

PLANE = """
[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
"""


def write_box(path, closed: bool):
    """A 4 cm box as an OBJ file; ``closed`` False leaves out its top face."""
    box = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    if not closed:
        box = trimesh.Trimesh(box.vertices, box.faces[box.face_normals[:, 2] < 0.5],
                              process=False)
    assert box.is_watertight == closed
    box.export(path)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return SphereCache(tmp_path_factory.mktemp("cache"))


@pytest.fixture(autouse=True)
def _meshes(tmp_path):
    write_box(tmp_path / "open.obj", closed=False)
    write_box(tmp_path / "closed.obj", closed=True)


def scene(tmp_path, text: str):
    path = tmp_path / "scene.toml"
    path.write_text(HEAD + text)
    return path


def check_json(path, cache):
    """`dempipe check --json` on ``path``, parsed (the CLI's own command)."""
    from dempipe_cli.main import app

    r = CliRunner().invoke(app, ["check", "--json", "--cache-dir", str(cache.root),
                                 str(path)])
    assert r.exit_code == 0, r.output
    return json.loads(r.output)


def coded(report, code):
    return [f for f in report.findings if f.code == code]


def preflight_warning(path, tmp_path, cache, words: str) -> str:
    """The bake's pre-flight warning about ``path`` that holds ``words``: the bake is
    stopped there (nothing to simulate); fails if it gives none."""
    from dempipe.pipeline.bake import bake

    class Stop(Exception):
        pass

    def warn(msg):
        if words in msg:
            raise Stop(msg)

    with pytest.raises(Stop) as stopped:
        bake(path, tmp_path / "o.usdc", device="cpu", cache=cache, warn=warn)
    return str(stopped.value)


def assert_counted(report, found):
    """``found`` is among the report's warnings, counted in its text's header."""
    assert found.level == "warning" and found in report.warnings
    text = report.format()
    n = len(report.warnings)
    assert f"0 errors, {n} warning{'s' * (n != 1)})" in text.splitlines()[0]
    assert f"warning: {found.message}" in text and f"  fix: {found.fix}" in text


def test_open_body_mesh_is_a_warning_naming_its_key(tmp_path, cache):
    path = scene(tmp_path, """
[shapes.b]
mesh = "open.obj"

[[bodies]]
name = "crates"
shape = "b"
position = [0.0, 0.0, 0.05]
""" + PLANE)
    import warnings

    with warnings.catch_warnings(record=True) as raised:
        warnings.simplefilter("always")
        report = analyze_scene(path, cache=cache)
    # said once, as the finding, not again by the sphere builder
    assert not [w for w in raised if "watertight" in str(w.message)]
    (found,) = coded(report, "open-mesh")
    assert found.message.startswith("scene.toml: shapes.b.mesh: mesh is not watertight")
    assert "mass" in found.message
    # a bake's model build warns it, naming the file and the shape
    from dempipe.scene.build import build_model
    from dempipe.scene.load import load_scene
    with pytest.warns(UserWarning, match=r"scene.toml: shapes.b: mesh is not watertight"):
        build_model(load_scene(path), cache=cache)
    assert found.fix.startswith("close the mesh's holes")
    assert_counted(report, found)
    assert report.ok
    as_json = check_json(path, cache)
    assert dict(level="warning", code="open-mesh", message=found.message,
                fix=found.fix) in as_json["findings"]


def test_open_collider_mesh_is_a_warning_naming_its_key(tmp_path, cache):
    path = scene(tmp_path, """
[shapes.b]
mesh = "closed.obj"

[[bodies]]
name = "crates"
shape = "b"
position = [0.0, 0.0, 0.2]
""" + PLANE + """
[[colliders]]
type = "mesh"
name = "bin"
mesh = "open.obj"
position = [0.5, 0.0, 0.03]
""")
    report = analyze_scene(path, cache=cache)
    (found,) = coded(report, "open-mesh")
    assert found.message.startswith(
        "scene.toml: colliders[1].mesh ('bin'): mesh is not watertight")
    assert found.fix.startswith("close the mesh's holes")
    assert_counted(report, found)
    assert found.message in [f["message"] for f in check_json(path, cache)["findings"]]


def test_body_behind_the_ground_plane_is_a_warning_naming_group_and_plane(tmp_path, cache):
    path = scene(tmp_path, """
[shapes.box]
builtin = "box"

[[bodies]]
name = "boxes"
shape = "box"
position = [0.0, 0.0, -1.0]
""" + PLANE)
    report = analyze_scene(path, cache=cache)
    (found,) = coded(report, "behind-plane")
    assert found.message.startswith(
        "scene.toml: bodies[0] ('boxes'): its body starts wholly behind colliders[0] "
        "('plane0')")
    assert "flip the plane's normal" in found.fix and "[0, 0, 1]" in found.fix
    assert report.overlap == 0.0            # the frame-0 overlap check sees nothing
    assert_counted(report, found)
    as_json = check_json(path, cache)
    assert dict(level="warning", code="behind-plane", message=found.message,
                fix=found.fix) in as_json["findings"]


def test_behind_plane_counts_the_bodies_of_a_group_and_emitted_bodies(tmp_path, cache):
    # a grid of two, one above the floor and one under it; a body emitted at 0.2 s
    # under it; a box partly through it is the frame-0 overlap check's, not this one's
    path = scene(tmp_path, """
[shapes.box]
builtin = "box"

[[bodies]]
name = "pair"
shape = "box"
layout = "grid"
origin = [0.0, 0.0, -0.5]
dims = [1, 1, 2]
spacing = [0.1, 0.1, 0.6]

[[bodies]]
name = "late"
shape = "box"
position = [0.5, 0.0, -0.3]
start_time = 0.2

[[bodies]]
name = "sunk"
shape = "box"
position = [1.0, 0.0, 0.0]
""" + PLANE)
    report = analyze_scene(path, cache=cache)
    found = coded(report, "behind-plane")
    assert [f.message.split(":")[1].strip() for f in found] == [
        "bodies[0] ('pair')", "bodies[1] ('late')"]
    assert "1 of its 2 bodies starts wholly behind colliders[0]" in found[0].message
    assert "its body starts wholly behind" in found[1].message
    assert coded(report, "frame0-overlap")


def test_a_plane_that_moves_is_taken_where_it_is_when_the_body_starts(tmp_path, cache):
    # the floor rises at 1 m/s; a box emitted 10 cm above where it started, at 0.4 s,
    # starts 30 cm under it; the same box emitted at once does not
    rising = PLANE + "\n[colliders.motion]\nvelocity = [0.0, 0.0, 1.0]\n"
    body = """
[shapes.box]
builtin = "box"

[[bodies]]
name = "late"
shape = "box"
position = [0.0, 0.0, 0.1]
start_time = {t}
"""
    report = analyze_scene(scene(tmp_path, body.format(t=0.25) + rising), cache=cache)
    (found,) = coded(report, "behind-plane")
    assert "bodies[0] ('late')" in found.message
    report = analyze_scene(scene(tmp_path, body.format(t=0.0) + rising), cache=cache)
    assert not coded(report, "behind-plane")


def test_bake_preflight_warns_of_a_body_behind_a_plane(tmp_path, cache):
    path = scene(tmp_path, """
[shapes.box]
builtin = "box"

[[bodies]]
name = "boxes"
shape = "box"
position = [0.0, 0.0, -1.0]
""" + PLANE)
    assert re.search(r"bodies\[0\] \('boxes'\).*colliders\[0\] \('plane0'\)",
                     preflight_warning(path, tmp_path, cache, "wholly behind"))


# a tray 60 cm across and 30 cm high, open at the top; the built-in box is 4 cm
# across, its spheres 6.7 mm, so the tray's walls are 13.3 mm deep (2 d) and reach
# 3.3 mm (a radius) past its inner corners
TRAY = """
[[colliders]]
type = "box"
name = "tray"
min = [-0.3, -0.3, 0.0]
max = [0.3, 0.3, 0.3]
"""

BOXES = """
[shapes.box]
builtin = "box"
"""


def test_body_under_a_box_floor_is_a_warning_naming_group_box_and_wall(tmp_path, cache):
    path = scene(tmp_path, BOXES + """
[[bodies]]
name = "boxes"
shape = "box"
position = [0.1, -0.1, -0.1]
""" + TRAY)
    report = analyze_scene(path, cache=cache)
    (found,) = coded(report, "behind-box-wall")
    assert found.message.startswith(
        "scene.toml: bodies[0] ('boxes'): its body starts outside colliders[0] ('tray'), "
        "wholly behind its floor, more than 0.0133 m")
    assert found.fix == ("move it inside the box, between its min [-0.3, -0.3, 0] and max "
                         "[0.3, 0.3, 0.3], or above its open top so that it falls in")
    assert report.overlap == 0.0            # the frame-0 overlap check sees nothing
    assert not coded(report, "behind-plane")
    assert_counted(report, found)
    as_json = check_json(path, cache)
    assert dict(level="warning", code="behind-box-wall", message=found.message,
                fix=found.fix) in as_json["findings"]


def test_bodies_inside_above_or_beside_a_box_are_not_behind_its_walls(tmp_path, cache):
    # inside; above the open top; beside a corner, outside every wall's extent; under
    # the floor but partly beside the tray (spheres outside the floor's extent are
    # never tested against it); one wholly under the floor, which alone is named; and
    # two placed far from it, farther behind a wall than the tray is deep: on the
    # ground 1 m below, and 1.2 m out from its +x wall
    path = scene(tmp_path, BOXES + """
[[bodies]]
name = "inside"
shape = "box"
position = [0.0, 0.0, 0.1]

[[bodies]]
name = "above"
shape = "box"
position = [0.0, 0.0, 0.6]

[[bodies]]
name = "beside"
shape = "box"
position = [0.5, 0.5, 0.1]

[[bodies]]
name = "straddling"
shape = "box"
position = [0.3, 0.0, -0.1]

[[bodies]]
name = "under"
shape = "box"
position = [0.0, 0.0, -0.1]

[[bodies]]
name = "ground"
shape = "box"
position = [0.1, 0.0, -1.0]

[[bodies]]
name = "away"
shape = "box"
position = [1.5, 0.0, 0.1]
""" + TRAY)
    report = analyze_scene(path, cache=cache)
    found = coded(report, "behind-box-wall")
    assert [f.message.split(":")[1].strip() for f in found] == ["bodies[4] ('under')"]
    assert report.overlap == 0.0


def test_behind_box_wall_counts_a_group_once_and_names_each_wall(tmp_path, cache):
    # a row of three along x, one in the tray and two beyond its +x wall; a block of
    # four, one beyond the -y wall, one under the floor, one inside, one both beside
    # and below the tray, outside every wall's extent; a closed crate names its lid
    path = scene(tmp_path, BOXES + """
[[bodies]]
name = "row"
shape = "box"
layout = "grid"
origin = [0.2, 0.0, 0.1]
dims = [3, 1, 1]
spacing = 0.2

[[bodies]]
name = "block"
shape = "box"
layout = "grid"
origin = [0.0, -0.5, -0.1]
dims = [1, 2, 2]
spacing = [0.1, 0.5, 0.2]

[[bodies]]
name = "lidded"
shape = "box"
position = [2.0, 1.2, 0.5]
""" + TRAY + """
[[colliders]]
type = "box"
name = "crate"
min = [1.8, 1.0, 0.0]
max = [2.2, 1.4, 0.3]
open_top = false
""")
    report = analyze_scene(path, cache=cache)
    found = coded(report, "behind-box-wall")
    assert [f.message.split(": ", 2)[1] for f in found] == [
        "bodies[0] ('row')", "bodies[1] ('block')", "bodies[2] ('lidded')"]
    assert ("2 of its 3 bodies start outside colliders[0] ('tray'), wholly behind its "
            "+x wall,") in found[0].message
    assert ("2 of its 4 bodies start outside colliders[0] ('tray'), wholly behind its "
            "-y wall and floor,") in found[1].message
    assert ("its body starts outside colliders[1] ('crate'), wholly behind its lid,"
            in found[2].message)
    assert found[0].fix.endswith("or above its open top so that they fall in")
    assert found[2].fix == ("move it inside the box, between its min [1.8, 1, 0] and "
                            "max [2.2, 1.4, 0.3]")
    assert report.overlap == 0.0


def test_bodies_in_a_second_box_are_not_behind_the_first_ones_wall(tmp_path, cache):
    # a bin beside the tray along x: the tray's +x wall and the bin's -x wall face
    # away from each other, each reaching on without end behind itself. Bodies in
    # either, or above the bin's open top, are held where they are; one in the gap
    # between them is behind both walls, one finding for each box
    path = scene(tmp_path, BOXES + """
[[bodies]]
name = "held"
shape = "box"
layout = "grid"
origin = [0.0, 0.0, 0.1]
dims = [2, 1, 2]
spacing = [0.8, 0.1, 0.5]

[[bodies]]
name = "gap"
shape = "box"
position = [0.4, 0.0, 0.1]
""" + TRAY + """
[[colliders]]
type = "box"
name = "bin"
min = [0.5, -0.3, 0.0]
max = [1.1, 0.3, 0.3]
""")
    report = analyze_scene(path, cache=cache)
    found = coded(report, "behind-box-wall")
    assert [f.message.split(": ", 2)[1] for f in found] == ["bodies[1] ('gap')"] * 2
    assert "outside colliders[0] ('tray'), wholly behind its +x wall," in found[0].message
    assert "outside colliders[1] ('bin'), wholly behind its -x wall," in found[1].message


def test_a_box_that_moves_is_taken_where_it_is_when_the_body_starts(tmp_path, cache):
    # the tray rises at 1 m/s; a box emitted 10 cm above where its floor started, at
    # 0.25 s, starts 15 cm under the floor; the same box emitted at once is in the tray
    rising = TRAY + "\n[colliders.motion]\nvelocity = [0.0, 0.0, 1.0]\n"
    body = BOXES + """
[[bodies]]
name = "late"
shape = "box"
position = [0.0, 0.0, 0.1]
start_time = {t}
"""
    report = analyze_scene(scene(tmp_path, body.format(t=0.25) + rising), cache=cache)
    (found,) = coded(report, "behind-box-wall")
    assert "bodies[0] ('late')" in found.message and "its floor" in found.message
    report = analyze_scene(scene(tmp_path, body.format(t=0.0) + rising), cache=cache)
    assert not coded(report, "behind-box-wall")


def test_bake_preflight_warns_of_a_body_behind_a_box_wall(tmp_path, cache):
    path = scene(tmp_path, BOXES + """
[[bodies]]
name = "boxes"
shape = "box"
position = [0.0, 0.0, -0.1]
""" + TRAY)
    assert re.search(r"bodies\[0\] \('boxes'\).*colliders\[0\] \('tray'\), "
                     r"wholly behind its floor",
                     preflight_warning(path, tmp_path, cache, "wholly behind"))


def test_a_normal_scene_gets_neither_warning(tmp_path, cache):
    path = scene(tmp_path, """
[shapes.b]
mesh = "closed.obj"

[shapes.box]
builtin = "box"

[[bodies]]
name = "crates"
shape = "b"
position = [0.0, 0.0, 0.05]

[[bodies]]
name = "boxes"
shape = "box"
layout = "grid"
origin = [0.2, 0.0, 0.05]
dims = [2, 1, 2]
spacing = 0.1
start_time = 0.1
""" + PLANE + """
[[colliders]]
type = "mesh"
name = "block"
mesh = "closed.obj"
position = [0.5, 0.0, 0.02]
""")
    report = analyze_scene(path, cache=cache)
    codes = {f.code for f in report.findings}
    assert not codes & {"open-mesh", "behind-plane"}, report.format()
    codes = {f["code"] for f in check_json(path, cache)["findings"]}
    assert not codes & {"open-mesh", "behind-plane"}


LAUNCH = HEAD + PLANE + """
[shapes.ball]
builtin = "sphere"
diameter = 0.05

[[bodies]]
name = "shot"
shape = "ball"
position = [0.0, 0.0, 0.5]
velocity = [0.0, 0.0, -{speed}]
"""


def test_a_body_launched_far_too_fast_is_a_long_bake_warning(tmp_path):
    # 500 m/s where 5 was meant: nothing is refused, but the automatic stiffness holds
    # that impact to the target overlap and the step shrinks with the speed (dt ∝ 1/v):
    # a warning naming the speed and the keys, in check and in the bake's pre-flight
    from dempipe.pipeline.bake import bake
    from dempipe.pipeline.check import STEPS_WARN

    cache = SphereCache(tmp_path / "cache")
    p = tmp_path / "launch.toml"
    p.write_text(LAUNCH.format(speed=5.0))
    calm = analyze_scene(p, cache=cache)
    assert calm.steps_per_frame < STEPS_WARN
    assert "long-bake" not in {f.code for f in calm.findings}
    p.write_text(LAUNCH.format(speed=500.0))
    report = analyze_scene(p, cache=cache)
    assert report.steps_per_frame > STEPS_WARN
    found = [f for f in report.findings if f.code == "long-bake"]
    assert len(found) == 1 and found[0].level == "warning"
    assert re.search(r"fastest body at 50\d m/s", found[0].message), found[0].message
    assert f"{report.steps_per_frame:,} steps per frame" in found[0].message
    assert "velocity" in found[0].fix and "stiffness" in found[0].fix
    assert report.ok                    # a warning: the bake is allowed
    said = []
    bake(p, tmp_path / "o.usda", device="cpu", cache=cache, frames="0:0", warn=said.append)
    assert any("steps per frame" in w and "fastest body" in w for w in said), said


DROP = """
[shapes.ball]
builtin = "sphere"
diameter = 0.05

[[bodies]]
name = "drop"
shape = "ball"
position = [{x}, 0.0, 0.5]
{extra}
"""

def test_a_body_dropped_with_nothing_under_it_is_a_warning(tmp_path, cache):
    # no collider at all: the ball falls for the whole shot, g t²/2 = 1.23 m in 0.5 s
    path = scene(tmp_path, DROP.format(x=0.0, extra=""))
    report = analyze_scene(path, cache=cache)
    (found,) = coded(report, "nothing-below")
    assert found.message == (
        "scene.toml: bodies[0] ('drop'): its body starts with nothing under it (no "
        "ground plane below, no box, static mesh or kinematic body under its centre): "
        "it falls for the whole shot, 1.23 m in 0.5 s")
    assert found.fix == ('add a ground (a [[colliders]] entry with type = "plane") or '
                         'move it over a collider')
    assert_counted(report, found)
    # beside the tray (its centre outside the box's extent): the same
    report = analyze_scene(scene(tmp_path, DROP.format(x=0.5, extra="") + TRAY),
                           cache=cache)
    assert len(coded(report, "nothing-below")) == 1


@pytest.mark.parametrize("extra, colliders, gravity", [
    ("", PLANE, ""),                                        # a ground plane
    ("", TRAY, ""),                                         # over the tray
    ("velocity = [1.0, 0.0, 0.0]", "", ""),                 # thrown: may land elsewhere
    ("", "", "gravity = [0.0, 0.0, 0.0]\n"),                # nothing falls
], ids=["plane", "box", "thrown", "weightless"])
def test_a_body_over_a_collider_thrown_or_weightless_is_not_named(tmp_path, cache, extra,
                                                                   colliders, gravity):
    path = tmp_path / "scene.toml"
    path.write_text(HEAD + gravity + DROP.format(x=0.0, extra=extra) + colliders)
    assert not coded(analyze_scene(path, cache=cache), "nothing-below")


def test_bake_preflight_warns_of_a_body_with_nothing_under_it(tmp_path, cache):
    path = scene(tmp_path, DROP.format(x=0.0, extra=""))
    assert "bodies[0] ('drop'): its body starts with nothing under it" in \
        preflight_warning(path, tmp_path, cache, "nothing under")


def test_an_emitted_body_falls_from_its_start_time(tmp_path, cache):
    # started at 0.3 s of the 0.5 s shot: g t²/2 over the 0.2 s left, 0.196 m
    path = scene(tmp_path, DROP.format(x=0.0, extra="start_time = 0.3"))
    (found,) = coded(analyze_scene(path, cache=cache), "nothing-below")
    assert found.message.endswith("it falls for the whole shot, 0.196 m in 0.2 s")
