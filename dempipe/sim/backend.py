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
