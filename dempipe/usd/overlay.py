"""Frames → an overlay layer over the USD stage they were simulated from.

The layer's ``subLayers`` hold the input stage (by a path relative to the overlay),
and it authors nothing but the animation of the input's own body prims, as ``over``
specs: no geometry, no copies of prims, but for a fractured body's pieces. Opening the
overlay shows the input shot, animated; a DCC can also load it as a layer on top of
its own stage.

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

A fractured body (``dempipe:fracture:*``, scene.usd_attributes) is its pieces: its prim
is made inactive and its pieces are defined beside it, under ``<name>_pieces``, one
Mesh body prim each with the ops above, the broken faces bound to an inside material
(``OverlayWriter._prepare_pieces`` says why inactive, not invisible).

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
from dempipe.scene.usd_geometry import matrix_array, matrix_to_quat, polar
from dempipe.sim.model import quat_to_matrix
from dempipe.usd.animation import EXTENSIONS, ExportInfo, save_atomically
from dempipe.usd.authoring import SDF_TYPES, author_attr
from dempipe.usd.meshes import (
    INSIDE_COLOR,
    PALETTE,
    author_material,
    author_mesh,
    broken_faces,
)
from dempipe.version import __version__

__all__ = ["OverlayWriter", "write_overlay"]

OPS_TRS = ("xformOp:translate:dempipe", "xformOp:orient:dempipe", "xformOp:scale:dempipe")
OP_MATRIX = "xformOp:transform:dempipe"
#: A stretch or a parent's scale counts as along the axes / even when the rest is
#: below this fraction of its largest entry.
_AXIS_TOL = 1e-9


#: Rates and the pose attribute whose samples they must share (USD reads velocities
#: only when they are sampled where the positions are): rate -> its poses, first found.
RATE_OF = {"velocities": ("positions",),
           "angularVelocities": ("orientations", "orientationsf"),
           "physics:velocity": (OPS_TRS[0], OP_MATRIX),
           "physics:angularVelocity": (OPS_TRS[1], OP_MATRIX)}


def _rows(v) -> np.ndarray:
    """A sample as (elements, components) float64: one row for a Gf vector,
    quaternion or matrix, a row per element of a Vt array."""
    if hasattr(v, "GetReal"):
        return np.array([[v.GetReal(), *v.GetImaginary()]], dtype=np.float64)
    if type(v).__module__.endswith("Gf"):
        return np.array(v, dtype=np.float64).reshape(1, -1)
    a = np.array(v, dtype=np.float64)
    return a.reshape(len(a), -1)


def _zeroed(v, still: np.ndarray):
    """The rate sample ``v`` (a Gf.Vec3f or a Vt.Vec3fArray) with the elements where
    ``still`` holds set to zero."""
    if not still.any():
        return v
    if type(v).__module__.endswith("Gf"):
        return type(v)(0.0)
    a = np.array(v, dtype=np.float32).reshape(len(still), -1)
    a[still] = 0.0
    return type(v).FromNumpy(a)


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
        if len(shot.bodies) != len(model.group_names):
            raise ExportError(f"the shot has {len(shot.bodies)} bodies, the model "
                              f"{len(model.group_names)} body groups")
        self.model, self.shot = model, shot
        #: each Model body's shot body (its group: a fractured body's pieces share one)
        self.of = [shot.bodies[int(g)] for g in np.asarray(model.body_group)[:model.n_bodies]]
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
        self.prims, self.instanced, pieces = {}, {}, {}
        #: body prim path -> body index, for a body nested under another one
        self.body_at = {body.prim: b for b, body in enumerate(self.of)
                        if body.instance < 0 and not body.kinematic and not body.fractured}
        for b, body in enumerate(self.of):
            if body.kinematic:
                continue        # it follows the input's own animation: left as authored
            if body.fractured:
                pieces.setdefault(body.prim, []).append(b)
            elif body.instance >= 0:
                self.instanced.setdefault(body.prim, []).append(b)
            else:
                prim = self.stage.GetPrimAtPath(body.prim)
                spec = Sdf.CreatePrimInLayer(self.layer, prim.GetPath())
                spec.specifier = Sdf.SpecifierOver
                self.prims[b] = self._prepare_prim(prim, spec, np.asarray(body.stretch))
        for path, bodies in pieces.items():
            self._prepare_pieces(self.stage.GetPrimAtPath(path), bodies)

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
    def _prepare_prim(self, prim, spec, S, own_reset: bool = True):
        """The attribute specs of a body written at ``spec``: an over of the input's
        ``prim``, or a piece beside it (``own_reset`` False: its parent holds the
        input's ``!resetXformStack!``); ``prim``'s parents are the parents."""
        xf = UsdGeom.Xformable(prim)
        reset = bool(xf.GetResetXformStack())
        times = np.arange(int(round(self.shot.start)), int(round(self.shot.end)) + 1)
        parents = [self._parent(prim, t, reset) for t in times[:1]]
        if self._parent_animated(prim):
            parents = [self._parent(prim, t, reset) for t in times]
        carrier = None if reset else self._carrier(prim)
        if carrier is not None:     # the parent turns with a simulated body
            c, rel = carrier
            parents = [rel @ np.block([[np.asarray(self.of[c].stretch), np.zeros((3, 1))],
                                       [np.zeros((1, 3)), np.ones((1, 1))]])]
        trs = _diagonal(S) and all(_conformal(P[:3, :3]) for P in parents)
        ops = list(OPS_TRS if trs else (OP_MATRIX,))
        order = Sdf.AttributeSpec(spec, "xformOpOrder", SDF_TYPES.TokenArray,
                                  variability=Sdf.VariabilityUniform)
        order.default = Vt.TokenArray((["!resetXformStack!"] if reset and own_reset else [])
                                      + ops)
        attrs = {}
        if trs:
            attrs["t"] = Sdf.AttributeSpec(spec, OPS_TRS[0], SDF_TYPES.Double3)
            attrs["r"] = Sdf.AttributeSpec(spec, OPS_TRS[1], SDF_TYPES.Quatd)
            attrs["s"] = Sdf.AttributeSpec(spec, OPS_TRS[2], SDF_TYPES.Double3)
        else:
            attrs["m"] = Sdf.AttributeSpec(spec, OP_MATRIX, SDF_TYPES.Matrix4d)
        attrs["v"] = Sdf.AttributeSpec(spec, "physics:velocity", SDF_TYPES.Vector3f)
        attrs["w"] = Sdf.AttributeSpec(spec, "physics:angularVelocity", SDF_TYPES.Vector3f)
        return dict(prim=prim, reset=reset, trs=trs, attrs=attrs, S=S, carrier=carrier)

    # -- fractured bodies ----------------------------------------------------------
    def _prepare_pieces(self, prim, bodies):
        """A fractured body: the input's prim deactivated, its pieces beside it.

        ``active = false`` rather than ``visibility = invisible``: the whole body leaves
        the composed stage with everything below it (its render meshes, its collision
        shapes and RigidBodyAPI), so neither a renderer nor a physics engine reading
        the composed stage finds the whole body over its pieces (an invisible prim
        still collides, and is still exported by a DCC). The pieces go under a new
        Xform beside it, ``<name>_pieces`` (so they keep its parents, and the input's
        prim is still there to turn back on): one Mesh per piece with RigidBodyAPI,
        CollisionAPI and its mass, the piece's mesh about its centre of mass, the
        broken faces a GeomSubset bound to an inside material (as usd/meshes.py writes
        a TOML scene's pieces), the outside bound to the input's own render material
        when it has one, and the physics material of its shapes bound for physics.
        """
        over = Sdf.CreatePrimInLayer(self.layer, prim.GetPath())
        over.specifier = Sdf.SpecifierOver
        over.active = False
        parent = prim.GetParent()
        name, k = f"{prim.GetName()}_pieces", 1
        while parent.GetChild(name) or self.layer.GetPrimAtPath(
                parent.GetPath().AppendChild(name)):
            name, k = f"{prim.GetName()}_pieces_{k}", k + 1
        group = Sdf.CreatePrimInLayer(self.layer, parent.GetPath().AppendChild(name))
        group.specifier = Sdf.SpecifierDef
        group.typeName = "Xform"
        if UsdGeom.Xformable(prim).GetResetXformStack():
            author_attr(group, "xformOpOrder", SDF_TYPES.TokenArray,
                        Vt.TokenArray(["!resetXformStack!"]),
                        uniform=True)
        colour, outside, physics = _looks_of(prim)
        looks = Sdf.PrimSpec(group, "Looks", Sdf.SpecifierDef, "Scope")
        if outside is None:
            outside = author_material(looks, "outside_mat", colour)
        inside = author_material(looks, "inside_mat", INSIDE_COLOR)
        kpu = float(self.shot.kilograms_per_unit)
        for k, b in enumerate(bodies):
            shape = self.model.shapes[self.model.body_shape[b]]
            spec = Sdf.PrimSpec(group, f"piece_{k:02d}", Sdf.SpecifierDef, "Mesh")
            author_mesh(spec, np.asarray(shape.vertices) / self.mpu, shape.faces, colour,
                        outside, broken_faces(shape, inside))
            spec.SetInfo("apiSchemas", Sdf.TokenListOp.CreateExplicit(
                ["MaterialBindingAPI", "PhysicsRigidBodyAPI", "PhysicsCollisionAPI",
                 "PhysicsMassAPI"]))
            author_attr(spec, "physics:mass", SDF_TYPES.Float,
                        float(self.model.body_mass[b]) / kpu)
            if physics is not None:
                rel = Sdf.RelationshipSpec(spec, "material:binding:physics", custom=False)
                rel.targetPathList.explicitItems = [physics]
            # the piece's mesh is about its centre of mass, in the body's stretched frame
            self.com[b] = np.zeros(3)
            self.prims[b] = self._prepare_prim(prim, spec, np.eye(3), own_reset=False)

    def _carrier(self, prim):
        """(body index, parent-to-body matrix) of the nearest simulated body above
        ``prim``, whose simulated pose moves ``prim``'s parent; None when there is none
        (the input stage's parents are then the parents)."""
        p = prim.GetParent()
        while p and not p.IsPseudoRoot():
            b = self.body_at.get(str(p.GetPath()))
            if b is not None:
                rel = UsdGeom.XformCache(self.t0).ComputeRelativeTransform(prim.GetParent(), p)
                return b, matrix_array(rel[0])
            p = p.GetParent()
        return None

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
        cache = UsdGeom.XformCache(Usd.TimeCode(float(t)))
        return matrix_array(cache.GetParentToWorldTransform(prim))

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
        carrier = info["carrier"]
        for k, t in enumerate(times):
            if carrier is not None:
                c, rel = carrier
                P = rel @ self._world(c, frames.x[k, c], frames.q[k, c],
                                      np.asarray(self.of[c].stretch))
            elif P is None or animated:
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
            Sdf.AttributeSpec(spec, "positions", SDF_TYPES.Point3fArray)
            Sdf.AttributeSpec(spec, "orientationsf" if use_f else "orientations",
                              SDF_TYPES.QuatfArray if use_f else SDF_TYPES.QuathArray)
            Sdf.AttributeSpec(spec, "velocities", SDF_TYPES.Vector3fArray)
            Sdf.AttributeSpec(spec, "angularVelocities", SDF_TYPES.Vector3fArray)
        attr = {k: spec.attributes[k] for k in ("positions", "velocities", "angularVelocities")}
        attr["orient"] = spec.attributes["orientationsf" if use_f else "orientations"]
        inv_proto = [np.linalg.inv(m) for m in proto_local]
        for k, t in enumerate(times):
            tc = Usd.TimeCode(float(t))
            W_inst = matrix_array(UsdGeom.XformCache(tc).GetLocalToWorldTransform(prim))
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
                i = self.of[b].instance
                W = self._world(b, frames.x[k, b], frames.q[k, b],
                                np.asarray(self.of[b].stretch))
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
        asleep writes nothing while it sleeps.

        A velocity keeps the sample times of the pose it is the rate of (RATE_OF): USD
        refuses velocities not sampled where the positions are (and warns at every
        read). Where a body's pose equals the frame's before or after, the body is
        still and its velocity there is zero: what is left is the solver's float
        noise (about 1e-11), which would otherwise be written."""
        layer = self.layer
        by_prim: dict = {}
        layer.Traverse(layer.pseudoRoot.path, lambda p: by_prim.setdefault(
            p.GetPrimPath(), {}).__setitem__(p.name, p) if p.IsPropertyPath() else None)
        with Sdf.ChangeBlock():
            for attrs in by_prim.values():
                timed = {n: p for n, p in attrs.items()
                         if len(layer.ListTimeSamplesForPath(p)) >= 2}
                follows: dict = {}
                for rate, poses in RATE_OF.items():
                    pose = next((n for n in poses if n in timed), None)
                    if rate in timed and pose is not None:
                        follows.setdefault(pose, []).append(timed[rate])
                rates = {p for ps in follows.values() for p in ps}
                for name, p in timed.items():
                    if p not in rates:
                        self._thin_with(p, follows.get(name, []))

    def _thin_with(self, pose, rates: list) -> None:
        """Thin ``pose`` on its runs of equal samples and ``rates`` at the same times,
        zeroed where the pose is still."""
        layer = self.layer
        times = list(layer.ListTimeSamplesForPath(pose))
        n = len(times)
        rows = np.stack([_rows(layer.QueryTimeSample(pose, t)) for t in times])
        # same_prev[k, i]: element i (an instance, or the prim) as at frame k - 1
        same_prev = np.zeros(rows.shape[:2], bool)
        same_prev[1:] = (rows[1:] == rows[:-1]).all(axis=2)
        same_next = np.zeros_like(same_prev)
        same_next[:-1] = same_prev[1:]
        still = same_prev | same_next
        constant = bool(same_prev[1:].all())
        keep = [k for k in range(n) if k in (0, n - 1)
                or not (same_prev[k].all() and same_next[k].all())]
        for p in [pose, *rates]:
            values = [layer.QueryTimeSample(p, t) for t in times]
            if p != pose:
                values = [_zeroed(v, still[k]) for k, v in enumerate(values)]
            for t in times:
                layer.EraseTimeSample(p, t)
            self.n_samples -= n
            if constant:
                layer.GetAttributeAtPath(p).default = values[0]
                continue
            for k in keep:
                layer.SetTimeSample(p, times[k], values[k])
            self.n_samples += len(keep)

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


def _looks_of(prim):
    """(display colour, render material path or None, physics material path or None)
    of a body prim: its own bindings or, failing those, the first gprim's below it."""
    from pxr import UsdPhysics, UsdShade

    colour, render, physics = tuple(PALETTE[0]), None, None
    for p in Usd.PrimRange(prim):
        if p.IsA(UsdGeom.Gprim) and colour == tuple(PALETTE[0]):
            c = UsdGeom.Gprim(p).GetDisplayColorAttr().Get()
            if c is not None and len(c):
                colour = tuple(float(x) for x in c[0])
        api = UsdShade.MaterialBindingAPI(p)
        if render is None:
            m = api.ComputeBoundMaterial()[0]
            # a material that draws: a physics-only one would hide the display colour
            if m and m.GetSurfaceOutput() and m.GetSurfaceOutput().HasConnectedSource():
                render = m.GetPath()
        if physics is None and p.HasAPI(UsdPhysics.CollisionAPI):
            m = api.ComputeBoundMaterial("physics")[0] or api.ComputeBoundMaterial()[0]
            if m and m.GetPrim().HasAPI(UsdPhysics.MaterialAPI):
                physics = m.GetPath()
    return colour, render, physics


def write_overlay(path, frames, model, shot) -> ExportInfo:
    """Write ``frames`` of ``model`` as an overlay over ``shot``'s stage at ``path``."""
    t0 = time.perf_counter()
    w = OverlayWriter(path, model, shot)
    w.add(frames)
    info = w.save()
    return ExportInfo(info.path, time.perf_counter() - t0, info.n_time_samples, info.bytes)
