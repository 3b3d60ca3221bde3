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

from . import linear

#: name -> law module.
LAWS: dict[str, ModuleType] = {linear.NAME: linear}

#: The law a scene uses unless it says otherwise.
DEFAULT = linear.NAME


def law(name: str = DEFAULT) -> ModuleType:
    """The law module registered as ``name`` (KeyError naming the known ones)."""
    try:
        return LAWS[name]
    except KeyError:
        raise KeyError(f"unknown contact law {name!r} (known: {', '.join(sorted(LAWS))})") \
            from None


def stiffest(contacts, law_name: str = DEFAULT) -> tuple[float, float, float]:
    """(ω_max, ζ_min, ζ_max) over ``contacts``, an iterable of (k, m_eff, ζ): the
    stiffest contact frequency [rad/s] and the extreme damping ratios. The one
    derivation ``ModelBuilder.finalize`` (dt) and ``stability.pair_stability`` (the
    report) share; (0, 1, 0) when there is no contact."""
    lw = law(law_name)
    omega_max, zeta_min, zeta_max = 0.0, 1.0, 0.0
    for k, m_eff, zeta in contacts:
        omega_max = max(omega_max, lw.omega(k, m_eff))
        zeta_min = min(zeta_min, zeta)
        zeta_max = max(zeta_max, zeta)
    return omega_max, zeta_min, zeta_max
