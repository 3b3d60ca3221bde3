"""Body placement: each body group expanded into its bodies' initial states.

    for p in expand_bodies(scene):          # one BodyPlacement per group
        p.positions, p.rotations, p.velocities, p.angular_velocities

Layouts "single", "grid", "random" and "emit"; random rotations and positions
are seeded from the scene's seed and independent per group, so adding a group
does not move the others. ``collider_frame`` and ``group_frame`` say what a
motion's keys are poses of. Positions place the mesh's own origin [m];
quaternions are (w, x, y, z).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Union

import numpy as np

from dempipe.scene.data import BodyGroup, BoxCollider, Collider, MeshCollider, Scene


@dataclass(frozen=True)
class BodyPlacement:
    """Initial state of every body of one group, from :func:`expand_bodies`."""

    name: str
    """Group name."""
    shape: Union[str, tuple]
    """Shape name, or a tuple of names cycled over the group's bodies."""
    material: str
    """Material name."""
    positions: np.ndarray
    """(n, 3) float64 mesh-origin positions [m], world frame."""

    def body_shapes(self) -> list:
        """Shape name of each body of the group."""
        names = (self.shape,) if isinstance(self.shape, str) else self.shape
        return [names[i % len(names)] for i in range(len(self.positions))]
    rotations: np.ndarray
    """(n, 4) float64 unit quaternions (w, x, y, z)."""
    velocities: np.ndarray
    """(n, 3) float64 linear velocities [m/s], world frame."""
    angular_velocities: np.ndarray
    """(n, 3) float64 angular velocities [rad/s], world frame."""
    start_times: np.ndarray | None = None
    """(n,) float64 [s]: when each body enters (layout "emit"), or None: the group's
    start_time for all."""


# ---------------------------------------------------------------------- expansion


