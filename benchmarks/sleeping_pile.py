"""A large pile that sleeps but for a few bodies: what its steps cost.

    python benchmarks/sleeping_pile.py                      # 100k spheres
    python benchmarks/sleeping_pile.py --spheres 25000 --wake 20 --steps 300
    python benchmarks/sleeping_pile.py --chess 4096 --at 2.0 --steps 1000   # minutes

The dense pile of benchmarks/cpu_bench.py (cubes of 3×3×3 spheres packed face to
face in a box, friction 0.5) with sleeping on (bodies sleep after 0.05 s at rest),
stepped until every cube sleeps; then the ``--wake`` highest cubes are woken and
nudged sideways (``--speed``, 5 cm/s), and steps are timed from that same start,
the variants alternated, REPEATS times:

* the baseline: the contact passes visit every slot with something in reach
  (kernels.cpu.stages.stage_busy) and the patch pass every body with one
  (``CpuBackend.quiet_share`` above 1), as without kernels.cpu.stages.stage_active,
  and every rebuild sorts the slots again and searches every list
  (``CpuBackend.keep_share`` 0);
* active slots: once half the bodies are quiet, the passes visit only those of
  them that are awake or touch an awake body (stage_active); rebuilds as the
  baseline's;
* the default: active slots, and a rebuild that few moved spheres force keeps the
  slots and searches again only the lists that can change (stage_slot_marks).

With ``--chess N`` the pile is instead N pieces of benchmarks/vs_bullet.py's chess
scene (examples/chess.toml) ``--at`` seconds into their bake, nothing woken: a
pile that falls asleep a piece at a time, a few still sliding and tipping.

Printed: ms per step of each (the best of the runs), the ratio, bodies awake
during the timed steps, rebuilds that kept the slots, and whether the runs end in
the same State bit for bit (they must: stage_active leaves out only visits that write
nothing, and the lists kept are those a search would find).
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
    ap.add_argument("--speed", type=float, default=0.05,
                    help="sideways speed given to the woken cubes [m/s] (default 0.05)")
    ap.add_argument("--chess", type=int, metavar="N",
                    help="instead: N pieces of benchmarks/vs_bullet.py's chess scene, timed "
                         "from --at seconds into their bake (its sleeping tail; long: 4,096 "
                         "pieces take minutes to get there)")
    ap.add_argument("--at", type=float, default=2.0, help="with --chess: when [s]")
    args = ap.parse_args()
    if args.chess:
        from dempipe.spheres.cache import SphereCache
        from vs_bullet import dempipe_model

        model = dempipe_model(args.chess, args.at + 1.0, SphereCache())
        what = f"chess pieces at {args.at:g} s"
    else:
        model = sleeping_pile(args.spheres)
        what = "cubes"
    nb = model.n_bodies
    print(f"# dempipe sleeping pile: {platform.machine()}, {os.cpu_count()} cores, numba "
          f"{numba.__version__}, {numba.get_num_threads()} threads; {model.n_spheres:,} "
          f"spheres, {nb:,} {what}, dt {model.dt:.3g} s")
    sim = Simulator(model, device="cpu")
    start = model.initial_state()
    if args.chess:
        settle = int(round(args.at / model.dt))
        sim.backend.step(start, settle)
        asleep = int(start.asleep(model.sleep_steps)[:nb].sum())
        print(f"after {settle:,} steps {asleep:,} of {nb:,} pieces asleep")
    else:
        settle = int(np.ceil(2 * SLEEP_TIME / model.dt))
        sim.backend.step(start, settle)
        asleep = int(start.asleep(model.sleep_steps)[:nb].sum())
        top = np.argsort(start.body_x[:nb, 2])[-args.wake:]
        start.body_rest[top] = 0
        start.body_P[top, 0] += model.body_mass[top] * args.speed
        print(f"after {settle:,} steps {asleep:,} of {nb:,} cubes asleep; {len(top)} woken")

    best = {}
    ends = {}
    awake = {}
    kept = {}
    variants = (("every busy slot, full rebuilds (baseline)", 2.0, 0.0),
                ("active slots, full rebuilds", None, 0.0),
                ("active slots, kept slots (default)", None, None))
    for _ in range(REPEATS):
        for name, share, keep in variants:
            backend = Simulator(model, device="cpu").backend
            if share is not None:
                backend.quiet_share = share
            if keep is not None:
                backend.keep_share = keep
            state = start.copy()
            backend.step(state, 1)           # compile or load, and the first step's rebuild
            k0 = int(backend.span_ctl[2])
            t0 = time.perf_counter()
            backend.step(state, args.steps)
            t = (time.perf_counter() - t0) / args.steps
            best[name] = min(best.get(name, t), t)
            ends[name] = state
            awake[name] = nb - int(state.asleep(model.sleep_steps)[:nb].sum())
            kept[name] = int(backend.span_ctl[2]) - k0
    base = best[variants[0][0]]
    a = ends[variants[0][0]]
    same = all(np.array_equal(getattr(a, f), getattr(ends[name], f))
               for name, _, _ in variants[1:]
               for f in ("body_x", "body_q", "body_P", "body_L", "body_rest",
                         "contact_partner", "contact_spring"))
    print("| passes, rebuilds | ms/step | vs baseline | bodies awake at the end "
          "| rebuilds that kept the slots |")
    print("|---|---:|---:|---:|---:|")
    for name in best:
        print(f"| {name} | {best[name] * 1e3:.3f} | {base / best[name]:.2f}x | {awake[name]:,} "
              f"| {kept[name]} |")
    print(f"\nsame State bit for bit: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
