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
