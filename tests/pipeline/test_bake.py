"""Scene file → bake → USD, read back with pxr."""

import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from dempipe.pipeline.bake import bake
from dempipe.sim.model import quat_to_matrix
from dempipe.scene.placement import expand_bodies
from dempipe.scene.load import load_scene
from dempipe_cli.main import app

pxr = pytest.importorskip("pxr")
from pxr import Usd, UsdGeom, UsdValidation  # noqa: E402

SCENE = """
[output]
fps = 24
duration = 0.25
up_axis = "Z"
start_frame = 1

[simulation]
resolution = 5
stiffness_target_overlap = 0.05
seed = 3

[materials.wood]
density = 700.0
restitution = 0.3
friction = 0.5

[shapes.pawn]
builtin = "pawn"
height = 0.05

[shapes.ring]
builtin = "torus"
major_radius = 0.02
minor_radius = 0.008

[[bodies]]
name = "pawns"
shape = "pawn"
material = "wood"
layout = "grid"
origin = [-0.05, -0.05, 0.06]
dims = [2, 2, 1]
count = 3
spacing = 0.1
rotation = "random"

[[bodies]]
name = "ring"
shape = "ring"
layout = "single"
position = [0.05, 0.05, 0.04]
rotation = [0.9238795, 0.3826834, 0.0, 0.0]
velocity = [0.0, 0.0, -0.5]

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "wood"
"""


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    d = tmp_path_factory.mktemp("bake")
    scene = d / "scene.toml"
    scene.write_text(SCENE)
    from dempipe.spheres.cache import SphereCache
    cache = SphereCache(d / "cache")
    out = {}
    for layout in ("instancer", "xforms"):
        path = d / f"{layout}.usda"
        out[layout] = bake(scene, path, device="cpu", layout=layout, cache=cache)
    return scene, out


def validation_errors(stage):
    reg = UsdValidation.ValidationRegistry()
    ctx = UsdValidation.ValidationContext(reg.GetOrLoadAllValidators())
    return [e for e in ctx.Validate(stage)
            if e.GetType() == UsdValidation.ValidationErrorType.Error]


def world_vertices_instancer(stage, time):
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    xf = pi.ComputeInstanceTransformsAtTime(Usd.TimeCode(time), Usd.TimeCode(time))
    proto_paths = pi.GetPrototypesRel().GetTargets()
    idx = pi.GetProtoIndicesAttr().Get()
    out = []
    for m, p in zip(xf, idx):
        pts = np.array(UsdGeom.Mesh(stage.GetPrimAtPath(proto_paths[p])).GetPointsAttr().Get())
        M = np.array(m)
        out.append(pts @ M[:3, :3] + M[3, :3])
    return out


def world_vertices_xforms(stage, time):
    cache = UsdGeom.XformCache(Usd.TimeCode(time))
    out = []
    bodies = stage.GetPrimAtPath("/World/Bodies")
    for group in bodies.GetChildren():
        prims = sorted(group.GetChildren(), key=lambda p: int(p.GetName().rsplit("_", 1)[1]))
        for prim in prims:
            M = np.array(cache.GetLocalToWorldTransform(prim))
            mesh = [c for c in Usd.PrimRange(prim, Usd.TraverseInstanceProxies())
                    if c.IsA(UsdGeom.Mesh)][0]
            pts = np.array(UsdGeom.Mesh(mesh).GetPointsAttr().Get())
            out.append(pts @ M[:3, :3] + M[3, :3])
    return out


def test_stage_metadata_counts_and_validation(baked):
    scene, out = baked
    r = out["instancer"].report
    assert r["bodies"] == 4 and r["frames"] == 7 and r["completed"]
    stage = Usd.Stage.Open(str(out["instancer"].path))
    assert stage.GetDefaultPrim().GetPath() == "/World"
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 24 and stage.GetFramesPerSecond() == 24
    assert stage.GetStartTimeCode() == 1 and stage.GetEndTimeCode() == 7
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    assert list(pi.GetIdsAttr().Get()) == [0, 1, 2, 3]
    assert len(pi.GetPositionsAttr().GetTimeSamples()) >= 2
    assert stage.GetPrimAtPath("/World/Colliders").GetChildren()
    for layout in out:
        assert validation_errors(Usd.Stage.Open(str(out[layout].path))) == []


