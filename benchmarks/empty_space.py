"""Empty space costs nothing: the same piles, packed together or spread over a kilometre.

    python benchmarks/empty_space.py            # ~30k spheres
    python benchmarks/empty_space.py --quick    # ~8k spheres
    python benchmarks/empty_space.py --spheres 100000 --repeat 5

Two scenes with the same bodies and the same contacts: K small piles (2×2×2
cubes of 3×3×3 spheres, 216 spheres each) resting on a ground plane, either on a
lattice 0.2 m apart ("compact", a few metres across) or at random places over
1 km × 1 km ("spread"). The CPU backend's grid is a table of 8 buckets per
sphere whatever the extent; in the spread scene far cells share buckets and are
told apart by their keys. Printed: ms per step of each (best of ``--repeat``
alternating runs, so that both see the same machine load), the ratio spread /
compact, and the memory the backend holds for each.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
from bodies import box_set  # noqa: E402

D = 0.01
PILE_SPHERES = 8 * 27


def piles_model(n_piles: int, spread: float | None, seed: int = 0):
    """``n_piles`` piles of 2×2×2 touching cubes on the plane z = 0; pile anchors on
    a 0.2 m lattice (spread None) or uniform over spread × spread metres."""
    from dempipe.sim.materials import Material
    from dempipe.sim.builder import ModelBuilder

    if spread is None:
        side = int(np.ceil(np.sqrt(n_piles)))
        ij = np.stack(np.unravel_index(np.arange(n_piles), (side, side)), -1)
        anchors = ij * 0.2
    else:
        anchors = np.random.default_rng(seed).uniform(-spread / 2, spread / 2, (n_piles, 2))
    pitch = 3 * D
    cube = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(-1, 3) * pitch
    pos = (np.c_[anchors, np.zeros(n_piles)][:, None, :] + cube[None] + pitch / 2).reshape(-1, 3)
    ss, mesh = box_set(3, 3, 3, D)
    b = ModelBuilder(D)
    s = b.add_shape("cube", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.3, friction=0.5))
    b.add_bodies("cubes", s, m, pos)
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=60, n_frames=2)


def backend_bytes(backend) -> tuple[int, int]:
    """(bytes of the grid's bucket arrays, bytes of every array the backend holds)."""
    arrays = {k: v for k, v in vars(backend).items() if isinstance(v, np.ndarray)}
    grid = sum(v.nbytes for k, v in arrays.items() if k.startswith("bucket_"))
    return grid, sum(v.nbytes for v in arrays.values())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spheres", type=int, default=30_000, help="about this many spheres")
    parser.add_argument("--quick", action="store_true", help="about 8,000 spheres")
    parser.add_argument("--spread", type=float, default=1000.0, help="side of the spread [m]")
    parser.add_argument("--repeat", type=int, default=3, help="alternating timed runs of each")
    args = parser.parse_args(argv)

    import numba

    from dempipe.sim.simulator import Simulator

    n_piles = max(1, round((8_000 if args.quick else args.spheres) / PILE_SPHERES))
    scenes = {"compact": piles_model(n_piles, None), "spread": piles_model(n_piles, args.spread)}
    sims, states, best = {}, {}, {}
    for name, model in scenes.items():
        sims[name] = Simulator(model)
        states[name] = model.initial_state()
        sims[name].backend.step(states[name], 20)          # compile, settle the contacts
        best[name] = float("inf")
    n = scenes["compact"].n_spheres
    steps = max(5, int(2e6 / n))
    for _ in range(max(1, args.repeat)):
        for name in scenes:
            t0 = time.perf_counter()
            sims[name].backend.step(states[name], steps)
            best[name] = min(best[name], (time.perf_counter() - t0) / steps)

    print(f"<!-- {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}, numba {numba.__version__} "
          f"({numba.config.NUMBA_NUM_THREADS} threads); {steps} steps x {args.repeat} runs, best "
          f"-->")
    print("| scene | spheres | extent | grid bits (x, y, z) | bucket arrays | all backend arrays "
          "| ms/step | vs compact |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, model in scenes.items():
        x = states[name].body_x[: model.n_bodies]
        extent = float(np.ptp(x[:, :2], axis=0).max())
        be = sims[name].backend
        bx, by = int(be.grid[0]), int(be.grid[1])
        bz = int(np.log2(int(be.grid[5]))) - bx - by
        grid_b, all_b = backend_bytes(be)
        print(f"| {name} | {model.n_spheres:,} | {extent:,.1f} m | {bx}, {by}, {bz} | "
              f"{grid_b / 1e6:.2f} MB | {all_b / 1e6:.2f} MB | {best[name] * 1e3:.3f} | "
              f"{best[name] / best['compact']:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
