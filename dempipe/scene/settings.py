"""The [output] and [simulation] tables, read for a TOML scene and for the settings file
of a USD stage alike."""

from __future__ import annotations

import math
from typing import Any

from dempipe.scene.data import (
    STANDARD_GRAVITY,
    OutputSettings,
    SimulationSettings,
    SleepSettings,
)
from dempipe.errors import SceneError
from dempipe.scene.keys import MAX_MAGNITUDE, SceneKeys
from dempipe.sim.laws import LAWS
from dempipe.spheres.options import SCENE_MODES, SPACING_RANGE

#: The keys of [output] and of [simulation] (and its [simulation.sleep]).
_OUTPUT_KEYS = ("fps", "duration", "up_axis", "meters_per_unit", "start_frame")
_SIM_KEYS = ("sphere_diameter", "resolution", "gravity", "dt", "device", "seed",
             "stiffness_target_overlap", "dt_safety", "sleeping", "sleep", "contact_layers",
             "spheres", "surface_spacing", "contact_law")
_SLEEP_KEYS = ("linear_speed", "angular_speed", "time")


def surface_spacing(ctx: SceneKeys, v: Any, key: str) -> float:
    """A surface set's spacing, a fraction of the sphere diameter in [SPACING_RANGE]."""
    lo, hi = SPACING_RANGE
    return ctx.number(v, key, lo=lo, hi=hi, unit="a fraction of the sphere diameter")


#: |output.start_frame| at most (a billion frames: 1.3 years at 24 fps).
MAX_START_FRAME = 10**9


def parse_output(ctx: SceneKeys, d: Any) -> OutputSettings:
    d = ctx.table(d, "output")
    ctx.check_keys(d, "output", _OUTPUT_KEYS)
    kw: dict[str, Any] = {}
    if "fps" in d:
        kw["fps"] = ctx.integer(d["fps"], "output.fps", lo=1, what="a positive integer")
    if "duration" in d:
        kw["duration"] = ctx.number(d["duration"], "output.duration", lo=0.0, lo_open=True,
                                    unit="seconds")
    if "up_axis" in d:
        up = ctx.string(d["up_axis"], "output.up_axis", ("Z", "Y", "z", "y"))
        kw["up_axis"] = up.upper()
    if "meters_per_unit" in d:
        kw["meters_per_unit"] = ctx.number(d["meters_per_unit"], "output.meters_per_unit",
                                           lo=0.0, lo_open=True)
    if "start_frame" in d:
        # frame numbers are USD time codes: float64, exact integers up to far beyond this
        kw["start_frame"] = ctx.integer(d["start_frame"], "output.start_frame",
                                        hi=MAX_START_FRAME)
    return OutputSettings(**kw)


def parse_simulation(ctx: SceneKeys, d: Any, up_axis: str) -> SimulationSettings:
    d = ctx.table(d, "simulation")
    ctx.check_keys(d, "simulation", _SIM_KEYS)
    kw: dict[str, Any] = {}
    if "sphere_diameter" in d and "resolution" in d:
        raise ctx.error("simulation.resolution", "both sphere_diameter and resolution are given",
                        "give only one of them")
    if "sphere_diameter" in d:
        kw["sphere_diameter"] = ctx.number(d["sphere_diameter"], "simulation.sphere_diameter",
                                           lo=0.0, lo_open=True, unit="metres")
        kw["resolution"] = None
    elif "resolution" in d:
        kw["resolution"] = ctx.integer(d["resolution"], "simulation.resolution", lo=1,
                                       what="a positive integer")
    if "gravity" in d:
        kw["gravity"] = ctx.vector(d["gravity"], "simulation.gravity",
                                   example="[0.0, 0.0, -9.81] (m/s², Z up)")
    else:
        g = [0.0, 0.0, 0.0]
        g[2 if up_axis == "Z" else 1] = -STANDARD_GRAVITY
        kw["gravity"] = tuple(g)
    if "dt" in d:
        v = d["dt"]
        if isinstance(v, str):
            kw["dt"] = ctx.string(v, "simulation.dt", ("auto",),
                                  or_number="a step in seconds, e.g. dt = 5e-05")
        else:
            kw["dt"] = ctx.number(v, "simulation.dt", lo=0.0, lo_open=True,
                                  unit='seconds, or "auto"')
    if "device" in d:
        kw["device"] = ctx.string(d["device"], "simulation.device", ("auto", "cpu", "cuda"))
    if "seed" in d:
        kw["seed"] = ctx.integer(d["seed"], "simulation.seed", lo=0,
                                 what="a non-negative integer")
    if "stiffness_target_overlap" in d:
        kw["stiffness_target_overlap"] = ctx.number(
            d["stiffness_target_overlap"], "simulation.stiffness_target_overlap",
            lo=0.0, hi=0.5, lo_open=True)
    if "dt_safety" in d:
        kw["dt_safety"] = ctx.number(d["dt_safety"], "simulation.dt_safety", lo=0.0, hi=1.0,
                                     lo_open=True)
    if "sleeping" in d:
        kw["sleeping"] = ctx.boolean(d["sleeping"], "simulation.sleeping")
    if "contact_layers" in d:
        v = d["contact_layers"]
        if isinstance(v, str):
            ctx.string(v, "simulation.contact_layers", ("all",))
            kw["contact_layers"] = 0
        else:
            what = 'an integer >= 0 (layers of surface spheres kept for contacts) or "all"'
            n = ctx.integer(v, "simulation.contact_layers", what=what)
            if n < 0:
                raise ctx.error("simulation.contact_layers", f"{n} is out of range",
                                f'expected {what}; 0 or "all" keeps every sphere')
            kw["contact_layers"] = n
    if "spheres" in d:
        kw["spheres"] = ctx.string(d["spheres"], "simulation.spheres", SCENE_MODES)
    if "surface_spacing" in d:
        kw["surface_spacing"] = surface_spacing(ctx, d["surface_spacing"],
                                                "simulation.surface_spacing")
    if "contact_law" in d:
        kw["contact_law"] = ctx.string(d["contact_law"], "simulation.contact_law", tuple(LAWS))
    if "sleep" in d:
        s = ctx.table(d["sleep"], "simulation.sleep")
        ctx.check_keys(s, "simulation.sleep", _SLEEP_KEYS)
        units = {"linear_speed": "m/s", "angular_speed": "rad/s", "time": "seconds"}
        kw["sleep"] = SleepSettings(**{
            k: ctx.number(s[k], f"simulation.sleep.{k}", lo=0.0, lo_open=True, unit=units[k])
            for k in _SLEEP_KEYS if k in s})
    return SimulationSettings(**kw)


