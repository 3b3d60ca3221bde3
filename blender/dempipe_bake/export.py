"""Blender's rigid-body world written as a dempipe TOML scene with OBJ mesh files.

Why TOML and meshes rather than a UsdPhysics stage: the stage reader has no form
for an emitted body's start time (UsdPhysics has none), and the TOML scene has
every piece a Blender rigid-body world needs (dynamic bodies from mesh files,
static and keyframed mesh colliders, planes, materials, gravity, timing, start
times). It needs nothing but Python inside Blender to write, not pxr.

Units: Blender units are taken as metres (``unit_settings.scale_length`` other
than 1 is reported); quaternions are (w, x, y, z) in Blender and in dempipe.
Every object maps to one prim name (the object name made a valid identifier,
unique), kept in the bake folder's ``map.json``; what cannot be represented is
listed in the report, never dropped silently.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import bmesh
from mathutils import Matrix, Vector

#: A passive mesh this flat (thickness / size) is an infinite plane.
FLAT = 1e-6
#: A world matrix whose rotation-times-scale part differs from a pure R S by more
#: than this (relative) has shear, which a rigid body cannot keep.
SHEAR_TOL = 1e-5
#: Custom properties the user may set on an object (Blender has no such settings).
PROP_VELOCITY = "dempipe_velocity"                  # [x, y, z] m/s, world frame
PROP_ANGULAR_VELOCITY = "dempipe_angular_velocity"  # [x, y, z] rad/s, world frame
PROP_START_FRAME = "dempipe_start_frame"            # frame the body enters the shot


@dataclass
class Export:
    """What :func:`write_scene` wrote.

    scene_path: the TOML scene; bodies: prim name -> object name of every dynamic
    body (the bake's xforms layout has it at ``/World/Bodies/<prim>/<prim>_0``);
    start_frames: object name -> the frame it enters (emitted bodies only);
    report: lines naming what dempipe does not represent, or represents otherwise.
    """

    scene_path: Path
    bodies: dict = field(default_factory=dict)
    start_frames: dict = field(default_factory=dict)
    frame_start: int = 1
    frame_end: int = 250
    report: list = field(default_factory=list)


def valid_name(name: str, taken: set) -> str:
    """A USD prim name from a Blender name (``Cube.001`` -> ``Cube_001``), unique in
    ``taken`` (which it joins)."""
    base = re.sub(r"[^A-Za-z0-9_]", "_", name) or "_"
    if not re.match(r"[A-Za-z_]", base[0]):
        base = "_" + base
    out, k = base, 1
    while out in taken:
        out, k = f"{base}_{k}", k + 1
    taken.add(out)
    return out


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"not a finite number: {value}")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)         # a TOML basic string for these names and paths
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + " }"
    raise TypeError(type(value))


def _table(header: str, items: dict) -> str:
    return f"{header}\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in items.items()) + "\n"


def _vec(v) -> list:
    return [float(c) for c in v]


def decompose(m: Matrix, name: str, report: list):
    """World matrix -> (location, rotation quaternion (w, x, y, z), scale); shear
    (a parent's uneven scale under a rotation) is reported: the rigid body keeps
    the nearest rotation and its axis scales."""
    loc, rot, scale = m.decompose()
    rebuilt = Matrix.LocRotScale(loc, rot, scale)
    size = max(max(abs(s) for s in scale), 1e-12)
    err = max(abs(rebuilt[i][j] - m[i][j]) for i in range(3) for j in range(3)) / size
    if err > SHEAR_TOL:
        report.append(f"{name}: its world matrix shears (a parent scales unevenly under a "
                      f"rotation); dempipe keeps its rotation and axis scales only")
    return loc, rot, scale


def _mesh_arrays(ob, depsgraph, scale):
    """The evaluated mesh (modifiers applied) in the object's frame with its scale
    applied: vertices (n, 3) and triangles (m, 3), and its volume [m^3]."""
    ev = ob.evaluated_get(depsgraph)
    mesh = ev.to_mesh()
    try:
        bm = bmesh.new()
        bm.from_mesh(mesh)
        bm.transform(Matrix.Diagonal(Vector((*scale, 1.0))))
        if any(s < 0 for s in scale) and (scale[0] * scale[1] * scale[2]) < 0:
            bmesh.ops.reverse_faces(bm, faces=bm.faces)     # a mirror turns faces inside out
        bmesh.ops.triangulate(bm, faces=bm.faces)
        volume = abs(bm.calc_volume(signed=True))
        verts = [tuple(v.co) for v in bm.verts]
        bm.verts.index_update()
        tris = [tuple(v.index for v in f.verts) for f in bm.faces]
        bm.free()
    finally:
        ev.to_mesh_clear()
    return verts, tris, volume


def _write_obj(path: Path, verts, tris) -> None:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in verts]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in tris]
    path.write_text("\n".join(lines) + "\n")


def rigid_objects(scene):
    """The objects of the rigid-body world's collection that have a rigid body."""
    rbw = scene.rigidbody_world
    if rbw is None or rbw.collection is None:
        return []
    return [ob for ob in rbw.collection.all_objects if ob.rigid_body is not None]


def _sample(scene, objects, frames):
    """Per object: world matrices and hide_render at each frame (Blender evaluates
    animation, drivers and constraints on frame_set). Blender's own rigid-body
    solver is off meanwhile (it would move the active bodies and cost a
    simulation). Restores the current frame."""
    current = scene.frame_current, scene.frame_subframe
    rbw = scene.rigidbody_world
    enabled = rbw.enabled
    rbw.enabled = False
    mats = {ob.name: [] for ob in objects}
    hidden = {ob.name: [] for ob in objects}
    try:
        for f in frames:
            scene.frame_set(f)
            for ob in objects:
                mats[ob.name].append(ob.matrix_world.copy())
                hidden[ob.name].append(bool(ob.hide_render))
    finally:
        rbw.enabled = enabled
        scene.frame_set(current[0], subframe=current[1])
    return mats, hidden


def _animated_paths(ob) -> set:
    """The data paths the object's action keys (layered actions in Blender 4.4+,
    the action's own F-curves before)."""
    ad = ob.animation_data
    if ad is None or ad.action is None:
        return set()
    action = ad.action
    curves = []
    if hasattr(action, "layers") and len(action.layers):
        slot = getattr(ad, "action_slot", None)
        for layer in action.layers:
            for strip in layer.strips:
                bag = strip.channelbag(slot) if slot is not None else None
                curves += list(bag.fcurves) if bag is not None else []
    elif hasattr(action, "fcurves"):
        curves = list(action.fcurves)
    return {fc.data_path for fc in curves}


def _is_animated(ob) -> bool:
    ad = ob.animation_data
    return bool(ad and (ad.action or ad.drivers or ad.nla_tracks)) or bool(ob.constraints) \
        or (ob.parent is not None and _is_animated(ob.parent))


def _report_world(scene, rbw, objects, report):
    if rbw.constraints is not None and len(rbw.constraints.objects):
        report.append(f"rigid-body constraints are not simulated: "
                      f"{', '.join(sorted(o.name for o in rbw.constraints.objects))}")
    if abs(rbw.time_scale - 1.0) > 1e-9:
        report.append(f"rigid-body world speed {rbw.time_scale:g} is not used (dempipe runs at 1)")
    if abs(scene.unit_settings.scale_length - 1.0) > 1e-9:
        report.append(f"unit scale {scene.unit_settings.scale_length:g}: Blender units are "
                      f"taken as metres")
    report.append("substeps and solver iterations are not used: dempipe picks its own "
                  "time step from the stiffness and masses")
    layers = {tuple(ob.rigid_body.collision_collections) for ob in objects}
    if len(layers) > 1:
        report.append("collision collections are not used: every body collides with "
                      "every other")


def write_scene(scene, folder: Path, *, resolution: int = 8, target_overlap: float = 0.0,
                spheres: str = "lattice") -> Export:
    """Write ``scene``'s rigid-body world to ``folder/scene.toml`` and
    ``folder/meshes/*.obj``; returns an :class:`Export` (also saved as
    ``folder/map.json``). ``target_overlap`` (0: dempipe decides) and ``spheres``
    are dempipe's ``[simulation]`` keys ``stiffness_target_overlap`` and ``spheres``."""
    folder = Path(folder)
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    rbw = scene.rigidbody_world
    if rbw is None:
        raise ValueError("the scene has no rigid-body world (Scene properties > Rigid Body "
                         "World)")
    objects = rigid_objects(scene)
    if not objects:
        raise ValueError("the rigid-body world has no objects with a rigid body")
    report: list[str] = []
    _report_world(scene, rbw, objects, report)
    fps_f = scene.render.fps / scene.render.fps_base
    fps = int(round(fps_f))
    if abs(fps - fps_f) > 1e-9:
        report.append(f"frame rate {fps_f:g} is not whole: baked at {fps} fps")
    f0, f1 = int(rbw.point_cache.frame_start), int(rbw.point_cache.frame_end)
    if f1 <= f0:
        raise ValueError(f"the rigid-body cache's frame range {f0}-{f1} is empty")
    frames = list(range(f0, f1 + 1))
    gravity = _vec(scene.gravity) if scene.use_gravity else [0.0, 0.0, 0.0]

    depsgraph = bpy.context.evaluated_depsgraph_get()
    animated = [ob for ob in objects if _is_animated(ob)]
    scene.frame_set(f0)
    mats, hidden = _sample(scene, animated, frames) if animated else ({}, {})

    out = Export(scene_path=folder / "scene.toml", frame_start=f0, frame_end=f1, report=report)
    taken: set = {"default"}
    shapes, bodies, colliders, materials = [], [], [], {}
    mesh_keys: dict = {}
    replaced: dict = {}     # Blender collision shape -> objects whose mesh is used instead

    def material(friction, restitution, density):
        key = (round(friction, 9), round(restitution, 9), float(f"{density:.9g}"))
        if key not in materials:
            materials[key] = valid_name(f"mat_{len(materials)}", taken)
        return materials[key]

    def shape_for(ob, scale):
        mods = any(m.show_viewport for m in ob.modifiers)
        key = (ob.name if mods else ob.data.name, tuple(round(s, 9) for s in scale))
        if key not in mesh_keys:
            verts, tris, volume = _mesh_arrays(ob, depsgraph, scale)
            name = valid_name(f"{ob.name}_shape", taken)
            _write_obj(folder / "meshes" / f"{name}.obj", verts, tris)
            mesh_keys[key] = (name, verts, volume)
        return mesh_keys[key]

    for ob in sorted(objects, key=lambda o: o.name):
        rb = ob.rigid_body
        if ob.type != "MESH":
            report.append(f"{ob.name}: a {ob.type.lower()} object has no mesh: not simulated")
            continue
        if rb.collision_shape == "COMPOUND" or (ob.parent is not None and
                                                ob.parent.rigid_body is not None):
            report.append(f"{ob.name}: compound shapes (a rigid body parented to another) are "
                          f"not simulated as one body: baked as a body of its own")
        m0 = mats[ob.name][0] if ob.name in mats else ob.matrix_world.copy()
        loc, rot, scale = decompose(m0, ob.name, report)
        dynamic = rb.type == "ACTIVE" and rb.enabled and not rb.kinematic
        if rb.collision_shape not in ("MESH", "COMPOUND"):
            replaced.setdefault(rb.collision_shape.lower().replace("_", " "), []).append(ob.name)
        if dynamic:
            name, verts, volume = shape_for(ob, scale)
            if volume <= 0:
                report.append(f"{ob.name}: its mesh encloses no volume: not simulated")
                continue
            prim = valid_name(ob.name, taken)
            mat = material(rb.friction, rb.restitution, rb.mass / volume)
            body = dict(name=prim, shape=name, material=mat, position=_vec(loc),
                        rotation=_vec(rot))
            if PROP_VELOCITY in ob:
                body["velocity"] = _vec(ob[PROP_VELOCITY])
            if PROP_ANGULAR_VELOCITY in ob:
                body["angular_velocity"] = _vec(ob[PROP_ANGULAR_VELOCITY])
            start = None
            if PROP_START_FRAME in ob:
                start = int(ob[PROP_START_FRAME])
            elif ob.name in hidden and hidden[ob.name][0]:
                shown = [f for f, h in zip(frames, hidden[ob.name]) if not h]
                start = shown[0] if shown else None
                if start is None:
                    report.append(f"{ob.name}: hidden in renders over the whole range: "
                                  f"not simulated")
                    continue
            if start is not None and start > f0:
                body["start_time"] = (min(start, f1) - f0) / fps
                out.start_frames[ob.name] = min(start, f1)
            if _animated_paths(ob) & {"location", "rotation_euler", "rotation_quaternion",
                                      "rotation_axis_angle", "scale"}:
                report.append(f"{ob.name}: its animation is not followed (an active body "
                              f"starts where it is at frame {f0}); turn on Animated to "
                              f"make it kinematic")
            bodies.append(body)
            out.bodies[prim] = ob.name
            shapes.append(name)
            continue
        # Passive (or an active one that is Animated or not Dynamic): a collider.
        if not rb.enabled and rb.type == "ACTIVE":
            report.append(f"{ob.name}: not Dynamic: baked as a collider")
        cname = valid_name(ob.name, taken)
        mat = material(rb.friction, rb.restitution, 1000.0)
        verts, tris, _ = _mesh_arrays(ob, depsgraph, scale)
        keys = None
        if "rigid_body.kinematic" in _animated_paths(ob):
            report.append(f"{ob.name}: Animated is keyed: dempipe keeps it as it is at frame "
                          f"{f0} for the whole bake")
        if ob.name in mats and rb.kinematic:
            poses = [m.decompose() for m in mats[ob.name]]
            if any(not _close(m, m0) for m in mats[ob.name]):
                keys = [dict(time=(f - f0) / fps, position=_vec(p[0]), rotation=_vec(p[1]))
                        for f, p in zip(frames, poses)]
        elif ob.name in mats and any(not _close(m, m0) for m in mats[ob.name]):
            report.append(f"{ob.name}: animated but not Animated (kinematic): dempipe holds "
                          f"it where it is at frame {f0}, as Blender's solver does")
        flat = _flatness(verts)
        if flat is not None and keys is None:
            normal = (rot @ Vector(flat[1])).normalized()
            point = rot @ Vector(flat[0]) + loc
            colliders.append(dict(type="plane", name=cname, material=mat,
                                  point=_vec(point), normal=_vec(normal)))
            report.append(f"{ob.name}: a flat passive mesh is an infinite plane")
            continue
        if flat is not None:
            report.append(f"{ob.name}: an animated flat mesh is simulated as a mesh collider "
                          f"(a plane cannot be keyframed in dempipe); give it a thickness")
        mesh_name = valid_name(f"{ob.name}_shape", taken)
        _write_obj(folder / "meshes" / f"{mesh_name}.obj", verts, tris)
        col = dict(type="mesh", name=cname, material=mat, mesh=f"meshes/{mesh_name}.obj",
                   position=_vec(loc), rotation=_vec(rot))
        colliders.append((col, keys))

    for kind, names in replaced.items():
        report.append(f"collision shape {kind} is replaced by the object's mesh (dempipe fills "
                      f"the mesh with spheres): {', '.join(names)}")
    if not bodies:
        raise ValueError("no dynamic bodies: give at least one object an Active rigid body")
    # A plane keeps bodies on the side its normal points to: the side they start on.
    centre = [sum(b["position"][i] for b in bodies) / len(bodies) for i in range(3)]
    for col in colliders:
        if isinstance(col, dict) and col["type"] == "plane":
            side = sum((c - p) * n for c, p, n in zip(centre, col["point"], col["normal"]))
            if side < 0:
                col["normal"] = [-n for n in col["normal"]]
    text = ["# Written by the dempipe Blender extension from "
            f"{bpy.data.filepath or 'an unsaved file'}, scene {scene.name!r}.\n\n"]
    text.append(_table("[output]", dict(fps=fps, duration=(f1 - f0) / fps, up_axis="Z",
                                        meters_per_unit=1.0, start_frame=f0)))
    sim = dict(resolution=int(resolution), gravity=gravity, spheres=spheres)
    if target_overlap > 0:
        sim["stiffness_target_overlap"] = float(target_overlap)
    text.append(_table("[simulation]", sim))
    for (friction, restitution, density), name in materials.items():
        text.append(_table(f"[materials.{name}]", dict(density=density, friction=friction,
                                                        restitution=restitution)))
    for name in dict.fromkeys(shapes):
        text.append(_table(f"[shapes.{name}]", dict(mesh=f"meshes/{name}.obj")))
    for body in bodies:
        text.append(_table("[[bodies]]", body))
    for col in colliders:
        if isinstance(col, dict):
            text.append(_table("[[colliders]]", col))
            continue
        col, keys = col
        text.append(_table("[[colliders]]", col))
        if keys:
            text.append(_table("[colliders.motion]", dict(interpolation="linear")))
            for key in keys:
                text.append(_table("[[colliders.motion.keys]]", key))
    out.scene_path.write_text("".join(text))
    (folder / "map.json").write_text(json.dumps(dict(
        bodies=out.bodies, start_frames=out.start_frames, frame_start=f0, frame_end=f1,
        report=report), indent=1))
    return out


def _close(a: Matrix, b: Matrix, tol: float = 1e-9) -> bool:
    return all(abs(a[i][j] - b[i][j]) <= tol for i in range(4) for j in range(4))


def _flatness(verts):
    """(a point, the normal) in the object's frame when the mesh is flat along one
    of its axes, else None (an axis-aligned check: a Blender plane is flat along z)."""
    if len(verts) < 3:
        return None
    lo = [min(v[i] for v in verts) for i in range(3)]
    hi = [max(v[i] for v in verts) for i in range(3)]
    size = [h - low for h, low in zip(hi, lo)]
    big = max(size)
    if big <= 0:
        return None
    for axis in range(3):
        if size[axis] <= FLAT * big:
            normal = [0.0, 0.0, 0.0]
            normal[axis] = 1.0
            return [(lo[i] + hi[i]) / 2 for i in range(3)], normal
    return None
