"""Hertz-Mindlin contact law with velocity-independent damping (Tsuji et al. 1992).

Normal force f_n = -K δ^{3/2} + η δ^{1/4} u_n on an overlap δ [m] closing at u_n
[m/s] (u_n < 0 closes), with K [N/m^{3/2}] the Hertz constant, K = (4/3) E* √R*
for two spheres of effective radius R* and modulus E*, and η = c √(m_eff K)
[N s/m^{5/4}] per contact from the two bodies' masses. Both terms vanish at δ = 0:
the force is continuous where a contact begins and ends, so nothing jumps within a
step. Scaled by L = (m v²/K)^{2/5} and T = L / v (v the impact speed), the
normal motion is ξ'' = -ξ^{3/2} - c ξ^{1/4} ξ', the same for every speed and mass:
the restitution e depends on c only (Tsuji's point), and the contact lasts
τ_c(c) (m/K)^{2/5} v^{-1/5} (τ_c(0) = 3.218; with K = (4/3) E* √R* that is the
classical 2.87 (m²/(R* E*² v))^{1/5}).

Tangential (Mindlin, no-slip): the spring and the dashpot follow the normal
stiffness, ks = ks_ratio K √δ and kt = kt_ratio √(m_eff K) δ^{1/4}, under the same
Coulomb cap and history as the linear law (physics.contact_force). The dashpot is
sized per step as the linear law's is (contact_coefficients).

``pair_k`` holds K and ``pair_zeta`` holds c for this law. Host functions that
need a frequency take the impact ``speed`` [m/s]: a Hertz contact stiffens as it
deepens, so its frequency ω = π / t_c(v) grows with the impact speed (as v^{1/5}).
"""

from __future__ import annotations

import functools
import math
from math import sqrt

import numpy as np

from dempipe.sim.laws.linear import DAMP_TERMS, damping_series  # noqa: F401 (DAMP_TERMS: the table's width)

NAME = "hertz"

#: Undamped contact time of ξ'' = -ξ^{3/2} from ξ' = 1 (Γ-function closed form).
TAU_UNDAMPED = 2.0 * (5.0 / 4.0) ** 0.4 * math.sqrt(math.pi) * math.gamma(0.4) / math.gamma(0.9) / 2.5

# ---------------------------------------------------------------------------
# Host: the dimensionless contact, solved once
# ---------------------------------------------------------------------------


def _bounce_py(c, h):
    """(e, τ_c) of ξ'' = -ξ^{3/2} - c ξ^{1/4} ξ' from ξ = 0, ξ' = 1: classical RK4
    in τ with step h, the exit (ξ back to 0) located by cubic Hermite
    interpolation of the last step. Compiled by numba on first use (_solver)."""
    x = 0.0
    v = 1.0
    t = 0.0
    for _ in range(10_000_000):
        xp = max(x, 0.0)
        k1x = v
        k1v = -xp * sqrt(xp) - c * sqrt(sqrt(xp)) * v
        x2 = max(x + 0.5 * h * k1x, 0.0)
        k2x = v + 0.5 * h * k1v
        k2v = -x2 * sqrt(x2) - c * sqrt(sqrt(x2)) * k2x
        x3 = max(x + 0.5 * h * k2x, 0.0)
        k3x = v + 0.5 * h * k2v
        k3v = -x3 * sqrt(x3) - c * sqrt(sqrt(x3)) * k3x
        x4 = max(x + h * k3x, 0.0)
        k4x = v + h * k3v
        k4v = -x4 * sqrt(x4) - c * sqrt(sqrt(x4)) * k4x
        xn = x + h / 6.0 * (k1x + 2.0 * k2x + 2.0 * k3x + k4x)
        vn = v + h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
        if xn <= 0.0 and t > h:
            # the root of the cubic through (x, v) and (xn, vn), by bisection in [0, 1]
            lo = 0.0
            hi = 1.0
            for _ in range(60):
                s = 0.5 * (lo + hi)
                s2 = s * s
                s3 = s2 * s
                xs = ((2 * s3 - 3 * s2 + 1) * x + (s3 - 2 * s2 + s) * h * v
                      + (-2 * s3 + 3 * s2) * xn + (s3 - s2) * h * vn)
                if xs > 0.0:
                    lo = s
                else:
                    hi = s
            s = 0.5 * (lo + hi)
            return -(v + s * (vn - v)), t + s * h
        x = xn
        v = vn
        t += h
    return 0.0, t


