"""Inputs that once escaped as internal errors or misleading messages: each one gets
one line naming the key or file and the fix, before any big allocation or simulation."""

import json
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest

from dempipe.errors import MeshError, SceneError, StabilityError
from dempipe.scene.load import load_scene

BASE = """
[output]
fps = {fps}
duration = {duration}

[simulation]
resolution = {resolution}
stiffness_target_overlap = {overlap}
gravity = [0.0, 0.0, {g}]

[shapes.ball]
builtin = "sphere"
diameter = 0.1

[[bodies]]
name = "balls"
shape = "ball"
layout = "{layout}"
{place}
velocity = [0.0, 0.0, {vz}]

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
"""


def scene_text(**kw):
    v = dict(fps=24, duration=0.1, resolution=3, overlap=0.05, g=-9.81, layout="single",
             place="position = [0.0, 0.0, 0.1]", vz=0.0)
    v.update(kw)
    return BASE.format(**v)


def cli(*args, cache, env_extra=None, timeout=600):
    env = dict(os.environ, DEMPIPE_CACHE_DIR=str(cache), **(env_extra or {}))
    p = subprocess.run([sys.executable, "-m", "dempipe_cli.main", *map(str, args)],
                       capture_output=True, text=True, env=env, timeout=timeout)
    return p.returncode, p.stdout, p.stderr


@pytest.mark.parametrize("change, key", [
    (dict(layout="grid", place="origin = [0, 0, 0.1]\ndims = [1000, 1000, 1000]\n"
                              "count = 1000000000\nspacing = 0.2"), "bodies[0].count"),
    (dict(resolution=1000000), "simulation.resolution"),
    (dict(fps=100000000), "output.fps"),
    (dict(duration=1e9), "output.duration"),
    (dict(duration=0.01), "output.duration"),       # under half a frame: frame 0 alone
    (dict(vz=-1e300), "velocity"),
    (dict(g=-1e30), "simulation.gravity"),
    (dict(overlap=1e-9), "simulation.stiffness_target_overlap"),
])
def test_absurd_sizes_refused_before_allocating(tmp_path, change, key):
    # `check` and `bake` both refuse, in one line naming the key, before the big
    # allocation (not a MemoryError or a ZeroDivisionError).
    from dempipe.pipeline.bake import bake
    from dempipe.spheres.cache import SphereCache
    from dempipe.pipeline.check import analyze_scene

    scene = tmp_path / "s.toml"
    scene.write_text(scene_text(**change))
    cache = SphereCache(tmp_path / "cache")
    try:
        report = analyze_scene(scene, cache=cache)
        refused = [f.message + " " + f.fix for f in report.errors]
        assert refused, "check said OK"
        text = " ".join(refused)
    except (StabilityError, SceneError) as exc:     # a scene value beyond reason: at the door
        text = str(exc)
    assert key in text, text
    with pytest.raises((StabilityError, SceneError),
                       match=key.replace("[", r"\[").replace("]", r"\]")):
        bake(scene, tmp_path / "o.usdc", device="cpu", cache=cache)
    assert not (tmp_path / "o.usdc").exists()


def test_spheres_lattice_refused(tmp_path):
    for opt, val in (("-r", "1e6"), ("-d", "1e-6")):
        code, _, err = cli("spheres", "box", opt, val, "--no-cache", cache=tmp_path)
        assert code == 3 and "Traceback" not in err and "MemoryError" not in err, err
        assert ("--resolution" if opt == "-r" else "--diameter") in err
        assert len(err.strip().splitlines()) == 1


def test_corrupt_binary_stl_named(tmp_path):
    import trimesh

    from dempipe.mesh.shapes import load_mesh

    good = tmp_path / "box.stl"
    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(good)
    data = good.read_bytes()
    bad = tmp_path / "cut.stl"
    bad.write_bytes(data[: len(data) - 30])           # a transfer cut short
    with pytest.raises(MeshError, match="damaged binary STL") as e:
        load_mesh(bad)
    assert "charset" not in str(e.value)
    assert len(load_mesh(good).faces) == 12


def test_shape_errors_name_the_scene_file_and_key(tmp_path):
    # the mesh's own message (its file, the problem) behind the scene's file and key,
    # as every other scene error: a scene with several meshes says which shape it was
    from dempipe.errors import ShapeError
    from dempipe.scene.build import build_model

    (tmp_path / "empty.obj").write_bytes(b"")
    scene = tmp_path / "s.toml"
    for shape, words in [('mesh = "empty.obj"', r"s.toml: shapes.ball: .*empty.obj: file is "
                                                r"empty \(export the mesh again\)"),
                         ('builtin = "torus"\nmajor_radius = 0.005\nminor_radius = 0.01',
                          "s.toml: shapes.ball: shape 'torus': minor_radius must be smaller")]:
        scene.write_text(scene_text().replace('builtin = "sphere"\ndiameter = 0.1', shape))
        with pytest.raises(ShapeError, match=words):
            build_model(load_scene(scene))


