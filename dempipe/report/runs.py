"""Error against run time: what `dempipe report` runs.

    result = run_report("examples/quickstart.toml", "report/", Sweep())

A bake trades accuracy for speed through three knobs: the sphere diameter (the
resolution), the contact stiffness and the time step. ``run_report`` bakes every
combination of a :class:`Sweep` (library calls: build_model + Simulator, no USD),
measures each run's error (dempipe/report/accuracy.py) and cost, and writes

    DIR/report.md      tables and the recommended setting    (report/tables.py)
    DIR/report.csv     one row per run                        (report/tables.py)
    DIR/error_vs_time.png, DIR/error_vs_setting.png           (report/plots.py)

Every file is written atomically (a temporary file, then os.replace). The
reference run is the finest resolution at the smallest dt factor and stiffness
factor 1; motion errors are measured against it. See docs/accuracy.md.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dempipe.check.sizes import MAX_FRAMES, check_run_time, memory_estimate
from dempipe.errors import StabilityError
from dempipe.farm.cluster import failure_reason
from dempipe.report import accuracy as acc
from dempipe.report.plots import require_matplotlib, plot_report
from dempipe.report.results import (
    HORIZON_AFTER_CONTACT,
    ReportError,
    ReportResult,
    Run,
    seconds,
    within_tolerances,
    write_atomically,
)
from dempipe.report.tables import format_markdown, write_csv
from dempipe.scene.build import Overrides, shape_mesh, build_model
from dempipe.scene.load import load_scene
from dempipe.sim import laws
from dempipe.sim.laws import LAWS
from dempipe.sim.simulator import BakeFailure, Simulator, resolve_device
from dempipe.spheres import fidelity
from dempipe.spheres.cache import SphereCache
from dempipe.spheres.options import DEFAULT_MODE, MODES
from dempipe.spheres.sphere_set import (
    build_sphere_set,
    build_sphere_set_with_info,
    mesh_for_errors,
)
from dempipe.spheres.surface import envelope_errors

#: Defaults sized to finish in a few minutes on 2 CPU cores for the quick start
#: scene (196 bodies): the scene's resolution and two coarser ones, two steps, two
#: stiffnesses, half a second. `--resolutions` etc. widen the sweep.
DEFAULT_RESOLUTION_FACTORS = (2 / 3, 5 / 6, 1.0)
DEFAULT_DT_FACTORS = (1.0, 0.5)
DEFAULT_STIFFNESS_FACTORS = (0.3, 1.0)
DEFAULT_DURATION = 0.5
#: Sweep values (resolutions, factors) from 1/SWEEP_SPAN to SWEEP_SPAN: beyond, a run
#: is a typing error whose stiffness or step count overflows before it can fail.
SWEEP_SPAN = 1e6
DEFAULT_TOLERANCE = 0.02
#: A scene with at least this many bodies is a pile: the report adds the statistics
#: a viewer sees of it, and the chaos floor they can be compared with.
PILE_BODIES = 10


def parse_values(text: str, option: str, kind=float) -> tuple:
    """'6,8,12' → (6, 8, 12); a ReportError naming ``option`` for anything else."""
    parts = [p.strip() for p in str(text).split(",") if p.strip()]
    if not parts:
        raise ReportError(f"{option}: expected comma-separated numbers, got {text!r}")
    out = []
    for p in parts:
        try:
            v = kind(p)
        except ValueError:
            what = "whole numbers" if kind is int else "numbers"
            raise ReportError(f"{option}: {p!r} is not a number (expected comma-separated "
                              f"{what}, e.g. {'4,6,8' if kind is int else '1,0.5'})") from None
        if not (math.isfinite(v) and v > 0):
            raise ReportError(f"{option}: {p} must be greater than 0")
        if not 1.0 / SWEEP_SPAN <= v <= SWEEP_SPAN:
            raise ReportError(f"{option}: {p} is out of range (expected "
                              f"{1.0 / SWEEP_SPAN:g} to {SWEEP_SPAN:g})")
        out.append(v)
    return tuple(sorted(set(out)))


@dataclass(frozen=True)
class Sweep:
    """What to bake. None picks the default (see the DEFAULT_* constants).

    resolutions : spheres across the smallest shape's longest extent; default: the
        scene's resolution times DEFAULT_RESOLUTION_FACTORS
    dt_factors : multiply the scene's step (dt="auto": its steps per contact divide)
    stiffness_factors : multiply every material's stiffness (auto included)
    duration : simulated seconds per run [s]; default min(scene, DEFAULT_DURATION)
    horizon : when the per-body motion error (the headline error) is taken [s];
        default: HORIZON_AFTER_CONTACT after the reference's median first contact
    tolerance : the error a recommended setting may have
    bodies : bake only the first N bodies of the scene (group order)
    sphere_modes : sphere-set modes to sweep ("lattice", "surface"); None: the scene's
        own (no mode axis). The reference takes the last one given.
    rolling_tolerance : the incline rolling error (accuracy.incline_rolling_error) a
        recommended setting may have; None: not a condition (it is still measured).
    contact_laws : contact laws to sweep ("linear", "hertz"; laws.LAWS); None: the
        scene's own (no law axis). The reference takes the last one given.
    """

    resolutions: tuple | None = None
    dt_factors: tuple = DEFAULT_DT_FACTORS
    stiffness_factors: tuple = DEFAULT_STIFFNESS_FACTORS
    duration: float | None = None
    horizon: float | None = None
    tolerance: float = DEFAULT_TOLERANCE
    bodies: int | None = None
    device: str | None = None
    threads: int | None = None
    plots: bool = True
    sphere_modes: tuple | None = None
    rolling_tolerance: float | None = None
    contact_laws: tuple | None = None






# --------------------------------------------------------------------------- sweep


def _scene_resolution(scene) -> float:
    """The scene's own resolution (derived from sphere_diameter when it gives one)."""
    sim = scene.simulation
    if sim.sphere_diameter is None:
        return float(sim.resolution)
    extents = []
    for g in scene.bodies:
        for n in ([g.shape] if isinstance(g.shape, str) else g.shape):
            mesh = shape_mesh(scene.shapes[n], n)     # builtin, file or in memory (USD)
            extents.append(float(np.max(mesh.extents)))
    return min(extents) / sim.sphere_diameter


