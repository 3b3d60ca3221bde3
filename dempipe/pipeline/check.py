"""analyze_scene(): a scene file's stability report without simulating. What `dempipe
check` runs: the scene is read and its Model built as the bake builds it, then
:func:`dempipe.check.stability.analyze` predicts what would go wrong, and what only
the scene's keys can name (an open mesh, a body behind a plane or a box's wall) is
added."""

from __future__ import annotations

import warnings

from dataclasses import replace
from pathlib import Path

import numpy as np

from dempipe.check.emission import emission_overlap
from dempipe.check.walls import behind_boxes, behind_planes, plane_walls, wall_name
from dempipe.check.prescribed import missing_surface_speed
from dempipe.check.sinking import sinking
from dempipe.check.stability import OVERLAP_ERROR
from dempipe.check.sizes import check_run_time
from dempipe.check.stability import (
    ERROR,
    WARNING,
    Finding,
    StabilityReport,
    analyze,
    expected_speeds,
    floor_below,
    tunnelling,
)
from dempipe.errors import StabilityError
from dempipe.scene.build import Overrides, build_model, full_sphere_model
from dempipe.scene.load import load_scene
from dempipe.scene.settings import with_simulation
from dempipe.sim.overlap import REFUSE_OVERLAP, WARN_OVERLAP
from dempipe.spheres.cache import SphereCache


def analyze_scene(path, cache=None, simulation: dict | None = None) -> StabilityReport:
    """Load ``path``, build its Model (sphere sets through ``cache``; None: the default
    SphereCache, as bake uses) and analyze it. ``simulation``: settings that replace
    the scene's, as bake takes them (scene.settings.with_simulation: a resolution, a
    sphere diameter), so that what is checked is what will be baked.

    A user dt that finalize refuses does not stop the check: the model is rebuilt
    with dt = "auto" (the sphere sets come from the cache) and the refusal becomes
    an error finding. Scene and mesh errors propagate (DempipeError).
    """
    # the sphere builder's warning of an open mesh: a finding here (open_mesh_findings),
    # naming the key and the fix, not a second line
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*mesh is not watertight")
        return _analyze_scene(path, cache, simulation)


def _analyze_scene(path, cache, simulation) -> StabilityReport:
    scene = with_simulation(load_scene(path), simulation)
    cache = cache if cache is not None else SphereCache()
    user_dt = scene.simulation.dt
    try:
        model = build_model(scene, cache=cache)
    except StabilityError as exc:
        if isinstance(user_dt, str):
            raise
        model = build_model(scene, cache=cache, overrides=Overrides(dt="auto"))
        report = analyze(model, dt=float(user_dt), dt_setting=user_dt, refused=str(exc),
                         scene=str(path),
                         full_model=full_sphere_model(scene, model, cache=cache))
        report.findings.extend(scene_findings(model, scene, Path(path).name))
        return _with_usd_findings(report, scene)
    report = analyze(model, dt_setting=user_dt, scene=str(path),
                     full_model=full_sphere_model(scene, model, cache=cache))
    try:    # what bake refuses before simulating: steps and frames beyond reason
        check_run_time(model, Path(path).name, scene)
    except StabilityError as exc:
        text = str(exc)
        message, _, fix = text.partition(". Fix: ")
        report.findings.append(Finding(ERROR, "run-size", message, fix))
    for found in (emission_finding(model, Path(path).name),
                  steps_finding(model, Path(path).name, user_dt),
                  spin_finding(model, Path(path).name, user_dt),
                  sinking_finding(model, Path(path).name)):
        if found is not None:
            report.findings.append(found)
    report.findings.extend(scene_findings(model, scene, Path(path).name))
    return _with_usd_findings(report, scene)


def scene_findings(model, scene, src: str) -> list:
    """What only the scene's keys can name, whatever the time step: open meshes
    (open_mesh_findings), bodies wholly behind a plane (behind_plane_findings) or a
    box's wall (behind_box_findings), and bodies dropped with nothing under them
    (nothing_below_findings)."""
    return (open_mesh_findings(model, scene, src) + behind_plane_findings(model, scene, src)
            + behind_box_findings(model, scene, src)
            + nothing_below_findings(model, scene, src))


