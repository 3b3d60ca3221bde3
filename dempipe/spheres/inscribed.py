"""Inscribed balls and rings: how a surface set meets a wall as smoothly as its mesh.

A surface set's shell spheres sit at depth r = d/2 under the mesh, a spacing h apart
(spheres/surface.py). Against a plane, the set's envelope dips between them: where the
body's lowest point falls between two centres, neither sphere reaches the plane as
deep as the surface would, by up to κ ρ²/2 (κ the curvature of the offset surface,
ρ ≤ h the distance to the nearest centre). A ball rolling across those dips rides
over a polygon of corners of radius r: past √(g R) it hops from sphere to sphere and
each landing loses what the restitution takes.

So each shell sphere also carries its osculating torus inside the mesh: a circle of
radius a about an axis, swept by a tube of radius b, touching the surface where the
sphere does with the surface's two curvatures there (b = r + 1/κ2, a + b = r + 1/κ1,
κ1 ≥ κ2 the principal curvatures of the offset surface, fitted to the sphere's shell
neighbours), the tube held inside the shell (a shrinking-ball test) and to
RHO_MAX_SHARE of the shape's smallest extent. On a ball it is the ball; on a
cylinder's side the cross-section, or near a cap the ring about the axis through the
sphere. A wall contact takes the torus's overlap at its point lowest towards the wall
(kernels/contacts.py inscribed_wall), never more than INSCRIBED_REACH d beyond the
sphere's own, which bounds what a torus fitted badly could add. Edge and corner
spheres (a fit across an edge is no surface), interior and thin-part spheres and every
lattice set keep their own sphere. docs/physics.md, "Round bodies on walls".
"""

from __future__ import annotations

import numpy as np

#: Shell spheres: centres within this share of r of depth r under the mesh.
SHELL_TOLERANCE = 0.02
#: Neighbours (the sphere itself included) each shell sphere's quadric is fitted to.
FIT_NEIGHBOURS = 32
#: A torus's tube radius is at most this share of the shape's smallest extent (its
#: bounding box's, body frame): a ball's own radius, a box's half side.
RHO_MAX_SHARE = 0.5
#: A fit whose RMS residual exceeds this [d], or whose tangent plane leans more than
#: this [rad] from the closest point's normal, spans an edge: no torus.
FIT_RESIDUAL = 0.01
FIT_TILT = 0.2
#: The offset surface of a faceted mesh is faceted: a torus's tube may reach this
#: far [d] past its neighbouring centres (a wall contact never takes more than
#: pairing.INSCRIBED_REACH beyond the sphere's own).
SHRINK_SLACK = 0.05


#: Columns of a sphere's row (inscribed_tori): the vector from the sphere's centre to
#: the torus's centre (3), its axis (3), the direction from its centre to the tube's
#: centre under the sphere (3), the circle's radius a, the tube's radius b [m], unused.
COLUMNS = 12
#: A circle larger than this many times the shape's largest extent is a straight line
#: to the contact: the sphere takes a ball instead.
CIRCLE_MAX_SHARE = 4.0


