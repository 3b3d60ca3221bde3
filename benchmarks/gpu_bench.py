"""GPU benchmark: the paper's workloads and a scaling run on the CUDA backend.

    python benchmarks/gpu_bench.py [--quick] [--steps N]

Workloads (Harada et al. 2007, Tables 1 and 2): chess pieces falling into a box
(1,024 / 4,096 / 16,384 pieces) and tori falling onto the ground (682 / 2,730 /
10,922), built from scene TOML like examples/chess.toml and examples/tori.toml;
then a scaling run of one-sphere balls on a lattice up to 1,000,000 bodies.

For each: ms per step (mean over N steps after a warm-up step that compiles the
kernels), sphere-steps per second, the share of each launch group of a step
(timed with CUDA events around each group over the same N steps), and the
speed-up against a baseline measured in the same run: the CPU backend on the
smallest chess scene (a few steps, all numba threads of this machine).
The scenes start in the air, so the first steps have few contacts; ``--steps``
longer runs measure a settled pile better (the chess box fills in ~0.3 s).

Without a usable CUDA GPU the script says so and exits with status 2.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

CHESS = """
[output]
fps = 24
duration = 1.0
[simulation]
resolution = 6
stiffness_target_overlap = 0.05
seed = 2007
[materials.boxwood]
density = 900.0
restitution = 0.35
friction = 0.5
[materials.felt]
density = 500.0
restitution = 0.2
friction = 0.7
[shapes.pawn]
builtin = "pawn"
[shapes.rook]
builtin = "rook"
[shapes.knight]
builtin = "knight"
[shapes.bishop]
builtin = "bishop"
[shapes.queen]
builtin = "queen"
[shapes.king]
builtin = "king"
[[bodies]]
name = "pieces"
shape = ["rook", "knight", "bishop", "queen", "king", "bishop", "knight", "rook",
         "pawn", "pawn", "pawn", "pawn", "pawn", "pawn", "pawn", "pawn"]
