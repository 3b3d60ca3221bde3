"""Error against run time: what `dempipe report` runs.

    result = run_report("examples/quickstart.toml", "report/", Sweep())

A bake trades accuracy for speed through three knobs: the sphere diameter (the
resolution), the contact stiffness and the time step. ``run_report`` bakes every
combination of a :class:`Sweep` (library calls: build_model + Simulator, no USD),
measures each run's error (dempipe/accuracy.py) and cost, and writes

    DIR/report.md      tables and the recommended setting
    DIR/report.csv     one row per run
    DIR/error_vs_time.png, DIR/error_vs_setting.png

Every file is written atomically (a temporary file, then os.replace). The
reference run is the finest resolution at the smallest dt factor and stiffness
factor 1; motion errors are measured against it. See docs/accuracy.md.
"""

from __future__ import annotations

import csv
import io
import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from . import accuracy as acc
from . import laws
from .errors import DempipeError, StabilityError


class ReportError(DempipeError):
    """A report's settings are unusable (bad sweep values, missing plotting extra)."""


#: Defaults sized to finish in a few minutes on 2 CPU cores for the quick start
#: scene (196 bodies): the scene's resolution and two coarser ones, two steps, two
#: stiffnesses, half a second. `--resolutions` etc. widen the sweep.
DEFAULT_RESOLUTION_FACTORS = (2 / 3, 5 / 6, 1.0)
DEFAULT_DT_FACTORS = (1.0, 0.5)
DEFAULT_STIFFNESS_FACTORS = (0.3, 1.0)
DEFAULT_DURATION = 0.5
DEFAULT_TOLERANCE = 0.02
#: The default horizon of the per-body motion error: this long after the median
#: body's first contact. Before any contact every run agrees (free flight is exact);
#: long after it, contacts have amplified every difference (chaos), whatever the
#: accuracy. A few frames of contact in between is where accuracy shows.
HORIZON_AFTER_CONTACT = 0.1
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


@dataclass
class Run:
    """One baked combination and everything measured about it (one CSV row)."""

    resolution: int
    dt_factor: float
    stiffness_factor: float
    reference: bool = False
    status: str = "ok"
    diameter: float = math.nan
    dt: float = math.nan
    steps: int = 0
    spheres: int = 0
    wall_s: float = math.nan
    memory_bytes: int = 0
    sphere_build_cold_s: float = math.nan
    sphere_build_cached_s: float = math.nan
    geometry: dict = field(default_factory=dict)      # worst shape: volume, inertia, hausdorff
    motion: dict = field(default_factory=dict)
    physics: dict = field(default_factory=dict)
    error: float = math.nan
    pareto: bool = False
    frames: object = None
    model: object = None
    pile: object = None
    mode: str | None = None          # sphere-set mode of the sweep's mode axis (None: none)
    law: str | None = None           # contact law of the sweep's law axis (None: none)
    envelope: dict = field(default_factory=dict)   # worst shape: hausdorff_d, bump_d

    @property
    def model_frames(self) -> int:
        """Frames stepped (the first is the initial state)."""
        return self.frames.n_frames - 1 if self.frames is not None else 0

    @property
    def label(self) -> str:
        mode = f" {self.mode}" if self.mode else ""
        law = f" {self.law}" if self.law else ""
        return (f"r{self.resolution} dt×{self.dt_factor:g} k×{self.stiffness_factor:g}"
                f"{mode}{law}")

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def s_per_step(self) -> float:
        return self.wall_s / self.steps if self.steps else math.nan

    @property
    def sim_seconds(self) -> float:
        return self.frames.times[-1] if self.frames is not None else math.nan

    @property
    def s_per_sim_s(self) -> float:
        return self.wall_s / self.sim_seconds if self.sim_seconds else math.nan


@dataclass
class ReportResult:
    """What run_report measured and wrote."""

    runs: list
    reference: Run
    recommended: Run | None
    shapes: dict            # (shape name, resolution) -> accuracy.GeometryError
    files: list
    wall_s: float
    scene: str
    material: str
    pile: bool
    duration: float
    horizon: float
    tolerance: float
    bodies: int
    target_overlap: float = 0.02
    rolling_tolerance: float | None = None
    stage: str | None = None    # the USD stage's file name when it was given as the scene


