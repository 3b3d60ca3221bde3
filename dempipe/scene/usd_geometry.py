"""Matrices and collision geometry of a USD stage, as NumPy and trimesh (no stage logic).

    S, R = polar(W[:3, :3])             # W: a prim's row-vector world matrix
    q = matrix_to_quat(R.T)             # (w, x, y, z) of the column-convention R.T
    mesh = gprim_mesh(prim, where)     # Cube/Sphere/Capsule/Cylinder/Cone/Mesh

Conventions are USD's: matrices are row-vector 4 × 4 (``p_world = p_local · M``), so
a rotation R here acts as ``p · R`` and its column-convention matrix is ``R.T``;
quaternions are (w, x, y, z) with w >= 0. ``polar`` splits ``A = S R`` (S the
stretch a body keeps, R proper). Gprim meshes are in the prim's own local
coordinates [stage units]: scene/usd_reader.py moves them into the body's stretched frame
and to metres. pxr and trimesh are imported inside ``gprim_mesh`` only, so this
module (like scene/usd_reader.py) imports neither until a stage is read.
"""

from __future__ import annotations

import math

import numpy as np

from dempipe.errors import SceneError
from dempipe.sim.model import quat_to_matrix

__all__ = ["polar", "matrix_to_quat", "matrix_array", "quat_matrix"]

#: Segments of tessellated round gprims (Sphere: icosphere subdivisions instead).
ROUND_SECTIONS = 48
SPHERE_SUBDIVISIONS = 4         # the built-in sphere's: its facets are what it rolls on


# ------------------------------------------------------------------------- matrices


def polar(A: np.ndarray):
    """(S, R) with ``A = S R``: S symmetric (the stretch), R a rotation (row convention).

    A mirror (det A < 0) is put into S, so R is always a proper rotation.
    """
    U, sig, Vt = np.linalg.svd(A)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        D = np.diag([1.0, 1.0, -1.0])
        R = U @ D @ Vt
        S = U @ np.diag(sig) @ D @ U.T
    else:
        S = U @ np.diag(sig) @ U.T
    return 0.5 * (S + S.T), R