def inscribed_tori(centers, diameter: float, vertices, faces) -> np.ndarray:
    """(N, COLUMNS) per sphere of ``centers`` (body frame [m], the set's order): its
    osculating torus, the torus inside the mesh that touches the surface where the
    sphere does with the surface's two curvatures there: a circle of radius a about an
    axis, swept by a tube (a ball) of radius b. A ball's spheres get the ball (a = 0),
    a cylinder's side spheres its cross-section (a = 0, b = R) or, near a cap, the
    ring of radius R − b through them; a flat face's a ball held clear of its edges.
    Where the sphere is its own (not on the shell, on an edge, a thin part), the row
    is (0, ..., 0, b = d/2, 0). Body frame, [m]."""
    # scipy and the numba mesh queries load here, when a surface set is built into a model
    from scipy.spatial import cKDTree

    from dempipe.spheres.surface import MeshQueries

    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    r = 0.5 * float(diameter)
    out = np.zeros((c.shape[0], COLUMNS))
    out[:, 10] = r
    v = np.asarray(vertices, dtype=np.float64)
    if c.shape[0] < FIT_NEIGHBOURS or v.shape[0] == 0:
        return out
    dist, q = MeshQueries(v, faces, 2.0 * diameter).closest(c)
    shell = np.flatnonzero(np.abs(dist - r) <= SHELL_TOLERANCE * r)
    if shell.size < FIT_NEIGHBOURS:
        return out
    cs = c[shell]
    n = (q[shell] - cs) / dist[shell, None]           # outward, from the closest point
    _, nb = cKDTree(cs).query(cs, k=FIT_NEIGHBOURS)
    rel = cs[nb] - cs[:, None, :]                     # (M, K, 3)
    # a tangent frame per sphere
    pick = np.where(np.abs(n[:, 0:1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(n, pick)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(n, e1)
    u = np.einsum("mkj,mj->mk", rel, e1)
    w = np.einsum("mkj,mj->mk", rel, e2)
    z = -np.einsum("mkj,mj->mk", rel, n)              # depth under the tangent plane
    # z = α u + β w + (A u² + 2 B u w + C w²) / 2, least squares per sphere
    basis = np.stack([u, w, 0.5 * u * u, u * w, 0.5 * w * w], axis=2)   # (M, K, 5)
    ata = np.einsum("mki,mkj->mij", basis, basis)
    atz = np.einsum("mki,mk->mi", basis, z)
    scale = np.einsum("mii->m", ata)[:, None, None] * 1e-12
    coef = np.linalg.solve(ata + scale * np.eye(5)[None], atz[..., None])[..., 0]
    alpha, beta, A, B, C = coef.T
    # a quadric fitted across an edge (a cylinder's rim, a box's edges) is no surface:
    # those spheres keep their own ball
    resid = z - np.einsum("mki,mi->mk", basis, coef)
    smooth = (np.sqrt(np.mean(resid * resid, axis=1)) <= FIT_RESIDUAL * diameter) & (
        alpha * alpha + beta * beta <= FIT_TILT * FIT_TILT)
    # principal curvatures of the offset surface, k1 ≥ k2, and k1's direction
    half = np.sqrt(0.25 * (A - C) ** 2 + B * B)
    k1 = 0.5 * (A + C) + half
    k2 = 0.5 * (A + C) - half
    phi = 0.5 * np.arctan2(2.0 * B, A - C)
    normal = n + alpha[:, None] * e1 + beta[:, None] * e2
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    d1 = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    d1 -= np.einsum("mj,mj->m", d1, normal)[:, None] * normal
    d1 /= np.linalg.norm(d1, axis=1)[:, None]
    extent = v.max(axis=0) - v.min(axis=0)

    def radius(k):                                    # r + 1/k of the mesh, inf if k ≤ 0
        with np.errstate(divide="ignore"):
            return np.where(k > 0.0, r + 1.0 / np.where(k > 0.0, k, 1.0), np.inf)

    # the tube: the surface's smaller radius, inside the shell (the shrinking-ball bound:
    # a face's sphere near an edge is held to the edge's distance, which the fit over a
    # flat face cannot see), at most RHO_MAX_SHARE of the smallest extent
    b = np.minimum(radius(k2), RHO_MAX_SHARE * float(extent.min()))
    b = np.minimum(b, r + _shrinking_ball(cs, -normal, SHRINK_SLACK * diameter))
    # the circle: the surface's larger radius R1 = a + b along d1
    r1 = radius(k1)
    b = np.minimum(b, r1)
    ring = np.isfinite(r1) & (r1 <= CIRCLE_MAX_SHARE * float(extent.max())) & (r1 - b > 1e-9 * r)
    a = np.where(ring, r1 - b, 0.0)
    centre = -(np.where(ring, r1, b) - r)[:, None] * normal     # inward: the circle's centre
    grow = smooth & ((b > r * (1.0 + 1e-9)) | ring)
    rows = shell[grow]
    out[rows, 0:3] = centre[grow]
    out[rows, 3:6] = np.where(ring[grow, None], np.cross(normal[grow], d1[grow]), 0.0)
    out[rows, 6:9] = np.where(ring[grow, None], normal[grow], 0.0)
    out[rows, 9] = a[grow]
    out[rows, 10] = b[grow]
    return out


def _shrinking_ball(points, inward, tau) -> np.ndarray:
    """Per point p_i with inward unit normal m_i: the radius ρ of the largest ball
    tangent at p_i (centre p_i + ρ m_i) that holds no other point deeper than ``tau``
    inside it (surface.shrinking_ball)."""
    from dempipe.spheres.surface import shrinking_ball

    out = np.empty(points.shape[0])
    shrinking_ball(np.ascontiguousarray(points, dtype=np.float64),
                   np.ascontiguousarray(inward, dtype=np.float64), float(tau), out)
    return out
