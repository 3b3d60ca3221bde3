"""Model: what a scene IS, as frozen arrays the kernels read.

Build one with :class:`ModelBuilder` (builder.py: shapes, materials, bodies,
colliders, then ``finalize()``), or from a scene file with :func:`build_model`. A Model never
changes during a bake; where things are lives in :class:`dempipe.sim.state.State`.

Body indexing: dynamic bodies 0..n_bodies-1 in scene order, then one static
pseudo-body per static mesh collider (zero inverse mass and inertia) whose
spheres sit in the grid like any other but are never integrated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from dempipe.sim import laws
from dempipe.sim.materials import contact_possible
from dempipe.sim.state import State

if TYPE_CHECKING:  # spheres imports numba; the model only needs the type
    from dempipe.spheres.sphere_set import SphereSet

#: Planes are half-spaces: a sphere up to this many diameters *behind* a plane is
#: still pushed out; deeper than that it is taken to be elsewhere (the far side of
#: an incline's infinite extension) and ignored.
PLANE_DEPTH_DIAMETERS = 2.0

#: Default of ModelBuilder's and the scene's ``contact_layers``: spheres more than
#: this many lattice layers inside a body are left out of the contact stages. With
#: 1, contacts are those of the full set while every sphere-sphere overlap stays
#: below (1 - √2/2) d ≈ 0.29 d (auto stiffness aims at 2-5%); docs/spheres.md.
CONTACT_LAYERS = 1


def frozen(a, dtype=np.float64):
    a = np.ascontiguousarray(a, dtype=dtype)
    a.flags.writeable = False
    return a


@dataclass(frozen=True)
class ShapeInstance:
    """A shape used by bodies: its mesh in the body frame and its sphere set.

    vertices : (V, 3) mesh vertices minus the centre of mass, mesh axes [m]
    faces : (F, 3) int triangle indices
    com : (3,) centre of mass in the mesh's own coordinates [m]
    sphere_set : the full sphere set (its geometry error, counts and small-body
        checks describe the shape); mass properties are the mesh's
    inside_faces : indices of the faces on a fracture piece's broken surface (int32),
        or None for a whole shape (dempipe.mesh.fracture)
    contact_centers : (K, 3) body-frame centres of the spheres that take part in
        contacts [m]: the full set's within ``contact_layers`` layers of its
        surface (spheres.surface_mask), in the set's order; all of them when
        contact_layers is 0. These become the Model's sphere_offset.
    inscribed : (K, spheres.inscribed.COLUMNS) per contact sphere, what it meets walls
        through (spheres.inscribed.wall_tori: a surface set's shell tori, or a lattice's
        from its mesh; a ball or a ring, body frame [m], and its reach); None where
        every sphere is its own (a lattice set with no curved part a fit follows).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    com: np.ndarray
    sphere_set: "SphereSet"
    contact_centers: np.ndarray = None
    inside_faces: np.ndarray = None
    inscribed: np.ndarray = None

    @property
    def contact_count(self) -> int:
        """Number of contact spheres (K)."""
        return int(np.shape(self.contact_centers)[0])


@dataclass(frozen=True)
class BoxCollider:
    """Axis-aligned container: inward-facing walls (and floor) from ``lo`` to ``hi`` [m]."""

    lo: np.ndarray
    hi: np.ndarray
    open_top: bool = True
    thickness: float = 0.0
    material: int = 0


