"""Stability check: predict, without simulating, whether a scene will bake well.

    report = analyze(model)                  # a Model from ModelBuilder or build_model
    report = analyze_scene("scene.toml")     # load + build (sphere sets cached) + analyze
    print(report.format()); report.ok        # False when `dempipe bake` would refuse

The report restates the figures ``ModelBuilder.finalize`` derived (stiffness,
damping, time step) per material pair, with the contact time and the critical
step of each pair for its translational effective mass (m against a wall, m/2
between bodies) and its rotational one (m / (1 + m (r×n)ᵀ I⁻¹ (r×n)), the
corner contact of model.rotational_mass_factor), and checks what the time step
alone cannot guarantee: how far the fastest body moves per step, frame-0
overlaps, mass ratios and bodies too small for their spheres. docs/stability.md
explains every limit and fix.

This module imports neither numba nor pxr: the frame-0 overlap is recomputed
in NumPy with the contact stage's exact rules (overlap.py; it agrees with
:func:`dempipe.scene.build.initial_overlap`, which compiles the CPU kernels), and the
memory estimate and the sizes refused before the work are in sizes.py. Only
``analyze_scene`` on a sphere-set cache miss imports numba, to voxelize.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from dempipe.check.sizes import memory_estimate
from dempipe.sim import glue, laws
from dempipe.sim import materials as mat
from dempipe.sim.materials import dt_fix
from dempipe.sim.model import Model, rotational_mass_factor
from dempipe.sim.overlap import REFUSE_OVERLAP, WARN_OVERLAP, frame0_overlap
from dempipe.spheres.fidelity import ROUND_SHARE, mesh_beyond_spheres, off_axis_share

#: Distance the fastest closing pair travels in one step, as a fraction of the
#: diameter: above TUNNEL_WARN contacts start a visible fraction of a diameter
#: deep; above TUNNEL_ERROR a sphere can skip past another's centre in one step.
TUNNEL_WARN = 0.10
TUNNEL_ERROR = 0.50
#: Expected deepest overlap (fraction of a diameter) of the fastest impact: above
#: OVERLAP_WARN contacts look soft, above OVERLAP_ERROR the bake's overlap guard
#: (simulator.MAX_OVERLAP_FRACTION) would stop it.
OVERLAP_WARN = 0.10
OVERLAP_ERROR = 0.50
#: Largest / smallest dynamic body mass beyond which heavy-on-light stacks sink.
MASS_RATIO_WARN = 100.0
#: Bodies farther than this many diameters from the origin get a warning
#: (half the grid keys' range of 2^20 cells per axis).
FAR_CELLS = 2.0 ** 19
#: A shape with fewer spheres than this, or a longest extent below
#: SMALL_EXTENT diameters, collides like a ball.
SMALL_SPHERES = 8
SMALL_EXTENT = 2.0
#: A shape whose mesh reaches more than this many diameters beyond its spheres
#: (spheres.fidelity.mesh_beyond_spheres: a feature thinner than the lattice can hold,
#: a rook's battlements at 6 across) gets a warning: where it touches something the
#: mesh looks sunk into it by up to that much.
COARSE_DIAMETERS = 1.0

ERROR = "error"
WARNING = "warning"


@dataclass(frozen=True)
class Finding:
    """One problem: ``level`` 'error' (bake refuses or the result is garbage) or
    'warning'; ``code`` a stable identifier; ``message`` what and why; ``fix`` what
    to change in the scene."""

    level: str
    code: str
    message: str
    fix: str = ""


@dataclass(frozen=True)
class PairStability:
    """Contact constants of one material pair as finalize() resolved them.

    kind : 'body-body' or 'body-wall' (planes, boxes and static mesh colliders)
    k [N/m], zeta [-], restitution [-] (from zeta), friction [-];
    mass_translational [kg]: lightest body mass, halved for body-body contacts;
    mass_rotational [kg]: lightest corner-contact mass m/(1 + factor), halved likewise;
    contact_time_* [s] = π/ωd; critical_dt_* [s] = 2(√(1+ζ²) - ζ)/ω0 (symplectic Euler);
    dt_ratio: the model's dt over the smaller (rotational) critical step.
    """

    materials: tuple
    kind: str
    k: float
    zeta: float
    restitution: float
    friction: float
    mass_translational: float
    mass_rotational: float
    contact_time_translational: float
    contact_time_rotational: float
    critical_dt_translational: float
    critical_dt_rotational: float
    dt_ratio: float


@dataclass
class StabilityReport:
    """What :func:`analyze` found. ``ok`` is False when bake would refuse (an error)."""

    scene: str | None
    bodies: int
    static_bodies: int
    spheres: int
    static_spheres: int
    diameter: float
    memory: dict
    pairs: list
    dt: float
    dt_setting: str
    steps_per_frame: int | None
    fps: float
    omega_max: float
    zeta_min: float
    critical_dt: float
    dt_ratio: float
    stiffness_auto: dict
    max_speed: float
    closing_speed: float
    impact_speed: float
    step_travel: float
    overlap: float
    overlap_body: str | None
    shapes: list
    findings: list = field(default_factory=list)
    prescribed: dict = field(default_factory=dict)
    """Prescribed inputs: moving colliders, kinematic bodies, emitters and the
    fastest prescribed surface speed [m/s] (counted in closing and impact speeds)."""
    glue: dict = field(default_factory=dict)
    """Glue bonds (sim/glue.py): bonds, sphere pairs, the stiffest bond's frequency
    omega [rad/s] (in omega_max) and the longest step their dashpots allow [s]
    (dashpot_step); empty without glue."""

    @property
    def ok(self) -> bool:
        return not any(f.level == ERROR for f in self.findings)

    @property
    def errors(self) -> list:
        return [f for f in self.findings if f.level == ERROR]

    @property
    def warnings(self) -> list:
        return [f for f in self.findings if f.level == WARNING]

    def to_dict(self) -> dict:
        """Plain JSON-ready dict (infinities and NaN become None)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["pairs"] = [asdict(p) for p in self.pairs]
        d["findings"] = [asdict(f) for f in self.findings]
        d["ok"] = self.ok
        return _json_ready(d)

    def to_json(self, **kw) -> str:
        return json.dumps(self.to_dict(), **kw)

    def format(self) -> str:
        """Human-readable text, as `dempipe check` prints it."""
        name = Path(self.scene).name if self.scene else "model"
        n_err, n_warn = len(self.errors), len(self.warnings)
        verdict = ("OK: safe to bake" if self.ok else "NOT SAFE: bake would refuse or fail")
        tail = f" ({n_err} error{'s' * (n_err != 1)}, {n_warn} warning{'s' * (n_warn != 1)})"
        lines = [f"{name}: {verdict}{tail}"]
        mem = self.memory
        lines.append(
            f"  bodies       {self.bodies:,} dynamic ({self.spheres - self.static_spheres:,} "
            f"spheres), {self.static_bodies} static mesh colliders ({self.static_spheres:,} "
            f"spheres); diameter {self.diameter * 1e3:.3g} mm")
        lines.append(
            f"  memory       ≈ {_size(mem['total'])} (model {_size(mem['model'])}, CPU scratch "
            f"{_size(mem['cpu_scratch'])}, state {_size(mem['state'])}, frames "
            f"{_size(mem['frames'])})")
        spf = f"{self.steps_per_frame:,} steps per frame" if self.steps_per_frame else \
            "refused"
        lines.append(
            f"  time step    dt = {self.dt:.3g} s ({self.dt_setting}), {spf} at "
            f"{self.fps:g} fps; critical step {_s(self.critical_dt)}, dt / critical = "
            f"{_ratio(self.dt_ratio)}")
        if self.stiffness_auto:
            ks = ", ".join(f"{n} {k:.3g} N/m" for n, k in self.stiffness_auto.items())
            lines.append(f"  auto k       {ks}")
        lines.append(
            f"  speed        fastest body {self.max_speed:.3g} m/s, closing {self.closing_speed:.3g} "
            f"m/s: {self.step_travel:.2%} of a diameter per step (auto stiffness assumed an "
            f"impact at {self.impact_speed:.3g} m/s)")
        if self.glue:
            g = self.glue
            lines.append(
                f"  glue         {g['bonds']:,} bonds of {g['pairs']:,} sphere pairs; stiffest "
                f"ω = {g['omega']:.4g} rad/s, dashpots stable below dt = "
                f"{_s(g['dashpot_step'])} ({g['damped_less']} damped less than asked)")
        pr = self.prescribed
        if pr:
            parts = []
            if pr.get("moving_colliders"):
                parts.append(f"{pr['moving_colliders']} moving collider"
                             f"{'s' * (pr['moving_colliders'] != 1)}")
            if pr.get("kinematic_bodies"):
                parts.append(f"{pr['kinematic_bodies']} kinematic bod"
                             f"{'ies' if pr['kinematic_bodies'] != 1 else 'y'}")
            if pr.get("emitted_bodies"):
                parts.append(f"{pr['emitted_bodies']} bodies emitted from "
                             f"t = {pr['first_emission']:.3g} s")
            lines.append(f"  prescribed   {', '.join(parts)}; fastest surface "
                         f"{pr['surface_speed']:.3g} m/s (in the closing and impact speeds)")
        where = f" ({self.overlap_body})" if self.overlap_body else ""
        lines.append(f"  frame 0      largest overlap {self.overlap:.1%} of a diameter{where}")
        if self.pairs:
            names = [" / ".join(p.materials) + ("" if p.kind == "body-body" else " (wall)")
                     for p in self.pairs]
            w = max(18, *(len(n) for n in names))      # the columns line up for any names
            lines.append(f"  contacts     {'pair':<{w}} k [N/m]    ζ     e    tc [s]     "
                         "critical dt [s] transl. / rot.   dt/crit")
            for pair, p in zip(names, self.pairs):
                lines.append(
                    f"               {pair:<{w}} {p.k:<10.3g} {p.zeta:<5.3f} "
                    f"{p.restitution:<4.2f} {p.contact_time_rotational:<10.3g} "
                    f"{p.critical_dt_translational:<9.3g} / "
                    f"{p.critical_dt_rotational:<18.3g} {_ratio(p.dt_ratio)}")
        else:
            lines.append("  contacts     none possible (one body, no colliders)")
        for f in self.findings:
            lines.append(f"{f.level}: {f.message}")
            if f.fix:
                lines.append(f"  fix: {f.fix}")
        return "\n".join(lines)