# --------------------------------------------------------------------------- sweep


def _scene_resolution(scene) -> float:
    """The scene's own resolution (derived from sphere_diameter when it gives one)."""
    from .build import _shape_mesh

    sim = scene.simulation
    if sim.sphere_diameter is None:
        return float(sim.resolution)
    extents = []
    for g in scene.bodies:
        for n in ([g.shape] if isinstance(g.shape, str) else g.shape):
            mesh = _shape_mesh(scene.shapes[n], n)     # builtin, file or in memory (USD)
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
    from .build import Overrides

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
    from .laws import LAWS

    return _axis(sweep.contact_laws, LAWS, "--laws", "contact law")


def _sphere_modes(sweep) -> tuple:
    """The sphere-set mode axis (spheres.MODES)."""
    from .spheres import MODES

    return _axis(sweep.sphere_modes, MODES, "--spheres", "mode")


def _envelope(model) -> dict:
    """The worst shape's envelope errors (surface_spheres.envelope_errors) in diameters."""
    import trimesh

    from .spheres import mesh_for_errors
    from .surface_spheres import envelope_errors

    worst = dict(hausdorff_d=0.0, bump_d=0.0)
    for s in model.shapes:
        mesh = trimesh.Trimesh(vertices=np.asarray(s.vertices) + s.sphere_set.com,
                               faces=np.asarray(s.faces), process=False)
        e = envelope_errors(mesh_for_errors(mesh), s.sphere_set.centers + s.sphere_set.com,
                            model.diameter)
        worst["hausdorff_d"] = max(worst["hausdorff_d"], e.hausdorff / model.diameter)
        worst["bump_d"] = max(worst["bump_d"], e.bump / model.diameter)
    return worst


def _dominant_material(model):
    """The material most dynamic bodies are made of (the closed-form cases use it)."""
    counts = np.bincount(np.asarray(model.body_material[:model.n_bodies]),
                         minlength=len(model.materials))
    mi = int(np.argmax(counts))
    return mi, model.materials[mi]


def _warm_voxelizer() -> None:
    """Load the voxelizer's compiled kernel, so cold build times are builds alone."""
    import trimesh

    from .spheres import build_sphere_set

    build_sphere_set(trimesh.creation.box(extents=(1.0, 1.0, 1.0)), 0.5, cache=None)


def _cold_build_seconds(model) -> float:
    """Sphere-set build time of every shape and mesh collider without the cache [s]."""
    import trimesh

    from .spheres import build_sphere_set_with_info

    total = 0.0
    meshes = [(s.vertices + s.com, s.faces) for s in model.shapes]
    meshes += [(m.vertices, m.faces) for m in model.static_meshes]
    for v, f in meshes:
        mesh = trimesh.Trimesh(vertices=np.asarray(v), faces=np.asarray(f), process=False)
        total += build_sphere_set_with_info(mesh, model.diameter, cache=None)[1].seconds
    return total


def _bake(model, device: str, threads):
    """Simulate ``model`` for all its frames; returns (frames, wall seconds, steps)."""
    from .simulator import Simulator

    # compile or load the kernels for this feature set before the clock starts
    Simulator(model, device=device, threads=threads).backend.step(model.initial_state(), 1)
    sim = Simulator(model, device=device, threads=threads)
    frames = sim.advance(model.initial_state())
    return frames, sim.stats.wall_seconds, sim.stats.steps


def _farm_bake(model, device: str, threads):
    """A farm task: _bake, with the bake's own failures returned as a line, not raised."""
    from .simulator import BakeFailure

    if threads is None:          # the pool this worker process was given
        import numba

        threads = numba.config.NUMBA_NUM_THREADS
    try:
        return _bake(model, device, threads)
    except (StabilityError, BakeFailure) as exc:
        return " ".join(str(exc).split())


def _gather_farmed(farm, farmed, n_runs: int, say) -> None:
    """Fill each farmed run as its task finishes (a line each); the reference must pass."""
    from .farm import failure_reason

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
            + (f"{run.spheres:,} spheres, {run.steps:,} steps in {run.wall_s:.1f} s"
               if run.ok else run.status))


