"""Fracture and glue from a UsdPhysics stage (scene.usd_attributes, usd.overlay pieces).

Stages are authored with pxr alone, as a DCC exporter would, the dempipe: attributes as
plain custom attributes. The bake is short and coarse; its checks are closed forms (mass,
momentum, free fall, the bonds' strength against the landing load) and the overlay read
back with pxr.
"""

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdShade, UsdValidation  # noqa: E402

from dempipe.errors import SceneError  # noqa: E402
from dempipe.pipeline.bake import bake  # noqa: E402
from dempipe.scene.build import build_model  # noqa: E402
from dempipe.scene.load import load_scene  # noqa: E402
from dempipe.spheres.cache import SphereCache  # noqa: E402
from processes import run  # noqa: E402

G = 9.81
_T = Sdf.ValueTypeNames
SIZE = (0.2, 0.1, 0.1)      # the block [m]
DENSITY = 2000.0            # [kg/m³]
GAP = 0.01                  # the blocks start this far above the ground [m]
VZ = -0.5                   # their initial vertical velocity [m/s]


def new_stage(path, mpu=1.0, end=3):
    st = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(st, "Z")
    UsdGeom.SetStageMetersPerUnit(st, mpu)
    st.SetStartTimeCode(0)
    st.SetEndTimeCode(end)
    st.SetTimeCodesPerSecond(24)
    st.SetDefaultPrim(UsdGeom.Xform.Define(st, "/World").GetPrim())
    UsdPhysics.Scene.Define(st, "/World/physicsScene")
    g = UsdGeom.Cube.Define(st, "/World/Ground")
    g.CreateSizeAttr(1.0)
    g.AddTranslateOp().Set(Gf.Vec3d(0, 0, -0.05 / mpu))
    g.AddScaleOp().Set(Gf.Vec3f(20 / mpu, 20 / mpu, 0.1 / mpu))
    UsdPhysics.CollisionAPI.Apply(g.GetPrim())
    return st


def glue_material(st, path, strength=None, mpu=1.0, **extra):
    mat = UsdShade.Material.Define(st, path)
    api = UsdPhysics.MaterialAPI.Apply(mat.GetPrim())
    api.CreateRestitutionAttr(0.2)
    api.CreateDynamicFrictionAttr(0.5)
    api.CreateDensityAttr(DENSITY * mpu ** 3)        # kg per cubic stage unit
    if strength is not None:
        mat.GetPrim().CreateAttribute("dempipe:glueStrength", _T.Double).Set(strength)
    for name, value in extra.items():
        mat.GetPrim().CreateAttribute(f"dempipe:{name}", _T.Double).Set(value)
    return mat


def block(st, path, at, mat=None, pieces=4, glue=True, mpu=1.0, velocity=(0, 0, VZ / 1.0),
          angular=None):
    """A SIZE box (a unit Cube scaled) at ``at`` [m], fractured into ``pieces``."""
    box = UsdGeom.Cube.Define(st, path)
    box.CreateSizeAttr(1.0)
    box.AddTranslateOp().Set(Gf.Vec3d(*(np.asarray(at) / mpu)))
    box.AddScaleOp().Set(Gf.Vec3f(*(np.asarray(SIZE) / mpu)))
    p = box.GetPrim()
    UsdPhysics.CollisionAPI.Apply(p)
    rb = UsdPhysics.RigidBodyAPI.Apply(p)
    rb.CreateVelocityAttr(Gf.Vec3f(*(np.asarray(velocity) / mpu)))
    if angular is not None:
        rb.CreateAngularVelocityAttr(Gf.Vec3f(*angular))
    if mat is not None:
        UsdShade.MaterialBindingAPI.Apply(p).Bind(mat, UsdShade.Tokens.weakerThanDescendants,
                                                  "physics")
    if pieces is not None:
        p.CreateAttribute("dempipe:fracture:pieces", _T.Int).Set(pieces)
        p.CreateAttribute("dempipe:fracture:seed", _T.Int).Set(2)
    if glue:
        p.CreateAttribute("dempipe:glue", _T.Bool).Set(True)
    return p


# ------------------------------------------------------------------ reading


