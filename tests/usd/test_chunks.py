"""USD written from frames in blocks (a bake's chunks on disk) equals USD written
from all frames at once, and keeps exactly the samples of the sparse rule
(kept_samples / constant_columns): what a bake that streams its frames to disk writes."""

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")
from pxr import Sdf  # noqa: E402

from dempipe.pipeline.checkpoint import FrameBuffer  # noqa: E402
from dempipe.sim.frames import save_frames  # noqa: E402
from dempipe.usd import animation as usd  # noqa: E402
from dempipe.usd.samples import ChunkSource  # noqa: E402
from dempipe.sim.frames import Frames  # noqa: E402
from dempipe.usd.authoring import constant_columns, kept_samples  # noqa: E402
from test_animation import make_model  # noqa: E402


def tricky_frames(n_frames=23, n_bodies=7, seed=1):
    """Bodies that never move, move only late, stop and start again, and one whose
    velocity is non-zero while its position stays put."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n_frames, n_bodies, 3))
    q = np.zeros((n_frames, n_bodies, 4))
    q[..., 0] = 1.0
    v = np.zeros_like(x)
    w = np.zeros_like(x)
    x[:] = rng.normal(size=(n_bodies, 3))               # body 0: never moves
    x[9:, 1, 2] += np.arange(n_frames - 9) * 0.01       # body 1: moves from frame 9
    x[3:7, 2, 0] += 0.5                                 # body 2: steps, rests, steps back
    x[15:, 2, 0] -= 0.25
    q[5:, 3] = [0.8, 0.6, 0.0, 0.0]                     # body 3: turns once at frame 5
    x[:, 4:] += rng.normal(size=(n_frames, n_bodies - 4, 3)) * 0.01   # 4..: move always
    v[11:14, 0, 1] = 1.0                                # body 0: a rate while it rests
    w[2:4, 3, 2] = 3.0
    fn = np.arange(n_frames) + 1
    return Frames(fn, fn / 24.0, x, q, v, w)


def chunk_files(tmp_path, frames, size):
    out = []
    for a in range(0, frames.n_frames, size):
        b = min(frames.n_frames, a + size)
        buf = FrameBuffer(frames.n_bodies, b - a)
        for k in range(a, b):
            buf.add(k, frames.frame_numbers[k], frames.times[k], frames.x[k], frames.q[k],
                    frames.v[k], frames.w[k])
        path = tmp_path / f"c{a}.npz"
        with open(path, "wb") as fh:
            save_frames(fh, buf.view())
        out.append((path, a, b - a))
    return out


def layer_samples(path):
    layer = Sdf.Layer.FindOrOpen(str(path))
    out = {}

    def visit(p):
        spec = layer.GetAttributeAtPath(p) if p.IsPropertyPath() else None
        if spec is None:
            return
        if spec.default is not None:
            out[(str(p), "default")] = np.array(spec.default)
        for t in layer.ListTimeSamplesForPath(p):
            out[(str(p), t)] = np.array(layer.QueryTimeSample(p, t))

    layer.Traverse(layer.pseudoRoot.path, visit)
    return out


def expected_times(values, sparse=True):
    """The frames the whole-bake rule keeps for (F, K, ...) values: None per series
    for a default only."""
    flat = values.reshape(values.shape[0], values.shape[1], -1)
    keep = kept_samples(flat)
    const = constant_columns(flat)
    return [None if const[k] else np.flatnonzero(keep[:, k]) for k in range(flat.shape[1])]


@pytest.mark.parametrize("layout", ["xforms", "instancer"])
@pytest.mark.parametrize("size", [1, 2, 5, 23])
def test_blocks_write_what_all_frames_write(tmp_path, layout, size):
    model = make_model()
    frames = tricky_frames()
    whole = tmp_path / "whole.usda"
    usd.write_usd(whole, frames, model, layout=layout)
    streamed = tmp_path / "streamed.usda"
    info = usd.write_usd(streamed, ChunkSource(chunk_files(tmp_path, frames, size), 7),
                         model, layout=layout)
    a, b = layer_samples(whole), layer_samples(streamed)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k
    assert info.n_time_samples == sum(1 for k in b if k[1] != "default")


def test_xforms_keep_the_sparse_rule(tmp_path):
    # The streamed writer against the rule over all frames: per body, the frames of
    # kept_samples, or a default only where constant_columns.
    model = make_model()
    frames = tricky_frames()
    path = tmp_path / "x.usda"
    usd.write_usd(path, ChunkSource(chunk_files(tmp_path, frames, 4), 7), model,
                  layout="xforms")
    layer = Sdf.Layer.FindOrOpen(str(path))
    trans = usd.flush_tiny(frames.x.copy() / model.meters_per_unit)
    want = expected_times(trans)
    assert want[0] is None and len(want[4]) == 23
    assert list(want[1]) == [0] + list(range(9, 23))       # rests until 9, moves from 10
    assert list(want[2]) == [0, 2, 3, 6, 7, 14, 15, 22]     # the ends of each run
    for b in range(7):
        g = model.group_names[model.body_group[b]]
        p = Sdf.Path(f"/World/Bodies/{g}/{g}_{model.body_group_index[b]}.xformOp:translate")
        times = layer.ListTimeSamplesForPath(p)
        if want[b] is None:
            assert not times and layer.GetAttributeAtPath(p).default is not None
        else:
            assert np.array_equal(np.array(times) - 1, want[b]), (b, times, want[b])
