"""Materials and contact parameters: where stability lives.

A user thinks in restitution, not in dashpot constants. For the linear
spring-dashpot contact of two masses with effective mass m_eff, stiffness k and
dashpot η, the normal motion during contact is a damped oscillator with

    ω0 = √(k/m_eff),   ζ = η / (2√(k m_eff)),   ωd = ω0 √(1-ζ²)
    e  = exp(-ζπ/√(1-ζ²))          (coefficient of restitution)
    tc = π / ωd                     (contact duration)

so ζ = -ln e / √(π² + ln² e) gives exactly the asked restitution, and
η = 2ζ√(k m_eff) is evaluated per contact from the two bodies' masses.

Explicit (symplectic Euler) integration of that oscillator is stable for
ω0 dt < 2(√(1+ζ²) - ζ); dempipe stays far below it, because accuracy of the
bounce (and of piles with many simultaneous contacts, whose stiffness adds up)
needs ~16 steps per contact, not ~1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import StabilityError

#: Steps per contact duration that dt="auto" aims for. The bounce-height test
#: (e² within 3%) needs ≥ ~10; piles with several contacts per body add stiffness,
#: so 16 leaves room for ~25 simultaneous contacts before the critical step.
STEPS_PER_CONTACT = 16.0

#: Tangential dashpot as a multiple of √(k m_eff). With the tangential spring
#: (ks = 2/7 k, below) doing the holding, the dashpot only damps the tangential
#: oscillation: for a ball (m_t = 2/7 m) 0.3 is a damping ratio of
#: 0.3 / (2 · 2/7) ≈ 0.52. It must stay small because a body touching on n
#: contacts feels n dashpots: at 1.0 a box resting on 16 contacts rocked
#: unstably at dt auto and crept down a 20° slope at 7 mm/s with μ = 0.6
#: (tests/test_friction.py); at 0.1-0.5 it holds to 1e-18 m/s.
TANGENTIAL_RATIO = 0.3

#: Tangential spring as a fraction of the normal one, ks = 2/7 k: a solid ball's
#: tangential oscillation (effective mass 2/7 m) then has the normal frequency,
#: so the static-friction spring adds no faster mode than dt already resolves
#: (Schäfer, Dippel and Wolf 1996).
TANGENTIAL_SPRING_RATIO = 2.0 / 7.0


@dataclass(frozen=True)
class Material:
    """A material as the user gives it.

    density : [kg/m³] > 0
    restitution : e ∈ [0, 1], normal rebound speed / approach speed
    friction : Coulomb μ ≥ 0 (0 turns friction off)
    stiffness : normal spring k [N/m], or None for "auto"
    """

    name: str
    density: float = 1000.0
    restitution: float = 0.5
    friction: float = 0.5
    stiffness: float | None = None


DEFAULT_MATERIAL = Material("default")


def damping_ratio(restitution: float) -> float:
    """ζ from e for the linear spring-dashpot: ζ = -ln e / √(π² + ln² e).

    e = 0 would need ζ = 1 and an infinitely long tail; we cap ζ at 1 (critical
    damping), which returns almost nothing: the rebound is below 1e-3 of the impact.
    """
    if restitution <= 0.0:
        return 1.0
    if restitution >= 1.0:
        return 0.0
    ln_e = math.log(restitution)
    return -ln_e / math.sqrt(math.pi**2 + ln_e**2)


def restitution_from_damping(zeta: float) -> float:
    """Inverse of :func:`damping_ratio` (for tests and reports)."""
    if zeta >= 1.0:
        return 0.0
    return math.exp(-zeta * math.pi / math.sqrt(1.0 - zeta * zeta))


def contact_time(k: float, m_eff: float, zeta: float) -> float:
    """Duration of one spring-dashpot contact, tc = π/ωd [s]."""
    omega0 = math.sqrt(k / m_eff)
    return math.pi / (omega0 * math.sqrt(max(1.0 - zeta * zeta, 1e-6)))


def critical_dt(k: float, m_eff: float, zeta: float) -> float:
    """Largest stable step of symplectic Euler for the damped oscillator [s]."""
    omega0 = math.sqrt(k / m_eff)
    return 2.0 * (math.sqrt(1.0 + zeta * zeta) - zeta) / omega0


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


def auto_stiffness(mass: float, impact_speed: float, weight_accel: float, diameter: float,
                   target_overlap: float) -> float:
    """Stiffness that keeps the largest overlap near ``target_overlap × diameter``.

    Two loads set the overlap of a contact between a body of ``mass`` and a
    static wall (the worst case: the partner does not give way):
      impact:  an undamped spring stops the body within δ = v √(m/k)
               → k ≥ m v² / δ²
      weight:  one sphere carrying the body's whole weight sinks δ = m g / k
               → k ≥ m g / δ
    Damping only shortens the overlap, so both bounds are conservative.
    """
    delta = target_overlap * diameter
    k_impact = mass * impact_speed**2 / delta**2
    k_weight = mass * weight_accel / delta
    return max(k_impact, k_weight)


@dataclass(frozen=True)
class PairTable:
    """Per material pair contact constants, indexed [material_i, material_j].

    k : (M, M) normal stiffness [N/m]
    zeta : (M, M) normal damping ratio [-]
    mu : (M, M) Coulomb friction [-]
    kt_ratio : tangential viscous coefficient as a multiple of √(k m_eff) [-]
    ks_ratio : tangential spring as a multiple of k [-] (static friction)
    """

    k: np.ndarray
    zeta: np.ndarray
    mu: np.ndarray
    kt_ratio: float = TANGENTIAL_RATIO
    ks_ratio: float = TANGENTIAL_SPRING_RATIO


def pair_table(materials: list[Material], stiffness: list[float]) -> PairTable:
    """Build the pair table from materials and their resolved stiffness (auto applied)."""
    m = len(materials)
    k = np.zeros((m, m))
    zeta = np.zeros((m, m))
    mu = np.zeros((m, m))
    for i, a in enumerate(materials):
        for j, b in enumerate(materials):
            ka, kb = stiffness[i], stiffness[j]
            k[i, j] = 2.0 * ka * kb / (ka + kb)
            _, e, f = mix(a, b)
            zeta[i, j] = damping_ratio(e)
            mu[i, j] = f
    return PairTable(k, zeta, mu)


#: Largest rotation per step dt "auto" allows a free spin [rad]: the midpoint
#: orientation update keeps a spinning needle's energy within 1e-3 at 0.04.
MAX_SPIN_STEP = 0.04

#: dt "auto" moves no point of a body launched at the scene's initial speeds
#: further than this fraction of a diameter per step: half the bake's travel
#: guard (simulator.MAX_STEP_TRAVEL), so a spinning needle's tip stays resolved.
AUTO_TRAVEL = 0.25

#: dt "auto" stays below this fraction of the critical step of a flat landing
#: (see flat_face_critical_step).
FLAT_FACE_SAFETY = 0.5


def damped_critical_step(omega: float, zeta: float) -> float:
    """Largest stable step of symplectic Euler on a damped oscillator [s]:
    ω dt < 2(√(1+ζ²) − ζ), which shrinks like 1/(ζ ω) when ζ is large."""
    return 2.0 * (math.sqrt(1.0 + zeta * zeta) - zeta) / omega


def flat_face_critical_step(n: int, k: float, m: float, zeta: float) -> float:
    """Critical step of a body of mass m landing flat on n spheres at once [s].

    Each contact's dashpot is η = 2ζ√(k m) (the body's mass, see docs/physics.md),
    so n contacts in parallel are one oscillator of stiffness n k and damping
    n η: ω_n = √n ω, ζ_n = √n ζ. A wide flat face (a tile: n = 64) makes ζ_n
    large and its critical step far shorter than a corner contact's.
    """
    return damped_critical_step(math.sqrt(n * k / m), math.sqrt(n) * zeta)


def auto_dt(omega_max: float, fps: float, steps_per_contact: float = STEPS_PER_CONTACT,
            zeta_max: float = 0.0, dt_max: float = math.inf) -> tuple[float, int]:
    """dt from the stiffest mode, rounded down so each frame is whole steps.

    omega_max : the largest contact frequency √(k/m_eff) of the scene [rad/s]
                (translational and rotational effective masses included).
    zeta_max : the largest damping ratio; the contact lasts π/(ω√(1−ζ²)), but
               for ζ → 1 (e → 0) that grows without bound while the dynamics
               do not slow down, so √(1−ζ²) is taken no smaller than 1/√2 (at
               1/2, e = 0 rebounded at 0.143 of its impact speed, above the exact
               e^-2 = 0.135; at 1/√2, 0.100: tests/test_extremes.py).
    dt_max : a further bound [s] (flat faces, free spin), see ModelBuilder.finalize.
    Returns (dt, steps_per_frame).
    """
    if omega_max == math.inf:
        raise StabilityError(_STIFF_REFUSAL.format(what="infinitely stiff (the speeds or "
                                                   "gravity overflow)"))
    if not (omega_max > 0.0 and math.isfinite(omega_max)):
        # No contact can happen (no colliders, one body): one step per 1/240 s
        # resolves free flight and tumbling well.
        dt_target = 1.0 / 240.0
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


def check_dt(dt: float, omega_max: float, zeta_min: float, where: str) -> None:
    """Refuse a user dt above the critical step of the stiffest contact."""
    if omega_max <= 0.0:
        return
    limit = 2.0 * (math.sqrt(1.0 + zeta_min**2) - zeta_min) / omega_max
    if dt >= limit:
        raise StabilityError(
            f"{where}: dt = {dt:.3g} s is above the critical step {limit:.3g} s of the "
            f"stiffest contact (ω = {omega_max:.4g} rad/s); use dt = \"auto\", a dt below "
            f"{limit / STEPS_PER_CONTACT * math.pi / 2:.3g} s, or softer materials"
        )
