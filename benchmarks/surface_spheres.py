"""Surface spheres for contact: sphere counts before and after, speed, and motion.

    python benchmarks/surface_spheres.py [--resolutions 6 12 24] [--steps 400] [--repeat 2]

1. For every built-in shape (default parameters) at each resolution (spheres across
   the longest extent): all spheres, and the ones kept for contacts with
   contact_layers = 1 and 2 (spheres.surface_mask).
2. Steps two scenes on the CPU from frame 0, with contact_layers = "all" (0, the
   baseline) and 1 alternating in the same run, and prints time per step, the
   ratio, how far bodies travelled, and the largest difference in body position and
   orientation between the two runs (0 when no sphere ever touched a buried one:
   then the report's errors are unchanged too):
   - quickstart: examples/quickstart.toml (chess pieces falling into a tray) with
     its resolution raised to --scene-resolution;
   - blocks: a generated scene, a 4 x 4 x 2 grid of boxes and balls resting in a
     tray, side by side and stacked two high, at --scene-resolution (solid bodies, the best case).
Kernels are compiled by a 2-step warm-up outside the timing.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))

BLOCKS = """
[output]
fps = 24
duration = 1.0
[simulation]
resolution = {res}
stiffness_target_overlap = 0.05
[materials.wood]
density = 700.0
restitution = 0.3
friction = 0.5
[shapes.box]
builtin = "box"
[shapes.ball]
builtin = "sphere"
[[bodies]]
name = "blocks"
shape = ["box", "ball"]
material = "wood"
layout = "grid"
origin = [-0.066, -0.066, 0.0201]
dims = [4, 4, 2]
spacing = {spacing}
[[colliders]]
type = "box"
min = [-0.1, -0.1, 0.0]
max = [0.1, 0.1, 0.2]
material = "wood"
"""


def counts_table(resolutions, cache):
    from dempipe.mesh.shapes import SHAPES, build_shape
    from dempipe.spheres.sphere_set import (
        build_sphere_set, diameter_for_resolution, surface_mask)

    print("| shape | spheres across | all spheres | contact_layers = 1 | kept | "
          "contact_layers = 2 | kept |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name in sorted(SHAPES):
        mesh = build_shape(name)
        for r in resolutions:
            s = build_sphere_set(mesh, diameter_for_resolution(mesh, r), name=name, cache=cache)
            k1 = int(surface_mask(s.centers, s.diameter, 1).sum())
            k2 = int(surface_mask(s.centers, s.diameter, 2).sum())
            print(f"| {name} | {r} | {s.count} | {k1} | {100 * k1 / s.count:.0f}% | "
                  f"{k2} | {100 * k2 / s.count:.0f}% |")


def build(scene, layers, res, cache):
    from dempipe.scene.build import Overrides, build_model

    return build_model(scene, cache=cache, overrides=Overrides(
        resolution=res, contact_layers=layers, sleeping=False))


def speed(name, scene, steps, res, cache, repeat):
    """Best of ``repeat`` timings of ``steps`` steps from frame 0, baseline and
    thinned alternating (so both see the same machine load)."""
    from dempipe.sim.simulator import Simulator

    models = {layers: build(scene, layers, res, cache) for layers in (0, 1)}
    sims = {layers: Simulator(m) for layers, m in models.items()}
    for layers in (0, 1):                                 # compile outside the timing
        sims[layers].backend.step(models[layers].initial_state(), 2)
    best = {0: float("inf"), 1: float("inf")}
    states = {}
    for _ in range(repeat):
        for layers in (0, 1):
            state = models[layers].initial_state()
            t0 = time.perf_counter()
            sims[layers].backend.step(state, steps)
            best[layers] = min(best[layers], time.perf_counter() - t0)
            states[layers] = state
    m0, m1 = models[0], models[1]
    d = m0.diameter
    dx = float(np.abs(states[1].body_x - states[0].body_x).max()) / d
    dq = float(np.abs(states[1].body_q - states[0].body_q).max())
    moved = float(np.abs(states[0].body_x - m0.initial_x).max()) / d
    print(f"| {name} | {m0.n_bodies} | {res} | {steps} ({steps * m0.dt * 1e3:.1f} ms) | "
          f"{m0.n_spheres} | {1e3 * best[0] / steps:.2f} | {m1.n_spheres} | "
          f"{1e3 * best[1] / steps:.2f} | {best[0] / best[1]:.2f}x | {moved:.2f} d | "
          f"{dx:.2g} d | {dq:.2g} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--resolutions", type=int, nargs="+", default=[6, 12, 24])
    ap.add_argument("--scene-resolution", type=int, default=12)
    ap.add_argument("--steps", type=int, default=400, help="steps timed per run")
    ap.add_argument("--repeat", type=int, default=2, help="timings per run (best kept)")
    args = ap.parse_args()

    import numba

    from dempipe.spheres.cache import SphereCache
    from dempipe.scene.load import load_scene, parse_scene

    cache = SphereCache()
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}, numba {numba.__version__}, "
          f"{numba.config.NUMBA_NUM_THREADS} threads")
    print("\n## sphere counts (built-in shapes, default parameters)\n")
    counts_table(args.resolutions, cache)

    print(f"\n## speed: contact_layers = \"all\" (baseline) vs 1, CPU, sleeping off, "
          f"best of {args.repeat}\n")
    print("| scene | bodies | res | steps (simulated) | spheres (all) | ms/step | "
          "spheres (1 layer) | ms/step | speed-up | largest travel | max diff x | max diff q |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    quick = load_scene(os.path.join(HERE, "..", "examples", "quickstart.toml"))
    speed("quickstart", quick, args.steps, args.scene_resolution, cache, args.repeat)
    blocks = parse_scene(BLOCKS.format(res=args.scene_resolution, spacing=0.04),
                         os.path.join(HERE, "blocks.toml"))
    speed("blocks", blocks, args.steps, args.scene_resolution, cache, args.repeat)


if __name__ == "__main__":
    sys.exit(main())