def random_quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` uniformly distributed unit quaternions (w, x, y, z), Shoemake's method."""
    u1, u2, u3 = rng.random((3, n))
    a, b = np.sqrt(1.0 - u1), np.sqrt(u1)
    t2, t3 = 2.0 * np.pi * u2, 2.0 * np.pi * u3
    q = np.stack([b * np.cos(t3), a * np.sin(t2), a * np.cos(t2), b * np.sin(t3)], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def grid_offsets(dims, spacing, count: int, up_axis: str = "Z") -> np.ndarray:
    """(count, 3) world offsets of the first ``count`` lattice points.

    Fill order: first horizontal axis fastest, then the second, then up. With
    up_axis "Z" the lattice axes are (x, y, z); with "Y" they are (x, z, y).
    ``dims`` and ``spacing`` are in lattice order.
    """
    nx, ny, _ = (int(v) for v in dims)
    i = np.arange(count)
    lattice = np.stack([i % nx, (i // nx) % ny, i // (nx * ny)], axis=1).astype(np.float64)
    lattice *= np.asarray(spacing, dtype=np.float64)
    if up_axis == "Y":
        return lattice[:, [0, 2, 1]]
    return lattice


def collider_frame(c: Collider):
    """The authored frame of a collider, (origin (3,) [m], rotation (4,) w, x, y, z):
    what its motion's keys are absolute poses of and its rates' default pivot — a
    mesh's position and rotation, a plane's point, a box's centre (identity for
    both)."""
    if isinstance(c, MeshCollider):
        return np.asarray(c.position, np.float64), np.asarray(c.rotation, np.float64)
    if isinstance(c, BoxCollider):
        centre = 0.5 * (np.asarray(c.min, np.float64) + np.asarray(c.max, np.float64))
        return centre, np.array([1.0, 0.0, 0.0, 0.0])
    return np.asarray(c.point, np.float64), np.array([1.0, 0.0, 0.0, 0.0])


def group_frame(g: BodyGroup, placement: BodyPlacement):
    """The frame a kinematic group's motion moves, (origin (3,) [m], rotation (4,)):
    a single body's own pose (as placed: a "random" rotation drawn), a grid's
    ``origin``, a random region's centre (identity for both). Its rates' default
    pivot, and what a key without ``position`` / ``rotation`` stands at; pass it to
    ``motion.reference_anchor(motion, *frame, group=g.layout != "single")``."""
    if g.layout == "single":
        return (np.asarray(placement.positions[0], np.float64),
                np.asarray(placement.rotations[0], np.float64))
    if g.layout == "grid":
        return np.asarray(g.origin, np.float64), np.array([1.0, 0.0, 0.0, 0.0])
    lo, hi = np.asarray(g.region_min, np.float64), np.asarray(g.region_max, np.float64)
    return 0.5 * (lo + hi), np.array([1.0, 0.0, 0.0, 0.0])


def expand_bodies(scene: Scene) -> list[BodyPlacement]:
    """Per-body initial state of every group, in group order.

    Random placements and rotations of group i come from generators seeded with
    ``(seed, i, 0)`` and ``(seed, i, 1)``, so a group's bodies do not change when
    other groups, or its own rotation setting, change.
    """
    seed = scene.simulation.seed
    up = scene.output.up_axis
    out = []
    for gi, g in enumerate(scene.bodies):
        n = g.count
        if g.layout == "grid":
            pos = np.asarray(g.origin, np.float64) + grid_offsets(g.dims, g.spacing, n, up)
        elif g.layout in ("random", "emit"):
            rng = np.random.default_rng([seed, gi, 0])
            lo = np.asarray(g.region_min, np.float64)
            hi = np.asarray(g.region_max, np.float64)
            pos = lo + rng.random((n, 3)) * (hi - lo)
        else:
            pos = np.tile(np.asarray(g.position, np.float64), (n, 1))
        if g.rotation == "random":
            rot = random_quaternions(np.random.default_rng([seed, gi, 1]), n)
        elif g.rotation == "identity":
            rot = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (n, 1))
        else:
            rot = np.tile(np.asarray(g.rotation, np.float64), (n, 1))
        out.append(BodyPlacement(
            name=g.name, shape=g.shape, material=g.material,
            positions=np.ascontiguousarray(pos, dtype=np.float64),
            rotations=np.ascontiguousarray(rot, dtype=np.float64),
            velocities=np.tile(np.asarray(g.velocity, np.float64), (n, 1)),
            angular_velocities=np.tile(np.asarray(g.angular_velocity, np.float64), (n, 1)),
            start_times=(g.start_time + np.arange(n) / g.rate if g.layout == "emit" else None),
        ))
    return out


# ---------------------------------------------------------------------- fracture


@dataclass(frozen=True)
class PieceBodies:
    """A group's bodies with each fractured instance replaced by its pieces.

    placement: one body per piece (``shape``: one shape name per body), at the
        instance's pose; a piece moves with the instance as one rigid body would
        (v + ω × r from the instance's centre of mass to the piece's).
    labels: each body's name after its group's: "3" (whole) or "3_piece_07".
    instance: (n,) int, the group's body each comes from.
    glue: (n,) int, one id per fractured instance shared by its pieces (counted
        from ``glue_start``), -1 for a whole body.
    mass_share: (n,) float, the piece's share of its instance's volume (1: whole).
    """

    placement: BodyPlacement
    labels: tuple
    instance: np.ndarray
    glue: np.ndarray
    mass_share: np.ndarray


def split_into_pieces(placement: BodyPlacement, pieces: dict, glue_start: int = 0) -> PieceBodies:
    """``placement`` with every body of a fractured shape replaced by its pieces.

    pieces: shape name -> list of (piece shape name, centre of mass (3,) in the
    shape's own coordinates [m], volume [m^3]) for each fractured shape.
    """
    from dempipe.sim.model import quat_to_matrix

    shapes, labels, inst, glue, share = [], [], [], [], []
    rows = []
    next_glue = glue_start
    for i, name in enumerate(placement.body_shapes()):
        if name not in pieces:
            shapes.append(name)
            labels.append(str(i))
            inst.append(i)
            glue.append(-1)
            share.append(1.0)
            rows.append(np.zeros(3))
            continue
        parts = pieces[name]
        vol = np.array([p[2] for p in parts], np.float64)
        com = np.array([p[1] for p in parts], np.float64).reshape(-1, 3)
        parent_com = (vol[:, None] * com).sum(axis=0) / vol.sum()
        R = quat_to_matrix(placement.rotations[i])
        for k, (piece_name, c, v) in enumerate(parts):
            shapes.append(piece_name)
            labels.append(f"{i}_piece_{k:02d}")
            inst.append(i)
            glue.append(next_glue)
            share.append(float(v / vol.sum()))
            rows.append(R @ (np.asarray(c, np.float64) - parent_com))
        next_glue += 1
    inst = np.asarray(inst, np.int64)
    r = np.asarray(rows, np.float64).reshape(-1, 3)
    w = placement.angular_velocities[inst]
    new = BodyPlacement(
        name=placement.name, shape=tuple(shapes), material=placement.material,
        positions=placement.positions[inst], rotations=placement.rotations[inst],
        velocities=placement.velocities[inst] + np.cross(w, r), angular_velocities=w,
        start_times=None if placement.start_times is None else placement.start_times[inst])
    return PieceBodies(new, tuple(labels), inst, np.asarray(glue, np.int64),
                       np.asarray(share, np.float64))
