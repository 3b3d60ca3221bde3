"""Bake, Cancel and Free Bake.

Bake writes the scene (export.py), starts `dempipe bake` (runner.py) and, with a
window, follows it from a modal timer: the progress bar and the status line move,
Blender stays responsive. Without one (``blender --background``, bpy as a module)
the same job is waited on in a loop: modal operators need a window's event loop.
When the child ends, its USD drives the objects (apply.py).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import bpy

from . import apply, export, runner

#: the running job of each scene (by name): one bake at a time per scene
JOBS: dict = {}
OUTPUT = "bake.usdc"
REPORT_TEXT = "dempipe report"


def settings(context):
    return context.scene.dempipe


def bake_folder(scene) -> Path:
    """Where the scene, meshes, map and baked USD go: the panel's folder (``//`` is
    the .blend's folder), or a temporary one for an unsaved file."""
    folder = scene.dempipe.folder
    if folder.startswith("//") and not bpy.data.filepath:
        return Path(tempfile.gettempdir()) / f"dempipe_bake_{scene.name}"
    return Path(bpy.path.abspath(folder)) / scene.name


def executable(context) -> str | None:
    prefs = context.preferences.addons.get(__package__)
    preferred = prefs.preferences.executable if prefs else ""
    return runner.find_executable(preferred)


def can_resume(scene) -> bool:
    return runner.resumable(bake_folder(scene) / OUTPUT)


def show_report(lines) -> None:
    """The export's report in a text block (the panel shows its first lines)."""
    text = bpy.data.texts.get(REPORT_TEXT) or bpy.data.texts.new(REPORT_TEXT)
    text.clear()
    text.write("\n".join(lines) + "\n")


def start(context, *, resume: bool = False) -> runner.BakeJob:
    """Export the scene and start `dempipe bake`; returns the job (also in JOBS)."""
    scene = context.scene
    s = scene.dempipe
    exe = executable(context)
    if exe is None:
        raise RuntimeError("dempipe not found: install it (pip install dempipe) or set its "
                           "path in the extension's preferences")
    folder = bake_folder(scene)
    exported = export.write_scene(scene, folder, resolution=s.resolution,
                                  target_overlap=s.target_overlap, spheres=s.spheres)
    show_report(exported.report)
    s.report = "\n".join(exported.report)
    job = runner.BakeJob(exe, exported.scene_path, folder / OUTPUT, device=s.device,
                         resume=resume, checkpoint_seconds=s.checkpoint_seconds)
    job.export = exported
    JOBS[scene.name] = job
    return job


def finish(context, job) -> tuple[str, str]:
    """Apply a finished job to the objects; (report level, message)."""
    scene = context.scene
    JOBS.pop(scene.name, None)
    if not job.ok:
        scene.dempipe.status = job.error
        return ("WARNING" if job.cancelled else "ERROR"), job.error
    e = job.export
    if scene.dempipe.drive == "cache":
        n = apply.apply_cache(scene, job.out, e.bodies, e.frame_start)
    else:
        n = apply.apply_bake(scene, job.out, e.bodies, e.start_frames, e.frame_start,
                             e.frame_end)
    scene.dempipe.status = f"baked {n} objects, frames {e.frame_start}-{e.frame_end}"
    return "INFO", scene.dempipe.status


class DEMPIPE_OT_bake(bpy.types.Operator):
    """Simulate the rigid-body world with dempipe and key its result on the objects"""

    bl_idname = "dempipe.bake"
    bl_label = "Bake"
    bl_options = {"REGISTER"}

    resume: bpy.props.BoolProperty(name="Resume", default=False,
                                   description="Go on from the stopped bake's last checkpoint")

    _timer = None
    _job = None

    @classmethod
    def poll(cls, context):
        return context.scene.rigidbody_world is not None and context.scene.name not in JOBS

    def execute(self, context):
        try:
            job = start(context, resume=self.resume)
        except (RuntimeError, ValueError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if bpy.app.background or not context.window_manager.windows:
            job.wait(on_progress=lambda j: None)
            level, msg = finish(context, job)
            self.report({level}, msg)
            return {"FINISHED"} if level == "INFO" else {"CANCELLED"}
        self._job = job
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.progress_begin(0, 1000)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        job = self._job
        wm = context.window_manager
        if not job.poll():
            wm.progress_update(int(job.fraction * 1000))
            context.scene.dempipe.status = job.status
            if context.workspace is not None:
                context.workspace.status_text_set(f"{job.status}  (Cancel in the dempipe panel)")
            for area in context.screen.areas if context.screen else ():
                area.tag_redraw()
            return {"RUNNING_MODAL"}
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        if context.workspace is not None:
            context.workspace.status_text_set(None)
        level, msg = finish(context, job)
        context.scene.dempipe.status = msg
        self.report({level}, msg)
        return {"FINISHED"} if level == "INFO" else {"CANCELLED"}


class DEMPIPE_OT_cancel(bpy.types.Operator):
    """Stop the bake (SIGINT): the frames done are kept and Bake offers Resume"""

    bl_idname = "dempipe.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context):
        return context.scene.name in JOBS

    def execute(self, context):
        JOBS[context.scene.name].cancel()
        context.scene.dempipe.status = "cancelling: dempipe saves its checkpoint"
        return {"FINISHED"}


class DEMPIPE_OT_free(bpy.types.Operator):
    """Remove the baked keys and put the objects and the rigid-body world back"""

    bl_idname = "dempipe.free"
    bl_label = "Free Bake"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return apply.is_baked(context.scene) and context.scene.name not in JOBS

    def execute(self, context):
        n = apply.free_bake(context.scene)
        context.scene.dempipe.status = f"freed {n} objects"
        return {"FINISHED"}


CLASSES = (DEMPIPE_OT_bake, DEMPIPE_OT_cancel, DEMPIPE_OT_free)
