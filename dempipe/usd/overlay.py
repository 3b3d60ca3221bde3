"""Frames → an overlay layer over the USD stage they were simulated from.

The layer's ``subLayers`` hold the input stage (by a path relative to the overlay),
and it authors nothing but the animation of the input's own body prims, as ``over``
specs: no geometry, no copies of prims. Opening the overlay shows the input shot,
animated; a DCC can also load it as a layer on top of its own stage.

Per body prim (see docs/usd-input.md, "The overlay"):

* ``xformOpOrder = [xformOp:translate:dempipe, xformOp:orient:dempipe,
  xformOp:scale:dempipe]`` with time samples, composing under the prim's own
  (possibly animated) parents to the simulated world pose and keeping the body's
  scale. Translate/orient/scale rather than one matrix: an orientation
  interpolates (slerp) between frames where a matrix would shear under motion
  blur, and DCCs show TRS channels. Their own ``:dempipe`` suffix keeps them apart
  from ops the input authored (another precision or type would clash). A body
  whose scale is not along its own axes, or whose parent scales unevenly, cannot
  be written as TRS; it gets one ``xformOp:transform:dempipe`` matrix instead.
  A prim that resets the transform stack keeps ``!resetXformStack!``.
* ``physics:velocity`` and ``physics:angularVelocity`` (degrees per second), in the
  parent's space as the schema has them.

Kinematic bodies (``kinematicEnabled``) are left out: the input's own animation
is what they follow (dempipe.scene.usd_reader reads it as their keys), so the overlay
does not restate it.

Bodies that are instances of a ``PointInstancer`` are written back into the
instancer's own ``positions``, ``orientations`` (or ``orientationsf`` when the
input uses it), ``velocities`` and ``angularVelocities``; instances that are not
simulated keep their input values. Redundant samples are left out (an attribute
constant over the frames gets a default only; runs of equal samples keep their ends).

:class:`OverlayWriter` takes frames in chunks (``add``) and writes once (``save``),
so a streamed bake can feed it as frames arrive; :func:`write_overlay` is the
one-shot form.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from dempipe.errors import ExportError
from dempipe.scene.usd_geometry import matrix_to_quat, polar
from dempipe.sim.model import quat_to_matrix
from dempipe.usd.animation import EXTENSIONS, ExportInfo, save_atomically
from dempipe.version import __version__

__all__ = ["OverlayWriter", "write_overlay"]

_T = Sdf.ValueTypeNames
OPS_TRS = ("xformOp:translate:dempipe", "xformOp:orient:dempipe", "xformOp:scale:dempipe")
OP_MATRIX = "xformOp:transform:dempipe"
#: A stretch or a parent's scale counts as along the axes / even when the rest is
#: below this fraction of its largest entry.
_AXIS_TOL = 1e-9


def _np(m) -> np.ndarray:
    return np.array(m, dtype=np.float64).reshape(4, 4)


def _conformal(A: np.ndarray) -> bool:
    """Whether the 3 × 3 ``A`` is a rotation times a uniform scale."""
    G = A @ A.T
    s = np.trace(G) / 3.0
    return bool(np.abs(G - s * np.eye(3)).max() <= _AXIS_TOL * max(s, 1e-300))


def _diagonal(S: np.ndarray) -> bool:
    off = S - np.diag(np.diag(S))
    return bool(np.abs(off).max() <= _AXIS_TOL * max(np.abs(S).max(), 1e-300))


class OverlayWriter:
    """Authors an overlay for ``shot`` (a dempipe.scene.usd_reader.UsdShot) of ``model``.

    path : the overlay file (.usd, .usdc, .usda); the input stage is referenced
        relative to its folder.
    """

    def __init__(self, path, model, shot):
        self.path = Path(path)
        if self.path.suffix.lower() not in EXTENSIONS:
            raise ExportError(f"{self.path}: unsupported extension {self.path.suffix!r} "
                              f"(use one of {', '.join(EXTENSIONS)})")
        if self.path.resolve() == Path(shot.stage_path).resolve():
            raise ExportError(f"{self.path}: is the input stage; write the overlay to "
                              "another file")
        if len(shot.bodies) != model.n_bodies:
            raise ExportError(f"the shot has {len(shot.bodies)} bodies, the model "
                              f"{model.n_bodies}")
        self.model, self.shot = model, shot
        self.mpu = float(shot.meters_per_unit)
        self.stage = Usd.Stage.Open(str(shot.stage_path), Usd.Stage.LoadAll)
        self.t0 = Usd.TimeCode(shot.start)
        self.n_samples = 0
        self.first = self.last = None
        # body centre of mass in its stretched local frame [m]: the origin dempipe moves
        self.com = [np.asarray(model.shapes[model.body_shape[b]].com)
                    for b in range(model.n_bodies)]
        self.layer = Sdf.Layer.CreateAnonymous("overlay" + self.path.suffix.lower())
        self._author_header()
        self.prims, self.instanced = {}, {}
        for b, body in enumerate(shot.bodies):
            if getattr(body, "kinematic", False):
                continue        # it follows the input's own animation: left as authored
            if body.instance >= 0:
                self.instanced.setdefault(body.prim, []).append(b)
            else:
                self.prims[b] = self._prepare_prim(body)

    # -- layer header ------------------------------------------------------------
    def _author_header(self):
        src = self.stage.GetRootLayer()
        layer = self.layer
        try:
            rel = os.path.relpath(self.shot.stage_path, self.path.resolve().parent)
        except ValueError:          # another drive: only an absolute path reaches it
            rel = str(self.shot.stage_path)
        layer.subLayerPaths.append(Path(rel).as_posix())
        layer.timeCodesPerSecond = src.timeCodesPerSecond
        layer.framesPerSecond = src.framesPerSecond
        root = layer.pseudoRoot
        # the root layer's metadata is the stage's: carry the input's over
        for key in ("upAxis", "metersPerUnit", "kilogramsPerUnit"):
            if src.pseudoRoot.HasInfo(key):
                root.SetInfo(key, src.pseudoRoot.GetInfo(key))
        if src.defaultPrim:
            layer.defaultPrim = src.defaultPrim
        layer.documentation = (f"dempipe {__version__} overlay: the rigid-body animation of "
                               f"{Path(self.shot.stage_path).name}")

    # -- body prims --------------------------------------------------------------
    def _prepare_prim(self, body):
        prim = self.stage.GetPrimAtPath(body.prim)
        xf = UsdGeom.Xformable(prim)
        reset = bool(xf.GetResetXformStack())
        S = np.asarray(body.stretch)
        times = np.arange(int(round(self.shot.start)), int(round(self.shot.end)) + 1)
        parents = [self._parent(prim, t, reset) for t in times[:1]]
        if self._parent_animated(prim):
            parents = [self._parent(prim, t, reset) for t in times]
        trs = _diagonal(S) and all(_conformal(P[:3, :3]) for P in parents)
        spec = Sdf.CreatePrimInLayer(self.layer, prim.GetPath())
        spec.specifier = Sdf.SpecifierOver
        ops = list(OPS_TRS if trs else (OP_MATRIX,))
        order = Sdf.AttributeSpec(spec, "xformOpOrder", _T.TokenArray,
                                  variability=Sdf.VariabilityUniform)
        order.default = Vt.TokenArray((["!resetXformStack!"] if reset else []) + ops)
        attrs = {}
        if trs:
            attrs["t"] = Sdf.AttributeSpec(spec, OPS_TRS[0], _T.Double3)
            attrs["r"] = Sdf.AttributeSpec(spec, OPS_TRS[1], _T.Quatd)
            attrs["s"] = Sdf.AttributeSpec(spec, OPS_TRS[2], _T.Double3)
        else:
            attrs["m"] = Sdf.AttributeSpec(spec, OP_MATRIX, _T.Matrix4d)
        attrs["v"] = Sdf.AttributeSpec(spec, "physics:velocity", _T.Vector3f)
        attrs["w"] = Sdf.AttributeSpec(spec, "physics:angularVelocity", _T.Vector3f)
        return dict(prim=prim, reset=reset, trs=trs, attrs=attrs, S=S)

    def _parent_animated(self, prim) -> bool:
        p = prim.GetParent()
        while p and not p.IsPseudoRoot():
            if p.IsA(UsdGeom.Xformable) and UsdGeom.Xformable(p).TransformMightBeTimeVarying():
                return True
            p = p.GetParent()
        return False

    def _parent(self, prim, t, reset) -> np.ndarray:
        if reset:
            return np.eye(4)
        return _np(UsdGeom.XformCache(Usd.TimeCode(float(t))).GetParentToWorldTransform(prim))

    def _world(self, b, x, q, S) -> np.ndarray:
        """Row-convention world matrix [stage units] of body ``b`` at (x [m], q)."""
        Rc = quat_to_matrix(q)
        W = np.eye(4)
        W[:3, :3] = S @ Rc.T
        W[3, :3] = (x - Rc @ self.com[b]) / self.mpu
        return W

    # -- frames ------------------------------------------------------------------
    def add(self, frames) -> None:
        """Author time samples for ``frames`` (a Frames or a chunk of one)."""
        times = np.asarray(frames.frame_numbers)
        if len(times) == 0:
            return
        self.first = float(times[0]) if self.first is None else min(self.first, float(times[0]))
        self.last = float(times[-1]) if self.last is None else max(self.last, float(times[-1]))
        with Sdf.ChangeBlock():
            for b, info in self.prims.items():
                self._add_prim(b, info, frames, times)
            for path, bodies in self.instanced.items():
                self._add_instancer(path, bodies, frames, times)

    def _sample(self, spec, t, value):
        self.layer.SetTimeSample(spec.path, float(t), value)
        self.n_samples += 1

    def _add_prim(self, b, info, frames, times):
        animated = self._parent_animated(info["prim"])
        P = None
        a = info["attrs"]
        for k, t in enumerate(times):
            if P is None or animated:
                P = self._parent(info["prim"], t, info["reset"])
            W = self._world(b, frames.x[k, b], frames.q[k, b], info["S"])
            L = W @ np.linalg.inv(P)
            if info["trs"]:
                S_l, R_l = polar(L[:3, :3])
                q = matrix_to_quat(R_l.T)
                self._sample(a["t"], t, Gf.Vec3d(*L[3, :3]))
                self._sample(a["r"], t, Gf.Quatd(q[0], Gf.Vec3d(*q[1:])))
                self._sample(a["s"], t, Gf.Vec3d(*np.diag(S_l)))
            else:
                self._sample(a["m"], t, Gf.Matrix4d(L.tolist()))
            P3inv = np.linalg.inv(P[:3, :3])
            _, Rp = polar(P[:3, :3])
            v = frames.v[k, b] / self.mpu @ P3inv
            w = np.degrees(frames.w[k, b]) @ Rp.T
            self._sample(a["v"], t, Gf.Vec3f(*v))
            self._sample(a["w"], t, Gf.Vec3f(*w))

    def _add_instancer(self, path, bodies, frames, times):
        prim = self.stage.GetPrimAtPath(path)
        pi = UsdGeom.PointInstancer(prim)
        n, proto_local = self.shot.instancers[path]
        use_f = pi.GetOrientationsfAttr().HasAuthoredValue()
        spec = self.layer.GetPrimAtPath(path)
        if spec is None:
            spec = Sdf.CreatePrimInLayer(self.layer, path)
            spec.specifier = Sdf.SpecifierOver
            Sdf.AttributeSpec(spec, "positions", _T.Point3fArray)
            Sdf.AttributeSpec(spec, "orientationsf" if use_f else "orientations",
                              _T.QuatfArray if use_f else _T.QuathArray)
            Sdf.AttributeSpec(spec, "velocities", _T.Vector3fArray)
            Sdf.AttributeSpec(spec, "angularVelocities", _T.Vector3fArray)
        attr = {k: spec.attributes[k] for k in ("positions", "velocities", "angularVelocities")}
        attr["orient"] = spec.attributes["orientationsf" if use_f else "orientations"]
        inv_proto = [np.linalg.inv(m) for m in proto_local]
        for k, t in enumerate(times):
            tc = Usd.TimeCode(float(t))
            W_inst = _np(UsdGeom.XformCache(tc).GetLocalToWorldTransform(prim))
            inv_inst = np.linalg.inv(W_inst)
            _, R_inst = polar(W_inst[:3, :3])
            pos = np.array(pi.GetPositionsAttr().Get(tc) or [(0, 0, 0)] * n, dtype=np.float64)
            src_q = (pi.GetOrientationsfAttr() if use_f else pi.GetOrientationsAttr()).Get(tc)
            quats = [Gf.Quatd(x) for x in src_q] if src_q else [Gf.Quatd(1.0)] * n
            vel = np.array(pi.GetVelocitiesAttr().Get(tc) or np.zeros((n, 3)), dtype=np.float64)
            ang = np.array(pi.GetAngularVelocitiesAttr().Get(tc) or np.zeros((n, 3)),
                           dtype=np.float64)
            if len(vel) != n:
                vel = np.zeros((n, 3))
            if len(ang) != n:
                ang = np.zeros((n, 3))
            for b in bodies:
                i = self.shot.bodies[b].instance
                W = self._world(b, frames.x[k, b], frames.q[k, b],
                                np.asarray(self.shot.bodies[b].stretch))
                K = inv_proto[i] @ W @ inv_inst          # scale · orient · translate
                _, R_i = polar(K[:3, :3])
                q = matrix_to_quat(R_i.T)
                pos[i] = K[3, :3]
                quats[i] = Gf.Quatd(q[0], Gf.Vec3d(*q[1:]))
                vel[i] = frames.v[k, b] / self.mpu @ np.linalg.inv(W_inst[:3, :3])
                ang[i] = np.degrees(frames.w[k, b]) @ R_inst.T
            qt = Gf.Quatf if use_f else Gf.Quath
            self._sample(attr["positions"], t, Vt.Vec3fArray.FromNumpy(pos.astype(np.float32)))
            self._sample(attr["orient"], t, (Vt.QuatfArray if use_f else Vt.QuathArray)(
                [qt(float(x.GetReal()), *[float(c) for c in x.GetImaginary()]) for x in quats]))
            self._sample(attr["velocities"], t, Vt.Vec3fArray.FromNumpy(vel.astype(np.float32)))
            self._sample(attr["angularVelocities"], t,
                         Vt.Vec3fArray.FromNumpy(ang.astype(np.float32)))

    # -- save --------------------------------------------------------------------
    def _thin(self) -> None:
        """Leave out redundant samples, as usd/animation.py does: an attribute equal at
        every frame gets a default value only; inside a run of equal samples only its
        ends are kept (linear interpolation between equal values is exact). A body
        asleep writes nothing while it sleeps."""
        layer = self.layer
        paths = []
        layer.Traverse(layer.pseudoRoot.path,
                       lambda p: paths.append(p) if p.IsPropertyPath() else None)
        with Sdf.ChangeBlock():
            for path in paths:
                times = layer.ListTimeSamplesForPath(path)
                if len(times) < 2:
                    continue
                values = [layer.QueryTimeSample(path, t) for t in times]
                if all(v == values[0] for v in values[1:]):
                    spec = layer.GetAttributeAtPath(path)
                    for t in times:
                        layer.EraseTimeSample(path, t)
                    spec.default = values[0]
                    self.n_samples -= len(times)
                    continue
                for k in range(1, len(times) - 1):
                    if values[k] == values[k - 1] and values[k] == values[k + 1]:
                        layer.EraseTimeSample(path, times[k])
                        self.n_samples -= 1

    def save(self) -> ExportInfo:
        """Write the layer atomically; returns ExportInfo."""
        t0 = time.perf_counter()
        if self.first is not None:
            self.layer.startTimeCode = self.first
            self.layer.endTimeCode = self.last
        self._thin()
        save_atomically(self.layer, self.path)
        return ExportInfo(path=self.path, seconds=time.perf_counter() - t0,
                          n_time_samples=self.n_samples, bytes=self.path.stat().st_size)


def write_overlay(path, frames, model, shot) -> ExportInfo:
    """Write ``frames`` of ``model`` as an overlay over ``shot``'s stage at ``path``."""
    t0 = time.perf_counter()
    w = OverlayWriter(path, model, shot)
    w.add(frames)
    info = w.save()
    return ExportInfo(info.path, time.perf_counter() - t0, info.n_time_samples, info.bytes)
