"""A TOML scene written as a UsdPhysics stage (`dempipe scene export`).

So a TOML user can move a scene to a DCC and back: reading the written stage with
:func:`dempipe.scene.usd_reader.load_usd_scene` gives the same bodies (mesh-origin
positions, orientations, velocities, masses), materials (restitution, friction,
density, glue), fracture and glue (dempipe's own ``dempipe:`` attributes), gravity,
timing and plane and mesh colliders.

Layout: ``/World/PhysicsScene``; ``/World/Looks/<material>`` (PhysicsMaterialAPI);
``/World/Bodies/<group>/<group>_<i>``: one Mesh per body with translate and orient
ops, RigidBodyAPI, CollisionAPI and its material bound for physics;
``/World/Colliders/<name>``: a Plane gprim per plane, a Mesh per mesh collider, and
per box collider one thin Cube per wall (a DCC sees the container; read back, the
walls are static box meshes, not dempipe's bounded walls). What UsdPhysics cannot
hold: a material's numeric stiffness, dempipe's simulation settings (sphere size,
dt, sleeping), which a settings TOML gives (docs/usd-input.md). Written atomically.

Prescribed motion: a kinematic group's bodies get
``physics:kinematicEnabled`` and time-sampled translate and orient ops (linear keys
at their key times, exactly; smooth keys and rates at every frame and at the key
times), which dempipe reads back as the same keys. A moving mesh or box collider
becomes a kinematic body with its motion as time-sampled ops over its world-space
geometry (UsdPhysics' way to animate a collider). A moving plane and a group's
``start_time`` have no UsdPhysics form: a warning says so and the stage holds the
plane still and the group from the start.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdShade, Vt

from dempipe.errors import ExportError
from dempipe.scene.build import collider_mesh, shape_mesh
from dempipe.scene.placement import collider_frame, expand_bodies, group_frame
from dempipe.sim.motion import carry, reference_anchor
from dempipe.usd.animation import EXTENSIONS, save_atomically
from dempipe.usd.prescribed import collider_xforms

__all__ = ["write_physics_stage"]


def _quat_between(a, b) -> np.ndarray:
    """Unit quaternion (w, x, y, z) turning unit vector a onto unit vector b."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = float(a @ b)
    if c < -1 + 1e-12:                       # opposite: half a turn about any normal
        axis = np.cross(a, [1.0, 0, 0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return np.array([0.0, *axis])
    q = np.array([1.0 + c, *np.cross(a, b)])
    return q / np.linalg.norm(q)


def _orient(xf, q):
    xf.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(
        Gf.Quatd(float(q[0]), Gf.Vec3d(*[float(v) for v in q[1:]])))


def _mesh(stage, path, vertices, faces, mpu):
    m = UsdGeom.Mesh.Define(stage, path)
    pts = np.asarray(vertices, dtype=np.float64) / mpu
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
    m.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray(np.asarray(faces, dtype=np.int64).ravel().tolist()))
    m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    m.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo), Gf.Vec3f(*hi)]))
    return m


def _motion_times(motion, out) -> np.ndarray:
    """Times [s] to sample a motion at: a linear one's key times (USD's linear
    interpolation between them is the motion); otherwise every frame and the key
    times."""
    keys = np.array([k.time for k in motion.keys], dtype=np.float64)
    if motion.keyed and motion.interpolation == "linear":
        return keys
    return np.union1d(np.arange(out.n_frames) / float(out.fps), keys)


def _animate(xf, translate, orient, times, out, mpu):
    """Time-sampled double translate and orient ops on the Xformable ``xf``:
    ``translate`` (F, 3) [m], ``orient`` (F, 4) (w, x, y, z) at ``times`` (F,) [s]."""
    t_op = xf.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
    o_op = xf.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
    for t, x, q in zip(times, translate, orient):
        code = Usd.TimeCode(out.start_frame + float(t) * out.fps)
        t_op.Set(Gf.Vec3d(*(np.asarray(x, float) / mpu)), code)
        o_op.Set(Gf.Quatd(float(q[0]), Gf.Vec3d(*[float(v) for v in q[1:]])), code)


def _kinematic(prim):
    UsdPhysics.RigidBodyAPI.Apply(prim).CreateKinematicEnabledAttr(True)


