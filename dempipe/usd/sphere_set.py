"""A sphere set written to look at: the mesh and its spheres side by side in the body
frame (USD), or the set's arrays (.npz). What `dempipe spheres -o` writes."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from dempipe.errors import ExportError
from dempipe.spheres.sphere_set import SphereSet

USD_SUFFIXES = (".usda", ".usdc", ".usd")


def _atomic_target(path):
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.tmp-", suffix=path.suffix, dir=folder)
    os.close(fd)
    return path, tmp


def save_sphere_set(path, sphere_set: SphereSet, mesh=None, name=None) -> None:
    """Write ``sphere_set`` to ``path`` atomically (temporary file + os.replace).

    ``.npz``: keys ``centers`` (N, 3) float32 body frame [m], ``diameter`` [m], ``com``
    (3,) [m], ``volume`` [m^3], ``inertia`` (3, 3) per unit density [m^5], ``mesh_sha256``.
    ``.usda`` / ``.usdc`` / ``.usd``: the mesh (needed) and the spheres side by side in
    the body frame, a UsdGeomMesh and a UsdGeomPoints with widths = diameter, under one
    Xform that is the stage's defaultPrim (upAxis Z, metersPerUnit 1).
    Raises ExportError when the file cannot be written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix != ".npz" and suffix not in USD_SUFFIXES:
        raise ExportError(f"{path}: unknown output type {path.suffix!r} "
                          "(use .npz, .usda, .usdc or .usd)")
    if suffix in USD_SUFFIXES and mesh is None:
        raise ExportError(f"{path}: writing USD needs the mesh as well as the spheres")
    tmp = None
    try:
        path, tmp = _atomic_target(path)
        if suffix == ".npz":
            with open(tmp, "wb") as f:
                np.savez(
                    f,
                    centers=np.asarray(sphere_set.centers, dtype=np.float32),
                    diameter=np.float64(sphere_set.diameter),
                    com=np.asarray(sphere_set.com, dtype=np.float64),
                    volume=np.float64(sphere_set.volume),
                    inertia=np.asarray(sphere_set.inertia, dtype=np.float64),
                    mesh_sha256=np.str_(sphere_set.mesh_sha256),
                )
                f.flush()
                os.fsync(f.fileno())
        else:
            _write_usd(tmp, sphere_set, mesh, name or path.stem)
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        raise ExportError(f"{path}: cannot write ({exc.strerror or exc})") from None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass


def _write_usd(file_path, sphere_set: SphereSet, mesh, name: str) -> None:
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt


    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, Sdf.Path("/" + Tf.MakeValidIdentifier(str(name))))
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind("component")

    vertices = np.asarray(mesh.vertices, dtype=np.float64) - sphere_set.com
    faces = np.asarray(mesh.faces, dtype=np.int32)
    geom = UsdGeom.Mesh.Define(stage, root.GetPath().AppendChild("mesh"))
    points = Vt.Vec3fArray.FromNumpy(vertices.astype(np.float32))
    geom.CreatePointsAttr(points)
    geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.ravel()))
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    geom.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
    geom.CreateDisplayColorAttr([Gf.Vec3f(0.8, 0.8, 0.8)])
    geom.CreateDisplayOpacityAttr([0.3])

    spheres = UsdGeom.Points.Define(stage, root.GetPath().AppendChild("spheres"))
    centers = Vt.Vec3fArray.FromNumpy(np.asarray(sphere_set.centers, dtype=np.float32))
    widths = Vt.FloatArray.FromNumpy(np.full(sphere_set.count, sphere_set.diameter, dtype=np.float32))
    spheres.CreatePointsAttr(centers)
    spheres.CreateWidthsAttr(widths)
    spheres.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    spheres.CreateExtentAttr(UsdGeom.Points.ComputeExtent(centers, widths))
    spheres.CreateDisplayColorAttr([Gf.Vec3f(0.9, 0.4, 0.1)])
    doc = (f"{sphere_set.count} spheres of diameter {sphere_set.diameter:.6g} m; "
           f"volume error {100 * sphere_set.sphere_volume_error:+.2f}%")
    root.GetPrim().SetDocumentation(doc)
    if not stage.GetRootLayer().Export(str(file_path)):
        raise ExportError(f"{file_path}: USD export failed")


