"""Content-addressed, atomic, versioned disk cache of sphere sets.

One entry per key (see :func:`dempipe.spheres.sphere_set.sphere_set_key`: mesh content, diameter,
builder options and BUILDER_VERSION), stored as ``<key>.npz`` written with
``np.savez`` (no pickle) to a temporary file in the same folder, flushed, fsynced and
renamed over the target with ``os.replace``: a reader sees the old entry, the new one,
or none, never half of one. Each entry carries its format version, its own key and a
sha256 of its arrays; an entry that fails any check is deleted, reported with a
warning and treated as a miss (the caller rebuilds it).

A folder that cannot be created or written is reported once with a warning and the
cache then does nothing (``strict=False``, the library default), or raises
:class:`~dempipe.errors.CacheError` (``strict=True``, used by the CLI when the user
named the folder with ``--cache-dir``).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from dempipe.errors import CacheError
from dempipe.spheres.sphere_set import SphereSet

#: Layout version of a cache entry; entries of another version are misses.
FORMAT_VERSION = 1

_ARRAYS = ("centers", "diameter", "volume", "com", "inertia")
_TMP_PREFIX = ".tmp-"


def default_cache_dir() -> Path:
    """``$DEMPIPE_CACHE_DIR``, else the platform's user cache folder + dempipe:
    ``$XDG_CACHE_HOME/dempipe`` or ``~/.cache/dempipe`` (Linux and other Unix),
    ``~/Library/Caches/dempipe`` (macOS), ``%LOCALAPPDATA%\\dempipe\\Cache`` (Windows)."""
    env = os.environ.get("DEMPIPE_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA") or str(Path.home() / "AppData" / "Local")
        return Path(base) / "dempipe" / "Cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "dempipe"
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg and os.path.isabs(xdg):
        return Path(xdg) / "dempipe"
    return Path.home() / ".cache" / "dempipe"


def _checksum(arrays: dict) -> str:
    h = hashlib.sha256()
    for name in _ARRAYS + ("mesh_sha256", "notes"):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode() + b"\0" + str(a.dtype).encode() + b"\0")
        h.update(np.array(a.shape, dtype=np.int64).tobytes())
        h.update(a.tobytes())
    return h.hexdigest()


def _checksum_all(arrays: dict) -> str:
    h = hashlib.sha256()
    for name in sorted(k for k in arrays if k != "checksum"):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode() + b"\0" + str(a.dtype).encode() + b"\0")
        h.update(np.array(a.shape, dtype=np.int64).tobytes())
        h.update(a.tobytes())
    return h.hexdigest()


class _Corrupt(Exception):
    pass


class SphereCache:
    """Disk cache of :class:`~dempipe.spheres.sphere_set.SphereSet` by key.

    root: the folder (default :func:`default_cache_dir`); created on first write.
    strict: raise CacheError instead of warning when the folder is unusable.
    """

    def __init__(self, root=None, *, strict: bool = False):
        self.root = Path(root).expanduser() if root is not None else default_cache_dir()
        self.strict = strict
        self._disabled = False
        if strict:
            self._ensure_writable()

    def __repr__(self):
        return f"SphereCache({str(self.root)!r})"

    # -- folder ------------------------------------------------------------------

    def _ensure_writable(self) -> bool:
        """Create the folder and check that a file can be written there."""
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            fd, probe = tempfile.mkstemp(prefix=_TMP_PREFIX, dir=self.root)
            os.close(fd)
            os.unlink(probe)
            return True
        except OSError as exc:
            self._unusable(exc)
            return False

    def _unusable(self, exc: OSError) -> None:
        why = exc.strerror or str(exc)
        if self.strict:
            raise CacheError(f"cache folder {self.root} is not writable ({why}); "
                             "choose another with --cache-dir or use --no-cache") from None
        if not self._disabled:
            warnings.warn(f"sphere cache: folder {self.root} is not writable ({why}); "
                          "continuing without the cache", stacklevel=3)
        self._disabled = True

    def path_for(self, key: str) -> Path:
        """The entry file of ``key``."""
        if not key or not all(c in "0123456789abcdef" for c in key):
            raise ValueError(f"not a cache key: {key!r}")
        return self.root / f"{key}.npz"

    # -- entries -----------------------------------------------------------------

    def get(self, key: str):
        """The cached SphereSet of ``key``, or None (missing, or corrupt: deleted and warned)."""
        if self._disabled:
            return None
        path = self.path_for(key)
        if path.is_dir():       # an entry replaced by a folder: remove it, rebuild
            warnings.warn(f"sphere cache: entry {path} was a folder; removed and rebuilt",
                          stacklevel=2)
            shutil.rmtree(path, ignore_errors=True)
            return None
        if not path.is_file():
            return None
        try:
            try:
                with np.load(path, allow_pickle=False) as z:
                    data = {name: z[name] for name in z.files}
            except Exception as exc:  # zip/npy errors of a truncated or garbled file
                raise _Corrupt(f"unreadable: {type(exc).__name__}") from None
            for name in ("format_version", "key", "checksum", "mesh_sha256", "notes") + _ARRAYS:
                if name not in data:
                    raise _Corrupt(f"missing {name}")
            if int(data["format_version"]) != FORMAT_VERSION:
                raise _Corrupt(f"format version {int(data['format_version'])}, expected {FORMAT_VERSION}")
            if str(data["key"]) != key:
                raise _Corrupt("key mismatch")
            if str(data["checksum"]) != _checksum(data):
                raise _Corrupt("checksum mismatch")
            centers = data["centers"]
            if centers.dtype != np.float64 or centers.ndim != 2 or centers.shape[1] != 3 \
                    or centers.shape[0] < 1 or data["inertia"].shape != (3, 3) \
                    or data["com"].shape != (3,):
                raise _Corrupt("bad array shapes")
            return SphereSet(
                centers=centers,
                diameter=float(data["diameter"]),
                volume=float(data["volume"]),
                com=data["com"],
                inertia=data["inertia"],
                mesh_sha256=str(data["mesh_sha256"]),
                key=key,
                notes=tuple(str(n) for n in data["notes"]),
            )
        except _Corrupt as exc:
            warnings.warn(f"sphere cache: entry {path} was corrupt ({exc}); rebuilt", stacklevel=2)
            try:
                path.unlink()
            except OSError:
                pass
            return None

    def put(self, key: str, sphere_set) -> bool:
        """Store ``sphere_set`` under ``key`` atomically. False when the cache is unusable."""
        if self._disabled:
            return False
        path = self.path_for(key)
        arrays = {
            "centers": np.asarray(sphere_set.centers, dtype=np.float64),
            "diameter": np.float64(sphere_set.diameter),
            "volume": np.float64(sphere_set.volume),
            "com": np.asarray(sphere_set.com, dtype=np.float64),
            "inertia": np.asarray(sphere_set.inertia, dtype=np.float64),
            "mesh_sha256": np.str_(sphere_set.mesh_sha256),
            "notes": np.array(list(sphere_set.notes), dtype="U32"),
        }
        arrays = {k: np.asarray(v) for k, v in arrays.items()}
        arrays["format_version"] = np.asarray(FORMAT_VERSION, dtype=np.int64)
        arrays["key"] = np.asarray(key)
        arrays["checksum"] = np.asarray(_checksum(arrays))
        return self._write(path, arrays)

    def _write(self, path: Path, arrays: dict) -> bool:
        tmp = None
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=_TMP_PREFIX, suffix=".npz", dir=self.root)
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
            tmp = None
            return True
        except OSError as exc:
            self._unusable(exc)
            return False
        finally:
            if tmp is not None:
                try:
                    os.unlink(tmp)
                except OSError:
                    pass

    # -- other entries (fractured shapes: dempipe.spheres.pieces) ------------------

    def put_arrays(self, key: str, arrays: dict) -> bool:
        """Store named arrays (no object dtype) under ``key`` atomically, with the
        format version, the key and a checksum over every array. False when the
        cache is unusable."""
        if self._disabled:
            return False
        data = {k: np.asarray(v) for k, v in arrays.items()}
        data["format_version"] = np.asarray(FORMAT_VERSION, dtype=np.int64)
        data["key"] = np.asarray(key)
        data["checksum"] = np.asarray(_checksum_all(data))
        return self._write(self.path_for(key), data)

    def get_arrays(self, key: str):
        """The arrays stored by :meth:`put_arrays` under ``key`` (a dict), or None
        (missing, or corrupt: deleted and warned)."""
        if self._disabled:
            return None
        path = self.path_for(key)
        if not path.is_file():
            return None
        try:
            try:
                with np.load(path, allow_pickle=False) as z:
                    data = {name: z[name] for name in z.files}
            except Exception as exc:  # zip/npy errors of a truncated or garbled file
                raise _Corrupt(f"unreadable: {type(exc).__name__}") from None
            for name in ("format_version", "key", "checksum"):
                if name not in data:
                    raise _Corrupt(f"missing {name}")
            if int(data["format_version"]) != FORMAT_VERSION or str(data["key"]) != key:
                raise _Corrupt("version or key mismatch")
            if str(data["checksum"]) != _checksum_all(data):
                raise _Corrupt("checksum mismatch")
        except _Corrupt as exc:
            warnings.warn(f"sphere cache: entry {path} was corrupt ({exc}); rebuilt", stacklevel=2)
            try:
                path.unlink()
            except OSError:
                pass
            return None
        return {k: v for k, v in data.items() if k not in ("format_version", "key", "checksum")}

    def _entries(self):
        if not self.root.is_dir():
            return []
        # a folder in an entry's place counts as an entry, so `cache clear` mends it
        return sorted(p for p in self.root.glob("*.npz")
                      if (p.is_file() or p.is_dir()) and not p.name.startswith(_TMP_PREFIX))

    def info(self) -> dict:
        """{"location": folder (str), "entries": count, "bytes": total size}."""
        entries = self._entries()
        size = 0
        for p in entries:
            try:
                size += p.stat().st_size if p.is_file() else 0
            except OSError:
                pass
        return {"location": str(self.root), "entries": len(entries), "bytes": size}

    def clear(self) -> int:
        """Delete every entry (and temporary files older than an hour, left by killed
        writers); returns how many entries went."""
        removed = 0
        for p in self._entries():
            try:
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p)
                else:
                    p.unlink()
                removed += 1
            except FileNotFoundError:
                pass
            except OSError as exc:
                raise CacheError(f"cannot remove {p} ({exc.strerror or exc})") from None
        if self.root.is_dir():
            now = time.time()
            for p in self.root.glob(_TMP_PREFIX + "*"):
                try:
                    if now - p.stat().st_mtime > 3600:
                        p.unlink()
                except OSError:
                    pass
        return removed
