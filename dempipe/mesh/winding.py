"""Generalized winding number of a triangle mesh at query points.

w(p) = (1 / 4 pi) * sum over triangles of the solid angle the triangle subtends at
p, with the Van Oosterom–Strackee formula

    tan(Omega / 2) = a . (b x c) / (|a||b||c| + (a.b)|c| + (b.c)|a| + (c.a)|b|)

where a, b, c are the triangle's corners relative to p. For a closed, consistently
oriented (outward) mesh w is 1 inside and 0 outside; for a mesh with small holes it
stays close to that (Jacobson et al. 2013), so ``|w| > 0.5`` is a robust inside test.

The kernel is a brute-force loop over query points x triangles (parallel over the
points). It is compiled on first use and cached on disk by numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from dempipe import interrupt

_FOUR_PI = 4.0 * math.pi


@numba.njit(parallel=True, cache=True, fastmath=False)
def _winding_kernel(points, tris, out):
    n = points.shape[0]
    m = tris.shape[0]
    for i in numba.prange(n):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        total = 0.0
        for t in range(m):
            ax = tris[t, 0, 0] - px
            ay = tris[t, 0, 1] - py
            az = tris[t, 0, 2] - pz
            bx = tris[t, 1, 0] - px
            by = tris[t, 1, 1] - py
            bz = tris[t, 1, 2] - pz
            cx = tris[t, 2, 0] - px
            cy = tris[t, 2, 1] - py
            cz = tris[t, 2, 2] - pz
            la = math.sqrt(ax * ax + ay * ay + az * az)
            lb = math.sqrt(bx * bx + by * by + bz * bz)
            lc = math.sqrt(cx * cx + cy * cy + cz * cz)
            det = (ax * (by * cz - bz * cy)
                   - ay * (bx * cz - bz * cx)
                   + az * (bx * cy - by * cx))
            den = (la * lb * lc
                   + (ax * bx + ay * by + az * bz) * lc
                   + (bx * cx + by * cy + bz * cz) * la
                   + (cx * ax + cy * ay + cz * az) * lb)
            total += 2.0 * math.atan2(det, den)
        out[i] = total / _FOUR_PI


def winding_numbers(points, triangles) -> np.ndarray:
    """Generalized winding number of the triangle soup at each point.

    points: (N, 3) query points [m]; triangles: (F, 3, 3) corner coordinates [m],
    counter-clockwise seen from outside. Returns (N,) float64.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    tris = np.ascontiguousarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
    out = np.zeros(pts.shape[0], dtype=np.float64)
    if pts.shape[0] and tris.shape[0]:
        # in batches of about BATCH_WORK point-triangle terms (a fraction of a
        # second), so that a stop signal is seen between two (dempipe.interrupt);
        # each point's sum is its own, whatever the batches
        step = max(1, BATCH_WORK // tris.shape[0])
        for a in range(0, pts.shape[0], step):
            interrupt.check()
            _winding_kernel(pts[a:a + step], tris, out[a:a + step])
    return out


#: Point-triangle terms per compiled call of winding_numbers (~0.1 s on one core).
BATCH_WORK = 20_000_000


def inside_mask(mesh, points, threshold: float = 0.5) -> np.ndarray:
    """Boolean inside test of ``points`` (N, 3) against ``mesh`` by the generalized
    winding number: inside where ``|w| > threshold``."""
    tris = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces, dtype=np.int64)]
    w = winding_numbers(points, tris)
    return np.abs(w) > threshold