@functools.lru_cache(maxsize=None)
def _solver():
    import numba
    return numba.njit(cache=True)(_bounce_py)


#: RK4 step of the dimensionless contact: e to ~1e-9 (halving it changes e by less).
_H = 1e-4


def _bounce(c: float) -> tuple[float, float]:
    return _solver()(float(c), _H)


def restitution(c: float) -> float:
    """e of a Hertz contact with Tsuji damping coefficient c (any impact speed)."""
    if c <= 0.0:
        return 1.0
    return float(_bounce(c)[0])


def damping_ratio(restitution_: float) -> float:
    """Tsuji's c from e: c = 2√(5/4) (-ln e)/√(π² + ln² e), the form LIGGGHTS uses
    (granular/hertz/history: γ = 2√(5/6) β √(S_n m*), S_n = (3/2) K √δ). It is the
    root of restitution(c) = e to 1e-6 for e in 0.05..0.95 (tests/sim/test_hertz.py
    checks it against the dimensionless contact solved here). e ≤ 0 gives c for
    e = 0.01; e ≥ 1 gives 0."""
    if restitution_ >= 1.0:
        return 0.0
    ln_e = math.log(max(restitution_, 0.01))
    return 2.0 * math.sqrt(1.25) * -ln_e / math.sqrt(math.pi ** 2 + ln_e ** 2)


def scaled_contact_time(c: float) -> float:
    """τ_c(c): the contact time in units of (m/K)^{2/5} v^{-1/5}."""
    return float(_bounce(max(c, 0.0))[1])


def contact_time(k: float, m_eff: float, zeta: float, speed: float = 1.0) -> float:
    """Duration of one contact at impact ``speed`` [s]: τ_c(c) (m/K)^{2/5} v^{-1/5}."""
    return scaled_contact_time(zeta) * (m_eff / k) ** 0.4 * max(speed, 1e-9) ** -0.2


def max_overlap(k: float, m_eff: float, speed: float) -> float:
    """Largest overlap of an undamped impact at ``speed`` [m]: ½ m v² = (2/5) K δ^{5/2}."""
    return (1.25 * m_eff * speed * speed / k) ** 0.4


def omega(k: float, m_eff: float, speed: float = 1.0) -> float:
    """π over the undamped contact time at impact ``speed`` [rad/s]: the frequency
    whose half period is the contact, so that "steps per contact" (dt="auto",
    materials.auto_dt) means what it means for the linear law."""
    return math.pi / (TAU_UNDAMPED * (m_eff / k) ** 0.4 * max(speed, 1e-9) ** -0.2)


#: The local frequency √(k_loc/m) at the deepest point, k_loc = (3/2) K √δ_max,
#: over :func:`omega`: the fastest oscillation a step must resolve is 1.31× ω.
PEAK = TAU_UNDAMPED * math.sqrt(1.5 * 1.25 ** 0.2) / math.pi


def critical_step(omega0: float, zeta: float) -> float:
    """Largest stable step of symplectic Euler [s] for a Hertz contact of
    :func:`omega` ω0 and Tsuji coefficient c: the linear bound at the local
    frequency PEAK ω0 and the local damping ratio c / (2√1.5) (η δ^{1/4} against
    2√(k_loc m) at the deepest point)."""
    if omega0 <= 0.0:
        return math.inf
    z = duration_zeta(zeta)
    return 2.0 * (math.sqrt(1.0 + z * z) - z) / (PEAK * omega0)


