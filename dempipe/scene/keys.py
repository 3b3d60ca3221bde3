"""Reading a scene's tables: typed values, and errors that name the key path.

    ctx = SceneKeys(path, "shot.toml")
    fps = ctx.integer(d.get("fps", 24), "output.fps", lo=1)
    raise ctx.error("bodies[2].shape", "unknown shape 'pwn'", "known: pawn, rook")

Every problem is a :class:`~dempipe.errors.SceneError` with a one-line message
``"<file>: <key.path>: <problem> (<fix or known values>)"``: the value found is
described (``describe_value``), a misspelt name gets the closest known one
(``suggestion``). scene.py's table parsers read every value through a ``SceneKeys``.
"""

from __future__ import annotations

import difflib
import math
import re
from pathlib import Path
from typing import Any

from dempipe.errors import SceneError
from dempipe.scene.data import Quat

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


_MISSING = object()

#: The largest and the smallest non-zero size of any number a scene gives, in SI
#: units: beyond them a value is a typing error, and squares and cubes of it (energies,
#: inertias, volumes) overflow or underflow float64 (1e300 squared is inf, 1e-300
#: cubed is 0) before any check that knows the key can name it.
MAX_MAGNITUDE = 1e15
MIN_MAGNITUDE = 1e-15
#: The largest integer a scene gives (counts, frames, seeds): exact in float64.
MAX_INTEGER = 2**53


def describe_value(v: Any) -> str:
    if isinstance(v, bool):
        return f"boolean {str(v).lower()}"
    if isinstance(v, str):
        return f"string {v!r}"
    if isinstance(v, int):
        return f"integer {v}"
    if isinstance(v, float):
        return f"float {v!r}"
    if isinstance(v, list):
        return f"array of length {len(v)}"
    if isinstance(v, dict):
        return "table"
    return type(v).__name__


def known_names(names) -> str:
    names = list(names)
    return ", ".join(names) if names else "none defined"


def suggestion(word: str, names) -> str:
    names = list(names)
    close = difflib.get_close_matches(word, names, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}? " if close else ""
    return f"{hint}known: {known_names(names)}"


