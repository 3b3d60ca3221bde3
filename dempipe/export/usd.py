"""Frames → USD: a baked rigid-body animation that DCC tools open as is.

Two layouts (see ``docs/usd-output.md``):

``"instancer"`` (default)
    One ``UsdGeom.PointInstancer`` at ``/World/Bodies`` whose prototypes are the
    shapes' meshes; per frame ``positions``, ``orientations``, ``velocities``,
    ``angularVelocities`` and ``extent``. Compact and fast; Houdini, usdview,
    Omniverse and Blender (4.x) read it.
``"xforms"``
    One instanceable ``Xform`` per body at ``/World/Bodies/<group>/<group>_<i>``
    referencing a class prototype ``/World/Prototypes/<shape>``, with time-sampled
    ``xformOp:translate`` and ``xformOp:orient``. Every body is a selectable
    prim (what Maya and Blender users expect).

Everything is authored with the Sdf API on an anonymous layer (no stage change
processing per edit), then exported to a temporary file next to the target and
moved over it with :func:`os.replace`, so a failed export never leaves a
half-written file behind.

Conventions: dempipe quaternions are (w, x, y, z); GfQuat memory layout is
(x, y, z, w), and the conversion happens here only. USD angular velocities are
in degrees per second. Lengths are divided by ``model.meters_per_unit``.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Tf, Vt

from .. import __version__
from ..errors import ExportError
from .prescribed import collider_xforms, first_shown_frame, plane_xforms
from .samples import Scan, SparseTrack, as_source

__all__ = ["ExportInfo", "write_usd", "LAYOUTS", "EXTENSIONS"]

LAYOUTS = ("instancer", "xforms")
EXTENSIONS = (".usd", ".usdc", ".usda")

_T = Sdf.ValueTypeNames
_DEF = Sdf.SpecifierDef
_CLASS = Sdf.SpecifierClass
_UNIFORM = Sdf.VariabilityUniform

# Display colours: bodies cycle through a palette by shape, colliders are grey.
_PALETTE = np.array(
    [
        [0.85, 0.33, 0.10], [0.00, 0.45, 0.74], [0.47, 0.67, 0.19],
        [0.93, 0.69, 0.13], [0.49, 0.18, 0.56], [0.30, 0.75, 0.93],
        [0.64, 0.08, 0.18], [0.90, 0.90, 0.85],
    ],
    dtype=np.float32,
)
_COLLIDER_COLOR = (0.55, 0.55, 0.55)


@dataclass(frozen=True)
class ExportInfo:
    """What :func:`write_usd` wrote.

    Attributes
    ----------
    path : Path
        The file written.
    seconds : float
        Wall time of the export (authoring + writing + rename) [s].
    n_time_samples : int
        Time samples written, summed over all attributes.
    bytes : int
        Size of the written file.
    """

    path: Path
    seconds: float
    n_time_samples: int
    bytes: int


# --------------------------------------------------------------------------- entry


def write_usd(path, frames, model, *, layout: str = "instancer", overwrite: bool = True,
              sparse: bool = True) -> ExportInfo:
    """Bake ``frames`` of ``model`` to the USD file ``path`` (.usd, .usdc or .usda).

    Parameters
    ----------
    path : str or Path
        Target file. Its extension picks the format (``.usd`` is binary crate).
        Missing parent folders are created.
    frames : Frames, or a samples.FrameSource (frames in blocks: a bake's chunks
        on disk, samples.ChunkSource, never all in memory at once)
        ``frame_numbers`` (used as USD time codes), ``x``, ``q`` (w, x, y, z),
        ``v``, ``w`` of the model's dynamic bodies.
    model : Model
        Reads ``shapes``, ``n_bodies``, ``body_shape``, ``body_group``,
        ``group_names``, ``body_group_index``, ``plane_point``, ``plane_normal``,
        ``boxes``, ``static_meshes``, ``fps``, ``up_axis``, ``meters_per_unit``;
        where present, ``collider_motions`` (animated colliders: each one's kind
        "plane" | "box" | "mesh", index, motion, ref_p, ref_q, origin, rotation;
        export/prescribed.py) and ``body_start_time`` ((n_bodies,) [s]: emitted
        bodies are hidden before it).
    layout : {"instancer", "xforms"}
        One PointInstancer, or one instanceable Xform per body.
    overwrite : bool
        If False and ``path`` exists, raise :class:`ExportError`.
    sparse : bool
        Leave out redundant samples: an attribute constant over all frames gets
        a default value only; inside a run of identical samples only the first
        and last are kept (linear interpolation between equal values is exact).
        Per body in the xforms layout, per whole array in the instancer layout.

    Returns
    -------
    ExportInfo

    Raises
    ------
    ExportError
        Bad extension or layout, inconsistent inputs, existing target with
        ``overwrite=False``, or any failure while writing (the target is then
        left as it was and no temporary file remains).
    """
    t0 = time.perf_counter()
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in EXTENSIONS:
        raise ExportError(
            f"{path}: unsupported extension {path.suffix!r} (use one of {', '.join(EXTENSIONS)})"
        )
    if layout not in LAYOUTS:
        raise ExportError(f"unknown USD layout {layout!r} (known: {', '.join(LAYOUTS)})")
    if path.exists() and not overwrite:
        raise ExportError(f"{path}: file exists (pass overwrite=True or choose another path)")
    source = as_source(frames)
    scan = _check_inputs(source, model)

    layer = Sdf.Layer.CreateAnonymous("dempipe" + ext)
    with Sdf.ChangeBlock():
        _author_metadata(layer, scan, model, layout)
        world = Sdf.PrimSpec(layer.pseudoRoot, "World", _DEF, "Xform")
        materials, collider_material = _shape_materials(world, model)
        if layout == "instancer":
            n_samples = _author_instancer(layer, world, source, scan, model, sparse, materials)
        else:
            n_samples = _author_xforms(layer, world, source, scan, model, sparse, materials)
        n_samples += _author_colliders(layer, world, source, scan, model, collider_material,
                                       sparse)

    _save_atomically(layer, path)
    return ExportInfo(
        path=path,
        seconds=time.perf_counter() - t0,
        n_time_samples=n_samples,
        bytes=path.stat().st_size,
    )


# ----------------------------------------------------------------------- checks


def _check_inputs(source, model):
    """Shapes, counts and model fields checked; returns the source's Scan."""
    n_bodies = int(model.n_bodies)
    expect = {"x": 3, "q": 4, "v": 3, "w": 3}
    scan = Scan()
    for frames in source.blocks():
        x = np.asarray(frames.x)
        n_frames = x.shape[0] if x.ndim == 3 else -1
        for name, k in expect.items():
            a = np.asarray(getattr(frames, name))
            if a.shape != (n_frames, n_bodies, k):
                raise ExportError(
                    f"frames.{name} has shape {a.shape}, expected ({n_frames}, {n_bodies}, "
                    f"{k}) (the model has {n_bodies} dynamic bodies)"
                )
        fn = np.asarray(frames.frame_numbers)
        if fn.shape != (n_frames,):
            raise ExportError(f"frames.frame_numbers has shape {fn.shape}, expected "
                              f"({n_frames},)")
        scan.add(frames)
    if scan.n_frames < 1:
        raise ExportError("no frames to export (bake at least one frame)")
    if not scan.increasing:
        raise ExportError("frames.frame_numbers must be strictly increasing")
    if not (float(model.meters_per_unit) > 0):
        raise ExportError(f"meters_per_unit must be > 0 (got {model.meters_per_unit})")
    if str(model.up_axis).upper() not in ("Y", "Z"):
        raise ExportError(f"up_axis must be 'Y' or 'Z' (got {model.up_axis!r})")
    if not (float(model.fps) > 0):
        raise ExportError(f"fps must be > 0 (got {model.fps})")
    if n_bodies:
        bs = np.asarray(model.body_shape)
        if bs.min() < 0 or bs.max() >= len(model.shapes):
            raise ExportError("model.body_shape refers to a shape that does not exist")
    return scan