def save_fractured(path, fractured, name=None, explode: float = 0.15) -> None:
    """Write a fractured shape's pieces to look at (``.usda`` / ``.usdc`` / ``.usd``):
    one Xform per piece (``piece_07``) holding its mesh, its broken faces as a
    materialBind ``GeomSubset`` "inside" bound to their own material, and its
    spheres (UsdGeomPoints), in the parent's coordinates [m], each piece moved out
    from the parent's centre of mass by ``explode`` times its own offset so the
    cuts show. Atomic; raises ExportError when the file cannot be written.
    """
    path = Path(path)
    if path.suffix.lower() not in USD_SUFFIXES:
        raise ExportError(f"{path}: pieces are written as USD (use .usda, .usdc or .usd)")
    tmp = None
    try:
        path, tmp = _atomic_target(path)
        _write_pieces(tmp, fractured, name or path.stem, explode)
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        raise ExportError(f"{path}: cannot write ({exc.strerror or exc})") from None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass


def _write_pieces(file_path, fractured, name: str, explode: float) -> None:
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdShade, Vt

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, Sdf.Path("/" + Tf.MakeValidIdentifier(str(name))))
    stage.SetDefaultPrim(root.GetPrim())
    looks = root.GetPath().AppendChild("Looks")

    def material(label, color):
        mat = UsdShade.Material.Define(stage, looks.AppendChild(label))
        shader = UsdShade.Shader.Define(stage, mat.GetPath().AppendChild("PreviewSurface"))
        shader.CreateIdAttr("UsdPreviewSurface")
        shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*color))
        mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        return mat

    outside, inside = material("outside_mat", (0.6, 0.6, 0.65)), material("inside_mat", (0.82, 0.78, 0.70))
    vols = np.array([s.volume for s in fractured.sphere_sets])
    coms = np.array([s.com for s in fractured.sphere_sets]).reshape(-1, 3)
    parent_com = (vols[:, None] * coms).sum(axis=0) / vols.sum()
    for k, (piece, ss) in enumerate(zip(fractured.pieces, fractured.sphere_sets)):
        xf = UsdGeom.Xform.Define(stage, root.GetPath().AppendChild(f"piece_{k:02d}"))
        xf.AddTranslateOp().Set(Gf.Vec3d(*(explode * (coms[k] - parent_com)).tolist()))
        geom = UsdGeom.Mesh.Define(stage, xf.GetPath().AppendChild("mesh"))
        pts = Vt.Vec3fArray.FromNumpy(np.asarray(piece.vertices, dtype=np.float32))
        faces = np.asarray(piece.faces, dtype=np.int32)
        geom.CreatePointsAttr(pts)
        geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.ravel()))
        geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        geom.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(pts))
        UsdShade.MaterialBindingAPI.Apply(geom.GetPrim()).Bind(outside)
        idx = np.flatnonzero(piece.inside).astype(np.int32)
        if len(idx):
            sub = UsdGeom.Subset.CreateGeomSubset(geom, "inside", UsdGeom.Tokens.face,
                                                  Vt.IntArray.FromNumpy(idx),
                                                  UsdShade.Tokens.materialBind,
                                                  UsdGeom.Tokens.nonOverlapping)
            UsdShade.MaterialBindingAPI.Apply(sub.GetPrim()).Bind(inside)
        spheres = UsdGeom.Points.Define(stage, xf.GetPath().AppendChild("spheres"))
        centers = Vt.Vec3fArray.FromNumpy(np.asarray(ss.centers + ss.com, dtype=np.float32))
        widths = Vt.FloatArray.FromNumpy(np.full(ss.count, ss.diameter, dtype=np.float32))
        spheres.CreatePointsAttr(centers)
        spheres.CreateWidthsAttr(widths)
        spheres.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
        spheres.CreateExtentAttr(UsdGeom.Points.ComputeExtent(centers, widths))
        spheres.CreateVisibilityAttr(UsdGeom.Tokens.invisible)     # the meshes show the cut
        xf.GetPrim().SetDocumentation(f"{ss.count} spheres; volume {ss.volume:.6g} m^3")
    if not stage.GetRootLayer().Export(str(file_path)):
        raise ExportError(f"{file_path}: USD export failed")
