"""usd/animation.py: read the written stages back with pxr and compare with the input.

The model is a ``SimpleNamespace`` carrying exactly the fields the exporter reads
(docs/architecture.md, "Contracts"), with real trimesh meshes, so these tests do
not depend on model.py. The motion is analytic: each body translates at a
constant velocity while spinning about world z at a constant rate on top of a
fixed initial tilt; one body never moves, one stops halfway.
"""

from __future__ import annotations

import os
import types

import numpy as np
import pytest
import trimesh
from pxr import Sdf, Usd, UsdGeom, UsdValidation

import dempipe
from dempipe.errors import ExportError
from dempipe.usd import animation as usd_export
from dempipe.usd.animation import ExportInfo, write_usd
from dempipe.sim.frames import Frames

FPS = 24.0
FIRST = 10          # first frame number: time codes need not start at 0
N_FRAMES = 12
REST = 6            # body that never moves
STOPPER = 5         # body that stops at frame STOP
STOP = 6


# ----------------------------------------------------------------- fixtures


def _quat_mul(a, b):
    """Hamilton product of (..., 4) quaternions (w, x, y, z)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def _quat_matrix(q):
    """(4,) unit quaternion (w, x, y, z) -> (3, 3) rotation matrix (column vectors)."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _shape(name, mesh):
    """A ShapeInstance stand-in: vertices in the body frame (COM at the origin)."""
    return types.SimpleNamespace(
        name=name, vertices=np.asarray(mesh.vertices - mesh.center_mass), faces=np.asarray(mesh.faces)
    )


def make_model(meters_per_unit=1.0, up_axis="Z"):
    cone = trimesh.creation.cone(radius=0.04, height=0.12)      # COM off the mesh origin
    assert np.linalg.norm(cone.center_mass) > 0.01
    shapes = (
        _shape("brick", trimesh.creation.box(extents=(0.10, 0.06, 0.04))),
        _shape("ball", trimesh.creation.icosphere(subdivisions=2, radius=0.05)),
        _shape("cone", cone),
    )
    body_shape = np.array([0, 1, 2, 1, 0, 1, 2])
    body_group = np.array([0, 1, 0, 1, 0, 1, 0])
    body_group_index = np.array([0, 0, 1, 1, 2, 2, 3])
    box = types.SimpleNamespace(lo=np.array([-1.0, -1.0, 0.0]), hi=np.array([1.0, 1.0, 1.0]),
                                open_top=True, thickness=0.02)
    ground = trimesh.creation.box(extents=(0.3, 0.3, 0.05))
    ground.apply_translation((1.5, 0.0, 0.3))
    static = types.SimpleNamespace(name="ramp 1", vertices=np.asarray(ground.vertices),
                                   faces=np.asarray(ground.faces))
    return types.SimpleNamespace(
        shapes=shapes,
        n_bodies=7,
        body_shape=body_shape,
        body_group=body_group,
        group_names=("pieces", "balls"),
        body_group_index=body_group_index,
        plane_point=np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]),
        plane_normal=np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]]),
        boxes=(box,),
        static_meshes=(static,),
        fps=FPS,
        up_axis=up_axis,
        meters_per_unit=meters_per_unit,
    )


