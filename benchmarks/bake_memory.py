"""Peak memory of a bake against its number of frames, and what checkpoints cost.

    python benchmarks/bake_memory.py                      # 10,000 balls, 4 s and 40 s
    python benchmarks/bake_memory.py --balls 2000 --durations 2 20
    python benchmarks/bake_memory.py --overhead           # + time with / without checkpoints

A resting scene: N balls (one sphere each) on a lattice, lying on the ground, with
sleeping on, so that a longer animation costs little simulation and what grows
with the frames is what a bake keeps of them. Each bake runs as `dempipe bake` in
a fresh child process; its peak resident memory is the child's ru_maxrss
(os.wait4), so the parent's own memory is not counted. The ratio column is each
row's peak over the first row's, measured in the same run.

--overhead bakes the same scene in this process through the library, alternating
with checkpoints (the default: one per chunk of 32 MiB of frames, at least every
60 s, here with --chunk-frames every few frames to make them frequent) and
without (``checkpoints=False``: chunks of frames still stream to disk), and prints
the median wall time of each and their ratio.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SCENE = """
[output]
fps = 24
duration = {duration}

[simulation]
sphere_diameter = 0.02
stiffness_target_overlap = 0.05
sleeping = true

[simulation.sleep]
time = 0.1

[shapes.ball]
builtin = "sphere"
diameter = 0.02
subdivisions = 1

[[bodies]]
name = "balls"
shape = "ball"
layout = "grid"
origin = [0.0, 0.0, 0.0100]
dims = [{side}, {side}, 1]
count = {balls}
spacing = 0.03

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
"""


def write_scene(folder: Path, balls: int, duration: float) -> Path:
    side = int(balls ** 0.5 + 0.999999)
    p = folder / f"rest_{balls}_{duration:g}.toml"
    p.write_text(SCENE.format(duration=duration, side=side, balls=balls))
    return p


def peak_rss(args, env) -> tuple[int, float, int]:
    """(peak RSS [bytes], wall [s], exit status) of one child."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        print(err, file=sys.stderr)
    return usage.ru_maxrss * 1024, wall, proc.returncode


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--balls", type=int, default=10_000)
    ap.add_argument("--durations", type=float, nargs="+", default=[4.0, 40.0])
    ap.add_argument("--layout", default="instancer")
    ap.add_argument("--overhead", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="dempipe-mem-"))
    env = dict(os.environ, DEMPIPE_CACHE_DIR=str(tmp / "cache"))
    print(f"# {a.balls} resting balls, {a.layout} layout; {platform.node()}, "
          f"{os.cpu_count()} cores, Python {platform.python_version()}")
    print("| animation [s] | frames | peak RSS [MiB] | ratio | bake wall [s] |")
    print("|---:|---:|---:|---:|---:|")
    first = None
    # a throw-away bake fills the sphere cache and numba's, so rows compare bakes
    warm = write_scene(tmp, a.balls, 0.1)
    peak_rss([sys.executable, "-m", "dempipe_cli.main", "bake", str(warm), "-o",
              str(tmp / "warm.usdc"), "--device", "cpu", "-q"], env)
    for duration in a.durations:
        scene = write_scene(tmp, a.balls, duration)
        rss, wall, code = peak_rss([sys.executable, "-m", "dempipe_cli.main", "bake",
                                    str(scene), "-o", str(tmp / "o.usdc"), "--device", "cpu",
                                    "--layout", a.layout, "-q"], env)
        if code:
            raise SystemExit(f"bake failed ({code})")
        first = first or rss
        frames = int(round(duration * 24)) + 1
        print(f"| {duration:g} | {frames} | {rss / 2**20:.0f} | {rss / first:.2f} | "
              f"{wall:.1f} |", flush=True)
    if a.overhead:
        from dempipe.pipeline.bake import bake
        from dempipe.spheres.cache import SphereCache

        scene = write_scene(tmp, a.balls, a.durations[0])
        cache = SphereCache(tmp / "cache")
        times = {True: [], False: []}
        inside = []
        n_ckpt = 0
        for _ in range(a.repeat):
            for ckpt in (False, True):
                t0 = time.perf_counter()
                r = bake(scene, tmp / "b.usdc", device="cpu", cache=cache, checkpoints=ckpt,
                         chunk_frames=8)
                times[ckpt].append(time.perf_counter() - t0)
                if ckpt:
                    n_ckpt = r.report["checkpoints"]
                    inside.append(r.report["checkpoint_seconds"])
        off, on = statistics.median(times[False]), statistics.median(times[True])
        print(f"\ncheckpoints: {n_ckpt} per bake (a chunk of 8 frames each); median of "
              f"{a.repeat}: without {off:.2f} s, with {on:.2f} s, ratio {on / off:.3f}; "
              f"time inside the checkpoints {statistics.median(inside):.2f} s "
              f"({statistics.median(inside) / on:.1%} of the bake)")


if __name__ == "__main__":
    main()
