"""Sphere sets with exact mass properties, for physics tests that need no mesh.

A rectangular lattice of nx × ny × nz spheres of diameter d is the sphere set of
a box of size (nx d, ny d, nz d); a single sphere is that of a ball. Mass
properties here are the closed forms of those solids (per unit density), so
the physics tests depend on nothing but the simulation core.
"""

import math
import types

import numpy as np


def box_set(nx, ny, nz, d):
    """Sphere set of a box nx·d × ny·d × nz·d, centred on its centre of mass."""
    g = np.stack(np.meshgrid((np.arange(nx) - (nx - 1) / 2) * d, (np.arange(ny) - (ny - 1) / 2) * d,
                             (np.arange(nz) - (nz - 1) / 2) * d, indexing="ij"), -1).reshape(-1, 3)
    a, b, c = nx * d, ny * d, nz * d
    V = a * b * c
    inertia = V / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    ss = types.SimpleNamespace(centers=g, com=np.zeros(3), volume=V, inertia=inertia, diameter=d,
                               notes=())
    mesh = types.SimpleNamespace(
        vertices=np.array([[sx * a / 2, sy * b / 2, sz * c / 2] for sx in (-1, 1) for sy in (-1, 1)
                           for sz in (-1, 1)]),
        faces=np.array([[0, 1, 3]]))
    return ss, mesh


def ball_set(d):
    """One sphere: a solid ball of diameter d (I = 2/5 m r²)."""
    V = math.pi / 6.0 * d**3
    ss = types.SimpleNamespace(centers=np.zeros((1, 3)), com=np.zeros(3), volume=V,
                               inertia=np.eye(3) * 0.4 * V * (d / 2) ** 2, diameter=d,
                               notes=())
    mesh = types.SimpleNamespace(vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]]))
    return ss, mesh


def slider_past_drifting_row(d, n_row, gap, speed, n_frames):
    """The Model of a pile where few bodies move: n_row boxes of 2 × 2 × 2 spheres of
    diameter d [m], 0.022 m apart along x, drifting at 1-3 mm/s on a frictionless
    floor, and one frictionless box (the last body) sliding along x at ``speed``
    [m/s] from x = -0.05 m, (2 + gap) d from the row's centre line (gap 0.1: inside
    the lists' reach, never touching; below 0: scraping the row). 24 fps."""
    from dempipe.sim.builder import ModelBuilder
    from dempipe.sim.materials import Material

    b = ModelBuilder(d)
    ss, mesh = box_set(2, 2, 2, d)
    s = b.add_shape("box", mesh, ss)
    wood = b.add_material(Material("wood", density=700, restitution=0.3, friction=0.5))
    ice = b.add_material(Material("ice", density=700, restitution=0.3, friction=0.0))
    b.add_bodies("row", s, wood, [[0.022 * i, 0.0, d] for i in range(n_row)],
                 velocities=[[0.002 * (1 + i % 3), 0.001 * (i % 2), 0.0]
                             for i in range(n_row)])
    b.add_bodies("slider", s, ice, [[-0.05, (2 + gap) * d, d]], velocities=[[speed, 0.0, 0.0]])
    b.add_plane([0, 0, 0], [0, 0, 1], ice)
    return b.finalize(fps=24, n_frames=n_frames)


def rotation_matrix(q):
    """The rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def body_energy(model, frames, g: float = 9.81) -> np.ndarray:
    """Kinetic plus potential energy [J] of body 0 at each frame (gravity g along -z;
    the contact springs' energy is left out)."""
    m = float(model.body_mass[0])
    s = model.body_inv_inertia[0]
    inertia = np.linalg.inv(np.array([[s[0], s[3], s[4]], [s[3], s[1], s[5]],
                                      [s[4], s[5], s[2]]]))
    out = []
    for x, q, v, w in zip(frames.x[:, 0], frames.q[:, 0], frames.v[:, 0], frames.w[:, 0]):
        R = rotation_matrix(q)
        out.append(0.5 * m * v @ v + 0.5 * w @ (R @ inertia @ R.T) @ w + m * g * x[2])
    return np.array(out)
