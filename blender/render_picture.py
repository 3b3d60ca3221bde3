"""The picture in docs/blender.md: the extension's test scene baked headless and
rendered at three frames, side by side.

    PATH=venv/bin:$PATH python blender/render_picture.py docs/img/blender_bake.png

Needs bpy (Blender as a Python module) and `dempipe` on PATH; renders with Cycles
on the CPU (no display or GPU needed), a few samples, 320 x 240 per frame.
"""

import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "blender"), str(ROOT / "tests" / "blender")]

import bpy  # noqa: E402

import scene as test_scene  # noqa: E402


def main(out: Path) -> None:
    test_scene.build()
    import dempipe_bake

    dempipe_bake.register()
    scene = bpy.context.scene
    s = scene.dempipe
    tmp = Path(tempfile.mkdtemp())
    s.folder, s.resolution, s.device, s.target_overlap = str(tmp), 4, "cpu", 0.15
    assert bpy.ops.dempipe.bake() == {"FINISHED"}, s.status

    colours = {"Cube": (0.8, 0.35, 0.2), "Torus": (0.25, 0.5, 0.85), "Drop": (0.9, 0.75, 0.2),
               "Paddle": (0.4, 0.4, 0.45), "Ground": (0.75, 0.75, 0.72)}
    for ob in scene.objects:
        if ob.type != "MESH":
            continue
        key = next(k for k in colours if ob.name.startswith(k))
        mat = bpy.data.materials.new(ob.name)
        mat.diffuse_color = (*colours[key], 1.0)
        mat.use_nodes = True
        mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = \
            (*colours[key], 1.0)
        ob.data.materials.append(mat)
        if ob.name == "Torus":
            for p in ob.data.polygons:
                p.use_smooth = True
    cam_data = bpy.data.cameras.new("Camera")
    cam = bpy.data.objects.new("Camera", cam_data)
    scene.collection.objects.link(cam)
    cam.location = (1.5, -2.3, 1.35)
    cam.rotation_euler = (1.1, 0.0, 0.55)
    scene.camera = cam
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (0.6, 0.2, 0.8)
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("World")
    world.color = (0.6, 0.65, 0.7)
    scene.world = world
    r = scene.render
    r.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 16
    r.resolution_x, r.resolution_y, r.resolution_percentage = 320, 240, 100
    r.image_settings.file_format = "PNG"
    frames = (test_scene.FRAME_START, test_scene.EMIT_FRAME, test_scene.FRAME_END)
    paths = []
    for f in frames:
        scene.frame_set(f)
        r.filepath = str(tmp / f"frame_{f}.png")
        bpy.ops.render.render(write_still=True)
        paths.append(r.filepath)
    from PIL import Image, ImageDraw

    images = [Image.open(p).convert("RGB") for p in paths]
    sheet = Image.new("RGB", (sum(i.width for i in images), images[0].height), "white")
    x = 0
    for f, im in zip(frames, images):
        ImageDraw.Draw(im).text((8, 8), f"frame {f}", fill=(0, 0, 0))
        sheet.paste(im, (x, 0))
        x += im.width
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out, optimize=True)
    print(f"wrote {out}: {out.stat().st_size / 1024:.0f} KiB")


if __name__ == "__main__":
    main(Path(sys.argv[-1]))