def make_frames(n_bodies=7, n_frames=N_FRAMES, rest=(REST,), stopper=STOPPER, stop=STOP):
    """Analytic motion: x = x0 + v t, q = q_z(omega t) * q0, world angular velocity (0, 0, omega)."""
    rng = np.random.default_rng(7)
    fn = np.arange(FIRST, FIRST + n_frames, dtype=np.int64)
    t = (fn - FIRST) / FPS
    x0 = rng.uniform(-0.8, 0.8, (n_bodies, 3)) + np.array([0, 0, 1.0])
    vel = rng.uniform(-1.0, 1.0, (n_bodies, 3))
    omega = rng.uniform(1.0, 6.0, n_bodies) * rng.choice([-1, 1], n_bodies)
    axis0 = rng.normal(size=(n_bodies, 3))
    axis0 /= np.linalg.norm(axis0, axis=1, keepdims=True)
    ang0 = rng.uniform(0, np.pi, n_bodies)
    q0 = np.concatenate([np.cos(ang0 / 2)[:, None], np.sin(ang0 / 2)[:, None] * axis0], axis=1)
    for b in rest:
        vel[b] = 0.0
        omega[b] = 0.0
    tb = np.broadcast_to(t[:, None], (n_frames, n_bodies)).copy()     # motion time per body
    moving = np.ones((n_frames, n_bodies), dtype=bool)
    if stopper is not None:
        tb[:, stopper] = np.minimum(t, t[stop])
        moving[stop:, stopper] = False
    x = x0[None] + tb[..., None] * vel[None]
    half = 0.5 * tb * omega[None]
    qz = np.zeros((n_frames, n_bodies, 4))
    qz[..., 0] = np.cos(half)
    qz[..., 3] = np.sin(half)
    q = _quat_mul(qz, np.broadcast_to(q0, qz.shape))
    v = np.where(moving[..., None], vel[None], 0.0)
    w = np.zeros((n_frames, n_bodies, 3))
    w[..., 2] = np.where(moving, omega[None], 0.0)
    return Frames(fn, t, x, q, v, w)


def expected_vertices(model, frames, f, b, scale=1.0):
    """World vertices of body b at frame index f from the inputs: x + R(q) (p - com)."""
    verts = model.shapes[model.body_shape[b]].vertices
    return (frames.x[f, b] + verts @ _quat_matrix(frames.q[f, b]).T) * scale


def _apply(matrix, points):
    """USD row-vector convention: p' = p M."""
    m = np.array(matrix, dtype=np.float64)
    return points @ m[:3, :3] + m[3, :3]


def validation_issues(path):
    """(errors, warnings) from every registered validator."""
    stage = Usd.Stage.Open(str(path))
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert len(validators) > 10
    issues = UsdValidation.ValidationContext(validators).Validate(stage)
    errors = [e.GetErrorAsString() for e in issues if e.GetType() == UsdValidation.ValidationErrorType.Error]
    warnings = [e.GetErrorAsString() for e in issues if e.GetType() == UsdValidation.ValidationErrorType.Warn]
    return errors, warnings


def instancer_vertices(stage, model, frames, f):
    """World vertices of every body at frame index f, read from the PointInstancer."""
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    t = Usd.TimeCode(float(frames.frame_numbers[f]))
    mats = pi.ComputeInstanceTransformsAtTime(t, t)
    indices = pi.GetProtoIndicesAttr().Get(t)
    targets = pi.GetPrototypesRel().GetTargets()
    out = []
    for b, m in enumerate(mats):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(targets[indices[b]]))
        out.append(_apply(m, np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)))
    return out


def body_prim_path(model, b):
    g = model.group_names[model.body_group[b]]
    return f"/World/Bodies/{g}/{g}_{model.body_group_index[b]}"


def xforms_vertices(stage, model, frames, f):
    """World vertices of every body at frame index f, read from the per-body Xforms."""
    cache = UsdGeom.XformCache(Usd.TimeCode(float(frames.frame_numbers[f])))
    out = []
    for b in range(model.n_bodies):
        prim = stage.GetPrimAtPath(body_prim_path(model, b))
        mesh = prim.GetChild(model.shapes[model.body_shape[b]].name)
        pts = np.array(UsdGeom.Mesh(mesh).GetPointsAttr().Get(), dtype=np.float64)
        out.append(_apply(cache.GetLocalToWorldTransform(mesh), pts))
    return out


def _radius(model, b):
    return float(np.linalg.norm(model.shapes[model.body_shape[b]].vertices, axis=1).max())


# Orientations of a PointInstancer are quath (IEEE half: 11 significant bits).
# Rounding each unit-quaternion component costs at most 2^-12 ≈ 2.4e-4, so the
# rotation is off by at most about 2·|dq| ≈ 1e-3 rad and a vertex at distance r
# from the centre of mass moves by about 1e-3·r; allow 2e-3·r. Positions are
# float32 (relative 6e-8, i.e. < 1e-6 m here).
HALF_ROT_TOL = 2e-3


# -------------------------------------------------------------------- tests