def write_physics_stage(scene, path) -> Path:
    """Write the TOML ``scene`` (a dempipe.scene.toml_reader.Scene) as a UsdPhysics stage at ``path``."""
    path = Path(path)
    if path.suffix.lower() not in EXTENSIONS:
        raise ExportError(f"{path}: unsupported extension {path.suffix!r} "
                          f"(use one of {', '.join(EXTENSIONS)})")
    if scene.usd is not None:
        raise ExportError(f"{path}: the scene already comes from a USD stage "
                          f"({scene.usd.stage_path.name})")
    out = scene.output
    mpu = float(out.meters_per_unit)
    layer = Sdf.Layer.CreateAnonymous("scene" + path.suffix.lower())
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageUpAxis(stage, out.up_axis)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(out.fps)
    stage.SetFramesPerSecond(out.fps)
    stage.SetStartTimeCode(out.start_frame)
    stage.SetEndTimeCode(out.start_frame + out.n_frames - 1)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())

    ps = UsdPhysics.Scene.Define(stage, "/World/PhysicsScene")
    g = np.asarray(scene.simulation.gravity, dtype=np.float64)
    gm = float(np.linalg.norm(g))
    if gm > 0:
        ps.CreateGravityDirectionAttr(Gf.Vec3f(*(g / gm)))
    ps.CreateGravityMagnitudeAttr(gm / mpu)

    mats = {}
    for name, spec in scene.materials.items():
        mat = UsdShade.Material.Define(stage, f"/World/Looks/{name}")
        api = UsdPhysics.MaterialAPI.Apply(mat.GetPrim())
        api.CreateRestitutionAttr(float(spec.restitution))
        api.CreateDynamicFrictionAttr(float(spec.friction))
        api.CreateStaticFrictionAttr(float(spec.friction))
        api.CreateDensityAttr(float(spec.density) * mpu ** 3)       # kg per unit³
        if spec.glue_strength is not None:      # dempipe's own attributes, in SI
            glue = {"dempipe:glueStrength": spec.glue_strength,
                    "dempipe:glueDamping": spec.glue_damping}
            if spec.glue_stiffness != "auto":
                glue["dempipe:glueStiffness"] = spec.glue_stiffness
            for key, value in glue.items():
                mat.GetPrim().CreateAttribute(key, Sdf.ValueTypeNames.Double).Set(float(value))
        if spec.stiffness != "auto":
            warnings.warn(f"materials.{name}.stiffness = {spec.stiffness:g} N/m has no "
                          "UsdPhysics attribute; the stage leaves it to 'auto'", stacklevel=2)
        mats[name] = mat

    def bind(prim, material):
        UsdShade.MaterialBindingAPI.Apply(prim).Bind(
            mats[material], UsdShade.Tokens.weakerThanDescendants, "physics")

    meshes = {n: shape_mesh(s, n) for n, s in scene.shapes.items()
              if any(n == gr.shape or (not isinstance(gr.shape, str) and n in gr.shape)
                     for gr in scene.bodies)}
    UsdGeom.Scope.Define(stage, "/World/Bodies")
    for group, placement in zip(scene.bodies, expand_bodies(scene)):
        UsdGeom.Xform.Define(stage, f"/World/Bodies/{group.name}")
        if group.start_time > 0 or group.layout == "emit":
            warnings.warn(f"bodies {group.name!r}: start_time = {group.start_time:g} s has no "
                          "UsdPhysics attribute; the stage has the group from the start",
                          stacklevel=2)
        motion = ref = None
        if group.kinematic:
            owner, rot = group_frame(group, placement)
            motion = group.motion.with_pivot(owner)
            ref = reference_anchor(motion, owner, rot, group=group.layout != "single")
            times = _motion_times(motion, out)
        for i, shape in enumerate(placement.body_shapes()):
            mesh = meshes[shape]
            m = _mesh(stage, f"/World/Bodies/{group.name}/{group.name}_{i}", mesh.vertices,
                      mesh.faces, mpu)
            prim = m.GetPrim()
            UsdPhysics.CollisionAPI.Apply(prim)
            rb = UsdPhysics.RigidBodyAPI.Apply(prim)
            if motion is not None:
                poses = [carry(motion, ref, placement.positions[i], placement.rotations[i], t)
                         for t in times]
                _animate(m, [p[0] for p in poses], [p[1] for p in poses], times, out, mpu)
                rb.CreateKinematicEnabledAttr(True)
            else:
                m.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(
                    Gf.Vec3d(*(placement.positions[i] / mpu)))
                _orient(m, placement.rotations[i])
                rb.CreateVelocityAttr(Gf.Vec3f(*(placement.velocities[i] / mpu)))
                rb.CreateAngularVelocityAttr(
                    Gf.Vec3f(*np.degrees(placement.angular_velocities[i])))
            bind(prim, placement.material)
            _fracture(prim, scene.shapes[shape].fracture, group.glue, mpu)

    UsdGeom.Scope.Define(stage, "/World/Colliders")
    for c in scene.colliders:
        kind = type(c).__name__
        p = f"/World/Colliders/{c.name}"
        if kind == "PlaneCollider":
            plane = UsdGeom.Plane.Define(stage, p)
            plane.CreateAxisAttr("Z")
            plane.CreateWidthAttr(20.0 / mpu)          # what a DCC draws; the plane is infinite
            plane.CreateLengthAttr(20.0 / mpu)
            plane.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(
                Gf.Vec3d(*(np.asarray(c.point) / mpu)))
            _orient(plane, _quat_between([0, 0, 1.0], c.normal))
            prims = [plane.GetPrim()]
            if c.motion is not None:
                warnings.warn(f"colliders {c.name!r}: a moving plane has no UsdPhysics form; "
                              "the stage holds it still", stacklevel=2)
        elif kind == "BoxCollider":
            box = UsdGeom.Xform.Define(stage, p)
            if c.motion is not None:
                _moving_collider(box, c.motion, *collider_frame(c), out, mpu)
            lo, hi = np.asarray(c.min, float), np.asarray(c.max, float)
            t = c.thickness or 0.02 * float(np.max(hi - lo))
            prims = []
            for axis in range(3):
                for side, sign in (("lo", -1), ("hi", 1)):
                    if axis == out.up_index and sign > 0 and c.open_top:
                        continue
                    centre = 0.5 * (lo + hi)
                    size = (hi - lo) + 2 * t
                    centre[axis] = (lo[axis] - t / 2) if sign < 0 else (hi[axis] + t / 2)
                    size[axis] = t
                    wall = UsdGeom.Cube.Define(stage, f"{p}/wall_{'xyz'[axis]}_{side}")
                    wall.CreateSizeAttr(1.0)
                    wall.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(
                        Gf.Vec3d(*(centre / mpu)))
                    wall.AddScaleOp().Set(Gf.Vec3f(*(size / mpu)))
                    prims.append(wall.GetPrim())
        else:
            mesh = collider_mesh(c, p)
            m = _mesh(stage, p, mesh.vertices, mesh.faces, mpu)
            prims = [m.GetPrim()]
            if c.motion is not None:
                _moving_collider(m, c.motion, *collider_frame(c), out, mpu)
        for prim in prims:
            UsdPhysics.CollisionAPI.Apply(prim)
            bind(prim, c.material)
    save_atomically(layer, path)
    return path


