"""`dempipe check`: every example is safe to bake; an unstable scene is refused with
the warning and its fix; --json parses; no traceback ever."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from dempipe_cli.main import app

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((ROOT / "examples").glob("*.toml"))

UNSTABLE = """
[output]
fps = 24
duration = 0.5

[simulation]
sphere_diameter = 0.01
dt = 0.005                     # far above the critical step of these contacts

[materials.wood]
density = 700.0
restitution = 0.3
friction = 0.5

[shapes.crate]
builtin = "box"
size = [0.03, 0.03, 0.03]

[[bodies]]
name = "crates"
shape = "crate"
material = "wood"
layout = "grid"
origin = [0.0, 0.0, 0.02]
dims = [2, 1, 1]
spacing = 0.05

[[colliders]]
type = "plane"
material = "wood"
"""


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    """One sphere-set cache for the module: each example's shapes are voxelized once."""
    return tmp_path_factory.mktemp("check-cache")


@pytest.fixture(autouse=True)
def _cache_env(monkeypatch, cache_dir):
    monkeypatch.setenv("DEMPIPE_CACHE_DIR", str(cache_dir))


def run(*args):
    return CliRunner().invoke(app, list(args), catch_exceptions=False)


def test_examples_are_found():
    names = {p.name for p in EXAMPLES}
    assert "quickstart.toml" in names


@pytest.mark.parametrize("scene", EXAMPLES, ids=lambda p: p.name)
def test_every_example_is_safe_to_bake(scene):
    result = run("check", str(scene))
    assert result.exit_code == 0, result.output
    assert f"{scene.name}: OK" in result.output
    assert "Traceback" not in result.output
    assert "encountered in" not in result.output        # no numpy RuntimeWarning leaks
    assert "critical step" in result.output


def test_unstable_scene_exits_nonzero_with_the_warning_and_the_fix(tmp_path):
    scene = tmp_path / "unstable.toml"
    scene.write_text(UNSTABLE)
    result = run("check", str(scene))
    assert result.exit_code == 1, result.output
    out = result.output
    assert "unstable.toml: NOT SAFE" in out
    assert "error: unstable.toml: simulation.dt = 0.005 s is" in out
    assert 'fix: use dt = "auto"' in out
    assert "Traceback" not in out


def test_json_parses(tmp_path):
    scene = tmp_path / "unstable.toml"
    scene.write_text(UNSTABLE)
    result = run("check", str(scene), "--json", "--cache-dir", str(tmp_path / "c"))
    assert result.exit_code == 1
    data = json.loads(result.output)
    assert data["ok"] is False and data["bodies"] == 2
    assert data["findings"][0]["code"] == "dt-above-critical"
    assert data["findings"][0]["fix"]
    assert data["pairs"][0]["critical_dt_rotational"] > 0
    assert list((tmp_path / "c").glob("*.npz"))          # --cache-dir was used
    result = run("check", str(EXAMPLES[0]), "--json")
    assert result.exit_code == 0 and json.loads(result.output)["ok"] is True


def test_resolution_and_sphere_diameter_check_what_bake_would_bake(tmp_path):
    # the flags bake takes replace the scene's setting here too: the JSON's diameter
    # is the one given, and the resolution's gives more spheres than the scene's
    scene = tmp_path / "unstable.toml"
    scene.write_text(UNSTABLE.replace("dt = 0.005", "dt = \"auto\""))
    base = json.loads(run("check", str(scene), "--json", "--cache-dir",
                          str(tmp_path / "c")).output)
    assert base["diameter"] == pytest.approx(0.01)
    given = json.loads(run("check", str(scene), "--json", "--cache-dir", str(tmp_path / "c"),
                           "--sphere-diameter", "0.005").output)
    assert given["diameter"] == pytest.approx(0.005) and given["spheres"] > base["spheres"]
    res = json.loads(run("check", str(scene), "--json", "--cache-dir", str(tmp_path / "c"),
                         "--resolution", "6").output)
    assert res["diameter"] == pytest.approx(0.005)       # 6 across the 3 cm crate
    both = run("check", str(scene), "--resolution", "6", "--sphere-diameter", "0.005")
    assert both.exit_code == 2 and "--resolution or --sphere-diameter" in both.output


def test_scene_error_is_one_line_exit_2(tmp_path):
    scene = tmp_path / "bad.toml"
    scene.write_text(UNSTABLE.replace("density = 700.0", "density = -1.0"))
    proc = subprocess.run([sys.executable, "-m", "dempipe_cli.main", "check", str(scene)],
                          capture_output=True, text=True, env=dict(os.environ), timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1
    assert "Traceback" not in proc.stderr + proc.stdout


def test_real_subprocess_on_the_quickstart_imports_no_pxr_nor_numba():
    # The console entry point, as a user runs it. With the sphere sets cached (the
    # in-process run first fills the cache) the check imports neither pxr nor numba:
    # the frame-0 overlap is computed in NumPy. A cache miss imports numba (CPU
    # only) to voxelize; numba.cuda never.
    scene = ROOT / "examples" / "quickstart.toml"
    assert run("check", str(scene)).exit_code == 0
    code = ("import sys; from dempipe_cli.main import main\n"
            "try:\n    main(['check', sys.argv[1]])\n"
            "except SystemExit as e:\n    code = e.code\nelse:\n    code = 0\n"
            "bad = [m for m in ('pxr', 'numba', 'numba.cuda') if m in sys.modules]\n"
            "print('IMPORTED', bad, file=sys.stderr); sys.exit(code)")
    proc = subprocess.run([sys.executable, "-c", code, str(scene)],
                          capture_output=True, text=True, env=dict(os.environ), timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "quickstart.toml: OK" in proc.stdout
    assert "IMPORTED []" in proc.stderr
    assert "Traceback" not in proc.stderr