def _first_bodies(scene, n: int):
    """The scene with only its first ``n`` bodies (group order; later groups dropped)."""
    groups, left = [], n
    for g in scene.bodies:
        if left <= 0:
            break
        groups.append(replace(g, count=min(g.count, left)))
        left -= groups[-1].count
    return replace(scene, bodies=tuple(groups))


def _overrides(scene, res: int, dt_factor: float, k_factor: float, duration: float,
               mode: str | None = None, law: str | None = None):
    dt = scene.simulation.dt
    if isinstance(dt, str):      # auto: more steps per contact
        return Overrides(resolution=res, dt_factor=dt_factor, stiffness_factor=k_factor,
                         duration=duration, spheres=mode, contact_law=law)
    return Overrides(resolution=res, dt=float(dt) * dt_factor, stiffness_factor=k_factor,
                     duration=duration, spheres=mode, contact_law=law)


def _axis(values, known, option: str, what: str) -> tuple:
    """A sweep axis of names: (None,) without one, else the names in the order given,
    each checked against ``known`` (ReportError naming ``option`` and the choices)."""
    if not values:
        return (None,)
    for v in values:
        if v not in known:
            raise ReportError(f"{option}: unknown {what} {v!r} (use {', '.join(known)})")
    return tuple(dict.fromkeys(values))


def _contact_laws(sweep) -> tuple:
    """The law axis (laws.LAWS)."""
    return _axis(sweep.contact_laws, LAWS, "--laws", "contact law")


