"""Meshes and their looks: polygon mesh prims with crease-angle normals, one
UsdPreviewSurface material per shape and one for the colliders.

    author_mesh(prim, vertices, faces, color, material)  # points, topology, normals
    corner_normals(vertices, faces)                       # faceted at sharp edges

Bodies cycle through ``PALETTE`` by shape; colliders are grey. Lengths are in
stage units (the caller divides by ``model.meters_per_unit``).
"""

from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Vt

from dempipe.usd.authoring import SPEC_DEF, SDF_TYPES, author_attr, unique_names

# Display colours: bodies cycle through a palette by shape, colliders are grey.
PALETTE = np.array(
    [
        [0.85, 0.33, 0.10], [0.00, 0.45, 0.74], [0.47, 0.67, 0.19],
        [0.93, 0.69, 0.13], [0.49, 0.18, 0.56], [0.30, 0.75, 0.93],
        [0.64, 0.08, 0.18], [0.90, 0.90, 0.85],
    ],
    dtype=np.float32,
)
COLLIDER_COLOR = (0.55, 0.55, 0.55)
# The broken faces of fracture pieces: a pale, rough fresh-break colour.
INSIDE_COLOR = (0.82, 0.78, 0.70)


def author_mesh(prim, vertices, faces, color, material=None, inside=None) -> None:
    """Points, topology, extent, normals, displayColor and material of a polygon mesh prim.

    ``material``: the path of a ``UsdShade.Material`` to bind (``material:binding``),
    so that DCC tools show ``color`` by default: most ignore ``displayColor`` unless a
    material reads it (Blender, Maya, Omniverse), and usdview draws the material too.
    ``inside``: (face indices, material path) of a fracture piece's broken faces:
    a ``GeomSubset`` "inside" of the materialBind family bound to that material.
    """
    pts = np.ascontiguousarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int32)
    author_attr(prim, "points", SDF_TYPES.Point3fArray, Vt.Vec3fArray.FromNumpy(pts))
    author_attr(prim, "faceVertexCounts", SDF_TYPES.IntArray,
                Vt.IntArray.FromNumpy(np.full(len(faces), faces.shape[1] if faces.ndim == 2 else 3,
                                        dtype=np.int32)))
    author_attr(prim, "faceVertexIndices", SDF_TYPES.IntArray,
                Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.reshape(-1))))
    if len(pts):
        ext = np.stack([pts.min(axis=0), pts.max(axis=0)])
    else:
        ext = np.zeros((2, 3), np.float32)
    author_attr(prim, "extent", SDF_TYPES.Float3Array, Vt.Vec3fArray.FromNumpy(ext))
    author_attr(prim, "subdivisionScheme", SDF_TYPES.Token, "none", uniform=True)
    if len(faces):
        normals = author_attr(prim, "normals", SDF_TYPES.Normal3fArray, Vt.Vec3fArray.FromNumpy(
            np.ascontiguousarray(corner_normals(vertices, faces), dtype=np.float32)))
        normals.SetInfo("interpolation", "faceVarying")
    col = author_attr(prim, "primvars:displayColor", SDF_TYPES.Color3fArray,
                      Vt.Vec3fArray([Gf.Vec3f(*map(float, color))]))
    col.SetInfo("interpolation", "constant")
    if material is not None:
        prim.SetInfo("apiSchemas", Sdf.TokenListOp.CreateExplicit(["MaterialBindingAPI"]))
        rel = Sdf.RelationshipSpec(prim, "material:binding", custom=False)
        rel.targetPathList.explicitItems = [material]
    if inside is not None and len(inside[0]):
        _author_subset(prim, "inside", inside[0], inside[1])


def _author_subset(prim, name, face_indices, material) -> None:
    """A face ``GeomSubset`` of the materialBind family bound to ``material``: how
    every DCC and renderer reads per-face materials (UsdShade subsets)."""
    author_attr(prim, "subsetFamily:materialBind:familyType", SDF_TYPES.Token, "nonOverlapping",
                uniform=True)
    sub = Sdf.PrimSpec(prim, name, SPEC_DEF, "GeomSubset")
    author_attr(sub, "elementType", SDF_TYPES.Token, "face", uniform=True)
    author_attr(sub, "familyName", SDF_TYPES.Token, "materialBind", uniform=True)
    author_attr(sub, "indices", SDF_TYPES.IntArray,
                Vt.IntArray.FromNumpy(np.ascontiguousarray(face_indices, dtype=np.int32)))
    sub.SetInfo("apiSchemas", Sdf.TokenListOp.CreateExplicit(["MaterialBindingAPI"]))
    rel = Sdf.RelationshipSpec(sub, "material:binding", custom=False)
    rel.targetPathList.explicitItems = [material]


#: Faces meeting at a smaller angle than this share their normals at a corner
#: (smooth shading); at a larger one the edge stays sharp. Blender's default
#: "auto smooth" angle: a box stays faceted, a revolved chess piece is smooth
#: between its 11.25-degree segments and sharp at the rim of its base.
CREASE_ANGLE_DEG = 30.0


