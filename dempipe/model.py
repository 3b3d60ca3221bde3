"""Model: what a scene IS, as frozen arrays the kernels read.

Build one with :class:`ModelBuilder` (shapes, materials, bodies, colliders, then
``finalize()``), or from a scene file with :func:`build_model`. A Model never
changes during a bake; where things are lives in :class:`dempipe.state.State`.

Body indexing: dynamic bodies 0..n_bodies-1 in scene order, then one static
pseudo-body per static mesh collider (zero inverse mass and inertia) whose
spheres sit in the grid like any other but are never integrated.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import replace, dataclass, field

import numpy as np

from . import laws
from . import materials as mat
from typing import TYPE_CHECKING, Any

from .errors import SceneError, StabilityError
from .state import State

if TYPE_CHECKING:  # spheres imports numba; the model only needs the type
    from .spheres import SphereSet

#: Planes are half-spaces: a sphere up to this many diameters *behind* a plane is
#: still pushed out; deeper than that it is taken to be elsewhere (the far side of
#: an incline's infinite extension) and ignored.
PLANE_DEPTH_DIAMETERS = 2.0

#: Default of ModelBuilder's and the scene's ``contact_layers``: spheres more than
#: this many lattice layers inside a body are left out of the contact stages. With
#: 1, contacts are those of the full set while every sphere-sphere overlap stays
#: below (1 - √2/2) d ≈ 0.29 d (auto stiffness aims at 2-5%); docs/spheres.md.
CONTACT_LAYERS = 1


def _frozen(a, dtype=np.float64):
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
    contact_centers : (K, 3) body-frame centres of the spheres that take part in
        contacts [m]: the full set's within ``contact_layers`` layers of its
        surface (spheres.surface_mask), in the set's order; all of them when
        contact_layers is 0. These become the Model's sphere_offset.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    com: np.ndarray
    sphere_set: "SphereSet"
    contact_centers: np.ndarray = None

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
    """A static mesh collider, in world coordinates [m], voxelized into static spheres."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    body: int  # its pseudo-body index


@dataclass(frozen=True)
class ColliderMotion:
    """A moving collider, for the exporter: at time t its prim moves by
    T(t) T_authored⁻¹, T(t) = motion.carry(motion, (ref_p, ref_q), origin, rotation, t)."""

    kind: str               # "plane", "box" or "mesh"
    index: int              # row of plane_point, index into boxes or static_meshes
    motion: Any             # dempipe.motion.Motion
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
    Per dynamic body (n_bodies,): body_shape, body_group, body_group_index.
    Per sphere (S,): sphere_body int32; sphere_offset (S, 3) from the body's centre
      of mass, body frame [m].
    Walls (planes and box walls) as bounded half-spaces (W,): wall_normal (W, 3)
      unit, pointing into the free side; wall_offset (W,) [m], n·x = offset on the
      surface; wall_lo, wall_hi (W, 3) box the sphere centre must be in [m];
      wall_depth (W,) [m] how far behind the surface a sphere still touches it;
      wall_material (W,).
    Materials: pair_k, pair_zeta, pair_mu (M, M); kt_ratio; ks_ratio; pair_damp
      (M, M, laws.linear.DAMP_TERMS): the law's step-sized dashpot (damping_table).
    Time: dt [s], steps_per_frame, fps, n_frames, first_frame.
    Sleeping: a body slower than sleep_linear [m/s] and sleep_angular [rad/s] for
      sleep_steps steps in a row sleeps (0: sleeping off); see kernels.cpu.stage_bodies.
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
    sphere_body: np.ndarray
    sphere_offset: np.ndarray
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
    sleep_steps: int = 0
    sleep_linear: float = 0.0
    sleep_angular: float = 0.0
    contact_layers: int = 0
    initial_asleep: np.ndarray = None
    """(n_bodies,) bool, bodies that start asleep (None: none)."""
    contact_law: str = laws.DEFAULT
    motions: tuple = ()
    """Prescribed motions (dempipe.motion.Motion), indexed by body_motion and wall_motion."""
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
    pair_rolling: np.ndarray = None
    """(M, M): each material pair's rolling-friction coefficient μ_r [1]
    (materials.mix_rolling; physics.rolling_torque)."""
    body_inv_radius: np.ndarray = None
    """(B,) [1/m]: 1 / each dynamic body's radius (its rolling radius; the pair's is
    1 / (1/R_i + 1/R_j)); 0 for static and kinematic bodies, which roll as a wall."""
    body_roll_gain: np.ndarray = None
    """(B,) [1/(kg m²)]: the spheres of the body's set × the largest eigenvalue of its
    inverse inertia; 0 for static and kinematic bodies. Bounds what the rolling
    torques of all its contacts can change its spin by in a step (the cap of
    physics.rolling_torque)."""

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
            L[b] = _world_inertia(q[b], self.body_inv_inertia[b]) @ self.initial_w[b]
        state = State(body_x=x, body_q=q, body_P=P, body_L=L)
        state.ensure_rest(nb)
        if self.initial_asleep is not None and self.sleep_steps > 0:
            state.body_rest[:self.n_bodies][self.initial_asleep] = self.sleep_steps
        if self.features.friction:
            state.ensure_contacts(self.n_spheres)
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


