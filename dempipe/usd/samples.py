"""Time samples written frame block by frame block: what lets a bake's USD file be
assembled from chunks of frames on disk without holding every frame in memory.

``FrameSource`` gives the frames in blocks, as often as asked (an in-memory
Frames is one block; ``ChunkSource`` reads a bake's chunk files one at a time).
``SparseTrack`` decides which samples to write as the frames stream past, by the
rule of usd/authoring.py's ``kept_samples`` and ``constant_columns`` (an attribute that
never changes gets a default value only; inside a run of identical samples only
its first and last are kept), so the file is the same whatever the blocks.
"""

from __future__ import annotations

import numpy as np

from dempipe.sim.frames import Frames, load_frames
from dempipe.usd.colliders import tangent_basis


class FrameSource:
    """Frames in blocks. ``blocks()`` yields Frames in order (each call starts over);
    ``n_bodies``; :meth:`scan` gathers what the writer needs from all frames first."""

    def __init__(self, frames: Frames):
        self._frames = frames
        self.n_bodies = int(np.asarray(frames.x).shape[1]) if np.asarray(frames.x).ndim == 3 \
            else -1

    def blocks(self):
        yield self._frames

    def scan(self) -> "Scan":
        s = Scan()
        for f in self.blocks():
            s.add(f)
        return s


class ChunkSource(FrameSource):
    """The frames of a bake's chunk files (dempipe.pipeline.checkpoint), from frame index
    ``start`` on; one chunk in memory at a time."""

    def __init__(self, chunks, n_bodies: int, start: int = 0):
        self.chunks = list(chunks)
        self.start = int(start)
        self.n_bodies = int(n_bodies)

    def blocks(self):

        for path, first, n in self.chunks:
            if first + n <= self.start:
                continue
            f = load_frames(path)
            lo = max(0, self.start - first)
            if lo:
                f = Frames(f.frame_numbers[lo:], f.times[lo:], f.x[lo:], f.q[lo:], f.v[lo:],
                           f.w[lo:])
            yield f


def as_source(frames) -> FrameSource:
    return frames if isinstance(frames, FrameSource) else FrameSource(frames)


class Scan:
    """What the writer needs to know of all frames before writing any: count, first
    and last frame numbers, whether they increase, the largest |coordinate| [m],
    frame 0's positions and the positions farthest out in each plane (colliders)."""

    def __init__(self):
        self.n_frames = 0
        self.first_number = None
        self.last_number = None
        self.increasing = True
        self.max_abs_x = 0.0
        self.x0 = None
        self.shapes_ok = True
        self.shape_problem = None
        self._numbers = []          # frame numbers and times [s] of every block
        self._times = []

    def add(self, f: Frames) -> None:
        fn = np.asarray(f.frame_numbers)
        if fn.size == 0:
            return
        if self.last_number is not None and not fn[0] > self.last_number:
            self.increasing = False
        if fn.size > 1 and not np.all(np.diff(fn) > 0):
            self.increasing = False
        if self.first_number is None:
            self.first_number = fn[0]
            self.x0 = np.array(f.x[0], dtype=np.float64)
        self.last_number = fn[-1]
        self.n_frames += int(fn.size)
        self._numbers.append(np.array(fn, dtype=np.float64))
        self._times.append(np.array(f.times, dtype=np.float64).reshape(-1))
        x = np.asarray(f.x, dtype=np.float64)
        if x.size:
            self.max_abs_x = max(self.max_abs_x, float(np.abs(x).max()))

    @property
    def numbers(self) -> np.ndarray:
        """(F,) frame numbers (USD time codes) of all frames."""
        return np.concatenate(self._numbers) if self._numbers else np.zeros(0)

    @property
    def times(self) -> np.ndarray:
        """(F,) simulation times [s] of all frames (what prescribed motion runs on)."""
        return np.concatenate(self._times) if self._times else np.zeros(0)

    def plane_positions(self, source: FrameSource, planes) -> np.ndarray:
        """(1 + P, B, 3) positions [m] standing in for all frames in usd._plane_quad:
        frame 0, then per plane frame 0 with its body 0 moved to the position of
        any frame farthest from frame 0's centroid within that plane. The quad's
        centre (frame 0) and half size (the largest in-plane distance) are those of
        all frames."""
        x0 = self.x0
        out = [x0]
        if x0 is None or x0.shape[0] == 0:
            return np.asarray([x0]) if x0 is not None else np.zeros((1, 0, 3))
        c0 = x0.mean(axis=0)
        best = []
        for p, n in planes:
            n = np.asarray(n, dtype=np.float64)
            n = n / np.linalg.norm(n)
            centre = c0 - np.dot(c0 - np.asarray(p, dtype=np.float64), n) * n
            best.append([centre, tangent_basis(n), -1.0, None])
        for f in source.blocks():
            pts = np.asarray(f.x, dtype=np.float64).reshape(-1, 3)
            for b in best:
                centre, (u, v), far, _ = b
                d = pts - centre
                r2 = (d @ u) ** 2 + (d @ v) ** 2
                i = int(np.argmax(r2))
                if r2[i] > far:
                    b[2], b[3] = float(r2[i]), pts[i].copy()
        for b in best:
            frame = x0.copy()
            frame[0] = b[3]
            out.append(frame)
        return np.stack(out)


class SparseTrack:
    """Streamed sample selection for K series of values (one per body, or one whole
    array): push each frame's (K, ...) values in order, then :meth:`finish`.

    ``push`` returns what it decided about earlier frames: ``(first_mask,
    prev_mask)``, the series whose frame 0 (values ``self.first``) and whose frame
    i - 1 (values ``self.prev`` until the next push) must be written. ``finish``
    returns ``(last_mask, constant_mask)``: series whose last frame to write, and
    those that never changed (a default value ``self.first`` only). The same
    samples as authoring.kept_samples / authoring.constant_columns over all frames at once.
    """

    def __init__(self, k: int):
        self.k = k
        self.i = 0
        self.first = None
        self.prev = None
        self.moved = np.zeros(k, dtype=bool)
        self.same_prev = np.zeros(k, dtype=bool)

    def push(self, values):
        values = np.asarray(values)
        none = np.zeros(self.k, dtype=bool)
        if self.i == 0:
            self.first = values.copy()
            self.prev = values
            self.i = 1
            return none, none
        axes = tuple(range(1, values.ndim))
        same = np.all(values == self.prev, axis=axes) if axes else values == self.prev
        new = ~self.moved & ~same
        keep_prev = (self.moved & ~(self.same_prev & same)) | (new if self.i > 1 else none)
        first_mask = new
        if self.i == 1:            # frame i - 1 is frame 0: written once, as "first"
            keep_prev = none
        self.moved |= new
        self.same_prev = same
        self._prev_out = self.prev
        self.prev = values
        self.i += 1
        return first_mask, keep_prev

    @property
    def prev_values(self):
        """The values of frame i - 1 of the last push."""
        return self._prev_out

    def finish(self):
        return self.moved.copy(), ~self.moved
