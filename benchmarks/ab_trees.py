"""Two source trees of dempipe against each other: the State bit for bit, and speed.

    git archive REV | tar -x -C /tmp/base          # the commit before, say
    python benchmarks/ab_trees.py /tmp/base .  --scene pile --spheres 25000 --steps 30
    python benchmarks/ab_trees.py /tmp/base .  --scene quickstart --steps 60 --pairs 3

Each run is a fresh interpreter with the tree on PYTHONPATH (its own numba cache,
warmed by a first unmeasured run); the two trees alternate (A B, B A, ...), so a
machine's changing load falls on both sides of each pair. Printed: each pair's
ms per step (with --cpu: CPU time of one thread) and ratio A/B (above 1: B is
faster), their median, and whether the
final States (x, q, P, L, rest counts, contact histories) are identical bit for
bit. Exit status 1 when they differ. For a refactor that must keep the State and
the speed (docs/performance.md, "Comparing two source trees").
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
FIELDS = ("body_x", "body_q", "body_P", "body_L", "body_rest", "contact_partner",
          "contact_spring")


def _child(root: str, scene: str, spheres: int, steps: int, out: str) -> None:
    """Run in the child: build, warm up 2 steps, time ``steps``, save the State."""
    sys.path[:0] = [root, os.path.join(root, "benchmarks"), os.path.join(root, "tests")]
    import time

    from dempipe.sim.simulator import Simulator
    if scene == "pile":
        from cpu_bench import dense_pile
        model = dense_pile(spheres)
    else:
        from dempipe.scene.build import build_model
        from dempipe.scene.load import load_scene
        model = build_model(load_scene(os.path.join(root, "examples", "quickstart.toml")))
    sim = Simulator(model)
    st = model.initial_state()
    sim.backend.step(st, 2)
    t0 = time.perf_counter()
    c0 = time.process_time()
    sim.backend.step(st, steps)
    ms = 1e3 * (time.perf_counter() - t0) / steps
    cpu_ms = 1e3 * (time.process_time() - c0) / steps
    np.savez(out, **{k: np.asarray(getattr(st, k)) for k in FIELDS
                     if getattr(st, k, None) is not None})
    print(json.dumps({"ms": ms, "cpu_ms": cpu_ms}))


def run(root: str, args, out: str) -> float:
    env = dict(os.environ, PYTHONPATH=os.path.abspath(root))
    env.pop("NUMBA_ENABLE_CUDASIM", None)
    if args.cpu:
        env["NUMBA_NUM_THREADS"] = "1"
    r = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", root, "--scene",
                        args.scene, "--spheres", str(args.spheres), "--steps", str(args.steps),
                        "--out", out], env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{root}: run failed\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])["cpu_ms" if args.cpu else "ms"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", nargs="?", help="tree A (the baseline)")
    ap.add_argument("b", nargs="?", help="tree B")
    ap.add_argument("--scene", choices=("pile", "quickstart"), default="pile")
    ap.add_argument("--spheres", type=int, default=25000, help="the pile's spheres")
    ap.add_argument("--steps", type=int, default=30, help="timed steps per run")
    ap.add_argument("--pairs", type=int, default=5, help="alternated A/B pairs")
    ap.add_argument("--cpu", action="store_true",
                    help="one thread, compare CPU time (steadier than wall time on a "
                         "shared machine)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _child(args.child, args.scene, args.spheres, args.steps, args.out)
        return 0
    if not (args.a and args.b):
        ap.error("give the two trees A and B")
    with tempfile.TemporaryDirectory() as work:
        outs = {t: os.path.join(work, f"{t}.npz") for t in "ab"}
        roots = {"a": args.a, "b": args.b}
        for t in "ab":                      # warm each tree's numba cache (unmeasured)
            run(roots[t], args, outs[t])
        ratios = []
        for i in range(args.pairs):
            ms = {t: run(roots[t], args, outs[t]) for t in ("ab" if i % 2 == 0 else "ba")}
            ratios.append(ms["a"] / ms["b"])
            print(f"pair {i}: A {ms['a']:.2f} ms/step, B {ms['b']:.2f} ms/step, "
                  f"A/B {ratios[-1]:.3f}", flush=True)
        a, b = np.load(outs["a"]), np.load(outs["b"])
        same = set(a.files) == set(b.files) and all(
            a[k].shape == b[k].shape and a[k].tobytes() == b[k].tobytes() for k in a.files)
    print(f"median A/B: {statistics.median(ratios):.3f} over {args.pairs} pairs "
          f"({args.scene}, {args.steps} steps); State {'identical' if same else 'DIFFERS'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
