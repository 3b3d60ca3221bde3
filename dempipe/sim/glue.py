"""Glue: the bonds between the pieces of a fractured shape, found at build time.

The pieces of one fractured instance partition one parent sphere lattice
(spheres/pieces.py), so the spheres of two neighbouring pieces that face each
other across their cut touch at exactly the diameter d. A *bond* is all such
sphere pairs between two pieces (bodies) with the same glue id; each pair is a
spring and dashpot, normal and shear (physics.glue_force), and the bond breaks,
for good, the first step one of its pairs carries an elastic load above the
glue's strength times d² (docs/physics.md, "Glue"). While it holds, ordinary
contacts between its sphere pairs do not act (kernels/glue.py).

The bond's stiffness K [N/m] is the whole bond's, shared equally by its n sphere
pairs (k = K/n each, the way a contact patch shares its spring:
kernels/patches.py): by default the law's stiffness of a contact between the two
pieces (K = m ω², ω the law's contact frequency for the reduced mass m at the
scene's impact speed), so a bond is no stiffer than a contact and the auto step
does not shrink; its dashpot gives the bond's translation the damping ratio
``glue_damping`` (eta = 2 ζ √(K m) / n), less where the step could not keep a
piece's dashpots stable (cap_dashpots).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from dempipe.errors import SceneError

#: Sphere pairs of two glued pieces within this many diameters (centre to centre)
#: are bonded: a lattice's face neighbours sit at d, its next neighbours at √2 d.
BOND_REACH = 1.05

#: Relative tolerance below d within which glued spheres count as touching, not
#: overlapping (the pieces' spheres come from one lattice: exactly d up to rounding).
TOUCH_TOLERANCE = 1e-9

#: Default damping ratio of a bond's translation (glue_damping): a load applied at
#: once overshoots by exp(-π ζ / √(1 - ζ²)) = 4.6 % (a hanging piece's bond sees at
#: most 1.046 times its weight's share). Critical damping (1) would not overshoot, but
#: a piece with several bonds is then more often damped less (cap_dashpots).
GLUE_DAMPING = 0.7

#: A body's bond dashpots times dt stay below this multiple of its corner mass
#: (dashpot_step). Explicit damping of one mass is stable below 2; measured on a wall
#: of 3 x 3 glued cubes of 2 x 2 x 2 spheres on the ground, glue_damping 1: stable at
#: 1.5, unstable at 1.95 (it explodes within a frame): 1 keeps a factor 2.
DASHPOT_STEP = 1.0


@dataclass(frozen=True, eq=False)
class Bonds:
    """A Model's glue, as frozen arrays (P sphere pairs, N bonds, B bodies).

    pair_i, pair_j : (P,) int32 the two spheres of each pair (pair_i < pair_j),
        pairs of one bond consecutive, bonds in order
    pair_rest : (P,) float64 rest length of each pair [m] (its distance when glued)
    bond_start : (N + 1,) int32, pairs of bond n are bond_start[n]:bond_start[n+1]
    bond_body : (N, 2) int32, the two bodies of each bond (lower index first)
    bond_k : (N,) float64 spring of each of the bond's pairs [N/m] (K / n)
    bond_eta : (N,) float64 dashpot of each of the bond's pairs [N s/m]
    bond_limit : (N,) float64 the largest elastic load a pair carries [N] (σ d²)
    body_bond_start : (B + 1,) int32, body_bond : (E,) int32: the bonds of each
        body, in bond order
    """

    pair_i: np.ndarray
    pair_j: np.ndarray
    pair_rest: np.ndarray
    bond_start: np.ndarray
    bond_body: np.ndarray
    bond_k: np.ndarray
    bond_eta: np.ndarray
    bond_limit: np.ndarray
    body_bond_start: np.ndarray
    body_bond: np.ndarray

    @property
    def n_bonds(self) -> int:
        return int(self.bond_body.shape[0])

    @property
    def n_pairs(self) -> int:
        return int(self.pair_i.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of the Model's bond arrays."""
        return int(sum(getattr(self, f).nbytes for f in self.__dataclass_fields__))


def no_bonds(n_bodies_all: int) -> Bonds:
    """The Bonds of a scene without glue."""
    z = lambda dt: np.zeros(0, dtype=dt)
    return Bonds(z(np.int32), z(np.int32), z(np.float64), np.zeros(1, np.int32),
                 np.zeros((0, 2), np.int32), z(np.float64), z(np.float64), z(np.float64),
                 np.zeros(n_bodies_all + 1, np.int32), z(np.int32))