def _sphere_modes(sweep) -> tuple:
    """The sphere-set mode axis (spheres.MODES)."""
    return _axis(sweep.sphere_modes, MODES, "--spheres", "mode")


def _is_surface(shape) -> bool:
    """Whether a model shape's sphere set was built in surface mode (its note says so;
    a scene's spheres setting may give each shape its own mode)."""
    return "surface" in shape.sphere_set.notes


def _shape_envelopes(model) -> dict:
    """Each shape's envelope errors (spheres.surface.envelope_errors) [m], by name."""
    import trimesh


    out = {}
    for s in model.shapes:
        mesh = trimesh.Trimesh(vertices=np.asarray(s.vertices) + s.sphere_set.com,
                               faces=np.asarray(s.faces), process=False)
        out[s.name] = envelope_errors(mesh_for_errors(mesh),
                                      s.sphere_set.centers + s.sphere_set.com, model.diameter)
    return out


def _worst_envelope(envelopes, diameter: float) -> dict:
    """The worst shape's envelope errors, in sphere diameters (the modes table)."""
    return dict(hausdorff_d=max((e.hausdorff / diameter for e in envelopes), default=0.0),
                bump_d=max((e.bump / diameter for e in envelopes), default=0.0))


def _shape_geometry(shape, envelope) -> fidelity.GeometryError:
    """One shape's sphere set against its mesh (the geometry table's row).

    A lattice set: fidelity.shape_geometry_error (its contact surface is found from
    the 26 lattice neighbours). A surface set has no lattice: its spheres overlap,
    so that contact surface and the cells' volume and inertia (N d³, which a shell
    of overlapping spheres overcounts) mean nothing; its Hausdorff is its envelope's
    (``envelope``, spheres.surface.envelope_errors: the mesh surface to the nearest
    sphere, the spheres past the mesh), in shape sizes as the lattice's, and the
    rest NaN (shown "—"). The bodies' mass properties come from the mesh in both."""
    if not _is_surface(shape):
        return fidelity.shape_geometry_error(shape.sphere_set, shape.vertices, shape.faces)
    v = np.asarray(shape.vertices, dtype=np.float64)
    size = float((v.max(axis=0) - v.min(axis=0)).max())
    return fidelity.GeometryError(
        spheres=shape.sphere_set.count, volume=math.nan, inertia=math.nan,
        hausdorff=envelope.hausdorff / size, mesh_to_spheres=math.nan,
        spheres_to_mesh=math.nan, size=size)


def _dominant_material(model):
    """The material most dynamic bodies are made of (the closed-form cases use it)."""
    counts = np.bincount(np.asarray(model.body_material[:model.n_bodies]),
                         minlength=len(model.materials))
    mi = int(np.argmax(counts))
    return mi, model.materials[mi]


def _warm_voxelizer() -> None:
    """Load the voxelizer's compiled kernel, so cold build times are builds alone."""
    import trimesh


    build_sphere_set(trimesh.creation.box(extents=(1.0, 1.0, 1.0)), 0.5, cache=None)


def _cold_build_seconds(model) -> float:
    """Sphere-set build time of every shape and mesh collider without the cache [s]."""
    import trimesh


    total = 0.0
    meshes = [(s.vertices + s.com, s.faces) for s in model.shapes]
    meshes += [(m.vertices, m.faces) for m in model.static_meshes]
    for v, f in meshes:
        mesh = trimesh.Trimesh(vertices=np.asarray(v), faces=np.asarray(f), process=False)
        total += build_sphere_set_with_info(mesh, model.diameter, cache=None)[1].seconds
    return total


def _bake(model, device: str, threads):
    """Simulate ``model`` for all its frames; returns (frames, wall seconds, steps)."""
    # compile or load the kernels for this feature set before the clock starts
    Simulator(model, device=device, threads=threads).backend.step(model.initial_state(), 1)
    sim = Simulator(model, device=device, threads=threads)
    frames = sim.advance(model.initial_state())
    return frames, sim.stats.wall_seconds, sim.stats.steps