def test_frame0_vertices_are_the_scene_placements(baked):
    # world vertex = position + R(rotation) · mesh vertex, as a DCC places a mesh by its
    # origin. Tolerance 2e-3 × the shape size: orientations are stored as quath
    # (half precision, ~1e-3 relative).
    scene, out = baked
    sc = load_scene(scene)
    from dempipe.scene.build import shape_mesh
    expected = []
    for placement in expand_bodies(sc):
        mesh = shape_mesh(sc.shapes[placement.shape], "")
        for p, q in zip(placement.positions, placement.rotations):
            expected.append(np.asarray(mesh.vertices) @ quat_to_matrix(q).T + p)
    stage = Usd.Stage.Open(str(out["instancer"].path))
    got = world_vertices_instancer(stage, 1)
    assert len(got) == len(expected)
    for g, e in zip(got, expected):
        assert np.abs(g - e).max() < 2e-3 * 0.05
    got = world_vertices_xforms(Usd.Stage.Open(str(out["xforms"].path)), 1)
    for g, e in zip(got, expected):
        assert np.abs(g - e).max() < 1e-5          # quatf: float precision


def test_both_layouts_give_the_same_world_transforms(baked):
    scene, out = baked
    a = Usd.Stage.Open(str(out["instancer"].path))
    b = Usd.Stage.Open(str(out["xforms"].path))
    for t in range(1, 8):
        for va, vb in zip(world_vertices_instancer(a, t), world_vertices_xforms(b, t)):
            assert np.abs(va - vb).max() < 2e-3 * 0.05     # quath vs quatf, as above


def test_bodies_fell_and_landed(baked):
    scene, out = baked
    stage = Usd.Stage.Open(str(out["instancer"].path))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    z0 = np.array(pi.GetPositionsAttr().Get(1))[:, 2]
    z1 = np.array(pi.GetPositionsAttr().Get(7))[:, 2]
    assert (z1 < z0).all()            # gravity pulls everything down
    assert (z1 > 0).all()             # and nothing went through the ground plane


BAD = [
    ("[output]\nfps = 24\nfps = 25\n", "line"),
    (SCENE.replace("seed = 3", "seeed = 3"), "simulation.seeed"),
    (SCENE.replace("density = 700.0", 'density = "heavy"'), "materials.wood.density"),
    (SCENE.replace('builtin = "torus"\nmajor_radius = 0.02\nminor_radius = 0.008',
                   'mesh = "missing.obj"'), "missing.obj"),
    (SCENE.replace('shape = "pawn"\nmaterial', 'shape = "pwn"\nmaterial'), "bodies[0].shape"),
    (SCENE.replace('material = "wood"\nlayout', 'material = "oak"\nlayout'), "bodies[0].material"),
    (SCENE.replace("count = 3", "count = 5"), "bodies[0]"),
]


@pytest.mark.parametrize("text,key", BAD)
def test_malformed_scene_one_line_nonzero_exit(tmp_path, text, key):
    scene = tmp_path / "bad.toml"
    scene.write_text(text)
    res = CliRunner().invoke(app, ["bake", str(scene), "-o", str(tmp_path / "o.usdc")])
    assert res.exit_code != 0
    proc = subprocess.run([sys.executable, "-c", "from dempipe_cli.main import main; main()",
                           "bake", str(scene), "-o", str(tmp_path / "o.usdc")],
                          capture_output=True, text=True)
    assert proc.returncode != 0
    err = proc.stderr.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert "bad.toml" in err and key in err, err
    assert not (tmp_path / "o.usdc").exists()


def test_missing_scene_file(tmp_path):
    proc = subprocess.run([sys.executable, "-c", "from dempipe_cli.main import main; main()",
                           "bake", str(tmp_path / "nope.toml"), "-o", str(tmp_path / "o.usdc")],
                          capture_output=True, text=True)
    assert proc.returncode != 0 and "nope.toml" in proc.stderr and "Traceback" not in proc.stderr