def test_attributes_become_the_fracture_spec_and_the_glue(tmp_path):
    # a centimetre stage: the impact point and radius are in the body's local space in
    # stage units (scaled by the Cube's scale op), the glue in SI
    st = new_stage(tmp_path / "s.usda", mpu=0.01)
    mat = glue_material(st, "/World/Looks/Stone", 3e5, mpu=0.01, glueStiffness=2e6, glueDamping=0.4)
    p = block(st, "/World/Block", (0, 0, 0.2), mat, mpu=0.01)
    p.CreateAttribute("dempipe:fracture:impact", _T.Point3d).Set(Gf.Vec3d(0.5, 0, 0))
    p.CreateAttribute("dempipe:fracture:impactShare", _T.Double).Set(0.75)
    p.CreateAttribute("dempipe:fracture:impactRadius", _T.Double).Set(0.1)
    st.GetRootLayer().Save()
    scene = load_scene(tmp_path / "s.usda")
    spec = scene.shapes["Block"].fracture
    assert (spec.pieces, spec.seed, spec.impact_share) == (4, 2, 0.75)
    # local (0.5, 0, 0) on a unit cube scaled 20 cm along x: its +x face, 0.1 m out
    assert spec.impact == pytest.approx((0.1, 0.0, 0.0), abs=1e-12)
    # 0.1 local units times the stretch's mean scale (20·10·10)^(1/3) cm
    assert spec.impact_radius == pytest.approx(0.1 * 2000 ** (1 / 3) * 0.01, rel=1e-12)
    g = scene.bodies[0]
    assert g.glue and scene.usd.bodies[0].fractured
    m = scene.materials[g.material]
    assert (m.glue_strength, m.glue_stiffness, m.glue_damping) == (3e5, 2e6, 0.4)


def _refusal(tmp_path, author):
    """Load a stage with one glued, fractured block after ``author(stage, prim, mat)``."""
    st = new_stage(tmp_path / "bad.usda")
    mat = glue_material(st, "/World/Looks/Stone", 2e5)
    p = block(st, "/World/Block", (0, 0, 0.1), mat)
    author(st, p, mat.GetPrim())
    st.GetRootLayer().Save()
    with pytest.raises(SceneError) as e:
        load_scene(tmp_path / "bad.usda")
    return str(e.value)


def _set(prim, name, type_name, value):
    prim.CreateAttribute(name, type_name).Set(value)


def _on_the_shape(st, p, m):
    """The attributes on a collision child of an Xform body, not on the body."""
    xf = UsdGeom.Xform.Define(st, "/World/Rig")
    UsdPhysics.RigidBodyAPI.Apply(xf.GetPrim())
    c = UsdGeom.Cube.Define(st, "/World/Rig/Shape")
    UsdPhysics.CollisionAPI.Apply(c.GetPrim())
    _set(c.GetPrim(), "dempipe:fracture:pieces", _T.Int, 8)


def _instancer_proto(st, p, m):
    pi = UsdGeom.PointInstancer.Define(st, "/World/Crates")
    proto = UsdGeom.Cube.Define(st, "/World/Crates/Protos/Crate")
    proto.CreateSizeAttr(0.06)
    UsdPhysics.CollisionAPI.Apply(proto.GetPrim())
    UsdPhysics.RigidBodyAPI.Apply(proto.GetPrim())
    _set(proto.GetPrim(), "dempipe:fracture:pieces", _T.Int, 4)
    pi.CreatePrototypesRel().SetTargets([proto.GetPath()])
    pi.CreateProtoIndicesAttr([0])
    pi.CreatePositionsAttr([Gf.Vec3f(1.0, 0.0, 0.1)])


# (what is authored, the prim and attribute the message names, a word of its fix)
REFUSALS = [
    (lambda st, p, m: (p.RemoveProperty("dempipe:fracture:pieces"),
                       p.RemoveProperty("dempipe:fracture:seed")),
     "/World/Block", "dempipe:glue", "dempipe:fracture:pieces"),
    (lambda st, p, m: _set(m, "dempipe:glueStrength", _T.Double, -5.0),
     "/World/Looks/Stone", "dempipe:glueStrength", "(0, 1e+15]"),
    (lambda st, p, m: (p.RemoveProperty("dempipe:fracture:pieces"),
                       _set(p, "dempipe:fracture:pieces", _T.Double, 8.5)),
     "/World/Block", "dempipe:fracture:pieces", "int dempipe:fracture:pieces"),
    (lambda st, p, m: p.GetAttribute("dempipe:fracture:pieces").Set(1),
     "/World/Block", "dempipe:fracture:pieces", "from 2 to"),
    (lambda st, p, m: _set(p, "dempipe:fracture:piece", _T.Int, 8),
     "/World/Block", "dempipe:fracture:piece", "known here"),
    (lambda st, p, m: m.RemoveProperty("dempipe:glueStrength"),
     "/World/Block", "dempipe:glue", "dempipe:glueStrength"),
    (lambda st, p, m: (m.RemoveProperty("dempipe:glueStrength"),
                       _set(m, "dempipe:glueDamping", _T.Double, 0.5)),
     "/World/Looks/Stone", "dempipe:glueDamping", "dempipe:glueStrength"),
    (lambda st, p, m: _set(p, "dempipe:fracture:impactShare", _T.Double, 0.5),
     "/World/Block", "impactShare", "dempipe:fracture:impact"),
    (lambda st, p, m: UsdPhysics.RigidBodyAPI(p).CreateKinematicEnabledAttr(True),
     "/World/Block", "kinematic", "physics:kinematicEnabled"),
    (_instancer_proto, "/World/Crates[0]", "PointInstancer", "a prim of its own"),
    (_on_the_shape, "/World/Rig/Shape", "dempipe:fracture:pieces", "move it to /World/Rig"),
]