def spin_finding(model, src: str, dt_setting) -> Finding | None:
    """The tunnelling finding at the closing speed with the kinematic bodies' whole
    surface speed (check.prescribed), when the Model's own speed left some out."""
    extra, b = missing_surface_speed(model)
    if extra <= 0:
        return None
    closing = expected_speeds(model)[1] + extra
    found = tunnelling(model, model.dt, closing, "auto" if isinstance(dt_setting, str)
                       else "given", src)
    if found is None:
        return None
    return Finding(found.level, "prescribed-speed",
                   f"{found.message} (kinematic body {model.body_name(b)}'s surface moves at "
                   f"{extra + float(model.surface_speed):.3g} m/s)",
                   f"lower its motion's speed, or {found.fix}")


#: Steps per frame above which check and bake warn (long-bake): about 30 times the
#: most any example takes (130-1,750 at 24 fps: the conveyor's 131, the USD shot's
#: 1,748), far under the refusal at check.sizes.MAX_STEPS_PER_FRAME.
STEPS_WARN = 50_000


def steps_finding(model, src: str, dt_setting) -> Finding | None:
    """A warning when the step is so short that the bake runs far longer than meant
    though nothing is refused: more than STEPS_WARN steps per frame, most often a body
    launched far faster than meant (500 m/s for 5 m/s), whose impact the automatic
    stiffness holds to the target overlap with a stiffer spring, hence a shorter step."""
    spf = int(model.steps_per_frame)
    if spf <= STEPS_WARN:
        return None
    fastest, _, impact = expected_speeds(model)
    message = (f"{src}: dt = {model.dt:.3g} s is {spf:,} steps per frame, "
               f"{spf * max(model.n_frames - 1, 1):.3g} steps in all (the examples take "
               f"130-1,750 a frame)")
    if isinstance(dt_setting, str):
        return Finding(WARNING, "long-bake",
                       message + f": the automatic stiffness holds the fastest impact it "
                       f"allows for, {_speed(impact)} m/s (the fastest body at "
                       f"{_speed(fastest)} m/s), to the target overlap, and the faster the "
                       f"impact, the stiffer the spring and the shorter the step",
                       "check the bodies' velocity and simulation.gravity; for a body meant "
                       "to be this fast, give its material an explicit, softer stiffness or "
                       "raise simulation.stiffness_target_overlap")
    return Finding(WARNING, "long-bake", message + " (simulation.dt as given)",
                   'use simulation.dt = "auto", or a larger dt')


def _speed(v: float) -> str:
    return f"{v:.3g}" if v < 100.0 else f"{v:.0f}"


def emission_finding(model, src: str) -> Finding | None:
    """The emitters' start overlap (check.emission) as a Finding: an error above the
    limit at which the bake's emission check stops it, a warning above WARN_OVERLAP."""
    depth, b, other = emission_overlap(model)
    if depth <= WARN_OVERLAP:
        return None
    t = float(model.body_start_time[b])
    message = (f"{src}: body {model.body_name(b)} starts {depth:.0%} of a sphere diameter "
               f"deep in {model.body_name(other)} at its start_time {t:.4g} s")
    if depth > REFUSE_OVERLAP:
        return Finding(ERROR, "emission-overlap", message + "; the bake would stop there",
                       "lower the emitter's rate, widen its region (region_min, region_max) "
                       "or start its groups at other times")
    return Finding(WARNING, "emission-overlap", message + "; it will be pushed out",
                   "lower the emitter's rate or widen its region")


def _with_usd_findings(report, scene):
    """A USD stage's reading warnings (what is not simulated, planes taken from
    cubes) as warning findings ahead of the stability ones."""
    if scene.usd is None or not scene.usd.warnings:
        return report
    found = [Finding(WARNING, "usd-not-simulated" if "not simulated" in w else "usd-reading", w)
             for w in scene.usd.warnings]
    return replace(report, findings=found + list(report.findings))


def sinking_finding(model, src: str) -> Finding | None:
    """An error when a heavy body's contact, one patch however many of its spheres
    touch, takes it past the overlap guard (check.sinking): what soft-contact leaves a
    warning under auto stiffness, the bake stops on."""
    depth, b, mi, mj = sinking(model, expected_speeds(model)[1])
    if depth <= OVERLAP_ERROR:
        return None
    names = [m.name for m in model.materials]
    return Finding(
        ERROR, "sinking",
        f"{src}: body {model.body_name(b)} ({names[mi]}, {float(model.body_mass[b]):.3g} kg) "
        f"sinks {depth:.0%} of a sphere diameter into {names[mj]} (its contact is one "
        f"patch however many spheres touch); the bake's overlap guard would stop it",
        f"keep densities within 100x of each other, or give {names[mj]} an explicit, "
        f"higher stiffness")