def matrix_to_quat(Rc: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of the column-convention rotation matrix Rc."""
    m = Rc
    t = m[0, 0] + m[1, 1] + m[2, 2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def matrix_array(m) -> np.ndarray:
    return np.array(m, dtype=np.float64).reshape(4, 4)


# -------------------------------------------------------------------------- geometry


def _axis_perm(axis: str) -> np.ndarray:
    """Vertices built along +Z moved to ``axis`` by a cyclic permutation (a rotation)."""
    if axis == "X":
        return np.array([2, 0, 1])      # (z, x, y): z goes to x
    if axis == "Y":
        return np.array([1, 2, 0])      # (y, z, x): z goes to y
    return np.array([0, 1, 2])


#: Largest coordinate or size read from a stage, in stage units: beyond it squares
#: and volumes overflow float64 (1e300 ** 2 is inf) long before a simulation could use it.
MAX_COORDINATE = 1e15
#: ... and the smallest size, radius or height: below it a shape is a typing error
#: (and its volume underflows to 0).
MIN_LENGTH = 1e-9


def _length(attr, where: str, zero: bool = False) -> float:
    """A gprim's size, radius or height: a finite number > 0 (>= 0 with ``zero``), or
    a SceneError naming the attribute."""
    v = attr.Get()
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise SceneError(f"{where}: {attr.GetName()} is not a number ({v!r})") from None
    if not (MIN_LENGTH <= x <= MAX_COORDINATE or (zero and x == 0)):     # NaN too
        raise SceneError(f"{where}: {attr.GetName()} = {x:g} (expected a length of "
                         f"{MIN_LENGTH:g} to {MAX_COORDINATE:g} stage units)")
    return x


def gprim_mesh(prim, where: str):
    """The collision geometry of a gprim in its own local coordinates [stage units],
    as a trimesh (None for a type dempipe cannot read)."""
    import trimesh
    from pxr import UsdGeom

    t = prim.GetTypeName()
    if t == "Cube":
        size = _length(UsdGeom.Cube(prim).GetSizeAttr(), where)
        return trimesh.creation.box(extents=[size] * 3)
    if t == "Sphere":
        r = _length(UsdGeom.Sphere(prim).GetRadiusAttr(), where)
        return trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=r)
    if t in ("Capsule", "Cylinder", "Cone"):
        g = getattr(UsdGeom, t)(prim)
        r = _length(g.GetRadiusAttr(), where)
        h = _length(g.GetHeightAttr(), where, zero=t == "Capsule")
        axis = g.GetAxisAttr().Get()
        if axis not in ("X", "Y", "Z"):
            raise SceneError(f"{where}: axis = {axis!r} (expected X, Y or Z)")
        if t == "Capsule":
            m = trimesh.creation.capsule(height=h, radius=r, count=[ROUND_SECTIONS, ROUND_SECTIONS])
        elif t == "Cylinder":
            m = trimesh.creation.cylinder(radius=r, height=h, sections=ROUND_SECTIONS)
        else:
            m = trimesh.creation.cone(radius=r, height=h, sections=ROUND_SECTIONS)
            m.apply_translation([0.0, 0.0, -0.5 * h])     # USD cones are centred
        v = np.asarray(m.vertices)[:, _axis_perm(axis)]
        return trimesh.Trimesh(v, m.faces, process=False)
    if t == "Mesh":
        mesh = UsdGeom.Mesh(prim)
        pts = mesh.GetPointsAttr().Get()
        counts = mesh.GetFaceVertexCountsAttr().Get()
        idx = mesh.GetFaceVertexIndicesAttr().Get()
        if not pts or not counts or not idx:
            raise SceneError(f"{where}: mesh has no points or faces (author points, "
                             "faceVertexCounts and faceVertexIndices)")
        pts = np.asarray(pts, dtype=np.float64)
        if not np.isfinite(pts).all() or np.abs(pts).max() > MAX_COORDINATE:
            raise SceneError(f"{where}: points hold a non-finite or huge coordinate "
                             f"(beyond ±{MAX_COORDINATE:g}); fix the mesh")
        counts = np.asarray(counts, dtype=np.int64)
        if (counts < 3).any():
            raise SceneError(f"{where}: faceVertexCounts holds a face of fewer than 3 "
                             f"corners")
        idx = np.asarray(idx, dtype=np.int64)
        if counts.sum() != len(idx) or idx.max() >= len(pts) or idx.min() < 0:
            raise SceneError(f"{where}: faceVertexCounts/faceVertexIndices do not match the "
                             f"{len(pts)} points")
        tris = []
        start = 0
        for c in counts:                  # fan triangulation of each polygon
            for k in range(1, c - 1):
                tris.append((idx[start], idx[start + k], idx[start + k + 1]))
            start += c
        faces = np.array(tris, dtype=np.int64).reshape(-1, 3)
        if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
            faces = faces[:, ::-1]
        return trimesh.Trimesh(pts, faces, process=False)
    return None


def quat_matrix(q) -> np.ndarray:
    """Column-convention rotation matrix of the quaternion (w, x, y, z), normalised
    first: an authored quatf (MassAPI principalAxes) need not be exactly unit."""
    q = np.asarray(q, float)
    return quat_to_matrix(q / np.linalg.norm(q))


#: A collision Cube or Mesh is taken as an infinite ground plane (its top face) when
#: it is flat (thickness at most this fraction of its shorter side: a DCC's ground
#: "plane", a quad of no thickness, is) ...
PLANE_FLATNESS = 0.1
#: ... its top face is perpendicular to gravity to within this cosine ...
PLANE_ALIGNMENT = 0.9999
#: ... and it is at least this many times wider than the largest body.
PLANE_WIDTH_BODIES = 10.0


def stage_up(gravity, up_axis: str) -> np.ndarray:
    """A stage's up, unit: against ``gravity``, or along ``up_axis`` ("Y" or "Z")
    without gravity."""
    g = float(np.linalg.norm(gravity))
    return -np.asarray(gravity, dtype=np.float64) / g if g > 0 else np.eye(3)[
        1 if up_axis == "Y" else 2]


def cube_ground_top(W, size, mpu, up, biggest):
    """(the centre of its top face [m], its width [m]) of a collision Cube of edge
    ``size`` [stage units] and row-vector world matrix ``W`` that is a ground plane:
    one face perpendicular to ``up`` (PLANE_ALIGNMENT), its thickness at most
    PLANE_FLATNESS of its shorter side, and at least PLANE_WIDTH_BODIES times as wide as
    ``biggest`` [m], the largest body; None otherwise."""
    axes = W[:3, :3] * size                          # rows: the cube's edges, world
    lengths = np.linalg.norm(axes, axis=1) * mpu
    cos = np.abs(axes @ up) / (np.linalg.norm(axes, axis=1) + 1e-300)
    k = int(np.argmax(cos))
    if cos[k] < PLANE_ALIGNMENT:
        return None
    wide = np.delete(lengths, k)
    if not (lengths[k] <= PLANE_FLATNESS * wide.min()
            and wide.min() >= PLANE_WIDTH_BODIES * biggest):
        return None
    return W[3, :3] * mpu + up * 0.5 * lengths[k], float(wide.min())


def mesh_ground_top(v, up, biggest, where):
    """(its highest point [m], its width [m]) of a collision Mesh whose vertices ``v``
    (world [m]) make a ground plane by a Cube's rules (cube_ground_top), measured along
    ``up`` and across it along the points' own axes (a rotated quad counts its width):
    a DCC's ground plane, a quad with no thickness, is one. None otherwise; a mesh of
    no thickness along ``up`` that is too small raises SceneError naming ``where`` and
    the rule: it encloses no volume to fill with spheres either."""
    h = v @ up
    thick = float(h.max() - h.min())
    across = v - np.outer(h, up)
    across = across - across.mean(axis=0)
    _, _, vt = np.linalg.svd(across, full_matrices=False)
    span = np.ptp(across @ vt[:2].T, axis=0)
    wide = float(span.min())
    if wide <= 0.0 or thick > PLANE_FLATNESS * wide:
        return None
    if wide < PLANE_WIDTH_BODIES * biggest:
        if thick <= 1e-9 * wide:
            raise SceneError(
                f"{where}: a flat collision mesh ({float(span.max()):.3g} x {wide:.3g} m) "
                f"encloses no volume to fill with spheres; dempipe takes one as a ground "
                f"plane only when it is level and at least {PLANE_WIDTH_BODIES:g} times as "
                f"wide as the largest body ({biggest:.3g} m): make it wider, or give it a "
                f"thickness")
        return None
    return v[int(np.argmax(h))], wide