@pytest.mark.parametrize("author, prim, attribute, fix", REFUSALS,
                         ids=["glue-unfractured", "negative-strength", "non-integer-pieces",
                              "one-piece", "typo", "glue-without-strength",
                              "damping-without-strength", "share-without-impact",
                              "kinematic", "instancer", "on-the-shape"])
def test_bad_attributes_are_refused_naming_prim_and_attribute(tmp_path, author, prim,
                                                              attribute, fix):
    text = _refusal(tmp_path, author)
    assert text.startswith("bad.usda: ") and "\n" not in text
    assert prim in text and attribute in text and fix in text, text


def test_pieces_replace_the_body_with_its_mass_pose_and_motion(tmp_path):
    # closed forms: the pieces' masses sum to ρV, their centre of mass is the block's,
    # each moves as a point of the rigid block (v + ω × r), and they are bonded
    st = new_stage(tmp_path / "s.usda")
    mat = glue_material(st, "/World/Looks/Stone", 2e5)
    v, w_deg = np.array([0.3, 0.0, -0.5]), np.array([0.0, 0.0, 90.0])
    block(st, "/World/Block", (0.1, 0.2, 0.3), mat, velocity=v, angular=w_deg)
    st.GetRootLayer().Save()
    scene = load_scene(tmp_path / "s.usda")
    m = build_model(scene, cache=SphereCache(tmp_path / "cache"))
    n = m.n_bodies
    assert n >= 4 and set(m.body_labels) == {f"0_piece_{k:02d}" for k in range(n)}
    mass = np.asarray(m.body_mass[:n])
    # the Cube's scale op is float32: each side carries a relative error below 6e-8
    assert mass.sum() == pytest.approx(DENSITY * np.prod(SIZE), rel=2e-7)
    x = np.asarray(m.initial_x[:n])
    assert (mass[:, None] * x).sum(0) / mass.sum() == pytest.approx((0.1, 0.2, 0.3), abs=1e-9)
    w = np.radians(w_deg)
    v32 = v.astype(np.float32).astype(np.float64)        # physics:velocity is a float3
    expect = v32 + np.cross(w, x - np.array([0.1, 0.2, 0.3]))
    assert np.asarray(m.initial_v[:n]) == pytest.approx(expect, abs=1e-12)
    assert np.asarray(m.initial_w[:n]) == pytest.approx(np.tile(w, (n, 1)), abs=1e-12)
    assert m.n_bonds > 0 and set(np.asarray(m.body_glue[:n]).tolist()) == {0}


# -------------------------------------------------------------------- a bake

STRONG, WEAK = 1e12, 1.0     # [Pa]: σ d² about 1e8 N, and about 1e-3 N


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    """Two glued blocks dropped onto the ground: one of a glue no landing breaks, one
    of a glue the weight alone breaks; 3 frames at resolution 6."""
    d = tmp_path_factory.mktemp("glue")
    st = new_stage(d / "blocks.usda")
    strong = glue_material(st, "/World/Looks/Strong", STRONG)
    weak = glue_material(st, "/World/Looks/Weak", WEAK)
    block(st, "/World/Strong", (0.0, 0.0, SIZE[2] / 2 + GAP), strong)
    block(st, "/World/Weak", (0.0, 0.5, SIZE[2] / 2 + GAP), weak)
    st.GetRootLayer().Save()
    (d / "blocks.toml").write_text('[usd]\nstage = "blocks.usda"\n'
                                   "[simulation]\nresolution = 6\n")
    cache = SphereCache(d / "cache")
    result = bake(d / "blocks.toml", d / "out" / "blocks_baked.usda", device="cpu",
                  cache=cache, warn=lambda w: None)
    scene = load_scene(d / "blocks.toml")
    model = build_model(scene, cache=cache)
    return dict(dir=d, stage=d / "blocks.usda", out=result.path, report=result.report,
                model=model, scene=scene)