def duration_zeta(zeta: float) -> float:
    """The local damping ratio c / (2√1.5) of a Tsuji coefficient c (materials.auto_dt
    lengthens the contact by it: 1.19× for e = 0.1, where the contact lasts 1.51×
    the undamped one, so the step errs on the short side)."""
    return zeta / (2.0 * math.sqrt(1.5))


def critical_dt(k: float, m_eff: float, zeta: float, speed: float = 1.0) -> float:
    """:func:`critical_step` of a contact of constant K, effective mass m_eff at
    impact ``speed`` [s]."""
    return critical_step(omega(k, m_eff, speed), zeta)


def rest_overlap(weight: float, k: float) -> float:
    """The overlap [m] at which a contact of Hertz constant ``k`` [N/m^1.5] carries
    ``weight`` [N]: F = k δ^1.5."""
    return (weight / k) ** (2.0 / 3.0)


def stiffness_for_overlap(mass: float, impact_speed: float, weight_accel: float,
                          diameter: float, target_overlap: float) -> float:
    """K [N/m^{3/2}] that keeps the largest overlap near ``target_overlap × diameter``:
    impact ½ m v² = (2/5) K δ^{5/2} → K ≥ (5/4) m v² / δ^{5/2}; weight on one
    sphere m g = K δ^{3/2} → K ≥ m g / δ^{3/2}."""
    delta = target_overlap * diameter
    return max(1.25 * mass * impact_speed ** 2 / delta ** 2.5,
               mass * weight_accel / delta ** 1.5)


def stiffness_from_modulus(young: float, poisson: float, diameter: float) -> float:
    """K = (4/3) E* √R* of two equal spheres of ``diameter`` of one material:
    E* = E / (2 (1 - ν²)), R* = d/4."""
    e_star = young / (2.0 * (1.0 - poisson * poisson))
    return 4.0 / 3.0 * e_star * math.sqrt(0.25 * diameter)


def overlap_for_stiffness_factor(target_overlap: float, factor: float) -> float:
    """The target overlap that scales auto stiffness by ``factor``: K ∝ δ^{-5/2}."""
    return target_overlap / factor ** 0.4


def elastic_energy(k: float, overlap) -> float:
    """Energy stored in contacts of constant K at ``overlap`` [J]: (2/5) K δ^{5/2}
    (``overlap`` a float or an array of overlaps, summed; negative ones store 0)."""
    ov = np.maximum(np.asarray(overlap, dtype=np.float64).ravel(), 0.0)
    return 0.4 * float(k) * float(np.sum(ov * ov * np.sqrt(ov)))


# ---------------------------------------------------------------------------
# Kernels: compiled for both targets (kernels/compile.py)
# ---------------------------------------------------------------------------


#: The stiffness, in K √δ, at which contact_coefficients sizes the step's dashpot:
#: a Hertz contact is not one linear oscillator, so the linear law's sizing
#: (damping_series) is taken at a representative stiffness, chosen by measurement
#: (benchmarks/restitution_vs_dt.py --law hertz, docs/physics.md): at the tangent
#: stiffness 1.5 K √δ, e = 0.1 bounced 8 % low in e² at 10 steps per contact and
#: 4 % low at 16; at 1.8, 1.7 % low at 12 and 0.8 % at 16; at 2.25, 4 % high.
SIZING_STIFFNESS = 1.8

#: dt="auto": steps per contact at the fastest impact (materials.auto_dt). 12 keeps
#: e² within 2 % mean / 4 % worst over contact phases for e from 0.1 to 0.9 (10 does
#: not: e = 0.1 bounces 2.7 % low); a slower impact lasts longer, so takes more.
STEPS_PER_CONTACT = 12.0


