"""Colliders as USD prims under /World/Colliders: planes as finite quads, boxes as
the slabs of their walls, static meshes as they are, in world coordinates.

A moving collider (``model.collider_motions``) gets time-sampled
``xformOp:translate`` and ``xformOp:orient`` from usd/prescribed.py, sparse
like the bodies' samples.
"""

from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Vt

from dempipe.usd.authoring import (
    SPEC_DEF,
    SDF_TYPES,
    author_attr,
    constant_columns,
    flush_tiny,
    kept_samples,
    unique_names,
)
from dempipe.usd.meshes import COLLIDER_COLOR, author_mesh
from dempipe.usd.prescribed import collider_xforms, plane_xforms


def tangent_basis(n: np.ndarray):
    """Orthonormal u, v with u × v = n."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    return u, v


def _plane_quad(point, normal, positions):
    """Quad vertices (4, 3) [m] of a finite stand-in for an infinite plane:
    centred at the projection of the bodies' frame-0 centroid onto the plane,
    half size max(1 m, 2 × the largest in-plane distance of any position from
    that centre)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    p = np.asarray(point, dtype=np.float64)
    u, v = tangent_basis(n)
    if positions.shape[1]:
        c0 = positions[0].mean(axis=0)
        centre = c0 - np.dot(c0 - p, n) * n
        d = positions.reshape(-1, 3) - centre
        spread = float(np.sqrt(np.max((d @ u) ** 2 + (d @ v) ** 2)))
    else:
        centre, spread = p, 0.0
    h = max(1.0, 2.0 * spread)
    return np.array([centre - h * u - h * v, centre + h * u - h * v,
                     centre + h * u + h * v, centre - h * u + h * v])


_CUBE_FACES = np.array(  # outward quads of the cuboid with corners indexed by bits (x, y, z)
    [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]],
    dtype=np.int32,
)