def _group(baked, name):
    """The Model's group index of the body prim /World/<name> (the shot's body index)."""
    return [b.prim for b in baked["scene"].usd.bodies].index(f"/World/{name}")


def _pieces(stage, group):
    return [p for p in stage.GetPrimAtPath(group).GetChildren() if p.IsA(UsdGeom.Mesh)]


def test_overlay_hides_the_whole_body_and_writes_each_piece(baked):
    stage = Usd.Stage.Open(str(baked["out"]))
    model = baked["model"]
    for name in ("Strong", "Weak"):
        assert not stage.GetPrimAtPath(f"/World/{name}").IsActive()
        pieces = _pieces(stage, f"/World/{name}_pieces")
        g = _group(baked, name)
        assert len(pieces) == int((np.asarray(model.body_group[:model.n_bodies]) == g).sum())
        for p in pieces:
            assert p.HasAPI(UsdPhysics.RigidBodyAPI) and p.HasAPI(UsdPhysics.CollisionAPI)
            assert UsdGeom.Xformable(p).TransformMightBeTimeVarying()
            sub = [s for s in UsdShade.MaterialBindingAPI(p).GetMaterialBindSubsets()]
            assert [s.GetPrim().GetName() for s in sub] == ["inside"]
            inside = UsdShade.MaterialBindingAPI(sub[0].GetPrim()).ComputeBoundMaterial()[0]
            assert inside.GetPath().name == "inside_mat"
            assert len(sub[0].GetIndicesAttr().Get()) > 0
            phys = UsdShade.MaterialBindingAPI(p).ComputeBoundMaterial("physics")[0]
            assert str(phys.GetPath()) == f"/World/Looks/{name}"
    ctx = UsdValidation.ValidationContext(
        UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    errors = [e.GetMessage() for e in ctx.Validate(stage)
              if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert errors == []


def _world_points(stage, prim, t):
    pts = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(), np.float64)
    M = np.asarray(UsdGeom.XformCache(Usd.TimeCode(t)).GetLocalToWorldTransform(prim))
    return np.c_[pts, np.ones(len(pts))] @ M


def test_pieces_start_as_the_block_and_fall_freely_until_they_land(baked):
    stage = Usd.Stage.Open(str(baked["out"]))
    model = baked["model"]
    pieces = _pieces(stage, "/World/Strong_pieces")
    # frame 0: the pieces' points fill the block's box (the cut is inside it)
    pts = np.concatenate([_world_points(stage, p, 0)[:, :3] for p in pieces])
    z0 = SIZE[2] / 2 + GAP
    lo, hi = np.array([-0.1, -0.05, z0 - 0.05]), np.array([0.1, 0.05, z0 + 0.05])
    # float32 points: 1e-6 m
    assert pts.min(0) == pytest.approx(lo, abs=1e-6) and pts.max(0) == pytest.approx(hi, abs=1e-6)
    # each piece starts with the block's velocity (no spin: v + ω × r = v)
    for p in pieces:
        v = UsdPhysics.RigidBodyAPI(p).GetVelocityAttr().Get(0)
        assert v[2] == pytest.approx(VZ, abs=1e-6)
    # after landing the strong block rests on the ground: its bottom within the
    # contact overlap (the auto stiffness aims at 2 % of a sphere) of z = 0
    end = int(stage.GetEndTimeCode())
    bottom = min(_world_points(stage, p, end)[:, 2].min() for p in pieces)
    assert abs(bottom) < 0.05 * model.diameter


def test_weak_glue_breaks_on_landing_and_strong_glue_holds(baked):
    # every bond of the weak block breaks (its weight, 4 kg·g ≈ 40 N, is 4e4 times a
    # bond's σ d²), none of the strong one's (σ d² ≈ 1e9 N). The strong block's pieces
    # keep their distances to 1e-3 of a sphere (a bond's stretch under the landing;
    # measured 1e-5), the weak one's move apart by more than 1e-2 (measured 0.06)
    model, report = baked["model"], baked["report"]
    bond_group = np.asarray(model.body_group)[np.asarray(model.bonds.bond_body[:, 0])]
    weak = _group(baked, "Weak")
    assert report["bonds"] == model.n_bonds
    assert sum(report["bonds_broken_per_frame"]) == int((bond_group == weak).sum()) > 0
    stage = Usd.Stage.Open(str(baked["out"]))
    end = int(stage.GetEndTimeCode())

    def change(name):
        pieces = _pieces(stage, f"/World/{name}_pieces")

        def distances(t):
            c = np.array([np.asarray(UsdGeom.XformCache(Usd.TimeCode(t))
                                     .GetLocalToWorldTransform(p))[3, :3] for p in pieces])
            return np.linalg.norm(c[:, None] - c[None], axis=2)

        return np.abs(distances(end) - distances(0)).max() / model.diameter

    assert change("Strong") < 1e-3
    assert change("Weak") > 1e-2


def test_preview_reader_draws_the_pieces_not_the_block(baked):
    from dempipe.preview.reader import StageReader

    r = StageReader(baked["out"])
    stage = r.stage
    n = sum(len(_pieces(stage, f"/World/{k}_pieces")) for k in ("Strong", "Weak"))
    drawn = [b for b in r.batches(0) if b.body]
    assert sum(len(b.matrices) for b in drawn) == n


def test_check_on_the_stage_counts_the_bonds(baked):
    # the stage itself, at dempipe's default resolution: its own Model's bonds
    cache = baked["dir"] / "cache"
    expect = build_model(load_scene(baked["stage"]), cache=SphereCache(cache)).n_bonds
    code, out, err = run("check", baked["stage"], cache=cache)
    assert f"{expect:,} bonds" in out + err, out + err


def test_example_stage_bakes_its_column_into_pieces(tmp_path):
    """examples/usd_glue.usda over its first 3 frames (1/12 s: it falls 3.4 cm of the
    7.8 cm between its lowest corner and the floor, and a lattice sphere reaches at most
    d/2 = 4.2 cm past the mesh): the column's prim off, its pieces moving beside it,
    no bond broken in free fall (gravity loads no bond)."""
    root = __import__("pathlib").Path(__file__).resolve().parents[2]
    stage = Usd.Stage.Open(str(root / "examples" / "usd_glue.usda"))
    stage.SetEndTimeCode(stage.GetStartTimeCode() + 2)
    stage.GetRootLayer().Export(str(tmp_path / "usd_glue.usda"))
    result = bake(tmp_path / "usd_glue.usda", tmp_path / "out.usda", device="cpu",
                  simulation={"resolution": 12}, cache=SphereCache(tmp_path / "cache"),
                  warn=lambda w: None)
    assert result.report["bonds"] > 0 and sum(result.report["bonds_broken_per_frame"]) == 0
    out = Usd.Stage.Open(str(result.path))
    assert not out.GetPrimAtPath("/World/Column").IsActive()
    pieces = _pieces(out, "/World/Column_pieces")
    assert len(pieces) == result.report["bodies"] >= 12
    # it falls: every piece lower at the last frame than at the first (Y up)
    for p in pieces:
        y = [np.asarray(UsdGeom.XformCache(Usd.TimeCode(t)).GetLocalToWorldTransform(p))[3, 1]
             for t in (1, 3)]
        assert y[1] < y[0]


def test_pieces_compose_to_the_simulated_pose_under_any_parents(tmp_path):
    """Frames with known poses (no simulation) written as an overlay: each piece's
    points, composed by USD through its ops and the fractured body's parents, land
    where dempipe's pose puts them (R(q) p + x, p the piece's body-frame vertex).
    Covers an uneven parent scale (the matrix op), a reset transform stack and an
    animated parent, in a centimetre stage."""
    from dempipe.sim.model import quat_to_matrix
    from moved import moved_frames
    from dempipe.usd.overlay import OP_MATRIX, write_overlay

    st = new_stage(tmp_path / "p.usda", mpu=0.01, end=2)
    squash = UsdGeom.Xform.Define(st, "/World/Squash")
    squash.AddRotateXOp().Set(30.0)
    squash.AddScaleOp().Set(Gf.Vec3f(1, 2, 3))
    mover = UsdGeom.Xform.Define(st, "/World/Mover")
    op = mover.AddTranslateOp()
    for t in range(3):
        op.Set(Gf.Vec3d(5 * t, 0, 0), t)
    for path, at, reset in (("/World/Squash/A", (0, 0, 10), False),
                            ("/World/Squash/B", (20, 0, 10), True),
                            ("/World/Mover/C", (-20, 0, 10), False)):
        c = UsdGeom.Cube.Define(st, path)
        c.CreateSizeAttr(4)
        c.AddTranslateOp().Set(Gf.Vec3d(*at))
        c.SetResetXformStack(reset)
        p = c.GetPrim()
        UsdPhysics.CollisionAPI.Apply(p)
        UsdPhysics.RigidBodyAPI.Apply(p)
        p.CreateAttribute("dempipe:fracture:pieces", _T.Int).Set(3)
    st.GetRootLayer().Save()

    scene = load_scene(tmp_path / "p.usda")
    model = build_model(scene, cache=SphereCache(tmp_path / "cache"))
    n = model.n_bodies
    frames = moved_frames(model)
    x, q = frames.x, frames.q
    out = tmp_path / "out" / "p_baked.usdc"
    write_overlay(out, frames, model, scene.usd)

    stage = Usd.Stage.Open(str(out))
    group = np.asarray(model.body_group)[:n]
    prims = [b.prim for b in scene.usd.bodies]
    checked = 0
    for g, path in enumerate(prims):
        assert not stage.GetPrimAtPath(path).IsActive()
        pieces = _pieces(stage, path + "_pieces")
        bodies = np.flatnonzero(group == g)
        assert len(pieces) == len(bodies) >= 2
        if path == "/World/Squash/A":
            assert list(pieces[0].GetAttribute("xformOpOrder").Get()) == [OP_MATRIX]
        for prim, k in zip(pieces, bodies):
            verts = np.asarray(model.shapes[model.body_shape[k]].vertices)
            for f in range(3):
                got = _world_points(stage, prim, f)[:, :3] * 0.01
                want = verts @ quat_to_matrix(q[f, k]).T + x[f, k]
                # float32 points (a few cm: 2e-9 m steps) under double matrices
                assert got == pytest.approx(want, abs=1e-6), (path, k, f)
                checked += 1
    assert checked == 3 * n


ROUND_TRIP = """
[output]
fps = 24
duration = 0.5
meters_per_unit = 0.01

[materials.stone]
density = 2400.0
glue_strength = 3.0e5
glue_stiffness = 2.0e6
glue_damping = 0.5

[shapes.column]
builtin = "box"
size = [0.1, 0.1, 0.4]
fracture = { pieces = 6, seed = 4, impact = [0.0, 0.0, 0.15], impact_share = 0.6, impact_radius = 0.05 }

[[bodies]]
name = "column"
shape = "column"
material = "stone"
position = [0.0, 0.0, 0.25]
velocity = [0.0, 0.0, -1.0]
glue = true
"""


def test_scene_export_keeps_fracture_and_glue(tmp_path):
    """A TOML scene's fracture and glue exported as dempipe: attributes (`dempipe scene
    export`, a centimetre stage) and read back: the same spec, glue and material glue,
    hence the same pieces (count, masses) and bonds."""
    from dempipe.usd.physics_stage import write_physics_stage

    (tmp_path / "s.toml").write_text(ROUND_TRIP)
    a = load_scene(tmp_path / "s.toml")
    write_physics_stage(a, tmp_path / "s.usda")
    b = load_scene(tmp_path / "s.usda")
    fa, fb = a.shapes["column"].fracture, b.shapes[b.bodies[0].shape].fracture
    assert (fb.pieces, fb.seed, fb.impact_share) == (fa.pieces, fa.seed, fa.impact_share)
    # through stage units (cm) and back: a double's rounding
    assert fb.impact == pytest.approx(fa.impact, abs=1e-15)
    assert fb.impact_radius == pytest.approx(fa.impact_radius, rel=1e-15)
    assert b.bodies[0].glue
    mb = b.materials[b.bodies[0].material]
    assert (mb.glue_strength, mb.glue_stiffness, mb.glue_damping) == (3e5, 2e6, 0.5)
    cache = SphereCache(tmp_path / "cache")
    ma, mb = build_model(a, cache=cache), build_model(b, cache=cache)
    assert mb.n_bodies == ma.n_bodies and mb.n_bonds == ma.n_bonds > 0
    # float32 points: the masses to float32 precision
    assert np.sort(mb.body_mass[:mb.n_bodies]) == pytest.approx(
        np.sort(ma.body_mass[:ma.n_bodies]), rel=1e-5)