def _fracture(prim, spec, glue: bool, mpu: float) -> None:
    """A fractured shape's FractureSpec and its group's glue as the body prim's
    ``dempipe:`` attributes (scene/usd_attributes.py); the prim's local space is the
    shape's own coordinates in stage units."""
    if spec is None:
        return
    T = Sdf.ValueTypeNames
    prim.CreateAttribute("dempipe:fracture:pieces", T.Int).Set(int(spec.pieces))
    prim.CreateAttribute("dempipe:fracture:seed", T.Int).Set(int(spec.seed))
    if spec.impact is not None:
        prim.CreateAttribute("dempipe:fracture:impact", T.Point3d).Set(
            Gf.Vec3d(*(np.asarray(spec.impact, float) / mpu)))
        prim.CreateAttribute("dempipe:fracture:impactShare", T.Double).Set(
            float(spec.impact_share))
        if spec.impact_radius is not None:
            prim.CreateAttribute("dempipe:fracture:impactRadius", T.Double).Set(
                float(spec.impact_radius) / mpu)
    if glue:
        prim.CreateAttribute("dempipe:glue", T.Bool).Set(True)


def _moving_collider(xf, motion, origin, rotation, out, mpu):
    """A moving mesh or box collider as a kinematic body: its geometry stays in world
    coordinates and its ops carry it by D(t) (usd/prescribed.py)."""
    motion = motion.with_pivot(origin)
    ref = reference_anchor(motion, origin, rotation)
    times = _motion_times(motion, out)
    tr, ori = collider_xforms(motion, ref, origin, rotation, times)
    _animate(xf, tr, ori, times, out, mpu)
    _kinematic(xf.GetPrim())
