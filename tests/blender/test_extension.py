"""The Blender extension end to end, headless: a scene built in bpy, baked by the
real `dempipe` child process, cancelled with a real SIGINT, resumed, keyed onto
the user's objects and freed.

Runs where Blender's Python module is importable (the ``test`` extra installs
``bpy`` on the one Python version its wheels exist for), in this interpreter or
the one named by ``DEMPIPE_BPY_PYTHON``; skipped otherwise. Blender runs in a
subprocess (bpy keeps global state, and its USD libraries stay out of this
process); tests/blender/drive.py prints what it shows as JSON.

Tolerances: Blender's matrices and F-curve values are float32, positions here are
below 1 m, so 1e-6 m holds with margin; the baked USD is read with pxr here.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

try:
    import tomllib
except ImportError:         # Python 3.10
    import tomli as tomllib
from pxr import Gf, Usd, UsdGeom

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from processes import assert_same_samples  # noqa: E402

import scene as test_scene  # noqa: E402  (constants only: bpy is imported inside build())


def _bpy_python():
    if importlib.util.find_spec("bpy") is not None:
        return sys.executable
    return os.environ.get("DEMPIPE_BPY_PYTHON") or None


BPY_PYTHON = _bpy_python()
pytestmark = pytest.mark.skipif(
    BPY_PYTHON is None, reason="Blender's Python module (bpy) is not installed "
    "(set DEMPIPE_BPY_PYTHON to a Python that has it)")
TOL = 1e-6      # m


def _env(tmp_path):
    env = dict(os.environ)
    # the `dempipe` of this environment, found on PATH as a user's would be
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    env["DEMPIPE_CACHE_DIR"] = str(tmp_path / "cache")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def run_bpy(script, *args, tmp_path, timeout=900):
    proc = subprocess.run([BPY_PYTHON, str(script), *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env=_env(tmp_path))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("DEMPIPE_JSON"))
    return json.loads(line[len("DEMPIPE_JSON"):])


@pytest.fixture(scope="module")
def driven(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("blender")
    return run_bpy(HERE / "drive.py", tmp / "bake", tmp_path=tmp), tmp


def usd_world_points(stage, prim_name, frame):
    """World-space points [m] of the mesh under a body prim at a time code, placed
    by the body's translate and orient (an emitted body's scale, 0 before its
    start, is what hides it: docs/usd-output.md)."""
    body = stage.GetPrimAtPath(f"/World/Bodies/{prim_name}/{prim_name}_0")
    assert body.IsValid(), prim_name
    meshes = [p for p in Usd.PrimRange(body, Usd.TraverseInstanceProxies())
              if p.IsA(UsdGeom.Mesh)]
    assert len(meshes) == 1
    pts = np.array(UsdGeom.Mesh(meshes[0]).GetPointsAttr().Get(frame), dtype=np.float64)
    x = np.array(body.GetAttribute("xformOp:translate").Get(frame), dtype=np.float64)
    q = body.GetAttribute("xformOp:orient").Get(frame)
    # from the components (Gf.Rotation would take the angle from acos(real), which
    # is 0 for a float32 real part of 1 and a rotation of 1e-5 rad)
    r = np.array(Gf.Matrix3d(Gf.Quatd(q.GetReal(), Gf.Vec3d(q.GetImaginary()))),
                 dtype=np.float64)
    return pts @ r + x          # Gf matrices act on row vectors


def nearest(a, b):
    """Largest distance from a point of ``a`` to its nearest point of ``b``."""
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    return float(d.min(axis=1).max())


def test_objects_follow_the_baked_usd(driven):
    got, _ = driven
    assert got["resume"] == ["FINISHED"], got["status"]
    stage = Usd.Stage.Open(got["out"])
    assert stage.GetMetadata("metersPerUnit") == 1.0
    by_object = {v: k for k, v in got["bodies"].items()}
    assert sorted(by_object) == sorted(test_scene.DYNAMIC)
    for frame, objects in got["frames"].items():
        for name, o in objects.items():
            usd = usd_world_points(stage, by_object[name], float(frame))
            blender = np.array(o["vertices"])
            # every vertex of the user's object lies on the baked mesh, and back
            assert nearest(blender, usd) < TOL, (frame, name)
            assert nearest(usd, blender) < TOL, (frame, name)
    # the bake moved things: the top cube fell, the emitted batch too
    first, last = got["frames"][str(test_scene.FRAME_START)], got["frames"][str(test_scene.FRAME_END)]
    for name in ("Cube.002", "Drop"):
        assert np.mean(last[name]["vertices"], axis=0)[2] < \
            np.mean(first[name]["vertices"], axis=0)[2] - 0.01


def test_emitted_bodies_hidden_before_their_start(driven):
    got, _ = driven
    stage = Usd.Stage.Open(got["out"])
    by_object = {v: k for k, v in got["bodies"].items()}
    for frame, objects in got["frames"].items():
        for name, o in objects.items():
            emitted = name.startswith("Drop")
            hidden = emitted and int(frame) < test_scene.EMIT_FRAME
            assert o["hide"] == [hidden, hidden], (frame, name)
            p = by_object[name]
            prim = stage.GetPrimAtPath(f"/World/Bodies/{p}/{p}_0")
            vis = UsdGeom.Imageable(prim).ComputeVisibility(float(frame))
            assert (vis == UsdGeom.Tokens.invisible) == hidden, (frame, name)


def test_free_bake_restores_the_scene(driven):
    got, _ = driven
    assert got["free"] == ["FINISHED"]
    assert got["rbw_enabled_before"] and not got["rbw_enabled_baked"]
    assert got["rbw_enabled_after"]
    assert got["actions_left"] == []
    assert got["after_free"].keys() == got["before"].keys()
    for name, before in got["before"].items():
        after = got["after_free"][name]
        assert after == before, name           # exactly: matrices, channels, actions


def test_cancel_leaves_a_resumable_bake(driven, tmp_path):
    """SIGINT mid-bake: dempipe exits 130 with its checkpoints kept, the panel
    offers Resume, and the resumed bake writes the uninterrupted bake's samples."""
    got, tmp = driven
    c = got["cancel"]
    assert c["returncode"] == 130, c
    assert c["resumable"] and c["frames_done"] >= 2 and not c["baked"], c
    assert c["error"] == "cancelled: the bake can be resumed"
    # dempipe's progress line, read from its terminal, moved the progress bar
    assert 0 < c["fraction"] < 1, c
    out = Path(got["out"])
    whole = tmp_path / "whole.usdc"
    proc = subprocess.run([str(Path(sys.executable).parent / "dempipe"), "bake",
                           got["scene_toml"], "-o", str(whole), "--layout",
                           "xforms", "--device", "cpu", "-q"], env=_env(tmp),
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr
    assert_same_samples(out, whole)


def test_extension_zip_installs_in_blender(tmp_path):
    zpath = tmp_path / "dempipe_bake.zip"
    proc = subprocess.run([str(Path(sys.executable).parent / "dempipe"), "blender-extension",
                           "-o", str(zpath)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    names = zipfile.ZipFile(zpath).namelist()
    assert "blender_manifest.toml" in names and "__init__.py" in names
    assert not any("__pycache__" in n for n in names)
    # Blender's own "Install from Disk" (its operator), into a user folder of its own
    env = _env(tmp_path)
    env["HOME"] = str(tmp_path / "home")
    proc = subprocess.run([BPY_PYTHON, "-c", INSTALL, str(zpath)], capture_output=True,
                          text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "INSTALLED ['bl_ext.user_default.dempipe_bake'] True True" in proc.stdout, \
        proc.stdout[-3000:]


INSTALL = r"""
import sys
import bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.extensions.package_install_files(filepath=sys.argv[-1], repo="user_default",
                                         enable_on_install=True)
print("INSTALLED", [m for m in bpy.context.preferences.addons.keys() if "dempipe" in m],
      hasattr(bpy.types, "DEMPIPE_PT_bake") and hasattr(bpy.types, "DEMPIPE_PT_bake_sidebar"),
      hasattr(bpy.types.Scene, "dempipe"))
"""


def test_an_error_shows_dempipes_one_line_message(driven):
    got, _ = driven
    assert got["error_bake"][0] == "ERROR" and not got["error_baked"]
    status = got["error_status"]
    assert status.startswith("error: ") and "overlaps" in status and "\n" not in status, status
    assert "frame 0" in status, status          # refused before the first step
    assert status in got["error_bake"][1]       # the operator reports the same line


def test_scene_toml_maps_blenders_settings(driven):
    """What the export wrote for dempipe (docs/blender.md, "What maps to what")."""
    got, _ = driven
    toml = tomllib.loads(Path(got["scene_toml"]).read_text())
    assert toml["output"] == dict(fps=24, duration=0.5, up_axis="Z", meters_per_unit=1.0,
                                  start_frame=1)
    assert toml["simulation"]["gravity"] == pytest.approx([0.0, 0.0, -9.81], abs=1e-6)
    bodies = {b["name"]: b for b in toml["bodies"]}
    assert sorted(bodies) == sorted(n.replace(".", "_") for n in test_scene.DYNAMIC)
    mats = toml["materials"]
    cube = mats[bodies["Cube"]["material"]]
    # mass 2 kg over a 0.2 m cube; Blender's friction and bounciness
    assert cube["density"] == pytest.approx(2.0 / 0.2 ** 3, rel=1e-5)
    assert (cube["friction"], cube["restitution"]) == pytest.approx((0.5, 0.2))
    # Cube.001 is scaled 1.3 along x: its mesh is, and its density follows the volume
    assert mats[bodies["Cube_001"]["material"]]["density"] == pytest.approx(
        2.0 / (1.3 * 0.2 ** 3), rel=1e-5)
    assert bodies["Torus"]["velocity"] == pytest.approx([0.0, 0.2, 0.0])
    for name in ("Drop", "Drop_001"):           # shown in renders from frame 7
        assert bodies[name]["start_time"] == pytest.approx((test_scene.EMIT_FRAME - 1) / 24)
    assert "start_time" not in bodies["Cube"]
    colliders = {c["name"]: c for c in toml["colliders"]}
    assert colliders["Ground"]["type"] == "plane"
    assert colliders["Ground"]["normal"] == pytest.approx([0.0, 0.0, 1.0])
    paddle = colliders["Paddle"]
    assert paddle["type"] == "mesh" and paddle["motion"]["interpolation"] == "linear"
    keys = paddle["motion"]["keys"]
    assert len(keys) == test_scene.FRAME_END - test_scene.FRAME_START + 1
    assert keys[-1]["position"] == pytest.approx([-0.45, 0.0, 0.1], abs=1e-6)
    assert keys[-1]["time"] == pytest.approx(0.5)
    # what dempipe does not simulate is named, not dropped
    assert "rigid-body constraints are not simulated: Hinge" in got["report"].splitlines()


def test_transform_cache_drive_puts_objects_where_the_keys_do(driven):
    """The panel's other Drive: each object under an empty with a Transform Cache
    constraint on the baked USD. The places of the keys, to 1e-4 m: Blender's USD
    reader drops a rotation whose float32 quaternion has a real part of exactly 1
    (below about 7e-4 rad), which the keys, built from the components, keep; a point
    0.14 m from its object's origin (the torus's rim) then moves by up to 1e-4 m
    (measured here: 3.4e-5 m on the torus, 4.6e-6 m on a 20 cm cube, depending on how
    far the bodies turn). Emitted bodies collapse to a
    point before their start (the USD's zero scale), and Free Bake leaves no
    empty, cache file or change behind."""
    got, _ = driven
    assert got["cache_applied"] == len(test_scene.DYNAMIC)
    for frame, objects in got["cache_frames"].items():
        for name, verts in objects.items():
            verts = np.array(verts)
            hidden = name.startswith("Drop") and int(frame) < test_scene.EMIT_FRAME
            if hidden:
                assert np.ptp(verts, axis=0).max() < 1e-9, (frame, name)
                continue
            keyed = np.array(got["frames"][frame][name]["vertices"])
            np.testing.assert_allclose(verts, keyed, atol=1e-4, err_msg=f"{frame} {name}")
    assert got["cache_left"] == [0, False, []]
    assert got["after_cache_free"] == got["before"]