@pytest.mark.parametrize("ext", [".usda", ".usdc", ".usd"])
def test_metadata_and_prim_types(tmp_path, ext):
    model, frames = make_model(), make_frames()
    info = write_usd(tmp_path / f"scene{ext}", frames, model)
    assert isinstance(info, ExportInfo)
    assert info.path == tmp_path / f"scene{ext}" and info.bytes == info.path.stat().st_size > 0
    assert info.seconds > 0 and info.n_time_samples > 0
    stage = Usd.Stage.Open(str(info.path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetRootLayer().pseudoRoot.GetInfo("kilogramsPerUnit") == 1.0
    assert stage.GetTimeCodesPerSecond() == FPS and stage.GetFramesPerSecond() == FPS
    assert stage.GetStartTimeCode() == FIRST
    assert stage.GetEndTimeCode() == FIRST + N_FRAMES - 1
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    assert "dempipe" in stage.GetRootLayer().documentation
    assert stage.GetRootLayer().customLayerData["dempipe"]["version"] == dempipe.__version__

    assert stage.GetPrimAtPath("/World").GetTypeName() == "Xform"
    pi_prim = stage.GetPrimAtPath("/World/Bodies")
    assert pi_prim.GetTypeName() == "PointInstancer"
    pi = UsdGeom.PointInstancer(pi_prim)
    targets = pi.GetPrototypesRel().GetTargets()
    assert [str(p) for p in targets] == [
        "/World/Bodies/brick", "/World/Bodies/ball", "/World/Bodies/cone"]
    for p, shape in zip(targets, model.shapes):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(p))
        assert mesh.GetPrim().GetTypeName() == "Mesh"
        np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get()), shape.vertices, atol=1e-7)
        np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()), shape.faces.ravel())
        assert set(mesh.GetFaceVertexCountsAttr().Get()) == {3}
        assert mesh.GetSubdivisionSchemeAttr().Get() == "none"
        ext_ = np.array(mesh.GetExtentAttr().Get())
        np.testing.assert_allclose(ext_, [shape.vertices.min(0), shape.vertices.max(0)], atol=1e-7)

    # protoIndices and ids: authored once, as defaults; ids are int64 scene indices.
    for attr in (pi.GetProtoIndicesAttr(), pi.GetIdsAttr()):
        assert attr.HasAuthoredValue() and attr.GetNumTimeSamples() == 0
    assert pi.GetIdsAttr().GetTypeName() == Sdf.ValueTypeNames.Int64Array
    np.testing.assert_array_equal(np.array(pi.GetIdsAttr().Get()), np.arange(7))
    np.testing.assert_array_equal(np.array(pi.GetProtoIndicesAttr().Get()), model.body_shape)
    for attr in (pi.GetPositionsAttr(), pi.GetOrientationsAttr(), pi.GetExtentAttr()):
        assert attr.GetNumTimeSamples() == N_FRAMES, attr.GetName()
    # Velocities are constant until STOPPER stops, but USD uses them only at the
    # times positions (orientations) are sampled: they keep those times.
    for attr in (pi.GetVelocitiesAttr(), pi.GetAngularVelocitiesAttr()):
        assert attr.GetNumTimeSamples() == N_FRAMES, attr.GetName()
    assert pi.GetOrientationsAttr().GetTypeName() == Sdf.ValueTypeNames.QuathArray

    colliders = stage.GetPrimAtPath("/World/Colliders")
    names = [c.GetName() for c in colliders.GetChildren()]
    assert names == ["plane_0", "plane_1", "box_0", "ramp_1"]
    assert all(c.GetTypeName() == "Mesh" for c in colliders.GetChildren())


def test_instancer_transforms_match_input(tmp_path):
    model, frames = make_model(), make_frames()
    path = write_usd(tmp_path / "scene.usdc", frames, model).path
    stage = Usd.Stage.Open(str(path))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    for f in range(N_FRAMES):
        t = Usd.TimeCode(float(frames.frame_numbers[f]))
        np.testing.assert_allclose(np.array(pi.GetPositionsAttr().Get(t)), frames.x[f], rtol=1e-6, atol=1e-7)
        got = instancer_vertices(stage, model, frames, f)
        for b in range(model.n_bodies):
            np.testing.assert_allclose(got[b], expected_vertices(model, frames, f, b),
                                       atol=HALF_ROT_TOL * _radius(model, b) + 1e-6)
        # The per-frame extent bounds every vertex of every instance.
        lo, hi = np.array(pi.GetExtentAttr().Get(t))
        allv = np.concatenate(got)
        assert np.all(allv >= lo - 1e-6) and np.all(allv <= hi + 1e-6)


