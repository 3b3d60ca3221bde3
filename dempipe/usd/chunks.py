"""USD from a bake's chunks of frames on disk (dempipe.pipeline.checkpoint).

``write_usd_chunks(path, chunks, model, layout=..., start=0)`` writes the file
``write_usd`` writes for the frames the chunks hold, reading one chunk at a time
(usd/samples.py), so the frames are never all in memory.
"""

from __future__ import annotations

from dempipe.usd.animation import write_usd
from dempipe.usd.samples import ChunkSource


def write_usd_chunks(path, chunks, model, *, layout: str = "instancer", start: int = 0):
    """write_usd of the frames in ``chunks`` ((path, first frame index, frames), in
    order) from frame index ``start`` on."""
    return write_usd(path, ChunkSource(chunks, model.n_bodies, start), model, layout=layout)
