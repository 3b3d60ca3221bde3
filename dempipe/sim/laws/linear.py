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

import numpy as np

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


def omega(k: float, m_eff: float, speed: float = 1.0) -> float:
    """Undamped frequency ω0 = √(k/m_eff) of a contact [rad/s] (at any impact speed)."""
    return math.sqrt(k / m_eff)


def contact_time(k: float, m_eff: float, zeta: float, speed: float = 1.0) -> float:
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


def critical_dt(k: float, m_eff: float, zeta: float, speed: float = 1.0) -> float:
    """:func:`critical_step` of a contact of stiffness k and effective mass m_eff [s]."""
    return critical_step(math.sqrt(k / m_eff), zeta)


def duration_zeta(zeta: float) -> float:
    """The damping ratio by which dt="auto" lengthens the contact (materials.auto_dt)."""
    return zeta


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


def rest_overlap(weight: float, k: float) -> float:
    """The overlap [m] at which a contact of stiffness ``k`` [N/m] carries ``weight`` [N]."""
    return weight / k


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


def _sigma_series(zeta):
    """(s1 .. s5) of σ = ζ a (1 + s1 a + ... + s5 a⁵) (step_damping)."""
    z2 = zeta * zeta
    return (0.5 * zeta,
            0.2916666666666667 * z2 + 0.041666666666666664,
            zeta * (0.16666666666666666 * z2 + 0.08333333333333333),
            0.08524305555555556 * z2 * z2 + 0.11006944444444444 * z2 + 0.0046875,
            zeta * (0.03333333333333333 * z2 * z2 + 0.11666666666666667 * z2
                    + 0.016666666666666666))


def step_damping(zeta: float, a: float) -> float:
    """The fraction b of a contact's relative normal speed its dashpot removes in one
    step of symplectic Euler, chosen so that the *discrete* oscillator bounces with
    exactly the restitution ζ stands for [dimensionless].

    a = ω0 dt. The step map of the undamped spring plus a dashpot η' has
    determinant 1 - b (b = η' dt / m_eff) and turns by θ per step; the contact
    lasts π/θ steps and returns (1 - b)^(π/2θ) of the speed. Asking that to be
    e = exp(-ζπ/√(1-ζ²)) gives, with 1 - b = exp(-2σ),

        a² = 1 + e^(-2σ) - 2 e^(-σ) cos(σ √(1-ζ²)/ζ),

    whose series inverse is σ = ζ a (1 + s1 a + ... + s5 a⁵) (error of e below
    0.1% for e ≥ 0.05 at 8 or more steps per contact, docs/physics.md).
    As dt → 0, b → 2ζ ω0 dt: the plain dashpot η = 2ζ√(k m_eff). The plain dashpot
    itself, taken at the step's velocity, removes too much (e = 0.2 bounced 10%
    low at 16 steps per contact). The kernels take b / a as a polynomial in a
    whose coefficients depend on ζ only (damping_table), so a contact pays a
    short Horner sum and no exponential."""
    s1, s2, s3, s4, s5 = _sigma_series(zeta)
    sigma = zeta * a * (1.0 + a * (s1 + a * (s2 + a * (s3 + a * (s4 + a * s5)))))
    return -math.expm1(-2.0 * sigma)


#: dt="auto": steps per contact at the stiffest contact (materials.auto_dt). With the
#: onset and end resolved within the step (normal_force) and the step-sized dashpot,
#: 10 keeps e² within 2 % mean / 4 % worst over contact phases for e from 0.1 to 0.9
#: (8 does not: e = 0.1 is 6.8 % off at worst); docs/physics.md has the table and
#: the settled piles it was checked on. (Before the onset was resolved: 16.)
STEPS_PER_CONTACT = 10.0

#: Coefficients per material pair of the dashpot's polynomial (damping_table).
DAMP_TERMS = 3


