"""Surface-following sphere sets: equal spheres whose envelope is the mesh surface.

The lattice builder (spheres.py) keeps the cells of a lattice of pitch d that lie
inside the mesh, so a round body becomes a polyhedron of facets a diameter wide: a
cylinder on its side rests on a face and does not roll. Here the spheres (all of the
one diameter d = 2r, so the uniform grid and its 27-cell search are unchanged) are put
where the surface is:

1. **Shell.** Sphere centres on the inward offset of the mesh surface at distance r
   (the level set sdf = -r), so every shell sphere touches the surface from inside and
   their outer envelope is the surface, rounded with radius r at convex edges (a ball of
   radius r cannot reach further into a sharp corner). Candidates: points of the mesh
   surface spread over every triangle h/3 apart (grid_samples), each moved by r along
   its face's inward normal and then projected onto the level set (c <- q + r (c - q)/
   |c - q|, q the closest point of the mesh; a few iterations), which also puts
   candidates near concave edges onto the offset's rounded part; kept where it settles
   at depth r inside the body.
2. **Thin parts.** Where the body is thinner than d there is no level set -r. A point
   whose ray inwards meets the far side within d may take a centre in the middle of
   that chord (one row on the medial surface, as the lattice's one row of cells),
   which sticks out of the mesh: it does where that is less than the offset's balls
   leave the point uncovered (a plate; an edge sharper than 60°), not at the milder
   acute edges of thick parts (offset_points).
3. **Even spacing.** Candidates are thinned greedily in a fixed order to a maximal
   Poisson-disk set of spacing h: no two centres closer than h, every candidate within
   h of a centre. On a flat face a point of the surface is then at most ~h from the
   nearest centre's axis and the envelope dips there by r - sqrt(r^2 - rho^2) ~ rho^2/d
   (the bump height; measured by :func:`envelope_errors`, docs/spheres.md).
4. **Interior.** The lattice cells of pitch d inside the mesh whose centre is deeper
   than d under the surface, so another body cannot sit inside the shell; they are
   deeper than the shell's centres and never shape the contact surface.

Everything is deterministic: fixed sample grids, fixed candidate order, serial
thinning, closest-point and ray kernels whose result does not depend on the thread
count (each point is computed alone; ties keep the first triangle in a fixed order).
Closest points use a uniform grid of triangles (cells of the search reach), so a
query visits only the triangles near it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from dempipe.mesh.winding import inside_mask, winding_numbers
from dempipe.spheres.fidelity import point_set_distance
from dempipe.spheres.options import DEFAULT_SPACING

#: Projection iterations onto the offset surface (converged to 1e-12 r on smooth parts
#: after 2-3; the rest is for candidates near concave edges).
_PROJECT_ITERS = 8
#: A candidate is on the offset when its depth is within this fraction of r of r.
_DEPTH_TOL = 1e-3
#: A medial centre is taken where it mends more of the envelope than it sticks out by
#: at least this fraction of r (offset_points): at a 60° edge the two are equal at
#: the edge itself, and a tie leaves the mesh unpoked.
_MEDIAL_GAIN = 0.02
#: Rays within asin(GRAZE) of a triangle's plane miss it (_ray_kernel): 0.57°.
GRAZE = 0.01
#: The inside test's ray (MeshQueries.inside): off the axes, so that it does not run
#: along the faces or through the shared edges of a mesh built on them.
INSIDE_RAY = np.array([0.0137, 0.0231, 1.0]) / math.sqrt(0.0137 ** 2 + 0.0231 ** 2 + 1.0)
#: How far offset_points' samples lie off their triangle's edges, as a fraction of the
#: way to its centroid: a point's normal is then its own face's, and the ray inwards
#: along it that finds thin parts starts inside the body even at an edge sharper than
#: 90°.
EDGE_INSET = 1e-6
#: Metric sample spacing on the mesh surface, as a fraction of d.
METRIC_SPACING = 0.1


# --------------------------------------------------------------------------- kernels


@numba.njit(cache=True)
def _closest_on_triangle(px, py, pz, t):
    """Closest point of triangle t (3, 3) to p (Ericson, Real-Time Collision Detection 5.1.5)."""
    ax, ay, az = t[0, 0], t[0, 1], t[0, 2]
    bx, by, bz = t[1, 0], t[1, 1], t[1, 2]
    cx, cy, cz = t[2, 0], t[2, 1], t[2, 2]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return ax + v * abx, ay + v * aby, az + v * abz
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return ax + w * acx, ay + w * acy, az + w * acz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz)
    den = va + vb + vc
    if den == 0.0:          # degenerate triangle: its first corner
        return ax, ay, az
    v = vb / den
    w = vc / den
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w


@numba.njit(cache=True)
def _bin_boxes(lo, hi, origin, cell, dims):
    """CSR lists of the boxes (lo, hi) (B, 3) overlapping each grid cell, boxes in
    index order within a cell (serial: the same lists for any thread count)."""
    ncell = dims[0] * dims[1] * dims[2]
    count = np.zeros(ncell + 1, dtype=np.int64)
    nb = lo.shape[0]
    for pass_ in range(2):
        if pass_ == 1:
            for c in range(ncell):
                count[c + 1] += count[c]
            items = np.empty(count[ncell], dtype=np.int64)
            fill = count[:ncell].copy()
        for b in range(nb):
            i0 = max(0, min(dims[0] - 1, int(math.floor((lo[b, 0] - origin[0]) / cell))))
            j0 = max(0, min(dims[1] - 1, int(math.floor((lo[b, 1] - origin[1]) / cell))))
            k0 = max(0, min(dims[2] - 1, int(math.floor((lo[b, 2] - origin[2]) / cell))))
            i1 = max(0, min(dims[0] - 1, int(math.floor((hi[b, 0] - origin[0]) / cell))))
            j1 = max(0, min(dims[1] - 1, int(math.floor((hi[b, 1] - origin[1]) / cell))))
            k1 = max(0, min(dims[2] - 1, int(math.floor((hi[b, 2] - origin[2]) / cell))))
            for k in range(k0, k1 + 1):
                for j in range(j0, j1 + 1):
                    for i in range(i0, i1 + 1):
                        c = (k * dims[1] + j) * dims[0] + i
                        if pass_ == 0:
                            count[c + 1] += 1
                        else:
                            items[fill[c]] = b
                            fill[c] += 1
    return count, items


@numba.njit(cache=True, inline="always")
def _cell_span(lx, ly, lz, hx, hy, hz, origin, cell, dims):
    """Grid cells (i0, j0, k0, i1, j1, k1) of the box (l, h): the low corner's clamped
    below at 0, the high corner's above at dims - 1, so a box outside the grid spans
    no cell."""
    i0 = max(0, int(math.floor((lx - origin[0]) / cell)))
    j0 = max(0, int(math.floor((ly - origin[1]) / cell)))
    k0 = max(0, int(math.floor((lz - origin[2]) / cell)))
    i1 = min(dims[0] - 1, int(math.floor((hx - origin[0]) / cell)))
    j1 = min(dims[1] - 1, int(math.floor((hy - origin[1]) / cell)))
    k1 = min(dims[2] - 1, int(math.floor((hz - origin[2]) / cell)))
    return i0, j0, k0, i1, j1, k1


@numba.njit(parallel=True, cache=True)
def _closest_kernel(points, tris, origin, cell, dims, start, items, reach, out_d, out_q):
    """Closest point of the mesh to each point among the triangles within ``reach``;
    out_d = inf where none is."""
    n = points.shape[0]
    for p in numba.prange(n):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        i0, j0, k0, i1, j1, k1 = _cell_span(px - reach, py - reach, pz - reach, px + reach,
                                            py + reach, pz + reach, origin, cell, dims)
        best = np.inf
        qx, qy, qz = px, py, pz
        for k in range(k0, k1 + 1):
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    c = (k * dims[1] + j) * dims[0] + i
                    for e in range(start[c], start[c + 1]):
                        x, y, z = _closest_on_triangle(px, py, pz, tris[items[e]])
                        d2 = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
                        if d2 < best:
                            best = d2
                            qx, qy, qz = x, y, z
        dist = math.sqrt(best)
        out_d[p] = dist if dist <= reach else np.inf
        out_q[p, 0] = qx
        out_q[p, 1] = qy
        out_q[p, 2] = qz


@numba.njit(cache=True, inline="always")
def _ray_hit(px, py, pz, dx, dy, dz, t, graze):
    """Distance along (dx, dy, dz) (unit) from p to triangle t (3, 3), either side
    (Moller-Trumbore); inf where it misses or runs along it (|cos| of its angle to the
    triangle's normal below ``graze``)."""
    e1x, e1y, e1z = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
    e2x, e2y, e2z = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
    hx = dy * e2z - dz * e2y
    hy = dz * e2x - dx * e2z
    hz = dx * e2y - dy * e2x
    a = e1x * hx + e1y * hy + e1z * hz
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    if abs(a) < 1e-300 or a * a < graze * graze * (nx * nx + ny * ny + nz * nz):
        return np.inf
    f = 1.0 / a
    sx, sy, sz = px - t[0, 0], py - t[0, 1], pz - t[0, 2]
    u = f * (sx * hx + sy * hy + sz * hz)
    if u < 0.0 or u > 1.0:
        return np.inf
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    v = f * (dx * qx + dy * qy + dz * qz)
    if v < 0.0 or u + v > 1.0:
        return np.inf
    return f * (e2x * qx + e2y * qy + e2z * qz)


@numba.njit(parallel=True, cache=True)
def _ray_kernel(points, dirs, tris, origin, cell, dims, start, items, length, out_t):
    """Distance along dirs (unit) from points to the nearest triangle hit beyond
    1e-9 length, within ``length``; inf where none (_ray_hit). A triangle the ray runs
    along (GRAZE) is not hit: a ray from a point on an edge, inwards along one face's
    normal, runs in the plane of the other face where the edge is square, and rounding
    would otherwise hit that face at any distance, 0 included."""
    n = points.shape[0]
    for p in numba.prange(n):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        dx, dy, dz = dirs[p, 0], dirs[p, 1], dirs[p, 2]
        ex, ey, ez = px + length * dx, py + length * dy, pz + length * dz
        i0, j0, k0, i1, j1, k1 = _cell_span(min(px, ex), min(py, ey), min(pz, ez),
                                            max(px, ex), max(py, ey), max(pz, ez),
                                            origin, cell, dims)
        best = np.inf
        for k in range(k0, k1 + 1):
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    c = (k * dims[1] + j) * dims[0] + i
                    for e in range(start[c], start[c + 1]):
                        tt = _ray_hit(px, py, pz, dx, dy, dz, tris[items[e]], GRAZE)
                        if tt > 1e-9 * length and tt < best:
                            best = tt
        out_t[p] = best if best <= length else np.inf


@numba.njit(parallel=True, cache=True)
def _crossing_kernel(points, direction, tris, origin, cell, dims, start, items, out):
    """out[p] = the winding number of the mesh at points[p], counted along the ray from
    it along ``direction`` (unit, dz > 0) to the grid's top: +1 for each face it leaves
    through (the face's normal along the ray), -1 for each it enters through; grazing
    faces count. Each triangle once, in the first cell of the ray's span that it is
    binned in. Exact for a closed mesh, overlapping closed parts included, unless the
    ray runs through an edge or a corner."""
    n = points.shape[0]
    dx, dy, dz = direction[0], direction[1], direction[2]
    top = origin[2] + dims[2] * cell
    for p in numba.prange(n):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        length = max(0.0, (top - pz) / dz)
        ex, ey, ez = px + length * dx, py + length * dy, pz + length * dz
        i0, j0, k0, i1, j1, k1 = _cell_span(min(px, ex), min(py, ey), min(pz, ez),
                                            max(px, ex), max(py, ey), max(pz, ez),
                                            origin, cell, dims)
        winding = 0
        for k in range(k0, k1 + 1):
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    c = (k * dims[1] + j) * dims[0] + i
                    for e in range(start[c], start[c + 1]):
                        t = tris[items[e]]
                        # the triangle's first cell in this span (its box's low corner)
                        ti = max(i0, int(math.floor((min(t[0, 0], t[1, 0], t[2, 0]) - origin[0]) / cell)))
                        tj = max(j0, int(math.floor((min(t[0, 1], t[1, 1], t[2, 1]) - origin[1]) / cell)))
                        tk = max(k0, int(math.floor((min(t[0, 2], t[1, 2], t[2, 2]) - origin[2]) / cell)))
                        if ti != i or tj != j or tk != k:
                            continue
                        tt = _ray_hit(px, py, pz, dx, dy, dz, t, 0.0)
                        if tt > 0.0 and tt <= length:
                            e1x, e1y, e1z = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
                            e2x, e2y, e2z = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
                            along = ((e1y * e2z - e1z * e2y) * dx + (e1z * e2x - e1x * e2z) * dy
                                     + (e1x * e2y - e1y * e2x) * dz)
                            winding += 1 if along > 0.0 else -1
        out[p] = winding


@numba.njit(cache=True)
def _poisson_thin(points, h):
    """Greedy maximal Poisson-disk subset of ``points`` (in their order) with spacing h:
    a point is kept when no kept point is closer than h. Serial (its result is the
    order's). Kept points are hashed by their cell of edge h into 2^k buckets."""
    n = points.shape[0]
    nb = 1
    while nb < 2 * n:
        nb *= 2
    head = np.full(nb, -1, dtype=np.int64)
    nxt = np.full(n, -1, dtype=np.int64)
    keep = np.zeros(n, dtype=np.bool_)
    h2 = h * h
    for p in range(n):
        ci = int(math.floor(points[p, 0] / h))
        cj = int(math.floor(points[p, 1] / h))
        ck = int(math.floor(points[p, 2] / h))
        ok = True
        for dk in range(-1, 2):
            for dj in range(-1, 2):
                for di in range(-1, 2):
                    b = ((ci + di) * 73856093 ^ (cj + dj) * 19349663 ^ (ck + dk) * 83492791) & (nb - 1)
                    q = head[b]
                    while q >= 0:
                        d2 = ((points[q, 0] - points[p, 0]) ** 2 + (points[q, 1] - points[p, 1]) ** 2
                              + (points[q, 2] - points[p, 2]) ** 2)
                        if d2 < h2:
                            ok = False
                            break
                        q = nxt[q]
                    if not ok:
                        break
                if not ok:
                    break
            if not ok:
                break
        if ok:
            keep[p] = True
            b = (ci * 73856093 ^ cj * 19349663 ^ ck * 83492791) & (nb - 1)
            nxt[p] = head[b]
            head[b] = p
    return keep


@numba.njit(parallel=True, cache=True)
def _nearest_within(points, centers, origin, cell, dims, start, items, out):
    """Distance from each point to the nearest of ``centers`` within ``cell`` (the grid's
    cell edge; binned by _bin_boxes with zero-size boxes); inf where none is."""
    n = points.shape[0]
    for p in numba.prange(n):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        i0, j0, k0, i1, j1, k1 = _cell_span(px - cell, py - cell, pz - cell, px + cell,
                                            py + cell, pz + cell, origin, cell, dims)
        best = np.inf
        for k in range(k0, k1 + 1):
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    c = (k * dims[1] + j) * dims[0] + i
                    for e in range(start[c], start[c + 1]):
                        q = items[e]
                        d2 = ((centers[q, 0] - px) ** 2 + (centers[q, 1] - py) ** 2
                              + (centers[q, 2] - pz) ** 2)
                        if d2 < best:
                            best = d2
        d = math.sqrt(best)
        out[p] = d if d <= cell else np.inf


@numba.njit(parallel=True, cache=True)
def shrinking_ball(points, inward, tau, out):
    """Per point p_i with inward unit normal m_i: the radius ρ of the largest ball
    tangent at p_i (centre p_i + ρ m_i) that holds no other point deeper than ``tau``
    inside it, into out[i]: min over j of (|p_j − p_i|² − τ²) / (2 ((p_j − p_i)·m_i − τ))
    for (p_j − p_i)·m_i > τ, inf where none is. All pairs (each point's minimum is its
    own: the same for any thread count)."""
    n = points.shape[0]
    for i in numba.prange(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        mx, my, mz = inward[i, 0], inward[i, 1], inward[i, 2]
        best = np.inf
        for j in range(n):
            rx = points[j, 0] - px
            ry = points[j, 1] - py
            rz = points[j, 2] - pz
            t = rx * mx + ry * my + rz * mz
            if t > tau:
                rad = (rx * rx + ry * ry + rz * rz - tau * tau) / (2.0 * (t - tau))
                if rad < best:
                    best = rad
        out[i] = best


# --------------------------------------------------------------------------- helpers


class _Grid:
    """Boxes (triangles' or points') binned into a uniform grid of cell ``cell``."""

    def __init__(self, lo, hi, cell, pad):
        lo = np.ascontiguousarray(lo, dtype=np.float64).reshape(-1, 3)
        hi = np.ascontiguousarray(hi, dtype=np.float64).reshape(-1, 3)
        self.cell = float(cell)
        self.origin = lo.min(axis=0) - pad
        top = hi.max(axis=0) + pad
        self.dims = np.maximum(1, np.ceil((top - self.origin) / self.cell).astype(np.int64))
        self.start, self.items = _bin_boxes(lo, hi, self.origin, self.cell, self.dims)


class MeshQueries:
    """Closest points and rays against one triangle mesh, searched within ``reach``."""

    def __init__(self, vertices, faces, reach):
        v = np.asarray(vertices, dtype=np.float64)
        self.tris = np.ascontiguousarray(v[np.asarray(faces, dtype=np.int64)])
        self.reach = float(reach)
        self.grid = _Grid(self.tris.min(axis=1), self.tris.max(axis=1), self.reach,
                          2.0 * self.reach)
        # closed: every directed edge once, and its reverse (a ray's crossings count)
        f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        key = e[:, 0] * (len(v) + 1) + e[:, 1]
        self.closed = bool(len(f)) and len(np.unique(key)) == len(key) and bool(
            np.isin(e[:, 1] * (len(v) + 1) + e[:, 0], key).all())

    def closest(self, points, reach=None):
        """(distance (N,), closest point (N, 3)); distance inf beyond ``reach`` (at
        most the grid's, which is the default)."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        d = np.empty(len(pts))
        q = np.empty_like(pts)
        g = self.grid
        reach = self.reach if reach is None else min(float(reach), self.reach)
        if len(pts):
            _closest_kernel(pts, self.tris, g.origin, g.cell, g.dims, g.start, g.items,
                            reach, d, q)
        return d, q

    def inside(self, points):
        """(N,) bool: inside the mesh, by its winding number's nonzero rule: counted
        along a ray (INSIDE_RAY) on a closed mesh, the generalized winding number
        (mesh.winding, every triangle) on one with holes. Points within rounding of the
        surface may go either way."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if not len(pts):
            return np.zeros(0, dtype=np.bool_)
        if not self.closed:
            return np.abs(winding_numbers(pts, self.tris)) > 0.5
        out = np.zeros(len(pts), dtype=np.int64)
        g = self.grid
        _crossing_kernel(pts, INSIDE_RAY, self.tris, g.origin, g.cell, g.dims, g.start,
                         g.items, out)
        return out != 0

    def ray(self, points, dirs, length):
        """Distance along unit ``dirs`` to the first triangle within ``length`` (inf: none).
        ``length`` must not exceed 2 reach (the grid's padding)."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        dd = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
        t = np.empty(len(pts))
        g = self.grid
        if len(pts):
            _ray_kernel(pts, dd, self.tris, g.origin, g.cell, g.dims, g.start, g.items,
                        float(length), t)
        return t


def nearest_distance(points, centers, reach):
    """Distance from each point to the nearest centre, inf where none is within reach."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    c = np.ascontiguousarray(centers, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(pts), np.inf)
    if len(pts) and len(c):
        g = _Grid(c, c, reach, reach)
        _nearest_within(pts, c, g.origin, g.cell, g.dims, g.start, g.items, out)
    return out


def grid_samples(vertices, faces, spacing, inset=0.0):
    """Points spread over every triangle about ``spacing`` apart, and each point's face
    normal (unit, the face's winding: outward for a repaired mesh).

    Per triangle: its corners, points along each edge at most ``spacing`` apart, and
    ceil(2 area / spacing^2) inside from the R2 low-discrepancy sequence (Roberts 2018)
    folded into the triangle, so slivers get points along their length and big faces
    by their area. ``inset``: each point moved that fraction of the way towards its
    triangle's centroid, off the edges (EDGE_INSET for offset_points). Deterministic;
    triangle order. Returns (points (P, 3), normals (P, 3)).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = v[f]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(nrm, axis=1)
    good = ln > 0
    tri, nrm, ln = tri[good], nrm[good] / ln[good, None], ln[good]
    if len(tri) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    s = float(spacing)
    owner, bary = [], []
    # edges (corner k to k+1), corners included once per triangle: t in [0, 1)
    for k in range(3):
        length = np.linalg.norm(tri[:, (k + 1) % 3] - tri[:, k], axis=1)
        n = np.maximum(1, np.ceil(length / s - 1e-9).astype(np.int64))
        t_owner = np.repeat(np.arange(len(tri)), n)
        first = np.repeat(np.cumsum(n) - n, n)
        t = (np.arange(len(t_owner)) - first) / np.repeat(n, n)
        w = np.zeros((len(t), 3))
        w[:, k] = 1.0 - t
        w[:, (k + 1) % 3] = t
        owner.append(t_owner)
        bary.append(w)
    # inside: R2 sequence in the unit square, folded onto the triangle
    n_in = np.ceil(ln / (s * s) - 1e-9).astype(np.int64)        # 2 area / s^2
    i_owner = np.repeat(np.arange(len(tri)), n_in)
    first = np.repeat(np.cumsum(n_in) - n_in, n_in)
    i = (np.arange(len(i_owner)) - first + 1).astype(np.float64)
    g = 1.32471795724474602596      # the plastic number
    a = np.mod(0.5 + i / g, 1.0)
    b = np.mod(0.5 + i / (g * g), 1.0)
    fold = a + b > 1.0
    a[fold], b[fold] = 1.0 - a[fold], 1.0 - b[fold]
    owner.append(i_owner)
    bary.append(np.stack([1.0 - a - b, a, b], axis=1))
    owner = np.concatenate(owner)
    bary = np.concatenate(bary)
    if inset:
        bary = (1.0 - inset) * bary + inset / 3.0
    order = np.argsort(owner, kind="stable")
    owner, bary = owner[order], bary[order]
    pts = np.einsum("pk,pkj->pj", bary, tri[owner])
    return np.ascontiguousarray(pts), np.ascontiguousarray(nrm[owner])


def offset_points(queries: MeshQueries, points, normals, radius):
    """Candidate centres for ``points`` of the surface with outward ``normals``.

    Each point is first projected onto the inward offset at distance ``radius`` r
    (kind 1 where it settles at depth r inside the body): the centres of the balls of
    diameter d inside the mesh, whose union is the best envelope spheres of d can make
    without sticking out. Where the ray inwards
    meets the far side within d (t < d), the body may be thinner than d, and a centre
    at the chord's middle m (kind 2, medial) covers the point at the cost of sticking
    out of the mesh by r - depth(m). It is taken only where that costs less than it
    mends: where the point is further than r + (r - depth(m)) from every offset centre
    (a plate thinner than d has none; a wedge under about 60° leaves its edge further
    out than its medial spheres stick out). Near an acute edge of a thick part (a
    frustum's base rim) the chord meets the next face, its middle lies near the edge
    and would stick out by nearly r, while the edge's offset rounds it by less: the
    point is left to the offset. Returns (centres (P, 3), kind (P,) int8: 1 offset,
    2 medial, 0 neither: covered by the others)."""
    r = float(radius)
    start = points - 1e-9 * r * normals
    t = queries.ray(start, -normals, 2.0 * r)
    kind = np.zeros(len(points), dtype=np.int8)
    reach = 1.05 * r                  # a candidate is never deeper than r: c0 and each step
    c = points - r * normals
    todo = np.arange(len(points))
    for _ in range(_PROJECT_ITERS):
        if not len(todo):
            break
        dist, q = queries.closest(c[todo], reach)
        ok = np.isfinite(dist) & (dist > 1e-12 * r)
        safe = np.where(ok, dist, 1.0)[:, None]
        new = np.where(ok[:, None], q + r * (c[todo] - q) / safe, c[todo])
        moved = np.abs(new - c[todo]).max(axis=1) > 1e-12 * r
        c[todo] = new
        todo = todo[moved]
    dist, _ = queries.closest(c, reach)
    on = np.flatnonzero(np.isfinite(dist) & (np.abs(dist - r) <= _DEPTH_TOL * r))
    # across a thin part the projection settles at depth r beyond its far side
    on = on[queries.inside(c[on])]
    kind[on] = 1
    thin = np.flatnonzero(np.isfinite(t) & (kind == 0))
    if len(thin):
        mid = points[thin] - 0.5 * t[thin, None] * normals[thin]
        depth, _ = queries.closest(mid, reach)
        poke = r - np.minimum(depth, r)
        gap = nearest_distance(points[thin], c[on], 4.0 * r) - r
        take = gap > poke + _MEDIAL_GAIN * r
        c[thin[take]] = mid[take]
        kind[thin[take]] = 2
    return c, kind


# --------------------------------------------------------------------------- builder


@dataclass(frozen=True)
class SurfaceCenters:
    """Centres of a surface-following set in mesh coordinates, shell first.

    shell: centres on the offset surface at depth r (count); medial: centres of thin
    parts on their medial surface (count); interior: lattice cells deeper than d (count).
    """

    centers: np.ndarray
    shell: int
    medial: int
    interior: int


def surface_centers(mesh, diameter, spacing=DEFAULT_SPACING, inside=None,
                    lattice=None) -> SurfaceCenters:
    """The surface-following centres of a repaired ``mesh`` (outward normals) for
    spheres of ``diameter`` d [m], shell spacing ``spacing`` d.

    inside(points) -> bool mask: the inside test for thin parts' medial centres (the
    shell's are inside by MeshQueries.inside);
    lattice: (M, 3) lattice cell centres inside the mesh (for the interior fill), or
    None to skip the interior.
    """
    d = float(diameter)
    r = 0.5 * d
    h = float(spacing) * d
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    queries = MeshQueries(v, f, reach=d)
    pts, nrm = grid_samples(v, f, h / 3.0, EDGE_INSET)
    cand, kind = offset_points(queries, pts, nrm, r)
    # features first: a candidate pulled further from its surface point than r sits on
    # the offset of a convex corner (sqrt(3) r for a cube's) or edge (sqrt(2) r) or of
    # a concave edge; placed before the faces' candidates, the thinning keeps them and
    # the envelope reaches into corners as far as spheres of diameter d can.
    pull = np.round(np.linalg.norm(pts - cand, axis=1) / r, 3)
    order = np.argsort(-pull, kind="stable")
    cand, kind = cand[order], kind[order]
    shell_c = cand[kind == 1]
    medial_c = cand[kind == 2]
    shell_c = shell_c[_poisson_thin(np.ascontiguousarray(shell_c), h)] if len(shell_c) else shell_c
    if len(medial_c):
        # thin parts: medial centres at the same spacing, away from the shell's
        both = np.concatenate([shell_c, medial_c])
        keep = _poisson_thin(both, h)
        medial_c = medial_c[keep[len(shell_c):]]
    if inside is not None:
        # (the shell's centres are inside already: offset_points keeps only those)
        medial_c = medial_c[inside(medial_c)] if len(medial_c) else medial_c
    interior = np.zeros((0, 3))
    if lattice is not None and len(lattice):
        dist, _ = queries.closest(lattice)
        interior = lattice[~np.isfinite(dist)]          # no triangle within d
    centers = np.concatenate([shell_c, medial_c, interior]).reshape(-1, 3)
    return SurfaceCenters(centers=centers, shell=len(shell_c), medial=len(medial_c),
                          interior=len(interior))


# --------------------------------------------------------------------------- errors


@dataclass(frozen=True)
class EnvelopeError:
    """How far the spheres' envelope is from the mesh surface, in metres.

    hausdorff: the larger of (a) the largest distance from a point of the mesh surface
        to the nearest sphere and (b) the most a sphere sticks out of the mesh.
    bump: the largest distance from a point of the mesh surface to the nearest sphere
        beyond that of the ideal envelope, offset_points' centres of a dense grid of
        the surface, unthinned: every ball of diameter d inside the mesh (which rounds
        convex edges with radius d/2 and cannot be beaten by spheres of that size) and
        the medial balls of its thin parts: the dips between neighbouring spheres.
    rounding: the ideal envelope's own largest distance (convex edges, corners).
    samples: surface points measured (a barycentric grid of METRIC_SPACING d).
    """

    hausdorff: float
    bump: float
    rounding: float
    samples: int


def envelope_errors(mesh, centers, diameter, *, spacing=METRIC_SPACING) -> EnvelopeError:
    """:class:`EnvelopeError` of spheres of ``diameter`` at ``centers`` (mesh coordinates)
    against a repaired, closed ``mesh``. Deterministic (grid samples, no randomness)."""

    d = float(diameter)
    r = 0.5 * d
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    queries = MeshQueries(v, f, reach=d)
    pts, nrm = grid_samples(v, f, spacing * d)
    # mesh -> spheres: nearest centre, searched within a growing reach
    near = nearest_distance(pts, c, 2.0 * d)
    miss = ~np.isfinite(near)
    if miss.any():
        near[miss] = point_set_distance(pts[miss], c)
    gap = np.maximum(near - r, 0.0)
    # the ideal envelope: balls on the offset (and medial) surface of the same grid, its
    # points off the edges as offset_points needs
    ideal, kind = offset_points(queries, *grid_samples(v, f, spacing * d, EDGE_INSET), r)
    ideal = ideal[kind > 0]
    # thinned to 1/16 d: the ideal envelope's distance is then off by < (d/32)^2 / r
    ideal = ideal[_poisson_thin(np.ascontiguousarray(ideal), d / 16.0)]
    best = nearest_distance(pts, ideal, 2.0 * d)
    miss = ~np.isfinite(best)
    if miss.any():
        best[miss] = point_set_distance(pts[miss], ideal) if len(ideal) else r
    ideal_gap = np.maximum(best - r, 0.0)
    # spheres -> mesh: how far each sphere reaches past the surface
    dist, _ = queries.closest(c)
    inside = inside_mask(mesh, c)
    out = np.where(inside, np.where(np.isfinite(dist), r - dist, -np.inf),
                   r + np.where(np.isfinite(dist), dist, d))
    poke = float(max(0.0, out.max())) if len(out) else 0.0
    return EnvelopeError(hausdorff=float(max(gap.max(), poke)),
                         bump=float(max(0.0, (gap - ideal_gap).max())),
                         rounding=float(ideal_gap.max()), samples=int(len(pts)))
