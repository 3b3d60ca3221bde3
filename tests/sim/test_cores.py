"""A CPU bake's threads follow the cores other processes leave (dempipe.sim.cores):
a real busy neighbour takes a core away, a thread count the user chose is kept, and
changing the count between stepping calls never changes the frames.

The suite's workers run one numba thread each (conftest.py), which is a choice a
CoreShare keeps; so the tests of what it changes run in a fresh interpreter with
NUMBA_NUM_THREADS unset, as a user's bake runs."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from dempipe.sim.cores import CoreShare, threads_for

HERE = Path(__file__).resolve().parent


def run_free(code: str) -> list[str]:
    """stdout words of ``code`` in a fresh interpreter, numba free to use every core."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    env["PYTHONPATH"] = os.pathsep.join([str(HERE), str(HERE.parent), env.get("PYTHONPATH", "")])
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return proc.stdout.split()


@pytest.mark.parametrize("others, cores_, most, want", [
    (0.0, 2, 2, 2),          # alone: every thread
    (0.1, 2, 2, 2),          # a little noise is not a neighbour
    (0.35, 2, 2, 1),         # a third of a core already makes one of ours wait
    (1.0, 2, 2, 1),          # a second bake at one core
    (3.7, 2, 2, 1),          # never fewer than one
    (1.0, 16, 8, 8),         # at most what numba may use
    (9.2, 16, 16, 7),
])
def test_threads_are_the_cores_the_others_leave(others, cores_, most, want):
    assert threads_for(others, cores_, most) == want


def test_a_busy_neighbour_takes_a_core_away():
    out = run_free("""
import subprocess, sys, time
from dempipe.sim import cores
share = cores.CoreShare()
if not share.enabled:
    print("skip", share.most); raise SystemExit
burn = subprocess.Popen([sys.executable, "-c", "while True: pass"])
try:
    time.sleep(0.3)                          # the neighbour is running
    share.adjust()
    time.sleep(cores.INTERVAL + 0.2)         # a window in which it used a whole core
    n = share.adjust()
finally:
    burn.kill(); burn.wait()
print(n, share.most, share.cores, share.changes)
""")
    if out[0] == "skip":
        pytest.skip(f"numba may use {out[1]} thread(s) here: nothing to share")
    n, most, ncores, changes = map(int, out)
    # the neighbour used a core: this process steps with the others at most (other
    # processes on the machine may take more, never less)
    assert n <= max(1, min(most, ncores - 1))
    assert changes >= (1 if n < most else 0)


def test_a_chosen_thread_count_is_kept():
    assert CoreShare(fixed=True).enabled is False
    code = ("from dempipe.sim.cores import CoreShare; s = CoreShare(); "
            "print(s.enabled, s.adjust())")
    env = dict(os.environ, NUMBA_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == ["False", "1"]


def test_frames_do_not_depend_on_when_the_thread_count_changes():
    # a bake's thread count changes between stepping calls as neighbours come and go:
    # one thread, two, alternating call by call, give the same State bit for bit
    out = run_free("""
import numba, numpy as np
from test_simulation import cluster_model
from dempipe.sim.kernels.cpu.backend import CpuBackend
if numba.config.NUMBA_NUM_THREADS < 2:
    print("skip"); raise SystemExit
model = cluster_model(n=20)
ends = []
for plan in ((2,) * 12, (1,) * 12, (1, 2) * 6, (2, 2, 1, 2, 1, 1) * 2):
    be = CpuBackend(model); st = model.initial_state()
    for n in plan:
        numba.set_num_threads(n)
        be.step(st, 25)
    ends.append(st)
same = all(np.array_equal(getattr(ends[0], k), getattr(e, k))
           for e in ends[1:] for k in ("body_x", "body_q", "body_P", "body_L"))
moved = float(np.abs(ends[0].body_x - model.initial_state().body_x).max())
print(same, moved > 0)
""")
    if out[0] == "skip":
        pytest.skip("one core: one thread")
    assert out == ["True", "True"]
