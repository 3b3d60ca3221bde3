"""Both sphere-set modes of every built-in shape: spheres, envelope errors, build times.

    python benchmarks/sphere_modes.py [--resolutions 8 12 16] [--shapes pawn torus]
    python benchmarks/sphere_modes.py --scenes examples/quickstart.toml examples/chess.toml


Resolution = spheres across the shape's longest bounding-box extent. For each shape,
resolution and mode ("lattice", "surface"): the sphere count; the Hausdorff distance
between the mesh and the spheres' envelope and the bump height
(spheres.surface.envelope_errors), as fractions of the diameter d; the build time
cold (no cache; kernels compiled or loaded before timing) and cached (a hit in a
fresh SphereCache in a temporary folder). Prints a markdown table.

--scenes: the cost of each mode in whole scenes instead: for each scene and mode
(the scene's every shape forced to it), the contact spheres, the automatic step, and
the wall time of --steps steps from frame 0 after a 2-step warm-up, the modes
alternating --repeat times (best kept), so both see the same machine load. A bake's
cost is about (steps per simulated second) x (seconds per step).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time


def scene_cost(paths, steps, repeat):
    from dempipe.scene.build import Overrides, build_model
    from dempipe.spheres.cache import SphereCache
    from dempipe.scene.load import load_scene
    from dempipe.sim.simulator import Simulator

    cache = SphereCache()
    print("| scene | mode | bodies | spheres | dt [s] | steps per simulated s | "
          "s per step | x lattice per step | x lattice per simulated s |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for path in paths:
        scene = load_scene(path)
        models = {m: build_model(scene, cache=cache, overrides=Overrides(spheres=m))
                  for m in ("lattice", "surface")}
        sims = {m: Simulator(mo) for m, mo in models.items()}
        for m in models:
            sims[m].backend.step(models[m].initial_state(), 2)
        best = {m: float("inf") for m in models}
        for _ in range(repeat):
            for m in models:
                state = models[m].initial_state()
                t0 = time.perf_counter()
                sims[m].backend.step(state, steps)
                best[m] = min(best[m], (time.perf_counter() - t0) / steps)
        for m, mo in models.items():
            per_s = 1.0 / mo.dt
            ratio = best[m] / best["lattice"]
            print(f"| {os.path.basename(path)} | {m} | {mo.n_bodies} | {mo.n_spheres} | "
                  f"{mo.dt:.3g} | {per_s:.0f} | {best[m]:.4f} | {ratio:.2f} | "
                  f"{ratio * models['lattice'].dt / mo.dt:.2f} |", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[8, 12, 16])
    parser.add_argument("--shapes", nargs="+", default=None, help="default: all built-in shapes")
    parser.add_argument("--scenes", nargs="+", default=None, help="measure these scenes instead")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args(argv)
    if args.scenes:
        scene_cost(args.scenes, args.steps, args.repeat)
        return 0

    import numba

    from dempipe.mesh import shapes
    from dempipe.spheres.cache import SphereCache
    from dempipe.spheres.options import BuildOptions
    from dempipe.spheres.sphere_set import (
        build_sphere_set, build_sphere_set_with_info, diameter_for_resolution,
        mesh_for_errors)
    from dempipe.spheres.surface import envelope_errors

    box = shapes.build_shape("box")
    for mode in ("lattice", "surface"):               # compile / load the kernels
        s = build_sphere_set(box, 0.01, options=BuildOptions(mode=mode))
        envelope_errors(mesh_for_errors(box), s.centers + s.com, 0.01)

    names = args.shapes or [spec.name for spec in shapes.list_shapes()]
    print(f"<!-- {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numba {numba.__version__} ({numba.config.NUMBA_NUM_THREADS} threads) -->")
    print("| shape | across | mode | spheres | Hausdorff [d] | bump [d] | cold [s] | cached [s] |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        cache = SphereCache(tmp)
        for name in names:
            mesh = shapes.build_shape(name)
            rm = mesh_for_errors(mesh)
            for r in args.resolutions:
                d = diameter_for_resolution(mesh, r)
                for mode in ("lattice", "surface"):
                    opts = BuildOptions(mode=mode)
                    t0 = time.perf_counter()
                    s = build_sphere_set(mesh, d, options=opts)
                    cold = time.perf_counter() - t0
                    build_sphere_set_with_info(mesh, d, options=opts, cache=cache)
                    _, info = build_sphere_set_with_info(mesh, d, options=opts, cache=cache)
                    assert info.cache == "hit"
                    e = envelope_errors(rm, s.centers + s.com, d)
                    print(f"| {name} | {r} | {mode} | {s.count} | {e.hausdorff / d:.3f} | "
                          f"{e.bump / d:.3f} | {cold:.3f} | {info.seconds:.4f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
