"""`dempipe bake` as a child process: start, progress, cancel, result.

No bpy here: the operator's modal timer and the blocking path (Blender in
background mode, the tests) both call :meth:`BakeJob.poll`. The child's stderr is
read by a thread, so Blender's main loop never blocks on a pipe; its progress
lines (``[####    ] frame 3/13 ...``, one per 5 s when stderr is not a terminal)
give the fraction done; its stderr is a pseudo-terminal, so that dempipe updates
that line every frame.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

_FRAME = re.compile(r"frame (\d+)/(\d+)")


def find_executable(preferred: str = "") -> str | None:
    """The `dempipe` to run: the one set in the preferences, else the one on PATH."""
    if preferred:
        p = Path(bpy_abspath(preferred)).expanduser()
        return str(p) if p.is_file() and os.access(p, os.X_OK) else None
    return shutil.which("dempipe")


def bpy_abspath(path: str) -> str:
    """A ``//``-relative Blender path made absolute (plain paths pass through)."""
    try:
        import bpy

        return bpy.path.abspath(path)
    except ImportError:
        return path


def work_dir(out: Path) -> Path:
    """dempipe's work folder of a bake to ``out`` (dempipe.pipeline.checkpoint.work_dir)."""
    return out.with_name(f".{out.name}.bake")


def resumable(out: Path) -> bool:
    """Whether a stopped bake to ``out`` left a checkpoint to go on from."""
    return (work_dir(out) / "meta.json").is_file()


class BakeJob:
    """One `dempipe bake SCENE -o OUT` child process.

    ``fraction`` (0-1) and ``status`` follow its progress lines; after it ends,
    ``returncode`` is set and ``error`` is dempipe's one-line message (its last
    stderr line) when it failed."""

    def __init__(self, executable: str, scene: Path, out: Path, *, device: str = "auto",
                 resume: bool = False, checkpoint_seconds: float | None = None,
                 extra: tuple = ()):
        self.out = Path(out)
        args = [executable, "bake", str(scene), "-o", str(out), "--layout", "xforms",
                "--device", device]
        if resume:
            args.append("--resume")     # without it a bake starts over (an old work folder goes)
        if checkpoint_seconds is not None:
            args += ["--checkpoint-every", repr(float(checkpoint_seconds))]
        args += list(extra)
        self.args = args
        self.fraction = 0.0
        self.status = "starting dempipe"
        self.lines: list[str] = []
        self.returncode: int | None = None
        self.cancelled = False
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # stderr on a pseudo-terminal where there is one: dempipe then updates its
        # progress line every frame (to a pipe it writes one every 5 s, for logs)
        try:
            self._fd, slave = os.openpty()
        except (AttributeError, OSError):
            self._fd, slave = None, subprocess.PIPE
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=slave,
                                     stdin=subprocess.DEVNULL, env=env,
                                     cwd=str(Path(scene).parent))
        if self._fd is not None:
            os.close(slave)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _chunk(self) -> bytes:
        if self._fd is None:
            return self.proc.stderr.read1(4096)
        try:
            return os.read(self._fd, 4096)
        except OSError:             # EIO: the child closed the terminal (it ended)
            return b""

    def _read(self) -> None:
        buf = b""
        while True:
            chunk = self._chunk()
            if not chunk:
                if self._fd is not None:
                    os.close(self._fd)
                break
            buf += chunk
            parts = re.split(rb"[\r\n]", buf)
            buf = parts.pop()
            for part in parts:
                self._line(part.decode("utf-8", "replace").strip())
        if buf:
            self._line(buf.decode("utf-8", "replace").strip())

    def _line(self, line: str) -> None:
        if not line:
            return
        self.lines.append(line)
        m = _FRAME.search(line)
        if m:
            done, n = int(m.group(1)), int(m.group(2))
            self.fraction = done / max(n, 1)
            self.status = f"dempipe: frame {done}/{n}"
        elif not line.startswith("warning:"):
            self.status = f"dempipe: {line[:120]}"

    def poll(self) -> bool:
        """True once the child has ended (then ``returncode`` is set)."""
        if self.returncode is None and self.proc.poll() is not None:
            self._reader.join(timeout=5)
            self.returncode = self.proc.returncode
        return self.returncode is not None

    def wait(self, on_progress=None, interval: float = 0.1, timeout: float | None = None) -> int:
        """Block until the child ends, calling ``on_progress(job)`` every ``interval`` s."""
        t0 = time.monotonic()
        while not self.poll():
            if on_progress is not None:
                on_progress(self)
            if timeout is not None and time.monotonic() - t0 > timeout:
                self.cancel()
                timeout = None
            time.sleep(interval)
        return self.returncode

    def cancel(self) -> None:
        """SIGINT, as Ctrl-C: dempipe writes the frames done to a .partial file and
        keeps its work folder, so a later bake with --resume goes on."""
        if self.proc.poll() is None:
            self.cancelled = True
            self.proc.send_signal(signal.SIGINT)

    @property
    def ok(self) -> bool:
        return self.returncode == 0

    @property
    def error(self) -> str:
        """dempipe's one-line message: its last line that is not progress."""
        if self.cancelled and self.returncode in (130, -signal.SIGINT):
            return "cancelled: the bake can be resumed"
        for line in reversed(self.lines):
            if not _FRAME.search(line):
                return line
        return f"dempipe exited with code {self.returncode}"
