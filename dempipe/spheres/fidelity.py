"""How closely a sphere set follows its mesh: volume and inertia of the set against the
exact mesh, and a two-sided Hausdorff estimate between the mesh surface and the
*contact surface* of the sphere union (the part of the spheres' surface another sphere
of the same diameter can touch). Lengths in metres; errors as fractions of the shape's
size."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Points sampled on the mesh surface (area-weighted, seeded) for the Hausdorff estimate.
MESH_SAMPLES = 2000
#: Directions sampled on each sphere (Fibonacci lattice) for the sphere-union surface;
#: neighbouring samples are ~0.11 d apart.
SPHERE_DIRECTIONS = 256
#: At most this many sphere-surface samples are measured against the mesh triangles.
SURFACE_SAMPLES = 2000


@dataclass(frozen=True)
class GeometryError:
    """One shape's sphere set against its mesh.

    spheres : sphere count
    volume : (N d³ − V) / V, the lattice cells against the mesh volume
    inertia : relative Frobenius error of the cells' inertia against the mesh's
    hausdorff : largest surface distance, either direction, / the shape's size
    mesh_to_spheres, spheres_to_mesh : the two one-sided parts of ``hausdorff``
    size : the shape's size, the longest extent of its bounding box [m]
    """

    spheres: int
    volume: float
    inertia: float
    hausdorff: float
    mesh_to_spheres: float
    spheres_to_mesh: float
    size: float


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (golden-angle spiral)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sample_surface(vertices, faces, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points on a triangle mesh, uniform by area (seeded, reproducible)."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    f = rng.choice(len(tri), size=n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1.0                      # fold the square onto the triangle
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[f]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def contact_surface(centers, diameter: float, n_dirs: int = SPHERE_DIRECTIONS) -> np.ndarray:
    """Points of the sphere union's surface that another sphere of diameter d can touch.

    Sphere sets are lattices of pitch d, so neighbouring spheres only touch: every
    sphere's whole surface belongs to the union, the buried ones included. What a
    contact sees is less: the point c + r n is touchable when a probe sphere at
    c + d n overlaps no other sphere. Only the 26 lattice neighbours can block it.
    Returns (P, 3) points [m].
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    d = float(diameter)
    dirs = fibonacci_directions(n_dirs)
    offs = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) != (0, 0, 0)], dtype=np.float64)
    # blocked[o, k]: a neighbour at lattice offset o stops a probe in direction k
    blocked = np.linalg.norm(dirs[None, :, :] - offs[:, None, :], axis=2) < 1.0 - 1e-9
    ijk = np.round((c - c.min(axis=0)) / d).astype(np.int64)
    occupied = {tuple(p) for p in ijk}
    has = np.array([[(p[0] + o[0], p[1] + o[1], p[2] + o[2]) in occupied for o in offs.astype(int)]
                    for p in ijk], dtype=bool)                               # (S, 26)
    free = ~(has.astype(np.int64) @ blocked.astype(np.int64)).astype(bool)  # (S, n_dirs)
    s, k = np.nonzero(free)
    return c[s] + 0.5 * d * dirs[k]


def point_mesh_distance(points, vertices, faces, chunk: int = 64) -> np.ndarray:
    """Unsigned distance from each point to a triangle mesh (exact) [m].

    For each triangle: the distance to its plane when the projection falls inside,
    else to the nearest of its three edges. Points go in chunks of ``chunk`` (pass
    them spatially ordered); a chunk only visits the triangles whose bounding box
    lies within its points' distance bound (the nearest vertex or edge midpoint).
    """
    p_all = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    verts = np.asarray(vertices, dtype=np.float64)
    tri_all = verts[np.asarray(faces, dtype=np.int64)]
    tri_lo, tri_hi = tri_all.min(axis=1), tri_all.max(axis=1)
    anchors = np.concatenate([verts, 0.5 * (tri_all + np.roll(tri_all, 1, axis=1)).reshape(-1, 3)])
    bound = point_set_distance(p_all, anchors)
    out = np.empty(len(p_all))
    for s in range(0, len(p_all), chunk):
        p = p_all[s:s + chunk]
        r = bound[s:s + chunk].max() * (1.0 + 1e-9)
        near = np.all((tri_lo <= p.max(axis=0) + r) & (tri_hi >= p.min(axis=0) - r), axis=1)
        out[s:s + chunk] = _points_triangles(p, tri_all[near])
    return out