def _farm_bake(model, device: str, threads):
    """A farm task: _bake, with the bake's own failures returned as a line, not raised."""
    if threads is None:          # the pool this worker process was given
        import numba

        threads = numba.config.NUMBA_NUM_THREADS
    try:
        return _bake(model, device, threads)
    except (StabilityError, BakeFailure) as exc:
        return " ".join(str(exc).split())


def _gather_farmed(farm, farmed, n_runs: int, say) -> None:
    """Fill each farmed run as its task finishes (a line each); the reference must pass."""
    by_future = {fut: (i, run) for i, run, fut in farmed}
    for fut, value, error in farm.finished(list(by_future)):
        i, run = by_future[fut]
        reason = failure_reason(error) if error is not None else \
            value if isinstance(value, str) else None
        if reason is None:
            run.frames, run.wall_s, run.steps = value
        elif run.reference:
            raise StabilityError(f"the reference run ({run.label}) failed: {reason}")
        else:
            run.status = "failed: " + reason
        say(f"run {i + 1}/{n_runs} {run.label}: "
            + (_run_line(run) if run.ok else run.status))


def _run_line(run: Run, total_s: float | None = None) -> str:
    """A run's progress line: its spheres, its steps and the wall time of its simulation
    alone (Run.wall_s, what the tables compare; three figures: a small scene steps in
    hundredths of a second) and, when known, the run's whole time, which adds the
    sphere sets' cold and cached builds and their measures, and loading the kernels."""
    line = f"{run.spheres:,} spheres, {run.steps:,} steps in {seconds(run.wall_s)} s simulating"
    if total_s is not None:
        line += f" ({seconds(total_s)} s in all, with the sphere sets and kernels)"
    return line