def test_mesh_path_that_is_a_folder(tmp_path):
    (tmp_path / "m.stl").mkdir()
    scene = tmp_path / "s.toml"
    scene.write_text(scene_text().replace('builtin = "sphere"\ndiameter = 0.1',
                                          'mesh = "m.stl"'))
    with pytest.raises(SceneError, match="is a folder, not a mesh file"):
        load_scene(scene)


def test_cache_entry_replaced_by_folder_is_mended(tmp_path):
    import trimesh

    from dempipe.spheres.cache import SphereCache
    from dempipe.spheres.sphere_set import build_sphere_set, sphere_set_key

    cache = SphereCache(tmp_path / "c")
    mesh = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    first = build_sphere_set(mesh, 0.01, cache=cache)
    path = cache.path_for(sphere_set_key(mesh, 0.01))
    path.unlink()
    path.mkdir()
    with pytest.warns(UserWarning, match="was a folder"):
        again = build_sphere_set(mesh, 0.01, cache=cache)
    assert path.is_file() and np.array_equal(again.centers, first.centers)
    path.unlink()
    path.mkdir()
    assert cache.clear() == 1 and not path.exists()


def test_mesh_collider_initial_state_warns_nothing(tmp_path):
    from dempipe.scene.build import build_model
    from dempipe.spheres.cache import SphereCache

    scene = tmp_path / "s.toml"
    scene.write_text(scene_text() + '\n[[colliders]]\ntype = "mesh"\nname = "ramp"\n'
                     'builtin = "box"\nsize = [0.3, 0.3, 0.02]\n'
                     'position = [0.5, 0.0, 0.01]\n')
    model = build_model(load_scene(scene), cache=SphereCache(tmp_path / "c"))
    assert model.n_static == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        state = model.initial_state()
    assert np.all(state.body_P[model.n_bodies:] == 0.0) and np.isfinite(state.body_P).all()


def chattr(flag, path):
    return subprocess.run(["chattr", flag, str(path)], capture_output=True).returncode == 0


def test_unwritable_cache_dir_same_for_every_command(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(scene_text())
    locked = tmp_path / "locked"
    locked.mkdir()
    if not chattr("+i", locked):
        pytest.skip("chattr +i is not supported here")
    try:
        for args in (("spheres", "box", "-r", "4"), ("check", scene),
                     ("bake", scene, "-o", tmp_path / "o.usdc")):
            code, _, err = cli(*args, "--cache-dir", locked, cache=tmp_path / "c")
            assert code == 2 and "not writable" in err and str(locked) in err, (args, err)
    finally:
        chattr("-i", locked)


def test_spheres_output_into_missing_folder(tmp_path):
    out = tmp_path / "new" / "deeper" / "box.npz"
    code, _, err = cli("spheres", "box", "-r", "3", "-o", out, "--no-cache", cache=tmp_path)
    assert code == 0 and out.is_file(), err


def test_report_into_a_missing_folder_is_written_there(tmp_path):
    # the folder is made at the end, as -o's is: a long bake does not fail on it
    scene = tmp_path / "s.toml"
    scene.write_text(scene_text(duration=0.05))
    report = tmp_path / "new" / "deeper" / "r.json"
    code, _, err = cli("bake", scene, "-o", tmp_path / "o.usdc", "-q", "--report", report,
                       cache=tmp_path)
    assert code == 0, err
    assert json.loads(report.read_text())["frames"] == 2


def test_debug_after_the_subcommand_shows_the_traceback(tmp_path):
    missing = tmp_path / "missing.toml"
    for args in (("check", missing, "--debug"), ("--debug", "check", missing)):
        code, _, err = cli(*args, cache=tmp_path)       # the exit code as without it
        assert code == 2 and "Traceback" in err and "file not found" in err, err
        assert err.strip().splitlines()[-1].startswith("error: ")
    code, _, err = cli("check", missing, cache=tmp_path)
    assert code == 2 and "Traceback" not in err and err.count("\n") == 1, err


def test_resolution_and_sphere_diameter_flags_together_name_the_flags(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(scene_text())
    code, _, err = cli("bake", scene, "-o", tmp_path / "o.usdc", "--resolution", "5",
                       "--sphere-diameter", "0.01", cache=tmp_path)
    assert code == 2 and "--resolution or --sphere-diameter" in err, err
    assert "Traceback" not in err and not (tmp_path / "o.usdc").exists()


def test_check_json_on_bad_input_is_json(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(scene_text().replace("fps = 24", "fps = -3"))
    code, out, err = cli("check", scene, "--json", cache=tmp_path)
    doc = json.loads(out)
    assert code == 2 and doc["ok"] is False and "output.fps" in doc["error"]


def test_auto_device_quiet_and_threads_clamped(tmp_path):
    # device = "auto" on a machine without a GPU: no warning, the summary says
    # where it ran; --threads above what numba may use: a note,
    # then the bake runs with what there is.
    scene = tmp_path / "s.toml"
    scene.write_text(scene_text(duration=0.05))
    code, _, err = cli("bake", scene, "-o", tmp_path / "o.usda", "--threads", "4",
                       cache=tmp_path / "c", env_extra={"NUMBA_NUM_THREADS": "1"})
    assert code == 0, err
    assert "CUDA" not in err
    assert "--threads 4: only 1 available here" in err
    assert "on the CPU (1 thread)" in err, err