def corner_normals(vertices, faces, crease_deg: float = CREASE_ANGLE_DEG) -> np.ndarray:
    """Face-varying normals (F * K, 3) of a polygon mesh (K corners a face).

    At each corner, the area-weighted mean of the normals of the faces that share
    its vertex and lie within ``crease_deg`` of the corner's own face: faceted
    where faces meet at a sharp angle, smooth across shallow ones (what Houdini's
    cusp angle and Blender's auto smooth do). Without authored normals every DCC
    smooths the whole mesh, so a box looks like a pillow. Deterministic (sums in a
    fixed order).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    k = f.shape[1]
    # Polygon normal by Newell's method (area-weighted; exact for triangles).
    p = v[f]
    q = np.roll(p, -1, axis=1)
    fn = np.stack([((p[..., 1] - q[..., 1]) * (p[..., 2] + q[..., 2])).sum(1),
                   ((p[..., 2] - q[..., 2]) * (p[..., 0] + q[..., 0])).sum(1),
                   ((p[..., 0] - q[..., 0]) * (p[..., 1] + q[..., 1])).sum(1)], axis=1)
    length = np.linalg.norm(fn, axis=1, keepdims=True)
    unit = fn / np.where(length > 0, length, 1.0)
    corner_v = f.reshape(-1)
    corner_f = np.repeat(np.arange(len(f)), k)
    # Every (corner, face at the corner's vertex) pair, grouped by vertex.
    order = np.argsort(corner_v, kind="stable")
    count = np.bincount(corner_v, minlength=len(v))
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    n_at = count[corner_v[order]]                      # faces at each sorted corner's vertex
    i = np.repeat(np.arange(len(order)), n_at)         # sorted corner of each pair
    first = start[corner_v[order]]
    run = np.repeat(np.cumsum(n_at) - n_at, n_at)
    j = first[i] + (np.arange(len(i)) - run)           # sorted corner giving the face
    c, g = order[i], corner_f[order[j]]
    near = (unit[g] * unit[corner_f[c]]).sum(1) >= np.cos(np.radians(crease_deg)) - 1e-9
    c, g = c[near], g[near]
    out = np.stack([np.bincount(c, weights=fn[g, a], minlength=len(corner_v))
                    for a in range(3)], axis=1)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    flat = unit[corner_f]
    return np.where(norm > 0, out / np.where(norm > 0, norm, 1.0), flat)


def author_material(looks, name, color):
    """A ``UsdPreviewSurface`` material of diffuse ``color`` under ``looks``; its path.

    Every renderer and DCC importer reads UsdPreviewSurface; the diffuse colour
    also reads as the object's colour in viewports. Authored with Sdf like the rest.
    """
    mat = Sdf.PrimSpec(looks, name, SPEC_DEF, "Material")
    shader = Sdf.PrimSpec(mat, "PreviewSurface", SPEC_DEF, "Shader")
    author_attr(shader, "info:id", SDF_TYPES.Token, "UsdPreviewSurface", uniform=True)
    author_attr(shader, "inputs:diffuseColor", SDF_TYPES.Color3f, Gf.Vec3f(*map(float, color)))
    author_attr(shader, "inputs:roughness", SDF_TYPES.Float, 0.6)
    author_attr(shader, "inputs:metallic", SDF_TYPES.Float, 0.0)
    out = author_attr(shader, "outputs:surface", SDF_TYPES.Token)
    surface = author_attr(mat, "outputs:surface", SDF_TYPES.Token)
    surface.connectionPathList.explicitItems = [out.path]
    return mat.path


def shape_materials(world, model):
    """One material per shape (its palette colour), one for the colliders and, when
    a shape is a fracture piece, one for the broken faces: ``(shape material paths,
    collider material path, inside material path or None)`` under ``/World/Looks``."""
    looks = Sdf.PrimSpec(world, "Looks", SPEC_DEF, "Scope")
    names = unique_names([f"{s.name}_mat" for s in model.shapes]
                         + ["collider_mat", "inside_mat"])
    paths = [author_material(looks, n, PALETTE[i % len(PALETTE)])
             for i, n in enumerate(names[:-2])]
    inside = None
    if any(getattr(s, "inside_faces", None) is not None for s in model.shapes):
        inside = author_material(looks, names[-1], INSIDE_COLOR)
    return paths, author_material(looks, names[-2], COLLIDER_COLOR), inside


def broken_faces(shape, inside_material):
    """``author_mesh``'s ``inside`` for a shape: its broken faces and their material."""
    if inside_material is None or getattr(shape, "inside_faces", None) is None:
        return None
    return shape.inside_faces, inside_material


def shape_points(model, mpu):
    """Body-frame prototype points in stage units, one array per shape."""
    return [np.asarray(s.vertices, dtype=np.float64) / mpu for s in model.shapes]
