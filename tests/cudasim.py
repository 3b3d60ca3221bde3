"""Running a CUDA test file as a script: under Numba's CUDA simulator (the parity
checks, which compare it with the CPU bit for bit) or on a real GPU.

A test file that uses this has a ``--sim`` entry point printing one JSON line;
``simulator_results`` runs it in a fresh process, since NUMBA_ENABLE_CUDASIM must be
set before numba is imported.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent


def cuda_env(sim: bool) -> dict:
    """The environment of a CUDA test process: the simulator on or off, one CPU
    thread unless the caller chose, and tests/sim, tests and the checkout importable."""
    env = dict(os.environ)
    env.pop("NUMBA_ENABLE_CUDASIM", None)
    if sim:
        env["NUMBA_ENABLE_CUDASIM"] = "1"
    env.setdefault("NUMBA_NUM_THREADS", "1")
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS / "sim"), str(TESTS), str(ROOT),
                                         env.get("PYTHONPATH", "")])
    return env


def simulator_results(script: str, timeout: float) -> dict:
    """``python script --sim`` under the simulator: the JSON of its last output line
    (the test fails with the script's output if it does not finish cleanly)."""
    proc = subprocess.run([sys.executable, str(Path(script).resolve()), "--sim"],
                          env=cuda_env(sim=True), capture_output=True, text=True,
                          timeout=timeout)
    if proc.returncode != 0:
        pytest.fail(f"simulator script failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])
