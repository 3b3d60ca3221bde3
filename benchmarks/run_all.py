"""Run every CPU benchmark in one command, each in its quick form, one after another.

    python benchmarks/run_all.py             # quick forms, about 4 minutes on 2 cores
    python benchmarks/run_all.py --full      # the sizes docs/performance.md quotes (long)
    python benchmarks/run_all.py --only cpu_bench,startup

Each benchmark is its own script (see its docstring) and prints its own table with
ratios against a baseline measured in the same run; this runner only starts them in
fresh interpreters (so one's compiled kernels or threads do not colour the next)
and stops with a non-zero status if any of them failed. vs_bullet needs pybullet
(``pip install 'dempipe[bench]'``); without it that row says so and is skipped.
gpu_bench.py is left out: it needs a CUDA GPU (run it alone where there is one);
cuda_compile_table.py too: it times nothing (tests/sim/test_cuda_compile.py runs it); and
ab_trees.py and quickstart_bake.py, which compare two source trees.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))

#: name -> (quick arguments, full arguments)
BENCHMARKS = {
    "cpu_bench": (["--quick"], []),
    "profile_stages": (["--steps", "30"], []),
    "specialize": ([], []),
    "surface_spheres": ([], []),
    "empty_space": (["--quick"], []),
    "startup": (["--repeat", "2"], []),
    "output_size": (["--quick"], []),
    "sleeping": (["--duration", "2"], []),
    "glue_cost": (["--duration", "1"], []),
    "sleeping_pile": (["--spheres", "25000", "--steps", "300"], []),
    "asleep_frames": (["--repeat", "1"], []),
    "restitution_vs_dt": ([], []),
    "steps_per_contact": (["--quick", "--steps", "10"], []),
    "vs_bullet": (["--n", "256", "--duration", "1"], ["--n", "256,1024,4096"]),
    "two_bakes": ([], []),
    "sphere_table": (["--resolutions", "8", "--repeat", "1"], []),
    "wedge": (["--quick"], []),
    "sphere_modes": (["--resolutions", "8", "--shapes", "sphere", "box"], []),
    "surface_rolling": (["--shapes", "ball", "--resolutions", "8", "--spacings", "0.3",
                         "--restitutions", "0.5"], []),
    "bake_memory": (["--balls", "400", "--durations", "1", "10", "--overhead", "--repeat", "1"],
                    ["--overhead"]),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--full", action="store_true", help="the full sizes, not the quick forms")
    ap.add_argument("--only", default=None, help="comma-separated benchmark names")
    args = ap.parse_args()
    names = list(BENCHMARKS)
    if args.only:
        names = [n.strip() for n in args.only.split(",") if n.strip()]
        unknown = [n for n in names if n not in BENCHMARKS]
        if unknown:
            print(f"unknown benchmark(s): {', '.join(unknown)} (known: {', '.join(BENCHMARKS)})",
                  file=sys.stderr)
            return 2
    failed = []
    for name in names:
        script = os.path.join(HERE, f"{name}.py")
        if not os.path.exists(script):
            print(f"\n## {name}: not present, skipped", flush=True)
            continue
        argv = BENCHMARKS[name][1 if args.full else 0]
        cmd = [sys.executable, script, *argv]
        print(f"\n## {name}: python benchmarks/{name}.py {' '.join(argv)}".rstrip(), flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call(cmd)
        print(f"({name}: exit {rc}, {time.perf_counter() - t0:.0f} s)", flush=True)
        if rc == 2 and name == "vs_bullet":
            continue                     # pybullet missing: said so above
        if rc != 0:
            failed.append(name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
