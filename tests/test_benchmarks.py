"""The benchmark scripts start as a user runs them: ``python benchmarks/NAME.py``.

Run that way, Python puts benchmarks/ first on sys.path, so a script named
after a standard-library module hides it from every library the benchmarks
import (benchmarks/concurrent.py once hid ``concurrent.futures`` from trimesh,
and every benchmark that voxelized a mesh failed). No timing is measured here.
"""

import os
import subprocess
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
BENCH = os.path.join(HERE, "..", "benchmarks")
SCRIPTS = sorted(f[:-3] for f in os.listdir(BENCH) if f.endswith(".py"))


def test_no_script_hides_a_standard_module():
    hidden = sorted(set(SCRIPTS) & set(sys.stdlib_module_names))
    assert not hidden, f"benchmarks/ scripts named after standard modules: {hidden}"


def test_run_all_lists_every_script():
    sys.path.insert(0, BENCH)
    try:
        import run_all
    finally:
        sys.path.remove(BENCH)
    # gpu_bench needs a CUDA GPU, perf_samples Linux perf, cuda_compile_table ptxas,
    # ab_trees and quickstart_bake two source trees (tools, not benchmarks), blender_drive
    # Blender as a Python module (bpy): run alone
    helpers = {"run_all", "gpu_bench", "perf_samples", "cuda_compile_table", "ab_trees",
               "quickstart_bake", "blender_drive"}
    missing = set(SCRIPTS) - set(run_all.BENCHMARKS) - helpers
    assert not missing, f"benchmarks not run by run_all.py: {sorted(missing)}"
    unknown = set(run_all.BENCHMARKS) - set(SCRIPTS)
    assert not unknown, f"run_all.py names scripts that do not exist: {sorted(unknown)}"


@pytest.mark.parametrize("name", [s for s in SCRIPTS if s != "run_all"])
def test_script_starts(name):
    # --help imports everything the script imports, from benchmarks/ as sys.path[0]
    r = subprocess.run([sys.executable, os.path.join(BENCH, f"{name}.py"), "--help"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "usage" in r.stdout.lower()
