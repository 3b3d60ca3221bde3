"""The baked USD on the user's own objects, as keyframes (or through a Transform
Cache, :func:`apply_cache`); Free Bake undoes either.

The bake (xforms layout) has each dynamic body at ``/World/Bodies/<prim>/<prim>_0``,
posed at its centre of mass. The object's world matrix at frame f is
``B(f) B(f0)^-1 M0``: the body's rigid motion since the first frame applied to
the object's own first-frame matrix M0, so its origin, scale and mesh stay as they
were. By default as keyframes (location, quaternion rotation, scale, one per
frame, linear), built from the quaternion's components; :func:`apply_cache`
reaches the same matrix through an empty with a Transform Cache constraint (a
constraint on the object itself would put it at the prim's pose: its centre of
mass, without its scale). The measured trade-off is in docs/blender.md.

Emitted bodies are hidden before their first frame with keyframes on
``hide_viewport`` and ``hide_render`` (constant), which Blender plays back.
The rigid-body world is muted (``enabled = False``) so that Blender's own solver
does not move the objects too. What was there before is kept as JSON on the
scene (``scene["dempipe_bake_state"]``), and Free Bake puts it back.
"""

from __future__ import annotations

import json

import bpy
from mathutils import Matrix, Quaternion

STATE = "dempipe_bake_state"
_RAW = ("location", "rotation_euler", "rotation_quaternion", "rotation_axis_angle", "scale")


def read_body_matrices(usd_path, prims, frames):
    """World matrices (mathutils, column vectors) of each body prim at each frame,
    from the baked USD: {prim: [Matrix per frame]}. Reads with pxr (bundled with
    Blender)."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(usd_path))
    paths = {p: f"/World/Bodies/{p}/{p}_0" for p in prims}
    found = {p: stage.GetPrimAtPath(path) for p, path in paths.items()}
    missing = [paths[p] for p, prim in found.items() if not prim.IsValid()]
    if missing:
        raise ValueError(f"the bake has no prim {missing[0]} ({len(missing)} missing): "
                         f"bake again")
    # The pose is the body's translate and orient ops (its parents are identity
    # Xforms); an emitted body's scale op, 0 before its start, is not part of it.
    out = {p: [] for p in prims}
    ops = {p: (prim.GetAttribute("xformOp:translate"), prim.GetAttribute("xformOp:orient"))
           for p, prim in found.items()}
    for f in frames:
        t = Usd.TimeCode(float(f))
        for p, (tr, ori) in ops.items():
            x, q = tr.Get(t), ori.Get(t)
            m = Quaternion((q.GetReal(), *q.GetImaginary())).normalized().to_matrix().to_4x4()
            m.translation = (x[0], x[1], x[2])
            out[p].append(m)
    return out


def _channelbag(action, slot):
    """The F-curve container of ``slot`` in ``action`` (layered actions, 4.4+), or
    the action itself (older Blender)."""
    try:
        from bpy_extras.anim_utils import action_ensure_channelbag_for_slot

        return action_ensure_channelbag_for_slot(action, slot)
    except ImportError:
        return action


def _curve(bag, path, index, frames, values, interpolation):
    fc = bag.fcurves.new(path, index=index)
    fc.keyframe_points.add(len(frames))
    co = [c for f, v in zip(frames, values) for c in (float(f), float(v))]
    fc.keyframe_points.foreach_set("co", co)
    mode = {"CONSTANT": 0, "LINEAR": 1}[interpolation]
    fc.keyframe_points.foreach_set("interpolation", [mode] * len(frames))
    fc.update()
    return fc


def _snapshot(ob) -> dict:
    ad = ob.animation_data
    slot = getattr(ad, "action_slot", None) if ad else None
    return dict(
        had_animation_data=ad is not None,
        action=ad.action.name if ad and ad.action else None,
        slot=slot.identifier if slot else None,
        rotation_mode=ob.rotation_mode,
        raw={k: list(getattr(ob, k)) for k in _RAW},
        hide_viewport=bool(ob.hide_viewport), hide_render=bool(ob.hide_render))


def apply_bake(scene, usd_path, bodies: dict, start_frames: dict, f0: int, f1: int) -> int:
    """Drive each body's object (``bodies``: prim -> object name) by the bake;
    returns how many. Records the objects' previous state for :func:`free_bake`."""
    if STATE in scene:
        free_bake(scene)
    frames = list(range(f0, f1 + 1))
    mats = read_body_matrices(usd_path, list(bodies), frames)
    current = scene.frame_current
    scene.frame_set(f0)
    rbw = scene.rigidbody_world
    state = dict(rbw_enabled=bool(rbw.enabled) if rbw else None, objects={})
    for prim, name in bodies.items():
        ob = bpy.data.objects.get(name)
        if ob is None:
            continue
        snap = _snapshot(ob)
        m0 = ob.matrix_world.copy()
        # the parent's pose at the first frame (a static parent; parented bodies
        # are listed in the export's report)
        to_basis = Matrix.Identity(4)
        if ob.parent is not None:
            to_basis = (ob.parent.matrix_world @ ob.matrix_parent_inverse).inverted()
        b0_inv = mats[prim][0].inverted()
        locs, quats, scales = [], [], []
        prev = None
        for b in mats[prim]:
            loc, q, s = (to_basis @ b @ b0_inv @ m0).decompose()
            if prev is not None and prev.dot(q) < 0:   # the short way between keys
                q.negate()
            prev = q
            locs.append(loc), quats.append(q), scales.append(s)
        action = bpy.data.actions.new(f"{ob.name}_dempipe")
        if ob.animation_data is None:
            ob.animation_data_create()
        slot = None
        if hasattr(action, "slots"):
            slot = action.slots.new(id_type="OBJECT", name=ob.name)
        ob.animation_data.action = action
        if slot is not None:
            ob.animation_data.action_slot = slot
        bag = _channelbag(action, slot)
        ob.rotation_mode = "QUATERNION"
        for i in range(3):
            _curve(bag, "location", i, frames, [v[i] for v in locs], "LINEAR")
            _curve(bag, "scale", i, frames, [v[i] for v in scales], "LINEAR")
        for i in range(4):
            _curve(bag, "rotation_quaternion", i, frames, [q[i] for q in quats], "LINEAR")
        start = start_frames.get(name)
        if start is not None and start > f0:
            for path in ("hide_viewport", "hide_render"):
                _curve(bag, path, 0, [f0, start], [1.0, 0.0], "CONSTANT")
        snap["baked_action"] = action.name
        state["objects"][name] = snap
    if rbw is not None:
        rbw.enabled = False          # Blender's solver would move the objects too
    scene[STATE] = json.dumps(state)
    scene.frame_set(current)
    return len(state["objects"])