def test_quath_order_round_trip():
    """GfQuath stores (i, j, k, real): the exporter's (w,x,y,z) -> memory conversion."""
    from pxr import Vt
    q = np.array([[0.5, 0.5, -0.5, 0.5]])
    arr = Vt.QuathArray.FromNumpy(usd_export.quat_xyzw(q, np.float16))
    assert arr[0].GetReal() == 0.5
    assert tuple(arr[0].GetImaginary()) == (0.5, -0.5, 0.5)


def test_velocities_read_back(tmp_path):
    model, frames = make_model(), make_frames()
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "scene.usda", frames, model).path))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    for f in range(N_FRAMES):
        t = Usd.TimeCode(float(frames.frame_numbers[f]))
        np.testing.assert_allclose(np.array(pi.GetVelocitiesAttr().Get(t)), frames.v[f], rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(np.array(pi.GetAngularVelocitiesAttr().Get(t)),
                                   np.degrees(frames.w[f]), rtol=1e-6, atol=1e-5)


def test_xforms_layout_matches_instancer(tmp_path):
    model, frames = make_model(), make_frames()
    inst = Usd.Stage.Open(str(write_usd(tmp_path / "a.usdc", frames, model).path))
    xf = Usd.Stage.Open(str(write_usd(tmp_path / "b.usdc", frames, model, layout="xforms").path))
    for b in range(model.n_bodies):
        prim = xf.GetPrimAtPath(body_prim_path(model, b))
        assert prim.IsValid() and prim.GetTypeName() == "Xform" and prim.IsInstance()
        ops = UsdGeom.Xformable(prim).GetOrderedXformOps()
        assert [op.GetOpName() for op in ops] == ["xformOp:translate", "xformOp:orient"]
        assert ops[0].GetPrecision() == UsdGeom.XformOp.PrecisionDouble
        assert ops[1].GetPrecision() == UsdGeom.XformOp.PrecisionFloat
        assert prim.GetChild(model.shapes[model.body_shape[b]].name).GetTypeName() == "Mesh"
    proto = xf.GetPrimAtPath("/World/Prototypes/cone")
    assert proto.GetSpecifier() == Sdf.SpecifierClass and proto.IsAbstract()
    # Prototypes, and the Scope holding them, are not part of the default traversal
    # (not drawn, not imported: no stray empty object in a DCC).
    assert not any(p.GetPath().HasPrefix("/World/Prototypes") for p in xf.Traverse())

    for f in range(N_FRAMES):
        a = instancer_vertices(inst, model, frames, f)
        b_ = xforms_vertices(xf, model, frames, f)
        for b in range(model.n_bodies):
            r = _radius(model, b)
            # xforms (quatf, double) is exact to float32; the instancer carries quath error.
            np.testing.assert_allclose(b_[b], expected_vertices(model, frames, f, b), atol=1e-6)
            np.testing.assert_allclose(a[b], b_[b], atol=HALF_ROT_TOL * r + 1e-6)


@pytest.mark.parametrize("layout", ["instancer", "xforms"])
@pytest.mark.parametrize("ext", [".usda", ".usdc"])
def test_validation_clean(tmp_path, layout, ext):
    path = write_usd(tmp_path / f"scene{ext}", make_frames(), make_model(), layout=layout).path
    errors, warnings = validation_issues(path)
    assert errors == []
    assert warnings == []


def test_y_up_and_single_frame(tmp_path):
    model = make_model(up_axis="Y")
    frames = make_frames().head(1)
    path = write_usd(tmp_path / "one.usda", frames, model).path
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetStartTimeCode() == stage.GetEndTimeCode() == FIRST
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    np.testing.assert_allclose(np.array(pi.GetPositionsAttr().Get(FIRST)), frames.x[0], rtol=1e-6)
    assert validation_issues(path)[0] == []


def test_colliders_geometry(tmp_path):
    model, frames = make_model(), make_frames()
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "s.usda", frames, model).path))
    # Ground plane quad: on z = 0, facing +z, covering every body position.
    pts = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/Colliders/plane_0")).GetPointsAttr().Get())
    assert np.allclose(pts[:, 2], 0.0)
    e1, e2 = pts[1] - pts[0], pts[2] - pts[0]
    n = np.cross(e1, e2)
    assert n[2] > 0
    xy = frames.x.reshape(-1, 3)[:, :2]
    assert np.all(xy >= pts[:, :2].min(0)) and np.all(xy <= pts[:, :2].max(0))
    assert pts[:, 0].max() - pts[:, 0].min() >= 2.0           # at least 1 m half size
    # Wall plane at x = 2 facing -x.
    pts = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/Colliders/plane_1")).GetPointsAttr().Get())
    assert np.allclose(pts[:, 0], 2.0)
    assert np.cross(pts[1] - pts[0], pts[2] - pts[0])[0] < 0
    # Open box: floor + 4 walls, 6 quads each, outside [lo, hi], rim at hi_z.
    box = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Colliders/box_0"))
    assert len(box.GetFaceVertexCountsAttr().Get()) == 5 * 6
    bp = np.array(box.GetPointsAttr().Get())
    np.testing.assert_allclose(bp.min(0), [-1.02, -1.02, -0.02], atol=1e-6)
    np.testing.assert_allclose(bp.max(0), [1.02, 1.02, 1.0], atol=1e-6)
    # Static mesh as it is, in world coordinates.
    ramp = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Colliders/ramp_1"))
    np.testing.assert_allclose(np.array(ramp.GetPointsAttr().Get()), model.static_meshes[0].vertices, atol=1e-6)