def run_report(scene_path, out_dir, sweep: Sweep = Sweep(), *, cache=None,
               progress=None, farm=None) -> ReportResult:
    """Bake every combination of ``sweep`` for the scene, measure, write DIR's files.

    progress : callable(str) for one line per run (the CLI prints them).
    farm : an open dempipe.farm.Farm (`--workers`/`--scheduler`): the runs' bakes are
        its tasks, run side by side (models are built here, measured here).
    Raises ReportError for unusable settings, SceneError etc. for the scene, and
    StabilityError when the reference run itself fails.
    """
    from .build import build_model
    from .cache import SphereCache
    from .scene import load_scene
    from .simulator import BakeFailure, resolve_device
    from .sizes import memory_estimate

    t_start = time.perf_counter()
    say = progress or (lambda line: None)
    if sweep.plots:
        _require_matplotlib()
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
    if sweep.horizon is not None and not sweep.horizon > 0:
        raise ReportError(f"--horizon: {sweep.horizon:g} must be greater than 0")

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
                if mode is not None:
                    envelopes[(r, mode)] = _envelope(first)
                if mode in (None, modes[0]):
                    # the lattice-based measures (contact surface of lattice neighbours)
                    for s in first.shapes:
                        shapes[(s.name, r)] = acc.shape_geometry_error(s.sphere_set,
                                                                       s.vertices, s.faces)
            model = build_model(scene, cache=cache,
                                overrides=_overrides(scene, r, f, k, duration, mode, law))
            run.model = model
            run.envelope = envelopes.get((r, mode), {})
            run.sphere_build_cold_s, run.sphere_build_cached_s = built[(r, mode)]
            run.diameter, run.dt, run.spheres = model.diameter, model.dt, model.n_spheres
            run.memory_bytes = int(memory_estimate(model)["total"])
            run.geometry = _worst_geometry([shapes[(s.name, r)] for s in model.shapes]) \
                if mode in (None, modes[0]) else {}
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
            + (f"{run.spheres:,} spheres, {run.steps:,} steps in {run.wall_s:.1f} s"
               if run.ok else run.status))

    if farmed:
        _gather_farmed(farm, farmed, len(keys), say)

    ref = runs[0]
    pile = ref.model.n_bodies >= PILE_BODIES
    if sweep.horizon is None:
        median = float(np.median(acc.first_contact_times(ref.frames, ref.model)))
        horizon = min(duration, median + HORIZON_AFTER_CONTACT)     # inf: most never touch
    else:
        horizon = min(sweep.horizon, duration)
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
        target_overlap=scene.simulation.stiffness_target_overlap or 0.02)
    out.mkdir(parents=True, exist_ok=True)
    result.files.append(_atomic_write(out / "report.csv", write_csv(runs).encode()))
    if sweep.plots:
        result.files += plot_report(result, out)
    result.wall_s = time.perf_counter() - t_start
    result.files.insert(0, _atomic_write(out / "report.md", format_markdown(result).encode()))
    return result


def recommend(runs, tolerance: float, rolling_tolerance: float | None = None):
    """The cheapest run (wall time) other than the reference whose error is within
    ``tolerance`` and, when given, whose incline rolling error is within
    ``rolling_tolerance``; None when there is none."""
    candidates = [u for u in runs if u.ok and not u.reference and u.error <= tolerance
                  and _rolls(u, rolling_tolerance)]
    return min(candidates, key=lambda u: u.wall_s) if candidates else None


def _rolls(u: Run, tolerance) -> bool:
    """Whether run ``u``'s incline error is within ``tolerance`` (None: not asked; an
    incline that could not be measured, NaN, passes: it says nothing against it)."""
    if tolerance is None:
        return True
    e = u.physics.get("incline", math.nan)
    return not e > tolerance


def scene_settings(u: Run, target_overlap: float) -> list:
    """The scene-file lines that bake run ``u``'s setting."""
    lines = [f"resolution = {u.resolution}"]
    if u.mode:
        lines.append(f'spheres = "{u.mode}"')
    if u.law:
        lines.append(f'contact_law = "{u.law}"')
    if u.dt_factor != 1.0:
        per_frame = u.steps // max(u.model_frames, 1)
        lines.append(f"dt = {u.dt:.6g}   # {per_frame} steps per frame")
    if u.stiffness_factor != 1.0:
        lines.append(f"stiffness_target_overlap = {target_overlap / u.stiffness_factor ** 0.5:.4g}"
                     f"   # auto stiffness ×{u.stiffness_factor:g}; a material's own "
                     "stiffness: multiply it")
    return lines