def settings_toml(sim: SimulationSettings, stage: str) -> str | None:
    """The settings TOML of a stage written from a TOML scene: ``[usd] stage`` (the
    stage's path relative to the TOML) and the ``[simulation]`` keys ``sim`` gives other
    than the defaults, which a UsdPhysics stage cannot hold (its gravity can, and is
    left out). None when every key is at its default: the stage alone bakes the same."""
    default = SimulationSettings()
    lines = []
    for key in _SIM_KEYS:
        v = getattr(sim, key)
        if key in ("gravity", "sleep") or v == getattr(default, key):
            continue
        if key == "resolution" and v is None:
            continue                # sphere_diameter is given instead
        lines.append(f"{key} = {_toml_value(v)}")
    sleep = [f"{k} = {_toml_value(getattr(sim.sleep, k))}" for k in _SLEEP_KEYS
             if getattr(sim.sleep, k) is not None]
    if not lines and not sleep:
        return None
    out = ["# dempipe's own settings for the stage (docs/usd-input.md): bake this file",
           "[usd]", f"stage = {_toml_value(stage)}", "", "[simulation]", *lines]
    if sleep:
        out += ["", "[simulation.sleep]", *sleep]
    return "\n".join(out) + "\n"


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(float(v)) if isinstance(v, float) else str(int(v))


def with_simulation(scene, simulation: dict | None):
    """``scene`` with ``simulation``'s keys replacing its SimulationSettings' (what a
    command line or a caller gives: `dempipe bake` and `dempipe check`
    --resolution, dempipe.bake's ``simulation``); a resolution clears a
    sphere_diameter and the other way round."""
    from dataclasses import fields, replace

    if not simulation:
        return scene
    known = {f.name for f in fields(scene.simulation)}
    for k in simulation:
        if k not in known:
            raise SceneError(f"unknown simulation setting {k!r} "
                             f"(known: {', '.join(sorted(known))})")
    changes = dict(simulation)
    for k, v in changes.items():    # what the command line or a caller gives, as a scene's
        if isinstance(v, (int, float)) and not isinstance(v, bool) and not (
                math.isfinite(v) and abs(v) <= MAX_MAGNITUDE):
            raise SceneError(f"simulation.{k}: {v!r} is not a finite number of at most "
                             f"{MAX_MAGNITUDE:g}")
    for k in ("resolution", "sphere_diameter"):
        if changes.get(k) is not None and not changes[k] > 0:
            raise SceneError(f"simulation.{k}: {changes[k]!r} must be greater than 0")
    if changes.get("resolution") is not None and changes.get("sphere_diameter") is not None:
        raise SceneError("simulation: give resolution or sphere_diameter, not both "
                         f"(got {changes['resolution']!r} and {changes['sphere_diameter']!r})")
    if changes.get("resolution") is not None:
        changes.setdefault("sphere_diameter", None)
    if changes.get("sphere_diameter") is not None:
        changes.setdefault("resolution", None)
    return replace(scene, simulation=replace(scene.simulation, **changes))
