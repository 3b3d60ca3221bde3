"""What the preview reads from a stage (dempipe.preview.reader), without drawing: every
gprim a UsdPhysics stage uses is a geometry, and animated visibility is read per frame.
Needs pxr only (no GL)."""

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Gf, Usd, UsdGeom  # noqa: E402

from dempipe.preview.reader import StageReader  # noqa: E402

ROOT = __import__("pathlib").Path(__file__).resolve().parents[2]


def _stage(path):
    st = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(st, "Z")
    st.SetStartTimeCode(0)
    st.SetEndTimeCode(4)
    UsdGeom.Xform.Define(st, "/World")
    shapes = {"Cube": dict(size=0.2), "Sphere": dict(radius=0.1),
              "Cylinder": dict(radius=0.1, height=0.3), "Capsule": dict(radius=0.05, height=0.2),
              "Cone": dict(radius=0.1, height=0.2)}
    for i, (kind, attrs) in enumerate(shapes.items()):
        g = getattr(UsdGeom, kind).Define(st, f"/World/{kind}")
        for name, value in attrs.items():
            g.GetPrim().GetAttribute(name).Set(value)
        op = g.AddTranslateOp()
        op.Set(Gf.Vec3d(i, 0, 1), 0)
        op.Set(Gf.Vec3d(i, 0, 0.5), 4)          # moving: a body
    pi = UsdGeom.PointInstancer.Define(st, "/World/Inst")
    proto = UsdGeom.Sphere.Define(st, "/World/Inst/Protos/Ball")
    proto.CreateRadiusAttr(0.05)
    pi.CreatePrototypesRel().SetTargets([proto.GetPath()])
    pi.CreateProtoIndicesAttr([0, 0, 0])
    pi.CreatePositionsAttr([(0, 2, 0), (1, 2, 0), (2, 2, 0)])
    # emitted: invisible until time code 2 (the xforms layout's emitters)
    late = UsdGeom.Cube.Define(st, "/World/Late")
    late.CreateSizeAttr(0.1)
    late.AddTranslateOp().Set(Gf.Vec3d(5, 5, 5))
    vis = late.CreateVisibilityAttr()
    vis.Set(UsdGeom.Tokens.invisible, 0)
    vis.Set(UsdGeom.Tokens.inherited, 2)
    st.GetRootLayer().Save()


def _instances(batches):
    return sum(len(b.matrices) for b in batches)


def test_gprims_and_instanced_gprims_are_drawn_at_their_size(tmp_path):
    _stage(tmp_path / "g.usda")
    r = StageReader(tmp_path / "g.usda")
    batches = r.batches(3)
    assert _instances(batches) == 5 + 3 + 1
    sizes = {}
    for b in batches:
        sizes.setdefault(b.geometry.key.split("(")[0], []).append(b.geometry.hi - b.geometry.lo)

    def has(kind, extent):
        return any(np.allclose(e, extent, atol=2e-3) for e in sizes[kind])

    assert has("Cube", [0.2] * 3) and has("Cube", [0.1] * 3)          # the body, Late
    assert has("Sphere", [0.2] * 3) and has("Sphere", [0.1] * 3)      # the body, the protos
    assert has("Cylinder", [0.2, 0.2, 0.3])
    assert has("Capsule", [0.1, 0.1, 0.3])                            # height + 2 radii
    assert has("Cone", [0.2, 0.2, 0.2])
    assert all(len(b.geometry.triangles) for b in batches)


def test_animated_visibility_is_read_per_frame(tmp_path):
    _stage(tmp_path / "g.usda")
    r = StageReader(tmp_path / "g.usda")
    far = lambda batches: [b for b in batches                          # noqa: E731
                           if (b.matrices[:, 3, :3] == [5, 5, 5]).all(axis=1).any()]
    assert far(r.batches(0)) == [] and far(r.batches(1)) == []
    assert len(far(r.batches(2))) == 1 and len(far(r.batches(4))) == 1


def test_the_usd_input_example_draws_every_body_and_collider():
    # examples/usd_shot.usda: Sphere, Cube and Cylinder bodies and colliders, a crate
    # Mesh and instanced blocks; each is something to draw.
    stage = Usd.Stage.Open(str(ROOT / "examples" / "usd_shot.usda"))
    kinds = {"Mesh", "Cube", "Sphere", "Cylinder", "Capsule", "Cone"}
    want = 0
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    for p in it:
        if p.IsA(UsdGeom.PointInstancer):
            pi = UsdGeom.PointInstancer(p)
            want += len(pi.GetProtoIndicesAttr().Get(stage.GetStartTimeCode()) or [])
            it.PruneChildren()
        elif (p.GetTypeName() in kinds and UsdGeom.Imageable(p).ComputeVisibility()
              != UsdGeom.Tokens.invisible and UsdGeom.Imageable(p).GetPurposeAttr().Get()
              not in ("guide", "proxy")):
            want += 1
    r = StageReader(ROOT / "examples" / "usd_shot.usda")
    got = _instances(r.batches(r.frames[0]))
    assert want > 3 and got == want
    assert np.isfinite(np.concatenate([b.matrices for b in r.batches(r.frames[0])])).all()


def test_an_overlay_whose_input_is_gone_is_one_line(tmp_path):
    from dempipe.preview.reader import PreviewError
    from dempipe.scene.usd_stage import captured_stderr

    _stage(tmp_path / "g.usda")
    over = Usd.Stage.CreateNew(str(tmp_path / "o.usda"))
    over.GetRootLayer().subLayerPaths.append("gone.usda")
    over.GetRootLayer().Save()
    said = []
    with captured_stderr(said), pytest.raises(PreviewError) as err:
        StageReader(tmp_path / "o.usda")
    assert "gone.usda" in str(err.value) and "\n" not in str(err.value)
    assert said == []
