"""Sleeping: speed-up on a long settle, and the error it adds.

    python benchmarks/sleeping.py [--scene examples/quickstart.toml] [--duration 4]

Bakes the scene twice in the same run, sleeping off (the baseline) and on
(the scene's defaults), on the CPU, and prints wall time of the simulation,
the ratio, and what the settled piles look like: bodies asleep at the end,
pile height (highest body centre), centre of mass, spread (RMS distance of the
bodies from it), and the largest final displacement between the two runs as a
fraction of the sphere diameter (piles are chaotic, so the statistics are the
fair comparison; the displacement shows how far single bodies differ).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=os.path.join(os.path.dirname(__file__), "..",
                                                    "examples", "quickstart.toml"))
    ap.add_argument("--duration", type=float, default=4.0, help="simulated seconds")
    args = ap.parse_args()

    import numba

    from dempipe.scene.build import Overrides, build_model
    from dempipe.spheres.cache import SphereCache
    from dempipe.scene.load import load_scene
    from dempipe.sim.simulator import Simulator

    scene = load_scene(args.scene)
    cache = SphereCache()
    rows = {}
    for sleeping in (False, True):
        model = build_model(scene, cache=cache,
                            overrides=Overrides(duration=args.duration, sleeping=sleeping))
        sim = Simulator(model)
        warm = model.initial_state()
        sim.backend.step(warm, 2)                      # compile outside the timing
        state = model.initial_state()
        t0 = time.perf_counter()
        frames = sim.advance(state)
        wall = time.perf_counter() - t0
        up = -model.gravity / np.linalg.norm(model.gravity)
        x = frames.x[-1]
        com = x.mean(axis=0)
        rows[sleeping] = dict(
            wall=wall, x=x, asleep=int(state.asleep(model.sleep_steps)[: model.n_bodies].sum()),
            height=float((x @ up).max()), com=com,
            spread=float(np.sqrt(((x - com) ** 2).sum(axis=1).mean())),
            n=model.n_bodies, d=model.diameter, spheres=model.n_spheres,
            steps=sim.stats.steps)
    off, on = rows[False], rows[True]
    d = off["d"]
    print(f"# sleeping on a {args.duration:g} s settle: {os.path.basename(args.scene)}, "
          f"{off['n']} bodies, {off['spheres']} spheres, {off['steps']} steps; "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numba {numba.__version__}, {numba.config.NUMBA_NUM_THREADS} threads")
    print("| sleeping | wall s | speed-up | asleep at end | pile height m | centre of mass m "
          "| spread m |")
    print("|---|---:|---:|---:|---:|---|---:|")
    for key, r in ((False, off), (True, on)):
        print(f"| {'on' if key else 'off (baseline)'} | {r['wall']:.1f} | "
              f"{off['wall'] / r['wall']:.2f}x | {r['asleep']} / {r['n']} | {r['height']:.4f} | "
              f"({', '.join(f'{c:.4f}' for c in r['com'])}) | {r['spread']:.4f} |")
    disp = np.linalg.norm(on["x"] - off["x"], axis=1)
    print(f"\nfinal displacement on vs off: median {np.median(disp) / d:.2f} d, "
          f"max {disp.max() / d:.2f} d; pile height differs by "
          f"{abs(on['height'] - off['height']) / d:.2f} d, centre of mass by "
          f"{np.linalg.norm(on['com'] - off['com']) / d:.2f} d")


if __name__ == "__main__":
    sys.exit(main())
