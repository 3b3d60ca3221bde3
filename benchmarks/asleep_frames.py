"""What a pile asleep costs a frame: calls skipped on the host against the kernels.

    python benchmarks/asleep_frames.py [--scene examples/chess.toml] [--spheres lattice]
                                       [--duration 3] [--repeat 2]

Bakes the scene on the CPU a call per frame (as a bake's calls go once its steps are
cheap: Simulator.run), with the backend's ``skip_idle`` off (the baseline: every call steps once to find that every
body sleeps, rebuilding every sphere's list) and on (a call that starts with every
body asleep and nothing moving is skipped outright: sim.backend.nothing_moves),
alternating, in the same run. Prints the whole bake's stepping time, that of the
frames after the last body fell asleep, their ratio, and whether the two bakes'
frames are bit-identical (they must be).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np


def bake(model, skip_idle):
    """(frames (x, q per frame), seconds per frame) of one bake."""
    from dempipe.sim.simulator import Simulator

    sim = Simulator(model)
    sim.backend.skip_idle = skip_idle
    warm = model.initial_state()
    sim.backend.step(warm, 2)                      # compile outside the timing
    state = model.initial_state()
    seconds, xs, qs, asleep = [], [], [], []
    for _ in range(model.n_frames - 1):
        t0 = time.perf_counter()
        sim.backend.step(state, model.steps_per_frame)
        seconds.append(time.perf_counter() - t0)
        xs.append(state.body_x.copy())
        qs.append(state.body_q.copy())
        asleep.append(bool(state.asleep(model.sleep_steps)[: model.n_bodies].all()))
    return np.array(xs), np.array(qs), np.array(seconds), np.array(asleep)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=os.path.join(os.path.dirname(__file__), "..",
                                                    "examples", "chess.toml"))
    ap.add_argument("--spheres", default=None, help="lattice, surface or auto (default: "
                    "the scene's)")
    ap.add_argument("--duration", type=float, default=None, help="simulated seconds "
                    "(default: the scene's)")
    ap.add_argument("--repeat", type=int, default=2, help="bakes of each, alternating")
    args = ap.parse_args()

    import numba

    from dempipe.scene.build import Overrides, build_model
    from dempipe.scene.load import load_scene

    model = build_model(load_scene(args.scene),
                        overrides=Overrides(spheres=args.spheres, duration=args.duration))
    print(f"# {platform.machine()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}, "
          f"numba {numba.__version__} ({numba.get_num_threads()} threads)")
    print(f"{args.scene}: {model.n_bodies:,} bodies, {model.n_spheres:,} spheres, "
          f"{model.n_frames - 1} frames of {model.steps_per_frame} steps")
    runs = {False: [], True: []}
    for _ in range(args.repeat):
        for skip in (False, True):
            runs[skip].append(bake(model, skip))
    base = runs[False][0]
    same = all(np.array_equal(a[0], base[0]) and np.array_equal(a[1], base[1])
               for a in runs[False] + runs[True])
    first = int(np.argmax(base[3])) if base[3].any() else len(base[3])
    print(f"every body asleep from frame {first + 1}" if first < len(base[3])
          else "never all asleep: nothing to skip")
    print("| skip_idle | bake [s] | asleep frames [s] | per asleep frame [ms] |")
    print("|---|---:|---:|---:|")
    med = {}
    for skip in (False, True):
        tot = [r[2].sum() for r in runs[skip]]
        tail = [r[2][first + 1:].sum() for r in runs[skip]]
        n_tail = max(1, len(base[2]) - first - 1)
        med[skip] = (float(np.median(tot)), float(np.median(tail)))
        print(f"| {'on' if skip else 'off (baseline)'} | "
              + "-".join(f"{t:.2f}" for t in sorted(tot)) + " | "
              + "-".join(f"{t:.3f}" for t in sorted(tail)) + " | "
              + f"{1e3 * med[skip][1] / n_tail:.2f} |")
    print(f"bake: {med[False][0] / med[True][0]:.2f}x, asleep frames: "
          f"{med[False][1] / max(med[True][1], 1e-9):.1f}x; frames bit-identical: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
