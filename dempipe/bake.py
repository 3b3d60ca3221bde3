"""bake(): scene file in, USD stage out. What `dempipe bake` runs.

    result = bake("examples/quickstart.toml", "out.usdc")

Loads and validates the scene, builds sphere sets (cached) and the Model,
refuses scenes that would blow up at frame 0, simulates, and writes the USD
stage atomically. A guard that stops the bake, an error or Ctrl-C still writes
every frame done so far, to a clearly named partial file beside the target.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from .errors import DempipeError, ExportError, SceneError, StabilityError
from .stability import REFUSE_OVERLAP, WARN_OVERLAP  # frame-0 overlap limits, defined there


@dataclass
class BakeResult:
    """What a bake did: the written path and the figures of --report."""

    path: Path
    report: dict = field(default_factory=dict)
    partial: bool = False


def partial_path(out: Path) -> Path:
    """Where an interrupted or failed bake keeps its frames: NAME.partial.EXT."""
    return out.with_name(f"{out.stem}.partial{out.suffix}")


def parse_frame_range(text: str | None, n_frames: int, first: int) -> tuple[int, int]:
    """'START:END' (inclusive, in frame numbers) → indices into the bake's frames."""
    if not text:
        return 0, n_frames - 1
    try:
        a, b = text.split(":")
        start = int(a) if a.strip() else first
        end = int(b) if b.strip() else first + n_frames - 1
    except ValueError:
        raise SceneError(f"--frames: expected START:END (e.g. 0:48), got {text!r}") from None
    if not (first <= start <= end <= first + n_frames - 1):
        raise SceneError(f"--frames: {start}:{end} is outside the scene's frames "
                         f"{first}:{first + n_frames - 1}")
    return start - first, end - first