def find_pairs(sphere_x, sphere_body, body_glue, diameter: float, where: str = "bodies"):
    """Sphere pairs of different bodies with the same glue id (body_glue ≥ 0) whose
    centres are within [d (1 - TOUCH_TOLERANCE), BOND_REACH d].

    sphere_x (S, 3) world centres [m]; sphere_body (S,); body_glue (B,) int (-1: none).
    Returns (i, j, dist) arrays sorted by (body pair, i, j), i < j. Glued spheres
    closer than d are refused (SceneError naming ``where``): a glued body must start
    as its lattice left it.
    """
    from scipy.spatial import cKDTree

    body_glue = np.asarray(body_glue)
    sphere_body = np.asarray(sphere_body)
    glued = np.flatnonzero(body_glue[sphere_body] >= 0)
    empty = (np.zeros(0, np.int64),) * 2 + (np.zeros(0),)
    if glued.size == 0:
        return empty
    x = np.asarray(sphere_x, dtype=np.float64)[glued]
    pairs = cKDTree(x).query_pairs(BOND_REACH * diameter, output_type="ndarray")
    if pairs.size == 0:
        return empty
    i, j = glued[pairs[:, 0]], glued[pairs[:, 1]]
    bi, bj = sphere_body[i], sphere_body[j]
    keep = (bi != bj) & (body_glue[bi] == body_glue[bj])
    i, j = np.minimum(i, j)[keep], np.maximum(i, j)[keep]
    dist = np.linalg.norm(np.asarray(sphere_x)[j] - np.asarray(sphere_x)[i], axis=1)
    close = dist < diameter * (1.0 - TOUCH_TOLERANCE)
    if close.any():
        k = int(np.argmax(close))
        raise SceneError(
            f"{where}: glued pieces overlap: spheres {int(i[k])} and {int(j[k])} of bodies "
            f"{int(sphere_body[i[k]])} and {int(sphere_body[j[k]])} are {dist[k]:.6g} m "
            f"apart, less than the diameter {diameter:g} m (place glued pieces as their "
            f"fracture left them, or remove glue)")
    b0 = np.minimum(sphere_body[i], sphere_body[j])
    b1 = np.maximum(sphere_body[i], sphere_body[j])
    order = np.lexsort((j, i, b1, b0))
    return i[order], j[order], dist[order]


def build_bonds(i, j, dist, sphere_body, n_bodies_all: int, stiffness, damping,
                limit) -> Bonds:
    """The Bonds of the pairs (i, j, dist) from find_pairs.

    stiffness(b0, b1) -> K [N/m] of the bond between bodies b0 < b1 (the whole bond);
    damping(b0, b1, K) -> the bond's dashpot [N s/m] (the whole bond);
    limit(b0, b1) -> the largest elastic load of one sphere pair [N].
    """
    sphere_body = np.asarray(sphere_body)
    if len(i) == 0:
        return no_bonds(n_bodies_all)
    b0 = np.minimum(sphere_body[i], sphere_body[j])
    b1 = np.maximum(sphere_body[i], sphere_body[j])
    new = np.ones(len(i), bool)
    new[1:] = (b0[1:] != b0[:-1]) | (b1[1:] != b1[:-1])
    first = np.flatnonzero(new)
    start = np.append(first, len(i)).astype(np.int32)
    bond_body = np.stack([b0[first], b1[first]], axis=1).astype(np.int32)
    n = np.diff(start).astype(np.float64)
    K = np.array([stiffness(int(a), int(b)) for a, b in bond_body])
    eta = np.array([damping(int(a), int(b), k) for (a, b), k in zip(bond_body, K)])
    lim = np.array([limit(int(a), int(b)) for a, b in bond_body])
    # each body's bonds, in bond order
    ends = np.concatenate([bond_body[:, 0], bond_body[:, 1]])
    ids = np.concatenate([np.arange(len(first)), np.arange(len(first))])
    order = np.lexsort((ids, ends))
    counts = np.bincount(ends, minlength=n_bodies_all)
    body_start = np.zeros(n_bodies_all + 1, np.int32)
    body_start[1:] = np.cumsum(counts)
    return Bonds(i.astype(np.int32), j.astype(np.int32), np.asarray(dist, np.float64),
                 start, bond_body, K / n, eta / n, lim, body_start,
                 ids[order].astype(np.int32))


