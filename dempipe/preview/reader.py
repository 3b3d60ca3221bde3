"""What a preview draws, read from any USD stage: meshes, their world transforms, colours.

Read generically through pxr, so it works on both dempipe layouts (a PointInstancer with
prototypes, or one Xform per body; docs/usd-output.md), on overlays of a USD input and on
stages written by other tools:

- a Mesh prim, or a Cube, Sphere, Cylinder, Capsule or Cone (tessellated as the
  UsdPhysics reader tessellates them: the bodies and colliders of a USD input shot), is
  drawn with its world transform from ``UsdGeom.XformCache`` at each time (instance
  proxies included, so the xforms layout's instanceable bodies are found);
- a PointInstancer draws the meshes and gprims under each prototype with
  ``ComputeInstanceTransformsAtTime`` (and its invisible-ids mask);
- visibility is computed at each frame where it is animated (emitted bodies stay hidden
  until their start);
- a mesh's colour is its bound UsdPreviewSurface's ``diffuseColor`` (what Hydra shows when a
  material is bound), else its ``displayColor`` primvar (the mean of a varying one), else grey.

Meshes sharing a topology (a prototype, or instance proxies of one prototype) are one
:class:`Geometry`; each frame is a list of :class:`Batch` es, one per geometry, holding the
instances' world matrices. Matrices follow pxr's row-vector convention: ``p_world = [p, 1] @ M``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dempipe.errors import DempipeError

USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")

#: The gprims drawn: what a UsdPhysics stage's bodies and colliders are made of.
DRAWN_TYPES = frozenset(("Mesh", "Cube", "Sphere", "Cylinder", "Capsule", "Cone"))

#: Colour of a mesh with neither a bound material nor a displayColor (USD's fallback grey).
DEFAULT_COLOR = (0.5, 0.5, 0.5)


def simplify(geom: Geometry, cell: float) -> Geometry:
    """A coarser copy of ``geom`` by vertex clustering: the points in each cube of edge
    ``cell`` merge into their mean; triangles that collapse are dropped. Keeps the
    silhouette to about a cell, which is all a preview of small bodies needs."""
    if cell <= 0 or not len(geom.triangles):
        return geom
    q = np.floor((geom.points - geom.lo) / cell).astype(np.int64)
    _, cluster, counts = np.unique(q, axis=0, return_inverse=True, return_counts=True)
    cluster = cluster.reshape(-1)
    pts = np.zeros((len(counts), 3))
    np.add.at(pts, cluster, geom.points)
    pts /= counts[:, None]
    tri = cluster[geom.triangles]
    keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    tri = tri[keep]
    if len(tri):
        tri = np.unique(tri, axis=0)   # (sorted rows would merge a face with its flip)
    return Geometry(geom.key, pts.astype(np.float32), tri.astype(np.int32))


class PreviewError(DempipeError):
    """A file cannot be previewed (not USD, nothing to draw, no such frame) or written."""


@dataclass
class Geometry:
    """One mesh's triangles in its own space (float32 points, int32 triangle indices)."""

    key: str
    points: np.ndarray
    triangles: np.ndarray
    lo: np.ndarray = field(init=False)
    hi: np.ndarray = field(init=False)

    def __post_init__(self):
        pts = self.points if len(self.points) else np.zeros((1, 3), np.float32)
        self.lo, self.hi = pts.min(axis=0), pts.max(axis=0)


@dataclass
class Batch:
    """Instances of one geometry at one time: world matrices (N, 4, 4) and colours (N, 3)."""

    geometry: Geometry
    matrices: np.ndarray
    colors: np.ndarray
    body: bool


@dataclass
class _MeshRef:
    prim: object            # Usd.Prim (possibly an instance proxy)
    key: str                # geometry key
    color: tuple
    body: bool
    animated_points: bool
    #: visibility animated on the prim or an ancestor: computed at each frame
    animated_visibility: bool = False


