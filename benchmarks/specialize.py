"""Specialized vs general CPU kernels: ms per step, same run.

    python benchmarks/specialize.py [--balls 3000] [--boxes 400] [--steps 400] [--repeat 3]

Scenes: a frictionless pile of one-sphere balls (specialized: no friction, no
rotation) and a frictionless pile of 2×2×2-sphere boxes (no friction). Each is
stepped first to settle into contact, then timed through the general kernel
(every feature compiled in, runtime checks) and the specialized one, from the
same State; the ratio general / specialized is the speed-up. Both kernels are
warmed (compiled or loaded from numba's cache) before timing.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from bodies import ball_set, box_set  # noqa: E402

from dempipe.sim.materials import Material  # noqa: E402
from dempipe.sim.builder import ModelBuilder  # noqa: E402
from dempipe.sim.kernels.cpu.backend import CpuBackend  # noqa: E402

D = 0.01


def pile(n, shape):
    b = ModelBuilder(D)
    ss, mesh = ball_set(D) if shape == "ball" else box_set(2, 2, 2, D)
    s = b.add_shape(shape, mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.0))
    pitch = 1.05 * D if shape == "ball" else 2.1 * D
    side = max(1, int(round(n ** (1 / 3))))
    rng = np.random.default_rng(0)
    pos = [[(i % side) * pitch + rng.uniform(0, 0.1 * D), (i // side % side) * pitch,
            0.5 * pitch + (i // (side * side)) * pitch] for i in range(n)]
    b.add_bodies(shape, s, m, pos)
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=24, n_frames=2)


def ms_per_step(backend, state, steps):
    st = state.copy()
    backend.step(st, 2)                    # warm (compile or load from the cache)
    t0 = time.perf_counter()
    backend.step(st, steps)
    return (time.perf_counter() - t0) / steps * 1e3, st


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--balls", type=int, default=3000)
    ap.add_argument("--boxes", type=int, default=400)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    rows = []
    for name, n, shape in (("balls, frictionless", a.balls, "ball"),
                           ("2x2x2 boxes, frictionless", a.boxes, "box")):
        model = pile(n, shape)
        spec = CpuBackend(model)
        gen = CpuBackend(model, specialize=False)
        state = model.initial_state()
        spec.step(state, 300)              # settle into contact
        tg, ts = [], []
        for _ in range(a.repeat):          # alternate, keep the best of each (noisy hosts)
            t, sg = ms_per_step(gen, state, a.steps)
            tg.append(t)
            t, ss = ms_per_step(spec, state, a.steps)
            ts.append(t)
        tg, ts = min(tg), min(ts)
        same = all(np.array_equal(getattr(sg, f), getattr(ss, f))
                   for f in ("body_x", "body_q", "body_P", "body_L"))
        rows.append((name, model.n_bodies, model.n_spheres, spec.flags, tg, ts, same))
    print(f"{'scene':28s} {'bodies':>6s} {'spheres':>7s} {'flags (F,R,S,W)':>16s} "
          f"{'general':>9s} {'special':>9s} {'ratio':>6s}  same")
    for name, nb, ns, flags, tg, ts, same in rows:
        fl = "".join("1" if f else "0" for f in flags)
        print(f"{name:28s} {nb:6d} {ns:7d} {fl:>16s} {tg:7.3f}ms {ts:7.3f}ms "
              f"{tg / ts:6.2f}  {same}")


if __name__ == "__main__":
    main()