def run_report(scene_path, out_dir, sweep: Sweep = Sweep(), *, cache=None,
               progress=None, farm=None) -> ReportResult:
    """Bake every combination of ``sweep`` for the scene, measure, write DIR's files.

    progress : callable(str) for one line per run (the CLI prints them).
    farm : an open dempipe.farm.cluster.Farm (`--workers`/`--scheduler`): the runs' bakes are
        its tasks, run side by side (models are built here, measured here).
    Raises ReportError for unusable settings, SceneError etc. for the scene, and
    StabilityError when the reference run itself fails.
    """
    t_start = time.perf_counter()
    say = progress or (lambda line: None)
    if sweep.plots:
        require_matplotlib()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ReportError(f"{out}: exists and is not a folder")
    scene = load_scene(scene_path)
    if sweep.bodies is not None:
        scene = _first_bodies(scene, int(sweep.bodies))
    if any(lw != scene.simulation.contact_law for lw in _contact_laws(sweep) if lw):
        for name, m in scene.materials.items():
            if m.stiffness != "auto" or m.young_modulus is not None:
                raise ReportError(
                    f"--laws: materials.{name} gives its stiffness in the units of the "
                    f"scene's law ({scene.simulation.contact_law}), which another law would "
                    f"read in its own (N/m against N/m^1.5): leave it \"auto\" to compare laws")
    device = resolve_device(sweep.device or scene.simulation.device)
    cache = cache if cache is not None else SphereCache()
    duration = sweep.duration or min(scene.output.duration, DEFAULT_DURATION)
    if not (math.isfinite(duration) and duration > 0):
        raise ReportError(f"--duration: {duration:g} must be a finite number above 0")
    frames = duration * scene.output.fps + 1
    if frames > MAX_FRAMES:
        raise ReportError(f"--duration {duration:g}: {frames:.3g} frames at "
                          f"{scene.output.fps:g} fps, at most {MAX_FRAMES:.0e} a run (each run "
                          f"keeps its frames in memory); give a shorter --duration")
    if sweep.horizon is not None and not (math.isfinite(sweep.horizon) and sweep.horizon > 0):
        raise ReportError(f"--horizon: {sweep.horizon:g} must be greater than 0")
    over = [f for f in sweep.dt_factors if f > 1.0]
    if over and isinstance(scene.simulation.dt, str):
        # the auto step is the largest the stability bounds allow: a factor above 1 is
        # cut back to it, and the run would be the factor-1 run under another label
        raise ReportError(
            f"--dt-factors: {', '.join(f'{f:g}' for f in over)} above 1, but the scene's "
            f"simulation.dt is \"auto\", already the largest stable step; give factors "
            f"of at most 1, or a fixed simulation.dt in the scene to sweep above it")

    resolutions = sweep.resolutions
    if resolutions is None:
        r0 = _scene_resolution(scene)
        resolutions = tuple(sorted({max(2, round(r0 * f)) for f in DEFAULT_RESOLUTION_FACTORS}))
    resolutions = tuple(sorted(int(r) for r in resolutions))
    dts = tuple(sorted(sweep.dt_factors, reverse=True))
    ks = tuple(sorted(sweep.stiffness_factors))
    modes = _sphere_modes(sweep)
    law_axis = _contact_laws(sweep)
    ref_key = (resolutions[-1], dts[-1], 1.0, modes[-1], law_axis[-1])
    keys = [ref_key] + [(r, f, k, m, lw) for r in resolutions for f in dts for k in ks
                        for m in modes for lw in law_axis
                        if (r, f, k, m, lw) != ref_key]
    # cheapest first after the reference: a user watching sees results soon
    keys[1:] = sorted(keys[1:], key=lambda x: (x[0], -x[1], x[2], modes.index(x[3]),
                                               law_axis.index(x[4])))

    _warm_voxelizer()
    runs, shapes, built, farmed = [], {}, {}, []
    envelopes = {}
    for i, (r, f, k, mode, law) in enumerate(keys):
        t_run = time.perf_counter()
        run = Run(r, f, k, reference=(i == 0), mode=mode, law=law)
        runs.append(run)
        try:
            if (r, mode) not in built:    # sphere sets once per resolution: cold, cached
                first = build_model(scene, cache=cache,
                                    overrides=_overrides(scene, r, 1.0, 1.0, duration, mode))
                again = build_model(scene, cache=cache,
                                    overrides=_overrides(scene, r, 1.0, 1.0, duration, mode))
                built[(r, mode)] = (_cold_build_seconds(first),
                                    again.build_info.get("sphere_build_seconds", math.nan))
                # every mode's geometry, each by its own measure (_shape_geometry)
                env = _shape_envelopes(first) if mode is not None or \
                    any(_is_surface(s) for s in first.shapes) else {}
                if mode is not None:
                    envelopes[(r, mode)] = _worst_envelope(env.values(), first.diameter)
                for s in first.shapes:
                    shapes[(s.name, r, mode)] = _shape_geometry(s, env.get(s.name))
            model = build_model(scene, cache=cache,
                                overrides=_overrides(scene, r, f, k, duration, mode, law))
            # what bake refuses before simulating (steps, frames beyond reason): the
            # report's --duration and factors reach it here, not at the allocation
            check_run_time(model, Path(scene_path).name)
            run.model = model
            run.envelope = envelopes.get((r, mode), {})
            run.sphere_build_cold_s, run.sphere_build_cached_s = built[(r, mode)]
            run.diameter, run.dt, run.spheres = model.diameter, model.dt, model.n_spheres
            run.memory_bytes = int(memory_estimate(model)["total"])
            run.geometry = _worst_geometry([shapes[(s.name, r, mode)] for s in model.shapes])
            if farm is not None:       # baked by a task; said when it finishes
                farmed.append((i, run, farm.submit(_farm_bake, model, device, sweep.threads,
                                                   key=f"dempipe-report-{i}-{time.time_ns()}")))
                continue
            run.frames, run.wall_s, run.steps = _bake(model, device, sweep.threads)
        except (StabilityError, BakeFailure) as exc:
            if run.reference:
                raise StabilityError(f"the reference run ({run.label}) failed: {exc}") from None
            run.status = "failed: " + " ".join(str(exc).split())
        say(f"run {i + 1}/{len(keys)} {run.label}: "
            + (_run_line(run, time.perf_counter() - t_run) if run.ok else run.status))

    if farmed:
        _gather_farmed(farm, farmed, len(keys), say)

    ref = runs[0]
    pile = ref.model.n_bodies >= PILE_BODIES
    first = acc.first_contact_times(ref.frames, ref.model)
    if sweep.horizon is None:
        median = float(np.median(first))
        horizon = min(duration, median + HORIZON_AFTER_CONTACT)     # inf: most never touch
    else:
        horizon = min(sweep.horizon, duration)
    touched = int((first <= horizon).sum())
    if touched == 0:
        say(f"note: no body touched anything by the horizon t = {horizon:g} s: the motion "
            f"errors measure free flight only (lengthen --duration or set --horizon)")
    _measure_motion(runs, ref, horizon)
    say("closed-form cases (bounce, rolling, spin) ...")
    mi, material = _measure_physics(runs, ref, fixed_dt=not isinstance(scene.simulation.dt, str),
                                    scene_mode=scene.simulation.spheres, cache=cache)
    _mark_pareto(runs)
    recommended = recommend(runs, sweep.tolerance, sweep.rolling_tolerance)
    result = ReportResult(
        runs=runs, reference=ref, recommended=recommended, shapes=shapes, files=[],
        wall_s=0.0, scene=str(scene_path), material=material.name, pile=pile,
        duration=duration, horizon=horizon, tolerance=sweep.tolerance,
        bodies=ref.model.n_bodies, rolling_tolerance=sweep.rolling_tolerance,
        stage=(Path(scene_path).name if scene.usd is not None
               and Path(scene_path).suffix.lower() in (".usd", ".usda", ".usdc") else None),
        target_overlap=scene.simulation.stiffness_target_overlap or 0.02, touched=touched)
    out.mkdir(parents=True, exist_ok=True)
    result.files.append(write_atomically(out / "report.csv", write_csv(runs).encode()))
    if sweep.plots:
        result.files += plot_report(result, out)
    result.wall_s = time.perf_counter() - t_start
    result.files.insert(0, write_atomically(out / "report.md", format_markdown(result).encode()))
    return result


