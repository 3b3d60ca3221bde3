"""Measure sphere-set errors and build times of every built-in shape; print a markdown table.

    python benchmarks/sphere_table.py [--resolutions 8 12 20] [--repeat 3]

Resolution = spheres across the shape's longest bounding-box extent. The cache is not
used; the winding-number kernel is compiled (or loaded from numba's cache) once before
timing. Build time is the best of --repeat runs of build_sphere_set.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[8, 12, 20])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--shapes", nargs="+", default=None, help="default: all built-in shapes")
    args = parser.parse_args(argv)

    import numba

    from dempipe.mesh import shapes
    from dempipe.spheres.sphere_set import build_sphere_set, diameter_for_resolution

    t0 = time.perf_counter()
    build_sphere_set(shapes.build_shape("box"), 0.01)  # compile / load the kernel
    warmup = time.perf_counter() - t0

    names = args.shapes or [spec.name for spec in shapes.list_shapes()]
    print(f"<!-- {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numba {numba.__version__} ({numba.config.NUMBA_NUM_THREADS} threads), "
          f"first build incl. kernel load {warmup:.2f} s -->")
    print("| shape | faces | spheres across | d [mm] | spheres | volume error | inertia error | build [s] |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in names:
        mesh = shapes.build_shape(name)
        for res in args.resolutions:
            d = diameter_for_resolution(mesh, res)
            best = float("inf")
            for _ in range(max(1, args.repeat)):
                t = time.perf_counter()
                s = build_sphere_set(mesh, d, name=name)
                best = min(best, time.perf_counter() - t)
            print(f"| {name} | {len(mesh.faces)} | {res} | {1000 * d:.3g} | {s.count} | "
                  f"{100 * s.sphere_volume_error:+.2f}% | {100 * s.inertia_error:.2f}% | {best:.3f} |")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
