"""Two bakes at once on one machine: each scene alone against two copies running
together, with the CPU threads fixed and following the load, in one run.

    python benchmarks/two_bakes.py [--scenes pile small quickstart] [--window 4]

numba's parallel loops run on libgomp here, whose idle threads spin for milliseconds
between a step's parallel regions: a copy spinning on a core that the other copy's
thread needs wastes that core, so two bakes at once can each be far slower than twice
one alone. Modes (each row of the table):

- fixed: every core's thread all the time, libgomp's own wait (what a bake did
  before its threads followed the load; the baseline of the last column);
- shared: what a bake does now: between stepping calls dempipe.sim.cores.CoreShare
  sets the thread count to the cores the other processes leave;
- passive: every thread, OMP_WAIT_POLICY=PASSIVE (threads sleep at once), for
  comparison;
- one: one thread per copy (NUMBA_NUM_THREADS=1): what the machine itself gives two
  processes at once, whatever the threading. Its "vs the ideal" column is the ideal
  for one-thread copies on their own cores, 1× alone; above it is the cores'
  shared caches, memory and, on a VM, the host.

For each scene and mode, fresh processes build the scene and warm up, then all start
together and step the same 30 steps over and over for a window of seconds, printing
their mean ms/step: one copy alone, then two copies at once. Printed per row: alone,
each of the two together, the slowdown against the ideal (two copies on the same
cores should each take twice as long as one alone), and alone against the fixed
mode's alone (same run). Scenes:

- pile: the dense pile of benchmarks/cpu_bench.py, 25 k spheres;
- small: the same pile at 2.7 k spheres (a step of ~0.3 ms: the parallel regions
  follow each other within microseconds, where the threads' wait matters most);
- quickstart: examples/quickstart.toml stepped from frame 0.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

CHILD = r"""
import sys, time
sys.path.insert(0, {here!r}); sys.path.insert(0, {tests!r})
from dempipe.sim.cores import CoreShare
from dempipe.sim.kernels.cpu.backend import CpuBackend
scene = {scene!r}
if scene == "quickstart":
    from dempipe.scene.build import build_model
    from dempipe.scene.load import load_scene
    model = build_model(load_scene({quickstart!r}))
else:
    from cpu_bench import dense_pile
    model = dense_pile(30000 if scene == "pile" else 3000)
be = CpuBackend(model); st = model.initial_state(); be.step(st, 60)
share = CoreShare(fixed={mode!r} != "shared")
print("ready", flush=True)
sys.stdin.readline()                     # every copy starts timing at once
steps, t0 = 0, time.perf_counter()
while time.perf_counter() - t0 < {window}:
    share.adjust()
    s = st.copy(); be.step(s, 30); steps += 30   # the same 30 steps, over and over
print((time.perf_counter() - t0) / steps * 1e3, share.threads)
"""

MODES = ("fixed", "shared", "passive", "one")


def environment(mode: str) -> dict:
    """The child's environment: the parent's, OpenMP's wait as the mode says."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "NUMBA_NUM_THREADS")}
    if mode == "passive":
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    if mode == "one":
        env["NUMBA_NUM_THREADS"] = "1"
    return env


def run(scene: str, copies: int, mode: str, window: float) -> list[tuple[float, int]]:
    """(mean ms/step, threads at the end) of each of ``copies`` processes stepping
    ``scene`` over the same ``window`` seconds: each builds and warms up, then all
    start timing together."""
    code = CHILD.format(here=HERE, tests=os.path.join(ROOT, "tests"), scene=scene,
                        quickstart=os.path.join(ROOT, "examples", "quickstart.toml"),
                        window=window, mode=mode)
    procs = [subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True, env=environment(mode))
             for _ in range(copies)]
    for p in procs:
        assert p.stdout.readline().strip() == "ready"
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    out = []
    for p in procs:
        ms, threads = p.communicate()[0].split()
        out.append((float(ms), int(threads)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["pile", "small", "quickstart"],
                    choices=["pile", "small", "quickstart"])
    ap.add_argument("--modes", nargs="+", default=list(MODES[:3]), choices=MODES)
    ap.add_argument("--window", type=float, default=4.0,
                    help="seconds each copy steps for, the copies' windows aligned")
    args = ap.parse_args(argv)
    import numba

    t0 = time.perf_counter()
    for scene in args.scenes:
        run(scene, 1, "fixed", 0.5)             # compile (or load) the kernels once
    print(f"# {os.cpu_count()} cores, {platform.processor() or platform.machine()}, numba "
          f"{numba.__version__} ({numba.config.NUMBA_NUM_THREADS} threads)")
    print("| scene | mode | alone ms/step (threads at the end) | each of two at once | "
          "vs the ideal (2× alone) | alone vs fixed's |")
    print("|---|---|---:|---|---:|---:|")
    for scene in args.scenes:
        base = None
        for mode in args.modes:
            (alone, n_alone), = run(scene, 1, mode, args.window)
            together = run(scene, 2, mode, args.window)
            base = alone if base is None else base
            each = " / ".join(f"{ms:.3f} ({n})" for ms, n in together)
            worst = max(ms for ms, _ in together)
            ideal = alone if mode == "one" else 2 * alone
            print(f"| {scene} | {mode} | {alone:.3f} ({n_alone}) | {each} | {worst / ideal:.2f}× | "
                  f"{base / alone:.2f}× |", flush=True)
    print(f"# {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