#: Widest band [fraction of d] below a set's extreme plane counted as one face: a
#: lattice's next layer of centres is a whole d behind its face, so any band below d
#: counts a lattice face exactly; 0.25 d is also the count without a landing.
FLAT_FACE_BAND = 0.25
#: A surface set's flat face: its centres lie on the offset plane within
#: surface_spheres._DEPTH_TOL r; heights below this fraction of d count as on it.
FLAT_FACE_TOL = 1e-3

_FLAT_FACE_MEMO: dict = {}


def flat_face_spheres(centers: np.ndarray, diameter: float, k: float | None = None,
                      mass: float = 0.0, speed: float = 0.0, g: float = 0.0) -> int:
    """Most spheres of a sphere set that a plane presses at once when the body lands
    or rests on it: the n of the flat-face critical step (n contacts in parallel).

    A body lands on a plane with a face of the convex hull of its centres (a vertex
    or an edge being a face of fewer), so the planes tried are the hull's facets and
    the six axis planes. Without ``k``: the centres within FLAT_FACE_BAND d of each
    plane. With the contact stiffness ``k`` [N/m], the body's ``mass`` [kg], its
    landing ``speed`` [m/s] and gravity ``g`` [m/s²] along the normal: the centres
    that the deepest landing on that plane presses, where the springs (the linear
    law's, each k (δ − h_i) for a centre h_i above the deepest point) have taken
    the kinetic energy and the weight's work,

        Σ_{h_i < δ} ½ k (δ − h_i)² = ½ m v² + m g δ,

    solved exactly piece by piece over the sorted heights (damping only makes the
    landing shallower; centres more than FLAT_FACE_BAND d above the plane are not
    counted, a landing that deep being past the overlap limits). On a face, every
    centre at h = 0, that is the whole face (a lattice's count is the same as
    without ``k``: its next layer is d away). On a curved part only the cap within δ
    presses: the surface ball of 8 spheres across counts 5 of its 916 spheres (a
    landing pressed 1), not the 35 within 0.25 d (docs/spheres.md, "The flat-face
    step of a surface set"). The linear law's springs; results are memoized.
    """
    c = np.ascontiguousarray(centers, dtype=np.float64)
    if c.shape[0] == 0:
        return 0
    load = None
    if k is not None and k > 0 and mass > 0 and math.isfinite(k):
        load = (mass * speed * speed / k, mass * max(g, 0.0) / k)
    shape_key = (hashlib.sha1(c.tobytes()).hexdigest(), c.shape[0], float(diameter))
    hit = _FLAT_FACE_MEMO.get(shape_key + (load,))
    if hit is not None:
        return hit
    heights = _FLAT_FACE_MEMO.get(shape_key)
    if heights is None:
        band = FLAT_FACE_BAND * diameter
        heights = []        # per plane: the heights above it of the centres within the band
        for a in range(3):
            x = c[:, a]
            for h in (x - x.min(), x.max() - x):
                heights.append(np.sort(h[h < band]))
        heights += _hull_heights(c, band)
        heights = _padded(heights)
    best = int(_pressed(heights, load, diameter).max())
    if len(_FLAT_FACE_MEMO) > 256:
        _FLAT_FACE_MEMO.clear()
    _FLAT_FACE_MEMO[shape_key] = heights
    _FLAT_FACE_MEMO[shape_key + (load,)] = best
    return best