@dataclass(frozen=True)
class StaticMesh:
    """A static mesh collider, in world coordinates [m], voxelized into static spheres.

    notes : its sphere set's notes (SphereSet.notes: "not_watertight", ...), which
        `dempipe check` reports; the set itself is not kept.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    body: int  # its pseudo-body index
    notes: tuple = ()


@dataclass(frozen=True)
class ColliderMotion:
    """A moving collider, for the exporter: at time t its prim moves by
    T(t) T_authored⁻¹, T(t) = motion.carry(motion, (ref_p, ref_q), origin, rotation, t)."""

    kind: str               # "plane", "box" or "mesh"
    index: int              # row of plane_point, index into boxes or static_meshes
    motion: Any             # dempipe.sim.motion.Motion
    ref_p: np.ndarray       # (3,) the anchor at which the collider stands as authored [m]
    ref_q: np.ndarray       # (4,)
    origin: np.ndarray      # (3,) the authored frame: mesh origin, plane point, box centre [m]
    rotation: np.ndarray    # (4,)


@dataclass(frozen=True)
class Features:
    """What the scene uses; the kernels skip what it does not."""

    friction: bool
    rotation: bool
    walls: bool
    static_spheres: bool
    gravity: bool
    sleeping: bool = False
    rolling: bool = False
    """Rolling resistance (a pair with μ_r > 0, with friction and rotation)."""


@dataclass(frozen=True, eq=False)
class Model:
    """Frozen description of a scene.

    Per body (dynamic first, then static pseudo-bodies; B = n_bodies + n_static):
      body_mass (B,) [kg]; body_inv_mass (B,) [1/kg] (0 for static);
      body_inv_inertia (B, 6) inverse inertia about the centre of mass in the body
        frame, entries (xx, yy, zz, xy, xz, yz) [1/(kg m²)];
      body_material (B,) int32; body_sphere_start (B+1,) int32, spheres of body b
        are body_sphere_start[b]:body_sphere_start[b+1].
    Per dynamic body (n_bodies,): body_shape, body_group, body_group_index;
      body_corner_mass [kg], m / (1 + f), f = rotational_mass_factor (its given
      inertia where one was given): the least effective mass a contact at one of its
      spheres sees, which auto stiffness and the stiffest contact
      (materials.contact_masses) take and `dempipe check` restates;
      body_labels, each body's name after its group's (its index, or for a fracture
      piece "3_piece_07"; empty: indices).
    Per sphere (S,): sphere_body int32; sphere_offset (S, 3) from the body's centre
      of mass, body frame [m]; sphere_inscribed (S, COLUMNS) each sphere's inscribed
      torus for wall contacts (ShapeInstance.inscribed, spheres.inscribed), or
      (0, COLUMNS) when every sphere is its own (no shape has tori).
    Walls (planes and box walls) as bounded half-spaces (W,): wall_normal (W, 3)
      unit, pointing into the free side; wall_offset (W,) [m], n·x = offset on the
      surface; wall_lo, wall_hi (W, 3) box the sphere centre must be in [m];
      wall_depth (W,) [m] how far behind the surface a sphere still touches it;
      wall_material (W,).
    Materials: pair_k, pair_zeta, pair_mu (M, M); kt_ratio; ks_ratio; pair_damp
      (M, M, laws.linear.DAMP_TERMS): the law's step-sized dashpot (damping_table).
    Time: dt [s], steps_per_frame, fps, n_frames, first_frame.
    Sleeping: a body slower than sleep_linear [m/s] and sleep_angular [rad/s] for
      sleep_steps steps in a row sleeps (0: sleeping off); see kernels.cpu.stages.stage_bodies.
    contact_layers: the spheres of each body (and static mesh) are those within this
      many lattice layers of its sphere set's surface (0: every sphere); mass and
      inertia never depend on it. See ShapeInstance.contact_centers.
    """

    diameter: float
    n_bodies: int
    n_static: int
    shapes: tuple
    materials: tuple
    group_names: tuple
    body_mass: np.ndarray
    body_inv_mass: np.ndarray
    body_inv_inertia: np.ndarray
    body_material: np.ndarray
    body_sphere_start: np.ndarray
    body_shape: np.ndarray
    body_group: np.ndarray
    body_group_index: np.ndarray
    body_radius: np.ndarray
    body_corner_mass: np.ndarray
    sphere_body: np.ndarray
    sphere_offset: np.ndarray
    sphere_inscribed: np.ndarray
    wall_normal: np.ndarray
    wall_offset: np.ndarray
    wall_lo: np.ndarray
    wall_hi: np.ndarray
    wall_depth: np.ndarray
    wall_material: np.ndarray
    plane_point: np.ndarray
    plane_normal: np.ndarray
    boxes: tuple
    static_meshes: tuple
    pair_k: np.ndarray
    pair_zeta: np.ndarray
    pair_damp: np.ndarray
    pair_mu: np.ndarray
    kt_ratio: float
    ks_ratio: float
    gravity: np.ndarray
    dt: float
    steps_per_frame: int
    fps: float
    n_frames: int
    first_frame: int
    up_axis: str
    meters_per_unit: float
    omega_max: float
    features: Features
    initial_x: np.ndarray
    initial_q: np.ndarray
    initial_v: np.ndarray
    initial_w: np.ndarray
    stiffness_auto: tuple = ()
    build_info: dict = field(default_factory=dict)
    body_labels: tuple = ()
    sleep_steps: int = 0
    sleep_linear: float = 0.0
    sleep_angular: float = 0.0
    contact_layers: int = 0
    initial_asleep: np.ndarray = None
    """(n_bodies,) bool, bodies that start asleep (None: none)."""
    contact_law: str = laws.DEFAULT
    motions: tuple = ()
    """Prescribed motions (dempipe.sim.motion.Motion), indexed by body_motion and wall_motion."""
    motion_table: Any = None
    """The motions packed for the kernels (motion.MotionTable; one dummy row when none)."""
    body_motion: np.ndarray = None
    """(B,) int32: the motion carrying each body (kinematic bodies, moving mesh
    colliders), -1 for none."""
    body_anchor_c: np.ndarray = None
    """(B, 3) [m], (B, 4): each carried body's centre of mass and orientation in its
    motion's anchor frame (motion.carried_state)."""
    body_anchor_q: np.ndarray = None
    driven_body: np.ndarray = None
    """(K,) int32: the bodies with a motion, in body order."""
    wall_motion: np.ndarray = None
    """(W,) int32: the motion carrying each wall, -1 for a static one; a moving wall's
    normal, offset and box are given in its anchor frame."""
    body_start: np.ndarray = None
    """(B,) int64: the step a body enters the simulation at (emitters; 0: from the
    start). Before it, it is not simulated and nothing touches it."""
    body_start_time: np.ndarray = None
    """(n_bodies,) float64 [s]: the same as a time (hidden before it in the output)."""
    body_kinematic: np.ndarray = None
    """(n_bodies,) bool: kinematic bodies (1/m = 0, carried by a motion)."""
    collider_motions: tuple = ()
    """ColliderMotion of each moving collider (the exporter animates them)."""
    surface_speed: float = 0.0
    """Fastest speed of a prescribed surface over the bake [m/s] (auto stiffness, dt
    and the tunnelling check count it as an impact speed)."""
    impact_speed: float = 1.0
    """The fastest impact the scene can produce [m/s] (auto stiffness; the Hertz
    law's contact frequency depends on it)."""
    patch_scale: float = 0.0
    """The length ℓ [m] the auto stiffness's overlap target is a fraction of
    (materials.patch_scale: the smallest dynamic shape's extent / 4, within [d, 5 d];
    d in a Model without dynamic bodies)."""
    pair_rolling: np.ndarray = None
    """(M, M): each material pair's rolling-friction coefficient μ_r [1]
    (materials.mix_rolling; physics.rolling_torque)."""
    body_inv_radius: np.ndarray = None
    """(B,) [1/m]: 1 / each dynamic body's radius (its rolling radius; the pair's is
    1 / (1/R_i + 1/R_j)); 0 for static and kinematic bodies, which roll as a wall."""
    bonds: Any = None
    """The glue between fractured pieces (sim.glue.Bonds), None without glue."""
    body_glue: np.ndarray = None
    """(n_bodies,) int32: each body's glue id (-1: not glued); bodies with the same id
    are bonded where their spheres touch (sim.glue)."""

    @property
    def n_bonds(self) -> int:
        """Glue bonds (body pairs) of the scene."""
        return 0 if self.bonds is None else self.bonds.n_bonds

    @property
    def onset_speed(self) -> float:
        """The speed [m/s] below which a contact that begins or ends is a resting one:
        the law resolves the onset and end of faster ones within the step
        (laws.ONSET_SPEED_FRACTION of impact_speed; laws.linear.normal_force)."""
        return laws.ONSET_SPEED_FRACTION * self.impact_speed

    @property
    def n_spheres(self) -> int:
        return int(self.sphere_body.shape[0])

    @property
    def body_static(self) -> np.ndarray:
        """(B,) bool: the bodies the body stage leaves alone (static mesh colliders;
        kinematic bodies, moved by Control, will be too). Their 1/m is 0, an infinite
        mass to every contact: the kernels ask physics.static_body, the same test."""
        return np.asarray(self.body_inv_mass) == 0.0

    @property
    def n_walls(self) -> int:
        return int(self.wall_normal.shape[0])

    @property
    def contact_possible(self) -> bool:
        """Whether any contact can happen (materials.contact_possible): False where dt
        "auto" is the free-flight step and the travel guards do not apply."""
        return contact_possible(self.omega_max)

    @property
    def contact_time(self) -> float:
        """Duration of the stiffest contact [s] (inf when nothing can touch)."""
        return math.pi / self.omega_max if self.omega_max > 0 else math.inf

    def body_name(self, b: int) -> str:
        """'group[index]' of a dynamic body, or the static mesh collider's name."""
        if b >= self.n_bodies:
            return self.static_meshes[b - self.n_bodies].name
        return f"{self.group_names[self.body_group[b]]}[{self.body_group_index[b]}]"

    def initial_state(self) -> State:
        """State at frame 0: positions, orientations, momenta from the initial velocities."""
        nb = self.body_mass.shape[0]
        x = np.array(self.initial_x, dtype=np.float64)
        q = np.array(self.initial_q, dtype=np.float64)
        P = np.zeros((nb, 3))      # static pseudo-bodies (infinite mass) carry none
        P[:self.n_bodies] = self.body_mass[:self.n_bodies, None] * self.initial_v[:self.n_bodies]
        L = np.zeros((nb, 3))
        for b in range(self.n_bodies):
            L[b] = world_inertia(q[b], self.body_inv_inertia[b]) @ self.initial_w[b]
        state = State(body_x=x, body_q=q, body_P=P, body_L=L)
        state.ensure_rest(nb)
        if self.initial_asleep is not None and self.sleep_steps > 0:
            state.body_rest[:self.n_bodies][self.initial_asleep] = self.sleep_steps
        if self.features.friction:
            state.ensure_contacts(self.n_spheres)
        if self.n_bonds:
            state.bond_broken = np.zeros(self.bonds.n_bonds, dtype=np.int32)
            state.bond_shear = np.zeros((self.bonds.n_pairs, 3))
        return state