def recommend(runs, tolerance: float, rolling_tolerance: float | None = None):
    """The cheapest run (wall time) whose error is within ``tolerance`` and, when given,
    whose incline rolling error is within ``rolling_tolerance`` (docs/accuracy.md);
    None when there is none. The reference (error 0) is one of the candidates: when no
    other run meets both, it is the setting to bake (with --spheres and
    --rolling-tolerance, often a mode other than the scene's, which its scene lines
    must then name); only a reference that does not roll leaves None."""
    candidates = [u for u in runs if within_tolerances(u, tolerance, rolling_tolerance)]
    return min(candidates, key=lambda u: u.wall_s) if candidates else None






def _worst_geometry(errs) -> dict:
    """The worst shape's volume, inertia and Hausdorff errors (NaN where no shape has
    the measure: a surface set's volume and inertia)."""
    def worst(values):
        values = [v for v in values if math.isfinite(v)]
        return max(values) if values else math.nan

    return dict(volume=worst(abs(e.volume) for e in errs), inertia=worst(e.inertia for e in errs),
                hausdorff=worst(e.hausdorff for e in errs))


def _measure_motion(runs, ref, horizon: float) -> None:
    sizes = acc.body_sizes(ref.model)
    size = float(sizes.mean())
    h = int(round(horizon * ref.model.fps))
    for u in runs:
        if not u.ok:
            continue
        u.pile = acc.pile_statistics(u.frames, u.model, sizes)
    for u in runs:
        if not u.ok:
            continue
        at_h = acc.motion_error(u.frames, ref.frames, sizes, h)
        end = acc.motion_error(u.frames, ref.frames, sizes, ref.frames.n_frames - 1)
        u.motion = dict(position_h=at_h.position, orientation_h_deg=at_h.orientation_deg,
                        position_end=end.position, orientation_end_deg=end.orientation_deg,
                        **acc.pile_error(u.pile, ref.pile, size))
        u.error = u.motion["position_h"]