def damping_series(zeta: float, terms: int = DAMP_TERMS) -> np.ndarray:
    """Taylor coefficients c_0 .. c_{terms-1} of step_damping(ζ, a) / a in a = ω0 dt
    [dimensionless]: η = √(k m_eff) Σ c_i a^i is the step-sized dashpot (c_0 = 2ζ,
    the plain one). The composition of σ(a) and 1 - exp(-2σ), truncated (σ is known to
    a⁶); within 1.5e-4 of step_damping / a for e ≥ 0.05 and a ≤ 0.4 (8 or more
    steps per contact), 1.5e-3 at a ≤ 0.6 (tests/sim/test_restitution.py)."""
    if zeta >= 1.0:
        # e = 0, critical damping: no rebound for the step to match, and the sizing
        # (which takes damping away as a grows) let a dropped ball leave its contact
        # at 0.17 of the impact speed, above the closed form's 0.135
        # (tests/sim/test_extremes.py): the plain dashpot 2ζ√(k m_eff)
        out = np.zeros(terms)
        out[0] = 2.0 * zeta
        return out
    x = np.zeros(terms + 1)                     # 2σ as a polynomial in a
    x[1:terms + 1] = 2.0 * zeta * np.array((1.0,) + _sigma_series(zeta))[:terms]
    b = np.zeros(terms + 1)
    power = np.zeros(terms + 1)
    power[0] = 1.0
    fact = 1.0
    for n in range(1, terms + 1):                # 1 - exp(-x) = Σ (-1)^(n+1) x^n / n!
        power = np.convolve(power, x)[:terms + 1]
        fact *= n
        b += (-1.0) ** (n + 1) * power / fact
    return b[1:]


def damping_table(zeta) -> np.ndarray:
    """The (M, M, DAMP_TERMS) table of damping_series for each material pair's ζ
    (``zeta``, (M, M)): what the kernels' contact_coefficients read."""
    zeta = np.asarray(zeta, dtype=np.float64)
    out = np.zeros(zeta.shape + (DAMP_TERMS,))
    for ij in np.ndindex(zeta.shape):
        out[ij] = damping_series(float(zeta[ij]))
    return out


def contact_coefficients(k, damp, mi, mj, inv_mass_sum, kt_ratio, ks_ratio, dt, overlap):
    """(k, η, kt, ks) of one contact between materials mi and mj: its normal spring
    [N/m], normal dashpot η [N s/m], tangential dashpot kt_ratio √(k m_eff)
    [N s/m] and tangential spring ks_ratio k [N/m], with m_eff = 1/inv_mass_sum
    the two bodies' effective mass (a static partner adds 0 to inv_mass_sum).

    η = √(k m_eff) Σ damp[mi, mj, i] a^i, a = ω0 dt (damping_table): the
    step-sized dashpot that makes the stepped contact lose what the closed form
    loses, so a one-sphere body bounces with exactly the restitution ζ came from
    (2ζ√(k m_eff) as dt → 0, and with dt = 0). ``overlap`` [m]: unused (the
    linear law's coefficients do not depend on it)."""
    root = sqrt(k / inv_mass_sum)            # √(k m_eff)
    a = root * inv_mass_sum * dt             # ω0 dt, as k / root
    eta = root * (damp[mi, mj, 0] + a * (damp[mi, mj, 1] + a * damp[mi, mj, 2]))
    return k, eta, kt_ratio * root, ks_ratio * k


def normal_force(k, eta, overlap, un, dt, vc):
    """Normal force along n (from i towards its partner) on sphere i [N]: the
    spring -k δ and a dashpot on the normal relative velocity u_n; negative
    pushes i away.

    The contact begins and ends within a step. Over the step that brought the
    overlap to δ, it changed linearly from δ_prev = δ + u_n dt (u_n < 0 closes),
    so the dashpot's impulse, -η ∫ dδ⁺, is -η (δ⁺ - δ_prev⁺): η u_n dt while
    the contact lasts, -η δ in the step it begins (the part of the step spent in
    contact), and +η δ_prev in the step after it ends (``overlap`` ≤ 0 then;
    the kernels call it while δ_prev > 0: ``closing``). Summed over a contact the
    impulses telescope to 0, as the closed form's do, and each is dissipative.

    Only for impacts: a contact that begins or ends slower than ``vc`` [m/s]
    (Model.onset_speed) is a resting one and takes the plain dashpot η u_n
    (and nothing once apart). Resolved there too, the onset and end act on a
    contact that flickers across δ = 0 (bodies resting side by side, lightly
    loaded) as a spring of stiffness η/dt on both sides of δ = 0, which a face
    of several such contacts turns unstable (a dense pile of touching cubes
    gained energy, docs/physics.md)."""
    if overlap > 0.0:
        if overlap + un * dt > 0.0 or un >= -vc:
            return -k * overlap + eta * un
        return -(k + eta / dt) * overlap          # it began within this step
    prev = overlap + un * dt
    if prev > 0.0 and un > vc:
        return eta * prev / dt                    # it ended within the last step
    return 0.0


def closing(overlap, un, dt):
    """Whether a contact apart by -``overlap`` [m] (≤ 0) was still touching one
    step ago, by δ_prev = δ + u_n dt > 0: the step in which normal_force applies
    the end of its dashpot."""
    return overlap + un * dt > 0.0


#: The functions the kernels compile from this law (callees first).
KERNEL = ("contact_coefficients", "normal_force", "closing")