# --------------------------------------------------------------------- metadata


def _author_metadata(layer, scan, model, layout) -> None:
    root = layer.pseudoRoot
    root.SetInfo("upAxis", str(model.up_axis).upper())
    root.SetInfo("metersPerUnit", float(model.meters_per_unit))
    root.SetInfo("kilogramsPerUnit", 1.0)
    fps = float(model.fps)
    layer.timeCodesPerSecond = fps
    layer.framesPerSecond = fps
    layer.startTimeCode = float(scan.first_number)
    layer.endTimeCode = float(scan.last_number)
    layer.defaultPrim = "World"
    layer.documentation = (
        f"Rigid-body animation baked by dempipe {__version__} ({layout} layout)"
    )
    layer.customLayerData = {"dempipe": {"version": __version__, "layout": layout}}


# ---------------------------------------------------------------------- helpers


def _unique_names(names) -> list[str]:
    """Valid, unique prim names, in order (``Tf.MakeValidIdentifier`` + suffixes)."""
    out, seen = [], set()
    for name in names:
        base = Tf.MakeValidIdentifier(str(name)) or "_"
        cand, k = base, 1
        while cand in seen:
            cand = f"{base}_{k}"
            k += 1
        seen.add(cand)
        out.append(cand)
    return out


def _attr(prim, name, type_name, default=None, *, uniform=False):
    spec = Sdf.AttributeSpec(prim, name, type_name, _UNIFORM if uniform else Sdf.VariabilityVarying)
    if default is not None:
        spec.default = default
    return spec


