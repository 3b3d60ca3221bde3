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
from .laws import law

#: An overlap beyond this fraction of the diameter means the contact model has
#: failed (bodies are passing through each other): stop rather than bake garbage.
MAX_OVERLAP_FRACTION = 0.5

#: Kinetic plus potential energy may exceed its frame-0 value (plus the elastic
#: energy of frame-0 overlaps) by at most this fraction of the scene's energy
#: scale: its kinetic energy plus what every body would release falling to the
#: lowest body's bottom, plus one diameter of fall. Damped contacts only lose
#: energy; the explicit integrator's gain stays far below 1% at dt auto
#: (tests/test_stability.py); a growth of 10% is a blow-up in the making.
MAX_ENERGY_GAIN = 0.10

#: A body whose fastest point moves more than this fraction of a diameter per
#: step can skip a contact entirely (stability.TUNNEL_ERROR, the check's limit).
MAX_STEP_TRAVEL = 0.5


class BakeFailure(StabilityError):
    """A guard stopped the bake. ``frames`` holds every frame recorded before it."""

    def __init__(self, message: str, frames: Frames):
        super().__init__(message)
        self.frames = frames


@dataclass
class RunStats:
    """What a run cost and how close it came to the limits."""

    steps: int = 0
    #: Of ``steps``, those the backend skipped because every body slept (exact: such
    #: a step changes nothing; the CPU target skips them, the CUDA one computes them).
    steps_skipped: int = 0
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


def make_backend(model, device: str = "cpu", features=None, specialize: bool = True):
    """The backend of ``device``; ``features`` and ``specialize`` as in CpuBackend."""
    if device == "cpu":
        from .kernels.cpu import CpuBackend

        return CpuBackend(model, features=features, specialize=specialize)
    if device == "cuda":
        from .kernels.cuda import CudaBackend

        return CudaBackend(model, features=features, specialize=specialize)
    raise DeviceError(f"unknown device {device!r} (known: cpu, cuda)")


