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

from dempipe import interrupt
from dempipe.errors import DeviceError, StabilityError
from dempipe.sim.backend import Backend
from dempipe.sim.cores import CoreShare, check_threads
from dempipe.sim.frames import Frames
from dempipe.sim.kernels.cpu.backend import CpuBackend
from dempipe.sim.laws import law
from dempipe.sim.model import sym6_to_mat, quat_to_matrix
from dempipe.sim.overlap import REFUSE_OVERLAP, emission_overlap

#: An overlap beyond this fraction of the diameter means the contact model has
#: failed (bodies are passing through each other): stop rather than bake garbage.
MAX_OVERLAP_FRACTION = 0.5

#: Kinetic plus potential energy may exceed its frame-0 value (plus the elastic
#: energy of frame-0 overlaps) by at most this fraction of the scene's energy
#: scale: its kinetic energy plus what every body would release falling to the
#: lowest body's bottom, plus one diameter of fall. Damped contacts only lose
#: energy; the explicit integrator's gain stays far below 1% at dt auto
#: (tests/check/test_stability.py); a growth of 10% is a blow-up in the making.
MAX_ENERGY_GAIN = 0.10

#: A body whose fastest point moves more than this fraction of a diameter per
#: step can skip a contact entirely (stability.TUNNEL_ERROR, the check's limit).
MAX_STEP_TRAVEL = 0.5


#: A stepping call lasts about this long [s] (Simulator.run), so that a stop
#: signal is seen within it; a frame whose steps take longer is split into calls.
#: Each call begins with a full rebuild of the neighbour lists and ends by placing
#: every sphere and writing the State's contact histories, and the steps per call
#: are timed with that in: at 0.2 s the 4,096-piece chess pile's calls held about 11
#: steps and its bake's frames took 17-19 s, at 1 s about 65 steps and 9-12 s
#: (docs/performance.md, "The 4,096-piece pile").
CALL_SECONDS = 1.0
#: Steps of the first call of a run, before a step has been timed.
FIRST_CALL_STEPS = 1


class BakeFailure(StabilityError):
    """A guard stopped the bake. ``frames`` holds every frame recorded before it
    (Simulator.advance; None from Simulator.run), ``frames_done`` their count."""

    def __init__(self, message: str, frames: Frames | None):
        super().__init__(message)
        self.frames = frames
        self.frames_done = 0 if frames is None else frames.n_frames


@dataclass
class RunPoint:
    """Where a Simulator.run stopped, besides the State: enough to go on bit for bit.

    base_step : State.step at frame index 0; first_number : frame number of index 0;
    e0, gain : the energy guard's budget (from frame 0); frames_done : frames
    recorded; pending_overlap : largest overlap [m] in the steps of the unfinished
    frame; stats : RunStats so far.
    """

    base_step: int
    first_number: int
    e0: float
    gain: float
    frames_done: int
    pending_overlap: float
    stats: "RunStats"


@dataclass
class RunStats:
    """What a run cost and how close it came to the limits."""

    steps: int = 0
    #: Of ``steps``, those the backend skipped because every body slept (exact: such
    #: a step changes nothing; the CPU target skips them, the CUDA one computes them).
    #: A count of work, not of the result: each call of the backend computes its
    #: first step, and the bake splits its steps into calls by wall time
    #: (CALL_SECONDS), so two runs of one bake may skip a few dozen steps more or
    #: less for the same State bit for bit (test_sleeping: one call against calls
    #: of one step).
    steps_skipped: int = 0
    wall_seconds: float = 0.0
    max_overlap: float = 0.0          # [m]
    #: Glue bonds broken by each frame recorded (cumulative; empty without glue).
    bonds_broken: list = field(default_factory=list)

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


def make_backend(model, device: str = "cpu", features=None,
                 specialize: bool | None = None) -> Backend:
    """The backend of ``device``; ``features`` and ``specialize`` as in CpuBackend."""
    if device == "cpu":
        return CpuBackend(model, features=features, specialize=specialize)
    if device == "cuda":
        # numba.cuda loads here, only for a CUDA run
        from dempipe.sim.kernels.cuda.backend import CudaBackend

        return CudaBackend(model, features=features, specialize=specialize)
    raise DeviceError(f"unknown device {device!r} (known: cpu, cuda)")


