"""USD from a bake's chunks of frames on disk (dempipe.checkpoint).

``write_usd_chunks(path, chunks, model, layout=..., start=0)`` writes the same
file ``write_usd`` writes for the frames the chunks hold, concatenated.
"""

from __future__ import annotations

import numpy as np

from ..frames import Frames


def read_chunks(chunks, start: int = 0) -> Frames:
    """The frames of ``chunks`` ((path, first frame index, frames) in order) from
    frame index ``start`` on, concatenated."""
    from ..checkpoint import load_frames

    parts = []
    for path, first, n in chunks:
        if first + n <= start:
            continue
        f = load_frames(path)
        lo = max(0, start - first)
        parts.append(Frames(f.frame_numbers[lo:], f.times[lo:], f.x[lo:], f.q[lo:],
                            f.v[lo:], f.w[lo:]))
    return Frames(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                    ("frame_numbers", "times", "x", "q", "v", "w")))


def write_usd_chunks(path, chunks, model, *, layout: str = "instancer", start: int = 0):
    """write_usd of the frames in ``chunks`` from frame index ``start`` on."""
    from .usd import write_usd

    return write_usd(path, read_chunks(chunks, start), model, layout=layout)
