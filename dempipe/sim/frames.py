"""Frames: the recorded animation, one row per output frame.

Frames are what the simulator hands to the exporters. They hold the dynamic
bodies only (static colliders never move), in scene order.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass

import numpy as np


@dataclass
class Frames:
    """Body motion sampled at output frames.

    Attributes
    ----------
    frame_numbers : (F,) int64
        USD time codes of the frames (frame 0 is the initial state).
    times : (F,) float64
        Simulated time of each frame [s].
    x : (F, B, 3) float64
        Centre of mass of each body, world frame [m].
    q : (F, B, 4) float64
        Orientation of each body as a unit quaternion (w, x, y, z), body to world.
    v : (F, B, 3) float64
        Linear velocity of the centre of mass, world frame [m/s].
    w : (F, B, 3) float64
        Angular velocity, world frame [rad/s].
    """

    frame_numbers: np.ndarray
    times: np.ndarray
    x: np.ndarray
    q: np.ndarray
    v: np.ndarray
    w: np.ndarray

    @classmethod
    def empty(cls, n_frames: int, n_bodies: int) -> "Frames":
        """Preallocated frames to be filled by the simulator."""
        return cls(
            frame_numbers=np.zeros(n_frames, dtype=np.int64),
            times=np.zeros(n_frames, dtype=np.float64),
            x=np.zeros((n_frames, n_bodies, 3)),
            q=np.zeros((n_frames, n_bodies, 4)),
            v=np.zeros((n_frames, n_bodies, 3)),
            w=np.zeros((n_frames, n_bodies, 3)),
        )

    @property
    def n_frames(self) -> int:
        return int(self.times.shape[0])

    @property
    def n_bodies(self) -> int:
        return int(self.x.shape[1])

    def head(self, n: int) -> "Frames":
        """The first ``n`` frames (used to keep what a failed bake had done)."""
        return Frames(
            self.frame_numbers[:n].copy(), self.times[:n].copy(), self.x[:n].copy(),
            self.q[:n].copy(), self.v[:n].copy(), self.w[:n].copy(),
        )


def save_npz(fh, arrays: dict) -> None:
    """Write ``arrays`` (name -> array) to the open binary file ``fh`` as np.savez does
    (an uncompressed .npz that np.load reads), the archive closed even when a write
    fails: np.savez leaves it open on a full disk, and its finaliser then printed
    "Exception ignored ... seek of closed file" to stderr after the one-line error."""
    with zipfile.ZipFile(fh, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as z:
        for name, a in arrays.items():
            with z.open(name + ".npy", mode="w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)


def save_frames(fh, frames: Frames) -> None:
    """Write ``frames`` to the open binary file ``fh`` (.npz; what :func:`load_frames` reads)."""
    save_npz(fh, dict(frame_numbers=frames.frame_numbers, times=frames.times, x=frames.x,
                      q=frames.q, v=frames.v, w=frames.w))


def load_frames(path) -> Frames:
    """The Frames written by :func:`save_frames` to ``path``."""
    with np.load(path) as z:
        return Frames(z["frame_numbers"], z["times"], z["x"], z["q"], z["v"], z["w"])