class SceneKeys:
    """Error reporting for one scene file."""

    def __init__(self, path: Path | None, name: str):
        self.path = path
        self.name = name
        self.base = path.parent if path is not None else Path.cwd()

    def error(self, key: str, problem: str, fix: str | None = None) -> SceneError:
        msg = f"{self.name}: {key}: {problem}" if key else f"{self.name}: {problem}"
        if fix:
            msg += f" ({fix})"
        return SceneError(" ".join(msg.split("\n")))

    # -- tables --------------------------------------------------------------

    def table(self, d: Any, key: str) -> dict:
        if not isinstance(d, dict):
            raise self.error(key, f"expected a table, got {describe_value(d)}",
                             f"write it as [{key}]" if key else None)
        return d

    def check_keys(self, d: dict, key: str, allowed, what: str = "key") -> None:
        allowed = list(allowed)
        for k in d:
            if k not in allowed:
                raise self.error(_join(key, k), f"unknown {what}", suggestion(k, allowed))

    def require(self, d: dict, key: str, k: str, hint: str | None = None):
        if k not in d:
            raise self.error(_join(key, k), "missing required key", hint)
        return d[k]

    # -- scalars -------------------------------------------------------------

    def number(self, v: Any, key: str, *, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False, hi_open: bool = False, unit: str = "") -> float:
        rng = _range_text(lo, hi, lo_open, hi_open)
        expect = f"a number{rng and ' ' + rng}{unit and ' (' + unit + ')'}"
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(key, f"expected {expect}, got {describe_value(v)}",
                             "write a number without quotes" if isinstance(v, str) else None)
        v = float(v)
        if not math.isfinite(v):
            raise self.error(key, f"expected a finite number, got {v!r}", None)
        if abs(v) > MAX_MAGNITUDE or 0 < abs(v) < MIN_MAGNITUDE:
            raise self.error(key, f"{v:g} is out of range",
                             f"dempipe reads SI units: a value is 0 or between "
                             f"{MIN_MAGNITUDE:g} and {MAX_MAGNITUDE:g} in size")
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise self.error(key, f"{v:g} is out of range", f"expected {expect}")
        if hi is not None and (v > hi or (hi_open and v == hi)):
            raise self.error(key, f"{v:g} is out of range", f"expected {expect}")
        return v

    def integer(self, v: Any, key: str, *, lo: int | None = None, hi: int | None = None,
                what: str = "an integer") -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            fix = None
            if isinstance(v, float) and math.isfinite(v) and v == int(v):
                fix = f"write {int(v)} without a decimal point"
            elif isinstance(v, str):
                fix = "write an integer without quotes"
            raise self.error(key, f"expected {what}, got {describe_value(v)}", fix)
        if lo is not None and v < lo:
            raise self.error(key, f"{v} is out of range", f"expected {what} >= {lo}")
        top = MAX_INTEGER if hi is None else hi
        if abs(v) > top:
            raise self.error(key, f"{v} is out of range", f"expected {what} of at most {top:,}"
                             + (" in size" if lo is None or lo < 0 else ""))
        return int(v)

    def boolean(self, v: Any, key: str) -> bool:
        if not isinstance(v, bool):
            raise self.error(key, f"expected a boolean, got {describe_value(v)}",
                             "write true or false without quotes")
        return v

    def string(self, v: Any, key: str, choices=None, *, or_number: str | None = None) -> str:
        """A string among ``choices``; ``or_number``: what a number there means, for a
        key that also takes one (e.g. 'a step in seconds, e.g. dt = 5e-05')."""
        if not isinstance(v, str):
            known = f"one of: {known_names(choices)}" if choices else None
            raise self.error(key, f"expected a string, got {describe_value(v)}", known)
        if choices is not None and v not in choices:
            fix = suggestion(v, choices)
            raise self.error(key, f"unknown value {v!r}",
                             f"{fix}; or {or_number}" if or_number else fix)
        return v

    def vector(self, v: Any, key: str, n: int = 3, *, what: str = "number",
               example: str | None = None) -> tuple[float, ...]:
        """``n`` numbers; ``example``: the array the error message shows (zeros unless
        given)."""
        if not isinstance(v, list) or len(v) != n:
            shown = example or f"[{', '.join(['0.0'] * n)}]"
            raise self.error(key, f"expected an array of {n} numbers, got {describe_value(v)}",
                             f"e.g. {key.rsplit('.', 1)[-1]} = {shown}")
        return tuple(self.number(x, f"{key}[{i}]") for i, x in enumerate(v))

    def quaternion(self, v: Any, key: str) -> Quat:
        q = self.vector(v, key, 4, example="[1.0, 0.0, 0.0, 0.0] (w, x, y, z: no turn)")
        norm = math.sqrt(sum(c * c for c in q))
        if norm < 1e-12:
            raise self.error(key, "zero quaternion",
                             "give [w, x, y, z] with a non-zero length, e.g. [1, 0, 0, 0]")
        return tuple(c / norm for c in q)  # type: ignore[return-value]

    def usd_name(self, v: Any, key: str) -> str:
        v = self.string(v, key)
        if not _NAME_RE.match(v):
            fixed = re.sub(r"[^A-Za-z0-9_]", "_", v)
            if not fixed or fixed[0].isdigit():
                fixed = "_" + fixed
            raise self.error(key, f"{v!r} is not a valid USD prim name",
                             f"use letters, digits and _, not starting with a digit, e.g. {fixed!r}")
        return v

    def mesh_file(self, v: Any, key: str) -> Path:
        v = self.string(v, key)
        p = Path(v).expanduser()
        if not p.is_absolute():
            p = self.base / p
        p = p.resolve()
        if p.is_dir():
            raise self.error(key, f"{p} is a folder, not a mesh file",
                             "name the mesh file inside it")
        if not p.is_file():
            raise self.error(key, f"mesh file not found: {p}",
                             "paths are relative to the scene file's folder")
        return p


def _join(key: str, k: str) -> str:
    return f"{key}.{k}" if key else k


def _range_text(lo, hi, lo_open, hi_open) -> str:
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {hi:g}"
    return ""