@dataclass
class _Instancer:
    prim: object
    # per prototype: list of (geometry key, colour, relative matrix or None if time-varying)
    protos: list
    body: bool = True


def _triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons (faceVertexCounts, faceVertexIndices) → (T, 3) int32."""
    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    if counts.size == 0 or counts.sum() != indices.size:
        return np.zeros((0, 3), np.int32)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n_tri = np.maximum(counts - 2, 0)
    face = np.repeat(np.arange(counts.size), n_tri)
    k = np.arange(n_tri.sum()) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    s = starts[face]
    tri = np.stack([indices[s], indices[s + k + 1], indices[s + k + 2]], axis=1)
    return tri.astype(np.int32)


def _gprim_key(prim) -> str:
    """A geometry key of a Cube, Sphere, Cylinder, Capsule or Cone: its type and the
    attributes that shape it, so equal gprims are one geometry."""
    attrs = [prim.GetAttribute(n).Get() for n in ("size", "radius", "height", "axis")]
    return f"{prim.GetTypeName()}{tuple(a for a in attrs if a is not None)!r}"


def _gprim_geometry(prim, key: str) -> Geometry:
    """A gprim tessellated as the UsdPhysics reader does (scene.usd_geometry); nothing
    drawn for one whose sizes are unusable."""
    from dempipe.errors import SceneError
    from dempipe.scene.usd_geometry import gprim_mesh

    try:
        mesh = gprim_mesh(prim, str(prim.GetPath()))
    except SceneError:
        mesh = None
    if mesh is None:
        return Geometry(key, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    return Geometry(key, np.asarray(mesh.vertices, np.float32),
                    np.asarray(mesh.faces, np.int32))


def _visibility_varies(prim, sampled: set | None) -> bool:
    """Whether ``prim``'s or an ancestor's visibility is animated (and adds its
    sample times to ``sampled``)."""
    from pxr import UsdGeom

    varies = False
    p = prim
    while p and not p.IsPseudoRoot():
        img = UsdGeom.Imageable(p)
        if img:
            attr = img.GetVisibilityAttr()
            if attr.ValueMightBeTimeVarying():
                varies = True
                if sampled is not None:
                    sampled.update(attr.GetTimeSamples())
        p = p.GetParent()
    return varies


def _color_of(prim, time) -> tuple:
    """Bound UsdPreviewSurface diffuseColor, else displayColor, else DEFAULT_COLOR."""
    from pxr import UsdGeom, UsdShade

    try:
        material = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
    except Exception:   # a malformed binding: fall back to displayColor, as Hydra does
        material = None
    if material:
        shader = material.ComputeSurfaceSource()[0]
        if shader and shader.GetIdAttr().Get() == "UsdPreviewSurface":
            inp = shader.GetInput("diffuseColor")
            value = None
            if inp:
                attrs = inp.GetValueProducingAttributes()
                attr = attrs[0] if attrs else inp.GetAttr()
                value = attr.Get(time) if attr.GetTypeName() == "color3f" else None
            if value is None:
                value = (0.18, 0.18, 0.18)   # UsdPreviewSurface's documented default
            return tuple(float(c) for c in value)
    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
    if primvar and primvar.HasValue():
        value = primvar.Get(time)
        if value is not None and len(value):
            return tuple(float(c) for c in np.asarray(value, dtype=np.float64).reshape(-1, 3)
                         .mean(axis=0))
    return DEFAULT_COLOR


class StageReader:
    """An opened USD stage, ready to give what to draw at each frame.

    ``frames`` are the integer time codes from the stage's startTimeCode to endTimeCode
    (a stage without a time range: the times its transforms are sampled at, else [0]).
    """

    def __init__(self, path):
        self.path = Path(path)
        from pxr import Usd, UsdGeom

        if not self.path.is_file():
            raise PreviewError(f"{self.path}: no such file")
        if self.path.suffix.lower() not in USD_EXTENSIONS:
            raise PreviewError(f"{self.path}: not a USD file (expected a dempipe bake: "
                               f"{', '.join(USD_EXTENSIONS)})")
        from dempipe.scene.usd_stage import captured_stderr, pxr_reason

        said: list = []
        try:
            with captured_stderr(said):     # pxr's C++ diagnostics: one line, below
                stage = Usd.Stage.Open(str(self.path), Usd.Stage.LoadAll)
        except Exception as exc:    # pxr.Tf.ErrorException: not USD, or corrupt
            text = " ".join(str(exc).split())
            why = pxr_reason(said) or (text.rsplit(" : ", 1)[-1].strip("' ") if text
                                       else type(exc).__name__)
            raise PreviewError(f"{self.path}: not a USD file pxr can open ({why})") from None
        if stage is None:
            raise PreviewError(f"{self.path}: not a USD file pxr can open")
        if said:    # a sublayer (an overlay's input stage) or reference that is missing
            raise PreviewError(f"{self.path}: the stage does not compose whole "
                               f"({pxr_reason(said)}); restore the missing layer")
        self.stage = stage
        self.up_axis = str(UsdGeom.GetStageUpAxis(stage)).upper()
        self.fps = float(stage.GetFramesPerSecond() or stage.GetTimeCodesPerSecond() or 24.0)
        meta = dict(stage.GetRootLayer().customLayerData or {})
        self.dempipe = dict(meta.get("dempipe", {}) or {})
        self._geometries: dict[str, Geometry] = {}
        self._meshes: list[_MeshRef] = []
        self._instancers: list[_Instancer] = []
        sampled = None if stage.HasAuthoredTimeCodeRange() else set()
        self._collect(sampled)
        if not self._meshes and not self._instancers:
            raise PreviewError(
                f"{self.path}: no Mesh, gprim or PointInstancer prims to draw; not a dempipe bake "
                f"(bake one with `dempipe bake SCENE -o {self.path.name}`)")
        if stage.HasAuthoredTimeCodeRange():
            start, end = stage.GetStartTimeCode(), stage.GetEndTimeCode()
            self.frames = list(range(math.ceil(start), math.floor(end) + 1))
            if not self.frames:
                raise PreviewError(f"{self.path}: no frames (startTimeCode {start:g} is after "
                                   f"endTimeCode {end:g})")
        else:
            times = sorted({int(round(t)) for t in sampled})  # type: ignore[union-attr]
            self.frames = times or [0]

    # ------------------------------------------------------------------ traversal

    def _geometry(self, mesh_prim, key, time):
        from pxr import UsdGeom

        geom = self._geometries.get(key)
        if geom is None and not mesh_prim.IsA(UsdGeom.Mesh):
            geom = _gprim_geometry(mesh_prim, key)
            self._geometries[key] = geom
        elif geom is None:
            mesh = UsdGeom.Mesh(mesh_prim)
            pts = mesh.GetPointsAttr().Get(time)
            counts = mesh.GetFaceVertexCountsAttr().Get(time)
            idx = mesh.GetFaceVertexIndicesAttr().Get(time)
            pts = np.asarray(pts if pts is not None else [], dtype=np.float32).reshape(-1, 3)
            tri = _triangulate(counts if counts is not None else [], idx if idx is not None else [])
            tri = tri[(tri < len(pts)).all(axis=1)] if len(tri) else tri
            geom = Geometry(key, pts, tri)
            self._geometries[key] = geom
        return geom

    def _is_body(self, prim, moving_cache) -> bool:
        """A body: under dempipe's /World/Bodies, else any mesh whose transform animates."""
        path = str(prim.GetPath())
        if self.dempipe:
            return "/Colliders" not in path
        from pxr import UsdGeom

        p = prim
        chain = []
        while p and not p.IsPseudoRoot():
            key = str(p.GetPath())
            if key in moving_cache:
                moving = moving_cache[key]
                break
            chain.append(key)
            xf = UsdGeom.Xformable(p)
            if xf and xf.TransformMightBeTimeVarying():
                moving = True
                break
            p = p.GetParent()
        else:
            moving = False
        for key in chain:
            moving_cache[key] = moving
        return moving

    def _collect(self, sampled: set | None) -> None:
        from pxr import Usd, UsdGeom

        stage = self.stage
        predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        default = Usd.TimeCode.Default()
        # Prototypes of point instancers are drawn only through their instancer.
        skip = set()
        instancers = []
        for prim in stage.Traverse(predicate):
            if prim.IsA(UsdGeom.PointInstancer):
                instancers.append(prim)
                skip.update(str(t) for t in
                            UsdGeom.PointInstancer(prim).GetPrototypesRel().GetTargets())
        moving = {}
        it = iter(Usd.PrimRange.Stage(stage, predicate))
        for prim in it:
            path = str(prim.GetPath())
            img = UsdGeom.Imageable(prim)
            vis = img.GetVisibilityAttr() if img else None
            if path in skip or prim.IsA(UsdGeom.PointInstancer) or (
                    img and ((not vis.ValueMightBeTimeVarying()
                              and vis.Get() == UsdGeom.Tokens.invisible)
                             or img.GetPurposeAttr().Get() in (UsdGeom.Tokens.guide,
                                                               UsdGeom.Tokens.proxy))):
                it.PruneChildren()      # never visible (animated visibility: per frame)
                continue
            xf = UsdGeom.Xformable(prim)
            if sampled is not None and xf and not prim.IsInstanceProxy():
                for op in xf.GetOrderedXformOps():
                    sampled.update(op.GetTimeSamples())
            if prim.GetTypeName() not in DRAWN_TYPES:
                continue
            source = prim.GetPrimInPrototype() if prim.IsInstanceProxy() else prim
            key = str(source.GetPath())
            animated = False
            if prim.IsA(UsdGeom.Mesh):
                points_attr = UsdGeom.Mesh(prim).GetPointsAttr()
                animated = points_attr.ValueMightBeTimeVarying()
                if animated:
                    key = path      # deforming: its own geometry, re-read at each frame
                    if sampled is not None:
                        sampled.update(points_attr.GetTimeSamples())
            else:
                key = _gprim_key(prim)      # equal gprims share one geometry
            self._geometry(prim, key, default)
            self._meshes.append(_MeshRef(prim, key, _color_of(prim, default),
                                         self._is_body(prim, moving), animated,
                                         _visibility_varies(prim, sampled)))
        for prim in instancers:
            inst = UsdGeom.PointInstancer(prim)
            for attr in (inst.GetPositionsAttr(), inst.GetOrientationsAttr(),
                         inst.GetScalesAttr(), inst.GetProtoIndicesAttr()):
                if sampled is not None:
                    sampled.update(attr.GetTimeSamples())
            protos = []
            for target in inst.GetPrototypesRel().GetTargets():
                root = stage.GetPrimAtPath(target)
                meshes = []
                if root:
                    for p in Usd.PrimRange(root, predicate):
                        if p.GetTypeName() in DRAWN_TYPES:
                            source = p.GetPrimInPrototype() if p.IsInstanceProxy() else p
                            key = (str(source.GetPath()) if p.IsA(UsdGeom.Mesh)
                                   else _gprim_key(p))
                            self._geometry(p, key, default)
                            meshes.append((key, _color_of(p, default), p, root))
                protos.append(meshes)
            self._instancers.append(_Instancer(prim, protos))

    # --------------------------------------------------------------------- frames

    def simplify_bodies(self, budget: int, batches) -> int:
        """Coarsen the bodies' shared geometries (vertex clustering) until the instanced
        triangles of ``batches`` are at most ``budget``; returns the triangles left."""
        used: dict[str, int] = {}
        total = 0
        for b in batches:
            total += len(b.geometry.triangles) * len(b.matrices)
            if b.body and len(b.matrices) > 1:
                used[b.geometry.key] = used.get(b.geometry.key, 0) + len(b.matrices)
        original = {k: self._geometries[k] for k in used}
        divisions = 48
        while total > budget and used and divisions >= 6:
            total = sum(len(b.geometry.triangles) * len(b.matrices) for b in batches
                        if b.geometry.key not in used)
            for key, n in used.items():
                g = original[key]
                diag = float(np.linalg.norm(g.hi - g.lo))
                self._geometries[key] = simplify(g, diag / divisions)
                total += len(self._geometries[key].triangles) * n
            divisions = divisions * 2 // 3
        return total

    def check_frame(self, frame: int) -> None:
        if frame not in self.frames:
            raise PreviewError(f"--frame {frame}: outside {self.path.name}'s frames "
                               f"{self.frames[0]}:{self.frames[-1]}")

    def batches(self, frame) -> list[Batch]:
        """What to draw at time code ``frame``: one Batch per geometry and kind (body or not)."""
        from pxr import Usd, UsdGeom

        time = Usd.TimeCode(frame)
        cache = UsdGeom.XformCache(time)
        groups: dict[tuple, tuple[list, list]] = {}

        def add(key, body, matrices, colors):
            mats, cols = groups.setdefault((key, body), ([], []))
            mats.append(matrices)
            cols.append(colors)

        for ref in self._meshes:
            if ref.animated_visibility and (UsdGeom.Imageable(ref.prim).ComputeVisibility(time)
                                            == UsdGeom.Tokens.invisible):
                continue
            key = ref.key
            if ref.animated_points:
                self._geometries.pop(key, None)
                self._geometry(ref.prim, key, time)
            m = np.asarray(cache.GetLocalToWorldTransform(ref.prim), dtype=np.float64)
            add(key, ref.body, m[None], np.asarray([ref.color]))
        for inst in self._instancers:
            pi = UsdGeom.PointInstancer(inst.prim)
            xf = np.asarray(pi.ComputeInstanceTransformsAtTime(time, time), dtype=np.float64)
            if not len(xf):
                continue
            xf = xf.reshape(-1, 4, 4)
            idx = np.asarray(pi.GetProtoIndicesAttr().Get(time), dtype=np.int64)[:len(xf)]
            mask = pi.ComputeMaskAtTime(time)
            keep = np.ones(len(xf), bool) if not mask else np.asarray(mask, bool)[:len(xf)]
            world = xf @ np.asarray(cache.GetLocalToWorldTransform(inst.prim), np.float64)
            for p, meshes in enumerate(inst.protos):
                sel = world[(idx == p) & keep]
                if not len(sel):
                    continue
                for key, color, mesh_prim, root in meshes:
                    # the prototype root's own transform applies before the instance's
                    rel = (np.asarray(cache.GetLocalToWorldTransform(mesh_prim), np.float64)
                           @ np.linalg.inv(np.asarray(
                               cache.GetParentToWorldTransform(root), np.float64)))
                    add(key, inst.body, rel @ sel, np.broadcast_to(color, (len(sel), 3)))
        out = []
        for (key, body), (mats, cols) in groups.items():
            geom = self._geometries[key]
            if not len(geom.triangles):
                continue
            out.append(Batch(geom, np.concatenate(mats), np.concatenate(cols).astype(np.float32),
                             body))
        return out


def batch_bounds(batches, bodies_only=True):
    """World AABB (lo, hi) of the batches' instances (their meshes' boxes, transformed)."""
    los, his = [], []
    for b in batches:
        if bodies_only and not b.body:
            continue
        g = b.geometry
        corners = np.array([[x, y, z, 1.0] for x in (g.lo[0], g.hi[0]) for y in (g.lo[1], g.hi[1])
                            for z in (g.lo[2], g.hi[2])])
        w = corners @ b.matrices        # (N, 8, 4)
        w = w[..., :3]
        los.append(w.min(axis=(0, 1)))
        his.append(w.max(axis=(0, 1)))
    if not los:
        return None
    return np.min(los, axis=0), np.max(his, axis=0)
