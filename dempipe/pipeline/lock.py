"""One bake per output at a time: an OS lock on a file in the bake's work folder.

Two bakes to the same output would share a work folder: the first would write a file
of mixed frames and the second fail on a chunk the first removed. ``WorkLock`` takes
``fcntl.flock`` on ``.NAME.bake/lock`` before the bake reads anything; a second bake
finds it held and is refused up front. The kernel drops the lock when its process
ends however it ends (SIGKILL, the OOM killer), so a killed bake never leaves a
stale lock that would block ``--resume``.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from dempipe.errors import DempipeError

#: The lock file's name inside the work folder; the work folder's code keeps it.
LOCK_NAME = "lock"


def work_dir(out) -> Path:
    """The work folder of a bake to ``out``: ``.NAME.bake`` beside it."""
    out = Path(out)
    return out.with_name(f".{out.name}.bake")


class BakeLockedError(DempipeError):
    """Another bake to the same output is running."""


class WorkLock:
    """``flock`` on ``folder/lock``; ``acquire`` creates the folder (and the output's
    folders) if missing, and ``release`` removes them again when the lock file is all
    they hold (a bake that failed on its scene leaves nothing behind)."""

    def __init__(self, folder, out):
        self.folder = Path(folder)
        self.out = Path(out)
        self.path = self.folder / LOCK_NAME
        self.fd: int | None = None
        self.created: list = []

    def acquire(self) -> None:
        """Take the lock or raise BakeLockedError naming the other bake's process."""
        try:
            missing = []
            up = self.folder
            while not up.exists() and up != up.parent:
                missing.append(up)
                up = up.parent
            self.folder.mkdir(parents=True, exist_ok=True)
            self.created = missing         # deepest first: removed again if left empty
        except FileExistsError:
            pass
        except OSError as exc:
            from dempipe.errors import ExportError

            raise ExportError(f"{self.folder}: cannot create the bake's work folder "
                              f"({exc.strerror or exc})") from None
        for _ in range(20):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                other = _read_pid(fd)
                os.close(fd)
                who = f" (process {other})" if other else ""
                raise BakeLockedError(
                    f"{self.out}: another bake to this output is running{who}; its work "
                    f"folder {self.folder} is in use: wait for it to finish, or give "
                    f"another -o") from None
            # the holder before us may have removed the file while we waited on it:
            # a lock on a removed file locks nothing
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                self.fd = fd
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                return
            os.close(fd)
            self.folder.mkdir(parents=True, exist_ok=True)
        raise BakeLockedError(f"{self.out}: cannot lock the work folder {self.folder}")

    def release(self) -> None:
        """Drop the lock; remove the folder when nothing but the lock file is left."""
        if self.fd is None:
            return
        try:
            left = [p.name for p in self.folder.iterdir()] if self.folder.is_dir() else []
            if left == [LOCK_NAME]:
                self.path.unlink(missing_ok=True)       # still held: no one locks it now
                for folder in self.created or [self.folder]:
                    try:
                        folder.rmdir()      # only when empty: a written output stays
                    except OSError:
                        break
        finally:
            os.close(self.fd)
            self.fd = None

    def __enter__(self):
        self.acquire()
        return self

    def __exit__(self, *exc):
        self.release()


def _read_pid(fd: int) -> int | None:
    try:
        return int(os.pread(fd, 32, 0).decode().strip() or 0) or None
    except (OSError, ValueError):
        return None
