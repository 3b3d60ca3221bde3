"""Materials and contact parameters: where stability lives.

A user thinks in restitution, not in dashpot constants. The contact law
(``laws.law(name)``, laws/linear.py for the linear spring-dashpot) turns the
asked restitution into a damping ratio, the asked overlap into a stiffness,
and gives each contact's frequency and critical step; this module holds what
does not depend on the law: the materials, how two of them mix, the table of
pair constants and the choice of dt (explicit symplectic Euler integration
stays far below the critical step, because accuracy of the bounce, and of
piles with many simultaneous contacts whose stiffness adds up, needs ~16 steps
per contact, not ~1). The functions below named for a derived quantity
(damping_ratio, contact_time, critical_dt, auto_stiffness, ...) are the linear
law's, kept here under the names callers know.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dempipe.errors import SceneError, StabilityError
from dempipe.sim.laws import linear as _law

#: Steps per contact duration that dt="auto" aims for, the default law's (each law
#: says its own: laws.linear.STEPS_PER_CONTACT, laws.hertz.STEPS_PER_CONTACT).
STEPS_PER_CONTACT = _law.STEPS_PER_CONTACT

#: Tangential dashpot as a multiple of √(k m_eff). With the tangential spring
#: (ks = 2/7 k, below) doing the holding, the dashpot only damps the tangential
#: oscillation: for a ball (m_t = 2/7 m) 0.3 is a damping ratio of
#: 0.3 / (2 · 2/7) ≈ 0.52. It must stay small because a body touching on n
#: contacts feels n dashpots: at 1.0 a box resting on 16 contacts rocked
#: unstably at dt auto and crept down a 20° slope at 7 mm/s with μ = 0.6
#: (tests/sim/test_friction.py); at 0.1-0.5 it holds to 1e-18 m/s.
TANGENTIAL_RATIO = 0.3

#: Tangential spring as a fraction of the normal one, ks = 2/7 k: a solid ball's
#: tangential oscillation (effective mass 2/7 m) then has the normal frequency,
#: so the static-friction spring adds no faster mode than dt already resolves
#: (Schäfer, Dippel and Wolf 1996).
TANGENTIAL_SPRING_RATIO = 2.0 / 7.0


#: Default rolling-friction coefficient μ_r [1]: the rolling-resistance torque's
#: lever arm as a fraction of the rolling radius (physics.rolling_torque). Small
#: but not zero, so a ball on a plane comes to rest (after 7 v0² / (10 μ_r g): 7 m
#: from 1 m/s) instead of rolling forever; a billiard ball on cloth is near 0.01,
#: a steel ball on steel near 0.001 (the coefficient of rolling resistance).
ROLLING_FRICTION = 0.01


@dataclass(frozen=True)
class Material:
    """A material as the user gives it.

    density : [kg/m³] > 0
    restitution : e ∈ [0, 1], normal rebound speed / approach speed
    friction : Coulomb μ ≥ 0 (0 turns friction off)
    stiffness : normal spring k [N/m] (the Hertz law: its constant K [N/m^1.5]), or
        None for "auto"
    young_modulus : Young's modulus E [Pa] for the Hertz law, or None: K from E and
        poisson_ratio ν (laws.hertz.stiffness_from_modulus) instead of "auto"
    rolling_friction : rolling-resistance coefficient μ_r ≥ 0 [1] (0 turns it off;
        physics.rolling_torque)
    glue_strength : tensile strength σ [Pa] of the glue between fractured pieces of
        this material: a bonded sphere pair carries at most σ d² (sim/glue.py); None:
        bodies of this material cannot be glued
    glue_stiffness : a bond's whole spring K [N/m], or None: the law's contact
        stiffness between the two pieces (sim/glue.py)
    glue_damping : damping ratio ζ [1] of a bond's translation (sim.glue.GLUE_DAMPING)
    """

    name: str
    density: float = 1000.0
    restitution: float = 0.5
    friction: float = 0.5
    stiffness: float | None = None
    young_modulus: float | None = None
    poisson_ratio: float = 0.3
    rolling_friction: float = ROLLING_FRICTION
    glue_strength: float | None = None
    glue_stiffness: float | None = None
    glue_damping: float = 0.7

    def __post_init__(self):
        # the ranges the scene readers check (scene/toml_reader.py), for a Material built
        # in Python: a negative density would make a body that hangs in the air
        def bad(key, v, need):
            return SceneError(f"material {self.name!r}: {key} = {v!r} {need}")

        def number(key, lo, hi=math.inf, lo_open=False, optional=False):
            v = getattr(self, key)
            if v is None and optional:
                return
            ok = (isinstance(v, (int, float, np.floating, np.integer))
                  and not isinstance(v, bool) and math.isfinite(v) and v <= hi
                  and (v > lo if lo_open else v >= lo))
            if not ok:
                side = f"> {lo:g}" if lo_open else f">= {lo:g}"
                upper = f" and <= {hi:g}" if math.isfinite(hi) else ""
                raise bad(key, v, f"must be a finite number {side}{upper}"
                          + (" (or None)" if optional else ""))

        number("density", 0.0, lo_open=True)
        number("restitution", 0.0, 1.0)
        number("friction", 0.0)
        number("rolling_friction", 0.0)
        number("stiffness", 0.0, lo_open=True, optional=True)
        number("young_modulus", 0.0, lo_open=True, optional=True)
        number("poisson_ratio", 0.0, 0.4999)
        number("glue_strength", 0.0, lo_open=True, optional=True)
        number("glue_stiffness", 0.0, lo_open=True, optional=True)
        number("glue_damping", 0.0)


DEFAULT_MATERIAL = Material("default")


damping_ratio = _law.damping_ratio
restitution_from_damping = _law.restitution
contact_time = _law.contact_time
critical_dt = _law.critical_dt
damped_critical_step = _law.critical_step
auto_stiffness = _law.stiffness_for_overlap


def mix(a: Material, b: Material) -> tuple[float | None, float, float]:
    """Contact parameters of a pair of materials: (k, e, μ).

    Stiffness: springs in series, k = 2 k_a k_b / (k_a + k_b) (equal materials keep
    their k). Restitution and friction: geometric means (equal materials keep theirs,
    and a frictionless partner makes the pair frictionless, as in Bullet's product rule).
    """
    if a.stiffness is None or b.stiffness is None:
        k = None
    else:
        k = 2.0 * a.stiffness * b.stiffness / (a.stiffness + b.stiffness)
    return k, math.sqrt(a.restitution * b.restitution), math.sqrt(a.friction * b.friction)


def mix_rolling(a: Material, b: Material) -> float:
    """The pair's rolling-friction coefficient μ_r: the geometric mean, as friction's
    (equal materials keep theirs; a partner without rolling resistance has none)."""
    return math.sqrt(a.rolling_friction * b.rolling_friction)


@dataclass(frozen=True)
class PairTable:
    """Per material pair contact constants, indexed [material_i, material_j].

    k : (M, M) normal stiffness [N/m]
    zeta : (M, M) normal damping ratio [-]
    mu : (M, M) Coulomb friction [-]
    kt_ratio : tangential viscous coefficient as a multiple of √(k m_eff) [-]
    ks_ratio : tangential spring as a multiple of k [-] (static friction)
    mu_r : (M, M) rolling-friction coefficient [-] (mix_rolling; 0 for a frictionless pair)
    """

    k: np.ndarray
    zeta: np.ndarray
    mu: np.ndarray
    kt_ratio: float = TANGENTIAL_RATIO
    ks_ratio: float = TANGENTIAL_SPRING_RATIO
    mu_r: np.ndarray = None


def pair_table(materials: list[Material], stiffness: list[float], law=_law) -> PairTable:
    """Build the pair table from materials and their resolved stiffness (auto applied);
    ``law``: the contact law module whose damping ratio gives each pair's restitution."""
    m = len(materials)
    k = np.zeros((m, m))
    zeta = np.zeros((m, m))
    mu = np.zeros((m, m))
    mu_r = np.zeros((m, m))
    for i, a in enumerate(materials):
        for j, b in enumerate(materials):
            ka, kb = stiffness[i], stiffness[j]
            k[i, j] = 2.0 * ka * kb / (ka + kb)
            _, e, f = mix(a, b)
            zeta[i, j] = law.damping_ratio(e)
            mu[i, j] = f
            # a frictionless contact takes no tangential force: it cannot roll a body,
            # so it resists no rolling either (friction 0 means no grip of any kind)
            mu_r[i, j] = mix_rolling(a, b) if f > 0.0 else 0.0
    return PairTable(k, zeta, mu, mu_r=mu_r)


#: Largest rotation per step dt "auto" allows a free spin [rad]: the midpoint
#: orientation update keeps a spinning needle's energy within 1e-3 at 0.04.
MAX_SPIN_STEP = 0.04

#: dt "auto" moves no point of a body launched at the scene's initial speeds
#: further than this fraction of a diameter per step: half the bake's travel
#: guard (simulator.MAX_STEP_TRAVEL), so a spinning needle's tip stays resolved.
AUTO_TRAVEL = 0.25

#: Spheres across the patch scale's body (patch_scale): the overlap target of
#: auto stiffness is a fraction of a quarter of the smallest body's extent, or of d
#: where the spheres are coarser than that.
PATCH_RESOLUTION = 4.0

#: The patch scale is at most this many diameters: at the default overlap target
#: (0.02) a contact then overlaps at most 0.1 d, the depth `dempipe check` starts
#: warning at, whatever the shape (a rod one sphere thick and 100 d long would
#: otherwise take 25 d, and its contacts half a sphere deep).
PATCH_MAX_DIAMETERS = 5.0


def contact_masses(body_material, body_mass, corner_mass, moves, wall_materials) -> dict:
    """{(kind, mi, mj): (m_translational, m_rotational)} [kg]: the lightest effective
    mass of each kind of contact, the one derivation of the stiffest contact that
    ModelBuilder.finalize (its dt and critical step) and check.stability (its table)
    share. ``body_material``, ``body_mass``, ``corner_mass`` (m / (1 + f), the corner
    contact's rotational mode: ModelBuilder.finalize): per dynamic body; ``moves``:
    (n,) bool, False for a kinematic body, whose motion is given (it is a partner, its
    material present, never a mass); ``wall_materials``: the walls' and static meshes'.

    For each material mi of a moving body: against every body material mj when there
    are two bodies or more ("body-body", keyed (min, max) and taking the lighter side:
    two equal bodies meet as one of half the mass) and against each wall material
    ("body-wall", the body's whole mass). Empty where nothing can touch."""
    mat = np.asarray(body_material)
    n = mat.shape[0]
    moves = np.asarray(moves, dtype=bool)
    walls = sorted(set(int(w) for w in wall_materials))
    pairs: dict = {}
    if not (n > 1 or walls):
        return pairs
    present = sorted(set(mat.tolist()))
    mass = np.asarray(body_mass, dtype=np.float64)
    corner = np.asarray(corner_mass, dtype=np.float64)
    for mi in sorted(set(mat[moves].tolist())):
        sel = moves & (mat == mi)
        m_tr = float(mass[sel].min())
        m_rot = float(corner[sel].min())
        partners = [("body-body", mj) for mj in present] if n > 1 else []
        partners += [("body-wall", mj) for mj in walls]
        for kind, mj in partners:
            half = 0.5 if kind == "body-body" else 1.0
            key = (kind,) + ((min(mi, mj), max(mi, mj)) if kind == "body-body" else (mi, mj))
            mt, mr = m_tr * half, m_rot * half
            prev = pairs.get(key)
            if prev is not None:
                mt, mr = min(mt, prev[0]), min(mr, prev[1])
            pairs[key] = (mt, mr)
    return pairs


def patch_scale(diameter: float, extents) -> float:
    """The length ℓ [m] the overlap target (stiffness_target_overlap) is a fraction
    of: L / PATCH_RESOLUTION within [d, PATCH_MAX_DIAMETERS d], L the longest extent
    of the smallest dynamic shape ([m], ``extents``: each shape's; d alone when there
    is none).

    A contact between two bodies is one patch however many sphere pairs make it up
    (kernels/patches.py), so its stiffness is the bodies' business, not the
    spheres': with ℓ = d, a finer set would be stiffer (k ∝ 1/d²) and its step
    shorter, for the same bodies. With ℓ fixed by the bodies, the auto stiffness and
    the auto step do not depend on the resolution from PATCH_RESOLUTION up to
    PATCH_RESOLUTION × PATCH_MAX_DIAMETERS (20) spheres across; coarser sets keep the
    overlap a fraction of d, finer ones a fraction of 5 d.
    """
    d = float(diameter)
    ext = [float(e) for e in extents if e > 0.0]
    if not ext:
        return d
    return min(max(d, min(ext) / PATCH_RESOLUTION), PATCH_MAX_DIAMETERS * d)


#: dt "auto" of a scene in which no contact is possible [s] (contact_possible).
FREE_FLIGHT_DT = 1.0 / 240.0


def contact_possible(omega_max: float) -> bool:
    """Whether any contact can happen in a scene whose stiffest contact frequency
    ModelBuilder.finalize found to be ``omega_max`` [rad/s] (``Model.omega_max``).

    finalize finds no contact (ω_max = 0) where no body the physics moves can touch
    anything: one body and no colliders (no plane, box or static mesh), or kinematic
    bodies only (their motion is given). dt "auto" steps such a scene at
    FREE_FLIGHT_DT whatever its speeds, and there is nothing in it to pass through:
    the travel guards (Simulator, check.stability.tunnelling) leave it alone.
    """
    return omega_max > 0.0 and not math.isnan(omega_max)


def auto_dt(omega_max: float, fps: float, steps_per_contact: float = STEPS_PER_CONTACT,
            zeta_max: float = 0.0, dt_max: float = math.inf) -> tuple[float, int]:
    """dt from the stiffest mode, rounded down so each frame is whole steps.

    omega_max : the largest contact frequency √(k/m_eff) of the scene [rad/s]
                (translational and rotational effective masses included).
    zeta_max : the largest damping ratio; the contact lasts π/(ω√(1−ζ²)), but
               for ζ → 1 (e → 0) that grows without bound while the dynamics
               do not slow down, so √(1−ζ²) is taken no smaller than 1/√2 (at
               1/2, e = 0 rebounded at 0.143 of its impact speed, above the exact
               e^-2 = 0.135; at 1/√2, 0.100: tests/sim/test_extremes.py).
    dt_max : a further bound [s] (free spin, fast surfaces), see ModelBuilder.finalize.
    Returns (dt, steps_per_frame).
    """
    if omega_max == math.inf:
        raise StabilityError(_STIFF_REFUSAL.format(what="infinitely stiff (the speeds or "
                                                   "gravity overflow)"))
    if not contact_possible(omega_max):
        # one step per 1/240 s resolves free flight and tumbling well
        dt_target = FREE_FLIGHT_DT
    else:
        tc = math.pi / (omega_max * math.sqrt(max(1.0 - zeta_max**2, 0.5)))
        dt_target = tc / steps_per_contact
    dt_target = min(dt_target, dt_max)
    frame = 1.0 / fps
    per_frame = frame / dt_target if dt_target > 0.0 else math.inf
    if not per_frame < 1e15:
        raise StabilityError(_STIFF_REFUSAL.format(
            what=f"so stiff that a frame needs {per_frame:.3g} steps"))
    steps = max(1, math.ceil(per_frame - 1e-9))
    return frame / steps, steps


#: auto_dt's refusal of contacts no step can resolve (keys named for the user).
_STIFF_REFUSAL = ("simulation.dt: the auto step finds the contacts {what}: check the "
                  "bodies' velocity and angular_velocity, simulation.gravity and "
                  "simulation.stiffness_target_overlap (physical values are metres per "
                  "second, about 9.81 m/s² and 0.01-0.1)")


#: The share of the critical step a user dt is advised to stay below: a body pressed
#: by n partners at once adds their stiffnesses (ω grows as √n), so half the single
#: contact's critical step stays stable on up to three (docs/stability.md).
SAFE_SHARE = 0.5


def advised_dt(limit: float, auto: float) -> float:
    """The dt [s] a refusal of a user dt advises staying below: SAFE_SHARE of the
    critical step ``limit`` [s], or the automatic step ``auto`` [s] where that is
    longer and still below ``limit`` (a heavily damped contact's auto step can be),
    so the advice never asks for a shorter step than dt "auto" takes. The one figure
    materials.check_dt (the bake) and check.stability (the check) name."""
    safe = SAFE_SHARE * limit
    return auto if safe < auto < limit else safe


def dt_fix(limit: float, auto: float, steps_per_frame: int) -> str:
    """The fix for a user dt at or above the critical step ``limit`` [s], given the
    automatic step ``auto`` [s] and its ``steps_per_frame``: the text the bake's
    refusal and the check's finding share."""
    return (f"use dt = \"auto\" ({auto:.3g} s here, {steps_per_frame} steps per frame), a "
            f"dt below {advised_dt(limit, auto):.3g} s, or softer materials")


def check_dt(dt: float, omega_max: float, zeta_min: float, where: str, law=_law,
             auto: tuple[float, int] | None = None) -> None:
    """Refuse a user dt above the critical step of the stiffest contact (``law``'s).

    auto : (dt [s], steps per frame) of dt "auto" for the same scene, for the advice
    (dt_fix); None where dt "auto" is refused itself (the advice is then SAFE_SHARE of
    the critical step).
    """
    if not contact_possible(omega_max):
        return
    limit = law.critical_step(omega_max, zeta_min)
    if dt >= limit:
        fix = (dt_fix(limit, *auto) if auto is not None else
               f"use a dt below {advised_dt(limit, 0.0):.3g} s, or softer materials")
        raise StabilityError(
            f"{where}: dt = {dt:.3g} s is above the critical step {limit:.3g} s of the "
            f"stiffest contact (ω = {omega_max:.4g} rad/s); {fix}"
        )
