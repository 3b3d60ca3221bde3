"""UsdPhysics stages at the door: every attribute a stage gives is checked as it is
read (one SceneError line naming the prim and attribute), bodies nested under
bodies and bodies on instanceable prims are bodies, and the overlay's velocities
are sampled where its positions are.

Stages are authored with pxr alone; overlays are written from known Frames (no
simulation, no kernel compiled).
"""

import math
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics  # noqa: E402

from dempipe.errors import SceneError  # noqa: E402
from dempipe.scene.data import SimulationSettings  # noqa: E402
from dempipe.scene.usd_stage import captured_stderr  # noqa: E402
from dempipe.scene.usd_reader import load_usd_scene  # noqa: E402
from dempipe.sim.frames import Frames  # noqa: E402
from test_usd_reader import body, ground, new_stage  # noqa: E402


def base(path, **kw):
    st = new_stage(path, **kw)
    ground(st)
    s = UsdGeom.Sphere.Define(st, "/World/Ball")
    s.CreateRadiusAttr(0.05)
    s.AddTranslateOp().Set(Gf.Vec3d(0, 0, 0.2))
    body(s.GetPrim())
    return st


def _instancer(st, indices, positions):
    pi = UsdGeom.PointInstancer.Define(st, "/World/Inst")
    pr = UsdGeom.Sphere.Define(st, "/World/Inst/Protos/S")
    pr.CreateRadiusAttr(0.05)
    body(pr.GetPrim())
    pi.CreatePrototypesRel().SetTargets([pr.GetPath()])
    pi.CreateProtoIndicesAttr(indices)
    pi.CreatePositionsAttr(positions)
    return pi


def _sub(st):
    st.GetRootLayer().subLayerPaths.append("missing.usda")


BAD = {
    "metersPerUnit negative": (dict(mpu=-1.0), None, "metersPerUnit"),
    "metersPerUnit zero": (dict(mpu=0.0), None, "metersPerUnit"),
    "metersPerUnit nan": (dict(mpu=float("nan")), None, "metersPerUnit"),
    "metersPerUnit huge": (dict(mpu=1e300), None, "metersPerUnit"),
    "timeCodesPerSecond zero": (dict(tcps=0), None, "timeCodesPerSecond"),
    "timeCodesPerSecond fraction": (dict(tcps=23.976), None, "timeCodesPerSecond"),
    "endTimeCode huge": (dict(end=1e300), None, "endTimeCode"),
    "kilogramsPerUnit zero": ({}, lambda st: UsdPhysics.SetStageKilogramsPerUnit(st, 0.0),
                              "kilogramsPerUnit"),
    "cube size zero": ({}, lambda st: _body_cube(st, 0.0), "size"),
    "cube size nan": ({}, lambda st: _body_cube(st, float("nan")), "size"),
    "cube size 1e300": ({}, lambda st: _body_cube(st, 1e300), "size"),
    "sphere radius negative": ({}, lambda st: UsdGeom.Sphere(st.GetPrimAtPath("/World/Ball"))
                               .GetRadiusAttr().Set(-0.05), "radius"),
    "velocity nan": ({}, lambda st: UsdPhysics.RigidBodyAPI(st.GetPrimAtPath("/World/Ball"))
                     .CreateVelocityAttr(Gf.Vec3f(math.nan, 0, 0)), "physics:velocity"),
    "angular velocity inf": ({}, lambda st: UsdPhysics.RigidBodyAPI(
        st.GetPrimAtPath("/World/Ball")).CreateAngularVelocityAttr(Gf.Vec3f(0, math.inf, 0)),
        "physics:angularVelocity"),
    "translate 1e300": ({}, lambda st: UsdGeom.Xformable(st.GetPrimAtPath("/World/Ball"))
                        .GetOrderedXformOps()[0].Set(Gf.Vec3d(1e300, 0, 0)), "transform"),
    "protoIndices out of range": ({}, lambda st: _instancer(st, [0, 3], [(0, 1, 0.2)] * 2),
                                  "protoIndices"),
    "protoIndices negative": ({}, lambda st: _instancer(st, [-1], [(0, 1, 0.2)]),
                              "protoIndices"),
    "positions too few": ({}, lambda st: _instancer(st, [0, 0], [(0, 1, 0.2)]), "positions"),
    "positions nan": ({}, lambda st: _instancer(st, [0], [(math.nan, 1, 0.2)]), "positions"),
    "missing sublayer": ({}, _sub, "missing.usda"),
}


def _body_cube(st, size):
    c = UsdGeom.Cube.Define(st, "/World/C")
    c.CreateSizeAttr(size)
    c.AddTranslateOp().Set(Gf.Vec3d(0.5, 0, 0.3))
    body(c.GetPrim())


