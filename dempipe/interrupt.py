"""Stop requests: SIGINT, SIGTERM and SIGHUP stop a bake cleanly, a second one at once.

Render-farm managers (Deadline, Tractor, OpenCue, SLURM) stop and preempt tasks
with SIGTERM, a closed terminal sends SIGHUP, a user presses Ctrl-C. With the
handlers of :func:`install` in place:

* the first signal records itself (:func:`requested`). Outside a
  :func:`deferred` block it also raises :class:`StopRequested` (a
  KeyboardInterrupt) in the main thread at once, so start-up, imports, sphere
  building and the USD export stop within a bytecode; but not while a native
  extension module initialises (an exception there crashes the interpreter):
  then the next :func:`check` raises it. Code that catches every
  exception (``import trimesh`` wraps optional imports in ``except
  BaseException``) may swallow that exception, so the long phases also call
  :func:`check`, which raises again while a stop is pending.
* inside :func:`deferred` (the stepping loop) the handler only records: the loop
  polls :func:`requested` between short compiled calls, saves what it has and
  raises :class:`StopRequested` itself, at a point where State and frames agree.
* a second signal removes the temporary files registered with
  :func:`temporary` and exits at once with status 128 + signal number.

Handlers can only be set from the main thread; elsewhere :func:`install` does
nothing and the process keeps Python's defaults.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading

#: The signals that stop a bake.
SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))

_pending: int | None = None
_deferred = 0
_temporary: set = set()
_installed: dict = {}


class StopRequested(KeyboardInterrupt):
    """A stop signal arrived; ``signum`` says which. Exit status 128 + signum."""

    def __init__(self, signum: int):
        super().__init__(signal_name(signum))
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + int(self.signum)


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def _in_native_init(frame) -> bool:
    """Whether ``frame`` runs inside the creation or initialisation of a native
    extension module (importlib's ExtensionFileLoader). Such an init may call back
    into Python (manifold3d's nanobind makes its enums through enum.py); an exception
    raised there is not one its C++ expects, and the interpreter aborts or crashes
    (SIGABRT or SIGSEGV instead of a clean stop: 6 in 315 runs with SIGINT 0.3-0.5 s
    of CPU into a bake, all in ``import manifold3d``)."""
    from importlib.machinery import ExtensionFileLoader

    while frame is not None:
        if (frame.f_code.co_name in ("create_module", "exec_module")
                and isinstance(frame.f_locals.get("self"), ExtensionFileLoader)):
            return True
        frame = frame.f_back
    return False


def _handler(signum, frame):
    global _pending
    if _pending is not None:        # the second one: leave now
        _remove_temporary()
        os._exit(128 + int(signum))
    _pending = int(signum)
    # inside a native module's init only recorded: the next check() raises it
    if not _deferred and not _in_native_init(frame):
        raise StopRequested(signum)


def install() -> bool:
    """Put the stop handlers on SIGINT, SIGTERM and SIGHUP (idempotent). Returns
    False where they cannot be set (not the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return False
    for s in SIGNALS:
        if signal.getsignal(s) is not _handler:
            _installed.setdefault(s, signal.getsignal(s))
            signal.signal(s, _handler)
    return True


def uninstall() -> None:
    """Restore the handlers :func:`install` replaced, and forget a pending stop."""
    global _pending
    if threading.current_thread() is not threading.main_thread():
        return
    for s, old in list(_installed.items()):
        signal.signal(s, old if old is not None else signal.SIG_DFL)
    _installed.clear()
    _pending = None


def installed() -> bool:
    return bool(SIGNALS) and signal.getsignal(SIGNALS[0]) is _handler


@contextlib.contextmanager
def installed_for_call():
    """Install the handlers for the duration of a library call (``bake``), unless
    a caller (the CLI) already did; restores what was there before."""
    if installed() or not install():
        yield
        return
    try:
        yield
    finally:
        uninstall()


def requested() -> int | None:
    """The signal number of a pending stop, or None."""
    return _pending


def check() -> None:
    """Raise StopRequested if a stop is pending."""
    if _pending is not None:
        raise StopRequested(_pending)


def stop_behind(exc: BaseException) -> StopRequested | None:
    """The stop that a failure is the consequence of, or None: while a stop is
    pending, any exception but a StopRequested is taken as the stop's doing. A
    library that swallows the KeyboardInterrupt goes on half-imported and fails
    later with an unrelated error (``import trimesh`` interrupted in its optional
    imports stores a stand-in for a class, then fails with a TypeError on
    ``Path3D | None``); the user pressed Ctrl-C, and that is what to report."""
    if _pending is None or isinstance(exc, StopRequested):
        return None
    stop = StopRequested(_pending)
    stop.__cause__ = exc
    return stop


def reset() -> None:
    """Forget a pending stop (tests, or a caller that handled it)."""
    global _pending
    _pending = None


@contextlib.contextmanager
def deferred():
    """Within this block a signal only records itself; the code polls requested()."""
    global _deferred
    _deferred += 1
    try:
        yield
    finally:
        _deferred -= 1


_held = False


def hold() -> None:
    """Record signals without raising until :func:`release` (a program's module-level
    start-up, where an exception would escape every handler)."""
    global _deferred, _held
    if not _held:
        _held = True
        _deferred += 1


def release() -> None:
    """End :func:`hold`; a stop recorded meanwhile raises at the next check()."""
    global _deferred, _held
    if _held:
        _held = False
        _deferred -= 1


@contextlib.contextmanager
def undeferred():
    """Within a deferred() block: a stretch where a signal raises at once again
    (a pending stop raises on entry)."""
    global _deferred
    saved, _deferred = _deferred, 0
    try:
        check()
        yield
    finally:
        _deferred = saved


@contextlib.contextmanager
def temporary(path):
    """Register ``path`` as a temporary file that a second signal removes on its way
    out (the normal path removes or renames it itself)."""
    p = os.fspath(path)
    _temporary.add(p)
    try:
        yield
    finally:
        _temporary.discard(p)


def _remove_temporary() -> None:
    for p in list(_temporary):
        try:
            os.unlink(p)
        except OSError:
            pass