def _kept_samples(values: np.ndarray) -> np.ndarray:
    """(F, K...) samples -> (F, K) bool: which to write so that linear
    interpolation reproduces every sample. Inside a run of equal consecutive
    samples only the first and the last are kept. Comparison is exact."""
    n = values.shape[0]
    keep = np.ones(values.shape[:2], dtype=bool)
    if n > 2:
        same = np.all(values[1:] == values[:-1], axis=tuple(range(2, values.ndim)))
        keep[1:-1] = ~(same[:-1] & same[1:])
    return keep


def _constant(values: np.ndarray) -> np.ndarray:
    """(F, K...) -> (K,) bool: True where all samples equal the first."""
    return np.all(values == values[:1], axis=(0,) + tuple(range(2, values.ndim)))


#: float32's resolution, 2^-24. Written as 0: a component of a position or a
#: quaternion below this fraction of the vector's largest component (_flush_tiny),
#: a velocity that moves a body by less than this fraction of the scene's largest
#: coordinate in one frame, an angular velocity that turns it by less than this
#: many radians in one frame. What is left out is float noise of bodies at rest.
_TINY = 2.0**-24


def _flush_tiny(a: np.ndarray) -> np.ndarray:
    """(..., K) float64 -> the same with every component below ``_TINY`` times its
    vector's largest component set to 0 (in place).

    A body at rest still carries float noise around zero: a quaternion component
    of 1e-18 on a box lying flat, a coordinate of 1e-22 m on a body placed on an
    axis. Written as is, that noise makes every sample differ from the previous
    one and sparse output keeps them all. Each vector changes by less than
    float32's rounding of its largest component.
    """
    big = np.abs(a).max(axis=-1, keepdims=True)
    a[np.abs(a) < _TINY * big] = 0.0
    return a