@pytest.mark.parametrize("layout", ["instancer", "xforms"])
def test_meters_per_unit_scales_lengths(tmp_path, layout):
    model, frames = make_model(meters_per_unit=0.01), make_frames()
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "cm.usdc", frames, model, layout=layout).path))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    read = instancer_vertices if layout == "instancer" else xforms_vertices
    for f in (0, N_FRAMES - 1):
        got = read(stage, model, frames, f)
        for b in range(model.n_bodies):
            tol = 100 * (HALF_ROT_TOL * _radius(model, b) + 1e-6)
            np.testing.assert_allclose(got[b], expected_vertices(model, frames, f, b, scale=100.0), atol=tol)
    if layout == "instancer":
        pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
        t = Usd.TimeCode(FIRST + 3.0)
        np.testing.assert_allclose(np.array(pi.GetPositionsAttr().Get(t)), 100 * frames.x[3], rtol=1e-6)
        np.testing.assert_allclose(np.array(pi.GetVelocitiesAttr().Get(t)), 100 * frames.v[3], rtol=1e-6)
        np.testing.assert_allclose(np.array(pi.GetAngularVelocitiesAttr().Get(t)),
                                   np.degrees(frames.w[3]), rtol=1e-6)
    box = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/Colliders/box_0")).GetPointsAttr().Get())
    np.testing.assert_allclose(box.max(0), [102.0, 102.0, 100.0], rtol=1e-6)


# -------------------------------------------------------------------- sparse


