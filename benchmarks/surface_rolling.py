"""How well round sphere sets roll: error against the closed form, by resolution,
surface spacing and restitution, with the sphere count against the lattice.

    python benchmarks/surface_rolling.py
    python benchmarks/surface_rolling.py --shapes ball --resolutions 8 --spacings 0.2 0.3 0.5 \
        --restitutions 0.2 0.5 0.9 --threads 2

Each row is report.accuracy.incline_rolling_error: a ball, or a cylinder on its side,
0.1 m across, released on a 20° slope (tilted gravity over a plane), μ = 0.9, no
rolling friction, density 700, automatic stiffness and dt (10 steps per contact),
its acceleration fitted to x(t) from 0.03 to 0.5 s (by when it rolls at about
1.2 m/s). Printed: a / a_closed − 1 (a_closed = 5/7 g sin θ for the ball, 2/3 g sin θ
for the cylinder), the spheres of the set and of the lattice of the same diameter,
and the largest rise of the body's centre above where it started (resting on the
plane): a rise larger than the envelope's bumps means the body left the plane.
The first row of each shape is the lattice (spacing "-"). ``--floor body`` rolls it on a
static slab of spheres built in the same mode and spacing instead of the plane: its
spheres against the slab's, as bodies roll on each other. Accuracy only: no timing.
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys

import numba


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=["ball", "cylinder"])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[8, 16])
    parser.add_argument("--spacings", type=float, nargs="+", default=[0.2, 0.3, 0.5])
    parser.add_argument("--restitutions", type=float, nargs="+", default=[0.5, 0.9])
    parser.add_argument("--floor", choices=["plane", "body"], default="plane",
                        help="roll on a wall (plane) or on a static slab of spheres of the "
                             "same mode and spacing (body)")
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()
    if args.threads:
        numba.set_num_threads(args.threads)

    from dempipe.report import accuracy as acc
    from dempipe.sim.materials import Material

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip() or "unknown"
    print(f"commit {commit}, {platform.machine()}, python {sys.version.split()[0]}, "
          f"{numba.get_num_threads()} threads")
    print("| body | across | spacing [d] | e | spheres | ÷ lattice | a / a₀ − 1 | "
          "largest rise [d] |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for shape in args.shapes:
        for res in args.resolutions:
            d = acc.INCLINE_BALL / res
            lattice = None
            runs = [("lattice", None)] + [("surface", sp) for sp in args.spacings]
            for mode, spacing in runs:
                for e in args.restitutions:
                    material = Material("wood", density=700, restitution=e, friction=0.9,
                                        rolling_friction=0.0)
                    run = acc.incline_run(material, res, mode, acc.DtRule(), shape=shape,
                                          spacing=spacing, floor=args.floor)
                    z = run.frames.x[:, 0, 2][run.frames.times >= acc.INCLINE_FIT_FROM]
                    if mode == "lattice":
                        lattice = run.spheres
                    print(f"| {shape} | {res} | {'-' if spacing is None else spacing} | {e} | "
                          f"{run.spheres} | {run.spheres / lattice:.2f} | "
                          f"{run.accel / run.closed - 1.0:+.3f} | "
                          f"{(z.max() - run.rest_z) / d:.3f} |", flush=True)


if __name__ == "__main__":
    main()
