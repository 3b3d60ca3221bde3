"""A heavy body on a light material's auto spring: how deep its contact takes it.

``stability.soft_contact`` takes one contact stopping the heaviest corner-contact
mass m_c at the closing speed v: it sinks v √(m_c / k). A body landing flat is no
stiffer: its face is one contact patch of stiffness k however many of its spheres
touch (kernels/patches.py), so no sharing of the load saves it. When that depth
passes the bake's overlap guard, the bake stops (a density ratio of 1e6 under auto
stiffness: "sinks 1414 %", then the guard). ``sinking`` is that depth; `dempipe
check` and the bake make it an error. NumPy only.
"""

from __future__ import annotations

import math

import numpy as np

from dempipe.check.stability import OVERLAP_ERROR


def sinking(model, closing: float) -> tuple[float, int, int, int]:
    """(the depth the worst pair reaches, one patch stopping its heavy body, as a
    fraction of the diameter; that body; its material; the partner material).
    (0, -1, -1, -1) when nothing sinks."""
    n = model.n_bodies
    if n == 0 or closing <= 0.0:
        return 0.0, -1, -1, -1
    d = float(model.diameter)
    mass = np.asarray(model.body_corner_mass)    # m / (1 + f), as auto stiffness takes it
    moving = np.ones(n, bool)
    if model.body_kinematic is not None:
        moving &= ~np.asarray(model.body_kinematic[:n], bool)
    dyn_mat = np.asarray(model.body_material[:n])
    partners = set(np.asarray(model.wall_material).tolist()) | set(
        np.asarray(model.body_material[n:]).tolist()) | set(dyn_mat[moving].tolist())
    best = (0.0, -1, -1, -1)
    for b in np.flatnonzero(moving):
        mi = int(dyn_mat[b])
        for mj in partners:
            k = float(model.pair_k[mi, mj])
            depth = closing * math.sqrt(mass[b] / k) / d if k > 0 else math.inf
            if depth > best[0]:
                best = (depth, int(b), mi, int(mj))
    return best


def sinks_through(model, closing: float) -> bool:
    """Whether :func:`sinking` passes the overlap guard's limit (OVERLAP_ERROR)."""
    return sinking(model, closing)[0] > OVERLAP_ERROR