material = "boxwood"
count = {count}
layout = "grid"
origin = [{o}, {o}, 0.05]
dims = [{n}, {n}, {nz}]
spacing = [0.05, 0.05, 0.12]
[[colliders]]
type = "box"
min = [{lo}, {lo}, 0.0]
max = [{hi}, {hi}, {top}]
material = "felt"
"""

TORI = """
[output]
fps = 24
duration = 1.0
[simulation]
resolution = 10
stiffness_target_overlap = 0.05
seed = 2007
[materials.rubber]
density = 1100.0
restitution = 0.5
friction = 0.8
[shapes.ring]
builtin = "torus"
major_radius = 0.02
minor_radius = 0.008
[[bodies]]
name = "rings"
shape = "ring"
material = "rubber"
count = {count}
layout = "grid"
origin = [{o}, {o}, 0.06]
dims = [{n}, {n}, {nz}]
spacing = 0.065
rotation = "random"
[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "rubber"
"""


def chess_model(count: int, cache):
    from dempipe.scene.build import build_model
    from dempipe.scene.load import parse_scene

    n = 32 if count <= 16384 else int(np.ceil(np.sqrt(count / 16)))
    nz = int(np.ceil(count / (n * n)))
    half = (n - 1) * 0.05 / 2
    text = CHESS.format(count=count, n=n, nz=nz, o=-half, lo=-half - 0.045, hi=half + 0.045,
                        top=0.2 + nz * 0.12)
    return build_model(parse_scene(text), cache=cache)


def tori_model(count: int, cache):
    from dempipe.scene.build import build_model
    from dempipe.scene.load import parse_scene

    n = 32 if count <= 11264 else int(np.ceil(np.sqrt(count / 11)))
    nz = int(np.ceil(count / (n * n)))
    text = TORI.format(count=count, n=n, nz=nz, o=-(n - 1) * 0.065 / 2)
    return build_model(parse_scene(text), cache=cache)


def balls_model(count: int):
    """``count`` one-sphere balls (1 cm) on a lattice over a plane, randomly moving."""
    from dempipe.sim.materials import Material
    from dempipe.sim.builder import ModelBuilder
    from types import SimpleNamespace

    d = 0.01
    b = ModelBuilder(d)
    V = np.pi / 6 * d**3
    ss = SimpleNamespace(centers=np.zeros((1, 3)), com=np.zeros(3), volume=V,
                         inertia=np.eye(3) * 0.4 * V * (d / 2) ** 2, diameter=d)
    mesh = SimpleNamespace(vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]]))
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("glass", density=2500, restitution=0.5, friction=0.3))
    n = int(np.ceil(np.cbrt(count / 4)))
    nx, ny = 2 * n, 2 * n
    idx = np.arange(count)
    pos = np.stack([idx % nx, (idx // nx) % ny, idx // (nx * ny)], -1) * (1.2 * d)
    pos = pos + [0, 0, d]
    rng = np.random.default_rng(0)
    b.add_bodies("balls", s, m, pos, velocities=rng.normal(size=(count, 3)) * 0.1)
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=24, n_frames=2)


def gpu_message() -> str | None:
    """None when a CUDA GPU is usable, else why not."""
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        return "NUMBA_ENABLE_CUDASIM=1 is set: the CUDA simulator is not a benchmark target"
    try:
        from numba import cuda
    except Exception as exc:  # pragma: no cover - depends on the install
        return f"numba.cuda cannot be imported ({exc}); pip install 'dempipe[cuda]'"
    try:
        if not cuda.is_available():
            return "numba.cuda.is_available() is False (no GPU, driver or CUDA libraries)"
    except Exception as exc:  # pragma: no cover
        return f"CUDA is not usable: {exc}"
    return None


def time_cpu(model, steps: int) -> float:
    """Seconds per step of the CPU backend (after a compile/warm-up step)."""
    from dempipe.sim.kernels.cpu.backend import CpuBackend

    be = CpuBackend(model)
    st = model.initial_state()
    be.step(st, 1)
    t0 = time.perf_counter()
    be.step(st, steps)
    return (time.perf_counter() - t0) / steps


#: CudaBackend.STAGES without the underscore: the launch groups of a step. The
#: rebuild groups (save_pairs, spheres, grid_sort, gather, neighbours, pairs) exit at once on the
#: steps that do not rebuild the neighbour lists, so their shares are averages.
GROUPS = ("idle_check", "velocities", "spheres_sorted", "save_pairs", "spheres", "grid_sort",
          "gather", "neighbours", "pairs", "contacts", "bodies")


def time_gpu(model, steps: int):
    """(seconds per step, {stage: share}) of the CUDA backend."""
    from numba import cuda

    from dempipe.sim.kernels.cuda.backend import CudaBackend

    be = CudaBackend(model)
    st = model.initial_state()
    be.step(st, 1)                        # compiles every kernel once
    cuda.synchronize()
    t0 = time.perf_counter()
    be.step(st, steps)                    # ends with the copy back: synchronised
    per_step = (time.perf_counter() - t0) / steps
    # stage shares: CUDA events around each launch group, summed over the steps
    events = [cuda.event() for _ in range(len(be.STAGES) + 1)]
    total = dict.fromkeys(be.STAGES, 0.0)
    for step in range(steps):
        events[0].record()
        for k, name in enumerate(be.STAGES):
            if name == "_contacts":
                be._contacts(step & 1)        # the histories' parity, as step_once
            else:
                getattr(be, name)()
            events[k + 1].record()
        events[-1].synchronize()
        for k, name in enumerate(be.STAGES):
            total[name] += cuda.event_elapsed_time(events[k], events[k + 1])
    from dempipe.sim.kernels.cuda.device import CTL_OVER

    if be.d["ctl"].copy_to_host()[CTL_OVER]:   # contacts and bodies froze: shares skewed
        print(f"# warning: a neighbour list overflowed during the stage timing of "
              f"{model.n_bodies:,} bodies; its shares are not a step's", flush=True)
    s = sum(total.values()) or 1.0
    return per_step, {k.lstrip("_"): v / s for k, v in total.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="smallest size of each workload, scaling to 100k, fewer steps")
    parser.add_argument("--steps", type=int, default=None, help="timed steps per scene")
    args = parser.parse_args(argv)

    why = gpu_message()
    if why:
        print(f"gpu_bench: no CUDA GPU to benchmark: {why}.", file=sys.stderr)
        print("gpu_bench: run it on a machine with an NVIDIA GPU and numba-cuda "
              "(pip install 'dempipe[cuda]'); the CPU benchmark is benchmarks/cpu_bench.py.",
              file=sys.stderr)
        return 2

    import numba
    from numba import cuda

    from dempipe.spheres.cache import SphereCache

    steps = args.steps or (20 if args.quick else 100)
    cache = SphereCache()
    dev = cuda.get_current_device()
    print(f"# {dev.name.decode() if isinstance(dev.name, bytes) else dev.name}, "
          f"CC {dev.compute_capability}, numba {numba.__version__}; host {platform.machine()} "
          f"{os.cpu_count()} cores ({numba.config.NUMBA_NUM_THREADS} numba threads)")

    chess_sizes = [1024] if args.quick else [1024, 4096, 16384]
    tori_sizes = [682] if args.quick else [682, 2730, 10922]
    ball_sizes = [10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000]

    print("# baseline: CPU backend, chess 1,024 ...", flush=True)
    base_model = chess_model(1024, cache)
    cpu_s = time_cpu(base_model, 3 if args.quick else 10)
    print(f"# baseline: CPU chess 1,024 ({base_model.n_spheres:,} spheres): "
          f"{cpu_s * 1e3:.2f} ms/step, {base_model.n_spheres / cpu_s:.3g} sphere-steps/s")

    rows = []
    scenes = ([("chess", n, lambda n=n: chess_model(n, cache)) for n in chess_sizes]
              + [("tori", n, lambda n=n: tori_model(n, cache)) for n in tori_sizes]
              + [("balls", n, lambda n=n: balls_model(n)) for n in ball_sizes])
    print("| scene | bodies | spheres | ms/step | sphere-steps/s | vs CPU chess 1,024 "
          "(per sphere) | " + " | ".join(n.replace("_", " ") for n in GROUPS) + " |")
    print("|---|---:|---:|---:|---:|---:|" + "---:|" * len(GROUPS))
    for name, n, build in scenes:
        t0 = time.perf_counter()
        model = build()
        built = time.perf_counter() - t0
        try:
            s, shares = time_gpu(model, steps)
        except Exception as exc:          # e.g. DeviceError: does not fit
            print(f"| {name} | {n:,} | {model.n_spheres:,} | failed: {exc} |")
            continue
        rate = model.n_spheres / s
        ratio = rate / (base_model.n_spheres / cpu_s)
        sh = " | ".join(f"{shares[k]:.0%}" for k in GROUPS)
        print(f"| {name} | {model.n_bodies:,} | {model.n_spheres:,} | {s * 1e3:.3f} | {rate:.3g} "
              f"| {ratio:.1f}x | {sh} |", flush=True)
        rows.append((name, n, s))
        del model, built
    print(f"# {steps} timed steps per scene after one warm-up step; shares from CUDA events "
          "around each launch group")
    return 0


if __name__ == "__main__":
    sys.exit(main())