def contact_coefficients(k, damp, mi, mj, inv_mass_sum, kt_ratio, ks_ratio, dt, overlap):
    """(K, η, kt, ks) of one contact between materials mi and mj at ``overlap`` δ
    [m]: K [N/m^{3/2}]; the normal dashpot's constant η [N s/m^{5/4}]
    (normal_force multiplies it by δ^{1/4} u_n), Tsuji's c √(m_eff K); the
    tangential dashpot kt_ratio √(m_eff K) δ^{1/4} and Mindlin's spring
    ks_ratio K √δ [N/m] (the linear law's ratios to the local stiffness K √δ).

    As for the linear law, the dashpot is sized so the stepped contact loses what
    the closed form loses: at the local stiffness k_loc = (3/2) K √δ the contact
    is a linear one of damping ratio ζ_loc = c / (2√1.5) (damping_table) and
    frequency √(k_loc / m_eff), so η δ^{1/4} = √(k_loc m_eff) Σ damp[mi, mj, i] a^i,
    with a = √(SIZING_STIFFNESS K √δ / m_eff) dt (η → c √(m_eff K) as dt → 0;
    with dt = 0, that limit)."""
    root = sqrt(k / inv_mass_sum)           # √(K m_eff)
    if overlap <= 0.0:                      # the step after the contact (normal_force)
        return k, 1.224744871391589 * root * damp[mi, mj, 0], 0.0, 0.0
    r = sqrt(overlap)
    q = sqrt(r)
    a = sqrt(SIZING_STIFFNESS * k * r * inv_mass_sum) * dt
    eta = 1.224744871391589 * root * (damp[mi, mj, 0] + a * (damp[mi, mj, 1]
                                                             + a * damp[mi, mj, 2]))
    return k, eta, kt_ratio * root * q, ks_ratio * k * r


def damping_table(c) -> np.ndarray:
    """The (M, M, DAMP_TERMS) table the kernels' contact_coefficients read: the
    linear law's damping_series at ζ_loc = c / (2√1.5) for each material pair's
    Tsuji constant c (``c``, (M, M))."""
    c = np.asarray(c, dtype=np.float64)
    out = np.zeros(c.shape + (DAMP_TERMS,))
    for ij in np.ndindex(c.shape):
        out[ij] = damping_series(float(c[ij]) / (2.0 * math.sqrt(1.5)))
    return out


def normal_force(k, eta, overlap, un, dt, vc):
    """Normal force along n on sphere i [N]: the spring -K δ^{3/2} and the dashpot
    η δ^{1/4} u_n (negative pushes i away), the dashpot taken as the exact
    integral over the step, as the linear law's is: its impulse is
    -η ∫ δ⁺^{1/4} dδ = -(4/5) η (δ⁺^{5/4} - δ_prev⁺^{5/4}) with δ_prev = δ + u_n dt,
    which is η δ^{1/4} u_n dt inside a contact, covers the part of the step the
    contact began in, and the step after it ended (``closing``). An onset or end
    slower than ``vc`` [m/s] (a resting contact, as for the linear law) takes the
    plain η δ^{1/4} u_n."""
    hi = overlap if overlap > 0.0 else 0.0
    prev = overlap + un * dt
    lo = prev if prev > 0.0 else 0.0
    if (hi == 0.0 or lo == 0.0) and un * un <= vc * vc:   # a slow onset or end
        return -k * hi * sqrt(hi) + eta * sqrt(sqrt(hi)) * un
    fd = -0.8 * eta * (hi * sqrt(sqrt(hi)) - lo * sqrt(sqrt(lo))) / dt
    return -k * hi * sqrt(hi) + fd


def closing(overlap, un, dt):
    """Whether a contact apart by -``overlap`` [m] (≤ 0) was still touching one
    step ago (δ + u_n dt > 0): the step in which normal_force applies the end of
    its dashpot."""
    return overlap + un * dt > 0.0


#: The functions the kernels compile from this law (callees first).
KERNEL = ("contact_coefficients", "normal_force", "closing")
