"""ModelBuilder: shapes, materials, bodies and colliders in, a frozen Model out.

    b = ModelBuilder(diameter=0.01)
    steel = b.add_material(materials.Material("steel", density=7800.0, restitution=0.6))
    rook = b.add_shape("rook", mesh, sphere_set)
    b.add_bodies("rooks", rook, steel, positions)
    b.add_plane((0, 0, 0), (0, 0, 1), steel)
    model = b.finalize(fps=24, n_frames=97)

``finalize`` derives what the contacts need from the scene (stiffness, damping,
time step, the features the kernels specialize on; docs/stability.md), and packs
prescribed motion (``_prescribed``: moving colliders, kinematic and emitted
bodies). The Model and its records are in model.py; model.py still answers
``ModelBuilder`` for code that imports it from there.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from dempipe.errors import SceneError, StabilityError
from dempipe.sim import glue, laws
from dempipe.sim import materials as mat
from dempipe.sim import motion as mo
from dempipe.sim.model import (
    CONTACT_LAYERS,
    PLANE_DEPTH_DIAMETERS,
    BoxCollider,
    ColliderMotion,
    Features,
    Model,
    ShapeInstance,
    StaticMesh,
    frozen,
    quat_to_matrix,
    rotational_mass_factor,
    sleep_defaults,
)
from dempipe.spheres.inscribed import COLUMNS, COVERED, all_own, wall_tori
from dempipe.spheres.sphere_set import surface_mask

if TYPE_CHECKING:  # spheres imports numba; the model only needs the type
    from dempipe.spheres.sphere_set import SphereSet


def _finite_rows(group: str, what: str, values, width: int, n: int | None = None):
    """``values`` as an (n, width) float64 array (one row broadcast to n), or a
    SceneError naming ``group`` and ``what`` for a wrong shape or a value that is not
    finite."""
    try:
        a = np.atleast_2d(np.asarray(values, dtype=np.float64))
        if n is not None:
            a = np.broadcast_to(a, (n, width))
    except (TypeError, ValueError):
        raise SceneError(f"{group}: {what}: expected {width} numbers per body"
                         + ("" if n is None else f" for {n} bodies")) from None
    if a.ndim != 2 or a.shape[1] != width:
        raise SceneError(f"{group}: {what}: expected {width} numbers per body, got shape "
                         f"{a.shape}")
    if not np.isfinite(a).all():
        raise SceneError(f"{group}: {what}: a value that is not finite (NaN or infinity)")
    return np.array(a)


class ModelBuilder:
    """Collects shapes, materials, bodies and colliders, then ``finalize()`` → Model.

    All lengths in metres, in the simulation's world frame.
    contact_layers : keep for contacts only the spheres within this many lattice
        layers of each sphere set's surface (0: all); default CONTACT_LAYERS.
    cache : a spheres.cache.SphereCache that keeps the shapes' inscribed tori
        (spheres.inscribed.wall_tori) beside their sphere sets, or None.
    """

    def __init__(self, diameter: float, gravity=(0.0, 0.0, -9.81),
                 contact_layers: int = CONTACT_LAYERS, cache=None):
        if not (diameter > 0 and math.isfinite(diameter)):
            raise SceneError(f"sphere diameter must be positive and finite, got {diameter!r}")
        if (isinstance(contact_layers, bool) or not isinstance(contact_layers, (int, np.integer))
                or contact_layers < 0):
            raise SceneError(f"contact_layers must be an integer >= 0 (0: every sphere), "
                             f"got {contact_layers!r}")
        self.contact_layers = int(contact_layers)
        self.cache = cache
        self.diameter = float(diameter)
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self._shapes: list[ShapeInstance] = []
        self._materials: list[mat.Material] = [mat.DEFAULT_MATERIAL]
        self._groups: list[dict] = []
        self._walls: list[tuple] = []
        self._planes: list[tuple] = []
        self._boxes: list[BoxCollider] = []
        self._static: list[tuple] = []
        self._moving: list[tuple] = []      # (kind, index, motion, origin, rotation, walls)

    # -- inputs ---------------------------------------------------------------
    def add_material(self, material: mat.Material) -> int:
        """Register ``material`` (a dempipe.sim.materials.Material); returns its index
        for add_bodies and the colliders. A material of a name already given replaces
        it (index 0 is "default", what a collider without a material takes)."""
        for i, m in enumerate(self._materials):
            if m.name == material.name:
                self._materials[i] = material
                return i
        self._materials.append(material)
        return len(self._materials) - 1

    def _contact_centers(self, sphere_set) -> np.ndarray:
        c = np.asarray(sphere_set.centers, dtype=np.float64).reshape(-1, 3)
        if self.contact_layers == 0:
            return frozen(c)
        return frozen(c[surface_mask(c, self.diameter, self.contact_layers)])

    def add_shape(self, name: str, mesh, sphere_set: "SphereSet", inside_faces=None) -> int:
        """Register a shape: its mesh (mesh coordinates) and its full sphere set;
        the contact spheres are chosen by the builder's ``contact_layers``.
        ``inside_faces``: (F,) bool, the faces of a fracture piece's broken surface."""
        com = np.asarray(sphere_set.com, dtype=np.float64)
        verts = np.asarray(mesh.vertices, dtype=np.float64) - com
        inside = None if inside_faces is None else frozen(
            np.flatnonzero(np.asarray(inside_faces, bool)), np.int32)
        centers = self._contact_centers(sphere_set)
        inscribed = wall_tori(centers, self.diameter, verts, mesh.faces,
                              surface="surface" in getattr(sphere_set, "notes", ()),
                              cache=self.cache)
        if inscribed.shape[0]:
            # the spheres walls meet first, then those they never meet, each part in the
            # set's order: a body's slots follow its spheres' order, so the spheres a
            # resting face's wall contacts visit at every step lie together in memory
            first = np.argsort(inscribed[:, COVERED], kind="stable")
            centers, inscribed = frozen(centers[first]), inscribed[first]
        inscribed = frozen(inscribed) if (not all_own(inscribed, self.diameter)
                                          or np.any(inscribed[:, COVERED] != 0.0)) else None
        self._shapes.append(ShapeInstance(name, frozen(verts), frozen(mesh.faces, np.int32),
                                          frozen(com), sphere_set, centers, inside,
                                          inscribed))
        return len(self._shapes) - 1

    def add_bodies(self, group: str, shape, material: int, positions, rotations=None,
                   velocities=None, angular_velocities=None, *, masses=None, inertias=None,
                   asleep=None, kinematic: bool = False, motion=None, start_time: float = 0.0,
                   group_frame: bool = False, frame=None, labels=None, glue=None) -> None:
        """Add a group of bodies.

        shape : a shape index for all, or one per body (a mixed group)
        positions : (n, 3) where each body's *mesh origin* goes [m] (as a DCC places it)
        rotations : (n, 4) unit quaternions (w, x, y, z); identity if None
        velocities, angular_velocities : (n, 3) [m/s], [rad/s], world frame
        masses : (n,) [kg] given masses, or None: material density × shape volume
        inertias : (n, 3, 3) [kg m²] given inertias about the centre of mass in the
            body frame, or None: the shape's, scaled to the mass
        asleep : (n,) bool, bodies that start asleep (None: all awake)
        kinematic : the bodies follow ``motion`` (a dempipe.sim.motion.Motion) and are
            never pushed (1/m = 0); ``group_frame``: its keys move the group rigidly
            (motion.reference_anchor's ``group``), else each body's mesh origin;
            ``frame`` = (origin (3,) [m], rotation (4,)): the frame the motion moves
            (scene.group_frame: its rates' default pivot; default the first body's
            pose, or for a group frame the mean of its mesh origins)
        start_time : the bodies enter the simulation at this time [s] (an emitter), one
            for all or (n,) one per body
        labels : (n,) str, each body's name after the group's in the USD (default
            its index in the group; a fracture piece "3_piece_07")
        glue : (n,) int, each body's glue id (-1: none; default none): bodies with the
            same id, of any group, are bonded where their spheres touch (sim/glue.py;
            their material needs a glue_strength)
        """
        if kinematic and motion is None:
            raise SceneError(f"{group}: a kinematic group needs a motion")
        p = _finite_rows(group, "positions", positions, 3)
        n = p.shape[0]
        q = np.tile([1.0, 0, 0, 0], (n, 1)) if rotations is None else _finite_rows(
            group, "rotations", rotations, 4, n)
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        if not (norm > 0.0).all():
            raise SceneError(f"{group}: rotations: a quaternion (w, x, y, z) of length 0")
        q = q / norm
        v = np.zeros((n, 3)) if velocities is None else _finite_rows(
            group, "velocities", velocities, 3, n)
        w = np.zeros((n, 3)) if angular_velocities is None else _finite_rows(
            group, "angular_velocities", angular_velocities, 3, n)
        shapes = np.broadcast_to(np.asarray(shape, dtype=np.int64), (n,)).copy()
        if shapes.size and not ((shapes >= 0) & (shapes < len(self._shapes))).all():
            raise SceneError(f"{group}: shape index out of range (add_shape has given "
                             f"0..{len(self._shapes) - 1})")
        if not 0 <= int(material) < len(self._materials):
            raise SceneError(f"{group}: material index {material!r} out of range "
                             f"(add_material has given 0..{len(self._materials) - 1})")
        self._groups.append(dict(
            name=group, shapes=shapes, material=material, p=p, q=q, v=np.array(v),
            w=np.array(w), asleep=np.zeros(n, bool) if asleep is None else np.array(asleep, bool),
            masses=None if masses is None else np.array(masses, dtype=np.float64).reshape(n),
            inertias=None if inertias is None else np.array(inertias, np.float64).reshape(n, 3, 3),
            kinematic=bool(kinematic), motion=motion,
            start_time=np.broadcast_to(np.asarray(start_time, dtype=np.float64), (n,)).copy(),
            group_frame=bool(group_frame), frame=frame,
            labels=tuple(str(i) for i in range(n)) if labels is None else tuple(map(str, labels)),
            glue=(np.full(n, -1, np.int64) if glue is None
                  else np.broadcast_to(np.asarray(glue, np.int64), (n,)).copy())))

    def add_plane(self, point, normal, material: int = 0, motion=None) -> None:
        """An infinite plane through ``point`` [m] facing ``normal`` (any length but 0);
        ``motion`` (a dempipe.sim.motion.Motion) moves it (a belt: a velocity along
        itself)."""
        n = _finite_rows("plane", "normal", normal, 3, 1)[0]
        if not np.linalg.norm(n) > 0.0:
            raise SceneError(f"plane: normal {tuple(normal)!r} has length 0")
        n = n / np.linalg.norm(n)
        p = _finite_rows("plane", "point", point, 3, 1)[0]
        self._planes.append((p, n))
        depth = PLANE_DEPTH_DIAMETERS * self.diameter
        self._walls.append((n, float(n @ p), np.full(3, -np.inf), np.full(3, np.inf), depth,
                            material))
        if motion is not None:
            self._moving.append(("plane", len(self._planes) - 1, motion, p,
                                 np.array([1.0, 0.0, 0.0, 0.0]), [len(self._walls) - 1]))

    def add_box(self, lo, hi, open_top: bool = True, material: int = 0,
                thickness: float | None = None, up: int = 2, motion=None) -> None:
        """Axis-aligned container with inward walls; ``up`` is the up axis index;
        ``motion`` (a dempipe.sim.motion.Motion) moves it, its frame at the box's centre."""
        first_wall = len(self._walls)
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        t = float(thickness) if thickness else PLANE_DEPTH_DIAMETERS * self.diameter
        self._boxes.append(BoxCollider(frozen(lo), frozen(hi), open_top, t, material))
        r = 0.5 * self.diameter
        for axis in range(3):
            for sign in (+1.0, -1.0):
                if axis == up and sign < 0 and open_top:
                    continue  # no lid
                n = np.zeros(3)
                n[axis] = sign                      # inward: +x on the lo side, -x on hi
                surface = lo[axis] if sign > 0 else hi[axis]
                wlo = lo - r
                whi = hi + r
                wlo[axis] = -np.inf
                whi[axis] = np.inf
                if axis != up:                       # side walls reach up over an open top
                    whi[up] = np.inf if open_top else whi[up]
                self._walls.append((n, sign * surface, wlo, whi, t, material))
        if motion is not None:
            self._moving.append(("box", len(self._boxes) - 1, motion, 0.5 * (lo + hi),
                                 np.array([1.0, 0.0, 0.0, 0.0]),
                                 list(range(first_wall, len(self._walls)))))

    def add_static_mesh(self, name: str, mesh, sphere_set: "SphereSet", material: int = 0,
                        motion=None, frame=None) -> None:
        """A static mesh collider given in world coordinates, with its sphere set
        (its buried spheres are left out like a shape's, by ``contact_layers``).
        ``motion`` (a dempipe.sim.motion.Motion) moves it; ``frame`` = (origin (3,),
        rotation (4,)): its authored mesh origin [m], the frame keys are poses of."""
        self._static.append((name, mesh, sphere_set, material,
                             self._contact_centers(sphere_set)))
        if motion is not None:
            o, r = frame if frame is not None else ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
            self._moving.append(("mesh", len(self._static) - 1, motion,
                                 np.asarray(o, dtype=np.float64),
                                 np.asarray(r, dtype=np.float64), []))

    # -- derived --------------------------------------------------------------
    def finalize(self, *, fps: float = 24.0, n_frames: int = 97, first_frame: int = 0,
                 dt: float | str = "auto", target_overlap: float = 0.02,
                 steps_per_contact: float | None = None,
                 up_axis: str = "Z", meters_per_unit: float = 1.0,
                 where: str = "simulation.dt", force: bool = False,
                 sleep: tuple | None = None, contact_law: str = laws.DEFAULT) -> Model:
        """Derive contact constants, dt and features; freeze everything into a Model.

        fps : output frames per second (> 0); n_frames : frames to output, frame 0 (the
        start) included, so 11 frames at 10 fps are 1 s; first_frame : the number of
        frame 0 in the USD's time codes. dt : "auto" or the step [s].
        target_overlap : the overlap [fraction of the sphere diameter] "auto" stiffness
        gives the hardest expected impact. up_axis, meters_per_unit : the USD stage's
        (the gravity is the builder's own, in metres: give it along the up axis).
        A user dt at or above the critical step of the stiffest contact raises
        StabilityError, unless ``force`` (the bake's --force: the user takes the risk).
        sleep : None (off) or (linear [m/s] | None, angular [rad/s] | None,
                time [s] | None); None entries take the defaults of ``sleep_defaults``.
        contact_law : the registered law (``laws.LAWS``) every contact follows.
        steps_per_contact : dt="auto"'s steps per contact (None: the law's
        STEPS_PER_CONTACT).
        """
        if not (isinstance(fps, (int, float, np.number)) and math.isfinite(fps) and fps > 0):
            raise SceneError(f"fps: {fps!r} must be a finite number of frames per second > 0")
        if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) \
                or n_frames < 1:
            raise SceneError(f"n_frames: {n_frames!r} must be a whole number >= 1 (frame 0 "
                             f"counts: 11 frames at 10 fps are 1 s)")
        if up_axis not in ("Y", "Z"):
            raise SceneError(f"up_axis: {up_axis!r} must be \"Y\" or \"Z\"")
        g = self.gravity
        if float(np.linalg.norm(g)) > 0.0 and not g[1 if up_axis == "Y" else 2] < -0.5 * float(
                np.linalg.norm(g)):
            warnings.warn(f"gravity {tuple(float(x) for x in g)} does not point down the "
                          f"stage's up axis {up_axis}: bodies will fall sideways in a DCC "
                          f"(give ModelBuilder gravity along -{up_axis})", stacklevel=2)
        if contact_law not in laws.LAWS:
            raise SceneError(f"contact_law: unknown law {contact_law!r} "
                             f"(known: {', '.join(laws.LAWS)})")
        law_name = contact_law
        law = laws.law(law_name)
        if steps_per_contact is None:
            steps_per_contact = law.STEPS_PER_CONTACT
        d = self.diameter
        groups = self._groups
        # bodies
        body_shape, body_group, body_gidx, body_mat, xs, qs, vs, ws = [], [], [], [], [], [], [], []
        for gi, g in enumerate(groups):
            n = g["p"].shape[0]
            com = np.array([self._shapes[s].com for s in g["shapes"]]).reshape(n, 3)
            body_shape.append(g["shapes"])
            body_group.append(np.full(n, gi))
            body_gidx.append(np.arange(n))
            body_mat.append(np.full(n, g["material"]))
            # position places the mesh origin: the centre of mass is at p + R com
            R = np.stack([quat_to_matrix(q) for q in g["q"]]) if n else np.zeros((0, 3, 3))
            xs.append(g["p"] + np.einsum("nij,nj->ni", R, com))
            qs.append(g["q"])
            vs.append(g["v"])
            ws.append(g["w"])
        n_dyn = int(sum(len(a) for a in body_shape))
        cat = lambda parts, shape: np.concatenate(parts) if parts else np.zeros(shape)
        body_shape = cat(body_shape, (0,)).astype(np.int32)
        body_group = cat(body_group, (0,)).astype(np.int32)
        body_gidx = cat(body_gidx, (0,)).astype(np.int32)
        dyn_mat = cat(body_mat, (0,)).astype(np.int32)
        x0 = cat(xs, (0, 3))
        q0 = cat(qs, (0, 4))
        v0 = cat(vs, (0, 3))
        w0 = cat(ws, (0, 3))

        mass = np.zeros(n_dyn)
        inv_inertia = np.zeros((n_dyn, 6))
        shape_inv = []
        shape_rot = []
        for s in self._shapes:
            ss = s.sphere_set
            inv = np.linalg.inv(np.asarray(ss.inertia, dtype=np.float64))  # per unit density
            shape_inv.append(np.array([inv[0, 0], inv[1, 1], inv[2, 2], inv[0, 1], inv[0, 2],
                                       inv[1, 2]]))
            # per unit mass: I/m = inertia/volume. This, body_radius and the flat-face
            # count are decided by outermost spheres, which are always contact
            # spheres: full set and contact set give the same values
            shape_rot.append(rotational_mass_factor(np.asarray(ss.centers),
                                                    np.asarray(ss.inertia) / ss.volume))
        for b in range(n_dyn):
            s = self._shapes[body_shape[b]]
            rho = self._materials[dyn_mat[b]].density
            mass[b] = rho * s.sphere_set.volume
            inv_inertia[b] = shape_inv[body_shape[b]] / rho
        # given masses and inertias (UsdPhysics MassAPI): a given mass alone scales the
        # shape's inertia (its density becomes mass / volume)
        b0 = 0
        given_inertia = {}      # body -> inertia per unit mass, for its rotational mode
        for g in groups:
            n = g["p"].shape[0]
            for k in range(n):
                b = b0 + k
                if g["masses"] is not None:
                    m_b = float(g["masses"][k])
                    if not (m_b > 0 and math.isfinite(m_b)):
                        raise SceneError(f"{g['name']}: mass must be positive, got {m_b!r}")
                    inv_inertia[b] *= mass[b] / m_b
                    mass[b] = m_b
                if g["inertias"] is not None:
                    inv = np.linalg.inv(g["inertias"][k])
                    inv_inertia[b] = [inv[0, 0], inv[1, 1], inv[2, 2], inv[0, 1], inv[0, 2],
                                      inv[1, 2]]
                    given_inertia[b] = g["inertias"][k] / mass[b]
            b0 += n
        asleep0 = (np.concatenate([g["asleep"] for g in groups]) if groups
                   else np.zeros(0, bool))

        # static pseudo-bodies
        static_meshes = []
        st_x, st_mat = [], []
        for k, (name, mesh, ss, m, _) in enumerate(self._static):
            st_x.append(np.asarray(ss.com, dtype=np.float64))
            st_mat.append(m)
            static_meshes.append(StaticMesh(name, frozen(mesh.vertices), frozen(mesh.faces,
                                            np.int32), n_dyn + k, tuple(ss.notes)))
        n_static = len(static_meshes)
        kin = (np.concatenate([np.full(g["p"].shape[0], g["kinematic"]) for g in groups])
               if groups else np.zeros(0, bool))
        inv_inertia[kin] = 0.0      # carried by their motion: never pushed
        all_x = np.concatenate([x0, np.array(st_x).reshape(-1, 3)])
        all_q = np.concatenate([q0, np.tile([1.0, 0, 0, 0], (n_static, 1))])
        all_mass = np.concatenate([mass, np.full(n_static, np.inf)])
        all_inv_mass = np.concatenate([np.where(kin, 0.0, 1.0 / np.where(mass > 0, mass, np.inf)),
                                       np.zeros(n_static)])
        all_inv_inertia = np.concatenate([inv_inertia, np.zeros((n_static, 6))])
        all_mat = np.concatenate([dyn_mat, np.array(st_mat, dtype=np.int32)]).astype(np.int32)

        # contact spheres (the surface layers of each set), contiguous per body
        offsets = [self._shapes[s].contact_centers for s in body_shape]
        offsets += [c for (_, _, _, _, c) in self._static]
        counts = [c.shape[0] for c in offsets]
        start = np.zeros(len(counts) + 1, dtype=np.int32)
        start[1:] = np.cumsum(counts) if counts else []
        sphere_offset = np.concatenate(offsets) if offsets else np.zeros((0, 3))
        # each contact sphere's inscribed torus (no rows at all where every set is a lattice)
        if any(self._shapes[s].inscribed is not None for s in set(body_shape.tolist())):
            own = np.zeros(COLUMNS)
            own[10] = 0.5 * d
            sphere_inscribed = np.concatenate(
                [self._shapes[s].inscribed if self._shapes[s].inscribed is not None
                 else np.tile(own, (self._shapes[s].contact_count, 1)) for s in body_shape]
                + [np.tile(own, (c.shape[0], 1)) for (_, _, _, _, c) in self._static])
        else:
            sphere_inscribed = np.zeros((0, COLUMNS))
        sphere_body = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
        body_radius = np.array([np.linalg.norm(self._shapes[s].sphere_set.centers, axis=1).max()
                                + 0.5 * d for s in body_shape]) if n_dyn else np.zeros(0)

        driven = self._prescribed(groups, x0, q0, all_x, all_q, body_radius, n_dyn, n_static,
                                  fps, n_frames)
        surface_speed = driven["surface_speed"]

        # materials: auto stiffness from impact speed and weight (the law's
        # stiffness_for_overlap)
        g = float(np.linalg.norm(self.gravity))
        up = -self.gravity / g if g > 0 else np.array([0.0, 0.0, 1.0])
        falls = ~kin                    # kinematic bodies do not fall: their motion is given
        heights = x0[falls] @ up if falls.any() else np.zeros(1)
        floors = [heights.min() - (body_radius[falls].max() if falls.any() else 0.0)]
        floors += [float(p @ up) for (p, n) in self._planes if n @ up > 0.5]  # ground-like
        floors += [float(b.lo @ up) for b in self._boxes]
        floors += [float((np.asarray(mesh.vertices) @ up).min()) for (_, mesh, _, _, _) in self._static]
        floor = min(floors)
        launch = np.linalg.norm(v0, axis=1) + np.linalg.norm(w0, axis=1) * body_radius
        if falls.any():
            fall = np.sqrt(2.0 * g * np.maximum(heights - floor, 0.0))
            # the fastest body meets a static wall, or a partner launched towards it
            v_imp = float((fall + launch[falls]).max() + launch.max())
        else:
            v_imp = 0.0
        v_imp += surface_speed      # a moving surface meets a falling body head on
        # scenes at rest still feel their weight settling one sphere deep
        v_imp = max(v_imp, math.sqrt(2.0 * g * d) if g > 0 else 0.01)
        # corner-contact effective mass m / (1 + m (r×n)ᵀ I⁻¹ (r×n)): a falling body
        # first touches with one outer sphere; a flat landing shares the load
        body_rot = np.array([shape_rot[s] for s in body_shape]) if n_dyn else np.zeros(0)
        for b, i_per_m in given_inertia.items():
            body_rot[b] = rotational_mass_factor(
                np.asarray(self._shapes[body_shape[b]].sphere_set.centers), i_per_m)
        m_corner = mass / (1.0 + body_rot) if n_dyn else mass
        # what the overlap target is a fraction of: a contact is one patch whatever the
        # number of its spheres, so its stiffness follows the bodies' size, not d
        patch = mat.patch_scale(d, [float(np.ptp(self._shapes[s].vertices, axis=0).max())
                                    for s in np.unique(body_shape[~kin])] if n_dyn else [])
        stiffness = []
        auto_notes = []
        k_auto_all = 0.0
        for mi, m in enumerate(self._materials):
            used = (dyn_mat == mi) & ~kin       # kinematic bodies: carried, infinite mass
            if not (m.rolling_friction >= 0 and math.isfinite(m.rolling_friction)):
                raise SceneError(f"materials.{m.name}: rolling_friction must be a number >= 0, "
                                 f"got {m.rolling_friction!r}")
            if m.young_modulus is not None:
                if not (m.young_modulus > 0 and math.isfinite(m.young_modulus)) \
                        or m.stiffness is not None or not 0 <= m.poisson_ratio < 0.5:
                    raise SceneError(f"materials.{m.name}: young_modulus must be a positive "
                                     f"number in Pa, poisson_ratio in [0, 0.5), and stiffness "
                                     f"not given with them")
                if not hasattr(law, "stiffness_from_modulus"):
                    raise SceneError(f"materials.{m.name}.young_modulus: applies to the Hertz "
                                     f"law only (contact_law is {law_name!r}; give stiffness)")
                # equal spheres of diameter d (R* = d/4); a sphere on a wall (R* = d/2)
                # would be √2 stiffer: walls take the pair's K
                stiffness.append(law.stiffness_from_modulus(m.young_modulus, m.poisson_ratio, d))
            elif m.stiffness is None and used.any():
                k = law.stiffness_for_overlap(float(m_corner[used].max()), v_imp, g, patch,
                                              target_overlap)
                k_auto_all = max(k_auto_all, k)
                stiffness.append(k)
                auto_notes.append((m.name, k))
            else:
                stiffness.append(m.stiffness)
        # materials used only by colliders (or unused) take the stiffest auto value
        fallback = k_auto_all or max([s for s in stiffness if s] or [1e4])
        stiffness = [s if s is not None else fallback for s in stiffness]
        table = mat.pair_table(self._materials, stiffness, law)

        # stiffest mode: ω = √(k / m_eff) over every body, translation and rotation
        # (effective mass m / (1 + m (r×n)ᵀ I⁻¹ (r×n))), halved for body-body contacts
        wall_mats = {w[5] for w in self._walls} | {s[3] for s in self._static}
        present = set(np.unique(dyn_mat).tolist()) | wall_mats
        contacts = [(table.k[a, b], m_rot, table.zeta[a, b]) for (_, a, b), (_, m_rot)
                    in mat.contact_masses(dyn_mat, mass, m_corner, ~kin, wall_mats).items()]
        omega_max, zeta_min, zeta_max = laws.stiffest(contacts, law_name, v_imp)
        body_glue = (np.concatenate([g["glue"] for g in groups]) if groups
                     else np.zeros(0, np.int64))
        bonds = self._bonds(body_glue, all_x, all_q, sphere_offset, sphere_body, all_inv_mass,
                            mass, body_rot, all_mat, table, law, v_imp)
        # each bond's stiffest mode, on the corner masses as a contact's (glue.py: by
        # default no stiffer than a contact between the two pieces)
        corner = np.concatenate([np.where(kin, np.inf, mass / (1.0 + body_rot)),
                                 np.full(n_static, np.inf)])
        omega_max = max(omega_max, glue.bond_omega(bonds, corner))
        # free spin and fast surfaces bound dt further (a face landing flat is one
        # contact patch, kernels/patches.py: no stiffer than a corner)
        dt_max = math.inf
        if n_dyn and np.any(w0):
            dt_max = min(dt_max, mat.MAX_SPIN_STEP / float(np.linalg.norm(w0, axis=1).max()))
        if surface_speed > 0.0:
            # a moving surface's fastest point crosses at most AUTO_TRAVEL d per step
            dt_max = min(dt_max, mat.AUTO_TRAVEL * d / surface_speed)
        if n_dyn and float(launch.max()) > 0.0:
            # a launched or spinning body's fastest point (|v| + |w| r) crosses at most
            # AUTO_TRAVEL of a diameter per step, in free flight too (the travel guard)
            dt_max = min(dt_max, mat.AUTO_TRAVEL * d / float(launch.max()))

        def auto_step():
            return mat.auto_dt(omega_max, fps, steps_per_contact, law.duration_zeta(zeta_max),
                               dt_max)

        if isinstance(dt, str):
            if dt != "auto":
                raise SceneError(f"{where}: expected \"auto\" or seconds, got {dt!r}")
            dt_v, spf = auto_step()
        else:
            if not (dt > 0 and math.isfinite(dt)):
                raise SceneError(f"{where}: dt must be positive seconds, got {dt!r}")
            if not force:
                try:        # the refusal advises the auto step, as `dempipe check` does
                    auto = auto_step()
                except StabilityError:
                    auto = None
                mat.check_dt(float(dt), omega_max, zeta_min, where, law, auto)
            spf = max(1, round((1.0 / fps) / dt))
            dt_v = 1.0 / fps / spf
            if abs(dt_v - dt) > 1e-9 * dt and abs(dt_v - dt) / dt > 0.01:
                raise StabilityError(
                    f"{where}: dt = {dt:g} s does not divide a frame (1/{fps:g} s) into whole "
                    f"steps; use {dt_v:.6g} s ({spf} steps per frame)")

        # the bonds' dashpots are explicit: a body's, summed over its bonds, times dt
        # stays below its corner mass; where it would not, its bonds are damped less
        # (glue.cap_dashpots) rather than the step shortened
        bonds = glue.cap_dashpots(bonds, corner, float(dt_v))
        walls = driven["walls"]
        wall_arr = lambda i, shape: (np.array([w[i] for w in walls], dtype=np.float64)
                                     if walls else np.zeros(shape))
        friction = bool((table.mu > 0).any()) and bool(np.any(
            [table.mu[a, b] > 0 for a in present for b in present]))
        multi = any(s.sphere_set.centers.shape[0] > 1 for s in self._shapes)
        features = Features(
            friction=friction,
            rotation=multi or friction or bool(np.any(w0)) or bool(driven["motions"]),
            walls=bool(walls),
            static_spheres=n_static > 0,
            gravity=g > 0,
        )
        sleep_steps, sleep_lin, sleep_ang = 0, 0.0, 0.0
        if sleep is not None and n_dyn > 0:
            sleep_lin, sleep_ang, sleep_time = sleep_defaults(
                d, g, body_radius, *sleep)
            sleep_steps = max(1, math.ceil(sleep_time / float(dt_v) - 1e-9))
        features = replace(features, sleeping=sleep_steps > 0, rolling=(
            features.friction and features.rotation
            and bool(np.any([table.mu_r[a, b] > 0 for a in present for b in present]))))
        # rolling resistance (physics.rolling_torque): each body's rolling radius
        moves = np.concatenate([~np.asarray(kin, bool), np.zeros(n_static, bool)])
        inv_radius = np.zeros(n_dyn + n_static)
        inv_radius[:n_dyn][moves[:n_dyn]] = 1.0 / body_radius[moves[:n_dyn]]
        return Model(
            diameter=d, sleep_steps=int(sleep_steps), sleep_linear=float(sleep_lin),
            sleep_angular=float(sleep_ang), n_bodies=n_dyn, n_static=n_static, shapes=tuple(self._shapes),
            materials=tuple(self._materials), group_names=tuple(g["name"] for g in groups),
            body_mass=frozen(all_mass), body_inv_mass=frozen(all_inv_mass),
            body_inv_inertia=frozen(all_inv_inertia), body_material=frozen(all_mat, np.int32),
            body_sphere_start=frozen(start, np.int32), body_shape=frozen(body_shape, np.int32),
            body_group=frozen(body_group, np.int32), body_group_index=frozen(body_gidx, np.int32),
            body_labels=tuple(lab for g in groups for lab in g["labels"]),
            body_radius=frozen(body_radius), body_corner_mass=frozen(m_corner),
            sphere_body=frozen(sphere_body, np.int32), sphere_offset=frozen(sphere_offset),
            sphere_inscribed=frozen(sphere_inscribed),
            wall_normal=frozen(wall_arr(0, (0, 3)).reshape(-1, 3)),
            wall_offset=frozen(wall_arr(1, (0,))),
            wall_lo=frozen(wall_arr(2, (0, 3)).reshape(-1, 3)),
            wall_hi=frozen(wall_arr(3, (0, 3)).reshape(-1, 3)),
            wall_depth=frozen(wall_arr(4, (0,))),
            wall_material=frozen(np.array([w[5] for w in walls], dtype=np.int32), np.int32),
            plane_point=frozen(np.array([p for p, _ in self._planes]).reshape(-1, 3)),
            plane_normal=frozen(np.array([n for _, n in self._planes]).reshape(-1, 3)),
            boxes=tuple(self._boxes), static_meshes=tuple(static_meshes),
            pair_k=frozen(table.k), pair_zeta=frozen(table.zeta),
            pair_damp=frozen(law.damping_table(table.zeta)), pair_mu=frozen(table.mu),
            kt_ratio=table.kt_ratio, ks_ratio=table.ks_ratio, gravity=frozen(self.gravity), dt=float(dt_v),
            steps_per_frame=int(spf), fps=float(fps), n_frames=int(n_frames),
            first_frame=int(first_frame), up_axis=up_axis, meters_per_unit=float(meters_per_unit),
            omega_max=float(omega_max), features=features,
            initial_x=frozen(all_x), initial_q=frozen(all_q),
            initial_v=frozen(np.concatenate([v0, np.zeros((n_static, 3))])),
            initial_w=frozen(np.concatenate([w0, np.zeros((n_static, 3))])),
            stiffness_auto=tuple(auto_notes), contact_layers=self.contact_layers,
            initial_asleep=frozen(asleep0, bool) if asleep0.any() else None,
            contact_law=law_name, impact_speed=float(v_imp), patch_scale=float(patch),
            motions=driven["motions"], motion_table=driven["table"],
            body_motion=frozen(driven["body_motion"], np.int32),
            body_anchor_c=frozen(driven["anchor_c"]), body_anchor_q=frozen(driven["anchor_q"]),
            driven_body=frozen(np.flatnonzero(driven["body_motion"] >= 0), np.int32),
            wall_motion=frozen(driven["wall_motion"], np.int32),
            body_start=frozen(np.concatenate([
                np.ceil(driven["start_time"] / float(dt_v) - 1e-9).astype(np.int64),
                np.zeros(n_static, np.int64)]), np.int64),
            body_start_time=frozen(driven["start_time"]),
            body_kinematic=frozen(kin, bool),
            collider_motions=tuple(driven["colliders"]), surface_speed=float(surface_speed),
            pair_rolling=frozen(table.mu_r), body_inv_radius=frozen(inv_radius),
            bonds=bonds if bonds.n_bonds else None,
            body_glue=frozen(body_glue, np.int32),
        )

    def _bonds(self, body_glue, all_x, all_q, sphere_offset, sphere_body, inv_mass, mass,
               body_rot, body_mat, table, law, v_imp) -> glue.Bonds:
        """The glue bonds (sim/glue.py) between bodies of equal glue id, their springs
        and strengths from the bodies' materials."""
        n_all = all_x.shape[0]
        if not (body_glue >= 0).any():
            return glue.no_bonds(n_all)
        d = self.diameter
        for gdict in self._groups:
            m = self._materials[gdict["material"]]
            if (gdict["glue"] >= 0).any() and m.glue_strength is None:
                raise SceneError(f"materials.{m.name}.glue_strength: bodies '{gdict['name']}' "
                                 f"are glued but their material has no glue strength (add "
                                 f"glue_strength in Pa, or remove glue)")
            if (gdict["glue"] >= 0).any() and not (
                    m.glue_strength > 0 and math.isfinite(m.glue_strength)
                    and (m.glue_stiffness is None
                         or (m.glue_stiffness > 0 and math.isfinite(m.glue_stiffness)))
                    and m.glue_damping >= 0 and math.isfinite(m.glue_damping)):
                raise SceneError(f"materials.{m.name}: glue_strength [Pa] and glue_stiffness "
                                 f"[N/m] must be positive numbers, glue_damping a number >= 0")
        glue_all = np.concatenate([body_glue, np.full(n_all - body_glue.shape[0], -1)])
        R = np.stack([quat_to_matrix(q) for q in all_q])
        world = all_x[sphere_body] + np.einsum("sij,sj->si", R[sphere_body], sphere_offset)
        i, j, dist = glue.find_pairs(world, sphere_body, glue_all, d)
        mats = self._materials

        def m_red(a, b):
            inv = inv_mass[a] + inv_mass[b]
            return 1.0 / inv if inv > 0 else math.inf

        def stiffness(a, b):
            ma, mb = mats[body_mat[a]], mats[body_mat[b]]
            given = [m.glue_stiffness for m in (ma, mb) if m.glue_stiffness is not None]
            if given:
                return float(min(given))
            m = m_red(a, b)
            if not math.isfinite(m):
                return 0.0          # two carried pieces: nothing to hold
            return m * law.omega(table.k[body_mat[a], body_mat[b]], m, v_imp) ** 2

        def damping(a, b, K):
            zeta = min(mats[body_mat[a]].glue_damping, mats[body_mat[b]].glue_damping)
            return glue.bond_damping(K, m_red(a, b), zeta)

        def limit(a, b):
            return min(mats[body_mat[a]].glue_strength, mats[body_mat[b]].glue_strength) * d * d

        return glue.build_bonds(i, j, dist, sphere_body, n_all, stiffness, damping, limit)

    def _prescribed(self, groups, x0, q0, all_x, all_q, body_radius, n_dyn, n_static, fps,
                    n_frames) -> dict:
        """The motions of kinematic groups and moving colliders, each body's and
        wall's place in its motion's anchor frame, the start times, and the fastest
        prescribed surface speed over the bake [m/s]."""
        B = n_dyn + n_static
        motions, colliders = [], []
        body_motion = np.full(B, -1, dtype=np.int32)
        anchor_c = np.zeros((B, 3))
        anchor_q = np.tile([1.0, 0.0, 0.0, 0.0], (B, 1))
        walls = [list(w) for w in self._walls]
        wall_motion = np.full(len(walls), -1, dtype=np.int32)
        start_time = np.zeros(n_dyn)
        t_end = (n_frames - 1) / fps
        speed = 0.0
        # where contacts can happen: the bodies' reach from their initial places
        pts = [x0] if n_dyn else []
        pts += [np.asarray(m.vertices, dtype=np.float64) for (_, m, _, _, _) in self._static]
        reach = np.concatenate(pts) if pts else np.zeros((1, 3))
        r_body = float(body_radius.max()) if n_dyn else 0.0

        b0 = 0
        for g in groups:
            n = g["p"].shape[0]
            start_time[b0:b0 + n] = g["start_time"]
            if g["kinematic"]:
                m = g["motion"]
                frame = g["frame"]
                if frame is None:
                    frame = ((g["p"].mean(axis=0), (1.0, 0.0, 0.0, 0.0)) if g["group_frame"]
                             else (g["p"][0], g["q"][0]))
                ref = mo.reference_anchor(m, frame[0], frame[1], group=g["group_frame"])
                m = m.with_pivot(ref[0])
                c, a = mo.relative_pose(ref[0], ref[1], x0[b0:b0 + n], q0[b0:b0 + n])
                body_motion[b0:b0 + n] = len(motions)
                anchor_c[b0:b0 + n] = c
                anchor_q[b0:b0 + n] = a
                motions.append(m)
                # each body's centre, out by its radius along the way from the anchor
                dist = np.linalg.norm(c, axis=1, keepdims=True)
                pts = c * (1.0 + body_radius[b0:b0 + n, None] / np.maximum(dist, 1e-300))
                speed = max(speed, m.max_speed(pts, 0.0, t_end))
            b0 += n
        for kind, index, m, origin, rotation, wall_ids in self._moving:
            ref = mo.reference_anchor(m, origin, rotation)
            m = m.with_pivot(ref[0])
            k = len(motions)
            motions.append(m)
            colliders.append(ColliderMotion(kind, index, m, frozen(ref[0]), frozen(ref[1]),
                                            frozen(origin), frozen(rotation)))
            # the farthest point of it a body can touch, from its anchor: a mesh's or a
            # box's own extent; anywhere a body may be on a plane
            if kind == "mesh":
                body = n_dyn + index
                c, a = mo.relative_pose(ref[0], ref[1], all_x[body], all_q[body])
                body_motion[body] = k
                anchor_c[body] = c[0]
                anchor_q[body] = a[0]
                pts = np.asarray(self._static[index][1].vertices, dtype=np.float64)
            elif kind == "box":
                bx = self._boxes[index]
                pts = np.array([[(bx.lo, bx.hi)[i >> j & 1][j] for j in range(3)]
                                for i in range(8)])
            else:                       # a plane: wherever a body may meet it
                pts = reach + r_body * (reach - ref[0]) / np.maximum(
                    np.linalg.norm(reach - ref[0], axis=1, keepdims=True), 1e-300)
            # in the anchor frame (ref_q is the identity for planes and boxes)
            pts, _ = mo.relative_pose(ref[0], ref[1], pts, np.tile([1.0, 0, 0, 0], (len(pts), 1)))
            # the walls in the anchor frame (ref_q is the identity for planes and boxes)
            for w in wall_ids:
                n_w, off, lo, hi, depth, mat_w = walls[w]
                walls[w] = [n_w, off - float(n_w @ ref[0]), lo - ref[0], hi - ref[0], depth,
                            mat_w]
                wall_motion[w] = k
            speed = max(speed, m.max_speed(pts, 0.0, t_end))
        return dict(motions=tuple(motions), table=mo.pack(motions), body_motion=body_motion,
                    anchor_c=anchor_c, anchor_q=anchor_q, wall_motion=wall_motion,
                    walls=[tuple(w) for w in walls], colliders=colliders,
                    start_time=start_time, surface_speed=float(speed))
