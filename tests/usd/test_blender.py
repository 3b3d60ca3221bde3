"""What Blender shows of a bake: both layouts imported with Blender's own USD importer.

Optional: runs where Blender's Python module is importable, in this interpreter or in
the one named by ``DEMPIPE_BPY_PYTHON`` (bpy pins its own numpy and Python version, so
it usually lives in a venv of its own: ``python3.11 -m venv bpyenv && bpyenv/bin/pip
install bpy``); skipped otherwise. bpy is not a dependency of dempipe.

The import runs in a subprocess (bpy keeps global state); the script prints what Blender
made of the file as JSON, and the checks here compare it with the exporter's inputs:
object names, the material colour of each body, and each body's transform at a middle
frame. Blender's matrices are float32, so positions agree to about 1e-6 of the scene's
size; the instancer's orientations are half floats (docs/usd-output.md, "Precision").
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from test_animation import FIRST, _quat_matrix, make_frames, make_model

from dempipe.usd.meshes import PALETTE, COLLIDER_COLOR
from dempipe.usd.animation import write_usd


def _bpy_python():
    if importlib.util.find_spec("bpy") is not None:
        return sys.executable
    return os.environ.get("DEMPIPE_BPY_PYTHON") or None


BPY_PYTHON = _bpy_python()
pytestmark = pytest.mark.skipif(
    BPY_PYTHON is None, reason="Blender's Python module (bpy) is not installed "
    "(set DEMPIPE_BPY_PYTHON to a Python that has it)")

SCRIPT = r"""
import json, sys
import bpy
path, frame = sys.argv[-2], int(sys.argv[-1])
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.usd_import(filepath=path)
scene = bpy.context.scene
scene.frame_set(frame)
def colour(ob):
    slots = [s.material for s in ob.material_slots if s.material]
    if not slots:
        return None, None
    m = slots[0]
    bsdf = m.node_tree.nodes.get("Principled BSDF") if m.node_tree else None
    c = bsdf.inputs["Base Color"].default_value if bsdf else m.diffuse_color
    return m.name, [float(v) for v in c[:3]]
objects = {}
for ob in bpy.data.objects:
    mat, col = colour(ob)
    objects[ob.name] = dict(
        type=ob.type, parent=ob.parent.name if ob.parent else None, material=mat, colour=col,
        matrix=[list(r) for r in ob.matrix_world],
        instances=[o.name for o in ob.instance_collection.all_objects]
                  if ob.instance_collection else [],
        custom_normals=bool(ob.type == "MESH" and ob.data.has_custom_normals))
instances = []
deps = bpy.context.evaluated_depsgraph_get()
for inst in deps.object_instances:
    if inst.is_instance and inst.parent and inst.parent.original.type == "POINTCLOUD":
        instances.append(dict(object=inst.object.original.name,
                              matrix=[list(r) for r in inst.matrix_world]))
print("DEMPIPE_JSON" + json.dumps(dict(frame_start=scene.frame_start, frame_end=scene.frame_end,
                                       objects=objects, instances=instances)))
