"""A bake's work folder: frames streamed to disk in chunks, and checkpoints to resume.

A bake to ``out.usdc`` keeps, beside it, the hidden folder ``.out.usdc.bake/``::

    meta.json            what the folder holds (written last: the commit point)
    chunk-000000.npz     frames 0 .. a-1: frame numbers, times, x, q, v, w (float64)
    chunk-000001.npz     frames a .. b-1
    state-000001.npz     the State (and the backend's persistent arrays) after frame b-1

Frames are buffered in memory for one chunk at most (CHUNK_BYTES), so the memory
of a bake does not grow with its number of frames; the USD file is assembled
from the chunks at the end (dempipe.usd.chunks.write_usd_chunks) and the folder
is removed. Once CHECKPOINT_SECONDS have passed since the last checkpoint (or
after every chunk, when ``chunk_frames`` is given), the frames buffered go to a
chunk and a checkpoint follows: the full State, what the
simulator needs to go on (Simulator.run_point) and the backend's arrays that
carry from one step call to the next (PERSISTENT). ``dempipe bake --resume``
(``bake(..., resume=True)``) continues from the last one and, on the CPU, writes
the very bits an uninterrupted bake writes. Every file is written to a
temporary name, flushed, fsynced and renamed; meta.json is replaced last, so a
bake killed at any instant (SIGKILL, power loss) leaves the last checkpoint
whole and loses only the frames computed since.

A checkpoint records a fingerprint of the Model (every array and number that
the steps read: the scene file, its meshes, materials and settings all end up
there), the device, the frames asked for and the dempipe version; resuming with
any of them changed is refused (:class:`CheckpointError`).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np

from dempipe import interrupt
from dempipe.errors import DempipeError, ExportError
from dempipe.pipeline.lock import LOCK_NAME, work_dir
from dempipe.sim.frames import Frames, save_frames, save_npz
from dempipe.sim.simulator import RunPoint, RunStats
from dempipe.version import __version__

#: Format of meta.json; a folder of another format is refused. Format 2 records each
#: file's size and SHA-256, verified before a resume runs anything.
FORMAT = 2
#: Frames are written out once the buffered ones hold this many bytes.
CHUNK_BYTES = 8 << 20
#: ... or once this many seconds of wall time have passed since the last checkpoint:
#: what a SIGKILL can lose at most (besides the frame being computed).
CHECKPOINT_SECONDS = 60.0
#: Backend arrays that carry from one `step` call to the next and change results
#: (kernels/cpu/stages.py CpuBackend): which bodies a moving body woke, which slept
#: through the last step, the neighbour lists' adaptive skin (it changes only
#: the rebuild schedule, kept so that a resumed bake rebuilds when the first did).
PERSISTENT = ("body_wake", "body_still", "skin_ctl")
#: The State's arrays (state.State), saved when present.
STATE_ARRAYS = ("body_x", "body_q", "body_P", "body_L", "contact_partner", "contact_spring",
                "body_rest", "bond_broken", "bond_shear")


class CheckpointError(DempipeError):
    """A checkpoint that cannot be resumed (another scene, settings or version)."""


def model_fingerprint(model) -> str:
    """SHA-256 of what the steps read from ``model``: every array and number field
    (build_info, which holds timings, is left out), the shapes' and static meshes'
    geometry."""
    h = hashlib.sha256()

    def add(name, v):
        h.update(name.encode())
        if isinstance(v, np.ndarray):
            h.update(str(v.dtype).encode() + str(v.shape).encode())
            h.update(np.ascontiguousarray(v).tobytes())
        else:
            h.update(repr(v).encode())

    for f in fields(model):
        if f.name in ("build_info", "shapes", "static_meshes", "boxes", "materials"):
            continue
        add(f.name, getattr(model, f.name))
    for i, s in enumerate(model.shapes):
        add(f"shape{i}", s.name)
        add(f"shape{i}.v", np.asarray(s.vertices))
        add(f"shape{i}.f", np.asarray(s.faces))
        add(f"shape{i}.c", np.asarray(s.sphere_set.centers))
    for i, m in enumerate(model.static_meshes):
        add(f"static{i}", m.name)
        add(f"static{i}.v", np.asarray(m.vertices))
    for i, b in enumerate(model.boxes):
        add(f"box{i}", (np.asarray(b.lo).tolist(), np.asarray(b.hi).tolist(),
                        bool(getattr(b, "open_top", False))))
    add("materials", repr(model.materials))
    return h.hexdigest()


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: Path, write) -> None:
    """``write(file)`` into a temporary file beside ``path``, fsync, rename over it.
    The temporary file is removed on any failure or interrupt."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with interrupt.temporary(tmp):
        try:
            with open(tmp, "wb") as fh:
                write(fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            try:
                tmp.unlink()
            except OSError:
                pass
            raise
    _fsync_dir(path.parent)


def write_error(path, exc: OSError, what: str) -> DempipeError:
    """One line naming the path and the OS's reason."""
    why = exc.strerror or str(exc) or type(exc).__name__
    return ExportError(f"{path}: cannot write {what} ({why})")


def file_digest(path: Path) -> tuple[int, str]:
    """(size in bytes, SHA-256 hex) of ``path``."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(1 << 20):
            h.update(block)
    return path.stat().st_size, h.hexdigest()


def read_meta(folder: Path) -> dict:
    """meta.json of a work folder, its files verified against the sizes and checksums
    it records: CheckpointError, one line naming the damaged file, when any is missing,
    truncated or altered (a damaged checkpoint would fail only after re-simulating)."""
    again = "bake again without --resume to start over"
    try:
        meta = json.loads((folder / "meta.json").read_text())
        if not isinstance(meta, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise CheckpointError(f"{folder / 'meta.json'}: the checkpoint cannot be read "
                              f"({why}); {again}") from None
    if meta.get("format") != FORMAT or meta.get("dempipe") != __version__:
        raise CheckpointError(
            f"{folder}: the checkpoint was written by dempipe {meta.get('dempipe')} "
            f"(format {meta.get('format')}), this is dempipe {__version__}; it cannot be "
            f"resumed: {again}")
    try:
        files = [(c[0], int(c[3]), str(c[4])) for c in meta["chunks"]]
        for c in meta["chunks"]:
            int(c[1]), int(c[2])
        if meta.get("state"):
            files.append((meta["state"], int(meta["state_bytes"]), str(meta["state_sha256"])))
        int(meta["frames_done"])
    except (KeyError, TypeError, ValueError, IndexError):
        raise CheckpointError(f"{folder / 'meta.json'}: the checkpoint's record is "
                              f"incomplete or altered; {again}") from None
    for name, size, sha in files:
        path = folder / str(name)
        if Path(str(name)).name != str(name) or not path.is_file():
            raise CheckpointError(f"{path}: a file of the checkpoint is missing; {again}")
        try:
            got_size, got_sha = file_digest(path)
        except OSError as exc:
            raise CheckpointError(f"{path}: cannot read the checkpoint "
                                  f"({exc.strerror or exc}); {again}") from None
        if got_size != size:
            raise CheckpointError(f"{path}: the checkpoint file is damaged ({got_size} bytes, "
                                  f"{size} written); {again}")
        if got_sha != sha:
            raise CheckpointError(f"{path}: the checkpoint file is damaged (its checksum "
                                  f"differs from the one written); {again}")
    return meta


class FrameBuffer:
    """Up to ``capacity`` frames in memory, in the layout of Frames."""

    def __init__(self, n_bodies: int, capacity: int):
        self.frames = Frames.empty(capacity, n_bodies)
        self.first = 0          # frame index of row 0
        self.n = 0

    def add(self, k: int, frame_number: int, t: float, x, q, v, w) -> None:
        if self.n == 0:
            self.first = k
        f, i = self.frames, self.n
        f.frame_numbers[i] = frame_number
        f.times[i] = t
        f.x[i] = x
        f.q[i] = q
        f.v[i] = v
        f.w[i] = w
        self.n += 1

    @property
    def full(self) -> bool:
        return self.n >= self.frames.n_frames

    def view(self) -> Frames:
        f, n = self.frames, self.n
        return Frames(f.frame_numbers[:n], f.times[:n], f.x[:n], f.q[:n], f.v[:n], f.w[:n])






class BakeStore:
    """The work folder of one bake (see the module docstring).

    out : the bake's output path; fingerprint : model_fingerprint of its Model;
    settings : what else must match to resume (device, frames).
    chunk_frames : frames per chunk (default: CHUNK_BYTES' worth);
    checkpoint_seconds : a chunk and checkpoint at least this often.
    """

    def __init__(self, out, fingerprint: str, settings: dict, n_bodies: int, *,
                 chunk_frames: int | None = None,
                 checkpoint_seconds: float = CHECKPOINT_SECONDS):
        self.out = Path(out)
        self.dir = work_dir(out)
        self.fingerprint = fingerprint
        self.settings = dict(settings)
        frame_bytes = 16 + n_bodies * 13 * 8
        self.chunk_frames = int(chunk_frames or max(1, CHUNK_BYTES // frame_bytes))
        #: a checkpoint after every chunk (chunk_frames given), else once
        #: checkpoint_seconds have passed (chunks in between hold frames only)
        self.every_chunk = chunk_frames is not None
        self.checkpoint_seconds = float(checkpoint_seconds)
        self.buffer = FrameBuffer(n_bodies, self.chunk_frames)
        self.chunks: list = []        # [file, first frame index, frames] up to the checkpoint
        self.tail: list = []          # chunks written since (committed by the next one)
        self.frames_done = 0          # frames in self.chunks
        self.state_file = None
        self.state_bytes, self.state_sha256 = 0, ""
        self.point: dict | None = None
        self.last_checkpoint = time.monotonic()
        self.checkpoint_seconds_spent = 0.0
        self.checkpoints = 0

    # -- create / open ------------------------------------------------------------
    def create(self) -> None:
        """Start an empty folder (an old one's files are removed, its lock kept)."""
        self.clear()
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise write_error(self.dir, exc, "the bake's work folder") from None
        self._write_meta()

    def exists(self) -> bool:
        return (self.dir / "meta.json").is_file()

    def open(self) -> None:
        """Load the folder's last checkpoint; CheckpointError when it does not fit
        or a file of it is missing or damaged (read_meta)."""
        where = self.dir
        meta = read_meta(where)
        if meta.get("fingerprint") != self.fingerprint:
            raise CheckpointError(
                f"{where}: the checkpoint is of another scene: the scene file, a mesh it uses "
                f"or its settings changed since it was written; bake again without --resume "
                f"(or restore the scene as it was)")
        for k, v in self.settings.items():
            if meta.get("settings", {}).get(k) != v:
                raise CheckpointError(
                    f"{where}: the checkpoint was baked with {k} = "
                    f"{meta.get('settings', {}).get(k)!r}, this bake asks for {v!r}; resume "
                    f"with the same {k}, or bake again without --resume")
        self.chunks = [list(c) for c in meta["chunks"]]
        self.frames_done = int(meta["frames_done"])
        self.state_file = meta.get("state")
        self.state_bytes = int(meta.get("state_bytes", 0))
        self.state_sha256 = str(meta.get("state_sha256", ""))
        self.point = meta.get("point")
        self.checkpoints = int(meta.get("checkpoints", 0))
        # chunks written after the checkpoint (a stop that did not save the State)
        # are recomputed: remove them
        keep = {c[0] for c in self.chunks} | {self.state_file, "meta.json", LOCK_NAME}
        for p in self.dir.iterdir():
            if p.name not in keep:
                p.unlink(missing_ok=True)

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)

    def clear(self) -> None:
        """Remove the folder's files but its lock (pipeline.lock), held by this bake."""
        if not self.dir.is_dir():
            return
        for p in self.dir.iterdir():
            if p.name == LOCK_NAME:
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)

    # -- frames -------------------------------------------------------------------
    def add(self, k: int, frame_number: int, state, v, w) -> None:
        """Buffer frame ``k`` (the dynamic bodies of ``state``)."""
        nb = v.shape[0]
        self.buffer.add(k, frame_number, state.time, state.body_x[:nb], state.body_q[:nb],
                        v, w)

    def due(self) -> bool:
        """Whether a checkpoint is due now (after the frame just added)."""
        if self.every_chunk:
            return self.buffer.full
        return time.monotonic() - self.last_checkpoint >= self.checkpoint_seconds

    def _write_chunk(self) -> list | None:
        if self.buffer.n == 0:
            return None
        index = len(self.chunks) + len(self.tail)
        name = f"chunk-{index:06d}.npz"
        frames = self.buffer.view()
        try:
            atomic_write(self.dir / name, lambda fh: save_frames(fh, frames))
            size, sha = file_digest(self.dir / name)
        except OSError as exc:
            raise write_error(self.dir / name, exc, "frames") from None
        entry = [name, int(self.buffer.first), int(self.buffer.n), size, sha]
        self.buffer.n = 0
        return entry

    def checkpoint(self, sim, state) -> None:
        """Write the buffered frames and a checkpoint of ``state`` (consistent: after
        a finished step call) with ``sim``'s run point and backend arrays."""
        t0 = time.perf_counter()
        entry = self._write_chunk()
        if entry is not None:
            self.tail.append(entry)
        # what the folder holds until this checkpoint's meta.json replaces the last one:
        # restored when a write fails (a full disk), so messages and a later stop tell
        # the checkpoint that is really there
        before = (list(self.chunks), list(self.tail), self.frames_done, self.state_file,
                  self.state_bytes, self.state_sha256, self.point, self.checkpoints)
        try:
            old = self._commit(sim, state)
        except BaseException:
            (self.chunks, self.tail, self.frames_done, self.state_file, self.state_bytes,
             self.state_sha256, self.point, self.checkpoints) = before
            raise
        if old and old != self.state_file:
            (self.dir / old).unlink(missing_ok=True)
        self.last_checkpoint = time.monotonic()
        self.checkpoint_seconds_spent += time.perf_counter() - t0

    def _commit(self, sim, state) -> str | None:
        """Write the State and meta.json committing the tail's chunks; returns the
        previous State file's name (removed by the caller once meta.json is written)."""
        self.chunks += self.tail          # committed with this checkpoint's meta.json
        self.tail = []
        self.frames_done = sum(c[2] for c in self.chunks)
        saved = sim.backend.save_arrays(state, PERSISTENT)
        arrays = {f"state.{n}": getattr(state, n) for n in STATE_ARRAYS
                  if getattr(state, n, None) is not None}
        arrays.update({f"backend.{n}": a for n, a in saved.items()})
        name = f"state-{self.frames_done:06d}.npz"
        try:
            atomic_write(self.dir / name, lambda fh: save_npz(fh, arrays))
            self.state_bytes, self.state_sha256 = file_digest(self.dir / name)
        except OSError as exc:
            raise write_error(self.dir / name, exc, "a checkpoint") from None
        old = self.state_file
        self.state_file = name
        p = sim.run_point()
        stats = asdict(p.stats)
        self.point = dict(base_step=p.base_step, first_number=p.first_number, e0=p.e0,
                          gain=p.gain, frames_done=p.frames_done,
                          pending_overlap=p.pending_overlap, stats=stats,
                          step=int(state.step), time=float(state.time))
        self.checkpoints += 1
        self._write_meta()
        return old

    def keep_tail(self) -> None:
        """Write the buffered frames without a checkpoint (a full chunk between two
        checkpoints, or a stop that left the State unusable): they count for the
        file; a resume from the last checkpoint recomputes them."""
        entry = self._write_chunk()
        if entry is not None:
            self.tail.append(entry)

    def _write_meta(self) -> None:
        meta = dict(format=FORMAT, dempipe=__version__, fingerprint=self.fingerprint,
                    settings=self.settings, output=str(self.out), chunks=self.chunks,
                    frames_done=self.frames_done, state=self.state_file, point=self.point,
                    state_bytes=self.state_bytes, state_sha256=self.state_sha256,
                    checkpoints=self.checkpoints)
        text = json.dumps(meta, indent=1).encode()
        try:
            atomic_write(self.dir / "meta.json", lambda fh: fh.write(text))
        except OSError as exc:
            raise write_error(self.dir / "meta.json", exc, "a checkpoint") from None

    # -- resume ---------------------------------------------------------------------
    def restore(self, sim, state):
        """Put the checkpoint's State into ``state`` and its arrays into ``sim``'s
        backend; returns the simulator.RunPoint to pass to Simulator.run."""
        import zipfile

        backend = {}
        path = self.dir / self.state_file
        try:
            with np.load(path, allow_pickle=False) as z:
                for key in z.files:
                    kind, name = key.split(".", 1)
                    if kind == "state":
                        setattr(state, name, np.array(z[key]))
                    else:
                        backend[name] = np.array(z[key])
            p = self.point
            state.step = int(p["step"])
            state.time = float(p["time"])
        except (OSError, EOFError, ValueError, KeyError, TypeError,
                zipfile.BadZipFile) as exc:
            # read_meta verified the file; this is one written wrong, not damaged since
            raise CheckpointError(f"{path}: the checkpoint cannot be read "
                                  f"({type(exc).__name__}); bake again without --resume "
                                  f"to start over") from None
        sim.backend.load_arrays(state, backend)
        return RunPoint(base_step=int(p["base_step"]), first_number=int(p["first_number"]),
                        e0=float(p["e0"]), gain=float(p["gain"]),
                        frames_done=int(p["frames_done"]),
                        pending_overlap=float(p["pending_overlap"]),
                        stats=RunStats(**p["stats"]))

    def frame_chunks(self, include_tail: bool = True):
        """The chunks' file paths with (first frame index, frames), in order."""
        for name, first, n, *_ in self.chunks + (self.tail if include_tail else []):
            yield self.dir / name, first, n

    def frames_kept(self, include_tail: bool = True) -> int:
        return sum(c[2] for c in self.chunks + (self.tail if include_tail else []))