def test_sparse_xforms(tmp_path):
    model, frames = make_model(), make_frames()
    path = write_usd(tmp_path / "s.usda", frames, model, layout="xforms").path
    dense = write_usd(tmp_path / "d.usda", frames, model, layout="xforms", sparse=False).path
    stage, dstage = Usd.Stage.Open(str(path)), Usd.Stage.Open(str(dense))

    def ops(st, b):
        prim = st.GetPrimAtPath(body_prim_path(model, b))
        return prim.GetAttribute("xformOp:translate"), prim.GetAttribute("xformOp:orient")

    # Body at rest: a default value and no time samples.
    for attr in ops(stage, REST):
        assert attr.HasAuthoredValue() and attr.GetNumTimeSamples() == 0
    # Body that stops at STOP: frames STOP..end are one run -> keeps its first and last.
    for attr in ops(stage, STOPPER):
        assert attr.GetTimeSamples() == [float(FIRST + i) for i in range(STOP + 1)] + [FIRST + N_FRAMES - 1.0]
    # Moving bodies keep every frame; the dense file has every frame for everyone.
    for attr in ops(stage, 0):
        assert attr.GetNumTimeSamples() == N_FRAMES
    for b in range(model.n_bodies):
        for attr in ops(dstage, b):
            assert attr.GetNumTimeSamples() == N_FRAMES
    # Same transforms at every frame. Between two equal samples the translate
    # lerp is exact; the quatf slerp of two equal quaternions is not bit-exact
    # (it renormalizes in float), so allow float32 rounding (~1e-7 here).
    for f in range(N_FRAMES):
        a, b_ = xforms_vertices(stage, model, frames, f), xforms_vertices(dstage, model, frames, f)
        for b in range(model.n_bodies):
            np.testing.assert_allclose(a[b], b_[b], rtol=0, atol=2e-7)
            np.testing.assert_allclose(a[b], expected_vertices(model, frames, f, b), atol=1e-6)
    assert os.path.getsize(path) < os.path.getsize(dense)


def test_sparse_instancer_collapses_identical_tail(tmp_path):
    """Everything stops after frame STOP: positions keep frames 0..STOP and the last."""
    model = make_model()
    frames = make_frames(rest=range(7), stopper=None)             # nobody moves at all ...
    moving = make_frames(rest=(), stopper=None)
    tail = np.minimum(np.arange(N_FRAMES), STOP)                   # ... then: move, then stop
    frames = Frames(moving.frame_numbers, moving.times, moving.x[tail], moving.q[tail],
                    np.where((np.arange(N_FRAMES) < STOP)[:, None, None], moving.v, 0.0),
                    np.where((np.arange(N_FRAMES) < STOP)[:, None, None], moving.w, 0.0))
    info = write_usd(tmp_path / "s.usdc", frames, model)
    stage = Usd.Stage.Open(str(info.path))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    kept = [float(FIRST + i) for i in range(STOP + 1)] + [FIRST + N_FRAMES - 1.0]
    for attr in (pi.GetPositionsAttr(), pi.GetOrientationsAttr(), pi.GetExtentAttr()):
        assert attr.GetTimeSamples() == kept
    # Velocities are constant while moving and zero from STOP on (two runs), but
    # USD uses them only at the times positions are sampled: they keep those times.
    assert pi.GetVelocitiesAttr().GetTimeSamples() == kept
    assert pi.GetAngularVelocitiesAttr().GetTimeSamples() == kept
    for f in range(N_FRAMES):
        got = instancer_vertices(stage, model, frames, f)
        for b in range(model.n_bodies):
            np.testing.assert_allclose(got[b], expected_vertices(model, frames, f, b),
                                       atol=HALF_ROT_TOL * _radius(model, b) + 1e-6)
    assert validation_issues(info.path)[0] == []


def test_sparse_all_at_rest(tmp_path):
    model, frames = make_model(), make_frames(rest=range(7), stopper=None)
    info = write_usd(tmp_path / "rest.usda", frames, model)
    assert info.n_time_samples == 0
    stage = Usd.Stage.Open(str(info.path))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    assert pi.GetPositionsAttr().GetNumTimeSamples() == 0
    np.testing.assert_allclose(np.array(pi.GetPositionsAttr().Get(FIRST + 5.0)), frames.x[5], rtol=1e-6)
    info = write_usd(tmp_path / "rest_x.usda", frames, model, layout="xforms")
    assert info.n_time_samples == 0


# ------------------------------------------------------------- atomic write


def _leftovers(folder):
    return [p.name for p in folder.iterdir() if ".tmp-" in p.name]


def test_failed_write_leaves_target_untouched(tmp_path, monkeypatch):
    model, frames = make_model(), make_frames()
    target = tmp_path / "scene.usdc"
    target.write_bytes(b"previous bake")

    def broken_replace(src, dst):
        assert os.path.exists(src)           # the temp file was fully written ...
        raise OSError(28, "No space left on device (simulated)")

    monkeypatch.setattr(usd_export.os, "replace", broken_replace)
    with pytest.raises(ExportError) as exc:
        write_usd(target, frames, model)
    monkeypatch.undo()
    assert str(target) in str(exc.value) and "No space left" in str(exc.value)
    assert target.read_bytes() == b"previous bake"
    assert _leftovers(tmp_path) == []


