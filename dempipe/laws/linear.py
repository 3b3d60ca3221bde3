"""The linear spring-dashpot contact law (Harada et al. 2007, eq. 11-14).

Normal force f_n = -k δ + η u_n on an overlap δ [m] closing at u_n [m/s], with a
dashpot η = 2ζ√(k m_eff) [N s/m] taken per contact from the two bodies' masses.
The normal motion of a contact is then a damped oscillator:

    ω0 = √(k/m_eff),   ζ = η / (2√(k m_eff)),   ωd = ω0 √(1-ζ²)
    e  = exp(-ζπ/√(1-ζ²))          (coefficient of restitution)
    tc = π / ωd                     (contact duration)

so ζ = -ln e / √(π² + ln² e) gives exactly the asked restitution. Symplectic
Euler integrates it stably for ω0 dt < 2(√(1+ζ²) - ζ). Tangential: a dashpot
kt = kt_ratio √(k m_eff) and a spring ks = ks_ratio k (see materials.py for the
ratios and physics.contact_force for how they are capped by Coulomb).

Two kinds of functions:

* host functions (plain Python floats): what the model, the stability report,
  the build and the simulator's guards derive from the law;
* ``KERNEL`` functions, plain too and compiled for both targets by
  ``kernels.compile.compile_formulas`` (no numba import here): the per-contact
  coefficients and the normal force the contact kernels evaluate.

A second law (Hertz-Mindlin) is a module with the same names, registered in
``laws/__init__.py``; see docs/architecture.md, "Adding a contact law".
"""

from __future__ import annotations

import math
from math import sqrt

NAME = "linear"

# ---------------------------------------------------------------------------
# Host: what is derived from the law
# ---------------------------------------------------------------------------


def damping_ratio(restitution: float) -> float:
    """ζ from e: ζ = -ln e / √(π² + ln² e).

    e = 0 would need ζ = 1 and an infinitely long tail; we cap ζ at 1 (critical
    damping), which returns almost nothing: the rebound is below 1e-3 of the impact.
    """
    if restitution <= 0.0:
        return 1.0
    if restitution >= 1.0:
        return 0.0
    ln_e = math.log(restitution)
    return -ln_e / math.sqrt(math.pi**2 + ln_e**2)


def restitution(zeta: float) -> float:
    """e from ζ, the inverse of :func:`damping_ratio`."""
    if zeta >= 1.0:
        return 0.0
    return math.exp(-zeta * math.pi / math.sqrt(1.0 - zeta * zeta))


def omega(k: float, m_eff: float) -> float:
    """Undamped frequency ω0 = √(k/m_eff) of a contact [rad/s]."""
    return math.sqrt(k / m_eff)


def contact_time(k: float, m_eff: float, zeta: float) -> float:
    """Duration of one contact, tc = π/ωd [s]."""
    omega0 = math.sqrt(k / m_eff)
    return math.pi / (omega0 * math.sqrt(max(1.0 - zeta * zeta, 1e-6)))


def critical_step(omega0: float, zeta: float) -> float:
    """Largest stable step of symplectic Euler on the damped oscillator [s]:
    ω dt < 2(√(1+ζ²) − ζ), which shrinks like 1/(ζ ω) when ζ is large;
    inf when nothing can touch (ω = 0)."""
    if omega0 <= 0.0:
        return math.inf
    return 2.0 * (math.sqrt(1.0 + zeta * zeta) - zeta) / omega0


def critical_dt(k: float, m_eff: float, zeta: float) -> float:
    """:func:`critical_step` of a contact of stiffness k and effective mass m_eff [s]."""
    return critical_step(math.sqrt(k / m_eff), zeta)


def parallel(n: int, k: float, zeta: float) -> tuple[float, float]:
    """(k, ζ) of n equal contacts acting together on one body (a face landing
    flat): the dashpots scale with √(k m), so n contacts are one oscillator of
    stiffness n k and damping ratio √n ζ."""
    return n * k, math.sqrt(n) * zeta


def stiffness_for_overlap(mass: float, impact_speed: float, weight_accel: float,
                          diameter: float, target_overlap: float) -> float:
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


def overlap_for_stiffness_factor(target_overlap: float, factor: float) -> float:
    """The target overlap that scales auto stiffness by ``factor``: impacts set
    it, k ∝ 1/δ², so δ / √factor."""
    return target_overlap / factor ** 0.5


def elastic_energy(k: float, overlap) -> float:
    """Energy stored in a contact of stiffness k at ``overlap`` [J]: ½ k δ²
    (``overlap`` a float or an array of overlaps, summed)."""
    import numpy as np
    ov = np.asarray(overlap, dtype=np.float64).ravel()
    return 0.5 * float(k) * float(ov @ ov)


# ---------------------------------------------------------------------------
# Kernels: compiled for both targets (kernels/compile.py, LAW_FORMULAS)
# ---------------------------------------------------------------------------


def contact_coefficients(k, zeta, inv_mass_sum, kt_ratio, ks_ratio):
    """(k, η, kt, ks) of one contact: its normal spring [N/m], normal dashpot
    η = 2ζ√(k m_eff) [N s/m], tangential dashpot kt_ratio √(k m_eff) [N s/m] and
    tangential spring ks_ratio k [N/m], with m_eff = 1/inv_mass_sum the two
    bodies' effective mass (a static partner adds 0 to inv_mass_sum), so a
    one-sphere body bounces with exactly the restitution ζ came from."""
    root = sqrt(k / inv_mass_sum)
    return k, 2.0 * zeta * root, kt_ratio * root, ks_ratio * k


def normal_force(k, eta, overlap, un):
    """Normal force along n (from i towards its partner) on sphere i [N]: the
    spring -k δ and a dashpot on the normal relative velocity u_n; negative
    pushes i away."""
    return -k * overlap + eta * un


#: The functions the kernels compile from this law (callees first).
KERNEL = ("contact_coefficients", "normal_force")
