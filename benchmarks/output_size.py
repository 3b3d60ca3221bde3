"""USD stage size with and without sparse output, on the example scenes.

    python benchmarks/output_size.py                      # quickstart (2 s), chess (1 s), tori (0.5 s)
    python benchmarks/output_size.py --quick              # quickstart only, 1 s
    python benchmarks/output_size.py --scenes chess --duration 3.0 --frames-dir /tmp/frames

Each scene is simulated once (CPU backend) and the same Frames are written four
times: both layouts (``instancer``, ``xforms``), dense (``sparse=False``, every
frame of every attribute) and sparse (the default: a body or array that never
moves gets a default value only, a run of identical samples keeps its ends).
Printed per scene and layout: bytes, time samples and write time of both, and
the ratio sparse / dense measured in the same run. ``--duration`` shortens the
bakes (chess and tori take minutes per simulated second on 2 cores);
``--frames-dir`` keeps the simulated frames so that a rerun only writes.

"at rest" counts the bodies whose speed at the last frame is below 1 mm/s: the
xforms layout saves samples per body that has stopped, the instancer only while
every body is still.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENES = {"quickstart": 2.0, "chess": 1.0, "tori": 0.5}


def simulate(name: str, duration: float, frames_dir: Path | None):
    """(model, frames, simulate seconds) of examples/<name>.toml cut to ``duration``."""
    from dempipe.scene.build import Overrides, build_model
    from dempipe.sim.frames import Frames
    from dempipe.scene.load import load_scene
    from dempipe.sim.simulator import Simulator

    model = build_model(load_scene(ROOT / "examples" / f"{name}.toml"),
                        overrides=Overrides(duration=duration))
    saved = frames_dir / f"{name}-{duration:g}s.npz" if frames_dir else None
    if saved and saved.exists():
        d = np.load(saved)
        frames = Frames(d["frame_numbers"], d["times"], d["x"], d["q"], d["v"], d["w"])
        if frames.n_frames == model.n_frames and frames.n_bodies == model.n_bodies:
            return model, frames, float(d["seconds"])
    t0 = time.perf_counter()
    frames = Simulator(model).advance(model.initial_state())
    seconds = time.perf_counter() - t0
    if saved:
        saved.parent.mkdir(parents=True, exist_ok=True)
        np.savez(saved, frame_numbers=frames.frame_numbers, times=frames.times, x=frames.x,
                 q=frames.q, v=frames.v, w=frames.w, seconds=seconds)
    return model, frames, seconds


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", choices=sorted(SCENES), default=None)
    parser.add_argument("--duration", type=float, default=None,
                        help="simulated seconds per scene (default: quickstart 2, chess 1, "
                             "tori 0.5)")
    parser.add_argument("--quick", action="store_true", help="quickstart only, 1 s")
    parser.add_argument("--frames-dir", type=Path, default=None,
                        help="keep (and reuse) the simulated frames here")
    parser.add_argument("--ext", default=".usdc", choices=[".usdc", ".usda"])
    args = parser.parse_args(argv)

    import numba

    from dempipe.usd.animation import write_usd

    scenes = args.scenes or (["quickstart"] if args.quick else list(SCENES))
    print(f"<!-- {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}, numba {numba.__version__} "
          f"({numba.config.NUMBA_NUM_THREADS} threads) -->")
    print("| scene | bodies | frames | at rest (end) | layout | dense | sparse | sparse/dense "
          "| time samples dense → sparse | write dense / sparse [s] |")
    print("|---|---:|---:|---:|---|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory(prefix="dempipe-size-") as tmp:
        for name in scenes:
            duration = args.duration or (1.0 if args.quick else SCENES[name])
            model, frames, sim_s = simulate(name, duration, args.frames_dir)
            rest = int((np.linalg.norm(frames.v[-1], axis=1) < 1e-3).sum())
            print(f"<!-- {name}: {duration:g} s simulated in {sim_s:.0f} s, "
                  f"{model.n_spheres:,} spheres -->", flush=True)
            for layout in ("instancer", "xforms"):
                info = {}
                for sparse in (False, True):
                    path = Path(tmp) / f"{name}-{layout}-{'sparse' if sparse else 'dense'}{args.ext}"
                    info[sparse] = write_usd(path, frames, model, layout=layout, sparse=sparse)
                    path.unlink()
                d, s = info[False], info[True]
                print(f"| {name} ({duration:g} s) | {model.n_bodies:,} | {frames.n_frames} | "
                      f"{rest} | {layout} | {d.bytes / 1e6:.2f} MB | {s.bytes / 1e6:.2f} MB | "
                      f"{s.bytes / d.bytes:.2f} | {d.n_time_samples:,} → {s.n_time_samples:,} | "
                      f"{d.seconds:.2f} / {s.seconds:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
