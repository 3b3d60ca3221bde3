"""A stage at the door: opened whole, its numbers checked, pxr's diagnostics as one line.

pxr reports a missing sublayer, a file that is not USD or a broken reference as C++
text on the process's stderr (``Warning: in _ReportErrors at line 3326 of
.../stage.cpp -- Could not load sublayer @x.usda@ ...``) and carries on, so a stage
would be simulated without the part that did not load. ``open_stage`` takes that
text while the stage opens (``captured_stderr``) and refuses the stage with its
readable part (``pxr_reason``). ``stage_number`` and ``finite_vector`` check what the
stage gives (units, time codes, velocities) as the reader reads it.
"""

from __future__ import annotations

import math
import os
import re
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from dempipe.errors import SceneError

#: metersPerUnit and kilogramsPerUnit accepted (nanometres to a million km): outside,
#: a unit is a typing error, and a negative or zero one would reverse or void gravity.
UNIT_RANGE = (1e-9, 1e9)
#: Largest time code magnitude read: frame numbers stay exact integers in float64.
TIME_CODE_MAX = 1e9
#: Densities read from a stage [kg/m³] (far beyond any material both ways): outside,
#: masses and inertias underflow or overflow before the contact stiffness is derived.
DENSITY_RANGE = (1e-6, 1e9)
#: The largest mass read from a stage [kg].
MAX_MASS = 1e12
#: The largest friction coefficient read.
MAX_FRICTION = 100.0
#: The largest gravity read from a stage [m/s²] (a thousand g): beyond it no contact
#: stiffness holds a body, and a typing error is the likelier cause.
MAX_GRAVITY = 1e4


@contextmanager
def captured_stderr(lines: list):
    """Redirect file descriptor 2 (where pxr's C++ code writes) into ``lines`` for
    the block; the lines that look like diagnostics are appended when it ends."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):       # no real stderr: nothing to capture
        yield
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode(errors="replace")
            lines.extend(ln.strip() for ln in text.splitlines()
                         if re.match(r"\s*(Warning|Error|Coding Error|Fatal)", ln)
                         or " -- " in ln)


def pxr_reason(lines) -> str:
    """The readable part of pxr's first diagnostic: the text after its source
    location (``... -- TEXT``) or inside its quotes (``... : 'TEXT'``), without the
    trailing note in parentheses."""
    for ln in lines:
        ln = ln.strip()
        if not ln:
            continue
        if " -- " in ln:
            text = ln.split(" -- ", 1)[1]
        elif re.search(r": '(.*)'\s*$", ln):
            text = re.search(r": '(.*)'\s*$", ln).group(1)
        else:
            text = ln
        text = re.sub(r"\s*\((?:Recomposing|instantiating) stage[^)]*\)\s*$", "", text)
        return text.strip()
    return ""


def open_stage(path: Path):
    """The stage at ``path``, opened whole: a SceneError with pxr's reason for a file
    that is not USD or a layer of it that cannot be read."""
    from pxr import Tf, Usd

    if not path.is_file():
        raise SceneError(f"{path.name}: file not found")
    said = []
    try:
        with captured_stderr(said):
            stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        why = pxr_reason(said) or pxr_reason(str(exc).splitlines()) or "unreadable"
        raise SceneError(f"{path.name}: cannot open the USD stage ({why})") from None
    if stage is None:
        raise SceneError(f"{path.name}: cannot open the USD stage "
                         f"({pxr_reason(said) or 'unreadable'})")
    if said:
        # a sublayer, reference or payload that cannot be read: the stage would be
        # simulated without it
        raise SceneError(f"{path.name}: the stage does not compose whole "
                         f"({pxr_reason(said)}); fix or remove the missing layer")
    return stage


def stage_number(value, key: str, path: Path, bounds, zero: bool = False) -> float:
    """A number of the stage's metadata checked against ``bounds`` (a SceneError naming
    the key otherwise; ``zero`` lets 0 through a lower bound above it)."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"{path.name}: {key} is not a number ({value!r})") from None
    lo, hi = bounds
    if not math.isfinite(x) or not (lo <= x <= hi or (zero and x == 0)):
        raise SceneError(f"{path.name}: {key} = {x:g} is out of range (expected a finite "
                         f"number in [{lo:g}, {hi:g}])")
    return x


def finite_vector(v, where: str, key: str) -> np.ndarray:
    """``v`` as float64, or a SceneError naming ``key`` when a component is not finite."""
    a = np.asarray(v, float)
    if not np.isfinite(a).all():
        raise SceneError(f"{where}: {key} = {tuple(a.tolist())} is not finite (author "
                         "numbers)")
    return a


def density_of(attr, kpu: float, mpu: float, where: str) -> float:
    """A density attribute in kg/m³; 0 when unauthored (or 0: "not authored", as the
    schema has it). A SceneError for one out of DENSITY_RANGE."""
    v = float(attr.Get() or 0.0)
    if v == 0:
        return 0.0
    rho = v * kpu / mpu ** 3 if math.isfinite(v) else v
    lo, hi = DENSITY_RANGE
    if not lo <= rho <= hi:
        raise SceneError(f"{where}: {attr.GetName()} = {v:g} is {rho:g} kg/m³ (expected 0 "
                         f"for not authored, or {lo:g} to {hi:g} kg/m³)")
    return rho


def mass_of(attr, kpu: float, where: str) -> float | None:
    """A physics:mass in kg; None when unauthored or 0 (the schema's "not authored").
    A SceneError for a negative, non-finite or absurd one."""
    mv = float(attr.Get() or 0.0)
    if not (mv == 0 or 0 < mv * kpu <= MAX_MASS):
        raise SceneError(f"{where}: physics:mass = {mv:g} (expected 0 for not authored, or "
                         f"a mass above 0 and at most {MAX_MASS:g} kg)")
    return mv * kpu if mv > 0 else None


def check_instancer_arrays(pi, t0, n: int, where: str) -> None:
    """A PointInstancer's per-instance arrays at ``t0``: one entry per protoIndices entry
    (``n``), finite (a SceneError naming the array otherwise)."""
    for name, attr in (("positions", pi.GetPositionsAttr()),
                       ("orientations", pi.GetOrientationsAttr()),
                       ("orientationsf", pi.GetOrientationsfAttr()),
                       ("scales", pi.GetScalesAttr()),
                       ("velocities", pi.GetVelocitiesAttr()),
                       ("angularVelocities", pi.GetAngularVelocitiesAttr())):
        vals = attr.Get(t0)
        if vals is None or len(vals) == 0:
            if name == "positions" and n:
                raise SceneError(f"{where}: positions is not authored (one per "
                                 f"protoIndices entry, {n})")
            continue
        if len(vals) != n:
            raise SceneError(f"{where}: {name} has {len(vals)} entries, protoIndices "
                             f"{n} (author one per instance)")
        a = np.asarray([tuple(x.GetImaginary()) + (x.GetReal(),) if hasattr(x, "GetReal")
                        else tuple(x) for x in vals], float)
        if not np.isfinite(a).all():
            raise SceneError(f"{where}: {name} holds a non-finite number")