def test_failure_while_authoring_leaves_nothing(tmp_path, monkeypatch):
    model, frames = make_model(), make_frames()
    target = tmp_path / "scene.usda"

    def boom(*args, **kwargs):
        raise RuntimeError("simulated")

    monkeypatch.setattr(usd_export, "author_colliders", boom)
    with pytest.raises(RuntimeError):
        write_usd(target, frames, model)
    assert list(tmp_path.iterdir()) == []


def test_unwritable_destination(tmp_path):
    model, frames = make_model(), make_frames()
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("x")
    with pytest.raises(ExportError) as exc:
        write_usd(not_a_dir / "scene.usdc", frames, model)
    assert "scene.usdc" in str(exc.value)
    if os.geteuid() != 0:                     # root ignores directory permissions
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            with pytest.raises(ExportError):
                write_usd(ro / "scene.usdc", frames, model)
            assert list(ro.iterdir()) == []
        finally:
            ro.chmod(0o700)


def test_creates_missing_folders(tmp_path):
    info = write_usd(tmp_path / "out" / "deep" / "scene.usd", make_frames(), make_model())
    assert info.path.is_file()


def test_bad_extension_layout_overwrite(tmp_path):
    model, frames = make_model(), make_frames()
    with pytest.raises(ExportError, match=r"'\.abc'"):
        write_usd(tmp_path / "scene.abc", frames, model)
    with pytest.raises(ExportError, match="layout"):
        write_usd(tmp_path / "scene.usda", frames, model, layout="points")
    target = tmp_path / "scene.usda"
    target.write_text("keep")
    with pytest.raises(ExportError, match="exists"):
        write_usd(target, frames, model, overwrite=False)
    assert target.read_text() == "keep"
    with pytest.raises(ExportError, match="frames.x"):
        write_usd(tmp_path / "x.usda", make_frames(n_bodies=5, stopper=None, rest=()), model)
    assert _leftovers(tmp_path) == []


def test_lazy_public_name():
    assert dempipe.write_usd is write_usd


def test_mid_size_bake_keeps_every_moving_frame(tmp_path):
    """2,000 bodies all moving over 50 frames, both layouts: every time-sampled
    attribute holds all 50 frames (nothing rests, so the sparse rule drops nothing),
    ExportInfo counts exactly what the file holds, and the instancer's positions read
    back within float32 rounding. Its write time is benchmarks/output_size.py's."""
    from processes import samples

    n_bodies, n_frames = 2000, 50
    model = make_model()
    model.n_bodies = n_bodies
    model.body_shape = np.arange(n_bodies) % 3
    model.body_group = np.arange(n_bodies) % 2
    model.body_group_index = np.arange(n_bodies) // 2
    frames = make_frames(n_bodies=n_bodies, n_frames=n_frames, rest=(), stopper=None)
    for layout in ("instancer", "xforms"):
        path = tmp_path / f"{layout}.usdc"
        info = write_usd(path, frames, model, layout=layout)
        got = samples(path)
        per_attr = {}
        for (prop, when) in got:
            if when != "default":
                per_attr[prop] = per_attr.get(prop, 0) + 1
        assert info.n_time_samples == sum(per_attr.values())
        assert per_attr and set(per_attr.values()) == {n_frames}, layout
        assert len(per_attr) >= (2 if layout == "instancer" else n_bodies), layout
    stage = Usd.Stage.Open(str(tmp_path / "instancer.usdc"))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    mid = n_frames // 2
    np.testing.assert_allclose(np.array(pi.GetPositionsAttr().Get(FIRST + mid)), frames.x[mid],
                               rtol=1e-6, atol=1e-7)


# ------------------------------------------------------------------ what a DCC shows


def _meshes(stage):
    """Every Mesh a DCC imports or draws: instance proxies included, abstract prototypes not."""
    return [p for p in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate))
            if p.GetTypeName() == "Mesh"]


