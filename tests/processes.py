"""Real `dempipe` processes and what they write: start one, wait on its checkpoints,
compare the USD it wrote sample by sample (shared by the fault and USD-input tests)."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from pxr import Sdf

from dempipe.pipeline.lock import work_dir


def env(cache: Path) -> dict:
    e = dict(os.environ)
    e["DEMPIPE_CACHE_DIR"] = str(cache)
    e["PYTHONUNBUFFERED"] = "1"
    return e


def dempipe(*args, cache, **kw):
    return subprocess.Popen([sys.executable, "-m", "dempipe_cli.main", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env(cache), **kw)


def run(*args, cache, timeout=600):
    p = dempipe(*args, cache=cache)
    out, err = p.communicate(timeout=timeout)
    return p.returncode, out, err


def samples(path) -> dict:
    """Every attribute's default and time samples in the file, as numpy arrays."""
    layer = Sdf.Layer.FindOrOpen(str(path))
    out = {}

    def visit(p):
        if not p.IsPropertyPath():
            return
        spec = layer.GetAttributeAtPath(p)
        if spec is None:
            return
        if spec.default is not None:
            out[(str(p), "default")] = np.array(spec.default)
        for t in layer.ListTimeSamplesForPath(p):
            out[(str(p), t)] = np.array(layer.QueryTimeSample(p, t))

    layer.Traverse(layer.pseudoRoot.path, visit)
    return out


def assert_same_samples(a, b):
    sa, sb = samples(a), samples(b)
    assert sa.keys() == sb.keys()
    for k in sa:
        assert sa[k].dtype == sb[k].dtype and np.array_equal(sa[k], sb[k]), k


def frames_done(out: Path) -> int:
    try:
        return json.loads((work_dir(out) / "meta.json").read_text())["frames_done"]
    except (OSError, ValueError, KeyError):
        return -1


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far [s] (/proc/PID/stat)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_for(cond, proc, timeout=300.0):
    t0 = time.monotonic()
    while not cond():
        if proc.poll() is not None:
            raise AssertionError(f"dempipe exited early ({proc.returncode}): "
                                 f"{proc.stderr.read()}")
        if time.monotonic() - t0 > timeout:
            proc.kill()
            raise AssertionError("timed out waiting")
        time.sleep(0.02)


def run_python(code: str, threads: int | None = None, timeout: float = 600) -> str:
    """Run ``code`` in a fresh interpreter (the tests' helpers importable) with numba
    given ``threads`` threads; its stdout. A test of what the thread count changes runs
    its threads here: the suite's own workers run one thread each (conftest.py)."""
    env = dict(os.environ)
    if threads is not None:
        env["NUMBA_NUM_THREADS"] = str(threads)
    here = Path(__file__).resolve().parent
    env["PYTHONPATH"] = os.pathsep.join([str(here), str(here / "sim"), env.get("PYTHONPATH", "")])
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return proc.stdout
