"""analyze_scene(): a scene file's stability report without simulating. What `dempipe
check` runs: the scene is read and its Model built as the bake builds it, then
:func:`dempipe.check.stability.analyze` predicts what would go wrong."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from dempipe.check.sizes import check_run_time
from dempipe.check.stability import ERROR, WARNING, Finding, StabilityReport, analyze
from dempipe.errors import StabilityError
from dempipe.scene.build import Overrides, build_model, full_sphere_model
from dempipe.scene.load import load_scene
from dempipe.spheres.cache import SphereCache


def analyze_scene(path, cache=None) -> StabilityReport:
    """Load ``path``, build its Model (sphere sets through ``cache``; None: the default
    SphereCache, as bake uses) and analyze it.

    A user dt that finalize refuses does not stop the check: the model is rebuilt
    with dt = "auto" (the sphere sets come from the cache) and the refusal becomes
    an error finding. Scene and mesh errors propagate (DempipeError).
    """
    scene = load_scene(path)
    cache = cache if cache is not None else SphereCache()
    user_dt = scene.simulation.dt
    try:
        model = build_model(scene, cache=cache)
    except StabilityError as exc:
        if isinstance(user_dt, str):
            raise
        model = build_model(scene, cache=cache, overrides=Overrides(dt="auto"))
        return _with_usd_findings(
            analyze(model, dt=float(user_dt), dt_setting=user_dt, refused=str(exc),
                    scene=str(path), full_model=full_sphere_model(scene, model, cache=cache)),
            scene)
    report = analyze(model, dt_setting=user_dt, scene=str(path),
                     full_model=full_sphere_model(scene, model, cache=cache))
    try:    # what bake refuses before simulating: steps and frames beyond reason
        check_run_time(model, Path(path).name, scene)
    except StabilityError as exc:
        text = str(exc)
        message, _, fix = text.partition(". Fix: ")
        report.findings.append(Finding(ERROR, "run-size", message, fix))
    return _with_usd_findings(report, scene)


def _with_usd_findings(report, scene):
    """A USD stage's reading warnings (what is not simulated, planes taken from
    cubes) as warning findings ahead of the stability ones."""
    if scene.usd is None or not scene.usd.warnings:
        return report
    found = [Finding(WARNING, "usd-not-simulated" if "not simulated" in w else "usd-reading", w)
             for w in scene.usd.warnings]
    return replace(report, findings=found + list(report.findings))