class Simulator:
    """Advances a State of ``model`` on a device ('cpu' or 'cuda'; 'auto' resolves).

    ``threads``: the CPU threads, a whole number >= 1 (at most what numba may use
    here), or None: follow the cores other processes leave free (sim.cores.CoreShare).

    The kernels are compiled for the features the scene uses (Model.features);
    ``features`` runs it as if it used more, ``specialize=False`` through the
    general kernel (the frames are the same); ``specialize=None`` follows
    $DEMPIPE_KERNELS (sim.kernels.layout.run_flags).
    """

    def __init__(self, model, device: str = "cpu", threads: int | None = None,
                 features=None, specialize: bool | None = None):
        self.model = model
        self.device = resolve_device(device)
        check_threads(threads)
        if threads:
            import numba

            # more than numba may use here is an error there: use what there is
            numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
        self.backend = make_backend(model, self.device, features, specialize)
        #: the CPU target's threads follow the cores other processes leave (sim.cores);
        #: None on CUDA
        self.cores = CoreShare(fixed=bool(threads)) if self.device == "cpu" else None
        self.stats = RunStats()
        nb = model.n_bodies
        #: (n_bodies,) [kg]: the bodies' masses, 0 for kinematic ones (carried by
        #: their motion: no part of the dynamic energy)
        self.dynamic_mass = np.where(model.body_static[:nb], 0.0, model.body_mass[:nb])

    def energy(self, state, v, w) -> float:
        """Kinetic (½ P·V + ½ L·W) plus gravitational potential energy [J] of the
        dynamic bodies; springs' elastic energy is not included."""
        m = self.model
        nb = m.n_bodies
        kin = 0.5 * (float(np.einsum("bi,bi->", state.body_P[:nb], v))
                     + float(np.einsum("bi,bi->", state.body_L[:nb], w)))
        return kin - float(self.dynamic_mass @ (state.body_x[:nb] @ m.gravity))

    def energy_source(self, t: float) -> float:
        """The most energy prescribed motion can have given the dynamic bodies by time
        t [s] [J]: each body batted to twice the fastest surface speed v_s, and lifted
        by v_s t against gravity. The energy guard counts it as a source."""
        vs = self.model.surface_speed
        if vs <= 0.0:
            return 0.0
        g = float(np.linalg.norm(self.model.gravity))
        return float(self.dynamic_mass.sum()) * (2.0 * vs * vs + g * vs * t)

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
        mass = self.dynamic_mass
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
        Returns every frame in memory (tests, `dempipe report`); a bake streams them
        to disk instead (:meth:`run`). Raises BakeFailure (with the frames so far)
        when a guard trips; KeyboardInterrupt propagates after attaching the frames
        as ``exc.frames``.
        """
        m = self.model
        n_frames = m.n_frames if n_frames is None else int(n_frames)
        frames = Frames.empty(n_frames, m.n_bodies)

        def record(k, frame_number, st, v, w):
            self.store(frames, k, st, frame_number, (v, w))

        try:
            self.run(state, n_frames, record, progress=progress)
        except BakeFailure as exc:
            exc.frames = frames.head(exc.frames_done)
            raise
        except KeyboardInterrupt as exc:
            exc.frames = frames.head(getattr(self, "frames_done", 0))
            raise
        return frames

    def run(self, state, n_frames: int, record, progress=None, *, resume=None,
            after_frame=None) -> None:
        """Step ``state`` through frames 0 .. n_frames-1, handing each to ``record``.

        record : callable(k, frame_number, state, v, w) at each frame index k (v, w:
            the dynamic bodies' velocities, world frame).
        after_frame : optional callable(k, state) once frame k is recorded (a bake
            writes chunks and checkpoints there).
        resume : None to start with frame 0 = ``state``; else a :class:`RunPoint`
            from :meth:`run_point` of an earlier run of the same Model: ``state``
            (restored by the caller) is where that run stopped, and recording goes
            on from its next frame, bit for bit as if it had never stopped (CPU).

        The steps of a frame are run in calls short enough (about CALL_SECONDS
        each) that a stop signal (dempipe.interrupt) is seen between two of them:
        it raises StopRequested with ``frames_done`` (frames recorded) after a
        completed call, so :meth:`run_point` describes a consistent place to resume.
        How the steps are split into calls does not change a bit of the result
        (kernels/cpu/stages.py, run_steps; tests/sim/test_neighbours.py).
        A guard that trips raises BakeFailure with ``frames_done``.
        """
        m = self.model
        spf = int(m.steps_per_frame)
        if resume is None:
            self.frames_done = 0
            self.base_step = int(state.step)
            self.first_number = m.first_frame + round(state.time * m.fps)
            vw = self.backend.velocities(state)
            self._e0, self._gain = self._energy_budget(state, *vw)
            self.frames_done = 0
            self._pending_overlap = 0.0
        else:
            self.base_step = resume.base_step
            self.first_number = resume.first_number
            self._e0, self._gain = resume.e0, resume.gain
            self.frames_done = resume.frames_done
            self._pending_overlap = resume.pending_overlap
            self.stats = resume.stats
            self._skipped_before = int(resume.stats.steps_skipped)
        t0 = time.perf_counter() - self.stats.wall_seconds
        per_step = None          # seconds per step of the last call (None: not yet timed)
        with interrupt.deferred():
            if self.frames_done == 0:
                self._count_bonds(state)
                record(0, self.first_number, state, *vw)
                self.frames_done = 1
                if progress:
                    progress(0, n_frames, self.stats)
                if after_frame:
                    after_frame(0, state)
            starts = (np.unique(m.body_start[m.body_start > 0]) if m.body_start is not None
                      else np.zeros(0, np.int64))
            for k in range(self.frames_done, n_frames):
                target = self.base_step + k * spf
                while state.step < target:
                    if state.step in starts:      # emitters start here: the frame-0 check
                        problem = self._emission_check(state, k)
                        if problem:
                            exc = BakeFailure(problem, None)
                            exc.frames_done = k
                            raise exc
                    if interrupt.requested() is not None:
                        self._pending_overlap = max(self._pending_overlap,
                                                    self._peek_overlap())
                        stop = interrupt.StopRequested(interrupt.requested())
                        stop.frames_done = k
                        raise stop
                    n = target - state.step
                    later = starts[starts > state.step]
                    if later.size and later[0] < target:
                        n = int(later[0]) - state.step      # stop at the next emission
                    tc = time.perf_counter()
                    if per_step is None:
                        # the first call compiles the kernels (seconds, in Python): a
                        # signal stops it at once; the State is then not trusted
                        n = min(n, FIRST_CALL_STEPS)
                        try:
                            with interrupt.undeferred():
                                self.backend.step(state, n)
                        except interrupt.StopRequested as stop:
                            stop.frames_done = None
                            raise
                    else:
                        n = max(1, min(n, int(CALL_SECONDS / max(per_step, 1e-12))))
                        if self.cores is not None:
                            self.cores.adjust()
                        self.backend.step(state, n)
                    per_step = (time.perf_counter() - tc) / n
                    self.stats.steps += n
                    self.stats.steps_skipped = int(self.backend.steps_skipped) \
                        + self._skipped_before
                    self.stats.wall_seconds = time.perf_counter() - t0
                overlap = max(self.backend.take_max_overlap(), self._pending_overlap)
                self._pending_overlap = 0.0
                self.stats.max_overlap = max(self.stats.max_overlap, overlap)
                vw = self.backend.velocities(state)
                problem = self._check(state, overlap, k, *vw)
                if problem:
                    exc = BakeFailure(problem, None)
                    exc.frames_done = k
                    raise exc
                self._count_bonds(state)
                record(k, self.first_number + k, state, *vw)
                self.frames_done = k + 1
                if progress:
                    progress(k, n_frames, self.stats)
                if after_frame:
                    after_frame(k, state)

    _skipped_before = 0

    def _count_bonds(self, state) -> None:
        """Note how many glue bonds have broken by this frame (RunStats.bonds_broken)."""
        if state.bond_broken is not None:
            self.stats.bonds_broken.append(int(np.count_nonzero(state.bond_broken)))

    def _emission_check(self, state, k: int) -> str | None:
        """The frame-0 overlap check for the bodies an emitter starts at this step."""
        overlap, b = emission_overlap(self.model, state)
        if overlap <= REFUSE_OVERLAP:
            return None
        return (f"bake stopped before frame {k} (t = {state.time:.4g} s, step {state.step}): "
                f"body {self._body_name(b)} starts {overlap:.0%} of a sphere diameter deep in "
                f"another body or a collider (limit {REFUSE_OVERLAP:.0%}); the first step "
                f"would fling it away. Move the group's start position clear of what is "
                f"there at its start_time, or start it at another time")

    def _peek_overlap(self) -> float:
        """Largest overlap since the last frame [m], without resetting it."""
        ov = np.asarray(self.backend.sphere_overlap)
        return float(ov.max()) if ov.size else 0.0

    def run_point(self) -> "RunPoint":
        """Where :meth:`run` stands now, to resume from (with the State)."""
        return RunPoint(base_step=self.base_step, first_number=self.first_number,
                        e0=self._e0, gain=self._gain, frames_done=self.frames_done,
                        pending_overlap=max(self._pending_overlap, self._peek_overlap()),
                        stats=self.stats)

    def store(self, frames: Frames, k: int, state, frame_number: int, vw) -> None:
        """Frame ``k`` of ``frames`` from ``state`` and the velocities ``vw``."""
        nb = self.model.n_bodies
        frames.frame_numbers[k] = frame_number
        frames.times[k] = state.time
        frames.x[k] = state.body_x[:nb]
        frames.q[k] = state.body_q[:nb]
        frames.v[k] = vw[0]
        frames.w[k] = vw[1]

    def _check(self, state, overlap: float, k: int, v=None, w=None) -> str | None:
        """Guards: non-finite state, overlap beyond half a diameter, energy growing
        without a source, a body fast enough to skip contacts (where a contact is
        possible at all: Model.contact_possible)."""
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
        if e - self._e0 > self._gain + self.energy_source(t):
            kin = 0.5 * (np.einsum("bi,bi->b", state.body_P[:nb], v)
                         + np.einsum("bi,bi->b", state.body_L[:nb], w))
            b = int(np.argmax(kin))
            return (f"{where}: kinetic plus potential energy grew by {e - self._e0:.3g} J, more "
                    f"than the {MAX_ENERGY_GAIN:.0%} of the scene's energy allowed, with no "
                    f"source; body {self._body_name(b)} is the fastest. The explicit "
                    f"integration is unstable: dt = {m.dt:.3g} s is too long for the contact "
                    f"stiffness (use dt = \"auto\", a smaller dt, or softer materials)")
        if not m.contact_possible:
            # nothing to pass through, and dt "auto" is the free-flight step whatever
            # the speed: a long fall must not stop here
            return None
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

    I0 = np.stack([np.linalg.inv(sym6_to_mat(s)) for s in model.body_inv_inertia[:nb]]) \
        if nb else np.zeros((0, 3, 3))
    for f in range(frames.n_frames):
        R = np.stack([quat_to_matrix(q) for q in frames.q[f]]) if nb else np.zeros((0, 3, 3))
        wb = np.einsum("bji,bj->bi", R, frames.w[f])          # body frame
        ke[f] += 0.5 * np.einsum("bi,bij,bj->", wb, I0, wb)
    return ke


def elapsed_ratio(stats: RunStats, sim_seconds: float) -> float:
    return stats.wall_seconds / sim_seconds if sim_seconds > 0 else math.nan