def _quat_xyzw(q_wxyz: np.ndarray, dtype) -> np.ndarray:
    """dempipe (w, x, y, z) -> GfQuat memory layout (x, y, z, w), unit length."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    q = _flush_tiny(q / np.where(norm > 0, norm, 1.0))
    return np.ascontiguousarray(q[..., [1, 2, 3, 0]], dtype=dtype)


def _author_mesh(prim, vertices, faces, color, material=None) -> None:
    """Points, topology, extent, normals, displayColor and material of a polygon mesh prim.

    ``material``: the path of a ``UsdShade.Material`` to bind (``material:binding``),
    so that DCC tools show ``color`` by default: most ignore ``displayColor`` unless a
    material reads it (Blender, Maya, Omniverse), and usdview draws the material too.
    """
    pts = np.ascontiguousarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int32)
    _attr(prim, "points", _T.Point3fArray, Vt.Vec3fArray.FromNumpy(pts))
    _attr(prim, "faceVertexCounts", _T.IntArray,
          Vt.IntArray.FromNumpy(np.full(len(faces), faces.shape[1] if faces.ndim == 2 else 3,
                                        dtype=np.int32)))
    _attr(prim, "faceVertexIndices", _T.IntArray,
          Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.reshape(-1))))
    if len(pts):
        ext = np.stack([pts.min(axis=0), pts.max(axis=0)])
    else:
        ext = np.zeros((2, 3), np.float32)
    _attr(prim, "extent", _T.Float3Array, Vt.Vec3fArray.FromNumpy(ext))
    _attr(prim, "subdivisionScheme", _T.Token, "none", uniform=True)
    if len(faces):
        normals = _attr(prim, "normals", _T.Normal3fArray, Vt.Vec3fArray.FromNumpy(
            np.ascontiguousarray(corner_normals(vertices, faces), dtype=np.float32)))
        normals.SetInfo("interpolation", "faceVarying")
    col = _attr(prim, "primvars:displayColor", _T.Color3fArray,
                Vt.Vec3fArray([Gf.Vec3f(*map(float, color))]))
    col.SetInfo("interpolation", "constant")
    if material is not None:
        prim.SetInfo("apiSchemas", Sdf.TokenListOp.CreateExplicit(["MaterialBindingAPI"]))
        rel = Sdf.RelationshipSpec(prim, "material:binding", custom=False)
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


def _author_material(looks, name, color):
    """A ``UsdPreviewSurface`` material of diffuse ``color`` under ``looks``; its path.

    Every renderer and DCC importer reads UsdPreviewSurface; the diffuse colour
    also reads as the object's colour in viewports. Authored with Sdf like the rest.
    """
    mat = Sdf.PrimSpec(looks, name, _DEF, "Material")
    shader = Sdf.PrimSpec(mat, "PreviewSurface", _DEF, "Shader")
    _attr(shader, "info:id", _T.Token, "UsdPreviewSurface", uniform=True)
    _attr(shader, "inputs:diffuseColor", _T.Color3f, Gf.Vec3f(*map(float, color)))
    _attr(shader, "inputs:roughness", _T.Float, 0.6)
    _attr(shader, "inputs:metallic", _T.Float, 0.0)
    out = _attr(shader, "outputs:surface", _T.Token)
    surface = _attr(mat, "outputs:surface", _T.Token)
    surface.connectionPathList.explicitItems = [out.path]
    return mat.path


def _shape_materials(world, model):
    """One material per shape (its palette colour), and one for the colliders:
    ``(shape material paths, collider material path)`` under ``/World/Looks``."""
    looks = Sdf.PrimSpec(world, "Looks", _DEF, "Scope")
    names = _unique_names([f"{s.name}_mat" for s in model.shapes] + ["collider_mat"])
    paths = [_author_material(looks, n, _PALETTE[i % len(_PALETTE)])
             for i, n in enumerate(names[:-1])]
    return paths, _author_material(looks, names[-1], _COLLIDER_COLOR)


def _shape_points(model, mpu):
    """Body-frame prototype points in stage units, one array per shape."""
    return [np.asarray(s.vertices, dtype=np.float64) / mpu for s in model.shapes]


# -------------------------------------------------------------------- instancer


def _author_instancer(layer, world, source, scan, model, sparse, materials) -> int:
    mpu = float(model.meters_per_unit)
    bodies = Sdf.PrimSpec(world, "Bodies", _DEF, "PointInstancer")
    protos = Sdf.PrimSpec(bodies, "Prototypes", _DEF, "Scope")
    shape_names = _unique_names(s.name for s in model.shapes)
    points = _shape_points(model, mpu)
    proto_paths = []
    for i, (shape, name, pts) in enumerate(zip(model.shapes, shape_names, points)):
        mesh = Sdf.PrimSpec(protos, name, _DEF, "Mesh")
        _author_mesh(mesh, pts, shape.faces, _PALETTE[i % len(_PALETTE)], materials[i])
        proto_paths.append(mesh.path)
    rel = Sdf.RelationshipSpec(bodies, "prototypes", custom=False)
    rel.targetPathList.explicitItems = proto_paths

    n_bodies = int(model.n_bodies)
    _attr(bodies, "protoIndices", _T.IntArray,
          Vt.IntArray.FromNumpy(np.asarray(model.body_shape, dtype=np.int32).reshape(-1)))
    _attr(bodies, "ids", _T.Int64Array,
          Vt.Int64Array.FromNumpy(np.arange(n_bodies, dtype=np.int64)))
    n_vis = _author_invisible_ids(layer, bodies, model, scan)

    # Conservative per-frame bound: instance centres ± the largest prototype radius.
    radius = max((float(np.linalg.norm(p, axis=1).max()) for p in points if len(p)), default=0.0)
    specs = {name: _attr(bodies, name, type_name).path for name, type_name in (
        ("positions", _T.Point3fArray), ("orientations", _T.QuathArray),
        ("velocities", _T.Vector3fArray), ("angularVelocities", _T.Vector3fArray),
        ("extent", _T.Float3Array))}
    # USD moves instances by their (angular) velocities only where those are sampled
    # at the same times as the positions (orientations); elsewhere it ignores them
    # and warns. So while positions are sampled, velocities get the same times.
    writers = [
        _ArrayPair(layer, specs["positions"], specs["velocities"], Vt.Vec3fArray.FromNumpy,
                   Vt.Vec3fArray.FromNumpy, sparse),
        _ArrayPair(layer, specs["orientations"], specs["angularVelocities"],
                   Vt.QuathArray.FromNumpy, Vt.Vec3fArray.FromNumpy, sparse),
        _ArrayPair(layer, specs["extent"], None, Vt.Vec3fArray.FromNumpy, None, sparse),
    ]
    fps = float(model.fps)
    # the largest coordinate of all frames, as the whole-bake arrays had it
    x_max = scan.max_abs_x / mpu
    for frames in source.blocks():
        x = _flush_tiny(np.asarray(frames.x, dtype=np.float64) / mpu)
        pos = np.ascontiguousarray(x, dtype=np.float32)
        ori = _quat_xyzw(frames.q, np.float16)
        # A rate that turns or moves a body by less than float32's resolution of the
        # scene's coordinates in one frame is float noise of a body at rest: write 0.
        v = np.array(frames.v, dtype=np.float64) / mpu
        v[np.linalg.norm(v, axis=-1) < _TINY * fps * x_max] = 0.0
        w = np.array(frames.w, dtype=np.float64)
        w[np.linalg.norm(w, axis=-1) < _TINY * fps] = 0.0
        vel = np.ascontiguousarray(v, dtype=np.float32)
        ang = np.ascontiguousarray(np.degrees(w), dtype=np.float32)
        if n_bodies:
            ext = np.stack([pos.min(axis=1) - radius, pos.max(axis=1) + radius], axis=1)
        else:
            ext = np.zeros((pos.shape[0], 2, 3))
        ext = np.ascontiguousarray(ext, dtype=np.float32)
        for f, t in enumerate(np.asarray(frames.frame_numbers)):
            writers[0].push(float(t), pos[f], vel[f])
            writers[1].push(float(t), ori[f], ang[f])
            writers[2].push(float(t), ext[f], None)
    return n_vis + sum(wr.finish() for wr in writers)


def _author_invisible_ids(layer, bodies, model, scan) -> int:
    """Emitted bodies hidden before their first frame: ``invisibleIds`` (ids are the
    body indices) sampled at frame 0 and wherever the hidden set shrinks (an int
    array is held between samples). Nothing when every body is there from the
    start. Returns the samples written."""
    shown = _first_shown(model, scan)
    later = np.unique(shown[shown > 0])
    if not later.size:
        return 0
    numbers = scan.numbers
    spec = _attr(bodies, "invisibleIds", _T.Int64Array)
    n = 0
    for f in [0] + [int(k) for k in later if k < len(numbers)]:
        hidden = np.flatnonzero(shown > f).astype(np.int64)
        layer.SetTimeSample(spec.path, float(numbers[f]), Vt.Int64Array.FromNumpy(hidden))
        n += 1
    return n


class _ArrayPair:
    """Samples of a whole-array attribute (``moving``) and of the rate that goes
    with it (``rate``, or None), streamed frame by frame. Sparse: each keeps the
    samples of _kept_samples (a default only if it never changes); while the
    moving one is sampled, both are written at the union of their frames."""

    def __init__(self, layer, moving, rate, to_vt_m, to_vt_r, sparse):
        self.layer, self.paths, self.to_vt = layer, (moving, rate), (to_vt_m, to_vt_r)
        self.sparse = sparse
        self.tracks = (SparseTrack(1), SparseTrack(1) if rate is not None else None)
        self.i = 0
        self.t0 = self.t_prev = self.t_last = None
        self.rate_alone = []        # (frame, time) the rate was written at, moving unsampled
        self.written0 = [False, False]
        self.n = 0

    def _set(self, which, t, values):
        self.layer.SetTimeSample(self.paths[which], t, self.to_vt[which](values))
        self.n += 1

    def push(self, t, vm, vr) -> None:
        i = self.i
        self.i += 1
        if self.t0 is None:
            self.t0 = t
        if not self.sparse:
            self._set(0, t, vm)
            if vr is not None:
                self._set(1, t, vr)
            return
        tm, tr = self.tracks
        fm, pm = tm.push(vm[None])
        fr, pr = tr.push(vr[None]) if tr is not None else (fm & False, pm & False)
        t_prev = self.t_prev
        self.t_prev = t
        frames_m = ([0] if fm[0] else []) + ([i - 1] if pm[0] else [])
        frames_r = ([0] if fr[0] else []) + ([i - 1] if pr[0] else [])
        if tr is None or not tm.moved[0]:
            for f in frames_m:
                self._set_frame(0, f, t_prev)
            for f in frames_r:
                self._set_frame(1, f, t_prev)
                self.rate_alone.append((f, self.t0 if f == 0 else t_prev))
            return
        if fm[0]:       # the moving one starts to be sampled: at the rate's frames too
            for f, tf in self.rate_alone:
                if f == 0:
                    continue
                self.layer.SetTimeSample(self.paths[0], tf, self.to_vt[0](tm.first[0]))
                self.n += 1
            self.rate_alone = []
        for f in sorted(set(frames_m) | set(frames_r)):
            self._set_frame(0, f, t_prev)
            self._set_frame(1, f, t_prev)

    def _set_frame(self, which, f, t_prev) -> None:
        track = self.tracks[which]
        if f == 0:
            if self.written0[which]:
                return
            self.written0[which] = True
            self._set(which, self.t0, track.first[0])
        else:
            self._set(which, t_prev, track.prev_values[0])

    def finish(self) -> int:
        if not self.sparse:
            return self.n
        tm, tr = self.tracks
        last = self.t_prev
        for which, track in enumerate(self.tracks):
            if track is None:
                continue
            moved = track.moved[0] or (which == 1 and tm.moved[0])
            if moved:
                self._set(which, last, track.prev[0])
            else:
                self.layer.GetAttributeAtPath(self.paths[which]).default = \
                    self.to_vt[which](track.first[0])
        return self.n


# ----------------------------------------------------------------------- xforms


def _author_xforms(layer, world, source, scan, model, sparse, materials) -> int:
    mpu = float(model.meters_per_unit)
    # Prototypes: one class Xform per shape holding a Mesh child named after the
    # shape. Classes are abstract (not drawn, not imported as objects), and so is
    # the Scope that holds them, so no empty object appears in a DCC; each body
    # references its shape's class and is instanceable, so the mesh is stored and
    # drawn once, and a DCC lists each body's mesh under its shape's name.
    protos = Sdf.PrimSpec(world, "Prototypes", _CLASS, "Scope")
    shape_names = _unique_names(s.name for s in model.shapes)
    points = _shape_points(model, mpu)
    proto_paths = []
    for i, (shape, name, pts) in enumerate(zip(model.shapes, shape_names, points)):
        cls = Sdf.PrimSpec(protos, name, _CLASS, "Xform")
        mesh = Sdf.PrimSpec(cls, name, _DEF, "Mesh")
        _author_mesh(mesh, pts, shape.faces, _PALETTE[i % len(_PALETTE)], materials[i])
        proto_paths.append(cls.path)

    bodies = Sdf.PrimSpec(world, "Bodies", _DEF, "Xform")
    group_names = _unique_names(model.group_names)
    groups = [Sdf.PrimSpec(bodies, g, _DEF, "Xform") for g in group_names]

    body_shape = np.asarray(model.body_shape)
    body_group = np.asarray(model.body_group)
    body_group_index = np.asarray(model.body_group_index)
    op_order = Vt.TokenArray(["xformOp:translate", "xformOp:orient"])
    n_bodies = int(model.n_bodies)
    t_paths, o_paths = [], []
    for b in range(n_bodies):
        g = int(body_group[b])
        prim = Sdf.PrimSpec(groups[g], f"{group_names[g]}_{int(body_group_index[b])}", _DEF, "Xform")
        prim.referenceList.prependedItems.append(Sdf.Reference(primPath=proto_paths[int(body_shape[b])]))
        prim.instanceable = True
        t_paths.append(_attr(prim, "xformOp:translate", _T.Double3).path)
        o_paths.append(_attr(prim, "xformOp:orient", _T.Quatf).path)
        _attr(prim, "xformOpOrder", _T.TokenArray, op_order, uniform=True)

    # emitted bodies: "invisible" until their first frame, then "inherited" (a token
    # is held between samples, never interpolated)
    numbers = scan.numbers
    n_vis = 0
    for b, f in enumerate(_first_shown(model, scan)):
        if f == 0:
            continue
        vis = _attr(layer.GetPrimAtPath(t_paths[b].GetPrimPath()), "visibility", _T.Token)
        layer.SetTimeSample(vis.path, float(numbers[0]), "invisible")
        n_vis += 1
        if f < len(numbers):
            layer.SetTimeSample(vis.path, float(numbers[f]), "inherited")
            n_vis += 1

    writers = (_BodySamples(layer, t_paths, Vt.Vec3dArray.FromNumpy, sparse),
               _BodySamples(layer, o_paths, Vt.QuatfArray.FromNumpy, sparse))
    for frames in source.blocks():
        trans = np.ascontiguousarray(_flush_tiny(np.asarray(frames.x, dtype=np.float64) / mpu))
        orient = _quat_xyzw(frames.q, np.float32)
        for f, t in enumerate(np.asarray(frames.frame_numbers)):
            writers[0].push(float(t), trans[f])
            writers[1].push(float(t), orient[f])
    return n_vis + sum(wr.finish() for wr in writers)


def _first_shown(model, scan) -> np.ndarray:
    """(n_bodies,) index of the frame each body is first shown at (0: from the start;
    scan.n_frames: never), from ``model.body_start_time`` (zeros where absent)."""
    n = int(model.n_bodies)
    start = getattr(model, "body_start_time", None)
    if start is None:
        return np.zeros(n, dtype=np.int64)
    start = np.asarray(start, dtype=np.float64).reshape(-1)
    if start.shape != (n,):
        raise ExportError(f"model.body_start_time has shape {start.shape}, expected ({n},)")
    shown = first_shown_frame(start, scan.times)
    shown[start <= 0.0] = 0
    return shown


class _BodySamples:
    """Samples of one attribute per body (``paths``), streamed frame by frame: the
    kept frames of _kept_samples per body, a default only for a body whose value
    never changes (sparse), else every frame."""

    def __init__(self, layer, paths, to_vt, sparse):
        self.layer, self.paths, self.to_vt, self.sparse = layer, paths, to_vt, sparse
        self.track = SparseTrack(len(paths))
        self.t0 = self.t_prev = None
        self.n = 0

    def _write(self, t, values, mask) -> None:
        idx = np.flatnonzero(mask)
        if not idx.size:
            return
        vt = list(self.to_vt(np.ascontiguousarray(values[idx])))
        set_sample, paths = self.layer.SetTimeSample, self.paths
        for b, value in zip(idx.tolist(), vt):
            set_sample(paths[b], t, value)
        self.n += idx.size

    def push(self, t, values) -> None:
        if self.t0 is None:
            self.t0 = t
        if not self.sparse:
            self._write(t, values, np.ones(len(self.paths), dtype=bool))
            return
        first, prev = self.track.push(values)
        self._write(self.t0, self.track.first, first)
        if prev.any():
            self._write(self.t_prev, self.track.prev_values, prev)
        self.t_prev = t

    def finish(self) -> int:
        if not self.sparse or self.track.i == 0:
            return self.n
        last, constant = self.track.finish()
        self._write(self.t_prev, self.track.prev, last)
        idx = np.flatnonzero(constant)
        if idx.size:
            vt = list(self.to_vt(np.ascontiguousarray(self.track.first[idx])))
            for b, value in zip(idx.tolist(), vt):
                self.layer.GetAttributeAtPath(self.paths[b]).default = value
        return self.n


# -------------------------------------------------------------------- colliders


def _tangent_basis(n: np.ndarray):
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
    u, v = _tangent_basis(n)
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


def _author_colliders(layer, world, source, scan, model, material, sparse=True) -> int:
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
    col = Sdf.PrimSpec(world, "Colliders", _DEF, "Xform")
    # frame 0 and, per plane, the farthest position of all frames (samples.Scan)
    positions = scan.plane_positions(source, list(zip(plane_point, plane_normal))) \
        if len(plane_point) else None
    quad = np.array([[0, 1, 2, 3]], dtype=np.int32)
    for i, (p, nrm) in enumerate(zip(plane_point, plane_normal)):
        prim = Sdf.PrimSpec(col, f"plane_{i}", _DEF, "Mesh")
        verts = _plane_quad(p, nrm, positions)
        _author_mesh(prim, verts / mpu, quad, _COLLIDER_COLOR, material)
        m = moving.get(("plane", i))
        if m is not None:
            tr, ori = plane_xforms(m.motion, (m.ref_p, m.ref_q), m.origin, nrm,
                                   verts.mean(axis=0), times)
            n += _author_collider_motion(layer, prim, tr / mpu, ori, numbers, sparse)
    for i, box in enumerate(boxes):
        prim = Sdf.PrimSpec(col, f"box_{i}", _DEF, "Mesh")
        verts, faces = _box_walls(box, up)
        _author_mesh(prim, verts / mpu, faces, _COLLIDER_COLOR, material)
        n += _moving_collider(layer, prim, moving.get(("box", i)), times, numbers, mpu, sparse)
    reserved = {f"plane_{i}" for i in range(len(plane_point))} | {f"box_{i}" for i in range(len(boxes))}
    names = _unique_names(list(reserved) + [m.name for m in statics])[len(reserved):]
    for i, (name, mesh) in enumerate(zip(names, statics)):
        prim = Sdf.PrimSpec(col, name, _DEF, "Mesh")
        _author_mesh(prim, np.asarray(mesh.vertices, dtype=np.float64) / mpu, mesh.faces,
                     _COLLIDER_COLOR, material)
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
    kept samples of _kept_samples, a default only where nothing changes.
    Returns the time samples written."""
    t_spec = _attr(prim, "xformOp:translate", _T.Double3)
    o_spec = _attr(prim, "xformOp:orient", _T.Quatd)
    _attr(prim, "xformOpOrder", _T.TokenArray,
          Vt.TokenArray(["xformOp:translate", "xformOp:orient"]), uniform=True)
    orient = _flush_tiny(np.array(orient, dtype=np.float64))
    values = np.concatenate([translate, orient], axis=1)

    def quat(q):
        return Gf.Quatd(float(q[0]), Gf.Vec3d(float(q[1]), float(q[2]), float(q[3])))

    if sparse and bool(_constant(values[:, None])[0]):
        t_spec.default = Gf.Vec3d(*map(float, translate[0]))
        o_spec.default = quat(orient[0])
        return 0
    keep = _kept_samples(values[:, None])[:, 0] if sparse else np.ones(len(values), bool)
    for f in np.flatnonzero(keep):
        layer.SetTimeSample(t_spec.path, float(numbers[f]), Gf.Vec3d(*map(float, translate[f])))
        layer.SetTimeSample(o_spec.path, float(numbers[f]), quat(orient[f]))
    return 2 * int(keep.sum())


# ------------------------------------------------------------------ atomic save


def _save_atomically(layer, path: Path) -> None:
    """Export ``layer`` to a temp file beside ``path`` (same extension, so the
    same file format), fsync it, then rename it over ``path``."""
    from .. import interrupt

    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # create the file ourselves first: an unwritable folder or a full disk is
        # then an OSError with the OS's reason, not pxr's C++ error text
        with open(tmp, "wb"):
            pass
        with interrupt.temporary(tmp):
            ok = layer.Export(str(tmp))
        if not ok:
            raise OSError("USD could not write the layer")
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:  # Tf.ErrorException, OSError, KeyboardInterrupt, ...
        try:
            tmp.unlink()
        except OSError:
            pass
        if not isinstance(exc, Exception):
            raise
        if isinstance(exc, OSError) and exc.strerror:
            raise ExportError(f"{path}: cannot write USD file ({exc.strerror})") from None
        text = str(exc).strip()
        cause = text.splitlines()[-1] if text else type(exc).__name__
        raise ExportError(f"{path}: cannot write USD file ({cause})") from exc