def _cuboid(lo, hi):
    bits = np.array([[(k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)])
    return np.where(bits == 1, hi, lo).astype(np.float64)


def _box_walls(box, up: int):
    """Vertices (8S, 3) and quad faces (6S, 4) of the slabs around a box collider:
    the walls and floor outside [lo, hi] with the box's thickness, and a lid
    unless the box is open at the top."""
    lo = np.asarray(box.lo, dtype=np.float64)
    hi = np.asarray(box.hi, dtype=np.float64)
    t = getattr(box, "thickness", None)
    t = float(t) if t is not None and float(t) > 0 else max(0.01, 0.02 * float(np.min(hi - lo)))
    open_top = bool(getattr(box, "open_top", False))
    outer_lo, outer_hi = lo - t, hi + t
    if open_top:
        outer_hi[up] = hi[up]
    verts, faces = [], []
    for axis in range(3):
        for side in (0, 1):
            if open_top and axis == up and side == 1:
                continue
            s_lo, s_hi = outer_lo.copy(), outer_hi.copy()
            if side == 0:
                s_hi[axis] = lo[axis]
            else:
                s_lo[axis] = hi[axis]
            faces.append(_CUBE_FACES + 8 * len(verts))
            verts.append(_cuboid(s_lo, s_hi))
    return np.concatenate(verts), np.concatenate(faces)


def collider_names(model) -> list[str]:
    """The prim names under /World/Colliders, in order: ``plane_<i>``, ``box_<i>``,
    then the static meshes' names (made valid and unique)."""
    n_planes = len(np.asarray(getattr(model, "plane_point", np.zeros((0, 3)))).reshape(-1, 3))
    n_boxes = len(tuple(getattr(model, "boxes", ()) or ()))
    statics = tuple(getattr(model, "static_meshes", ()) or ())
    reserved = [f"plane_{i}" for i in range(n_planes)] + [f"box_{i}" for i in range(n_boxes)]
    return reserved + unique_names(reserved + [m.name for m in statics])[len(reserved):]


def author_colliders(layer, world, source, scan, model, material, sparse=True) -> int:
    """The colliders under /World/Colliders (geometry in world coordinates); the
    animated ones (``model.collider_motions``) with time-sampled xformOps.
    Returns the time samples written."""
    mpu = float(model.meters_per_unit)
    up = {"Y": 1, "Z": 2}[str(model.up_axis).upper()]
    plane_point = np.asarray(getattr(model, "plane_point", np.zeros((0, 3)))).reshape(-1, 3)
    plane_normal = np.asarray(getattr(model, "plane_normal", np.zeros((0, 3)))).reshape(-1, 3)
    boxes = tuple(getattr(model, "boxes", ()) or ())
    statics = tuple(getattr(model, "static_meshes", ()) or ())
    if not (len(plane_point) or boxes or statics):
        return 0
    moving = {(str(m.kind), int(m.index)): m for m in getattr(model, "collider_motions", ()) or ()}
    times, numbers = scan.times, scan.numbers
    n = 0
    col = Sdf.PrimSpec(world, "Colliders", SPEC_DEF, "Xform")
    # frame 0 and, per plane, the farthest position of all frames (samples.Scan)
    positions = scan.plane_positions(source, list(zip(plane_point, plane_normal))) \
        if len(plane_point) else None
    quad = np.array([[0, 1, 2, 3]], dtype=np.int32)
    for i, (p, nrm) in enumerate(zip(plane_point, plane_normal)):
        prim = Sdf.PrimSpec(col, f"plane_{i}", SPEC_DEF, "Mesh")
        verts = _plane_quad(p, nrm, positions)
        author_mesh(prim, verts / mpu, quad, COLLIDER_COLOR, material)
        m = moving.get(("plane", i))
        if m is not None:
            tr, ori = plane_xforms(m.motion, (m.ref_p, m.ref_q), m.origin, nrm,
                                   verts.mean(axis=0), times)
            n += _author_collider_motion(layer, prim, tr / mpu, ori, numbers, sparse)
    for i, box in enumerate(boxes):
        prim = Sdf.PrimSpec(col, f"box_{i}", SPEC_DEF, "Mesh")
        verts, faces = _box_walls(box, up)
        author_mesh(prim, verts / mpu, faces, COLLIDER_COLOR, material)
        n += _moving_collider(layer, prim, moving.get(("box", i)), times, numbers, mpu, sparse)
    names = collider_names(model)[len(plane_point) + len(boxes):]
    for i, (name, mesh) in enumerate(zip(names, statics)):
        prim = Sdf.PrimSpec(col, name, SPEC_DEF, "Mesh")
        author_mesh(prim, np.asarray(mesh.vertices, dtype=np.float64) / mpu, mesh.faces,
                    COLLIDER_COLOR, material)
        n += _moving_collider(layer, prim, moving.get(("mesh", i)), times, numbers, mpu, sparse)
    return n


def _moving_collider(layer, prim, m, times, numbers, mpu, sparse) -> int:
    """A box's or mesh's prim transform D(t) from its ColliderMotion ``m`` (None:
    static, nothing written)."""
    if m is None:
        return 0
    tr, ori = collider_xforms(m.motion, (m.ref_p, m.ref_q), m.origin, m.rotation, times)
    return _author_collider_motion(layer, prim, tr / mpu, ori, numbers, sparse)


def _author_collider_motion(layer, prim, translate, orient, numbers, sparse) -> int:
    """``xformOp:translate`` (F, 3) [stage units] and ``xformOp:orient`` (F, 4)
    (w, x, y, z), double precision, at time codes ``numbers`` (F,); sparse: the
    kept samples of kept_samples, a default only where nothing changes.
    Returns the time samples written."""
    t_spec = author_attr(prim, "xformOp:translate", SDF_TYPES.Double3)
    o_spec = author_attr(prim, "xformOp:orient", SDF_TYPES.Quatd)
    author_attr(prim, "xformOpOrder", SDF_TYPES.TokenArray,
                Vt.TokenArray(["xformOp:translate", "xformOp:orient"]), uniform=True)
    orient = flush_tiny(np.array(orient, dtype=np.float64))
    values = np.concatenate([translate, orient], axis=1)

    def quat(q):
        return Gf.Quatd(float(q[0]), Gf.Vec3d(float(q[1]), float(q[2]), float(q[3])))

    if sparse and bool(constant_columns(values[:, None])[0]):
        t_spec.default = Gf.Vec3d(*map(float, translate[0]))
        o_spec.default = quat(orient[0])
        return 0
    keep = kept_samples(values[:, None])[:, 0] if sparse else np.ones(len(values), bool)
    for f in np.flatnonzero(keep):
        layer.SetTimeSample(t_spec.path, float(numbers[f]), Gf.Vec3d(*map(float, translate[f])))
        layer.SetTimeSample(o_spec.path, float(numbers[f]), quat(orient[f]))
    return 2 * int(keep.sum())