# ------------------------------------------------------------------ scene keys


def _shape_key(scene, name: str) -> str:
    """Where a shape's mesh is given: its TOML key, or for a stage its body prim."""
    if scene.usd is None:
        spec = scene.shapes[name]
        return f"shapes.{name}.mesh" if spec.mesh_path is not None else f"shapes.{name}"
    for g, group in enumerate(scene.bodies):
        if group.shape == name and g < len(scene.usd.bodies):
            return scene.usd.bodies[g].prim
    return f"shape {name!r}"


def _group_key(scene, g: int) -> str:
    """A body group by its TOML key and name, or for a stage its prim."""
    if scene.usd is not None and g < len(scene.usd.bodies):
        return scene.usd.bodies[g].prim
    return f"bodies[{g}] ({scene.bodies[g].name!r})"


def _collider_key(scene, kind: str, k: int, field: str = "") -> str:
    """The k-th collider of type ``kind`` (a scene.data class name: "MeshCollider",
    "PlaneCollider"), the Model's k-th of that kind, by its TOML key (``field``
    appended) and name, or for a stage by its name."""
    i, c = [(i, c) for i, c in enumerate(scene.colliders) if type(c).__name__ == kind][k]
    if scene.usd is not None:
        return f"collider {c.name!r}"
    return f"colliders[{i}]{'.' + field if field else ''} ({c.name!r})"


# ------------------------------------------------------------- scene findings


def open_mesh_findings(model, scene, src: str) -> list:
    """A warning per shape and mesh collider whose mesh is not watertight (its
    sphere set's note "not_watertight"): the spheres fill it by winding number, a
    guess where it is open, and a body's mass properties come from its spheres
    instead of the exact mesh. Fracture pieces are always closed."""
    found = []
    for s in model.shapes:
        if s.name in scene.shapes and "not_watertight" in s.sphere_set.notes:
            found.append(Finding(
                WARNING, "open-mesh",
                f"{src}: {_shape_key(scene, s.name)}: mesh is not watertight: its spheres "
                f"fill it by winding number, and its mass, centre of mass and inertia come "
                f"from the spheres",
                "close the mesh's holes (a watertight mesh gives its exact mass properties)"))
    for k, m in enumerate(model.static_meshes):
        if "not_watertight" in m.notes:
            found.append(Finding(
                WARNING, "open-mesh",
                f"{src}: {_collider_key(scene, 'MeshCollider', k, 'mesh')}: mesh is not "
                f"watertight: its spheres fill it by winding number, a guess where it is "
                f"open",
                "close the mesh's holes (a watertight mesh gives its exact inside)"))
    return found


def behind_plane_findings(model, scene, src: str) -> list:
    """A warning per body group and plane collider for the group's bodies that
    start wholly behind the plane, beyond its depth (check.walls): the plane never
    touches them, so they fall or fly on through it."""
    found = []
    for k, bodies in behind_planes(model):
        nrm = np.asarray(model.plane_normal[k])
        depth = float(model.wall_depth[plane_walls(model)[k]])
        groups = np.asarray(model.body_group)[bodies]
        for g in np.unique(groups):
            count = int(np.count_nonzero(groups == g))
            who, verb = _who(model, int(g), count)
            plane = _collider_key(scene, "PlaneCollider", k)
            found.append(Finding(
                WARNING, "behind-plane",
                f"{src}: {_group_key(scene, int(g))}: {who} {verb} wholly behind {plane}, "
                f"more than {depth:.3g} m (the depth a plane pushes spheres out from) "
                f"behind its surface, where the plane never touches "
                f"{'it' if count == 1 else 'them'}",
                f"move {'it' if count == 1 else 'them'} to the side the plane's normal "
                f"[{', '.join(f'{v + 0.0:.3g}' for v in nrm)}] points to, or flip the plane's "
                f"normal"))
    return found


