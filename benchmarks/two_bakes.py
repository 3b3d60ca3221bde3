"""Two bakes at once on one machine: the dense pile alone against two copies running together.

    python benchmarks/two_bakes.py                       # default threading settings
    OMP_WAIT_POLICY=PASSIVE python benchmarks/two_bakes.py

Each copy is a fresh process stepping the dense pile of benchmarks/cpu_bench.py
(25 k spheres) in 60-step calls and printing its best ms/step of five. Baseline,
measured in the same run: one copy alone. Printed: ms/step alone, ms/step of each
of the two copies together, and the slowdown against the ideal (two copies on
the same cores should each take twice as long as one alone). The environment
(numba's thread count, OpenMP's wait policy) is passed on to the copies.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))

CHILD = r"""
import sys, time
sys.path.insert(0, {here!r}); sys.path.insert(0, {tests!r})
from cpu_bench import dense_pile
from dempipe.sim.kernels.cpu.backend import CpuBackend
model = dense_pile(30000)
be = CpuBackend(model); st = model.initial_state(); be.step(st, 60)
best = min(((lambda t0: (be.step(st, 60), time.perf_counter() - t0)[1])(time.perf_counter())
            for _ in range(5)))
print(best / 60 * 1e3)
"""


def run(copies: int) -> list[float]:
    """ms/step of each of ``copies`` processes started together."""
    code = CHILD.format(here=HERE, tests=os.path.join(HERE, "..", "tests"))
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
             for _ in range(copies)]
    return [float(p.communicate()[0].strip().splitlines()[-1]) for p in procs]


def main(argv=None) -> int:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)
    import numba

    run(1)                                     # compile (or load) the kernels once
    t0 = time.perf_counter()
    alone = run(1)[0]
    together = run(2)
    env = {k: os.environ[k] for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "NUMBA_NUM_THREADS")
           if k in os.environ}
    print(f"# {os.cpu_count()} cores, numba {numba.__version__} ({numba.config.NUMBA_NUM_THREADS} "
          f"threads), environment {env or 'default'}, {time.perf_counter() - t0:.0f} s")
    print("| copies | ms/step of each | vs alone | vs the ideal (2× alone) |")
    print("|---:|---|---:|---:|")
    print(f"| 1 | {alone:.2f} | 1.00× | |")
    print(f"| 2 | {' / '.join(f'{t:.2f}' for t in together)} | "
          f"{max(together) / alone:.2f}× | {max(together) / (2 * alone):.2f}× |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
