"""The test scene, built with bpy: a stack of cubes and a torus on a passive plane,
a keyframed Animated paddle, and a batch of two cubes emitted at frame 7 (and a
hinge constraint, which dempipe reports as not simulated).

Run inside a Python that has bpy (tests/blender/test_extension.py starts one);
``build()`` returns nothing and leaves the scene in bpy.context.scene. 13 frames
at 24 fps (0.5 s), so a bake is short.
"""

import bpy

FRAME_START, FRAME_END, EMIT_FRAME = 1, 13, 7
DYNAMIC = ("Cube", "Cube.001", "Cube.002", "Torus", "Drop", "Drop.001")


def _rigid(ob, kind, **kw):
    bpy.context.view_layer.objects.active = ob
    ob.select_set(True)
    bpy.ops.rigidbody.object_add(type=kind)
    for k, v in kw.items():
        setattr(ob.rigid_body, k, v)
    ob.select_set(False)


def build():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = 24
    scene.frame_start, scene.frame_end = FRAME_START, FRAME_END
    bpy.ops.rigidbody.world_add()
    rbw = scene.rigidbody_world
    rbw.point_cache.frame_start, rbw.point_cache.frame_end = FRAME_START, FRAME_END

    bpy.ops.mesh.primitive_plane_add(size=3.0, location=(0, 0, 0))
    ground = bpy.context.object
    ground.name = "Ground"
    _rigid(ground, "PASSIVE", friction=0.6, restitution=0.3)

    for i, z in enumerate((0.125, 0.35, 0.575)):   # gaps: lattice spheres stick out
        bpy.ops.mesh.primitive_cube_add(size=0.2, location=(0.02 * i, 0, z))
        cube = bpy.context.object
        cube.name = "Cube" if i == 0 else f"Cube.{i:03d}"
        _rigid(cube, "ACTIVE", mass=2.0, friction=0.5, restitution=0.2)
    bpy.data.objects["Cube.001"].scale = (1.3, 1.0, 1.0)     # scale is part of the body
    bpy.data.objects["Cube.002"].rotation_euler = (0.0, 0.0, 0.4)

    bpy.ops.mesh.primitive_torus_add(major_radius=0.15, minor_radius=0.05,
                                     major_segments=24, minor_segments=8,
                                     location=(0.5, 0.0, 0.15), rotation=(0.5, 0.0, 0.0))
    torus = bpy.context.object
    torus.name = "Torus"
    _rigid(torus, "ACTIVE", mass=0.5, restitution=0.4)
    torus["dempipe_velocity"] = [0.0, 0.2, 0.0]      # Blender has no initial velocity

    # a hinge between two cubes: dempipe has no joints, the report names it
    hinge = bpy.data.objects.new("Hinge", None)
    scene.collection.objects.link(hinge)
    bpy.context.view_layer.objects.active = hinge
    bpy.ops.rigidbody.constraint_add(type="HINGE")
    hinge.rigid_body_constraint.object1 = bpy.data.objects["Cube"]
    hinge.rigid_body_constraint.object2 = bpy.data.objects["Cube.001"]

    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(-0.6, 0.0, 0.1))
    paddle = bpy.context.object
    paddle.name = "Paddle"
    paddle.scale = (0.1, 0.6, 0.2)
    _rigid(paddle, "PASSIVE", kinematic=True)
    paddle.keyframe_insert("location", frame=FRAME_START)
    paddle.location.x = -0.45
    paddle.rotation_euler.z = 0.2
    paddle.keyframe_insert("location", frame=FRAME_END)
    paddle.keyframe_insert("rotation_euler", frame=FRAME_END)
    paddle.rotation_euler.z = 0.0
    paddle.keyframe_insert("rotation_euler", frame=FRAME_START)

    for i in range(2):     # the emitted batch: hidden in renders until EMIT_FRAME
        bpy.ops.mesh.primitive_cube_add(size=0.15, location=(0.5 + 0.3 * i, 0.3, 0.2))
        drop = bpy.context.object
        drop.name = "Drop" if i == 0 else f"Drop.{i:03d}"
        _rigid(drop, "ACTIVE", mass=1.0, restitution=0.2)
        drop.hide_render = True
        drop.keyframe_insert("hide_render", frame=FRAME_START)
        drop.hide_render = False
        drop.keyframe_insert("hide_render", frame=EMIT_FRAME)
    scene.frame_set(FRAME_START)