@pytest.mark.parametrize("case", list(BAD))
def test_bad_stage_values_are_one_scene_error(tmp_path, case):
    kw, change, key = BAD[case]
    path = tmp_path / "s.usda"
    st = base(path, **kw)
    if change is not None:
        change(st)
    st.GetRootLayer().Save()
    said = []
    with captured_stderr(said), pytest.raises(SceneError) as err:
        load_usd_scene(path)
    msg = str(err.value)
    assert key in msg and "s.usda" in msg and "\n" not in msg, msg
    assert "pxrInternal" not in msg and said == [], (msg, said)


def test_files_that_are_not_usd_are_one_line_through_the_cli(tmp_path):
    # The real command, for the kinds whose text pxr writes itself: no C++ warning
    # on stderr, one line, exit 2.
    (tmp_path / "text.usda").write_text("hello world\n")
    (tmp_path / "bin.usd").write_bytes(b"\x00\x01garbage" * 10)
    st = base(tmp_path / "sub.usda")
    _sub(st)
    st.GetRootLayer().Save()
    st = base(tmp_path / "mpu.usda", mpu=-1.0)
    st.GetRootLayer().Save()
    for name in ("text.usda", "bin.usd", "sub.usda", "mpu.usda"):
        r = subprocess.run([sys.executable, "-m", "dempipe_cli.main", "check", name],
                           cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert r.returncode == 2, (name, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: {name}"), (name, r.stderr)
        assert "pxrInternal" not in r.stderr and "Warning" not in r.stderr, r.stderr


def _np4(m):
    return np.array(m, dtype=np.float64).reshape(4, 4)


def _known_frames(model, n_frames=3, still=()):
    """Frames that move and turn each body by known amounts (those in ``still`` stay)."""
    from dempipe.sim.model import quat_to_matrix  # noqa: F401  (the convention used below)

    n = model.n_bodies
    x = np.repeat(np.asarray(model.initial_x)[None, :n], n_frames, axis=0)
    q = np.repeat(np.asarray(model.initial_q)[None, :n], n_frames, axis=0)
    v = np.zeros((n_frames, n, 3))
    turn = np.array([math.cos(0.3), 0.2, -0.4, 0.7])
    turn /= np.linalg.norm(turn)
    for f in range(1, n_frames):
        for k in range(n):
            if k in still:
                v[f, k] = 1e-11          # the solver's noise of a body at rest
                continue
            x[f, k] += [0.01 * f * (k + 1), -0.02, 0.03 * f]
            v[f, k] = [0.24 * (k + 1), 0.0, 0.72]
            w1, v1 = turn[0], turn[1:]
            w2, v2 = q[f - 1, k, 0], q[f - 1, k, 1:]
            q[f, k] = [w1 * w2 - v1 @ v2, *(w1 * v2 + w2 * v1 + np.cross(v1, v2))]
    return Frames(np.arange(n_frames), np.arange(n_frames) / 24.0, x, q, v, np.zeros_like(v))


def _assert_composed(stage_path, out, scene, model, frames, prims):
    from dempipe.sim.model import quat_to_matrix

    stage = Usd.Stage.Open(str(out))
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                       dtype=float) * 0.02
    for f in range(len(frames.times)):
        cache = UsdGeom.XformCache(Usd.TimeCode(f))
        for k, b in enumerate(scene.usd.bodies):
            if b.prim not in prims:
                continue
            W = _np4(cache.GetLocalToWorldTransform(stage.GetPrimAtPath(b.prim)))
            got = (np.c_[corners, np.ones(8)] @ W)[:, :3]
            S = np.asarray(b.stretch)
            com = np.asarray(model.shapes[model.body_shape[k]].com)
            want = (corners @ S - com) @ quat_to_matrix(frames.q[f, k]).T + frames.x[f, k]
            assert got == pytest.approx(want, abs=1e-6), (f, b.prim)


def test_nested_body_is_a_body_of_its_own_and_composes(tmp_path):
    # docs/usd-input.md: a body below a body is a body of its own; its overlay pose is
    # authored under its parent body's simulated pose, so it composes to its own.
    from dempipe.scene.build import build_model
    from dempipe.usd.overlay import write_overlay

    path = tmp_path / "n.usda"
    st = new_stage(path, end=2)
    ground(st)
    a = UsdGeom.Cube.Define(st, "/World/A")
    a.CreateSizeAttr(0.04)
    a.AddTranslateOp().Set(Gf.Vec3d(0, 0, 0.2))
    a.AddRotateZOp().Set(20.0)
    body(a.GetPrim())
    b = UsdGeom.Cube.Define(st, "/World/A/B")
    b.CreateSizeAttr(0.04)
    b.AddTranslateOp().Set(Gf.Vec3d(0.3, 0, 0))
    body(b.GetPrim())
    st.GetRootLayer().Save()
    scene = load_usd_scene(path, SimulationSettings(resolution=2))
    assert sorted(u.prim for u in scene.usd.bodies) == ["/World/A", "/World/A/B"]
    assert not any("A/B" in c.name for c in scene.colliders)   # not a static collider too
    model = build_model(scene)
    frames = _known_frames(model)
    out = tmp_path / "n_baked.usda"
    write_overlay(out, frames, model, scene.usd)
    _assert_composed(path, out, scene, model, frames, {"/World/A", "/World/A/B"})


def test_body_on_an_instanceable_prim_is_read_and_composes(tmp_path):
    # RigidBodyAPI on the instance, CollisionAPI in the prototype (what exporters write
    # for repeated props): each instance is a body; its overlay is on the instance prim.
    from dempipe.scene.build import build_model
    from dempipe.usd.overlay import write_overlay

    path = tmp_path / "i.usda"
    st = new_stage(path, end=2)
    ground(st)
    cls = st.CreateClassPrim("/Protos")
    UsdGeom.Xform.Define(st, "/Protos/P")
    geo = UsdGeom.Cube.Define(st, "/Protos/P/Geo")
    geo.CreateSizeAttr(0.04)
    UsdPhysics.CollisionAPI.Apply(geo.GetPrim())
    for i in range(2):
        x = UsdGeom.Xform.Define(st, f"/World/I{i}")
        x.GetPrim().GetInherits().AddInherit("/Protos/P")
        x.GetPrim().SetInstanceable(True)
        x.AddTranslateOp().Set(Gf.Vec3d(0.2 * i, 0, 0.2))
        UsdPhysics.RigidBodyAPI.Apply(x.GetPrim())
    assert cls
    st.GetRootLayer().Save()
    scene = load_usd_scene(path, SimulationSettings(resolution=2))
    assert sorted(u.prim for u in scene.usd.bodies) == ["/World/I0", "/World/I1"]
    model = build_model(scene)
    frames = _known_frames(model)
    out = tmp_path / "i_baked.usda"
    write_overlay(out, frames, model, scene.usd)
    _assert_composed(path, out, scene, model, frames, {"/World/I0", "/World/I1"})


def test_overlay_velocities_are_aligned_with_positions_and_still_is_zero(tmp_path):
    # An instancer of three bodies, one at rest with the solver's 1e-11 noise, and a
    # body prim at rest: velocities are sampled at the positions' times (pxr reads the
    # instancer without its "not aligned" warning) and a still body's are exactly 0.
    from dempipe.scene.build import build_model
    from dempipe.usd.overlay import write_overlay

    path = tmp_path / "v.usda"
    st = base(path, end=5)
    _instancer(st, [0, 0, 0], [(0, 0.3, 0.2), (0.2, 0.3, 0.2), (0.4, 0.3, 0.2)])
    st.GetRootLayer().Save()
    scene = load_usd_scene(path, SimulationSettings(resolution=2))
    model = build_model(scene)
    ball = next(k for k, b in enumerate(scene.usd.bodies) if b.prim == "/World/Ball")
    still_inst = next(k for k, b in enumerate(scene.usd.bodies) if b.instance == 1)
    frames = _known_frames(model, n_frames=6, still={ball, still_inst})
    out = tmp_path / "v_baked.usda"
    write_overlay(out, frames, model, scene.usd)
    layer = Sdf.Layer.FindOrOpen(str(out))
    for a, b in (("positions", "velocities"), ("orientations", "angularVelocities")):
        ta = layer.ListTimeSamplesForPath(f"/World/Inst.{a}")
        assert ta == layer.ListTimeSamplesForPath(f"/World/Inst.{b}"), (a, b)
    for t in layer.ListTimeSamplesForPath("/World/Inst.velocities"):
        vel = np.array(layer.QueryTimeSample("/World/Inst.velocities", t))
        assert (vel[1] == 0).all() and (t == 0 or (vel[0] != 0).any())
    ball_v = layer.GetAttributeAtPath("/World/Ball.physics:velocity")
    assert layer.ListTimeSamplesForPath(ball_v.path) == [] and ball_v.default == Gf.Vec3f(0)
    said = []
    with captured_stderr(said):
        stage = Usd.Stage.Open(str(out))
        pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Inst"))
        for t in range(6):
            pi.ComputeInstanceTransformsAtTime(Usd.TimeCode(t + 0.5), Usd.TimeCode(0))
    assert said == []


def test_output_that_is_the_stage_a_settings_file_names_is_refused_before_work(tmp_path):
    from dempipe.errors import ExportError
    from dempipe.pipeline.bake import bake

    st = base(tmp_path / "shot.usda")
    st.GetRootLayer().Save()
    (tmp_path / "shot.toml").write_text('[usd]\nstage = "shot.usda"\n')
    before = (tmp_path / "shot.usda").read_bytes()
    t0 = __import__("time").monotonic()
    with pytest.raises(ExportError, match="is the input stage"):
        bake(tmp_path / "shot.toml", tmp_path / "shot.usda", device="cpu")
    assert __import__("time").monotonic() - t0 < 30
    assert (tmp_path / "shot.usda").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shot.toml", "shot.usda"]
