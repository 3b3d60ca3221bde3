"""Frames → USD: a baked rigid-body animation that DCC tools open as is.

Two layouts (see ``docs/usd-output.md``):

``"instancer"`` (default)
    One ``UsdGeom.PointInstancer`` at ``/World/Bodies`` whose prototypes are the
    shapes' meshes (its own children); per frame ``positions``, ``orientations``, ``velocities``,
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
(x, y, z, w), and the conversion happens in the writers only (usd/authoring.py's
``quat_xyzw``). USD angular velocities are in degrees per second. Lengths are
divided by ``model.meters_per_unit``.

This module lays out the bodies (the two layouts) and saves; the shapes' meshes
and materials are authored by usd/meshes.py, the colliders by
usd/colliders.py, with the Sdf helpers of usd/authoring.py.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Sdf, Vt

from dempipe import interrupt
from dempipe.errors import ExportError
from dempipe.usd.authoring import (
    SPEC_CLASS,
    SPEC_DEF,
    SDF_TYPES,
    TINY,
    author_attr,
    flush_tiny,
    quat_xyzw,
    unique_names,
)
from dempipe.usd.colliders import author_colliders, collider_names
from dempipe.usd.meshes import (
    PALETTE,
    author_mesh,
    broken_faces,
    shape_materials,
    shape_points,
)
from dempipe.usd.prescribed import first_shown_frame
from dempipe.usd.samples import Scan, SparseTrack, as_source
from dempipe.version import __version__

__all__ = ["ExportInfo", "write_usd", "LAYOUTS", "EXTENSIONS"]

LAYOUTS = ("instancer", "xforms")
EXTENSIONS = (".usd", ".usdc", ".usda")


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
        usd/prescribed.py) and ``body_start_time`` ((n_bodies,) [s]: emitted
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
        world = Sdf.PrimSpec(layer.pseudoRoot, "World", SPEC_DEF, "Xform")
        materials, collider_material, inside = shape_materials(world, model)
        if layout == "instancer":
            n_samples = _author_instancer(layer, world, source, scan, model, sparse, materials,
                                          inside)
        else:
            n_samples = _author_xforms(layer, world, source, scan, model, sparse, materials,
                                       inside)
        n_samples += author_colliders(layer, world, source, scan, model, collider_material,
                                      sparse)

    save_atomically(layer, path)
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


# -------------------------------------------------------------------- instancer


def _author_instancer(layer, world, source, scan, model, sparse, materials,
                      inside_material=None) -> int:
    mpu = float(model.meters_per_unit)
    bodies = Sdf.PrimSpec(world, "Bodies", SPEC_DEF, "PointInstancer")
    # The prototypes are the instancer's own children, with no Scope around them:
    # Blender imports a Scope as an empty object (a stray "Prototypes" under
    # Bodies), and Hydra and the importers draw an instancer's children only
    # through it anyway.
    protos = bodies
    shape_names = mesh_names(model, [])
    points = shape_points(model, mpu)
    proto_paths = []
    for i, (shape, name, pts) in enumerate(zip(model.shapes, shape_names, points)):
        mesh = Sdf.PrimSpec(protos, name, SPEC_DEF, "Mesh")
        author_mesh(mesh, pts, shape.faces, PALETTE[i % len(PALETTE)], materials[i],
                    broken_faces(shape, inside_material))
        proto_paths.append(mesh.path)
    rel = Sdf.RelationshipSpec(bodies, "prototypes", custom=False)
    rel.targetPathList.explicitItems = proto_paths

    n_bodies = int(model.n_bodies)
    author_attr(bodies, "protoIndices", SDF_TYPES.IntArray,
                Vt.IntArray.FromNumpy(np.asarray(model.body_shape, dtype=np.int32).reshape(-1)))
    author_attr(bodies, "ids", SDF_TYPES.Int64Array,
                Vt.Int64Array.FromNumpy(np.arange(n_bodies, dtype=np.int64)))
    n_vis = _author_invisible_ids(layer, bodies, model, scan)

    # Conservative per-frame bound: instance centres ± the largest prototype radius.
    radius = max((float(np.linalg.norm(p, axis=1).max()) for p in points if len(p)), default=0.0)
    specs = {name: author_attr(bodies, name, type_name).path for name, type_name in (
        ("positions", SDF_TYPES.Point3fArray), ("orientations", SDF_TYPES.QuathArray),
        ("velocities", SDF_TYPES.Vector3fArray), ("angularVelocities", SDF_TYPES.Vector3fArray),
        ("extent", SDF_TYPES.Float3Array))}
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
        x = flush_tiny(np.asarray(frames.x, dtype=np.float64) / mpu)
        pos = np.ascontiguousarray(x, dtype=np.float32)
        ori = quat_xyzw(frames.q, np.float16)
        # A rate that turns or moves a body by less than float32's resolution of the
        # scene's coordinates in one frame is float noise of a body at rest: write 0.
        v = np.array(frames.v, dtype=np.float64) / mpu
        v[np.linalg.norm(v, axis=-1) < TINY * fps * x_max] = 0.0
        w = np.array(frames.w, dtype=np.float64)
        w[np.linalg.norm(w, axis=-1) < TINY * fps] = 0.0
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
    spec = author_attr(bodies, "invisibleIds", SDF_TYPES.Int64Array)
    n = 0
    for f in [0] + [int(k) for k in later if k < len(numbers)]:
        hidden = np.flatnonzero(shown > f).astype(np.int64)
        layer.SetTimeSample(spec.path, float(numbers[f]), Vt.Int64Array.FromNumpy(hidden))
        n += 1
    return n


class _ArrayPair:
    """Samples of a whole-array attribute (``moving``) and of the rate that goes
    with it (``rate``, or None), streamed frame by frame. Sparse: each keeps the
    samples of kept_samples (a default only if it never changes); while the
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


