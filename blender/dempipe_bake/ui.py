"""The panel (Physics properties, and the 3D view's sidebar), the scene's settings
and the preferences."""

from __future__ import annotations

import bpy

from . import apply, operators


class DempipeSettings(bpy.types.PropertyGroup):
    """Per scene: what the panel sets, and the last bake's status and report."""

    resolution: bpy.props.IntProperty(
        name="Resolution", default=8, min=2, soft_max=40,
        description="Spheres across the smallest body's longest extent (quality)")
    spheres: bpy.props.EnumProperty(
        name="Spheres", default="lattice",
        items=[("lattice", "Lattice", "Fill each mesh with a lattice of spheres (fast; a body "
                "resting exactly on another at the first frame overlaps it: leave a gap)"),
               ("surface", "Surface", "Spheres on the surface (round bodies roll, bodies may "
                "touch at the first frame; more spheres, slower)"),
               ("auto", "Auto", "Surface spheres for the round meshes, so they roll (balls, "
                "wheels, tori); a lattice for the others (boxes, bricks)")])
    target_overlap: bpy.props.FloatProperty(
        name="Softness", default=0.0, min=0.0, max=0.5,
        description="Overlap of a contact, as a fraction of a sphere diameter, that the "
                    "automatic stiffness aims for (0: dempipe decides). Softer is faster")
    device: bpy.props.EnumProperty(
        name="Device", default="auto",
        items=[("auto", "Auto", "The GPU when CUDA works, else the CPU"),
               ("cpu", "CPU", "The CPU"), ("cuda", "CUDA", "An NVIDIA GPU")])
    folder: bpy.props.StringProperty(
        name="Folder", default="//dempipe_bake", subtype="DIR_PATH",
        description="Where the scene for dempipe and the baked USD go (// is the .blend's "
                    "folder)")
    checkpoint_seconds: bpy.props.FloatProperty(
        name="Checkpoint Every", default=30.0, min=0.0, unit="TIME_ABSOLUTE",
        description="Seconds between checkpoints: what Cancel can lose at most")
    drive: bpy.props.EnumProperty(
        name="Drive", default="keys",
        items=[("keys", "Keyframes", "Key every frame on the objects: the .blend holds the "
                "result (best up to a few thousand objects)"),
               ("cache", "Transform Cache", "Parent each object to an empty that follows the "
                "baked USD: faster and smaller with many objects; the USD must stay")])
    status: bpy.props.StringProperty(name="Status", default="")
    report: bpy.props.StringProperty(name="Report", default="")


class DempipePreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    executable: bpy.props.StringProperty(
        name="dempipe Executable", subtype="FILE_PATH", default="",
        description="The `dempipe` program to run; empty: the one on PATH")

    def draw(self, context):
        self.layout.prop(self, "executable")
        exe = operators.executable(context)
        self.layout.label(text=f"Runs: {exe}" if exe else "dempipe not found on PATH",
                          icon="CHECKMARK" if exe else "ERROR")


class DEMPIPE_PT_bake(bpy.types.Panel):
    bl_label = "dempipe Bake"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "physics"

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def draw(self, context):
        scene = context.scene
        s = scene.dempipe
        layout = self.layout
        if scene.rigidbody_world is None:
            layout.label(text="Add a Rigid Body World (Scene properties)", icon="INFO")
            return
        col = layout.column()
        col.prop(s, "resolution")
        col.prop(s, "spheres")
        col.prop(s, "target_overlap")
        col.prop(s, "device")
        col.prop(s, "folder")
        col.prop(s, "checkpoint_seconds")
        col.prop(s, "drive")
        running = scene.name in operators.JOBS
        row = layout.row(align=True)
        if running:
            job = operators.JOBS[scene.name]
            row.label(text=job.status)
            layout.operator("dempipe.cancel", icon="CANCEL")
            return
        if operators.can_resume(scene):
            row.operator("dempipe.bake", text="Resume", icon="PLAY").resume = True
            row.operator("dempipe.bake", text="Bake from Start", icon="FILE_REFRESH").resume = False
        else:
            row.operator("dempipe.bake", icon="PHYSICS").resume = False
        row.operator("dempipe.free", icon="TRASH")
        if s.status:
            layout.label(text=s.status, icon="INFO" if apply.is_baked(scene) else "NONE")
        if s.report:
            box = layout.box()
            box.label(text="Not simulated as in Blender (full list: text 'dempipe report'):")
            for line in s.report.splitlines()[:8]:
                box.label(text=line)


class DEMPIPE_PT_bake_sidebar(DEMPIPE_PT_bake):
    """The same panel in the 3D view's sidebar (N), tab dempipe."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "dempipe"
    bl_context = ""


CLASSES = (DempipeSettings, DempipePreferences, DEMPIPE_PT_bake, DEMPIPE_PT_bake_sidebar)