def chaos_floor(r: ReportResult):
    """The run that differs from the reference only by the next larger dt factor, or None."""
    ref = r.reference
    same = [u for u in r.runs if u.ok and not u.reference and u.resolution == ref.resolution
            and u.stiffness_factor == ref.stiffness_factor and u.dt_factor > ref.dt_factor]
    return min(same, key=lambda u: u.dt_factor) if same else None


def _worst_geometry(errs) -> dict:
    return dict(volume=max(abs(e.volume) for e in errs), inertia=max(e.inertia for e in errs),
                hausdorff=max(e.hausdorff for e in errs))


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

    With dt="auto" a ball's own contact is resolved in 16/dt_factor steps whatever
    its size and stiffness, so the cases run once per dt factor (at the reference's
    diameter and stiffness); with a fixed scene dt they run per run. The spin runs at
    each run's own dt. The incline (a ball of the run's resolution and sphere-set
    mode rolling down a slope) runs once per resolution, mode and dt factor, at its
    own automatic contact resolved in 16/dt_factor steps.
    """
    from .spheres import DEFAULT_MODE

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
    """Pareto front over (wall time, error): no other run is both faster and better."""
    ok = [u for u in runs if u.ok and not u.reference and math.isfinite(u.error)]
    for u in ok:
        u.pareto = not any(o is not u and o.wall_s <= u.wall_s and o.error <= u.error
                           and (o.wall_s < u.wall_s or o.error < u.error) for o in ok)


# --------------------------------------------------------------------------- files


def _atomic_write(path: Path, data: bytes) -> Path:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ReportError(f"{path}: cannot write ({exc.strerror or exc})") from None
    return path


CSV_COLUMNS = (
    "label", "resolution", "dt_factor", "stiffness_factor", "reference", "status",
    "diameter_m", "dt_s", "steps", "spheres", "wall_s", "s_per_step", "s_per_sim_s",
    "memory_mib", "sphere_build_cold_s", "sphere_build_cached_s",
    "volume_err", "inertia_err", "hausdorff", "position_h", "orientation_h_deg",
    "position_end", "orientation_end_deg", "pile_height", "pile_com", "pile_spread",
    "settle_s", "at_rest", "bounce", "rolling", "incline", "spin_L", "spin_energy", "error",
    "pareto",
    "sphere_mode", "envelope_hausdorff_d", "envelope_bump_d", "contact_law")


def csv_row(u: Run) -> dict:
    g, mo, ph = u.geometry, u.motion, u.physics
    return dict(
        label=u.label, resolution=u.resolution, dt_factor=u.dt_factor,
        stiffness_factor=u.stiffness_factor, reference=int(u.reference), status=u.status,
        diameter_m=u.diameter, dt_s=u.dt, steps=u.steps, spheres=u.spheres, wall_s=u.wall_s,
        s_per_step=u.s_per_step, s_per_sim_s=u.s_per_sim_s,
        memory_mib=u.memory_bytes / 2 ** 20, sphere_build_cold_s=u.sphere_build_cold_s,
        sphere_build_cached_s=u.sphere_build_cached_s,
        volume_err=g.get("volume", math.nan), inertia_err=g.get("inertia", math.nan),
        hausdorff=g.get("hausdorff", math.nan),
        **{k: mo.get(k, math.nan) for k in ("position_h", "orientation_h_deg", "position_end",
                                            "orientation_end_deg", "pile_height", "pile_com",
                                            "pile_spread", "settle_s", "at_rest")},
        **{k: ph.get(k, math.nan) for k in ("bounce", "rolling", "incline", "spin_L",
                                           "spin_energy")},
        error=u.error, pareto=int(u.pareto), sphere_mode=u.mode or "",
        envelope_hausdorff_d=u.envelope.get("hausdorff_d", math.nan),
        envelope_bump_d=u.envelope.get("bump_d", math.nan), contact_law=u.law or "")


def write_csv(runs) -> str:
    """The runs as CSV text, one row per run (columns: CSV_COLUMNS)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    w.writeheader()
    for u in runs:
        row = csv_row(u)
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    return buf.getvalue()


