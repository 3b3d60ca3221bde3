"""Contact laws: one module per law, registered by name.

A law module provides the host functions the model, the stability report, the
build and the simulator derive from it (damping from restitution, stiffness for
a target overlap, the contact frequency and critical step, the elastic energy)
and plain ``KERNEL`` functions the contact kernels compile for both targets
(kernels/compile.py). Every caller asks ``law(name)``; nothing else assumes a
linear spring. ``Model.contact_law`` names the scene's law.
"""

from __future__ import annotations

from types import ModuleType

from dempipe.sim.laws import hertz, linear

#: name -> law module.
LAWS: dict[str, ModuleType] = {linear.NAME: linear, hertz.NAME: hertz}

#: The law a scene uses unless it says otherwise.
DEFAULT = linear.NAME

#: Model.onset_speed as a fraction of the scene's fastest impact: contacts that
#: begin or end slower are resting ones, whose onset and end the laws leave
#: unresolved (laws.linear.normal_force says why). Small enough that a bounce at a
#: tenth of the fastest impact with e ≥ 0.1 is resolved at both ends; above the
#: flicker of a pile's lightly loaded contacts.
ONSET_SPEED_FRACTION = 0.01


def law(name: str = DEFAULT) -> ModuleType:
    """The law module registered as ``name`` (KeyError naming the known ones)."""
    try:
        return LAWS[name]
    except KeyError:
        raise KeyError(f"unknown contact law {name!r} (known: {', '.join(sorted(LAWS))})") \
            from None


def stiffest(contacts, law_name: str = DEFAULT,
             speed: float = 1.0) -> tuple[float, float, float]:
    """(ω_max, ζ_min, ζ_max) over ``contacts``, an iterable of (k, m_eff, ζ): the
    stiffest contact frequency [rad/s] and the extreme damping ratios. The one
    derivation ``ModelBuilder.finalize`` (dt) and ``stability.pair_stability`` (the
    report) share; (0, 1, 0) when there is no contact. ``speed``: the fastest
    impact [m/s], for laws whose frequency depends on it (Hertz)."""
    lw = law(law_name)
    omega_max, zeta_min, zeta_max = 0.0, 1.0, 0.0
    for k, m_eff, zeta in contacts:
        omega_max = max(omega_max, lw.omega(k, m_eff, speed))
        zeta_min = min(zeta_min, zeta)
        zeta_max = max(zeta_max, zeta)
    return omega_max, zeta_min, zeta_max