#: Defaults of sleeping: a body sleeps after SLEEP_TIME seconds slower than
#: SLEEP_SPEED_FACTOR √(g d) (about 1.6 cm/s at d = 1 cm: a hundredth of the
#: speed of a fall from one diameter is well below anything a viewer sees at
#: 24 fps) and spinning slower than that speed over the body's median radius.
SLEEP_SPEED_FACTOR = 0.05
SLEEP_TIME = 0.5


def sleep_defaults(diameter, g, body_radius, linear=None, angular=None, time=None):
    """(linear [m/s], angular [rad/s], time [s]) thresholds of sleeping, with the
    defaults above for the ones given as None."""
    if linear is None:
        linear = SLEEP_SPEED_FACTOR * math.sqrt(max(g, 1.0) * diameter)
    if angular is None:
        r = float(np.median(body_radius)) if len(body_radius) else diameter
        angular = linear / max(r, 0.5 * diameter)
    return float(linear), float(angular), float(SLEEP_TIME if time is None else time)


def sym6_to_mat(s):
    """The symmetric 3x3 matrix of its 6 entries (xx, yy, zz, xy, xz, yz)."""
    return np.array([[s[0], s[3], s[4]], [s[3], s[1], s[5]], [s[4], s[5], s[2]]])


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix of the unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def world_inertia(q, inv_inertia6):
    """World-frame inertia tensor R I0 Rᵀ from the body-frame inverse (6 entries)."""
    inv = sym6_to_mat(inv_inertia6)
    if not inv.any():
        return np.zeros((3, 3))
    R = quat_to_matrix(q)
    return R @ np.linalg.inv(inv) @ R.T


def rotational_mass_factor(offsets: np.ndarray, inertia: np.ndarray) -> float:
    """max over spheres and normal directions of (r×n)ᵀ I⁻¹ (r×n), per unit mass⁻¹.

    With ``inertia`` per unit mass, a contact at offset r with normal n sees the
    effective mass 1 / (1/m + (r×n)ᵀ I⁻¹ (r×n)) = m / (1 + this). The rotational
    mode of a light, long body is stiffer than its translation; dt="auto" uses it.
    """
    if offsets.shape[0] <= 1:
        return 0.0
    inv = np.linalg.inv(inertia)
    rx, ry, rz = offsets[:, 0], offsets[:, 1], offsets[:, 2]
    z = np.zeros_like(rx)
    S = np.stack([np.stack([z, -rz, ry], -1), np.stack([rz, z, -rx], -1),
                  np.stack([-ry, rx, z], -1)], -2)           # [r]x per sphere
    M = np.einsum("sji,jk,skl->sil", S, inv, S)               # [r]xᵀ I⁻¹ [r]x
    return float(np.linalg.eigvalsh(M)[:, -1].max())

