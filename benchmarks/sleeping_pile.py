"""A large pile that sleeps but for a few bodies: what its steps cost.

    python benchmarks/sleeping_pile.py                      # 100k spheres
    python benchmarks/sleeping_pile.py --spheres 25000 --wake 20 --steps 300

The dense pile of benchmarks/cpu_bench.py (cubes of 3×3×3 spheres packed face to
face in a box, friction 0.5) with sleeping on (bodies sleep after 0.05 s at rest),
stepped until every cube sleeps; then the ``--wake`` highest cubes are woken and
nudged sideways (5 cm/s), and steps are timed from that same start twice,
alternated, REPEATS times:

* the baseline: the contact passes visit every chunk of sorted slots
  (``CpuBackend.quiet_share`` above 1), as before kernels.cpu.stages.stage_active;
* the default: once half the bodies are quiet, they visit only the chunks
  with a slot that is awake or touches an awake body (stage_active).

Printed: ms per step of each (the best of the runs), the ratio, bodies awake
during the timed steps, and whether the two runs end in the same State bit for
bit (they must: the spans leave out only visits that write nothing).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from cpu_bench import dense_pile  # noqa: E402

import numba  # noqa: E402

from dempipe.sim.simulator import Simulator  # noqa: E402

REPEATS = 3
#: How long a body must be at rest before it sleeps here [s]: short, so the pile
#: sleeps within a few thousand steps (the scene default is 0.5 s).
SLEEP_TIME = 0.05


def sleeping_pile(n_spheres: int):
    """cpu_bench's dense pile (about n_spheres spheres) with sleeping on."""
    return dense_pile(n_spheres, sleep=(None, None, SLEEP_TIME))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spheres", type=int, default=100_000, help="size of the pile")
    ap.add_argument("--wake", type=int, default=20, help="cubes woken on top of the pile")
    ap.add_argument("--steps", type=int, default=500, help="timed steps per run")
    args = ap.parse_args()
    model = sleeping_pile(args.spheres)
    nb = model.n_bodies
    print(f"# dempipe sleeping pile: {platform.machine()}, {os.cpu_count()} cores, numba "
          f"{numba.__version__}, {numba.get_num_threads()} threads; {model.n_spheres:,} "
          f"spheres, {nb:,} cubes, dt {model.dt:.3g} s")
    sim = Simulator(model, device="cpu")
    start = model.initial_state()
    settle = int(np.ceil(2 * SLEEP_TIME / model.dt))
    sim.backend.step(start, settle)
    asleep = int(start.asleep(model.sleep_steps)[:nb].sum())
    top = np.argsort(start.body_x[:nb, 2])[-args.wake:]
    start.body_rest[top] = 0
    start.body_P[top, 0] += model.body_mass[top] * 0.05
    print(f"after {settle:,} steps {asleep:,} of {nb:,} cubes asleep; {len(top)} woken")

    best = {}
    ends = {}
    awake = {}
    for _ in range(REPEATS):
        for name, share in (("every chunk (baseline)", 2.0), ("spans (default)", None)):
            backend = Simulator(model, device="cpu").backend
            if share is not None:
                backend.quiet_share = share
            state = start.copy()
            backend.step(state, 1)           # compile or load, and the first step's rebuild
            t0 = time.perf_counter()
            backend.step(state, args.steps)
            t = (time.perf_counter() - t0) / args.steps
            best[name] = min(best.get(name, t), t)
            ends[name] = state
            awake[name] = nb - int(state.asleep(model.sleep_steps)[:nb].sum())
    base = best["every chunk (baseline)"]
    a, b = ends["every chunk (baseline)"], ends["spans (default)"]
    same = all(np.array_equal(getattr(a, f), getattr(b, f))
               for f in ("body_x", "body_q", "body_P", "body_L", "body_rest",
                         "contact_partner", "contact_spring"))
    print("| contact passes over | ms/step | vs baseline | cubes awake at the end |")
    print("|---|---:|---:|---:|")
    for name in best:
        print(f"| {name} | {best[name] * 1e3:.3f} | {base / best[name]:.2f}x | {awake[name]:,} |")
    print(f"\nsame State bit for bit: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