def bond_damping(K: float, m_red: float, zeta: float) -> float:
    """The dashpot [N s/m] that gives a spring K [N/m] on the reduced mass m_red [kg]
    the damping ratio ζ."""
    return 2.0 * zeta * math.sqrt(K * m_red) if m_red > 0 and math.isfinite(m_red) else 0.0


def bond_energy(bonds: Bonds, state, sphere_x) -> float:
    """Elastic energy stored in the unbroken bonds [J]: ½ k (|r| - rest)² + ½ k |s|²
    per pair (sphere_x: the spheres' world centres [m])."""
    if bonds.n_pairs == 0:
        return 0.0
    r = np.linalg.norm(sphere_x[bonds.pair_j] - sphere_x[bonds.pair_i], axis=1)
    bond = np.repeat(np.arange(bonds.n_bonds), np.diff(bonds.bond_start))
    k = bonds.bond_k[bond]
    alive = state.bond_broken[bond] == 0
    s2 = (state.bond_shear ** 2).sum(axis=1)
    return float((0.5 * k * ((r - bonds.pair_rest) ** 2 + s2))[alive].sum())


def dashpot_step(bonds: Bonds, corner_mass) -> float:
    """The longest step [s] at which the bonds' dashpots stay stable: for every body
    with bonds, DASHPOT_STEP × its corner mass m / (1 + m (r×n)ᵀ I⁻¹ (r×n)) [kg]
    (``corner_mass``, (B,), inf for static ones) over Σ eta of its bonds' dashpots
    (each bond's whole: n pairs × bond_eta [N s/m]); inf without bonds."""
    if bonds.n_bonds == 0:
        return math.inf
    eta = bonds.bond_eta * np.diff(bonds.bond_start)
    total = np.zeros(np.asarray(corner_mass).shape[0])
    np.add.at(total, bonds.bond_body[:, 0], eta)
    np.add.at(total, bonds.bond_body[:, 1], eta)
    with np.errstate(divide="ignore", invalid="ignore"):
        step = DASHPOT_STEP * np.asarray(corner_mass) / total
    step = step[(total > 0) & np.isfinite(step)]
    return float(step.min()) if step.size else math.inf


def bond_omega(bonds: Bonds, corner_mass) -> float:
    """The stiffest bond's frequency [rad/s]: √(K (1/m_a + 1/m_b)) over the bonds, K the
    whole bond's spring, m the bodies' corner masses [kg] (``corner_mass``, (B,), inf for
    static and kinematic ones), as a contact's (ModelBuilder.finalize); 0 without bonds."""
    if bonds.n_bonds == 0:
        return 0.0
    inv = 1.0 / np.asarray(corner_mass, np.float64)
    K = bonds.bond_k * np.diff(bonds.bond_start)
    w2 = K * (inv[bonds.bond_body[:, 0]] + inv[bonds.bond_body[:, 1]])
    return float(np.sqrt(w2.max()))


def cap_dashpots(bonds: Bonds, corner_mass, dt: float) -> Bonds:
    """``bonds`` with each dashpot lowered where needed so that every body's, summed
    over its bonds, times ``dt`` [s] stays below DASHPOT_STEP × its corner mass
    (dashpot_step): a bond takes the smaller of its two bodies' factors. The springs,
    hence the step, are unchanged; a piece with many stiff bonds is damped less than
    glue_damping asks (dempipe check reports how many)."""
    if bonds.n_bonds == 0:
        return bonds
    eta = bonds.bond_eta * np.diff(bonds.bond_start)
    total = np.zeros(np.asarray(corner_mass).shape[0])
    np.add.at(total, bonds.bond_body[:, 0], eta)
    np.add.at(total, bonds.bond_body[:, 1], eta)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(total * dt > DASHPOT_STEP * np.asarray(corner_mass),
                          DASHPOT_STEP * np.asarray(corner_mass) / (total * dt), 1.0)
    f = np.minimum(factor[bonds.bond_body[:, 0]], factor[bonds.bond_body[:, 1]])
    if (f >= 1.0).all():
        return bonds
    return replace(bonds, bond_eta=bonds.bond_eta * np.minimum(f, 1.0))