class Simulator:
    """Advances a State of ``model`` on a device ('cpu' or 'cuda'; 'auto' resolves).

    The kernels are compiled for the features the scene uses (Model.features);
    ``features`` runs it as if it used more, ``specialize=False`` through the
    general kernel (both for tests and benchmarks: the frames are the same).
    """

    def __init__(self, model, device: str = "cpu", threads: int | None = None,
                 features=None, specialize: bool = True):
        self.model = model
        self.device = resolve_device(device)
        if threads:
            import numba

            numba.set_num_threads(int(threads))
        self.backend = make_backend(model, self.device, features, specialize)
        self.stats = RunStats()

    def record(self, frames: Frames, k: int, state, frame_number: int, vw=None) -> None:
        m = self.model
        nb = m.n_bodies
        v, w = vw if vw is not None else self.backend.velocities(state)
        frames.frame_numbers[k] = frame_number
        frames.times[k] = state.time
        frames.x[k] = state.body_x[:nb]
        frames.q[k] = state.body_q[:nb]
        frames.v[k] = v
        frames.w[k] = w

    def energy(self, state, v, w) -> float:
        """Kinetic (½ P·V + ½ L·W) plus gravitational potential energy [J] of the
        dynamic bodies; springs' elastic energy is not included."""
        m = self.model
        nb = m.n_bodies
        kin = 0.5 * (float(np.einsum("bi,bi->", state.body_P[:nb], v))
                     + float(np.einsum("bi,bi->", state.body_L[:nb], w)))
        return kin - float(m.body_mass[:nb] @ (state.body_x[:nb] @ m.gravity))

    def _energy_budget(self, state, v, w) -> tuple[float, float]:
        """(E0, allowed gain) for the energy guard, see MAX_ENERGY_GAIN."""
        m = self.model
        nb = m.n_bodies
        e0 = self.energy(state, v, w)
        g = float(np.linalg.norm(m.gravity))
        if nb == 0:
            return e0, math.inf
        up = -np.asarray(m.gravity) / g if g > 0 else np.zeros(3)
        h = state.body_x[:nb] @ up
        low = float(h.min() - m.body_radius.max())
        mass = m.body_mass[:nb]
        kin0 = e0 + float(mass @ (state.body_x[:nb] @ m.gravity))
        scale = kin0 + g * float(mass @ (h - low + m.diameter))
        # elastic energy of frame-0 overlaps: at most the stiffest pair's per sphere
        elastic = 0.0
        if m.n_spheres:
            self.backend.probe(state)
            elastic = law(m.contact_law).elastic_energy(np.max(m.pair_k),
                                                        self.backend.sphere_overlap)
        return e0, MAX_ENERGY_GAIN * scale + elastic + 1e-300

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
        vw = self.backend.velocities(state)
        self.record(frames, 0, state, first, vw)
        self._e0, self._gain = self._energy_budget(state, *vw)
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
            self.stats.steps_skipped = int(getattr(self.backend, "steps_skipped", 0))
            self.stats.wall_seconds = time.perf_counter() - t0
            overlap = self.backend.take_max_overlap()
            self.stats.frame_overlap.append(overlap)
            self.stats.max_overlap = max(self.stats.max_overlap, overlap)
            vw = self.backend.velocities(state)
            problem = self._check(state, overlap, k, *vw)
            if problem:
                raise BakeFailure(problem, frames.head(k))
            self.record(frames, k, state, first + k, vw)
            if progress:
                progress(k, n_frames, self.stats)
        return frames

    def _check(self, state, overlap: float, k: int, v=None, w=None) -> str | None:
        """Guards: non-finite state, overlap beyond half a diameter, energy growing
        without a source, a body fast enough to skip contacts."""
        m = self.model
        nb = m.n_bodies
        x = state.body_x[:nb]
        finite = np.isfinite(x).all(axis=1) & np.isfinite(state.body_q[:nb]).all(axis=1)
        t = state.time
        where = f"bake stopped at frame {k} (t = {t:.4g} s, step {state.step})"
        if not finite.all():
            b = int(np.flatnonzero(~finite)[0])
            return (f"{where}: body {b} ({self._body_name(b)}) has a non-finite position; the "
                    f"step dt = {m.dt:.3g} s is likely too large for the stiffness (use "
                    f"dt = \"auto\" or softer materials)")
        if overlap > MAX_OVERLAP_FRACTION * m.diameter:
            return (f"{where}: spheres overlap by {overlap / m.diameter:.0%} of the diameter "
                    f"(limit {MAX_OVERLAP_FRACTION:.0%}); contacts are too soft for the impact "
                    f"speeds, or dt too large: raise the stiffness, lower "
                    f"stiffness_target_overlap, or use dt = \"auto\"")
        if v is None or nb == 0:
            return None
        e = self.energy(state, v, w)
        if e - self._e0 > self._gain:
            kin = 0.5 * (np.einsum("bi,bi->b", state.body_P[:nb], v)
                         + np.einsum("bi,bi->b", state.body_L[:nb], w))
            b = int(np.argmax(kin))
            return (f"{where}: kinetic plus potential energy grew by {e - self._e0:.3g} J, more "
                    f"than the {MAX_ENERGY_GAIN:.0%} of the scene's energy allowed, with no "
                    f"source; body {self._body_name(b)} is the fastest. The explicit "
                    f"integration is unstable: dt = {m.dt:.3g} s is too long for the contact "
                    f"stiffness (use dt = \"auto\", a smaller dt, or softer materials)")
        speed = np.linalg.norm(v, axis=1) + np.linalg.norm(w, axis=1) * m.body_radius[:nb]
        b = int(np.argmax(speed))
        travel = float(speed[b]) * m.dt / m.diameter
        if travel > MAX_STEP_TRAVEL:
            return (f"{where}: body {self._body_name(b)} moves at {speed[b]:.3g} m/s, "
                    f"{travel:.0%} of a sphere diameter per step (limit "
                    f"{MAX_STEP_TRAVEL:.0%}): it can pass through walls and bodies. The scene "
                    f"reaches speeds dt was not chosen for (a launch or fall faster than "
                    f"`dempipe check` predicts): use a smaller dt or a higher stiffness")
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
