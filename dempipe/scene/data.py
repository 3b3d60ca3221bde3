"""The scene as data: the frozen records a scene file is read into.

    scene = load_scene("shot.toml")      # scene.py (TOML) or scene/usd_reader.py (USD)
    scene.simulation.dt, scene.materials["steel"].friction, scene.bodies[0].count

One record per table of the format (``docs/scene-format.md``): ``[output]``,
``[simulation]`` (with ``[simulation.sleep]``), ``[materials.NAME]``,
``[shapes.NAME]``, ``[[bodies]]`` and ``[[colliders]]``, and the :class:`Scene`
that holds them. Each field's docstring gives its unit and default. SI units;
positions place the mesh's own origin (not the centre of mass); quaternions are
(w, x, y, z). No numba, no pxr.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

from dempipe.sim import laws
from dempipe.sim.materials import ROLLING_FRICTION, Material

#: Spheres across the longest extent of the smallest shape when neither
#: ``sphere_diameter`` nor ``resolution`` is given.
DEFAULT_RESOLUTION = 12

#: Standard gravity [m/s²].
STANDARD_GRAVITY = 9.81

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


# --------------------------------------------------------------------------- data


@dataclass(frozen=True)
class OutputSettings:
    """``[output]``: timing and coordinate conventions of the baked animation."""

    fps: int = 24
    """Frames per second of the animation [1/s], positive integer."""
    duration: float = 4.0
    """Length of the animation [s], > 0."""
    up_axis: str = "Z"
    """World up axis, "Z" or "Y"."""
    meters_per_unit: float = 1.0
    """USD stage metadata: metres per scene unit [m], > 0. Scene values stay in metres."""
    start_frame: int = 0
    """USD time code of frame 0 [frames]."""

    @property
    def n_frames(self) -> int:
        """Number of output frames including frame 0: round(duration*fps) + 1."""
        return int(round(self.duration * self.fps)) + 1

    @property
    def up_index(self) -> int:
        """Index of the up axis in (x, y, z): 2 for "Z", 1 for "Y"."""
        return 2 if self.up_axis == "Z" else 1


@dataclass(frozen=True)
class SleepSettings:
    """``[simulation.sleep]``: thresholds below which a body is put to sleep.

    ``None`` leaves the choice to the simulator.
    """

    linear_speed: float | None = None
    """Speed below which a body may sleep [m/s], > 0."""
    angular_speed: float | None = None
    """Angular speed below which a body may sleep [rad/s], > 0."""
    time: float | None = None
    """How long a body must stay below both thresholds before it sleeps [s], > 0."""


@dataclass(frozen=True)
class SimulationSettings:
    """``[simulation]``: sphere size, gravity, time step, device, seed."""

    sphere_diameter: float | None = None
    """Diameter of every sphere [m]; None when ``resolution`` sets it."""
    resolution: int | None = DEFAULT_RESOLUTION
    """Spheres across the longest extent of the smallest shape [count]; None when
    ``sphere_diameter`` is given."""
    gravity: Vec3 = (0.0, 0.0, -STANDARD_GRAVITY)
    """Gravitational acceleration, world frame [m/s²]; default -9.81 along the up axis."""
    dt: Union[float, str] = "auto"
    """Time step [s], or "auto" (derived from stiffness and masses)."""
    device: str = "auto"
    """Compute device: "cpu", "cuda" or "auto"."""
    seed: int = 0
    """Seed of random rotations and placements [integer ≥ 0]."""
    stiffness_target_overlap: float | None = None
    """Target overlap of "auto" stiffness as a fraction of the diameter [1], in (0, 0.5];
    None lets the library decide."""
    dt_safety: float | None = None
    """Safety factor on the automatic/critical time step [1], in (0, 1]; None lets the
    library decide."""
    sleeping: bool = True
    """Whether resting bodies are put to sleep."""
    sleep: SleepSettings = field(default_factory=SleepSettings)
    """Sleep thresholds."""
    contact_layers: int = 1
    """Spheres within this many lattice layers of each body's surface take part in
    contacts [integer ≥ 0]; 0 (or "all" in the file) keeps every sphere. Mass and
    inertia do not depend on it (docs/spheres.md, "Surface spheres")."""
    spheres: str | None = None
    """Sphere-set mode of every shape that names none: "lattice", "surface" or "auto"
    (each shape's own: spheres.fidelity.auto_mode; docs/spheres.md); None: the
    library's default (spheres.DEFAULT_MODE)."""
    surface_spacing: float | None = None
    """Spacing of a surface set's shell spheres as a fraction of the diameter [1], in
    [0.05, 1], for every shape that names none; None: spheres.DEFAULT_SPACING. Wider
    is cheaper and bumpier between bodies (docs/spheres.md, "Spacing")."""
    contact_law: str = laws.DEFAULT
    """Contact force law (laws.LAWS): "linear" (the paper's spring-dashpot) or "hertz"
    (Hertz-Mindlin with Tsuji's damping); docs/physics.md."""


@dataclass(frozen=True)
class MaterialSpec:
    """``[materials.<name>]``: a contact material."""

    name: str
    """Material name (table key)."""
    density: float = 1000.0
    """Density [kg/m³], > 0."""
    restitution: float = 0.5
    """Coefficient of restitution [1], in [0, 1]."""
    friction: float = 0.5
    """Coulomb friction coefficient μ [1], ≥ 0."""
    stiffness: Union[float, str] = "auto"
    """Normal contact stiffness [N/m] > 0, or "auto"."""
    young_modulus: Optional[float] = None
    """Young's modulus E [Pa] > 0 (contact_law = "hertz" only): the Hertz constant
    from it instead of "auto"."""
    poisson_ratio: float = 0.3
    """Poisson's ratio ν [1], in [0, 0.5), with young_modulus."""
    rolling_friction: Optional[float] = None
    """Rolling-resistance coefficient μ_r [1], ≥ 0 (0: off); None: the default
    (materials.ROLLING_FRICTION). A ball rolling at v stops after 7 v² / (10 μ_r g)."""
    glue_strength: Optional[float] = None
    """Tensile strength σ [Pa] > 0 of the glue between this material's fractured
    pieces (``[[bodies]] glue = true``): a bonded sphere pair breaks above σ d²."""
    glue_stiffness: Union[float, str] = "auto"
    """A glue bond's whole spring [N/m] > 0, or "auto": the contact's (sim/glue.py)."""
    glue_damping: float = 0.7
    """Damping ratio ζ [1] ≥ 0 of a glue bond (1: critical; sim.glue.GLUE_DAMPING)."""

    def to_material(self):
        """The :class:`dempipe.sim.materials.Material` (stiffness None for "auto")."""

        k = None if self.stiffness == "auto" else float(self.stiffness)
        return Material(self.name, float(self.density), float(self.restitution),
                        float(self.friction), k,
                        None if self.young_modulus is None else float(self.young_modulus),
                        float(self.poisson_ratio),
                        ROLLING_FRICTION if self.rolling_friction is None
                        else float(self.rolling_friction),
                        None if self.glue_strength is None else float(self.glue_strength),
                        None if self.glue_stiffness == "auto" else float(self.glue_stiffness),
                        float(self.glue_damping))


@dataclass(frozen=True)
class ShapeSpec:
    """``[shapes.<name>]``: a built-in shape with parameters, or a mesh file."""

    name: str
    """Shape name (table key)."""
    builtin: str | None = None
    """Built-in shape name (see ``dempipe.mesh.shapes.SHAPES``), or None for a mesh file."""
    params: dict = field(default_factory=dict)
    """Built-in shape parameters [m for lengths], passed to the builder as keywords."""
    mesh_path: Path | None = None
    """Absolute path of the mesh file (resolved relative to the scene file), or None."""
    scale: float = 1.0
    """Uniform scale applied to the mesh file's coordinates [1], > 0 (mesh only)."""
    mesh: Any = field(default=None, compare=False)
    """An in-memory ``trimesh.Trimesh`` in the shape's own coordinates [m] (a USD
    stage's collision geometry, dempipe.scene.usd_reader), or None: builtin or mesh_path."""
    center_of_mass: Vec3 | None = None
    """Centre of mass in the shape's own coordinates [m] when given rather than
    computed from the mesh (UsdPhysics MassAPI); None: the mesh's."""
    spheres: str | None = None
    """This shape's sphere-set mode, "lattice", "surface" or "auto"; None: the scene's."""
    surface_spacing: float | None = None
    """This shape's surface-set spacing as a fraction of the diameter [1]; None: the
    scene's."""
    fracture: Any = None
    """A ``dempipe.mesh.fracture.FractureSpec``: every body of this shape is its
    pieces, placed with the body's pose; None: whole."""


@dataclass(frozen=True)
class BodyGroup:
    """``[[bodies]]``: a group of bodies of one shape and material."""

    name: str
    """Group name, a USD prim name ([A-Za-z_][A-Za-z0-9_]*), unique."""
    shape: Union[str, tuple]
    """Name of a ``[shapes.*]`` table, or a tuple of names: body i takes shape[i % n]."""
    material: str = "default"
    """Name of a material."""
    count: int = 1
    """Number of bodies in the group [count] ≥ 1."""
    layout: str = "single"
    """Placement: "single", "grid", "random" or "emit" (random, released over time)."""
    position: Vec3 | None = None
    """single: where the mesh origin goes [m], world frame."""
    origin: Vec3 | None = None
    """grid: mesh-origin position of lattice index (0, 0, 0) [m], world frame."""
    dims: tuple[int, int, int] | None = None
    """grid: lattice size in lattice order (horizontal 1, horizontal 2, up) [count]."""
    spacing: Vec3 | None = None
    """grid: lattice spacing in lattice order (horizontal 1, horizontal 2, up) [m]."""
    region_min: Vec3 | None = None
    """random: lower corner of the box of mesh origins [m], world frame."""
    region_max: Vec3 | None = None
    """random: upper corner of the box of mesh origins [m], world frame."""
    rotation: Union[str, Quat] = "identity"
    """Initial orientation: "identity", "random" (uniform, seeded, per body) or a unit
    quaternion (w, x, y, z)."""
    velocity: Vec3 = (0.0, 0.0, 0.0)
    """Initial linear velocity of every body [m/s], world frame."""
    angular_velocity: Vec3 = (0.0, 0.0, 0.0)
    """Initial angular velocity of every body [rad/s], world frame."""
    mass: float | None = None
    """Mass of every body [kg] when given rather than density × volume (UsdPhysics
    MassAPI); None: the material's density times the shape's volume."""
    inertia: tuple | None = None
    """Inertia about the centre of mass, body frame (the shape's axes), 3 × 3 rows
    [kg m²], when given; None: the shape's, scaled to the mass."""
    starts_asleep: bool = False
    """Whether the bodies start asleep (they wake when something touches them)."""
    kinematic: bool = False
    """Whether the bodies follow ``motion`` instead of integrating (``[bodies.motion]``):
    they push dynamic bodies and are never pushed."""
    motion: Any = None
    """A ``dempipe.sim.motion.Motion`` for a kinematic group, or None."""
    start_time: float = 0.0
    """Time the bodies enter the simulation [s] (an emitter): before it they are not
    simulated, not touched and hidden in the output."""
    rate: float | None = None
    """emit: bodies released per second [1/s] from start_time on, body i at
    start_time + i / rate, each at a random place in the region (seeded)."""
    glue: bool = False
    """Whether the pieces of each body of a fractured shape start glued to their
    neighbours (sim/glue.py; the material's glue_strength)."""


@dataclass(frozen=True)
class PlaneCollider:
    """``[[colliders]] type = "plane"``: an infinite static half-space boundary."""

    point: Vec3 = (0.0, 0.0, 0.0)
    """A point on the plane [m], world frame."""
    normal: Vec3 = (0.0, 0.0, 1.0)
    """Unit normal pointing into the free side [1], world frame (normalized on load)."""
    material: str = "default"
    """Material name."""
    name: str = "plane"
    """Collider name (USD prim name)."""
    motion: Any = None
    """A ``dempipe.sim.motion.Motion`` (``[colliders.motion]``), or None: static."""


@dataclass(frozen=True)
class BoxCollider:
    """``[[colliders]] type = "box"``: an axis-aligned container, walls facing inward."""

    min: Vec3
    """Lower inner corner [m], world frame."""
    max: Vec3
    """Upper inner corner [m], world frame."""
    open_top: bool = True
    """Whether the wall at the top (along the up axis) is left out."""
    thickness: float | None = None
    """Wall thickness [m] > 0; None lets the library decide."""
    material: str = "default"
    """Material name."""
    name: str = "box"
    """Collider name (USD prim name)."""
    motion: Any = None
    """A ``dempipe.sim.motion.Motion`` (``[colliders.motion]``), or None: static."""


@dataclass(frozen=True)
class MeshCollider:
    """``[[colliders]] type = "mesh"``: a static mesh (a mesh file or a built-in shape)."""

    builtin: str | None = None
    """Built-in shape name, or None for a mesh file."""
    params: dict = field(default_factory=dict)
    """Built-in shape parameters [m for lengths]."""
    mesh_path: Path | None = None
    """Absolute path of the mesh file, or None."""
    scale: float = 1.0
    """Uniform scale of the mesh [1], > 0."""
    position: Vec3 = (0.0, 0.0, 0.0)
    """Where the mesh origin goes [m], world frame."""
    rotation: Quat = (1.0, 0.0, 0.0, 0.0)
    """Orientation, unit quaternion (w, x, y, z)."""
    material: str = "default"
    """Material name."""
    mesh: Any = field(default=None, compare=False)
    """An in-memory ``trimesh.Trimesh`` [m] (a USD stage's static collider), or None:
    builtin or mesh_path."""
    name: str = "mesh"
    """Collider name (USD prim name)."""
    motion: Any = None
    """A ``dempipe.sim.motion.Motion`` (``[colliders.motion]``), or None: static."""


Collider = Union[PlaneCollider, BoxCollider, MeshCollider]


@dataclass(frozen=True)
class Scene:
    """A validated scene file."""

    path: Path | None
    """Absolute path of the scene file (None for a string without a file)."""
    output: OutputSettings
    """``[output]``."""
    simulation: SimulationSettings
    """``[simulation]``."""
    materials: dict[str, MaterialSpec]
    """All materials by name; always contains "default"."""
    shapes: dict[str, ShapeSpec]
    """All shapes by name."""
    bodies: tuple[BodyGroup, ...]
    """Body groups in file order."""
    colliders: tuple[Collider, ...] = ()
    """Static colliders in file order."""
    usd: Any = None
    """The USD stage this scene was read from (a ``dempipe.scene.usd_reader.UsdShot``: body
    prims, warnings, what the overlay writes back), or None for a TOML scene."""

    @property
    def base_dir(self) -> Path:
        """Folder relative paths are resolved against."""
        return self.path.parent if self.path is not None else Path.cwd()

    @property
    def n_bodies(self) -> int:
        """Total number of dynamic bodies."""
        return sum(g.count for g in self.bodies)
