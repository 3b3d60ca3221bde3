"""Option types shared by the commands: numbers checked at the door.

click's ``float`` takes ``nan``, ``inf`` and ``1e300``, and its FloatRange lets NaN
through (every comparison with NaN is false), so ``--sphere-diameter nan`` reached the
library as a diameter. ``Number`` refuses what is not finite or is beyond ``hi`` in
size, as click refuses a word: a usage error naming the option, exit 2.
"""

from __future__ import annotations

import math

import click

#: The largest size of any number given on the command line (as dempipe.scene.keys
#: holds scene values): beyond it squares overflow float64 before a check sees them.
MAX_MAGNITUDE = 1e15


class Number(click.ParamType):
    """A finite float in [lo, hi] (lo_open: > lo), at most MAX_MAGNITUDE in size."""

    name = "number"

    def __init__(self, lo: float | None = None, hi: float | None = None,
                 lo_open: bool = False):
        self.lo, self.hi, self.lo_open = lo, hi, lo_open

    def convert(self, value, param, ctx):
        if isinstance(value, float) and math.isfinite(value):
            x = value
        else:
            try:
                x = float(value)
            except (TypeError, ValueError):
                self.fail(f"{value!r} is not a number", param, ctx)
        if not math.isfinite(x):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        hi = MAX_MAGNITUDE if self.hi is None else self.hi
        if abs(x) > MAX_MAGNITUDE or x > hi:
            self.fail(f"{x:g} is too large (at most {hi:g})", param, ctx)
        if self.lo is not None and (x < self.lo or (self.lo_open and x == self.lo)):
            self.fail(f"{x:g} must be {'>' if self.lo_open else '>='} {self.lo:g}", param, ctx)
        return x