def _author_xforms(layer, world, source, scan, model, sparse, materials,
                   inside_material=None) -> int:
    mpu = float(model.meters_per_unit)
    # Prototypes: one class Xform per shape holding a Mesh child named after the
    # shape. Classes are abstract (not drawn, not imported as objects), and so is
    # the Scope that holds them, so no empty object appears in a DCC; each body
    # references its shape's class and is instanceable, so the mesh is stored and
    # drawn once, and a DCC lists each body's mesh under its shape's name.
    protos = Sdf.PrimSpec(world, "Prototypes", SPEC_CLASS, "Scope")
    group_names = unique_names(model.group_names)
    body_group = np.asarray(model.body_group)
    body_group_index = np.asarray(model.body_group_index)
    labels = getattr(model, "body_labels", ()) or [str(int(i)) for i in body_group_index]
    body_names = [f"{group_names[int(g)]}_{lab}" for g, lab in zip(body_group, labels)]
    shape_names = unique_names(s.name for s in model.shapes)
    mesh_names_ = mesh_names(model, group_names + body_names)
    points = shape_points(model, mpu)
    proto_paths = []
    for i, (shape, name, pts) in enumerate(zip(model.shapes, shape_names, points)):
        cls = Sdf.PrimSpec(protos, name, SPEC_CLASS, "Xform")
        mesh = Sdf.PrimSpec(cls, mesh_names_[i], SPEC_DEF, "Mesh")
        author_mesh(mesh, pts, shape.faces, PALETTE[i % len(PALETTE)], materials[i],
                    broken_faces(shape, inside_material))
        proto_paths.append(cls.path)

    bodies = Sdf.PrimSpec(world, "Bodies", SPEC_DEF, "Xform")
    groups = [Sdf.PrimSpec(bodies, g, SPEC_DEF, "Xform") for g in group_names]

    body_shape = np.asarray(model.body_shape)
    op_order = Vt.TokenArray(["xformOp:translate", "xformOp:orient"])
    shown = _first_shown(model, scan)
    n_bodies = int(model.n_bodies)
    t_paths, o_paths = [], []
    for b in range(n_bodies):
        prim = Sdf.PrimSpec(groups[int(body_group[b])], body_names[b], SPEC_DEF, "Xform")
        prim.referenceList.prependedItems.append(Sdf.Reference(primPath=proto_paths[int(body_shape[b])]))
        prim.instanceable = True
        t_paths.append(author_attr(prim, "xformOp:translate", SDF_TYPES.Double3).path)
        o_paths.append(author_attr(prim, "xformOp:orient", SDF_TYPES.Quatf).path)
        order = op_order if shown[b] == 0 else Vt.TokenArray(list(op_order) + ["xformOp:scale"])
        author_attr(prim, "xformOpOrder", SDF_TYPES.TokenArray, order, uniform=True)

    # Emitted bodies: "invisible" until their first frame, then "inherited" (a token
    # is held between samples, never interpolated): usdview, Houdini, Omniverse.
    # Blender's importer reads visibility once, not animated, but follows animated
    # transforms (a Transform Cache constraint): a scale of 0 until the first frame,
    # then 1, hides the body there too.
    numbers = scan.numbers
    n_vis = 0
    for b, f in enumerate(shown):
        if f == 0:
            continue
        prim = layer.GetPrimAtPath(t_paths[b].GetPrimPath())
        vis = author_attr(prim, "visibility", SDF_TYPES.Token)
        scale = author_attr(prim, "xformOp:scale", SDF_TYPES.Float3)
        layer.SetTimeSample(vis.path, float(numbers[0]), "invisible")
        layer.SetTimeSample(scale.path, float(numbers[0]), (0.0, 0.0, 0.0))
        n_vis += 2
        if f < len(numbers):
            layer.SetTimeSample(vis.path, float(numbers[f]), "inherited")
            if f > 1:       # held at 0 up to the frame before, so it pops in at f
                layer.SetTimeSample(scale.path, float(numbers[f - 1]), (0.0, 0.0, 0.0))
            layer.SetTimeSample(scale.path, float(numbers[f]), (1.0, 1.0, 1.0))
            n_vis += 2 + (f > 1)

    writers = (_BodySamples(layer, t_paths, Vt.Vec3dArray.FromNumpy, sparse),
               _BodySamples(layer, o_paths, Vt.QuatfArray.FromNumpy, sparse))
    for frames in source.blocks():
        trans = np.ascontiguousarray(flush_tiny(np.asarray(frames.x, dtype=np.float64) / mpu))
        orient = quat_xyzw(frames.q, np.float32)
        for f, t in enumerate(np.asarray(frames.frame_numbers)):
            writers[0].push(float(t), trans[f])
            writers[1].push(float(t), orient[f])
    return n_vis + sum(wr.finish() for wr in writers)


def mesh_names(model, taken) -> list[str]:
    """Names of the shapes' Mesh prims: the shape's name, unless that is already
    the name of another prim a DCC makes an object of (``taken``: groups, bodies;
    always World, Bodies, Colliders, Looks and the colliders). Blender's object
    names are global: a mesh ``ball`` beside a group ``ball`` would rename one of
    them ``ball.001``. A clash takes ``<shape>_mesh`` (then ``_1``, ...)."""
    taken = set(taken) | {"World", "Bodies", "Colliders", "Looks", "Prototypes"}
    taken |= set(collider_names(model))
    out = []
    for name in unique_names(s.name for s in model.shapes):
        cand, k = name, 0
        while cand in taken:
            cand = f"{name}_mesh" + (f"_{k}" if k else "")
            k += 1
        taken.add(cand)
        out.append(cand)
    return out


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
    kept frames of kept_samples per body, a default only for a body whose value
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


# ------------------------------------------------------------------ atomic save


def save_atomically(layer, path: Path) -> None:
    """Export ``layer`` to a temp file beside ``path`` (same extension, so the
    same file format), fsync it, then rename it over ``path``."""
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