def _padded(heights: list) -> np.ndarray:
    """Sorted heights (1-D arrays: one plane; 2-D: a plane per row, padded with +inf)
    as the rows of one array, padded with +inf."""
    rows = [np.atleast_2d(h) for h in heights]
    n = max(1, max(r.shape[1] for r in rows))
    out = np.full((sum(r.shape[0] for r in rows), n), np.inf)
    i = 0
    for r in rows:
        out[i:i + r.shape[0], :r.shape[1]] = r
        i += r.shape[0]
    return out


def _pressed(h: np.ndarray, load, diameter: float) -> np.ndarray:
    """Per row of sorted heights ``h`` [m] (padded with +inf; one row may be given as
    a 1-D array), how many of them a landing of ``load`` = (m v²/k, m g/k) presses
    (flat_face_spheres); all of them without a load, at least one."""
    h = np.atleast_2d(np.asarray(h, dtype=np.float64))
    n_row = np.count_nonzero(np.isfinite(h), axis=1)
    if load is None or h.shape[1] <= 1:
        return np.maximum(n_row, 1)
    h = np.maximum(h - FLAT_FACE_TOL * diameter, 0.0)
    e2, w = load
    j = np.arange(1, h.shape[1] + 1, dtype=np.float64)
    fin = np.where(np.isfinite(h), h, 0.0)
    s1 = np.cumsum(fin, axis=1) + w
    s2 = np.cumsum(fin * fin, axis=1)
    # j δ² − 2 δ (S1 + w) + S2 − m v²/k = 0 with the j lowest centres pressed
    disc = np.maximum(s1 * s1 - j * (s2 - e2), 0.0)
    delta = (s1 + np.sqrt(disc)) / j
    nxt = np.concatenate([h[:, 1:], np.full((h.shape[0], 1), np.inf)], axis=1)
    stop = delta <= nxt                 # the first j whose δ stays below the next centre
    first = np.argmax(stop, axis=1) + 1
    return np.maximum(np.minimum(first, n_row), 1)


def _hull_heights(c: np.ndarray, band: float) -> list:
    """Per distinct facet plane of the centres' convex hull, the sorted heights of
    the centres within ``band`` of it: 2-D arrays, a plane per row padded with +inf
    (one plane through all of them when the set is flat, which has no hull)."""
    from scipy.spatial import ConvexHull, QhullError

    if c.shape[0] < 4:
        return []
    try:
        eq = ConvexHull(c).equations
    except (QhullError, ValueError):
        x = c - c.mean(axis=0)
        normal = np.linalg.svd(x, full_matrices=False)[2][-1]
        off = x @ normal
        h = off - off.min()
        return [np.sort(h[h < band])]
    # coplanar triangles of one facet share their plane: each plane once
    eq = np.unique(np.round(eq, 9), axis=0)
    out = []
    for i in range(0, eq.shape[0], 512):
        e = eq[i:i + 512]
        # a plane per row: every centre's height above it, >= 0 inside the hull
        dist = -(e[:, :3] @ c.T + e[:, 3:4])
        dist[dist >= band] = np.inf
        k = max(1, int(np.count_nonzero(np.isfinite(dist), axis=1).max()))
        if k < dist.shape[1]:
            dist = np.partition(dist, k - 1, axis=1)[:, :k]
        out.append(np.sort(dist, axis=1))
    return out


def _sym6_to_mat(s):
    return np.array([[s[0], s[3], s[4]], [s[3], s[1], s[5]], [s[4], s[5], s[2]]])


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix of the unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _world_inertia(q, inv_inertia6):
    """World-frame inertia tensor R I0 Rᵀ from the body-frame inverse (6 entries)."""
    inv = _sym6_to_mat(inv_inertia6)
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


