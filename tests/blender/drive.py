"""Inside a Python with bpy: build the test scene, run the extension's operators
headless (Bake, Cancel, Resume, Free Bake) and print what Blender shows as one
JSON line (``DEMPIPE_JSON{...}``) for tests/blender/test_extension.py to check.

argv: the bake folder. The extension is imported from blender/ and registered as
Blender's own add-on loader would; `dempipe` is found on PATH.
"""

import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parents[1] / "blender"), str(HERE)]

import bpy  # noqa: E402

import scene as test_scene  # noqa: E402

folder = Path(sys.argv[-1])
test_scene.build()
import dempipe_bake  # noqa: E402
from dempipe_bake import operators  # noqa: E402

dempipe_bake.register()
scene = bpy.context.scene
s = scene.dempipe
s.folder, s.resolution, s.device, s.target_overlap = str(folder), 4, "cpu", 0.15
s.checkpoint_seconds = 0.0          # a checkpoint after every frame: Cancel keeps them
RAW = ("location", "rotation_euler", "rotation_quaternion", "scale")


def snapshot():
    out = {}
    for ob in bpy.data.objects:
        ad = ob.animation_data
        out[ob.name] = dict(
            matrix=[list(r) for r in ob.matrix_world], rotation_mode=ob.rotation_mode,
            raw={k: list(getattr(ob, k)) for k in RAW},
            action=ad.action.name if ad and ad.action else None,
            hide=[ob.hide_viewport, ob.hide_render])
    return out


def world_vertices(ob):
    dg = bpy.context.evaluated_depsgraph_get()
    ev = ob.evaluated_get(dg)
    m = ev.matrix_world
    return [list(m @ v.co) for v in ev.data.vertices]


result = dict(frames={}, before=None, after_free=None)
scene.frame_set(test_scene.FRAME_START)
result["before"] = snapshot()
result["rbw_enabled_before"] = scene.rigidbody_world.enabled

# Bake, then Cancel once it has checkpointed two frames: SIGINT to the real child.
job = operators.start(bpy.context)
t0 = time.monotonic()
meta = job.out.with_name(f".{job.out.name}.bake") / "meta.json"
while not job.poll():
    try:
        done = json.loads(meta.read_text())["frames_done"]
    except (OSError, ValueError, KeyError):
        done = 0
    if done >= 2:
        bpy.ops.dempipe.cancel()
        break
    if time.monotonic() - t0 > 600:
        raise SystemExit("the bake did not checkpoint within 600 s")
    time.sleep(0.02)
job.wait()
result["cancel"] = dict(returncode=job.returncode, error=job.error,
                        resumable=operators.can_resume(scene),
                        frames_done=json.loads(meta.read_text())["frames_done"]
                        if meta.exists() else None,
                        baked=bool(scene.get("dempipe_bake_state")),
                        fraction=job.fraction, status=job.status)
operators.finish(bpy.context, job)

# Resume: the operator's blocking path (no window here), as the panel's Resume button.
result["resume"] = list(bpy.ops.dempipe.bake(resume=True))
result["status"] = s.status
result["report"] = s.report
result["out"] = str(job.out)
result["bodies"] = job.export.bodies
result["rbw_enabled_baked"] = scene.rigidbody_world.enabled
for f in (test_scene.FRAME_START, test_scene.EMIT_FRAME - 1, test_scene.EMIT_FRAME,
          (test_scene.FRAME_START + test_scene.FRAME_END) // 2, test_scene.FRAME_END):
    scene.frame_set(f)
    result["frames"][f] = {name: dict(vertices=world_vertices(bpy.data.objects[name]),
                                      hide=[bpy.data.objects[name].hide_viewport,
                                            bpy.data.objects[name].hide_render])
                           for name in test_scene.DYNAMIC}

result["free"] = list(bpy.ops.dempipe.free())
scene.frame_set(test_scene.FRAME_START)
result["after_free"] = snapshot()
result["rbw_enabled_after"] = scene.rigidbody_world.enabled
result["actions_left"] = sorted(a.name for a in bpy.data.actions if a.name.endswith("_dempipe"))

# The same bake through a Transform Cache (the panel's Drive), then freed again.
from dempipe_bake import apply  # noqa: E402
e = job.export
result["cache_applied"] = apply.apply_cache(scene, job.out, e.bodies, e.frame_start)
result["cache_frames"] = {}
for f in (test_scene.FRAME_START, test_scene.EMIT_FRAME - 1, test_scene.EMIT_FRAME,
          test_scene.FRAME_END):
    scene.frame_set(f)
    result["cache_frames"][f] = {name: world_vertices(bpy.data.objects[name])
                                 for name in test_scene.DYNAMIC}
apply.free_bake(scene)
scene.frame_set(test_scene.FRAME_START)
result["after_cache_free"] = snapshot()
result["cache_left"] = [len(bpy.data.cache_files), bool(bpy.data.collections.get(apply.DRIVERS)),
                        sorted(o.name for o in bpy.data.objects if o.name.endswith("_dempipe"))]

# The scene the bake above read, kept for the test's uninterrupted bake of it.
scene_toml = job.out.parent / "scene.toml"
result["scene_toml"] = str(scene_toml.with_name("baked_scene.toml"))
Path(result["scene_toml"]).write_text(scene_toml.read_text())

# An error: a cube moved into the one below it; dempipe refuses, its line is shown.
bpy.data.objects["Cube.001"].location.z = 0.15
try:
    result["error_bake"] = list(bpy.ops.dempipe.bake())
except RuntimeError as exc:         # an operator's ERROR report, raised to its caller
    result["error_bake"] = ["ERROR", str(exc)]
result["error_status"] = s.status
result["error_baked"] = bool(scene.get("dempipe_bake_state"))
print("DEMPIPE_JSON" + json.dumps(result))
