"""The quickstart's whole bake (stepping only, no USD) with two source trees.

    git archive REV | tar -x -C /tmp/base
    python benchmarks/quickstart_bake.py /tmp/base . --pairs 2

Each run is a fresh interpreter with its tree first on sys.path: it builds
examples/quickstart.toml, steps twice to compile (warm numba cache), then times
``backend.step`` over every step of the bake from frame 0. The trees alternate
(A B, B A, ...); printed per run: dt, steps per frame, steps, wall and CPU seconds,
the final largest speed and mean height (the two piles should settle alike); then
the median ratio of wall times A/B (above 1: B bakes faster). A whole bake, not
ab_trees.py's few steps: the quickstart's first steps are free fall and cost
nearly nothing, and a change of dt auto shows only per bake (docs/performance.md).
``--spheres surface`` bakes the same scene with surface sphere sets (``--spacing``: at
that surface_spacing); ``--scene
examples/column_drop.toml`` another scene of the repository, the same way (its path
taken in each tree). ``--cost-of-surface`` (tree A only) bakes the scene with surface
sets and with the lattice, alternating, and prints the ratio of their wall times:

    python benchmarks/quickstart_bake.py . --cost-of-surface --pairs 2
"""

import argparse
import json
import statistics
import subprocess
import sys
import time


def child(root: str, spheres: str | None, name: str = "examples/quickstart.toml",
          spacing: float | None = None) -> None:
    sys.path[:0] = [root]
    import tempfile
    from pathlib import Path

    import numpy as np

    from dempipe.scene.build import build_model
    from dempipe.scene.load import load_scene
    from dempipe.sim.simulator import Simulator

    scene = Path(root) / name
    if spheres or spacing:
        keys = (f'spheres = "{spheres}"\n' if spheres else "") + (
            f"surface_spacing = {spacing}\n" if spacing else "")
        text = scene.read_text().replace("[simulation]\n", f"[simulation]\n{keys}", 1)
        scene = Path(tempfile.mkdtemp()) / Path(name).name
        scene.write_text(text)
    model = build_model(load_scene(scene))
    sim = Simulator(model)
    st = model.initial_state()
    sim.backend.step(st, 2)
    st = model.initial_state()
    n = model.steps_per_frame * (model.n_frames - 1)
    t0 = time.perf_counter()
    c0 = time.process_time()
    sim.backend.step(st, n)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    v = np.asarray(st.body_P) * model.body_inv_mass[:, None]
    print(json.dumps(dict(dt=model.dt, spf=model.steps_per_frame, steps=n, wall=wall, cpu=cpu,
                          speed=float(np.abs(v).max()),
                          height=float(np.asarray(st.body_x)[:, 2].mean()))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("a")
    ap.add_argument("b", nargs="?")
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--spheres", choices=("lattice", "surface"),
                    help="the scene's sphere sets (default: as the scene says)")
    ap.add_argument("--spacing", type=float, default=None,
                    help="the scene's surface_spacing (surface sets' shell spacing, in d)")
    ap.add_argument("--scene", default="examples/quickstart.toml",
                    help="a scene file, relative to each tree (default: the quickstart)")
    ap.add_argument("--cost-of-surface", action="store_true",
                    help="bake tree A's scene with surface sets and with the lattice, "
                         "alternating: the ratio is surface sets' cost over the lattice's")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args.a, args.spheres, args.scene, args.spacing)
    if args.cost_of_surface:
        # one tree, its scene with surface sets (A) and with the lattice (B)
        sides = [(args.a, "surface", "surface"), (args.a, "lattice", "lattice")]
    else:
        sides = [(args.a, args.spheres, args.a), (args.b, args.spheres, args.b)]
    ratios = []
    for k in range(args.pairs):
        walls = {}
        for root, spheres, name in (sides if k % 2 == 0 else sides[::-1]):
            r = subprocess.run([sys.executable, __file__, root, "--child", "--scene", args.scene]
                               + (["--spheres", spheres] if spheres else [])
                               + (["--spacing", str(args.spacing)] if args.spacing else []),
                               check=True, capture_output=True, text=True)
            res = json.loads(r.stdout.strip().splitlines()[-1])
            walls[name] = res["wall"]
            print(f"{name}: dt {res['dt']:.3e} s, {res['spf']} steps per frame, "
                  f"{res['steps']} steps, wall {res['wall']:.2f} s, cpu {res['cpu']:.2f} s; "
                  f"largest speed {res['speed']:.2e} m/s, mean height {res['height']:.5f} m")
        ratios.append(walls[sides[0][2]] / walls[sides[1][2]])
        what = "surface / lattice" if args.cost_of_surface else "A/B"
        print(f"pair {k}: {what} {ratios[-1]:.3f}")
    print(f"median {what}: {statistics.median(ratios):.3f} over {args.pairs} pairs (whole bake)")

if __name__ == "__main__":
    main()