def bake(scene_path, out_path, *, device: str | None = None, layout: str = "instancer",
         frames: str | None = None, threads: int | None = None, cache=None,
         progress=None, warn=None, force: bool = False,
         simulation: dict | None = None) -> BakeResult:
    """Bake ``scene_path`` to the USD file ``out_path``; returns a BakeResult.

    device : 'cpu' | 'cuda' | 'auto' (default: the scene's simulation.device)
    layout : 'instancer' | 'xforms' (see docs/usd-output.md)
    frames : 'START:END' frame numbers to write (the simulation always starts at 0)
    progress : callable(frame_index, n_frames, stats) for a progress display
    warn : callable(str) for one-line warnings (default: warnings.warn)
    simulation : settings replacing the scene's ``[simulation]`` ones (the
        SimulationSettings fields, e.g. ``{"resolution": 4}``); how a bare USD stage
        gets dempipe's own settings from the command line
    """
    import warnings

    from .build import build_model, initial_overlap_all_spheres
    from .cache import SphereCache
    from .scene import load_scene
    from .simulator import BakeFailure, Simulator, resolve_device

    warn = warn or (lambda msg: warnings.warn(msg, stacklevel=2))
    out = Path(out_path)
    if out.suffix not in (".usd", ".usdc", ".usda"):
        raise ExportError(f"{out}: unknown extension {out.suffix!r} (use .usd, .usdc or .usda)")
    t_start = time.perf_counter()
    scene = with_simulation(load_scene(scene_path), simulation)
    for msg in scene.usd.warnings if scene.usd is not None else ():
        warn(msg)
    device_asked = device or scene.simulation.device
    dev = resolve_device(device_asked)
    if device_asked == "auto" and dev == "cpu":
        warn("no usable CUDA GPU: baking on the CPU")
    cache = cache if cache is not None else SphereCache()
    model = build_model(scene, cache=cache, force=force)
    start, end = parse_frame_range(frames, model.n_frames, model.first_frame)

    src = Path(scene_path).name
    from .stability import ERROR, expected_speeds, soft_contact, tunnelling

    closing = expected_speeds(model)[1]
    for risk in (tunnelling(model, model.dt, closing,
                            "auto" if isinstance(scene.simulation.dt, str) else "given", src),
                 soft_contact(model, closing, src)):
        if risk is not None and risk.level == ERROR and not force:
            raise StabilityError(f"{risk.message}. Fix: {risk.fix} (or bake with --force)")
        if risk is not None:
            warn(risk.message)

    overlap, body = initial_overlap_all_spheres(scene, model, cache=cache)
    if overlap > REFUSE_OVERLAP and not force:
        raise StabilityError(
            f"{src}: body {model.body_name(body)} overlaps another body or a collider by "
            f"{overlap:.0%} of the sphere diameter at frame 0; the first step would fling it "
            f"away. Space the bodies further apart (a randomly turned body swings about its "
            f"mesh origin) or move it clear of the colliders")
    if overlap > WARN_OVERLAP:
        warn(f"{src}: body {model.body_name(body)} starts {overlap:.0%} of a diameter deep in "
             f"contact; it will be pushed out in the first steps")

    sim = Simulator(model, device=dev, threads=threads)
    state = model.initial_state()
    failure = None
    try:
        recorded = sim.advance(state, n_frames=end + 1, progress=progress)
    except BakeFailure as exc:
        failure, recorded = exc, exc.frames
    except KeyboardInterrupt as exc:
        failure, recorded = exc, getattr(exc, "frames", None)

    from .export.usd import write_usd

    report = dict(
        scene=str(scene_path), output=str(out), bodies=model.n_bodies, spheres=model.n_spheres,
        static_spheres=int(model.n_spheres - model.body_sphere_start[model.n_bodies]),
        diameter=model.diameter, dt=model.dt, steps_per_frame=model.steps_per_frame,
        steps=sim.stats.steps, frames=0, device=dev, threads=threads,
        wall_seconds=0.0, simulate_seconds=sim.stats.wall_seconds,
        seconds_per_step=(sim.stats.wall_seconds / (sim.stats.steps - sim.stats.steps_skipped)
                          if sim.stats.steps > sim.stats.steps_skipped else 0.0),
        steps_skipped_asleep=sim.stats.steps_skipped,
        # over the steps computed: a step skipped while every body slept costs nothing
        sphere_steps_per_second=(model.n_spheres * (sim.stats.steps - sim.stats.steps_skipped)
                                 / sim.stats.wall_seconds if sim.stats.wall_seconds else 0.0),
        max_overlap=sim.stats.max_overlap / model.diameter,
        sphere_build_seconds=model.build_info.get("sphere_build_seconds", 0.0),
        sphere_cache=[dict(shape=n, cache=c, seconds=s, spheres=k)
                      for n, c, s, k in model.build_info.get("shapes", [])],
        stiffness={n: k for n, k in model.stiffness_auto},
        export_seconds=0.0, layout=layout, completed=failure is None,
    )
    if recorded is None or recorded.n_frames <= start:
        if failure is not None:
            raise failure
        raise StabilityError(f"{src}: no frame in {frames} was reached")
    written = recorded
    if start > 0:
        from .frames import Frames

        written = Frames(recorded.frame_numbers[start:], recorded.times[start:],
                         recorded.x[start:], recorded.q[start:], recorded.v[start:],
                         recorded.w[start:])
    target = out if failure is None else partial_path(out)
    if scene.usd is not None:   # a USD stage in: an overlay over it out
        from .export.overlay import write_overlay

        info = write_overlay(target, written, model, scene.usd)
    else:
        info = write_usd(target, written, model, layout=layout)
    report.update(frames=written.n_frames, export_seconds=info.seconds,
                  wall_seconds=time.perf_counter() - t_start, output=str(target))
    if failure is not None:
        kept = f"{written.n_frames} frames kept in {target}"
        if isinstance(failure, KeyboardInterrupt):
            exc = BakeInterrupted(f"interrupted; {kept}")
        else:
            exc = StabilityError(f"{failure} — {kept}")
        exc.result = BakeResult(target, report, partial=True)
        raise exc
    return BakeResult(target, report)


def with_simulation(scene, simulation: dict | None):
    """``scene`` with ``simulation``'s keys replacing its SimulationSettings'; a
    resolution clears a sphere_diameter and the other way round."""
    from dataclasses import fields, replace

    if not simulation:
        return scene
    known = {f.name for f in fields(scene.simulation)}
    for k in simulation:
        if k not in known:
            raise SceneError(f"unknown simulation setting {k!r} "
                             f"(known: {', '.join(sorted(known))})")
    changes = dict(simulation)
    if changes.get("resolution") is not None:
        changes.setdefault("sphere_diameter", None)
    if changes.get("sphere_diameter") is not None:
        changes.setdefault("resolution", None)
    return replace(scene, simulation=replace(scene.simulation, **changes))


class BakeInterrupted(DempipeError):
    """Ctrl-C during a bake; the frames done so far were written."""

    exit_code = 130


def write_report(path, report: dict) -> None:
    """Write --report JSON atomically."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(json.dumps(report, indent=2, default=float))
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ExportError(f"{path}: cannot write the report ({exc.strerror})") from None