"""


def blender_import(path, frame):
    proc = subprocess.run([BPY_PYTHON, "-c", SCRIPT, str(path), str(frame)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("DEMPIPE_JSON"))
    return json.loads(line[len("DEMPIPE_JSON"):])


def _rotation_angle(a, b):
    """Angle [rad] between two rotation matrices, from the skew part of a^T b
    (well conditioned for small angles, unlike the arc cosine of the trace)."""
    r = a.T @ b
    return float(np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2)


@pytest.mark.parametrize("mpu", [1.0, 0.01])
def test_blender_imports_the_xforms_layout(tmp_path, mpu):
    model, frames = make_model(meters_per_unit=mpu), make_frames()
    path = write_usd(tmp_path / "bake.usdc", frames, model, layout="xforms").path
    mid = len(frames.frame_numbers) // 2
    got = blender_import(path, FIRST + mid)
    objects = got["objects"]
    assert (got["frame_start"], got["frame_end"]) == (FIRST, FIRST + len(frames.frame_numbers) - 1)
    assert "Prototypes" not in objects                     # no stray empty
    assert not any(n.split(".")[0].lower() == "mesh" for n in objects)
    for b in range(model.n_bodies):
        group = model.group_names[model.body_group[b]]
        name = f"{group}_{model.body_group_index[b]}"
        shape = model.shapes[model.body_shape[b]].name
        ob = objects[name]
        assert ob["parent"] == group
        # Scene instancing: the body instances a collection holding its shape's mesh,
        # named after the shape, with the shape's colour and authored normals.
        assert ob["instances"] == [shape]
        mesh = objects[shape]
        assert mesh["material"] == f"{shape}_mat" and mesh["custom_normals"]
        np.testing.assert_allclose(mesh["colour"], PALETTE[model.body_shape[b] % len(PALETTE)],
                                   atol=1e-6)
        # Blender applies metersPerUnit itself: its world transforms are in metres.
        m = np.array(ob["matrix"])
        np.testing.assert_allclose(m[:3, 3], frames.x[mid, b], atol=2e-6)
        assert _rotation_angle(m[:3, :3], _quat_matrix(frames.q[mid, b])) < 1e-5
    for name in ("plane_0", "box_0"):
        assert objects[name]["material"] == "collider_mat"
        np.testing.assert_allclose(objects[name]["colour"], COLLIDER_COLOR, atol=1e-6)


def test_blender_imports_the_instancer_layout(tmp_path):
    model, frames = make_model(), make_frames()
    path = write_usd(tmp_path / "bake.usdc", frames, model).path
    mid = len(frames.frame_numbers) // 2
    got = blender_import(path, FIRST + mid)
    objects = got["objects"]
    for i, shape in enumerate(model.shapes):
        assert objects[shape.name]["material"] == f"{shape.name}_mat"
        np.testing.assert_allclose(objects[shape.name]["colour"], PALETTE[i % len(PALETTE)],
                                   atol=1e-6)
    # no stray empty for the prototypes, and every name as written (no ".001")
    assert "Prototypes" not in objects
    assert not any("." in n for n in objects), sorted(objects)
    inst = got["instances"]
    assert len(inst) == model.n_bodies
    # Instances come in body order (ids); each at its body's pose at the middle frame.
    for b, item in enumerate(inst):
        assert item["object"] == model.shapes[model.body_shape[b]].name
        m = np.array(item["matrix"])
        np.testing.assert_allclose(m[:3, 3], frames.x[mid, b], atol=2e-6)
        # quath orientations: up to ~1e-3 rad (docs/usd-output.md, "Precision")
        assert _rotation_angle(m[:3, :3], _quat_matrix(frames.q[mid, b])) < 2e-3


def test_blender_shows_an_emitted_instance_from_its_start(tmp_path):
    """The instancer's invisibleIds, as Blender plays them: the last body, emitted at
    the middle frame, is not instanced before it and is from it on."""
    model, frames = make_model(), make_frames()       # a namespace standing for a Model
    mid = len(frames.frame_numbers) // 2
    model.body_start_time = np.zeros(model.n_bodies)
    model.body_start_time[-1] = frames.times[mid]
    path = write_usd(tmp_path / "bake.usdc", frames, model).path
    before = blender_import(path, FIRST + mid - 1)["instances"]
    after = blender_import(path, FIRST + mid)["instances"]
    assert len(before) == model.n_bodies - 1 and len(after) == model.n_bodies


def test_blender_hides_an_emitted_xforms_body_before_its_start(tmp_path):
    """Blender reads a prim's visibility once, not animated; the xforms layout also
    scales an emitted body by 0 until its first frame (docs/usd-output.md), which
    Blender's Transform Cache constraint follows: before it the object has no
    extent, from it on it stands at its pose, unscaled."""
    model, frames = make_model(), make_frames()
    mid = len(frames.frame_numbers) // 2
    model.body_start_time = np.zeros(model.n_bodies)
    model.body_start_time[-1] = frames.times[mid]
    path = write_usd(tmp_path / "bake.usdc", frames, model, layout="xforms").path
    b = model.n_bodies - 1
    name = f"{model.group_names[model.body_group[b]]}_{model.body_group_index[b]}"
    for frame, shown in ((FIRST, False), (FIRST + mid - 1, False), (FIRST + mid, True),
                         (FIRST + mid + 1, True)):
        m = np.array(blender_import(path, frame)["objects"][name]["matrix"])
        if shown:
            np.testing.assert_allclose(np.linalg.svd(m[:3, :3])[1], 1.0, atol=1e-6)
            np.testing.assert_allclose(m[:3, 3], frames.x[frame - FIRST, b], atol=2e-6)
        else:
            assert np.abs(m[:3, :3]).max() < 1e-9, frame
    # a body there from the start keeps its two ops and no scale
    other = blender_import(path, FIRST)["objects"][f"{model.group_names[0]}_0"]
    np.testing.assert_allclose(np.linalg.svd(np.array(other["matrix"])[:3, :3])[1], 1.0,
                               atol=1e-6)


def test_blender_names_do_not_collide(tmp_path):
    """A group named like a shape (wrecking_ball's ``ball``): the mesh takes
    ``<shape>_mesh``, so the group keeps its name in Blender (object names are
    global there; a clash becomes ``ball.001``)."""
    model, frames = make_model(), make_frames()
    model.group_names = ("pieces", "ball")
    path = write_usd(tmp_path / "bake.usdc", frames, model, layout="xforms").path
    objects = blender_import(path, FIRST)["objects"]
    assert not any("." in n for n in objects), sorted(objects)
    assert objects["ball"]["type"] == "EMPTY" and objects["ball"]["parent"] == "Bodies"
    assert objects["ball_0"]["instances"] == ["ball_mesh"]
    assert objects["ball_mesh"]["type"] == "MESH"
