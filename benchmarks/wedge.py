"""A wedge of seeds on a local Dask cluster against the same bakes in a row in one process.

    python benchmarks/wedge.py                  # quickstart, 4 seeds, 0.5 s each
    python benchmarks/wedge.py --quick          # 0.125 s each
    python benchmarks/wedge.py --workers 2 --threads 1 --serial-threads 2 --repeat 2

The wedge: `dempipe.farm.wedge.wedge(scene, seeds=N)` on a LocalCluster of --workers
processes of --threads numba threads each (OMP_WAIT_POLICY=PASSIVE, as dempipe
starts it), timed from the call to its return: starting the cluster, loading the
kernels in each worker, the bakes and the table. Baseline, measured in the same
run: the same variants' scene files baked one after the other by
`dempipe.pipeline.bake.bake` in this process with --serial-threads threads, after one
warm-up bake (so the baseline pays no kernel loading; the wedge does). Printed:
both wall times, the sum of the bakes' own times on each side, and the ratio
(baseline / wedge: above 1, the wedge is faster). With --repeat the two alternate.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def scene_copy(src: Path, folder: Path, duration: float) -> Path:
    """``src`` with output.duration set (and relative meshes made absolute)."""
    from dempipe.farm.wedge import absolute_meshes, toml_loads, dumps_toml, set_key

    data = toml_loads(src.read_text(encoding="utf-8"))
    set_key(data, ("output", "duration"), duration)
    absolute_meshes(data, src.resolve().parent)
    out = folder / src.name
    out.write_text(dumps_toml(data), encoding="utf-8")
    return out


def serial(scene: Path, folder: Path, seeds: int, threads: int, cache) -> tuple[float, float]:
    """The wedge's variants baked in a row here: (wall seconds, sum of the bakes' seconds)."""
    from dempipe.pipeline.bake import bake
    from dempipe.farm.wedge import plan

    folder.mkdir(parents=True, exist_ok=True)
    _, variants = plan(scene, folder, seeds=seeds)
    for v in variants:
        v.scene.write_text(v.text, encoding="utf-8")
    t0 = time.perf_counter()
    total = 0.0
    for v in variants:
        r = bake(v.scene, v.output, device="cpu", threads=threads, cache=cache,
                 warn=lambda msg: None)
        total += r.report["wall_seconds"]
    return time.perf_counter() - t0, total


def farmed(scene: Path, folder: Path, seeds: int, workers: int, threads: int,
           cache_dir) -> tuple[float, float]:
    from dempipe.farm.wedge import wedge

    t0 = time.perf_counter()
    r = wedge(scene, folder, seeds=seeds, workers=workers, threads=threads, device="cpu",
              cache_dir=cache_dir)
    wall = time.perf_counter() - t0
    if r.failed:
        raise SystemExit(f"wedge failed: {r.failed[0].name}: {r.failed[0].status}")
    return wall, sum(v.wall_s for v in r.variants)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=os.path.join(ROOT, "examples", "quickstart.toml"))
    ap.add_argument("--duration", type=float, default=0.5, help="simulated seconds per bake")
    ap.add_argument("--quick", action="store_true", help="--duration 0.125")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="numba threads per worker")
    ap.add_argument("--serial-threads", type=int, default=2, help="threads of the baseline")
    ap.add_argument("--repeat", type=int, default=1, help="alternate wedge and baseline")
    args = ap.parse_args(argv)
    try:
        import distributed  # noqa: F401
    except ImportError:
        print('needs Dask: pip install "dempipe[farm]"', file=sys.stderr)
        return 2
    import numba

    from dempipe.pipeline.bake import bake
    from dempipe.spheres.cache import SphereCache

    duration = 0.125 if args.quick else args.duration
    with tempfile.TemporaryDirectory(prefix="dempipe-wedge-bench-") as tmp:
        tmp = Path(tmp)
        scene = scene_copy(Path(args.scene), tmp, duration)
        cache_dir = tmp / "cache"
        cache = SphereCache(cache_dir)
        # warm-up: sphere sets into the cache, the kernels compiled (or loaded) here
        (tmp / "warm").mkdir()
        warm = scene_copy(Path(args.scene), tmp / "warm", 2.0 / 24)
        bake(warm, tmp / "warm.usdc", device="cpu", threads=args.serial_threads, cache=cache,
             warn=lambda msg: None)
        env = {k: os.environ[k] for k in ("OMP_WAIT_POLICY", "NUMBA_NUM_THREADS")
               if k in os.environ}
        print(f"# {os.cpu_count()} cores, numba {numba.__version__}, {Path(args.scene).name}, "
              f"{args.seeds} seeds of {duration:g} s, this process's environment "
              f"{env or 'default'}", flush=True)
        print("| run | wedge: workers x threads | wedge wall s | its bakes' s | "
              f"in a row ({args.serial_threads} threads) wall s | their bakes' s | "
              "in a row / wedge |", flush=True)
        print("|---:|---|---:|---:|---:|---:|---:|", flush=True)
        t_all = time.perf_counter()
        for k in range(args.repeat):       # alternate: the machine's load changes
            w = farmed(scene, tmp / f"wedge{k}", args.seeds, args.workers, args.threads,
                       cache_dir)
            s = serial(scene, tmp / f"serial{k}", args.seeds, args.serial_threads, cache)
            print(f"| {k + 1} | {args.workers} x {args.threads} | {w[0]:.1f} | {w[1]:.1f} | "
                  f"{s[0]:.1f} | {s[1]:.1f} | {s[0] / w[0]:.2f}x |", flush=True)
        print(f"# {time.perf_counter() - t_all:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
