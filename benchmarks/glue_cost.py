"""Glue: what a glued object costs against the same pieces unglued, and the bonds' memory.

    python benchmarks/glue_cost.py [--scene examples/wall_breach.toml] [--duration 2]

Bakes the scene twice in the same run on the CPU, its glue off (the baseline: every
``[[bodies]] glue = true`` group set to false, the same pieces as separate bodies)
and as written, and prints the wall time of the simulation, the ratio, the bonds
broken, and the memory the bonds take: the Model's bond arrays (sim/glue.py Bonds),
the State's bond_broken and bond_shear, and the step's scratch (glue_f per bonded
pair, body_glue per body), against the sphere arrays the two runs share.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=os.path.join(os.path.dirname(__file__), "..",
                                                    "examples", "wall_breach.toml"))
    ap.add_argument("--duration", type=float, default=None,
                    help="simulated seconds (default: the scene's)")
    args = ap.parse_args()

    import numba
    import numpy as np

    from dempipe.scene.build import Overrides, build_model
    from dempipe.scene.load import load_scene
    from dempipe.sim.kernels.layout import cpu_scratch
    from dempipe.sim.simulator import Simulator
    from dempipe.spheres.cache import SphereCache

    scene = load_scene(args.scene)
    if not any(g.glue for g in scene.bodies):
        print(f"{args.scene}: no [[bodies]] group has glue = true: nothing to compare",
              file=sys.stderr)
        return 2
    unglued = dataclasses.replace(
        scene, bodies=tuple(dataclasses.replace(g, glue=False) for g in scene.bodies))
    cache = SphereCache()
    rows = {}
    for name, sc in (("unglued", unglued), ("glued", scene)):
        model = build_model(sc, cache=cache, overrides=Overrides(duration=args.duration))
        sim = Simulator(model)
        sim.backend.step(model.initial_state(), 2)     # compile outside the timing
        state = model.initial_state()
        t0 = time.perf_counter()
        sim.advance(state)
        wall = time.perf_counter() - t0
        bonds = model.bonds
        mem = 0
        if bonds is not None:
            mem = sum(a.nbytes for a in dataclasses.astuple(bonds))
            mem += state.bond_broken.nbytes + state.bond_shear.nbytes
            scratch = cpu_scratch(model, friction=True)
            mem += sum(scratch[k][0][0] * scratch[k][0][1] * np.dtype(scratch[k][1]).itemsize
                       for k in ("glue_f", "body_glue"))
        spheres = (model.sphere_offset.nbytes + model.sphere_body.nbytes
                   + (state.contact_spring.nbytes if state.contact_spring is not None else 0))
        rows[name] = dict(
            wall=wall, steps=sim.stats.steps, n=model.n_bodies, spheres=model.n_spheres,
            bonds=0 if bonds is None else bonds.n_bonds,
            pairs=0 if bonds is None else bonds.n_pairs,
            broken=0 if bonds is None else int(state.bond_broken.sum()),
            asleep=int(state.asleep(model.sleep_steps)[: model.n_bodies].sum()),
            mem=mem, sphere_mem=spheres)
    off, on = rows["unglued"], rows["glued"]
    print(f"# glue on {os.path.basename(args.scene)}: {on['n']} pieces, {on['spheres']} "
          f"spheres, {on['bonds']} bonds of {on['pairs']} sphere pairs, {on['steps']} steps; "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numba {numba.__version__}, {numba.config.NUMBA_NUM_THREADS} threads")
    print("| | wall s | cost | asleep at end | bonds broken | bond memory |")
    print("|---|---:|---:|---:|---:|---:|")
    print(f"| unglued (baseline) | {off['wall']:.1f} | 1.00x | {off['asleep']} / {off['n']} "
          "| - | - |")
    per = on["mem"] / max(on["pairs"], 1)
    print(f"| glued | {on['wall']:.1f} | {on['wall'] / off['wall']:.2f}x | "
          f"{on['asleep']} / {on['n']} | "
          f"{on['broken']} / {on['bonds']} | {on['mem'] / 1024:.1f} KiB "
          f"({per:.0f} B per bonded pair) |")
    print(f"\nthe bonds' memory is {on['mem'] / on['sphere_mem']:.3f} of the sphere offsets, "
          f"bodies and contact histories ({on['sphere_mem'] / 2 ** 20:.1f} MiB)")


if __name__ == "__main__":
    sys.exit(main())
