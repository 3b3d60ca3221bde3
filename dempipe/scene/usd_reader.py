"""A UsdPhysics stage read as a dempipe Scene (what a DCC exports for a shot).

:func:`load_usd_scene` opens a stage with pxr and returns the same
:class:`~dempipe.scene.toml_reader.Scene` the TOML path builds, so ``build_model``, ``bake``,
``check`` and ``report`` take it unchanged. Its ``usd`` field is a :class:`UsdShot`:
which prim (or point-instancer entry) each body is, the matrices the overlay writer
(``dempipe.usd.overlay``) needs to author each body's animation back under its
own parents, and the one warning listing what dempipe does not simulate.

Conventions: the simulation runs in SI units in the stage's own world axes (a Y-up
stage stays Y-up); lengths are multiplied by ``metersPerUnit``, masses by
``kilogramsPerUnit``, angular velocities converted from degrees per second.
Matrices are USD's row-vector 4 × 4 (``p_world = p_local · M``); a body's world
matrix is split into a stretch S (symmetric: the scale it keeps) and a rotation R,
``A = S R``: the body's collision geometry is built in the stretched local frame,
so dempipe moves a rigid shape and the overlay puts S back. What is read and the
precedence rules are in docs/usd-input.md.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dempipe.errors import SceneError
from dempipe.scene.data import (
    STANDARD_GRAVITY,
    BodyGroup,
    MaterialSpec,
    MeshCollider,
    OutputSettings,
    PlaneCollider,
    Scene,
    ShapeSpec,
    SimulationSettings,
)
from dempipe.scene.settings import parse_simulation
from dempipe.scene.usd_attributes import fracture_and_glue, glue_material
from dempipe.scene.usd_stage import (
    MAX_FRICTION,
    MAX_GRAVITY,
    MAX_MASS,
    TIME_CODE_MAX,
    UNIT_RANGE,
    check_instancer_arrays,
    density_of,
    finite_vector,
    mass_of,
    open_stage,
    stage_number,
)
from dempipe.scene.usd_geometry import (
    MAX_COORDINATE,
    cube_ground_top,
    gprim_mesh,
    matrix_array,
    quat_matrix,
    matrix_to_quat,
    mesh_ground_top,
    polar,
    stage_up,
)
from dempipe.sim.motion import Key, Motion

__all__ = ["UsdBody", "UsdShot", "load_usd_scene", "load_usd_settings"]

#: Density of a body whose shapes have none (no MassAPI, no material density) [kg/m³]:
#: water, as PhysX and Newton default.
DEFAULT_DENSITY = 1000.0
#: Duration baked when the stage has no time range [s].
DEFAULT_DURATION = 4.0

_USD_SETTINGS_KEYS = ("stage",)
_SIM_FROM_STAGE = ("gravity",)


# ----------------------------------------------------------------------------- data


@dataclass(frozen=True)
class UsdBody:
    """Where one simulated body lives in the stage.

    prim : path of the body prim (RigidBodyAPI), or of the point instancer.
    instance : index into the instancer's arrays, or -1 for a body prim.
    stretch : (3, 3) the scale the body keeps, S of ``A = S R`` (row convention,
        stage units per local unit; symmetric).
    com : (3,) centre of mass in the body's stretched local frame [m] (what dempipe
        puts at the body origin); filled in from the Model by the overlay writer.
    kinematic : whether the body follows its authored animation (not written back).
    fractured : whether the body is its pieces (``dempipe:fracture:*``, its group's
        bodies in the Model).
    """

    prim: str
    instance: int = -1
    stretch: np.ndarray = field(default_factory=lambda: np.eye(3))
    kinematic: bool = False
    """A kinematic body (``kinematicEnabled``): it follows the prim's own animation,
    which the overlay leaves as it is."""
    fractured: bool = False
    """A fractured body (``dempipe:fracture:pieces``): the Model has a body per piece
    (of the group this body is), which the overlay writes as prims of their own."""


@dataclass(frozen=True)
class UsdShot:
    """A stage read for baking: what the overlay writer needs besides Frames.

    stage_path : absolute path of the input stage (the overlay's subLayer).
    bodies : one UsdBody per body group of the Scene (and the Model's body_group): a
        whole body is one Model body, a fractured one its pieces.
    instancers : {instancer path: (n_instances, proto transform matrices (n,4,4) of
        each instance's prototype root local xform)} for instancers of bodies.
    meters_per_unit, kilograms_per_unit, up_axis : the stage's.
    start, end, tcps : the stage's time range and time codes per second.
    warnings : one-line messages for the user (what is not simulated, planes taken
        from flat cubes and meshes, ...).
    """

    stage_path: Path
    bodies: tuple
    instancers: dict
    meters_per_unit: float
    kilograms_per_unit: float
    up_axis: str
    start: float
    end: float
    tcps: float
    warnings: tuple = ()


# ---------------------------------------------------------------------------- reader


def _name(path: str, used: set) -> str:
    """A unique group/shape name from a prim path (its last element)."""
    base = re.sub(r"[^A-Za-z0-9_]", "_", path.rstrip("]").split("/")[-1]) or "body"
    if base[0].isdigit():
        base = "_" + base
    name, k = base, 1
    while name in used:
        name = f"{base}_{k}"
        k += 1
    used.add(name)
    return name


class _Reader:
    """One pass over a stage; see load_usd_scene."""

    def __init__(self, stage, path: Path, sim: SimulationSettings, gravity_given: bool):
        from pxr import Usd, UsdGeom, UsdPhysics

        self.stage, self.path, self.sim = stage, path, sim
        self.src = path.name
        self.mpu = stage_number(UsdGeom.GetStageMetersPerUnit(stage), "metersPerUnit",
                                 path, UNIT_RANGE)
        self.kpu = stage_number(UsdPhysics.GetStageKilogramsPerUnit(stage),
                                 "kilogramsPerUnit", path, UNIT_RANGE)
        up = str(UsdGeom.GetStageUpAxis(stage))
        self.up_axis = "Y" if up == "Y" else "Z"
        self.start = stage_number(stage.GetStartTimeCode(), "startTimeCode", path,
                                   (-TIME_CODE_MAX, TIME_CODE_MAX), zero=True)
        self.end = stage_number(stage.GetEndTimeCode(), "endTimeCode", path,
                                 (-TIME_CODE_MAX, TIME_CODE_MAX), zero=True)
        self.tcps = stage_number(stage.GetTimeCodesPerSecond(), "timeCodesPerSecond", path,
                                  (1.0, 1e5))
        if abs(self.tcps - round(self.tcps)) > 1e-9:
            raise SceneError(f"{path.name}: timeCodesPerSecond = {self.tcps:g} is not a whole "
                             "number of frames per second (dempipe samples one frame per "
                             "time code)")
        if not stage.HasAuthoredTimeCodeRange() or self.end <= self.start:
            self.end = self.start + DEFAULT_DURATION * self.tcps
            self.no_range = True
        else:
            self.no_range = False
        self.t0 = Usd.TimeCode(self.start)
        self.xf = UsdGeom.XformCache(self.t0)
        self.gravity_given = gravity_given
        self.ignored: list[str] = []
        self.notes: list[str] = []
        self.materials: dict[str, MaterialSpec] = {"default": MaterialSpec("default")}
        self.material_of_prim: dict[str, str] = {}
        self.names: set = {"default"}
        self.shapes: dict[str, ShapeSpec] = {}
        self.groups: list[BodyGroup] = []
        self.bodies: list[UsdBody] = []
        self.colliders: list = []
        self.instancers: dict = {}
        self.collider_names: set = set()

    # -- helpers ----------------------------------------------------------------
    def where(self, prim) -> str:
        return f"{self.src}: {prim.GetPath()}"

    def world(self, prim) -> np.ndarray:
        W = matrix_array(self.xf.GetLocalToWorldTransform(prim))
        if not (np.isfinite(W).all() and np.abs(W).max() <= MAX_COORDINATE):
            raise SceneError(f"{self.where(prim)}: its transform (or a parent's) holds a "
                             f"non-finite or huge number (beyond ±{MAX_COORDINATE:g}); fix "
                             "the xformOps")
        return W

    def material(self, prim) -> tuple[str, MaterialSpec | None]:
        """The physics material bound to ``prim`` (purpose physics, then all-purpose)."""
        from pxr import UsdPhysics, UsdShade

        api = UsdShade.MaterialBindingAPI(prim)
        mat = api.ComputeBoundMaterial("physics")[0]
        if not mat:
            mat = api.ComputeBoundMaterial()[0]
        if not mat or not mat.GetPrim().HasAPI(UsdPhysics.MaterialAPI):
            return "default", None
        p = str(mat.GetPath())
        if p in self.material_of_prim:
            name = self.material_of_prim[p]
            return name, self.materials[name]
        m = UsdPhysics.MaterialAPI(mat.GetPrim())
        key = f"{self.src}: {p}"
        e = float(m.GetRestitutionAttr().Get() or 0.0)
        if not 0.0 <= e <= 1.0:     # NaN too
            raise SceneError(f"{key}: physics:restitution = {e:g} is out of range "
                             "(expected a number in [0, 1])")
        mu = float(m.GetDynamicFrictionAttr().Get() or 0.0)
        if not 0 <= mu <= MAX_FRICTION:
            raise SceneError(f"{key}: physics:dynamicFriction = {mu:g} (expected a number in "
                             f"[0, {MAX_FRICTION:g}])")
        rho = density_of(m.GetDensityAttr(), self.kpu, self.mpu, key)
        glue = glue_material(mat.GetPrim(), key)
        name = _name(p, self.names)
        spec = MaterialSpec(name, density=rho if rho > 0 else DEFAULT_DENSITY, restitution=e,
                            friction=mu, **glue)
        self.materials[name] = spec
        self.material_of_prim[p] = name
        # remember whether the density was authored for the mass rules
        if rho > 0:
            self.notes_density = getattr(self, "notes_density", set()) | {name}
        return name, spec

    def material_density(self, name: str) -> float | None:
        return (self.materials[name].density
                if name in getattr(self, "notes_density", set()) else None)

    # -- traversal --------------------------------------------------------------
    def read(self):
        from pxr import Usd, UsdGeom, UsdPhysics

        scenes = [p for p in self.stage.Traverse() if p.IsA(UsdPhysics.Scene)]
        self.gravity = self.read_gravity(scenes[0] if scenes else None)
        if len(scenes) > 1:
            self.ignored.append("extra physics scenes (the first is used): "
                                + ", ".join(str(p.GetPath()) for p in scenes[1:]))
        # prototypes of instancers of rigid bodies are read through the instancer
        protos: set = set()
        for prim in self.stage.Traverse():
            if prim.IsA(UsdGeom.PointInstancer):
                for t in UsdGeom.PointInstancer(prim).GetPrototypesRel().GetTargets():
                    protos.add(str(t))
        body_prims, kinematic_prims, static_colliders = [], [], []
        bodies_at: set = set()
        unsupported = {"joints": [], "articulations": [], "filtered pairs": [],
                       "collision groups": [], "deformables": [],
                       "disabled bodies (their shapes are static colliders)": [],
                       "bodies inside native instances (make them not instanceable)": [],
                       "static colliders inside native instances (make them not "
                       "instanceable)": []}
        it = iter(Usd.PrimRange(self.stage.GetPseudoRoot()))
        for prim in it:
            ps = str(prim.GetPath())
            if ps in protos:
                it.PruneChildren()
                continue
            if prim.IsA(UsdGeom.PointInstancer):
                self.read_instancer(prim)
                it.PruneChildren()
                continue
            if prim.IsInstance():
                # an instance proxy cannot be overridden by the overlay; the instance
                # prim itself can: a body there has its shapes in the prototype
                inside = [p for p in Usd.PrimRange(prim, Usd.TraverseInstanceProxies())
                          if p != prim and p.HasAPI(UsdPhysics.RigidBodyAPI)]
                if inside:
                    unsupported["bodies inside native instances (make them not "
                                "instanceable)"].append(ps)
                it.PruneChildren()
                if not prim.HasAPI(UsdPhysics.RigidBodyAPI):
                    if (not self.inside_body(prim, bodies_at)
                            and any(p.HasAPI(UsdPhysics.CollisionAPI)
                                    and self.collision_enabled(p) for p in
                                    Usd.PrimRange(prim, Usd.TraverseInstanceProxies()))):
                        unsupported["static colliders inside native instances (make them "
                                    "not instanceable)"].append(ps)
                    continue
            schemas = [str(s) for s in prim.GetAppliedSchemas()]
            if prim.IsA(UsdPhysics.Joint):
                unsupported["joints"].append(ps)
            if prim.HasAPI(UsdPhysics.ArticulationRootAPI):
                unsupported["articulations"].append(ps)
            if prim.HasAPI(UsdPhysics.FilteredPairsAPI):
                unsupported["filtered pairs"].append(ps)
            if prim.IsA(UsdPhysics.CollisionGroup):
                unsupported["collision groups"].append(ps)
            if any("Deformable" in s for s in schemas) or "Deformable" in str(prim.GetTypeName()):
                unsupported["deformables"].append(ps)
            if prim.HasAPI(UsdPhysics.RigidBodyAPI):
                rb = UsdPhysics.RigidBodyAPI(prim)
                if not rb.GetRigidBodyEnabledAttr().Get():
                    unsupported["disabled bodies (their shapes are static colliders)"].append(ps)
                else:
                    (kinematic_prims if rb.GetKinematicEnabledAttr().Get()
                     else body_prims).append(prim)
                    # its collision prims are its shapes; a body nested below it is a
                    # body of its own (the traversal goes on to find it)
                    bodies_at.add(prim.GetPath())
                    if prim.IsInstance():
                        it.PruneChildren()
                continue
            if (prim.HasAPI(UsdPhysics.CollisionAPI) and self.collision_enabled(prim)
                    and not self.inside_body(prim, bodies_at)):
                static_colliders.append((prim, "static"))
        for prim in body_prims:
            self.read_body(prim)
        for prim in kinematic_prims:
            self.read_kinematic(prim)
        for prim, why in static_colliders:
            self.read_static(prim)
        for what, prims in unsupported.items():
            if prims:
                self.ignored.append(f"{what}: {', '.join(prims)}")

    @staticmethod
    def inside_body(prim, bodies_at: set) -> bool:
        """Whether an ancestor of ``prim`` is an enabled rigid body (its shapes are
        that body's, not static colliders)."""
        p = prim.GetParent()
        while p and not p.IsPseudoRoot():
            if p.GetPath() in bodies_at:
                return True
            p = p.GetParent()
        return False

    def collision_enabled(self, prim) -> bool:
        from pxr import UsdPhysics

        return bool(UsdPhysics.CollisionAPI(prim).GetCollisionEnabledAttr().Get())

    def collision_prims(self, root) -> list:
        """Prims with CollisionAPI at or below ``root``, not inside a nested body."""
        from pxr import Usd, UsdPhysics

        out = []
        # an instanceable body's shapes are instance proxies in its prototype
        it = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies()) if root.IsInstance()
                  else Usd.PrimRange(root))
        for prim in it:
            if prim != root and prim.HasAPI(UsdPhysics.RigidBodyAPI):
                it.PruneChildren()          # a nested body is its own body
                continue
            if prim.HasAPI(UsdPhysics.CollisionAPI) and self.collision_enabled(prim):
                out.append(prim)
        return out

    def read_gravity(self, scene_prim) -> np.ndarray:
        """Gravity [m/s²], world frame: the scene's direction and magnitude, each
        defaulting as the schema says (−up; 9.81 m/s² expressed in stage units)."""
        up = np.array([0.0, 1.0, 0.0]) if self.up_axis == "Y" else np.array([0.0, 0.0, 1.0])
        if self.gravity_given:
            return np.asarray(self.sim.gravity, dtype=np.float64)
        direction, magnitude = -up, STANDARD_GRAVITY
        if scene_prim is not None:
            from pxr import UsdPhysics

            s = UsdPhysics.Scene(scene_prim)
            where = self.where(scene_prim)
            d = finite_vector(s.GetGravityDirectionAttr().Get() or (0, 0, 0), where,
                              "physics:gravityDirection")
            big = float(np.abs(d).max())
            if big > 0:                 # scaled first: the norm of (1e300, 0, 0) is inf
                direction = (d / big) / np.linalg.norm(d / big)
            g = float(s.GetGravityMagnitudeAttr().Get())
            if g != -math.inf:          # the schema's "not authored"
                if not (math.isfinite(g) and 0 <= g * self.mpu <= MAX_GRAVITY):
                    raise SceneError(f"{where}: physics:gravityMagnitude = {g:g} (expected "
                                     f"-inf for the default, or a number in [0, "
                                     f"{MAX_GRAVITY / self.mpu:g}] stage units/s²)")
                magnitude = g * self.mpu          # stage units/s² → m/s²
        return direction * magnitude

    # -- bodies -----------------------------------------------------------------
    def shape_meshes(self, body_prim, W_body, prims, S):
        """Each collision prim's mesh in the body's stretched local frame [m], its
        material name and MassAPI (mass [kg], density [kg/m³]) if any."""
        from pxr import UsdPhysics

        inv_body = np.linalg.inv(W_body)
        out = []
        for c in prims:
            mesh = gprim_mesh(c, self.where(c))
            if mesh is None:
                self.ignored.append(f"collision shapes of an unread type "
                                    f"({c.GetTypeName()}): {c.GetPath()}")
                continue
            rel = self.relative(c, body_prim, W_body, inv_body)
            # local → body local, then the body's stretch, then metres
            M = rel.copy()
            M[:3, :3] = rel[:3, :3] @ S
            M[3, :3] = rel[3, :3] @ S
            v = (np.c_[mesh.vertices, np.ones(len(mesh.vertices))] @ M)[:, :3] * self.mpu
            faces = np.asarray(mesh.faces)
            if np.linalg.det(M[:3, :3]) < 0:
                faces = faces[:, ::-1]
            import trimesh

            m = trimesh.Trimesh(v, faces)            # merged: DCC meshes repeat corners
            if m.is_watertight:
                m.fix_normals()
            name, _ = self.material(c)
            mass = density = None
            if c.HasAPI(UsdPhysics.MassAPI):
                api = UsdPhysics.MassAPI(c)
                cw = self.where(c)
                mass = mass_of(api.GetMassAttr(), self.kpu, cw)
                density = density_of(api.GetDensityAttr(), self.kpu, self.mpu, cw) or None
            out.append((c, m, name, mass, density))
        return out

    def relative(self, c, body_prim, W_body, inv_body):
        """Transform from collision prim ``c``'s local space to the body prim's."""
        if self._proto_root is not None:
            return (np.eye(4) if c == body_prim
                    else matrix_array(self.xf.ComputeRelativeTransform(c, body_prim)[0]))
        return self.world(c) @ inv_body

    _proto_root = None

    def read_body(self, prim, W=None, instancer: str | None = None, instance: int = -1,
                  velocity=None, angular=None):
        """One rigid body: a prim with RigidBodyAPI, or one instance of a prototype
        (``W`` its world matrix, ``velocity``/``angular`` in world units [stage units/s,
        deg/s])."""
        import trimesh
        from pxr import UsdPhysics

        where = self.where(prim) if instancer is None else f"{self.src}: {instancer}[{instance}]"
        self._proto_root = prim if instancer is not None else None
        W_body = self.world(prim) if W is None else W
        if not (np.isfinite(W_body).all() and np.abs(W_body).max() <= MAX_COORDINATE):
            raise SceneError(f"{where}: the instance's transform holds a non-finite or huge "
                             "number; fix positions, orientations or scales")
        S, R = polar(W_body[:3, :3])
        if abs(np.linalg.det(S)) < 1e-300:
            raise SceneError(f"{where}: the body's transform has zero scale")
        prims = self.collision_prims(prim)
        if not prims:
            raise SceneError(f"{where}: a rigid body without collision shapes (apply "
                             "PhysicsCollisionAPI to it or to a mesh or gprim below it)")
        parts = self.shape_meshes(prim, W_body, prims, S)
        self._proto_root = None
        if not parts:
            raise SceneError(f"{where}: none of the body's collision shapes can be read "
                             "(Mesh, Cube, Sphere, Capsule, Cylinder, Cone)")
        mesh = trimesh.util.concatenate([m for _, m, _, _, _ in parts]) if len(parts) > 1 \
            else parts[0][1]
        # contacts use the material of the largest shape; mass sums the shapes' (PhysX's rule)
        vols = [abs(float(m.volume)) if m.is_watertight else float(np.prod(m.extents))
                for _, m, _, _, _ in parts]
        mat = parts[int(np.argmax(vols))][2]
        mats = {name for _, _, name, _, _ in parts}
        if len(mats) > 1:
            self.notes.append(f"{where}: collision shapes bound to different materials "
                              f"({', '.join(sorted(mats))}); contacts use {mat!r}, the "
                              "largest shape's, and the mass sums each shape's")

        mass, com, inertia = self.mass_properties(prim, parts, S, where)
        fracture, glue = fracture_and_glue(
            prim, where, S, self.mpu, instancer is not None, self.materials[mat],
            next((p for p, n in self.material_of_prim.items() if n == mat), None), prims)
        if fracture is not None and (com is not None or inertia is not None):
            self.notes.append(f"{where}: a fractured body: each piece's centre of mass and "
                              "inertia come from its mesh at one density (physics:centerOfMass"
                              ", diagonalInertia or unequal shape densities are not used)")
            com = inertia = None
        group = _name(instancer + f"_{instance}" if instancer else str(prim.GetPath()),
                      self.names)
        self.shapes[group] = ShapeSpec(name=group, mesh=mesh, fracture=fracture,
                                       center_of_mass=None if com is None else tuple(com))
        rb = UsdPhysics.RigidBodyAPI(prim)
        if velocity is None:
            # "in the same space as the node's xform": the parent's space
            parent = self.xf.GetParentToWorldTransform(prim)
            P3 = matrix_array(parent)[:3, :3]
            v = finite_vector(rb.GetVelocityAttr().Get() or (0, 0, 0), where,
                               "physics:velocity") @ P3
            _, Rp = polar(P3)
            w = finite_vector(rb.GetAngularVelocityAttr().Get() or (0, 0, 0), where,
                               "physics:angularVelocity") @ Rp
        else:
            v, w = np.asarray(velocity, float), np.asarray(angular, float)
        if not (np.isfinite(W_body).all() and np.abs(W_body).max() <= MAX_COORDINATE):
            raise SceneError(f"{where}: the body's transform holds a non-finite or huge "
                             "number; fix its xformOps or its parents'")
        q = matrix_to_quat(R.T)
        self.groups.append(BodyGroup(
            name=group, shape=group, material=mat, position=tuple(W_body[3, :3] * self.mpu),
            rotation=tuple(q), velocity=tuple(v * self.mpu), angular_velocity=tuple(np.radians(w)),
            mass=mass, inertia=None if inertia is None else tuple(map(tuple, inertia)),
            starts_asleep=bool(rb.GetStartsAsleepAttr().Get()), glue=glue))
        self.bodies.append(UsdBody(prim=instancer or str(prim.GetPath()), instance=instance,
                                   stretch=S, fractured=fracture is not None))

    def read_kinematic(self, prim):
        """A kinematic body: a single-body group with ``kinematic = True`` whose Motion
        keys are the prim's world pose (mesh origin [m], rotation) at every time
        sample authored on its xformOps or its ancestors' (linear keys: USD
        interpolates between samples); one key, held, when nothing is animated."""
        from pxr import Usd, UsdGeom

        if not self.collision_prims(prim):
            self.ignored.append(f"kinematic bodies without collision shapes (nothing "
                                f"to push with): {prim.GetPath()}")
            return
        self.read_body(prim)
        codes = set()
        p = prim
        while p and not p.IsPseudoRoot():
            if p.IsA(UsdGeom.Xformable):
                codes.update(UsdGeom.Xformable(p).GetTimeSamples())
            p = p.GetParent()
        codes = sorted(codes) or [self.start]
        origin = float(round(self.start))           # simulation time 0 (the first frame)
        S0 = self.bodies[-1].stretch
        keys, scaled = [], False
        for code in codes:
            W = matrix_array(UsdGeom.XformCache(Usd.TimeCode(code)).GetLocalToWorldTransform(prim))
            S, R = polar(W[:3, :3])
            scaled |= bool(np.abs(S - S0).max() > 1e-6 * max(np.abs(S0).max(), 1e-300))
            keys.append(Key(time=(code - origin) / self.tcps,
                            position=tuple(float(x) for x in W[3, :3] * self.mpu),
                            rotation=tuple(float(x) for x in matrix_to_quat(R.T))))
        if scaled:
            self.notes.append(f"{self.where(prim)}: a kinematic body whose scale is "
                              "animated; it moves at its start-time scale")
        g = self.groups[-1]
        self.groups[-1] = replace(g, kinematic=True, motion=Motion(keys=tuple(keys)),
                                  velocity=(0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 0.0),
                                  starts_asleep=False)
        self.bodies[-1] = replace(self.bodies[-1], kinematic=True)

    def mass_properties(self, prim, parts, S, where):
        """(mass [kg] | None, centre of mass [m] | None, inertia [kg m²] | None), the
        schema's precedence: the body's MassAPI mass, then its density, then each
        shape's MassAPI mass or density, its material's density, DEFAULT_DENSITY."""
        from pxr import UsdPhysics

        body_mass = body_density = com = inertia = None
        if prim.HasAPI(UsdPhysics.MassAPI):
            api = UsdPhysics.MassAPI(prim)
            body_mass = mass_of(api.GetMassAttr(), self.kpu, where)
            dv = density_of(api.GetDensityAttr(), self.kpu, self.mpu, where)
            body_density = dv if dv > 0 else None
            c = api.GetCenterOfMassAttr().Get()
            # the schema's "not authored" is -inf in each component
            if c is not None and not all(x == -math.inf for x in c):
                c = finite_vector(c, where, "physics:centerOfMass")
                if np.abs(c).max() > MAX_COORDINATE:
                    raise SceneError(f"{where}: physics:centerOfMass = {tuple(c)} is beyond "
                                     f"±{MAX_COORDINATE:g}")
                com = (np.asarray(c, float) @ S) * self.mpu
            dg = api.GetDiagonalInertiaAttr().Get()
            if dg is not None and any(x != 0 for x in dg):
                if any(not 0 <= x <= MAX_MASS * MAX_COORDINATE for x in dg):
                    raise SceneError(f"{where}: physics:diagonalInertia = {tuple(dg)} must be "
                                     "positive and finite")
                pa = api.GetPrincipalAxesAttr().Get()
                Rpa = np.eye(3)
                if pa is not None and pa.GetLength() > 0:
                    im = pa.GetImaginary()
                    Rpa = quat_matrix([pa.GetReal(), im[0], im[1], im[2]])
                inertia = Rpa @ np.diag(np.asarray(dg, float)) @ Rpa.T * self.kpu * self.mpu ** 2
        if body_mass is not None:
            return body_mass, com, inertia      # the shapes' inertia, scaled to the mass
        # each shape's mass or density (the body's density wins over the shapes')
        entries = []                             # (mass [kg] | None, density | None, mesh)
        for c, m, name, smass, sdens in parts:
            if body_density is not None:
                entries.append((None, body_density, m))
            elif smass is not None:
                entries.append((smass, None, m))
            else:
                entries.append((None, sdens or self.material_density(name) or DEFAULT_DENSITY,
                                m))
        closed = all(m.is_watertight for _, _, m in entries)
        if not closed:
            rhos = [r for _, r, _ in entries if r is not None]
            if len(set(rhos)) > 1 or len(rhos) < len(entries):
                self.notes.append(f"{where}: open collision meshes; mass from the spheres at "
                                  "one density")
            # the Model takes density × the sphere set's volume
            return None, com, inertia
        masses = [(mm if mm is not None else r * abs(float(m.volume)), m)
                  for mm, r, m in entries]
        total = sum(x for x, _ in masses)
        densities = {round(x / abs(float(m.volume)), 9) for x, m in masses}
        if len(densities) > 1 and com is None and inertia is None:
            # shapes of different densities: sum their mass properties (PhysX's rule)
            com = sum(x * np.asarray(m.center_mass) for x, m in masses) / total
            inertia = np.zeros((3, 3))
            for x, m in masses:
                d = np.asarray(m.center_mass) - com
                inertia += (x / abs(float(m.volume))) * np.asarray(m.moment_inertia) + x * (
                    float(d @ d) * np.eye(3) - np.outer(d, d))
        return total, com, inertia

    # -- instancers -------------------------------------------------------------
    def read_instancer(self, prim):
        """Each instance of a prototype carrying RigidBodyAPI is a body."""
        from pxr import UsdGeom, UsdPhysics

        pi = UsdGeom.PointInstancer(prim)
        targets = [self.stage.GetPrimAtPath(t) for t in pi.GetPrototypesRel().GetTargets()]
        is_body = [bool(t) and t.HasAPI(UsdPhysics.RigidBodyAPI)
                   and bool(UsdPhysics.RigidBodyAPI(t).GetRigidBodyEnabledAttr().Get())
                   and not UsdPhysics.RigidBodyAPI(t).GetKinematicEnabledAttr().Get()
                   for t in targets]
        if not any(is_body):
            if any(t and t.HasAPI(UsdPhysics.RigidBodyAPI) for t in targets):
                self.ignored.append(f"instancers of kinematic or disabled bodies: "
                                    f"{prim.GetPath()}")
            return
        ps = str(prim.GetPath())
        where = self.where(prim)
        proto_idx = np.asarray(pi.GetProtoIndicesAttr().Get(self.t0) or [], dtype=np.int64)
        n = len(proto_idx)
        bad = proto_idx[(proto_idx < 0) | (proto_idx >= len(targets))]
        if len(bad):
            raise SceneError(f"{where}: protoIndices holds {int(bad[0])}, but the instancer "
                             f"has {len(targets)} prototype(s) (indices 0..{len(targets) - 1})")
        check_instancer_arrays(pi, self.t0, n, where)
        xforms = pi.ComputeInstanceTransformsAtTime(self.t0, self.t0)
        W_inst = self.world(prim)
        vel = pi.GetVelocitiesAttr().Get(self.t0)
        ang = pi.GetAngularVelocitiesAttr().Get(self.t0)
        proto_local = np.zeros((n, 4, 4))

        for i in range(n):
            k = int(proto_idx[i])
            root = targets[k]
            proto_local[i] = (np.eye(4) if not root.IsA(UsdGeom.Xformable) else
                              matrix_array(UsdGeom.Xformable(root).GetLocalTransformation(self.t0)))
            if not is_body[k]:
                continue
            W = matrix_array(xforms[i]) @ W_inst
            v = (np.asarray(vel[i], float) if vel and len(vel) > i else np.zeros(3)) \
                @ W_inst[:3, :3]
            _, Ri = polar(W_inst[:3, :3])
            w = (np.asarray(ang[i], float) if ang and len(ang) > i else np.zeros(3)) @ Ri
            self.read_body(root, W=W, instancer=ps, instance=i, velocity=v, angular=w)
        self.instancers[ps] = (n, proto_local)

    # -- static colliders --------------------------------------------------------
    def read_static(self, prim):
        import trimesh
        from pxr import UsdGeom

        where = self.where(prim)
        W = self.world(prim)
        name = _name(str(prim.GetPath()), self.collider_names)
        mat, _ = self.material(prim)
        if prim.GetTypeName() == "Plane":
            axis = UsdGeom.Plane(prim).GetAxisAttr().Get()
            n_local = np.eye(3)[{"X": 0, "Y": 1, "Z": 2}[axis]]
            n = np.linalg.inv(W[:3, :3]) @ n_local          # normals: inverse transpose
            self.add_plane(W[3, :3] * self.mpu, n, mat, name)
            return
        mesh = gprim_mesh(prim, where)
        if mesh is None:
            self.ignored.append(f"collision shapes of an unread type ({prim.GetTypeName()}): "
                                f"{prim.GetPath()}")
            return
        v = (np.c_[mesh.vertices, np.ones(len(mesh.vertices))] @ W)[:, :3] * self.mpu
        if prim.GetTypeName() in ("Cube", "Mesh") and self.as_ground_plane(prim, W, v, mat,
                                                                           name):
            return
        faces = np.asarray(mesh.faces)
        if np.linalg.det(W[:3, :3]) < 0:
            faces = faces[:, ::-1]
        self.colliders.append(MeshCollider(mesh=trimesh.Trimesh(v, faces, process=False),
                                           material=mat, name=name))

    def add_plane(self, point, normal, mat, name):
        n = np.asarray(normal, float)
        n /= np.linalg.norm(n)
        # the free side is the side the bodies are on (their mean start position)
        if self.groups:
            centre = np.mean([g.position for g in self.groups], axis=0)
            if float((centre - point) @ n) < 0:
                n = -n
        self.colliders.append(PlaneCollider(point=tuple(point), normal=tuple(n),
                                            material=mat, name=name))

    def as_ground_plane(self, prim, W, v, mat, name) -> bool:
        """A collision Cube or Mesh that is a ground plane (usd_geometry.cube_ground_top,
        mesh_ground_top: huge, flat and level, as a DCC's ground quad is) becomes an
        infinite plane at its top, said in a note; ``v``: its vertices, world [m]."""
        from pxr import UsdGeom

        up = stage_up(self.gravity, self.up_axis)
        biggest = max((float(np.max(s.mesh.extents)) for s in self.shapes.values()),
                      default=0.0)
        kind = prim.GetTypeName()
        if kind == "Cube":
            size = float(UsdGeom.Cube(prim).GetSizeAttr().Get())
            got = cube_ground_top(W, size, self.mpu, up, biggest)
        else:
            got = mesh_ground_top(v, up, biggest, self.where(prim))
        if got is None:
            return False
        self.add_plane(got[0], up, mat, name)
        self.notes.append(f"{self.where(prim)}: a flat {kind.lower()} {got[1]:.3g} m wide "
                          "taken as an infinite ground plane at its top")
        return True


# ------------------------------------------------------------------------------ API


def load_usd_scene(path, simulation: SimulationSettings | None = None, *,
                   gravity_given: bool = False, settings_path: Path | None = None) -> Scene:
    """Read the UsdPhysics stage at ``path`` as a Scene whose ``usd`` is a UsdShot.

    simulation : dempipe's own settings (sphere size, dt, stiffness, sleeping); the
        defaults when None. Its gravity replaces the stage's only with gravity_given.
    settings_path : the TOML file that named the stage (the Scene's path then, so
        messages name it); None: the stage itself.
    Raises SceneError naming the file and prim for anything unusable.
    """
    p = Path(path).expanduser().resolve()
    stage = open_stage(p)
    sim = simulation or SimulationSettings()
    r = _Reader(stage, p, sim, gravity_given)
    r.read()
    if not r.groups:
        left = f"; not simulated: {'; '.join(r.ignored)}" if r.ignored else ""
        raise SceneError(f"{p.name}: no rigid bodies to simulate (apply PhysicsRigidBodyAPI "
                         f"to a prim with PhysicsCollisionAPI at or below it){left}")
    warnings = []
    if r.no_range:
        warnings.append(f"{p.name}: no time range (startTimeCode/endTimeCode); baking "
                        f"{DEFAULT_DURATION:g} s from time code {r.start:g}")
    not_sim = list(r.ignored)
    if not_sim:
        warnings.append(f"{p.name}: not simulated: " + "; ".join(not_sim))
    warnings += r.notes
    sim = SimulationSettings(**{**{f: getattr(sim, f) for f in sim.__dataclass_fields__},
                                "gravity": tuple(float(x) for x in r.gravity)})
    start = int(round(r.start))
    output = OutputSettings(fps=int(round(r.tcps)), duration=(r.end - r.start) / r.tcps,
                            up_axis=r.up_axis, meters_per_unit=r.mpu, start_frame=start)
    shot = UsdShot(stage_path=p, bodies=tuple(r.bodies), instancers=dict(r.instancers),
                   meters_per_unit=r.mpu, kilograms_per_unit=r.kpu, up_axis=r.up_axis,
                   start=float(start), end=r.end, tcps=r.tcps, warnings=tuple(warnings))
    return Scene(path=settings_path or p, output=output, simulation=sim,
                 materials=dict(r.materials), shapes=dict(r.shapes), bodies=tuple(r.groups),
                 colliders=tuple(r.colliders), usd=shot)


def load_usd_settings(ctx, data: dict) -> Scene:
    """A TOML file of dempipe settings for a stage: ``[usd] stage = "shot.usda"`` and an
    optional ``[simulation]`` table (the scene itself comes from the stage)."""
    for k in data:
        if k not in ("usd", "simulation"):
            raise ctx.error(k, "not used with [usd]",
                            "the stage gives the bodies, colliders, materials and timing; "
                            "keep only [usd] and [simulation]")
    u = ctx.table(data["usd"], "usd")
    ctx.check_keys(u, "usd", _USD_SETTINGS_KEYS)
    stage = ctx.string(ctx.require(u, "usd", "stage", 'e.g. stage = "shot.usda"'), "usd.stage")
    sp = Path(stage).expanduser()
    if not sp.is_absolute():
        sp = ctx.base / sp
    if not sp.is_file():
        raise ctx.error("usd.stage", f"stage not found: {sp}",
                        "paths are relative to the settings file's folder")
    sim_raw = data.get("simulation", {})
    sim = parse_simulation(ctx, sim_raw, "Z")
    given = isinstance(sim_raw, dict) and "gravity" in sim_raw
    return load_usd_scene(sp, sim, gravity_given=given, settings_path=ctx.path)