def _measure_physics(runs, ref, fixed_dt: bool, scene_mode=None, cache=None):
    """Closed-form cases per dt rule, in the scene's dominant material.

    With dt="auto" a ball's own contact is resolved in S/dt_factor steps (S: the
    law's STEPS_PER_CONTACT, 10 linear, 12 Hertz) whatever its size and stiffness,
    so the cases run once per dt factor (at the reference's diameter and
    stiffness); with a fixed scene dt they run per run. The spin runs at
    each run's own dt. The incline (a ball of the run's resolution and sphere-set
    mode rolling down a slope) runs once per resolution, mode and dt factor, at its
    own automatic contact resolved in S/dt_factor steps.
    """
    mi, material = _dominant_material(ref.model)
    memo = {}
    smallest = int(np.argmin([s.sphere_set.volume for s in ref.model.shapes]))
    for u in runs:
        if not u.ok:
            continue
        m = u.model
        law = m.contact_law
        spc = laws.law(law).STEPS_PER_CONTACT   # dt="auto"'s
        # the stiffness in the run's law's units (a law axis: the reference's may differ)
        base = ref.model if ref.model.contact_law == law else m
        if not fixed_dt:
            # a law other than the reference's: its own run's stiffness, so its own key
            key = ("auto", u.dt_factor, law) + (() if base is ref.model else
                                                 (u.resolution, u.stiffness_factor))
            rule = acc.DtRule(steps_per_contact=spc / u.dt_factor, law=law)
            d, k = base.diameter, float(base.pair_k[mi, mi])
        else:
            key = (u.resolution, u.dt_factor, u.stiffness_factor, law)
            rule = acc.DtRule(dt=m.dt, law=law)
            d, k = m.diameter, float(m.pair_k[mi, mi])
        if key not in memo:
            try:
                memo[key] = (acc.bounce_error(material, d, k, rule),
                             acc.rolling_error(material, d, k, rule))
            except StabilityError:
                memo[key] = (math.nan, math.nan)
        spin_key = ("spin", m.dt)
        if spin_key not in memo:
            memo[spin_key] = acc.spin_drift(m.shapes[smallest], m.dt)
        mode = u.mode or scene_mode or DEFAULT_MODE
        incline_key = ("incline", u.resolution, mode, u.dt_factor, law)
        if incline_key not in memo:
            try:
                memo[incline_key] = acc.incline_rolling_error(
                    material, u.resolution, mode,
                    acc.DtRule(steps_per_contact=spc / u.dt_factor, law=law), cache=cache)
            except StabilityError:
                memo[incline_key] = math.nan
        bounce, rolling = memo[key]
        spin_L, spin_E = memo[spin_key]
        u.physics = dict(bounce=bounce, rolling=rolling, spin_L=spin_L, spin_energy=spin_E,
                         incline=memo[incline_key])
    return mi, material


def _mark_pareto(runs) -> None:
    """Pareto front over (wall time, error): the runs no other run beats in both, i.e.
    none is at least as fast and as accurate and better in one (docs/accuracy.md).
    The reference is one of them unless a run of its error 0 is faster: it must not be
    left out, since every run is measured against it, and it is often the only
    setting within the tolerances."""
    ok = [u for u in runs if u.ok and math.isfinite(u.error)]
    for u in ok:
        u.pareto = not any(o is not u and o.wall_s <= u.wall_s and o.error <= u.error
                           and (o.wall_s < u.wall_s or o.error < u.error) for o in ok)




