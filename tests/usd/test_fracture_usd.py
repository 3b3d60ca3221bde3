"""A fractured shape in the USD: one body per piece in both layouts, each piece's
broken faces a materialBind GeomSubset bound to the inside material; read back
with pxr from a real bake (the chunked writer) of a dropped fractured box."""

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdShade

import dempipe
from dempipe.scene.build import build_model
from dempipe.scene.load import load_scene

SCENE = """
[output]
fps = 24
duration = {duration}

[simulation]
resolution = 8

[materials.stone]
density = 2000.0
restitution = 0.2
friction = 0.5

[shapes.block]
builtin = "box"
size = [0.2, 0.1, 0.1]
fracture = {{ pieces = 4, seed = 2 }}

[[bodies]]
name = "block"
shape = "block"
material = "stone"
layout = "grid"
origin = [0.0, 0.0, 0.1]
dims = [2, 1, 1]
spacing = [0.4, 0.2, 0.2]
velocity = [0.0, 0.0, -0.5]
angular_velocity = [0.0, 0.0, 2.0]

[[colliders]]
type = "plane"
material = "stone"
"""


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("frac") / "block.toml"
    p.write_text(SCENE.format(duration=0.125))
    return p


@pytest.fixture(scope="module")
def model(scene_file):
    return build_model(load_scene(scene_file))


def _all_prims(stage):
    return list(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)))


def test_each_instance_is_its_pieces_moving_as_one_body(model):
    n_pieces = len(model.shapes)
    assert model.n_bodies == 2 * n_pieces
    assert model.body_labels[:2] == ("0_piece_00", "0_piece_01")
    assert model.body_labels[n_pieces] == "1_piece_00"
    # the pieces' masses add up to the block's: density x volume (the pieces'
    # volumes sum to the box's within 1e-9, tests/mesh/test_fracture.py)
    assert model.body_mass[:n_pieces].sum() == pytest.approx(2000.0 * 0.2 * 0.1 * 0.1, rel=1e-9)
    # rigid motion of the whole: v_piece = v + w x r (r from the block's centre of
    # mass, at the grid origin; the box is centred on its own origin)
    x = model.initial_x[:n_pieces]
    r = x - np.array([0.0, 0.0, 0.1])
    expect = np.array([0.0, 0.0, -0.5]) + np.cross([0.0, 0.0, 2.0], r)
    np.testing.assert_allclose(model.initial_v[:n_pieces], expect, atol=1e-12)
    # momentum of the pieces is that of the block (centre of mass velocity)
    m = model.body_mass[:n_pieces]
    np.testing.assert_allclose((m[:, None] * model.initial_v[:n_pieces]).sum(0) / m.sum(),
                               [0.0, 0.0, -0.5], atol=1e-12)


@pytest.mark.parametrize("layout", ["instancer", "xforms"])
def test_baked_pieces_and_their_inside_material_read_back(tmp_path, scene_file, model, layout):
    out = tmp_path / f"block_{layout}.usda"
    dempipe.bake(scene_file, out, layout=layout, device="cpu", checkpoints=False)
    stage = Usd.Stage.Open(str(out))
    prims = _all_prims(stage)
    subsets = [p for p in prims if p.GetTypeName() == "GeomSubset"
               and "Bodies" in str(p.GetPath())]
    inside = stage.GetPrimAtPath("/World/Looks/inside_mat")
    assert inside and inside.GetTypeName() == "Material"
    n_pieces = len(model.shapes)
    # instancer: one prototype per piece; xforms: one per body, through its instance
    assert len(subsets) == (n_pieces if layout == "instancer" else model.n_bodies)
    for sub in subsets:
        s = UsdGeom.Subset(sub)
        assert s.GetElementTypeAttr().Get() == "face"
        assert s.GetFamilyNameAttr().Get() == "materialBind"
        mesh = UsdGeom.Mesh(sub.GetParent())
        ok, why = UsdGeom.Subset.ValidateFamily(mesh, "face", "materialBind")
        assert ok, why
        bound, _ = UsdShade.MaterialBindingAPI(sub).ComputeBoundMaterial()
        assert bound.GetPath() == inside.GetPath()
        # the subset is exactly the piece's broken faces
        shape = next(sh for sh in model.shapes if str(sh.name) in str(sub.GetPath()))
        np.testing.assert_array_equal(np.asarray(s.GetIndicesAttr().Get()), shape.inside_faces)
    if layout == "xforms":
        names = {p.GetName() for p in prims if p.GetParent().GetName() == "block"}
        assert {"block_0_piece_00", f"block_1_piece_{n_pieces - 1:02d}"} <= names


def test_the_column_example_bakes_a_short_range_to_a_valid_stage(tmp_path):
    """examples/column_drop.toml (README) in a real subprocess, the first frames:
    16 piece bodies, a stage every USD validator passes (GeomSubsets included)."""
    import subprocess
    import sys
    from pathlib import Path

    from pxr import UsdValidation

    example = Path(__file__).resolve().parents[2] / "examples" / "column_drop.toml"
    out = tmp_path / "out.usda"
    proc = subprocess.run([sys.executable, "-m", "dempipe_cli.main", "bake", str(example),
                           "-o", str(out), "--frames", "0:2", "-q", "--layout", "xforms"],
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr
    stage = Usd.Stage.Open(str(out))
    ctx = UsdValidation.ValidationContext(
        UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    errors = [e for e in ctx.Validate(stage)
              if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert not errors, [e.GetMessage() for e in errors]
    bodies = stage.GetPrimAtPath("/World/Bodies/column").GetChildren()
    assert [b.GetName() for b in bodies][:2] == ["column_0_piece_00", "column_0_piece_01"]
    assert len(bodies) == 16