def _pct(x) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{100 * x:.2g}%" if abs(x) < 0.1 \
        else f"{100 * x:.0f}%"


def _num(x, fmt=".3g") -> str:
    return "—" if x is None or not math.isfinite(x) else format(x, fmt)


def format_markdown(r: ReportResult) -> str:
    """report.md: what was run, the recommendation, and the tables."""
    ref = r.reference
    ok = [u for u in r.runs if u.ok]
    L = [f"# dempipe report: {Path(r.scene).name}", ""]
    L.append(f"{len(r.runs)} runs of {r.bodies} bodies, {r.duration:g} s simulated each, "
             f"{r.wall_s:.0f} s in all. Reference: **{ref.label}** ({ref.spheres:,} spheres, "
             f"dt {ref.dt:.3g} s). Motion errors are against the reference; geometry errors "
             f"against each shape's mesh; physical errors against closed forms "
             f"(material `{r.material}`). Lengths are in body sizes (the mesh's longest "
             f"extent). How to read this: docs/accuracy.md.")
    L.append("")
    L.append(f"**Error** (the headline, plotted against run time): the RMS over bodies of "
             f"|x − x_ref| in body sizes at the horizon t = {r.horizon:.3g} s, "
             f"{HORIZON_AFTER_CONTACT:g} s after the median body's first contact unless "
             f"--horizon says otherwise: late enough for contacts to have acted, early "
             f"enough that chaos has not yet amplified every difference.")
    L.append("")
    L.append("## Recommendation")
    L.append("")
    if r.recommended is not None:
        u = r.recommended
        rolls = ("" if r.rolling_tolerance is None else
                 f" and incline rolling error within {r.rolling_tolerance:g}")
        L.append(f"Cheapest run with error within the tolerance {r.tolerance:g}{rolls}: "
                 f"**{u.label}** (error {_num(u.error)}, {_num(u.wall_s, '.1f')} s, "
                 f"{_num(ref.wall_s / u.wall_s, '.1f')}× faster than the reference). "
                 + ("In the scene file:" if r.stage is None else
                    "dempipe's settings for a stage go in a small TOML beside it that names "
                    "it (docs/usd-input.md), baked with `dempipe bake SETTINGS.toml -o OUT`:"))
        L.append("")
        L.append("```toml")
        if r.stage is not None:
            L += ["[usd]", f'stage = "{r.stage}"', ""]
        L.append("[simulation]")
        L += scene_settings(u, r.target_overlap)
        L.append("```")
    else:
        best = min((u for u in ok if not u.reference), key=lambda u: u.error, default=None)
        L.append(f"No run other than the reference stays within the tolerance {r.tolerance:g}"
                 + ("" if r.rolling_tolerance is None else
                    f" (and the incline rolling tolerance {r.rolling_tolerance:g})")
                 + (f"; the closest is {best.label} (error {_num(best.error)})" if best else "")
                 + ". Keep the reference's setting, loosen --tolerance, or widen the sweep.")
    L.append("")
    L.append("## Runs")
    L.append("")
    L.append("| run | spheres | dt [s] | steps | wall [s] | s/step | s per sim. s | memory "
             "[MiB] | hausdorff | pos. @h | orient. @h [°] | bounce e² | incline roll | "
             "error | Pareto |")
    L.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|:-:|")
    for u in r.runs:
        if not u.ok:
            L.append(f"| {u.label} | {u.spheres:,} | {_num(u.dt)} | | | | | | | | | | | "
                     f"{u.status} | |")
            continue
        name = f"**{u.label}** (ref.)" if u.reference else u.label
        L.append(f"| {name} | {u.spheres:,} | {_num(u.dt)} | {u.steps:,} | "
                 f"{_num(u.wall_s, '.1f')} | {_num(u.s_per_step, '.2e')} | "
                 f"{_num(u.s_per_sim_s, '.1f')} | {_num(u.memory_bytes / 2 ** 20, '.1f')} | "
                 f"{_pct(u.geometry.get('hausdorff', math.nan))} | {_num(u.motion['position_h'])} | "
                 f"{_num(u.motion['orientation_h_deg'], '.1f')} | {_pct(u.physics['bounce'])} | "
                 f"{_pct(u.physics.get('incline', math.nan))} | "
                 f"{_num(u.error)} | {'●' if u.pareto else ''} |")
    L.append("")
    L.append(f"pos. @h, orient. @h: per-body RMS at the horizon t = {r.horizon:g} s. s/step "
             "and s per sim. s are wall time of the simulation alone (kernels already "
             "compiled). Incline roll: a ball of the run's resolution and sphere-set mode "
             f"rolling down a {acc.INCLINE_DEGREES:g}° slope, its acceleration against "
             "5/7 g sin θ (docs/accuracy.md); what the sphere set does to round bodies.")
    L.append("")
    L.append(f"## {'Pile statistics' if r.pile else 'Bodies'} at the last frame "
             f"(t = {r.duration:g} s)")
    L.append("")
    L.append("| run | height [m] | spread [m] | at rest | settled at [s] | Δheight | ΔCOM | "
             "Δspread | Δsettle [s] | pos. @end | orient. @end [°] |")
    L.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for u in ok:
        p, mo = u.pile, u.motion
        L.append(f"| {u.label} | {p.height:.4f} | {p.spread:.4f} | {p.at_rest:.0%} | "
                 f"{_num(p.settle_s, '.2f')} | {_num(mo['pile_height'])} | "
                 f"{_num(mo['pile_com'])} | {_num(mo['pile_spread'])} | "
                 f"{_num(mo['settle_s'], '.2f')} | {_num(mo['position_end'])} | "
                 f"{_num(mo['orientation_end_deg'], '.0f')} |")
    L.append("")
    L.append(f"Height: {acc.HEIGHT_PERCENTILE:g}th percentile of the centres of mass; spread: "
             "RMS horizontal distance from the centre of mass; at rest: moving less than "
             f"{acc.REST_FRACTION_PER_FRAME:.0%} of its size per frame; settled: from when "
             f"{acc.SETTLED_FRACTION:.0%} stay at rest (— : not within the run). Δ: against "
             "the reference, lengths in body sizes.")
    floor = chaos_floor(r)
    if r.pile and floor is not None:
        mo = floor.motion
        L.append(f"**Chaos floor**: {floor.label} differs from the reference only in dt, and "
                 f"its pile differs by Δheight {_num(mo['pile_height'])}, ΔCOM "
                 f"{_num(mo['pile_com'])}, Δspread {_num(mo['pile_spread'])}. Two equally "
                 "valid bakes of a pile differ this much; smaller differences are not a loss "
                 "of accuracy.")
    L.append("")
    L.append("## Geometry: sphere sets against their meshes")
    L.append("")
    L.append("| shape | resolution | spheres | volume | inertia | hausdorff | mesh→spheres | "
             "spheres→mesh | build cold [s] | build cached [s] |")
    L.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    build = {u.resolution: (u.sphere_build_cold_s, u.sphere_build_cached_s) for u in r.runs}
    for (name, res), g in sorted(r.shapes.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        cold, cached = build.get(res, (math.nan, math.nan))
        L.append(f"| {name} | {res} | {g.spheres} | {_pct(g.volume)} | {_pct(g.inertia)} | "
                 f"{_pct(g.hausdorff)} | {_pct(g.mesh_to_spheres)} | {_pct(g.spheres_to_mesh)} "
                 f"| {_num(cold, '.3f')} | {_num(cached, '.3f')} |")
    L.append("")
    L.append("Volume and inertia: the lattice cells (cubes of side d) against the exact mesh "
             "(the bodies' mass properties come from the mesh itself). Hausdorff: the largest "
             f"distance between the mesh surface ({acc.MESH_SAMPLES} area-weighted samples) and "
             "the spheres' contact surface (the part another sphere can touch; "
             f"{acc.SPHERE_DIRECTIONS} directions per sphere), either way, in shape sizes. "
             "Build times are for all shapes of the scene at that resolution (cold: no cache).")
    L.append("")
    if any(u.mode for u in r.runs):
        L.append("## Sphere-set modes")
        L.append("")
        L.append("| run | spheres | Hausdorff [d] | bump [d] | incline roll | error | wall [s] |")
        L.append("|---|---:|---:|---:|---:|---:|---:|")
        for u in ok:
            e = u.envelope
            L.append(f"| {u.label} | {u.spheres:,} | {_num(e.get('hausdorff_d', math.nan))} | "
                     f"{_num(e.get('bump_d', math.nan))} | "
                     f"{_pct(u.physics.get('incline', math.nan))} | {_pct(u.error)} | "
                     f"{_num(u.wall_s, '.1f')} |")
        L.append("")
        L.append("Hausdorff and bump: the worst shape's spheres' envelope against its mesh "
                 "(docs/spheres.md, \"Surface mode\"), in sphere diameters. The geometry "
                 "table above is the first mode's.")
        L.append("")
    if any(u.law for u in r.runs):
        L.append("## Contact laws")
        L.append("")
        L.append("| run | dt [s] | steps | bounce: error of e² | error | wall [s] |")
        L.append("|---|---:|---:|---:|---:|---:|")
        for u in ok:
            L.append(f"| {u.label} | {_num(u.dt, '.3g')} | {u.steps:,} | "
                     f"{_pct(u.physics.get('bounce', math.nan))} | {_pct(u.error)} | "
                     f"{_num(u.wall_s, '.1f')} |")
        L.append("")
        L.append("Each law at its own automatic step (docs/physics.md, \"Contact laws\"): "
                 "for the same error, the cheaper is the one with the smaller wall time. "
                 "The motion error is against the reference, which takes the last law "
                 "given; a law's own stiffness is in its own units (Hertz: N/m^1.5).")
        L.append("")
    L.append("## Physics: closed forms against dt")
    L.append("")
    L.append("| run | dt factor | bounce: mean abs. error of e² | rolling 5/7 v0 | |L| drift | "
             "energy drift (free spin) |")
    L.append("|---|---:|---:|---:|---:|---:|")
    for u in ok:
        ph = u.physics
        L.append(f"| {u.label} | {u.dt_factor:g} | {_pct(ph['bounce'])} | "
                 f"{_num(ph['rolling'], '.2g')} | {_num(ph['spin_L'], '.1e')} | "
                 f"{_num(ph['spin_energy'], '.1e')} |")
    L.append("")
    L.append(f"Bounce: {acc.BOUNCE_PHASES} balls of one sphere diameter dropped "
             f"{acc.BOUNCE_HEIGHT:g} diameters, impacts spread over a step; the ball's "
             "contact is resolved in as many steps as the pile's stiffest contact. Rolling: a "
             "ball launched sliding; the larger of the end-speed and travel errors. Spin: the "
             "smallest shape tumbling torque-free for 0.2 s at the run's dt.")
    L.append("")
    return "\n".join(L)


# --------------------------------------------------------------------------- plots


def _require_matplotlib():
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ReportError("the report's plots need matplotlib: pip install 'dempipe[report]' "
                          "(or pass --no-plots)") from None


def _save(fig, path: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return _atomic_write(path, buf.getvalue())


def _log_axes(ax, xticks=None) -> None:
    """Log-log axes labelled 1, 2, 5, 10, ... in plain numbers."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis, lim in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
        narrow = math.log10(max(lim) / min(lim)) < 3.0
        axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0) if narrow else (1.0,)))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())
    if xticks:
        ax.set_xticks(xticks)
    ax.grid(True, which="both", alpha=0.3)


def plot_report(r: ReportResult, out: Path) -> list:
    """error_vs_time.png and error_vs_setting.png; returns their paths.

    The reference (error 0 by definition) has no place on a log axis: its run time
    is the dotted line.
    """
    from matplotlib.figure import Figure

    ok = [u for u in r.runs if u.ok and not u.reference and math.isfinite(u.error)
          and u.error > 0]
    res_lo, res_hi = min(u.resolution for u in r.runs), max(u.resolution for u in r.runs)
    fig = Figure(figsize=(6.4, 4.4))
    ax = fig.add_subplot()
    for i, k in enumerate(sorted({u.stiffness_factor for u in r.runs})):
        pts = [u for u in ok if u.stiffness_factor == k]
        if pts:
            ax.scatter([u.wall_s for u in pts], [u.error for u in pts], marker="os^Dv<>p"[i % 8],
                       c=[u.resolution for u in pts], cmap="viridis", vmin=res_lo, vmax=res_hi,
                       label=f"stiffness ×{k:g}", edgecolors="k", linewidths=0.5, zorder=3)
    front = sorted((u for u in ok if u.pareto), key=lambda u: u.wall_s)
    if front:
        ax.plot([u.wall_s for u in front], [u.error for u in front], "o-", color="C3", lw=1.0,
                ms=11, mfc="none", label="Pareto front", zorder=2)
    for u in ok:
        ax.annotate(f"r{u.resolution} dt×{u.dt_factor:g}", (u.wall_s, u.error), fontsize=6,
                    xytext=(4, 3), textcoords="offset points")
    if r.recommended is not None:
        u = r.recommended
        ax.scatter([u.wall_s], [u.error], marker="*", s=160, c="C3", zorder=4,
                   label="recommended")
    ax.axhline(r.tolerance, color="0.4", ls="--", lw=0.8, label=f"tolerance {r.tolerance:g}")
    ax.axvline(r.reference.wall_s, color="0.4", ls=":", lw=0.8,
               label=f"reference ({r.reference.label})")
    _log_axes(ax)
    ax.set_xlabel("run time [s] (simulation, wall clock)")
    ax.set_ylabel(f"error [body sizes] at t = {r.horizon:.3g} s")
    ax.set_title(f"{Path(r.scene).name}: error against run time (colour: resolution "
                 f"{res_lo}–{res_hi})", fontsize=9)
    ax.legend(fontsize=6, loc="best")
    fig.tight_layout()
    files = [_save(fig, out / "error_vs_time.png")]

    fig = Figure(figsize=(9.6, 3.9))
    a1, a2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    ress = sorted({res for (_, res) in r.shapes})
    for name in sorted({n for (n, _) in r.shapes}):
        a1.plot(ress, [r.shapes[(name, res)].hausdorff for res in ress], "o-", lw=0.8, ms=3,
                alpha=0.7, label=f"{name}: Hausdorff")
    k1 = [u for u in ok if u.stiffness_factor == 1.0]
    for f in sorted({u.dt_factor for u in k1}, reverse=True):
        row = sorted((u for u in k1 if u.dt_factor == f), key=lambda u: u.resolution)
        a1.plot([u.resolution for u in row], [u.error for u in row], "ks-", lw=1.4, ms=5,
                alpha=1.0 if f == max(u.dt_factor for u in k1) else 0.5,
                label=f"motion, dt×{f:g}")
    _log_axes(a1, ress)
    a1.set_xlabel("resolution (spheres across the smallest shape)")
    a1.set_ylabel("error (shape sizes; motion: body sizes)")
    a1.legend(fontsize=6)
    physics = {}
    for u in r.runs:
        if u.ok and u.stiffness_factor == 1.0:
            physics.setdefault(u.dt_factor, u.physics)
    dts = sorted(physics)
    a2.plot(dts, [physics[f]["bounce"] for f in dts], "o-", color="C1",
            label="bounce: error of e²")
    a2.plot(dts, [physics[f]["rolling"] for f in dts], "v-", color="C2",
            label="rolling: 5/7 v0 and travel")
    for res in sorted({u.resolution for u in k1}):
        row = sorted((u for u in k1 if u.resolution == res), key=lambda u: u.dt_factor)
        a2.plot([u.dt_factor for u in row], [u.error for u in row], "s--", ms=5, lw=1.0,
                color=_viridis((res - res_lo) / max(res_hi - res_lo, 1)),
                label=f"motion, r{res}")
    _log_axes(a2, dts)
    a2.set_xlabel("dt factor (1: the scene's own dt)")
    a2.legend(fontsize=6)
    fig.suptitle(f"{Path(r.scene).name}: error against resolution (stiffness ×1) and dt "
                 f"(the reference r{r.reference.resolution} dt×{r.reference.dt_factor:g} "
                 "has motion error 0)", fontsize=9)
    fig.tight_layout()
    files.append(_save(fig, out / "error_vs_setting.png"))
    return files


def _viridis(x: float):
    from matplotlib import colormaps

    return colormaps["viridis"](x)