def test_overlapping_start_is_refused_and_nothing_written(tmp_path):
    text = SCENE.replace("spacing = 0.1", "spacing = 0.01")
    scene = tmp_path / "overlap.toml"
    scene.write_text(text)
    res = CliRunner().invoke(app, ["bake", str(scene), "-o", str(tmp_path / "o.usdc")])
    assert res.exit_code != 0 and "frame 0" in str(res.exception) + res.output
    assert not (tmp_path / "o.usdc").exists()


def test_failed_bake_keeps_its_frames(tmp_path, monkeypatch):
    # A guard that trips mid-bake: the frames before it are written to a partial
    # file that opens and validates; the target is not created.
    import dempipe.sim.simulator as simulator
    original = simulator.Simulator._check

    def trip(self, state, overlap, k, *vw):
        return "synthetic failure" if k == 4 else original(self, state, overlap, k, *vw)

    monkeypatch.setattr(simulator.Simulator, "_check", trip)
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE)
    out = tmp_path / "o.usdc"
    with pytest.raises(Exception) as info:
        bake(scene, out, device="cpu")
    assert "synthetic failure" in str(info.value) and "4 frames kept" in str(info.value)
    partial = tmp_path / "o.partial.usdc"
    assert partial.exists() and not out.exists()
    stage = Usd.Stage.Open(str(partial))
    assert stage.GetEndTimeCode() - stage.GetStartTimeCode() == 3
    assert validation_errors(stage) == []


def test_cli_bake_report_and_frames(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE)
    res = CliRunner().invoke(app, ["bake", str(scene), "-o", str(tmp_path / "o.usdc"),
                                   "--frames", "3:5", "--report", str(tmp_path / "r.json"),
                                   "--quiet", "--threads", "1", "--device", "cpu",
                                   "--cache-dir", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    import json
    r = json.loads((tmp_path / "r.json").read_text())
    for key in ("bodies", "spheres", "dt", "steps", "frames", "device", "wall_seconds",
                "seconds_per_step", "max_overlap", "sphere_build_seconds", "export_seconds"):
        assert key in r
    assert r["frames"] == 3 and r["device"] == "cpu"
    stage = Usd.Stage.Open(str(tmp_path / "o.usdc"))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (3, 5)


GLUED = """
[output]
fps = 24
duration = 0.5
[simulation]
resolution = 6
[materials.m]
density = 1000.0
friction = 0.5
glue_strength = {strength}
[shapes.block]
builtin = "box"
size = [0.3, 0.1, 0.1]
fracture = {{ pieces = 3, seed = 1 }}
[[bodies]]
name = "block"
shape = "block"
material = "m"
position = [0.0, 0.0, 0.4]
glue = true
[[colliders]]
type = "plane"
"""


@pytest.mark.parametrize("strength,breaks", [(1.0, True), (1e12, False)])
def test_cli_bake_says_how_many_glue_bonds_broke(tmp_path, strength, breaks):
    # a block of three glued pieces lands from 0.35 m: glue of 1 Pa holds a sphere
    # pair to 1e-4 of the landing's load and breaks, 1e12 Pa holds everything
    scene = tmp_path / "s.toml"
    scene.write_text(GLUED.format(strength=strength))
    res = CliRunner().invoke(app, ["bake", str(scene), "-o", str(tmp_path / "o.usdc"),
                                   "--report", str(tmp_path / "r.json"), "--threads", "1",
                                   "--device", "cpu", "--cache-dir", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    import json
    import re
    r = json.loads((tmp_path / "r.json").read_text())
    m = re.search(r"; (\d+) of (\d+) glue bonds broke", res.output)
    assert m, res.output
    assert int(m.group(2)) == r["bonds"] > 0
    assert int(m.group(1)) == sum(r["bonds_broken_per_frame"])
    assert (int(m.group(1)) > 0) == breaks
    assert ("in one frame" in res.output) == breaks