def behind_box_findings(model, scene, src: str) -> list:
    """A warning per body group and box collider for the group's bodies that start
    outside the box, wholly behind one of its walls within the wall's extent and
    beyond its depth, the box's thickness (check.walls): that wall never touches
    them (a body under a tray's floor falls on past it). A body that starts inside
    another box is not named. The walls of one box are one finding, naming them; a
    body counts once however many it is behind."""
    found = []
    hits = behind_boxes(model)
    group = np.asarray(model.body_group)
    for k in sorted({k for k, _, _ in hits}):
        box = model.boxes[k]
        of_box = [(w, bodies) for kk, w, bodies in hits if kk == k]
        bodies = np.unique(np.concatenate([b for _, b in of_box]))
        for g in np.unique(group[bodies]):
            mine = bodies[group[bodies] == g]
            walls = [wall_name(model, w) for w, b in of_box if np.isin(b, mine).any()]
            count = len(mine)
            who, verb = _who(model, int(g), count)
            it = "it" if count == 1 else "them"
            depth = float(model.wall_depth[of_box[0][0]])
            names = walls[0] if len(walls) == 1 else (", ".join(walls[:-1]) + " and "
                                                      + walls[-1])
            fix = (f"move {it} inside the box, between its min "
                   f"[{', '.join(f'{v + 0.0:.3g}' for v in box.lo)}] and max "
                   f"[{', '.join(f'{v + 0.0:.3g}' for v in box.hi)}]")
            if box.open_top:
                fix += (", or above its open top so that "
                        f"{'it falls' if count == 1 else 'they fall'} in")
            found.append(Finding(
                WARNING, "behind-box-wall",
                f"{src}: {_group_key(scene, int(g))}: {who} {verb} outside "
                f"{_collider_key(scene, 'BoxCollider', k)}, wholly behind its {names}, "
                f"more than {depth:.3g} m (the box's wall thickness, the depth a wall "
                f"pushes spheres out from) behind the wall's surface, where that wall "
                f"never touches {it}",
                fix))
    return found


def nothing_below_findings(model, scene, src: str) -> list:
    """A warning per body group for its dynamic bodies that start with no velocity
    across gravity and nothing under their centre (check.stability.floor_below: no
    ground-like plane below, no box collider, static mesh or kinematic body whose
    horizontal extent holds it): they fall for the whole shot, from their start time
    on. A body thrown sideways may land on something elsewhere and is not named;
    without gravity nothing falls."""
    n = model.n_bodies
    g = float(np.linalg.norm(model.gravity))
    if n == 0 or g == 0.0:
        return []
    up = -np.asarray(model.gravity) / g
    v0 = np.asarray(model.initial_v[:n]).reshape(n, 3)
    across = np.linalg.norm(v0 - np.outer(v0 @ up, up), axis=1)
    floor, _ = floor_below(model)
    dropped = np.flatnonzero(~np.asarray(model.body_static[:n]) & np.isinf(floor)
                             & (across == 0.0))
    found = []
    groups = np.asarray(model.body_group)[dropped]
    start = (np.zeros(n) if model.body_start_time is None
             else np.asarray(model.body_start_time, dtype=np.float64))
    falls = np.maximum((model.n_frames - 1) / model.fps - start[dropped], 0.0)
    for gr in np.unique(groups):
        count = int(np.count_nonzero(groups == gr))
        t = float(falls[groups == gr].max())    # the longest fall: an emitter's first
        who, verb = _who(model, int(gr), count)
        it = "it" if count == 1 else "them"
        found.append(Finding(
            WARNING, "nothing-below",
            f"{src}: {_group_key(scene, int(gr))}: {who} {verb} with nothing under "
            f"{it} (no ground plane below, no box, static mesh or kinematic body under "
            f"{'its' if count == 1 else 'their'} centre): "
            f"{'it falls' if count == 1 else 'they fall'} for the whole shot, "
            f"{g * t * t / 2:.3g} m in {t:.3g} s",
            f"add a ground (a [[colliders]] entry with type = \"plane\") or move {it} over "
            f"a collider"))
    return found


def _who(model, g: int, count: int) -> tuple[str, str]:
    """How many of group g's bodies a finding is about, in words, and the verb's
    form: ("its body", "starts"), ("all 4 of its bodies", "start"), ..."""
    total = int(np.count_nonzero(np.asarray(model.body_group) == g))
    who = ("its body" if total == 1 else
           f"all {total} of its bodies" if count == total else
           f"{count} of its {total} bodies")
    return who, "starts" if count == 1 else "start"
