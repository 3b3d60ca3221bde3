"""Simulator: runs the eight stages on a backend, samples Frames, guards the bake.

    sim = Simulator(model, device="cpu")
    state = model.initial_state()
    frames = sim.advance(state, n_frames=model.n_frames)

``advance`` calls the backend once per output frame (each call runs
``model.steps_per_frame`` steps in compiled code), records every dynamic body's
x, q, v, w, and checks the guards. A guard that trips raises
:class:`BakeFailure` carrying the frames recorded so far, so the caller can
still write them out.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import DeviceError, StabilityError
from .frames import Frames

#: An overlap beyond this fraction of the diameter means the contact model has
#: failed (bodies are passing through each other): stop rather than bake garbage.
MAX_OVERLAP_FRACTION = 0.5


class BakeFailure(StabilityError):
    """A guard stopped the bake. ``frames`` holds every frame recorded before it."""

    def __init__(self, message: str, frames: Frames):
        super().__init__(message)
        self.frames = frames


@dataclass
class RunStats:
    """What a run cost and how close it came to the limits."""

    steps: int = 0
    wall_seconds: float = 0.0
    max_overlap: float = 0.0          # [m]
    frame_overlap: list = field(default_factory=list)

    @property
    def seconds_per_step(self) -> float:
        return self.wall_seconds / self.steps if self.steps else 0.0


def cuda_available() -> bool:
    """True when numba can reach a CUDA GPU (or the simulator is forced on)."""
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        return True
    try:
        from numba import cuda

        return bool(cuda.is_available())
    except Exception:
        return False


def resolve_device(device: str) -> str:
    """'cpu' | 'cuda' | 'auto' → the device to use; 'cuda' without a GPU is an error."""
    if device == "cpu":
        return "cpu"
    if device == "cuda":
        if not cuda_available():
            raise DeviceError("device 'cuda' asked for, but no usable CUDA GPU was found "
                              "(use --device cpu or auto)")
        return "cuda"
    if device == "auto":
        return "cuda" if cuda_available() and os.environ.get("NUMBA_ENABLE_CUDASIM") != "1" \
            else "cpu"
    raise DeviceError(f"unknown device {device!r} (known: auto, cpu, cuda)")


def make_backend(model, device: str = "cpu"):
    if device == "cpu":
        from .kernels.cpu import CpuBackend

        return CpuBackend(model)
    if device == "cuda":
        from .kernels.cuda import CudaBackend

        return CudaBackend(model)
    raise DeviceError(f"unknown device {device!r} (known: cpu, cuda)")


class Simulator:
    """Advances a State of ``model`` on a device ('cpu' or 'cuda'; 'auto' resolves)."""

    def __init__(self, model, device: str = "cpu", threads: int | None = None):
        self.model = model
        self.device = resolve_device(device)
        if threads:
            import numba

            numba.set_num_threads(int(threads))
        self.backend = make_backend(model, self.device)
        self.stats = RunStats()

    def record(self, frames: Frames, k: int, state, frame_number: int) -> None:
        m = self.model
        nb = m.n_bodies
        v, w = self.backend.velocities(state)
        frames.frame_numbers[k] = frame_number
        frames.times[k] = state.time
        frames.x[k] = state.body_x[:nb]
        frames.q[k] = state.body_q[:nb]
        frames.v[k] = v
        frames.w[k] = w

    def advance(self, state, n_frames: int | None = None, progress=None) -> Frames:
        """Record frame 0 (``state`` as given), then step to each further frame.

        progress : optional callable(frame_index, n_frames, stats) after each frame.
        Raises BakeFailure (with the frames so far) when a guard trips;
        KeyboardInterrupt propagates after attaching the frames as ``exc.frames``.
        """
        m = self.model
        n_frames = m.n_frames if n_frames is None else int(n_frames)
        frames = Frames.empty(n_frames, m.n_bodies)
        first = m.first_frame + round(state.time * m.fps)
        self.record(frames, 0, state, first)
        if progress:
            progress(0, n_frames, self.stats)
        t0 = time.perf_counter()
        for k in range(1, n_frames):
            try:
                self.backend.step(state, m.steps_per_frame)
            except KeyboardInterrupt as exc:
                exc.frames = frames.head(k)
                raise
            self.stats.steps += m.steps_per_frame
            self.stats.wall_seconds = time.perf_counter() - t0
            overlap = self.backend.take_max_overlap()
            self.stats.frame_overlap.append(overlap)
            self.stats.max_overlap = max(self.stats.max_overlap, overlap)
            problem = self._check(state, overlap, k)
            if problem:
                raise BakeFailure(problem, frames.head(k))
            self.record(frames, k, state, first + k)
            if progress:
                progress(k, n_frames, self.stats)
        return frames

    def _check(self, state, overlap: float, k: int) -> str | None:
        """Guards: non-finite state, overlap beyond half a diameter."""
        m = self.model
        nb = m.n_bodies
        x = state.body_x[:nb]
        finite = np.isfinite(x).all(axis=1) & np.isfinite(state.body_q[:nb]).all(axis=1)
        t = state.time
        if not finite.all():
            b = int(np.flatnonzero(~finite)[0])
            return (f"bake stopped at frame {k} (t = {t:.4g} s, step {state.step}): body {b} "
                    f"({self._body_name(b)}) has a non-finite position; the step dt = {m.dt:.3g} s "
                    f"is likely too large for the stiffness (use dt = \"auto\" or softer materials)")
        if overlap > MAX_OVERLAP_FRACTION * m.diameter:
            return (f"bake stopped at frame {k} (t = {t:.4g} s, step {state.step}): spheres overlap "
                    f"by {overlap / m.diameter:.0%} of the diameter (limit "
                    f"{MAX_OVERLAP_FRACTION:.0%}); contacts are too soft for the impact speeds, "
                    f"or dt too large: raise the stiffness, lower stiffness_target_overlap, or "
                    f"use dt = \"auto\"")
        return None

    def _body_name(self, b: int) -> str:
        m = self.model
        g = m.body_group[b]
        return f"{m.group_names[g]}[{m.body_group_index[b]}]"


def kinetic_energy(model, frames: Frames) -> np.ndarray:
    """Total kinetic energy per frame [J] (translation + rotation)."""
    nb = model.n_bodies
    mass = model.body_mass[:nb]
    ke = 0.5 * np.einsum("b,fbi,fbi->f", mass, frames.v, frames.v)
    # rotational: ½ wᵀ I w with I = R I0 R^T; I0 from the stored inverse
    from .model import _sym6_to_mat, quat_to_matrix

    I0 = np.stack([np.linalg.inv(_sym6_to_mat(s)) for s in model.body_inv_inertia[:nb]]) \
        if nb else np.zeros((0, 3, 3))
    for f in range(frames.n_frames):
        R = np.stack([quat_to_matrix(q) for q in frames.q[f]]) if nb else np.zeros((0, 3, 3))
        wb = np.einsum("bji,bj->bi", R, frames.w[f])          # body frame
        ke[f] += 0.5 * np.einsum("bi,bij,bj->", wb, I0, wb)
    return ke


def elapsed_ratio(stats: RunStats, sim_seconds: float) -> float:
    return stats.wall_seconds / sim_seconds if sim_seconds > 0 else math.nan