class ModelBuilder:
    """Collects shapes, materials, bodies and colliders, then ``finalize()`` → Model.

    All lengths in metres, in the simulation's world frame.
    contact_layers : keep for contacts only the spheres within this many lattice
        layers of each sphere set's surface (0: all); default CONTACT_LAYERS.
    """

    def __init__(self, diameter: float, gravity=(0.0, 0.0, -9.81),
                 contact_layers: int = CONTACT_LAYERS):
        if not (diameter > 0 and math.isfinite(diameter)):
            raise SceneError(f"sphere diameter must be positive and finite, got {diameter!r}")
        if (isinstance(contact_layers, bool) or not isinstance(contact_layers, (int, np.integer))
                or contact_layers < 0):
            raise SceneError(f"contact_layers must be an integer >= 0 (0: every sphere), "
                             f"got {contact_layers!r}")
        self.contact_layers = int(contact_layers)
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
        for i, m in enumerate(self._materials):
            if m.name == material.name:
                self._materials[i] = material
                return i
        self._materials.append(material)
        return len(self._materials) - 1

    def _contact_centers(self, sphere_set) -> np.ndarray:
        from .spheres import surface_mask

        c = np.asarray(sphere_set.centers, dtype=np.float64).reshape(-1, 3)
        if self.contact_layers == 0:
            return _frozen(c)
        return _frozen(c[surface_mask(c, self.diameter, self.contact_layers)])

    def add_shape(self, name: str, mesh, sphere_set: "SphereSet") -> int:
        """Register a shape: its mesh (mesh coordinates) and its full sphere set;
        the contact spheres are chosen by the builder's ``contact_layers``."""
        com = np.asarray(sphere_set.com, dtype=np.float64)
        verts = np.asarray(mesh.vertices, dtype=np.float64) - com
        self._shapes.append(ShapeInstance(name, _frozen(verts), _frozen(mesh.faces, np.int32),
                                          _frozen(com), sphere_set,
                                          self._contact_centers(sphere_set)))
        return len(self._shapes) - 1

    def add_bodies(self, group: str, shape, material: int, positions, rotations=None,
                   velocities=None, angular_velocities=None, *, masses=None, inertias=None,
                   asleep=None, kinematic: bool = False, motion=None, start_time: float = 0.0,
                   group_frame: bool = False, frame=None) -> None:
        """Add a group of bodies.

        shape : a shape index for all, or one per body (a mixed group)
        positions : (n, 3) where each body's *mesh origin* goes [m] (as a DCC places it)
        rotations : (n, 4) unit quaternions (w, x, y, z); identity if None
        velocities, angular_velocities : (n, 3) [m/s], [rad/s], world frame
        masses : (n,) [kg] given masses, or None: material density × shape volume
        inertias : (n, 3, 3) [kg m²] given inertias about the centre of mass in the
            body frame, or None: the shape's, scaled to the mass
        asleep : (n,) bool, bodies that start asleep (None: all awake)
        kinematic : the bodies follow ``motion`` (a dempipe.motion.Motion) and are
            never pushed (1/m = 0); ``group_frame``: its keys move the group rigidly
            (motion.reference_anchor's ``group``), else each body's mesh origin;
            ``frame`` = (origin (3,) [m], rotation (4,)): the frame the motion moves
            (scene.group_frame: its rates' default pivot; default the first body's
            pose, or for a group frame the mean of its mesh origins)
        start_time : the bodies enter the simulation at this time [s] (an emitter), one
            for all or (n,) one per body
        """
        if kinematic and motion is None:
            raise SceneError(f"{group}: a kinematic group needs a motion")
        p = np.atleast_2d(np.asarray(positions, dtype=np.float64))
        n = p.shape[0]
        q = np.tile([1.0, 0, 0, 0], (n, 1)) if rotations is None else np.atleast_2d(
            np.asarray(rotations, dtype=np.float64))
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        v = np.zeros((n, 3)) if velocities is None else np.broadcast_to(
            np.asarray(velocities, dtype=np.float64), (n, 3))
        w = np.zeros((n, 3)) if angular_velocities is None else np.broadcast_to(
            np.asarray(angular_velocities, dtype=np.float64), (n, 3))
        shapes = np.broadcast_to(np.asarray(shape, dtype=np.int64), (n,)).copy()
        self._groups.append(dict(
            name=group, shapes=shapes, material=material, p=p, q=q, v=np.array(v),
            w=np.array(w), asleep=np.zeros(n, bool) if asleep is None else np.array(asleep, bool),
            masses=None if masses is None else np.array(masses, dtype=np.float64).reshape(n),
            inertias=None if inertias is None else np.array(inertias, np.float64).reshape(n, 3, 3),
            kinematic=bool(kinematic), motion=motion,
            start_time=np.broadcast_to(np.asarray(start_time, dtype=np.float64), (n,)).copy(),
            group_frame=bool(group_frame), frame=frame))

    def add_plane(self, point, normal, material: int = 0, motion=None) -> None:
        """An infinite plane through ``point`` facing ``normal``; ``motion`` (a
        dempipe.motion.Motion) moves it (a belt: a velocity along itself)."""
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        p = np.asarray(point, dtype=np.float64)
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
        ``motion`` (a dempipe.motion.Motion) moves it, its frame at the box's centre."""
        first_wall = len(self._walls)
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        t = float(thickness) if thickness else PLANE_DEPTH_DIAMETERS * self.diameter
        self._boxes.append(BoxCollider(_frozen(lo), _frozen(hi), open_top, t, material))
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
        ``motion`` (a dempipe.motion.Motion) moves it; ``frame`` = (origin (3,),
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

        A user dt at or above the critical step of the stiffest contact raises
        StabilityError, unless ``force`` (the bake's --force: the user takes the risk).
        sleep : None (off) or (linear [m/s] | None, angular [rad/s] | None,
                time [s] | None); None entries take the defaults of ``sleep_defaults``.
        contact_law : the registered law (``laws.LAWS``) every contact follows.
        steps_per_contact : dt="auto"'s steps per contact (None: the law's
        STEPS_PER_CONTACT).
        """
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
            static_meshes.append(StaticMesh(name, _frozen(mesh.vertices), _frozen(mesh.faces,
                                            np.int32), n_dyn + k))
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
                k = law.stiffness_for_overlap(float(m_corner[used].max()), v_imp, g, d,
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
        contacts = []       # (k, m_eff, ζ) of each kind of contact (laws.stiffest)
        wall_mats = {w[5] for w in self._walls} | {s[3] for s in self._static}
        present = set(np.unique(dyn_mat).tolist()) | wall_mats
        has_contacts = n_dyn > 1 or bool(self._walls) or bool(self._static)
        if has_contacts:
            for gi, gdict in enumerate(groups):
                if gdict["p"].shape[0] == 0 or gdict["kinematic"]:
                    continue
                mi = gdict["material"]
                in_group = body_group == gi
                m_eff = float((mass[in_group] / (1.0 + body_rot[in_group])).min())
                partners = present if n_dyn > 1 else wall_mats
                dyn_present = set(np.unique(dyn_mat).tolist())
                for mj in partners:
                    k = table.k[mi, mj]
                    half = 0.5 if (n_dyn > 1 and mj in dyn_present) else 1.0
                    contacts.append((k, m_eff * half, table.zeta[mi, mj]))
        omega_max, zeta_min, zeta_max = laws.stiffest(contacts, law_name, v_imp)
        # flat landings (n spheres of a face at once) and free spin bound dt further
        dt_max = math.inf
        flat_crit = math.inf        # the same without the safety: a user dt's limit
        if has_contacts:
            dyn_present = set(np.unique(dyn_mat).tolist())
            for gi, gdict in enumerate(groups):
                if gdict["p"].shape[0] == 0 or gdict["kinematic"]:
                    continue
                mi = gdict["material"]
                in_group = body_group == gi
                m_flat = float(mass[in_group].min())
                m_deep = float(mass[in_group].max())    # the heaviest sinks deepest
                for mj in (present if n_dyn > 1 else wall_mats):
                    half = 0.5 if (n_dyn > 1 and mj in dyn_present) else 1.0
                    # the spheres a plane presses at once in the deepest landing
                    n_face = max(flat_face_spheres(
                        np.asarray(self._shapes[sj].sphere_set.centers), d,
                        float(table.k[mi, mj]), m_deep * half, v_imp, g)
                        for sj in np.unique(gdict["shapes"]))
                    flat = mat.flat_face_critical_step(n_face, table.k[mi, mj],
                                                       m_flat * half, table.zeta[mi, mj],
                                                       law, v_imp)
                    flat_crit = min(flat_crit, flat)
                    dt_max = min(dt_max, mat.FLAT_FACE_SAFETY * flat)
        if n_dyn and np.any(w0):
            dt_max = min(dt_max, mat.MAX_SPIN_STEP / float(np.linalg.norm(w0, axis=1).max()))
        if surface_speed > 0.0:
            # a moving surface's fastest point crosses at most AUTO_TRAVEL d per step
            dt_max = min(dt_max, mat.AUTO_TRAVEL * d / surface_speed)
        if n_dyn and float(launch.max()) > 0.0:
            # a launched or spinning body's fastest point (|v| + |w| r) crosses at most
            # AUTO_TRAVEL of a diameter per step, in free flight too (the travel guard)
            dt_max = min(dt_max, mat.AUTO_TRAVEL * d / float(launch.max()))
        if isinstance(dt, str):
            if dt != "auto":
                raise SceneError(f"{where}: expected \"auto\" or seconds, got {dt!r}")
            dt_v, spf = mat.auto_dt(omega_max, fps, steps_per_contact,
                                    law.duration_zeta(zeta_max), dt_max)
        else:
            if not (dt > 0 and math.isfinite(dt)):
                raise SceneError(f"{where}: dt must be positive seconds, got {dt!r}")
            if not force:
                mat.check_dt(float(dt), omega_max, zeta_min, where, law)
                if float(dt) >= flat_crit:
                    raise StabilityError(
                        f"{where}: dt = {dt:.3g} s is above the critical step {flat_crit:.3g} s "
                        f"of a body resting flat on a face of its spheres (its contacts act "
                        f"in parallel); use dt = \"auto\", a dt below {flat_crit / 2:.3g} s, "
                        f"or softer materials")
            spf = max(1, round((1.0 / fps) / dt))
            dt_v = 1.0 / fps / spf
            if abs(dt_v - dt) > 1e-9 * dt and abs(dt_v - dt) / dt > 0.01:
                raise StabilityError(
                    f"{where}: dt = {dt:g} s does not divide a frame (1/{fps:g} s) into whole "
                    f"steps; use {dt_v:.6g} s ({spf} steps per frame)")

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
        # rolling resistance (physics.rolling_torque): each body's rolling radius, and
        # its spheres times the largest eigenvalue of its inverse inertia
        moves = np.concatenate([~np.asarray(kin, bool), np.zeros(n_static, bool)])
        inv_radius = np.zeros(n_dyn + n_static)
        inv_radius[:n_dyn][moves[:n_dyn]] = 1.0 / body_radius[moves[:n_dyn]]
        ii = all_inv_inertia
        full = np.stack([np.stack([ii[:, 0], ii[:, 3], ii[:, 4]], -1),
                         np.stack([ii[:, 3], ii[:, 1], ii[:, 5]], -1),
                         np.stack([ii[:, 4], ii[:, 5], ii[:, 2]], -1)], -2)
        # (every sphere of the set, not the contact ones only: a bound all the same, and
        # the motion then does not depend on contact_layers)
        n_set = np.array([self._shapes[s].sphere_set.centers.shape[0] for s in body_shape]
                         + [0] * n_static, dtype=np.float64)
        roll_gain = np.where(moves, n_set * (np.linalg.eigvalsh(full)[:, -1]
                                                      if len(full) else 0.0), 0.0)
        return Model(
            diameter=d, sleep_steps=int(sleep_steps), sleep_linear=float(sleep_lin),
            sleep_angular=float(sleep_ang), n_bodies=n_dyn, n_static=n_static, shapes=tuple(self._shapes),
            materials=tuple(self._materials), group_names=tuple(g["name"] for g in groups),
            body_mass=_frozen(all_mass), body_inv_mass=_frozen(all_inv_mass),
            body_inv_inertia=_frozen(all_inv_inertia), body_material=_frozen(all_mat, np.int32),
            body_sphere_start=_frozen(start, np.int32), body_shape=_frozen(body_shape, np.int32),
            body_group=_frozen(body_group, np.int32), body_group_index=_frozen(body_gidx, np.int32),
            body_radius=_frozen(body_radius),
            sphere_body=_frozen(sphere_body, np.int32), sphere_offset=_frozen(sphere_offset),
            wall_normal=_frozen(wall_arr(0, (0, 3)).reshape(-1, 3)),
            wall_offset=_frozen(wall_arr(1, (0,))),
            wall_lo=_frozen(wall_arr(2, (0, 3)).reshape(-1, 3)),
            wall_hi=_frozen(wall_arr(3, (0, 3)).reshape(-1, 3)),
            wall_depth=_frozen(wall_arr(4, (0,))),
            wall_material=_frozen(np.array([w[5] for w in walls], dtype=np.int32), np.int32),
            plane_point=_frozen(np.array([p for p, _ in self._planes]).reshape(-1, 3)),
            plane_normal=_frozen(np.array([n for _, n in self._planes]).reshape(-1, 3)),
            boxes=tuple(self._boxes), static_meshes=tuple(static_meshes),
            pair_k=_frozen(table.k), pair_zeta=_frozen(table.zeta),
            pair_damp=_frozen(law.damping_table(table.zeta)), pair_mu=_frozen(table.mu),
            kt_ratio=table.kt_ratio, ks_ratio=table.ks_ratio, gravity=_frozen(self.gravity), dt=float(dt_v),
            steps_per_frame=int(spf), fps=float(fps), n_frames=int(n_frames),
            first_frame=int(first_frame), up_axis=up_axis, meters_per_unit=float(meters_per_unit),
            omega_max=float(omega_max), features=features,
            initial_x=_frozen(all_x), initial_q=_frozen(all_q),
            initial_v=_frozen(np.concatenate([v0, np.zeros((n_static, 3))])),
            initial_w=_frozen(np.concatenate([w0, np.zeros((n_static, 3))])),
            stiffness_auto=tuple(auto_notes), contact_layers=self.contact_layers,
            initial_asleep=_frozen(asleep0, bool) if asleep0.any() else None,
            contact_law=law_name, impact_speed=float(v_imp),
            motions=driven["motions"], motion_table=driven["table"],
            body_motion=_frozen(driven["body_motion"], np.int32),
            body_anchor_c=_frozen(driven["anchor_c"]), body_anchor_q=_frozen(driven["anchor_q"]),
            driven_body=_frozen(np.flatnonzero(driven["body_motion"] >= 0), np.int32),
            wall_motion=_frozen(driven["wall_motion"], np.int32),
            body_start=_frozen(np.concatenate([
                np.ceil(driven["start_time"] / float(dt_v) - 1e-9).astype(np.int64),
                np.zeros(n_static, np.int64)]), np.int64),
            body_start_time=_frozen(driven["start_time"]),
            body_kinematic=_frozen(kin, bool),
            collider_motions=tuple(driven["colliders"]), surface_speed=float(surface_speed),
            pair_rolling=_frozen(table.mu_r), body_inv_radius=_frozen(inv_radius),
            body_roll_gain=_frozen(roll_gain),
        )

    def _prescribed(self, groups, x0, q0, all_x, all_q, body_radius, n_dyn, n_static, fps,
                    n_frames) -> dict:
        """The motions of kinematic groups and moving colliders, each body's and
        wall's place in its motion's anchor frame, the start times, and the fastest
        prescribed surface speed over the bake [m/s]."""
        from . import motion as mo

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
            colliders.append(ColliderMotion(kind, index, m, _frozen(ref[0]), _frozen(ref[1]),
                                            _frozen(origin), _frozen(rotation)))
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