def _points_triangles(p, tri) -> np.ndarray:
    """Distance from each point of p (P, 3) to the nearest of the triangles (F, 3, 3)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, bc = b - a, c - a, c - b
    n = np.cross(ab, ac)
    nn = np.einsum("fi,fi->f", n, n)
    good = nn > 1e-30
    n_unit = np.where(good[:, None], n / np.sqrt(np.where(good, nn, 1.0))[:, None], 0.0)
    d00 = np.einsum("fi,fi->f", ab, ab)
    d01 = np.einsum("fi,fi->f", ab, ac)
    d11 = np.einsum("fi,fi->f", ac, ac)
    den = np.where(good, d00 * d11 - d01 * d01, 1.0)

    def seg(ap, e):
        ee = np.einsum("fi,fi->f", e, e)
        t = np.clip(np.einsum("pfi,fi->pf", ap, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
        return np.linalg.norm(ap - t[..., None] * e, axis=2)

    ap = p[:, None, :] - a[None]
    d20 = np.einsum("pfi,fi->pf", ap, ab)
    d21 = np.einsum("pfi,fi->pf", ap, ac)
    v = (d11 * d20 - d01 * d21) / den       # barycentric coordinates of the projection
    w = (d00 * d21 - d01 * d20) / den
    inside = good & (v >= 0) & (w >= 0) & (v + w <= 1)
    plane = np.abs(np.einsum("pfi,fi->pf", ap, n_unit))
    edge = np.minimum(np.minimum(seg(ap, ab), seg(ap, ac)), seg(p[:, None, :] - b[None], bc))
    return np.where(inside, plane, edge).min(axis=1)


def point_set_distance(p, q, chunk: int = 256) -> np.ndarray:
    """Distance from each point of p to the nearest point of q (brute force)."""
    out = np.empty(len(p))
    qq = np.einsum("ij,ij->i", q, q)
    for s in range(0, len(p), chunk):
        x = p[s:s + chunk]
        d2 = np.einsum("ij,ij->i", x, x)[:, None] - 2.0 * x @ q.T + qq[None, :]
        out[s:s + chunk] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
    return out


#: A face lies along the lattice when its normal is within this angle [degrees] of one
#: of the lattice's axes (±x, ±y, ±z of the shape's frame, which the lattice shares).
AXIS_TOLERANCE_DEGREES = 5.0
#: A shape more than this share of whose area is off the lattice's axes is round for
#: the lattice (off_axis_share): it rests on terraces there and does not roll
#: (docs/spheres.md, "Rolling"). `dempipe check` names such lattice shapes
#: (round-lattice) and spheres = "auto" gives them surface sets (auto_mode).
ROUND_SHARE = 0.5


def off_axis_share(vertices, faces) -> float:
    """The share of a mesh's area whose normal is more than AXIS_TOLERANCE_DEGREES from
    every axis of the shape's frame: its curved or slanted surface, where a lattice
    sphere set (cells along those axes) can only follow the mesh in terraces. 0 for a
    box in its own axes, 0.99 for the built-in ball, 0.65 for the built-in cylinder
    (its flat ends lie along the axes), 0.58-0.88 for the chess pieces."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if f.shape[0] == 0:
        return 0.0
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = np.linalg.norm(n, axis=1)        # twice each face's area
    keep = area > 0.0
    if not keep.any():
        return 0.0
    unit = n[keep] / area[keep, None]
    along = np.abs(unit).max(axis=1) >= math.cos(math.radians(AXIS_TOLERANCE_DEGREES))
    return float(area[keep][~along].sum() / area[keep].sum())


def auto_mode(vertices, faces) -> str:
    """The sphere-set mode spheres = "auto" picks for a mesh: "surface" when it is
    round for the lattice (off_axis_share above ROUND_SHARE: a ball, a wheel, a torus,
    a chess piece), else "lattice" (a box, a brick: faces along the axes)."""
    return "surface" if off_axis_share(vertices, faces) > ROUND_SHARE else "lattice"


def mesh_beyond_spheres(centers, diameter: float, vertices, faces, *, samples: int = 2000,
                        seed: int = 0) -> float:
    """How far [m] the mesh reaches beyond its spheres: the largest distance from the
    union of the spheres of ``diameter`` at ``centers`` to ``samples`` area-weighted
    points of the mesh (0 where every point is inside a sphere). Where a shape touches
    something, the mesh looks sunk into it by up to this much. A slight underestimate
    (sampled); the mesh → spheres half of :func:`shape_geometry_error`'s Hausdorff."""
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    verts = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    tri = verts[faces]
    if not len(c) or not np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0],
                                                 tri[:, 2] - tri[:, 0]), axis=1).sum() > 0.0:
        return 0.0                  # no surface to compare (a shape given as spheres only)
    pts = sample_surface(verts, faces, samples, seed)
    return max(0.0, float((point_set_distance(pts, c) - 0.5 * float(diameter)).max()))


def shape_geometry_error(sphere_set, vertices, faces, *, seed: int = 0) -> GeometryError:
    """Errors of ``sphere_set`` against its mesh (``vertices`` in the body frame, i.e.
    mesh coordinates minus the centre of mass, as ``ShapeInstance.vertices``).

    Hausdorff estimate, both directions, as a fraction of the shape's size:
      mesh → spheres: MESH_SAMPLES area-weighted points on the mesh; a point outside
        every sphere is min |p − c| − r from the union (exact); one inside is taken
        to the nearest sample of the contact surface (:func:`contact_surface`).
      spheres → mesh: up to SURFACE_SAMPLES samples of the contact surface, exact
        distance to the mesh triangles.
    Sampling makes both a slight underestimate of a true maximum, and the inside
    points' distance an overestimate of at most half the sample spacing (~0.06 d).
    """
    verts = np.asarray(vertices, dtype=np.float64)
    c = np.asarray(sphere_set.centers, dtype=np.float64).reshape(-1, 3)
    d = float(sphere_set.diameter)
    size = float((verts.max(axis=0) - verts.min(axis=0)).max())
    surf = contact_surface(c, d)
    pts = sample_surface(verts, faces, MESH_SAMPLES, seed)
    outside = point_set_distance(pts, c) - 0.5 * d
    to_surface = point_set_distance(pts, surf) if len(surf) else np.full(len(pts), np.inf)
    a = np.where(outside > 0.0, outside, to_surface)
    rng = np.random.default_rng(seed + 1)
    if len(surf) > SURFACE_SAMPLES:     # sorted back: chunks stay spatially compact
        surf = surf[np.sort(rng.choice(len(surf), SURFACE_SAMPLES, replace=False))]
    pick = surf
    b = point_mesh_distance(pick, verts, faces) if len(pick) else np.zeros(1)
    return GeometryError(
        spheres=int(c.shape[0]), volume=float(sphere_set.sphere_volume_error),
        inertia=float(sphere_set.inertia_error), hausdorff=float(max(a.max(), b.max()) / size),
        mesh_to_spheres=float(a.max() / size), spheres_to_mesh=float(b.max() / size), size=size)
