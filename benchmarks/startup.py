"""Start-up times: the CLI, `import dempipe`, `dempipe check`, and a first bake step.

    python benchmarks/startup.py              # warm rows: best of 3
    python benchmarks/startup.py --repeat 5

Every row is a fresh interpreter (``sys.executable``), timed from spawn to exit.
"cold" points NUMBA_CACHE_DIR at a new, empty folder, so numba compiles every
kernel the command needs; "warm" reruns the same command with that folder as the
cold run left it (numba loads the compiled kernels from disk). Commands that never
import numba have nothing to compile: their two columns differ only by noise.

Rows:
  dempipe --help                        the click application, no subcommand imported
  import dempipe                        the package (lazy: no numba, no pxr)
  dempipe check (sphere sets cached)    stability analysis; NumPy only
  dempipe check (sphere cache empty)    voxelizes pawn and rook first (numba CPU kernel)
  first bake step                       load + build the quickstart Model (sphere sets
                                        cached), Simulator, one step: the kernels'
                                        compile (cold) or cache load (warm)

The first bake step is broken down in a second table (times measured inside the
child). The sphere-set cache is a temporary folder (DEMPIPE_CACHE_DIR), filled once
before the timed rows that say "cached". Python bytecode is written and reused as a
user's Python does (PYTHONDONTWRITEBYTECODE is removed from the children's
environment), and a throw-away run before the timed ones fills it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "examples" / "quickstart.toml"

CLI = [sys.executable, "-m", "dempipe_cli.main"]

BAKE_STEP = """
import json, sys, time
t0 = time.perf_counter()
from dempipe.scene.build import build_model
from dempipe.spheres.cache import SphereCache
from dempipe.scene.load import load_scene
from dempipe.sim.simulator import Simulator
t1 = time.perf_counter()
model = build_model(load_scene(sys.argv[1]), cache=SphereCache())
t2 = time.perf_counter()
sim = Simulator(model, device="cpu")
state = model.initial_state()
sim.backend.step(state, 1)
t3 = time.perf_counter()
sim.backend.step(state, 1)
t4 = time.perf_counter()
print(json.dumps(dict(imports=t1 - t0, build=t2 - t1, first_step=t3 - t2, second_step=t4 - t3,
                      spheres=model.n_spheres)))
"""


def run(cmd, env) -> tuple[float, str]:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT, timeout=1800)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"startup: {' '.join(map(str, cmd))} failed ({proc.returncode}):\n"
                         f"{proc.stderr[-2000:]}")
    return seconds, proc.stdout


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="warm runs per row (best is shown)")
    args = parser.parse_args(argv)

    import numba

    with tempfile.TemporaryDirectory(prefix="dempipe-startup-") as tmp:
        tmp = Path(tmp)
        base = {k: v for k, v in os.environ.items()
                if k not in ("PYTHONDONTWRITEBYTECODE", "NUMBA_CACHE_DIR", "DEMPIPE_CACHE_DIR")}
        counter = iter(range(1_000_000))

        def env(numba_dir: Path, sphere_dir: Path | None = None) -> dict:
            e = dict(base, NUMBA_CACHE_DIR=str(numba_dir))
            e["DEMPIPE_CACHE_DIR"] = str(sphere_dir or tmp / f"spheres-{next(counter)}")
            return e

        cached_spheres = tmp / "spheres-filled"
        # fill the sphere-set cache and Python's bytecode, untimed
        run(CLI + ["check", str(SCENE)], env(tmp / "numba-fill", cached_spheres))
        run([sys.executable, "-c", BAKE_STEP, str(SCENE)], env(tmp / "numba-fill", cached_spheres))

        rows = [
            ("dempipe --help", "python -m dempipe_cli.main --help", CLI + ["--help"], True),
            ("import dempipe", 'python -c "import dempipe"',
             [sys.executable, "-c", "import dempipe"], True),
            ("dempipe check (sphere sets cached)",
             "python -m dempipe_cli.main check examples/quickstart.toml",
             CLI + ["check", str(SCENE)], True),
            ("dempipe check (sphere cache empty)",
             "DEMPIPE_CACHE_DIR=<empty> python -m dempipe_cli.main check examples/quickstart.toml",
             CLI + ["check", str(SCENE)], False),
            ("first bake step (quickstart)",
             "python -c BAKE_STEP examples/quickstart.toml (benchmarks/startup.py)",
             [sys.executable, "-c", BAKE_STEP, str(SCENE)], True),
        ]
        results, bake = [], {}
        for k, (name, shown, cmd, use_cached) in enumerate(rows):
            numba_dir = tmp / f"numba-{k}"
            sphere_dir = cached_spheres if use_cached else None
            cold, out = run(cmd, env(numba_dir, sphere_dir))
            if name.startswith("first bake"):
                bake["cold"] = json.loads(out.strip().splitlines()[-1])
            warm = []
            for _ in range(max(1, args.repeat)):
                s, out = run(cmd, env(numba_dir, sphere_dir))
                warm.append(s)
                if name.startswith("first bake"):
                    w = json.loads(out.strip().splitlines()[-1])
                    if "warm" not in bake or w["first_step"] < bake["warm"]["first_step"]:
                        bake["warm"] = w
            results.append((name, shown, cold, min(warm), statistics.median(warm)))
            print(f"# {name}: cold {cold:.2f} s, warm {min(warm):.2f} s", file=sys.stderr,
                  flush=True)

    print(f"<!-- {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}, numba {numba.__version__} "
          f"({numba.config.NUMBA_NUM_THREADS} threads); warm = best of {args.repeat} -->")
    print("| what | command | cold Numba cache [s] | warm Numba cache [s] (median) |")
    print("|---|---|---:|---:|")
    for name, shown, cold, best, median in results:
        print(f"| {name} | `{shown}` | {cold:.2f} | {best:.2f} ({median:.2f}) |")
    print()
    print(f"First bake step, inside the child (quickstart, {bake['cold']['spheres']:,} spheres):")
    print()
    print("| phase | cold [s] | warm [s] |")
    print("|---|---:|---:|")
    for phase, label in (("imports", "imports (dempipe.scene.build, .scene, .simulator)"),
                         ("build", "load scene + build Model (sphere sets cached)"),
                         ("first_step", "Simulator + first step (compile or cache load)"),
                         ("second_step", "second step")):
        print(f"| {label} | {bake['cold'][phase]:.3f} | {bake['warm'][phase]:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
