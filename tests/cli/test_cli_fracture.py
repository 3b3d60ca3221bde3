"""Fracture from the command line: `dempipe spheres --fracture` shows the pieces, and
bad fracture keys of a scene are refused at the door with one line naming the key.
Real `dempipe` processes."""

import os
import subprocess
import sys

import numpy as np
import pytest
from pxr import Usd, UsdGeom

SCENE = """
[shapes.column]
builtin = "cylinder"
diameter = 0.1
height = 0.3
{fracture}

[[bodies]]
name = "column"
shape = "column"
position = [0.0, 0.0, 0.1]

[[colliders]]
type = "plane"
"""


def dempipe(tmp_path, *args, timeout=600):
    env = dict(os.environ, DEMPIPE_CACHE_DIR=str(tmp_path / "cache"))
    return subprocess.run([sys.executable, "-m", "dempipe_cli.main", *map(str, args)],
                          cwd=tmp_path, capture_output=True, text=True, env=env,
                          timeout=timeout)


@pytest.mark.parametrize("fracture, key", [
    ("fracture = { pieces = 1 }", "shapes.column.fracture.pieces"),
    ("fracture = { pieces = 4.5 }", "shapes.column.fracture.pieces"),
    ("fracture = { seed = 3 }", "shapes.column.fracture"),
    ("fracture = { pieces = 4, impact = [0, 0] }", "shapes.column.fracture.impact"),
    ("fracture = { pieces = 4, impact = [0, 0, 0.2], impact_share = 2.0 }",
     "shapes.column.fracture.impact_share"),
    ("fracture = { pieces = 4, impact_share = 0.5 }", "shapes.column.fracture.impact_share"),
    ("fracture = { pieces = 4, shards = 2 }", "shapes.column.fracture"),
    ("fracture = 4", "shapes.column.fracture"),
    ("spheres = \"surface\"\nfracture = { pieces = 4 }", "shapes.column.fracture"),
])
def test_bad_fracture_keys_are_one_line_naming_the_key(tmp_path, fracture, key):
    (tmp_path / "s.toml").write_text(SCENE.format(fracture=fracture))
    r = dempipe(tmp_path, "check", "s.toml")
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and key in lines[0], r.stderr
    assert "Traceback" not in r.stderr


def test_a_mesh_that_cannot_be_cut_is_one_line_naming_the_key(tmp_path):
    # a box with its top face missing: manifold3d cannot cut it; the error names the
    # scene's key that asked for the cut, as the keys above do, and how to fix it
    import trimesh
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    box.update_faces(np.abs(box.face_normals[:, 2] - 1.0) > 1e-9)
    box.export(tmp_path / "open.obj")
    scene = SCENE.replace('builtin = "cylinder"\ndiameter = 0.1\nheight = 0.3',
                          'mesh = "open.obj"')
    (tmp_path / "s.toml").write_text(scene.format(fracture="fracture = { pieces = 4 }"))
    r = dempipe(tmp_path, "bake", "s.toml", "-o", "out.usdc")
    assert r.returncode == 2, r.stderr
    err = [ln for ln in r.stderr.strip().splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "s.toml: shapes.column.fracture:" in err[0], r.stderr
    assert "repair the mesh" in err[0] and "Traceback" not in r.stderr


def test_spheres_fracture_prints_each_piece_and_writes_them(tmp_path):
    r = dempipe(tmp_path, "spheres", "cylinder", "--resolution", "8", "--fracture", "5",
                "--seed", "2", "-o", "pieces.usda")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    pieces = [ln for ln in lines if ln.lstrip().startswith("piece ")]
    assert len(pieces) >= 5 and all("watertight yes" in ln and "spheres" in ln for ln in pieces)
    stage = Usd.Stage.Open(str(tmp_path / "pieces.usda"))
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert len(meshes) == len(pieces)
    for m in meshes:
        subs = UsdGeom.Subset.GetGeomSubsets(UsdGeom.Mesh(m), "face", "materialBind")
        assert len(subs) == 1 and len(subs[0].GetIndicesAttr().Get()) > 0
    again = dempipe(tmp_path, "spheres", "cylinder", "--resolution", "8", "--fracture", "5",
                    "--seed", "2")
    assert "cache hit" in again.stdout and again.stdout.count("piece ") == len(pieces)