def _size(n: int) -> str:
    """``n`` bytes in the largest binary unit that keeps a number at least 1 (KiB to PiB)."""
    for unit, shift in (("PiB", 50), ("TiB", 40), ("GiB", 30), ("MiB", 20)):
        if n >= 2**shift:
            return f"{n / 2**shift:.1f} {unit}"
    return f"{n / 1024:.1f} KiB"


def _s(x: float) -> str:
    return f"{x:.3g} s" if math.isfinite(x) else "none (no contact possible)"


def _ratio(x: float) -> str:
    return f"{x:.3g}" if math.isfinite(x) else "-"


def _json_ready(x):
    if isinstance(x, dict):
        return {str(k): _json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_ready(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    return x


# --------------------------------------------------------------------------- figures


def expected_speeds(model: Model) -> tuple[float, float, float]:
    """(fastest body, fastest closing pair, finalize's impact speed) [m/s].

    The closing and impact speeds replicate ModelBuilder.finalize: each body falls
    freely from its height to the lowest floor (the lowest body's bottom, ground-like
    planes, box floors, static meshes) on top of its launch speed |v| + |w| r. The
    impact speed of auto stiffness adds the fastest launch of a partner and is at least
    √(2 g d). The closing speed is the fastest body against a wall, or against the
    fastest launched partner when there are two or more bodies.

    The fastest body is the fastest any body gets (``falling_speeds``): at the floor
    under it, or, with nothing under it, by the end of the shot.
    """
    n = model.n_bodies
    d = model.diameter
    g = float(np.linalg.norm(model.gravity))
    if n == 0:
        return 0.0, 0.0, (math.sqrt(2.0 * g * d) if g > 0 else 0.01)
    up = -np.asarray(model.gravity) / g if g > 0 else np.array([0.0, 0.0, 1.0])
    falls = (np.ones(n, bool) if model.body_kinematic is None
             else ~np.asarray(model.body_kinematic))    # kinematic: their motion is given
    if not falls.any():
        falls[:] = True
    x0 = np.asarray(model.initial_x[:n])[falls]
    v0 = np.asarray(model.initial_v[:n])[falls]
    w0 = np.asarray(model.initial_w[:n])[falls]
    radius = np.asarray(model.body_radius)[falls]
    heights = x0 @ up
    floors = [heights.min() - radius.max()]
    floors += [float(p @ up) for p, nrm in zip(model.plane_point, model.plane_normal)
               if nrm @ up > 0.5]
    floors += [float(b.lo @ up) for b in model.boxes]
    floors += [float((np.asarray(m.vertices) @ up).min()) for m in model.static_meshes]
    floor = min(floors)
    fall = np.sqrt(2.0 * g * np.maximum(heights - floor, 0.0))
    launch = np.linalg.norm(v0, axis=1) + np.linalg.norm(w0, axis=1) * radius
    landing = float((fall + launch).max())
    impact = landing + float(launch.max())
    closing = impact if n > 1 else landing
    impact = max(impact, math.sqrt(2.0 * g * d) if g > 0 else 0.01)
    fastest = float(falling_speeds(model).max())
    # a moving surface meets a body head on: the speeds add (ModelBuilder.finalize)
    return fastest, closing + model.surface_speed, impact + model.surface_speed


def falling_speeds(model: Model) -> np.ndarray:
    """(n,) the fastest each dynamic body gets [m/s] if nothing but gravity acts on it,
    its spin's surface speed |w| r included (r the body's radius): sqrt(|v|² + 2 g h)
    at the floor under its centre, its bottom h above it (energy: the same for any
    launch direction), and at most |v| + g t, t its time in the shot (from its
    start_time to the last frame). With nothing under it (no ground-like plane below;
    no box floor, static mesh or kinematic body under its centre) it falls for the
    whole shot, at |v| + g t by the end. A body carried by another is where that one
    is: an upper bound for a pile, not a guess at its bounces. Kinematic bodies: 0
    (their motion is given)."""
    n = model.n_bodies
    out = np.zeros(n)
    if n == 0:
        return out
    g = float(np.linalg.norm(model.gravity))
    moves = ~model.body_static[:n]          # 1/m = 0: kinematic
    spin = np.linalg.norm(np.asarray(model.initial_w[:n]), axis=1) * np.asarray(
        model.body_radius)
    v = np.linalg.norm(np.asarray(model.initial_v[:n]), axis=1)
    start = (np.zeros(n) if model.body_start_time is None
             else np.asarray(model.body_start_time, dtype=np.float64))
    t = np.maximum((model.n_frames - 1) / model.fps - start, 0.0)
    floor, height = floor_below(model)
    by_end = v + g * t
    drop = np.where(np.isfinite(floor),
                    np.maximum(height - np.asarray(model.body_radius) - floor, 0.0), 0.0)
    at_floor = np.sqrt(v * v + 2.0 * g * drop)
    out = np.where(np.isfinite(floor), np.minimum(at_floor, by_end), by_end) + spin
    return np.where(moves, out, 0.0)


def floor_below(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """(floor, height), each (n,) [m] along up (against gravity; +z without it): the
    highest floor under each body's centre at the start, and the centre's height.
    A floor is a ground-like plane collider (its normal within 60° of up) below the
    centre, or the base of a box collider, a static mesh's bounds or a kinematic
    body's bounding box whose horizontal extent holds the centre; -inf where there is
    none."""
    n = model.n_bodies
    g = float(np.linalg.norm(model.gravity))
    up = -np.asarray(model.gravity) / g if g > 0 else np.array([0.0, 0.0, 1.0])
    x0 = np.asarray(model.initial_x[:n]).reshape(n, 3)
    height = x0 @ up
    floor = np.full(n, -np.inf)             # the highest floor under each body
    for p, nrm in zip(model.plane_point, model.plane_normal):
        lean = float(np.asarray(nrm) @ up)
        if lean > 0.5:                      # ground-like: under every body above it
            gap = (x0 - np.asarray(p)) @ np.asarray(nrm)
            floor = np.where(gap > 0.0, np.maximum(floor, height - gap / lean), floor)
    flat = x0 - height[:, None] * up        # the centres' horizontal parts
    spans = [(np.asarray(b.lo), np.asarray(b.hi)) for b in model.boxes]
    spans += [(np.asarray(m.vertices).min(axis=0), np.asarray(m.vertices).max(axis=0))
              for m in model.static_meshes]
    if model.body_kinematic is not None:
        for b in np.flatnonzero(np.asarray(model.body_kinematic)):
            r = float(model.body_radius[b])
            spans.append((x0[b] - r, x0[b] + r))
    for lo, hi in spans:
        lo_flat = lo - (lo @ up) * up
        hi_flat = hi - (hi @ up) * up
        under = np.all((flat >= np.minimum(lo_flat, hi_flat) - 1e-12)
                       & (flat <= np.maximum(lo_flat, hi_flat) + 1e-12), axis=1)
        base = min(float(lo @ up), float(hi @ up))
        floor = np.where(under & (base < height), np.maximum(floor, base), floor)
    return floor, height


def pair_stability(model: Model, dt: float | None = None) -> tuple[list, float, float]:
    """Per material pair figures, and (ω_max, ζ_min) as finalize derives them: the
    same effective masses (materials.contact_masses, from the Model's corner masses)
    and laws.stiffest."""
    dt = model.dt if dt is None else dt
    n = model.n_bodies
    moves = ~model.body_static[:n]          # 1/m = 0: kinematic, a partner only
    wall_mats = set(np.asarray(model.wall_material).tolist()) | set(
        np.asarray(model.body_material[n:]).tolist())
    names = [m.name for m in model.materials]
    pairs = mat.contact_masses(np.asarray(model.body_material[:n]),
                               np.asarray(model.body_mass[:n]), model.body_corner_mass,
                               moves, wall_mats)
    law = laws.law(model.contact_law)
    out = []
    contacts = []
    for (kind, a, b), (mt, mr) in sorted(pairs.items(), key=lambda kv: (kv[0][1], kv[0][2],
                                                                      kv[0][0])):
        k = float(model.pair_k[a, b])
        z = float(model.pair_zeta[a, b])
        contacts.append((k, mr, z))
        v = model.impact_speed
        crit_r = law.critical_dt(k, mr, z, v)
        out.append(PairStability(
            materials=(names[a], names[b]), kind=kind, k=k, zeta=z,
            restitution=law.restitution(z), friction=float(model.pair_mu[a, b]),
            mass_translational=mt, mass_rotational=mr,
            contact_time_translational=law.contact_time(k, mt, z, v),
            contact_time_rotational=law.contact_time(k, mr, z, v),
            critical_dt_translational=law.critical_dt(k, mt, z, v),
            critical_dt_rotational=crit_r, dt_ratio=dt / crit_r))
    omega_max, zeta_min, _ = laws.stiffest(contacts, model.contact_law, model.impact_speed)
    return out, omega_max, zeta_min


def critical_step(omega_max: float, zeta_min: float, law_name: str = laws.DEFAULT) -> float:
    """The step materials.check_dt refuses at (the law's critical step of the
    stiffest contact with the least damping) [s]; inf when nothing touches."""
    return laws.law(law_name).critical_step(omega_max, zeta_min)


# --------------------------------------------------------------------------- analysis


def tunnelling(model: Model, step: float, closing: float, setting: str,
               src: str) -> Finding | None:
    """The tunnelling finding (or None): the fastest closing pair's travel per step.

    Beyond TUNNEL_ERROR of a diameter per step contacts can be skipped entirely
    (bake refuses without --force); beyond TUNNEL_WARN they start deep. None where no
    contact is possible (Model.contact_possible: the bake's travel guard skips it too).
    """
    if not model.contact_possible:
        return None
    d = model.diameter
    travel = closing * step / d
    if travel <= TUNNEL_WARN:
        return None
    level = ERROR if travel > TUNNEL_ERROR else WARNING
    limit = TUNNEL_WARN * d / closing
    user_k = [m.name for m in model.materials if m.stiffness is not None]
    why = (f"the user stiffness of {', '.join(user_k)} makes the automatic step long"
           if setting == "auto" and user_k else "the step is long for these speeds")
    return Finding(
        level, "tunnelling",
        f"{src}: the fastest closing pair ({closing:.3g} m/s) moves {travel:.0%} of a "
        f"sphere diameter per step (dt = {step:.3g} s): {why}; contacts "
        + ("can be skipped entirely (bodies pass through each other or through walls)"
           if level == ERROR else "start deep and bounce wrongly"),
        (f"set stiffness = \"auto\" (or a higher stiffness) for {', '.join(user_k)}, so that "
         f"dt = \"auto\" follows the speeds" if setting == "auto" and user_k else
         f"use dt = \"auto\" or a dt below {limit:.3g} s (≤ {TUNNEL_WARN:.0%} of a diameter "
         f"per step)"))


def soft_contact(model: Model, closing: float, src: str) -> Finding | None:
    """The soft-contact finding (or None): the deepest overlap the fastest closing
    pair can reach, δ = v √(m_c / k) (an undamped spring stopping, at v, the heaviest
    corner-contact mass m_c = m / (1 + f) of a material: what auto stiffness is chosen
    for), against the bake's overlap guard (simulator.MAX_OVERLAP_FRACTION).

    dt "auto" follows the speeds, but no step saves a spring too soft to stop them:
    beyond OVERLAP_ERROR of a diameter bodies sink through each other or the walls.
    """
    n = model.n_bodies
    if n == 0 or closing <= 0.0:
        return None
    d = model.diameter
    # the corner-contact effective mass m / (1 + f), as auto stiffness assumes
    mass = np.asarray(model.body_corner_mass)
    dyn_mat = np.asarray(model.body_material[:n])
    partners = set(np.asarray(model.wall_material).tolist()) | set(
        np.asarray(model.body_material[n:]).tolist())
    if n > 1:
        partners |= set(dyn_mat.tolist())
    worst, pair = 0.0, None
    for mi in sorted(set(dyn_mat.tolist())):
        m_heavy = float(mass[dyn_mat == mi].max())
        for mj in sorted(partners):
            k = float(model.pair_k[mi, mj])
            depth = closing * math.sqrt(m_heavy / k) / d if k > 0 else math.inf
            if depth > worst:
                worst, pair = depth, (mi, mj)
    # A warning beyond OVERLAP_WARN of the patch scale ℓ (≥ d): auto stiffness aims at
    # a fraction of ℓ (materials.patch_scale), so a scene at its own target is quiet
    # (the quickstart, 0.09 ℓ = 0.135 d) and a heavy body on a light material's spring
    # is not; the error stays a fraction of d, the overlap guard's unit.
    ell = max(float(getattr(model, "patch_scale", 0.0) or 0.0), d) / d
    if pair is None or worst <= OVERLAP_WARN * ell:
        return None
    names = [m.name for m in model.materials]
    user_k = sorted({names[i] for i in pair if model.materials[i].stiffness is not None})
    # An error only where a user stiffness sets the spring; under auto stiffness the
    # depth past the guard is check.sinking's error (pipeline/check.py).
    level = ERROR if worst > OVERLAP_ERROR and user_k else WARNING
    return Finding(
        level, "soft-contact",
        f"{src}: a contact of {names[pair[0]]} on {names[pair[1]]} "
        f"(k = {float(model.pair_k[pair]):.3g} N/m) closing at {closing:.3g} m/s sinks "
        f"{worst:.0%} of a sphere diameter deep"
        + (": bodies pass through each other or the walls" if level == ERROR else ""),
        (f"set stiffness = \"auto\" (or a higher stiffness) for {', '.join(user_k)}"
         if user_k else "raise the materials' stiffness, or lower the drop heights and "
         "speeds"))


def analyze(model: Model, *, dt: float | None = None, dt_setting: str | float | None = None,
            refused: str | None = None, scene: str | None = None,
            full_model: Model | None = None) -> StabilityReport:
    """Check ``model`` for everything that makes a bake unstable or refused.

    dt : evaluate this step instead of model.dt (a user dt that finalize refused;
         ``refused`` then holds finalize's message)
    dt_setting : what the scene asked for ("auto" or seconds), for the report
    full_model : the same scene with every sphere in contact (build.full_sphere_model):
         frame-0 overlaps are taken from both, since surface spheres alone do not see
         a body placed wholly inside another
    """
    d = model.diameter
    n = model.n_bodies
    step = float(model.dt if dt is None else dt)
    pairs, omega_max, zeta_min = pair_stability(model, step)
    glue_info = {}
    if model.n_bonds:
        corner = np.full(model.body_mass.shape[0], np.inf)
        moves = ~np.asarray(model.body_static)[:n]
        corner[:n][moves] = np.asarray(model.body_corner_mass)[moves]
        zeta = np.array([model.materials[model.body_material[a]].glue_damping
                         for a in model.bonds.bond_body[:, 0]])
        K = model.bonds.bond_k * np.diff(model.bonds.bond_start)
        inv = np.zeros(model.body_mass.shape[0])        # 1/m [1/kg], 0: never moved
        inv[:n][moves] = 1.0 / np.asarray(model.body_mass[:n])[moves]
        m_red = 1.0 / (inv[model.bonds.bond_body[:, 0]] + inv[model.bonds.bond_body[:, 1]])
        asked = 2.0 * zeta * np.sqrt(K * m_red) / np.diff(model.bonds.bond_start)
        glue_info = dict(bonds=model.n_bonds, pairs=model.bonds.n_pairs,
                         omega=glue.bond_omega(model.bonds, corner),
                         dashpot_step=glue.dashpot_step(model.bonds, corner),
                         damped_less=int(np.count_nonzero(
                             model.bonds.bond_eta < asked * (1.0 - 1e-9))))
        omega_max = max(omega_max, glue_info["omega"])
    crit = critical_step(omega_max, zeta_min, model.contact_law)
    ratio = step / crit if math.isfinite(crit) else 0.0
    fastest, closing, impact = expected_speeds(model)
    travel = closing * step / d
    overlap, ob = frame0_overlap(model)
    if full_model is not None:          # every sphere, not only the contact spheres
        o2, b2 = frame0_overlap(full_model)
        if o2 > overlap:
            overlap, ob = o2, b2
    if dt_setting is None:
        setting = "given" if dt is not None else "model"
    else:
        setting = dt_setting if isinstance(dt_setting, str) else f"{float(dt_setting):g} s asked"
    src = Path(scene).name if scene else "model"
    findings: list[Finding] = []

    # 1. the critical step (finalize refuses a user dt at or above it)
    if refused is not None:
        if step >= crit:
            findings.append(Finding(
                ERROR, "dt-above-critical",
                f"{src}: simulation.dt = {step:.3g} s is {ratio:.3g}× the critical step "
                f"{crit:.3g} s of "
                + f"the stiffest contact (ω = {omega_max:.4g} rad/s)"
                + "; bake refuses it",
                dt_fix(crit, model.dt, model.steps_per_frame)))
        else:
            findings.append(Finding(ERROR, "dt-refused", refused,
                                    f"use dt = \"auto\" ({model.dt:.3g} s here)"))
    elif step >= crit:
        findings.append(Finding(
            ERROR, "dt-above-critical",
            f"{src}: dt = {step:.3g} s is {ratio:.3g}× the critical step {crit:.3g} s of "
            "the stiffest contact; the integration diverges",
            "use dt = \"auto\", a smaller dt, or softer materials"))

    if glue_info and step > glue_info["dashpot_step"] * (1.0 + 1e-9):
        findings.append(Finding(
            ERROR, "glue-dashpot",
            f"{src}: dt = {step:.3g} s is above {glue_info['dashpot_step']:.3g} s, the longest "
            f"step the glue bonds' dashpots are stable at; the integration diverges",
            "use dt = \"auto\" or the scene's dt (the bake lowers the dashpots for it)"))
    elif glue_info and glue_info["damped_less"]:
        findings.append(Finding(
            WARNING, "glue-damped-less",
            f"{src}: {glue_info['damped_less']} of {glue_info['bonds']} glue bonds are damped "
            f"less than glue_damping asks: at dt = {step:.3g} s their pieces' dashpots "
            f"would be unstable (glue.cap_dashpots)",
            "glued pieces may ring a little longer; a smaller dt restores the damping"))

    # 2. tunnelling: distance per step against the diameter
    found = tunnelling(model, step, closing, setting, src)
    if found is not None:
        findings.append(found)
    found = soft_contact(model, closing, src)
    if found is not None:
        findings.append(found)

    # 3. frame-0 overlap (bake.py refuses above 50% without --force)
    name = model.body_name(ob) if ob >= 0 else None
    if overlap > REFUSE_OVERLAP:
        findings.append(Finding(
            ERROR, "frame0-overlap",
            f"{src}: body {name} overlaps another body or a collider by {overlap:.0%} of the "
            f"sphere diameter at frame 0; the first step would fling it away (bake refuses "
            f"without --force)",
            "space the bodies further apart (a randomly turned body swings about its mesh "
            "origin) or move it clear of the colliders"))
    elif overlap > WARN_OVERLAP:
        findings.append(Finding(
            WARNING, "frame0-overlap",
            f"{src}: body {name} starts {overlap:.0%} of a diameter deep in contact; it will "
            f"be pushed out in the first steps",
            "space the bodies a little further apart or lift them off the colliders"))

    # 4. mass ratio
    if n > 1:
        mass = np.asarray(model.body_mass[:n])
        heavy, light = int(np.argmax(mass)), int(np.argmin(mass))
        mr = float(mass[heavy] / mass[light])
        if mr > MASS_RATIO_WARN:
            findings.append(Finding(
                WARNING, "mass-ratio",
                f"{src}: body masses span {mr:.3g}× (heaviest {model.body_name(heavy)} "
                f"{mass[heavy]:.3g} kg, lightest {model.body_name(light)} {mass[light]:.3g} kg): "
                f"a heavy body stacked on light ones sinks into them and stacks jitter",
                f"keep densities and sizes within {MASS_RATIO_WARN:g}× of each other, or give "
                f"the light bodies' material an explicit, higher stiffness"))

    # 5. shapes too small for their spheres, or too coarse, or round on a lattice
    shapes = []
    round_shapes = []
    for s in model.shapes:
        c = np.asarray(s.sphere_set.centers)
        extent = float((c.max(axis=0) - c.min(axis=0)).max() + d) / d
        count = int(c.shape[0])
        small = count < SMALL_SPHERES or extent < SMALL_EXTENT
        beyond = mesh_beyond_spheres(c, d, s.vertices, s.faces) / d
        lattice = "surface" not in s.sphere_set.notes
        off_axis = off_axis_share(s.vertices, s.faces)
        shapes.append(dict(name=s.name, spheres=count, extent_diameters=extent,
                           rotational_mass_factor=rotational_mass_factor(
                               c, np.asarray(s.sphere_set.inertia) / s.sphere_set.volume),
                           small=small,
                           mesh_beyond_spheres_diameters=beyond,
                           mode="lattice" if lattice else "surface",
                           off_axis_share=off_axis))
        # (a fracture piece keeps its lattice; a lattice with its mesh's inscribed tori
        # rolls on walls: spheres/inscribed.py lattice_tori)
        if (lattice and off_axis > ROUND_SHARE and not small and s.inside_faces is None
                and s.inscribed is None):
            round_shapes.append((s.name, off_axis))
        if beyond > COARSE_DIAMETERS and not small:
            findings.append(Finding(
                WARNING, "coarse-shape",
                f"{src}: shape {s.name!r}: its mesh reaches {beyond * d * 1e3:.3g} mm "
                f"({beyond:.2f} diameters) beyond its spheres: where it touches something "
                f"it will look sunk in by up to that",
                "raise simulation.resolution or lower simulation.sphere_diameter, or give "
                'the shape spheres = "surface" (docs/spheres.md)'))
        if small:
            findings.append(Finding(
                WARNING, "small-body",
                f"{src}: shape {s.name!r} is {count} sphere{'s' * (count != 1)}, "
                f"{extent:.3g} diameter{'s' * (extent != 1)} across: it will collide and roll like a ball",
                "raise simulation.resolution or lower simulation.sphere_diameter (the "
                "smallest shape sets the diameter)"))

    if round_shapes:
        names = ", ".join(f"{n!r} ({share:.0%})" for n, share in round_shapes)
        findings.append(Finding(
            WARNING, "round-lattice",
            f"{src}: shape{'s' * (len(round_shapes) > 1)} {names}: that share of "
            f"{'their' if len(round_shapes) > 1 else 'its'} surface is curved or slanted "
            f"to the lattice, whose spheres follow it in terraces, too coarse for a fit of "
            f"its curvature to give it its mesh's own contacts with the ground: such a "
            f"body rolls badly or not at all (a ball, a wheel, a piece on its side)",
            'where rolling shows, raise simulation.resolution (a lattice of about 8 '
            'spheres across a round part rolls on walls), or give the shape spheres = '
            '"surface", or the scene simulation.spheres = "auto" (surface sets for its '
            'round shapes only): more spheres, a slower bake (docs/spheres.md, "Rolling")'))

    # 6. far from the origin: grid keys hold ±2^20 cells per axis (kernels/cpu/stages.py);
    # beyond half of that the bake still collides correctly but slowly
    if n:
        far = float(np.abs(np.asarray(model.initial_x[:n])).max()) / d
        if far > FAR_CELLS:
            findings.append(Finding(
                WARNING, "far-from-origin",
                f"{src}: bodies start {far * d:.4g} m from the origin, {far:.3g} sphere "
                f"diameters; beyond about {2 ** 20:.3g} cells of 1.2 diameters the grid "
                f"clamps them into its outermost cells (correct, but at a neighbour-list "
                f"rebuild every sphere there is a candidate of every other: slow)",
                "recentre the scene near the origin (move the bodies and colliders together)"))

    nb_all = int(model.body_mass.shape[0])
    static_spheres = int(model.n_spheres - model.body_sphere_start[n]) if nb_all else 0
    return StabilityReport(
        scene=scene, bodies=n, static_bodies=model.n_static, spheres=model.n_spheres,
        static_spheres=static_spheres, diameter=d, memory=memory_estimate(model), pairs=pairs,
        dt=step, dt_setting=setting,
        steps_per_frame=None if refused is not None else int(model.steps_per_frame),
        fps=model.fps, omega_max=omega_max, zeta_min=zeta_min, critical_dt=crit,
        dt_ratio=ratio, stiffness_auto={k: float(v) for k, v in model.stiffness_auto},
        max_speed=fastest, closing_speed=closing, impact_speed=impact, step_travel=travel,
        overlap=overlap, overlap_body=name, shapes=shapes, findings=findings,
        prescribed=_prescribed(model), glue=glue_info)


def _prescribed(model: Model) -> dict:
    """What ``check`` says of a scene's prescribed inputs ({} for none)."""
    n = model.n_bodies
    kin = int(np.count_nonzero(model.body_kinematic)) if model.body_kinematic is not None else 0
    start = (np.asarray(model.body_start_time) if model.body_start_time is not None
             else np.zeros(n))
    emitted = int(np.count_nonzero(start > 0))
    moving = len(model.collider_motions or ())
    if not (kin or emitted or moving):
        return {}
    return dict(moving_colliders=moving, kinematic_bodies=kin, emitted_bodies=emitted,
                first_emission=float(start[start > 0].min()) if emitted else None,
                surface_speed=float(model.surface_speed))