@pytest.mark.parametrize("layout", ["instancer", "xforms"])
def test_every_mesh_has_a_bound_preview_surface_of_its_colour(tmp_path, layout):
    from pxr import UsdShade

    model, frames = make_model(), make_frames()
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "a.usda", frames, model, layout=layout).path))
    meshes = _meshes(stage)
    # 3 prototypes (instancer) or 7 bodies (xforms), plus 2 planes, a box and a static mesh
    assert len(meshes) == (3 if layout == "instancer" else 7) + 4
    colours = set()
    for prim in meshes:
        material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        assert material, f"{prim.GetPath()} has no bound material"
        shader = material.ComputeSurfaceSource()[0]
        assert shader and shader.GetIdAttr().Get() == "UsdPreviewSurface"
        diffuse = np.array(shader.GetInput("diffuseColor").Get())
        display = np.array(UsdGeom.Mesh(prim).GetDisplayColorAttr().Get()[0])
        np.testing.assert_allclose(diffuse, display, atol=1e-7)
        colours.add(tuple(np.round(diffuse, 4)))
    assert len(colours) == 4          # a colour per shape, one for the colliders


@pytest.mark.parametrize("layout", ["instancer", "xforms"])
def test_meshes_are_named_after_their_shapes(tmp_path, layout):
    model, frames = make_model(), make_frames()
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "a.usdc", frames, model, layout=layout).path))
    shape_names = {s.name for s in model.shapes}
    for prim in _meshes(stage):
        assert prim.GetName().lower() not in ("mesh", "geo", "geometry", "shape")
        if prim.GetPath().HasPrefix("/World/Bodies"):
            assert prim.GetName() in shape_names
    if layout == "xforms":     # the bodies keep their own names on their Xforms
        for b in range(model.n_bodies):
            prim = stage.GetPrimAtPath(body_prim_path(model, b))
            assert prim.GetChild(model.shapes[model.body_shape[b]].name).IsValid()


def test_normals_are_faceted_on_a_box_and_smooth_on_a_ball(tmp_path):
    model, frames = make_model(), make_frames()
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "a.usdc", frames, model).path))
    for name in ("brick", "ball"):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/Bodies/{name}"))
        assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.faceVarying
        normals = np.array(mesh.GetNormalsAttr().Get(), dtype=np.float64)
        pts = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
        idx = np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        assert normals.shape == (idx.size, 3)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
        tri = pts[idx]
        face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        face_n /= np.linalg.norm(face_n, axis=1, keepdims=True)
        corner_face_n = np.repeat(face_n, 3, axis=0)
        if name == "brick":    # every corner carries its own face's normal: flat shading
            np.testing.assert_allclose(normals, corner_face_n, atol=1e-6)
        else:                  # smooth: radial to 1.5 degrees (a subdivision-2 icosphere's
            # vertex normal is the mean of 5-6 faces ~ 8 degrees apart, all within the crease)
            radial = pts[idx.reshape(-1)] / np.linalg.norm(pts[idx.reshape(-1)], axis=1, keepdims=True)
            assert np.degrees(np.arccos(np.clip((normals * radial).sum(1), -1, 1))).max() < 1.5
            assert not np.allclose(normals, corner_face_n, atol=1e-3)
        # outward: the normals point away from the body's centre of mass
        assert ((normals * pts[idx.reshape(-1)]).sum(1) > 0).all()


def test_corner_normals_crease_at_the_angle():
    from dempipe.usd.meshes import corner_normals

    # Two triangles folded along the x axis by 20 degrees: one smooth normal at the shared
    # edge; folded by 60 degrees: each keeps its own.
    def fold(deg):
        a = np.radians(deg)
        v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -np.cos(a), np.sin(a)]], float)
        return v, np.array([[0, 1, 2], [1, 0, 3]])
    for deg, smooth in ((20.0, True), (60.0, False)):
        v, f = fold(deg)
        n = corner_normals(v, f)
        shared0, shared1 = n[0], n[4]     # vertex 0 in face 0 and in face 1
        assert np.allclose(shared0, shared1) == smooth
