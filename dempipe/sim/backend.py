"""The Backend protocol: what the Simulator and the bake's checkpoints ask of a target.

Two targets implement it, :class:`~dempipe.sim.kernels.cpu.backend.CpuBackend` (numba
CPU) and :class:`~dempipe.sim.kernels.cuda.backend.CudaBackend` (numba CUDA), with one
physics: a backend owns the scratch arrays of one Model and advances States with the
paper's eight stages. Lengths in metres, times in seconds, forces in newtons.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Backend(Protocol):
    """A target that steps one Model's States."""

    #: "cpu" or "cuda".
    name: str
    #: Steps skipped because every body slept (counted as done, not computed).
    steps_skipped: int

    def step(self, state, n_steps: int, control=None) -> None:
        """Advance ``state`` in place by ``n_steps`` steps of the Model's dt."""

    def probe(self, state) -> None:
        """Compute the contacts of ``state`` without moving it (sphere_overlap, forces)."""

    def velocities(self, state) -> tuple[np.ndarray, np.ndarray]:
        """(v, w) of the dynamic bodies of ``state`` [m/s, rad/s], world frame."""

    def take_max_overlap(self) -> float:
        """Largest sphere overlap since the last call [m], then reset."""

    @property
    def sphere_overlap(self) -> np.ndarray:
        """(n_spheres,) each sphere's deepest overlap at the last step or probe [m]."""

    def save_arrays(self, state, names) -> dict[str, np.ndarray]:
        """Host copies of the backend arrays ``names`` that a resumed run needs (those
        it has), after bringing ``state``'s contact histories up to date."""

    def load_arrays(self, state, arrays: dict) -> None:
        """Put ``arrays`` (as :meth:`save_arrays` gave them) back, and ``state`` with them."""


def copy_matching(backend, arrays: dict) -> None:
    """Copy each of ``arrays`` into ``backend``'s host array of the same name and shape
    (names it has no such array for are left out)."""
    for name, a in arrays.items():
        target = getattr(backend, name, None)
        if isinstance(target, np.ndarray) and target.shape == a.shape:
            target[...] = a


def nothing_moves(model, sleeping: bool, drive, body_rest, step: int) -> bool:
    """Whether steps from a State at step ``step`` with rest counts ``body_rest`` change
    nothing, so that a backend may skip them outright (counted in steps_skipped).

    They do when sleeping is on (``sleeping``, the kernels' flag, and
    model.sleep_steps > 0), every dynamic body that has started (drive.body_start) is
    asleep, every kinematic one holds still (rest count ≥ 0), nothing is prescribed
    (drive.motion_now empty: no carried body, no moving wall) and no glue bond could
    load. A sleeper moves only when something moving touches it, and nothing is left
    to: the kernels would step once, find no body awake, and skip the rest, with the
    same State bit for bit; skipped here, the step's rebuild of every sphere's list (the
    CPU) or its launches (CUDA) are saved too. The caller splits its steps at the
    emitters' start steps first (control.split_at): a body that starts is awake."""
    sleep_steps = int(model.sleep_steps)
    if (not sleeping or sleep_steps <= 0 or model.n_bonds > 0 or body_rest is None
            or drive.motion_now.shape[0] > 0):
        return False
    n = int(model.n_bodies)
    rest = np.asarray(body_rest)[:n]
    kinematic = np.asarray(model.body_inv_mass)[:n] == 0.0
    still = np.where(kinematic, rest >= 0, rest >= sleep_steps)
    return bool(np.all(still | (np.asarray(drive.body_start)[:n] > step)))


def skip_idle_call(backend, state, n_steps: int, prescribed: bool) -> bool:
    """Skip ``n_steps`` steps of ``state`` when nothing_moves says they change nothing
    (and ``backend.skip_idle``, and no Control prescribed poses this call): the State's
    step and time advance, counted in ``backend.steps_skipped``. Whether it did.
    Both backends ask it before each call's piece of steps."""
    if not backend.skip_idle or prescribed or not nothing_moves(
            backend.model, backend.features.sleeping, backend.drive, state.body_rest,
            int(state.step)):
        return False
    state.step += n_steps
    state.time = state.step * backend.model.dt
    backend.steps_skipped += n_steps
    return True