DRIVERS = "dempipe drivers"


def apply_cache(scene, usd_path, bodies: dict, f0: int) -> int:
    """Drive each body's object through a Transform Cache on the baked USD: an
    empty per object follows its body prim (a Transform Cache constraint) and the
    object becomes its child, with the parent inverse ``B(f0)^-1`` and its own
    first-frame world matrix as its basis, so that it is at ``B(f) B(f0)^-1 M0``
    as with keys. An emitted body's prim is scaled 0 before its start
    (docs/usd-output.md), which hides the child. Nothing is keyed: the .blend stays
    small and needs the USD where it is (docs/blender.md, the measured choice)."""
    if STATE in scene:
        free_bake(scene)
    b0 = read_body_matrices(usd_path, list(bodies), [f0])
    current = scene.frame_current
    scene.frame_set(f0)
    rbw = scene.rigidbody_world
    state = dict(rbw_enabled=bool(rbw.enabled) if rbw else None, objects={})
    with bpy.context.temp_override(scene=scene):
        bpy.ops.cachefile.open(filepath=str(usd_path))
    cache = bpy.data.cache_files[-1]
    cache.name = f"{scene.name}_dempipe"
    state["cache_file"] = cache.name
    coll = bpy.data.collections.new(DRIVERS)
    scene.collection.children.link(coll)
    coll.hide_render = True
    state["collection"] = coll.name
    for prim, name in bodies.items():
        ob = bpy.data.objects.get(name)
        if ob is None:
            continue
        snap = _snapshot(ob)
        snap["parent"] = ob.parent.name if ob.parent else None
        snap["parent_inverse"] = [list(r) for r in ob.matrix_parent_inverse]
        m0 = ob.matrix_world.copy()
        driver = bpy.data.objects.new(f"{ob.name}_dempipe", None)
        driver.empty_display_size = 0.02
        coll.objects.link(driver)
        c = driver.constraints.new("TRANSFORM_CACHE")
        c.cache_file = cache
        c.object_path = f"/World/Bodies/{prim}/{prim}_0"
        ob.parent = driver
        ob.matrix_parent_inverse = b0[prim][0].inverted()
        ob.matrix_basis = m0
        snap["driver"] = driver.name
        state["objects"][name] = snap
    if rbw is not None:
        rbw.enabled = False
    scene[STATE] = json.dumps(state)
    scene.frame_set(current)
    return len(state["objects"])


def free_bake(scene) -> int:
    """Put the baked objects back as they were before :func:`apply_bake`: their
    actions, rotation modes, transform channels, visibility, and the rigid-body
    world's switch. Returns how many objects were restored."""
    if STATE not in scene:
        return 0
    state = json.loads(scene[STATE])
    n = 0
    for name, snap in state["objects"].items():
        ob = bpy.data.objects.get(name)
        if ob is None:
            continue
        baked = bpy.data.actions.get(snap.get("baked_action") or "")
        if ob.animation_data is not None:
            ob.animation_data.action = None
        if snap["action"] is not None:
            ob.animation_data.action = bpy.data.actions.get(snap["action"])
            if snap["slot"] and hasattr(ob.animation_data, "action_slot"):
                slot = next((s for s in ob.animation_data.action.slots
                             if s.identifier == snap["slot"]), None)
                if slot is not None:
                    ob.animation_data.action_slot = slot
        elif not snap["had_animation_data"]:
            ob.animation_data_clear()
        if baked is not None:
            bpy.data.actions.remove(baked)
        if snap.get("driver"):
            ob.parent = bpy.data.objects.get(snap["parent"] or "")
            ob.matrix_parent_inverse = Matrix(snap["parent_inverse"])
            driver = bpy.data.objects.get(snap["driver"])
            if driver is not None:
                bpy.data.objects.remove(driver)
        ob.rotation_mode = snap["rotation_mode"]
        for k, v in snap["raw"].items():
            setattr(ob, k, v)
        ob.hide_viewport = snap["hide_viewport"]
        ob.hide_render = snap["hide_render"]
        n += 1
    coll = bpy.data.collections.get(state.get("collection") or "")
    if coll is not None:
        bpy.data.collections.remove(coll)
    cache = bpy.data.cache_files.get(state.get("cache_file") or "")
    if cache is not None:            # cache_files has no remove(); batch_remove takes any ID
        bpy.data.batch_remove([cache])
    rbw = scene.rigidbody_world
    if rbw is not None and state.get("rbw_enabled") is not None:
        rbw.enabled = state["rbw_enabled"]
    del scene[STATE]
    scene.frame_set(scene.frame_current)
    return n


def is_baked(scene) -> bool:
    return STATE in scene
