"""Sphere sets: a rigid body approximated by equal spheres (Harada et al. 2007, sec. 3).

A mesh is voxelized solidly on a lattice of pitch = sphere diameter, centred on the
mesh's bounding box; a cell is kept when its centre is inside the mesh by the
generalized winding number (robust to small holes and non-watertight meshes). Each
kept cell becomes one sphere of that diameter. Mass properties come from the exact
mesh when it is watertight, so the approximation changes how a body collides, not
how heavy it is or how it spins.

See docs/spheres.md for the method and the measured errors.
"""

from __future__ import annotations

import hashlib
import math
import time
import warnings
from dataclasses import dataclass

import numpy as np

from dempipe.errors import MeshError, ShapeError
from dempipe.spheres.options import DEFAULT_OPTIONS, BuildOptions

#: Bumped whenever the builder's output for the same input could change; part of
#: the cache key, so old cache entries become misses.
BUILDER_VERSION = 2

# Lattice tolerance: an extent within 1e-9 diameters of a whole number of cells does
# not get an extra cell (a sphere mesh of exactly one diameter is one sphere). Meshes
# read from float32 formats get a tolerance of their own precision (cell_tolerance).
_CELL_TOL = 1e-9
# Rounding steps of one float32 coordinate: each end of an extent is rounded once
# (half an ulp), the float64 subtraction and division add nothing comparable; 4 ulps
# of the largest coordinate leaves a margin of 8 over that.
_F32_ULPS = 4.0
# A mesh whose smallest bounding-box extent is below this fraction of its largest is flat.
_FLAT_TOL = 1e-9






def _readonly(a, dtype=np.float64) -> np.ndarray:
    a = np.array(a, dtype=dtype, copy=True)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class SphereSet:
    """A rigid body's equal-sphere approximation and its mass properties.

    centers: (N, 3) float64, sphere centres in the BODY frame (mesh axes, origin at the
        centre of mass) [m]; lattice order (x fastest, then y, then z), or for a
        surface set (note "surface") shell, thin parts, interior. Read-only.
    diameter: the one sphere diameter [m].
    volume: body volume [m^3] (of the exact mesh when it is watertight).
    com: (3,) centre of mass in mesh coordinates [m]. Read-only.
    inertia: (3, 3) inertia tensor about the centre of mass per unit density [m^5];
        multiply by density [kg/m^3] for kg m^2. Read-only.
    mesh_sha256: content hash of the mesh's vertices (float64) and faces (int64).
    key: the cache key (mesh, diameter, options, builder version).
    notes: conditions met while building, re-reported on a cache hit:
        "not_watertight" (mass properties from the cells) and/or "tiny" (the shape
        is smaller than one sphere and got one sphere at its centre of mass) and/or
        "surface" (built in surface mode: BuildOptions.mode).
    """

    centers: np.ndarray
    diameter: float
    volume: float
    com: np.ndarray
    inertia: np.ndarray
    mesh_sha256: str
    key: str
    notes: tuple = ()

    def __post_init__(self):
        c = _readonly(self.centers).reshape(-1, 3)
        object.__setattr__(self, "centers", c)
        object.__setattr__(self, "com", _readonly(self.com).reshape(3))
        object.__setattr__(self, "inertia", _readonly(self.inertia).reshape(3, 3))
        object.__setattr__(self, "diameter", float(self.diameter))
        object.__setattr__(self, "volume", float(self.volume))
        object.__setattr__(self, "notes", tuple(str(n) for n in self.notes))

    def __hash__(self):
        return hash(self.key)

    @property
    def count(self) -> int:
        """Number of spheres."""
        return int(self.centers.shape[0])

    @property
    def radius(self) -> float:
        """Sphere radius [m]."""
        return 0.5 * self.diameter

    @property
    def sphere_volume_error(self) -> float:
        """(N d^3 - V) / V: the lattice cells' volume against the body's."""
        return (self.count * self.diameter ** 3 - self.volume) / self.volume

    @property
    def cell_inertia(self) -> np.ndarray:
        """Inertia per unit density of the sphere set's cells (cubes of side d) about
        the cells' own centre of mass [m^5]."""
        return _cells_mass_properties(self.centers, self.diameter)[2]

    @property
    def inertia_error(self) -> float:
        """Relative Frobenius error of the cells' inertia (cubes of side d, about
        their own centre of mass) against the body's inertia."""
        diff = np.linalg.norm(self.cell_inertia - self.inertia)
        return float(diff / np.linalg.norm(self.inertia))

    def surface(self, layers: int = 1) -> "SphereSet":
        """The spheres within ``layers`` lattice layers of the surface: the ones that
        can touch another body while overlaps stay small (see :func:`surface_mask`).

        Same diameter and mass properties (they are the mesh's, not the spheres');
        lattice order kept; ``key`` is this key + ``":surface<layers>"`` and
        ``notes`` gains ``"surface<layers>"``. ``layers`` = 0 returns ``self``.
        The result is hollow: its ``sphere_volume_error`` and ``inertia_error``
        describe the shell, not how well the spheres fill the mesh; take those
        from the full set.
        """
        layers = _check_layers(layers)
        if layers == 0:
            return self
        keep = surface_mask(self.centers, self.diameter, layers)
        return SphereSet(centers=self.centers[keep], diameter=self.diameter,
                         volume=self.volume, com=self.com, inertia=self.inertia,
                         mesh_sha256=self.mesh_sha256, key=f"{self.key}:surface{layers}",
                         notes=self.notes + (f"surface{layers}",))

    def __repr__(self):
        return (f"SphereSet(count={self.count}, diameter={self.diameter:.6g}, "
                f"volume={self.volume:.6g}, key={self.key[:12]}...)")


@dataclass(frozen=True)
class BuildInfo:
    """How a sphere set was obtained.

    cache: "hit", "miss" (built and stored) or "off" (no cache given or usable).
    seconds: wall time of build_sphere_set_with_info, lookup included [s].
    """

    cache: str
    seconds: float
    key: str


# ---------------------------------------------------------------------------
# helpers


def mesh_label(name) -> str:
    return str(name) if name else "mesh"


def mesh_arrays(mesh, name):
    """Vertices (V,3) float64 and faces (F,3) int64 of a mesh, validated."""
    label = mesh_label(name)
    try:
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
    except (AttributeError, TypeError, ValueError) as exc:
        raise MeshError(f"{label}: not a triangle mesh ({exc})") from None
    if vertices.size == 0 or faces.size == 0:
        raise MeshError(f"{label}: mesh is empty (no vertices or no faces)")
    vertices = vertices.reshape(-1, 3)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshError(f"{label}: faces must be triangles, got shape {faces.shape}")
    if not np.all(np.isfinite(vertices)):
        raise MeshError(f"{label}: mesh has NaN or infinite vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{label}: face indices out of range")
    used = vertices[np.unique(faces)]
    extents = used.max(axis=0) - used.min(axis=0)
    if extents.max() <= 0 or extents.min() <= _FLAT_TOL * extents.max():
        raise MeshError(
            f"{label}: mesh is flat or degenerate (bounding box {np.array2string(extents, precision=4)}); "
            "a body needs a closed volume")
    return np.ascontiguousarray(vertices), np.ascontiguousarray(faces)


def mesh_sha256(mesh) -> str:
    """sha256 hex of the mesh's vertex bytes (float64, C order) then face bytes (int64);
    the same value as :func:`dempipe.mesh.shapes.mesh_digest`."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()


def check_diameter(diameter, name) -> float:
    try:
        d = float(diameter)
    except (TypeError, ValueError):
        d = float("nan")
    if not (math.isfinite(d) and d > 0.0):
        raise ShapeError(
            f"{mesh_label(name)}: sphere diameter must be a positive finite length in metres, "
            f"got {diameter!r}")
    return d


def sphere_set_key(mesh, diameter, options: BuildOptions = DEFAULT_OPTIONS) -> str:
    """The cache key: sha256 over the mesh content, diameter, options and BUILDER_VERSION."""
    h = hashlib.sha256()
    h.update(b"dempipe-sphere-set\0")
    h.update(f"builder={BUILDER_VERSION}\0".encode())
    h.update(mesh_sha256(mesh).encode())
    h.update(np.array([np.shape(mesh.vertices)[0], np.shape(mesh.faces)[0]], dtype=np.int64).tobytes())
    h.update(np.float64(diameter).tobytes())
    h.update(repr(float(diameter)).encode())
    h.update(options.key_text().encode())
    return h.hexdigest()


def diameter_for_resolution(mesh, resolution) -> float:
    """Sphere diameter that puts ``resolution`` spheres across the mesh's longest
    bounding-box extent [m]."""
    try:
        r = float(resolution)
    except (TypeError, ValueError):
        r = float("nan")
    if not (math.isfinite(r) and r > 0):
        raise ShapeError(f"resolution must be a positive number of spheres across, got {resolution!r}")
    extents = np.asarray(mesh.extents, dtype=np.float64)
    return float(extents.max() / r)


def cell_tolerance(vertices, diameter) -> float:
    """How far [cells] an extent may exceed a whole number of cells and still count as
    that number, for a mesh of these ``vertices``: the mesh's own precision.

    Vertices that are all float32 numbers (STL, PLY, GLB and most DCC exports store
    float32) can be off by half a float32 ulp at each end of an extent: an STL box of
    0.4 m has the extent 0.40000001. The tolerance is then _F32_ULPS float32 ulps of the
    largest coordinate, in cells (4 x 1.19e-7 x 0.2 m / 0.1 m = 9.5e-7 cells for that
    box); float64 vertices keep 1e-9 cells. Either way far below any physical length.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.size == 0:
        return _CELL_TOL
    if not np.array_equal(v.astype(np.float32).astype(np.float64), v):
        return _CELL_TOL
    ulp = float(np.finfo(np.float32).eps) * float(np.abs(v).max())
    return max(_CELL_TOL, _F32_ULPS * ulp / float(diameter))


def lattice_centers(lo, hi, diameter, tol: float = _CELL_TOL) -> np.ndarray:
    """Cell centres of the lattice of pitch ``diameter`` centred on the box [lo, hi].

    Cells per axis: max(1, ceil(extent / d - tol)), symmetric about the box centre;
    ``tol`` [cells] is the mesh's precision (:func:`cell_tolerance`), 1e-9 by default.
    Order: x fastest, then y, then z. Returns (N, 3) float64.
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    center = 0.5 * (lo + hi)
    axes = []
    for k in range(3):
        n = max(1, int(math.ceil((hi[k] - lo[k]) / diameter - tol)))
        axes.append(center[k] + (np.arange(n, dtype=np.float64) - 0.5 * (n - 1)) * diameter)
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def _check_layers(layers) -> int:
    if isinstance(layers, bool) or not isinstance(layers, (int, np.integer)) or layers < 0:
        raise ShapeError(f"contact layers must be an integer >= 0 (0: every sphere), got {layers!r}")
    return int(layers)


#: Largest distance of a centre from its lattice site, as a fraction of the diameter,
#: for :func:`surface_mask` to treat a set as lying on a lattice.
_LATTICE_TOL = 1e-6


def surface_mask(centers, diameter, layers: int = 1) -> np.ndarray:
    """Which spheres of a lattice sphere set lie within ``layers`` layers of its surface.

    ``centers`` (N, 3) on a lattice of pitch ``diameter`` (any order, any offset).
    A sphere is *buried*, and its entry False, when every lattice site within
    Chebyshev distance ``layers`` of it (the (2L+1)^3 - 1 sites around it; the 26
    neighbours at ±d for L = 1) holds a sphere of the set; every other sphere is
    True. ``layers`` = 0 keeps every sphere. Centres that are not on one lattice
    (off by more than 1e-6 d) are all kept: the test needs the lattice.

    Why buried spheres can be dropped for contacts (docs/spheres.md, "Surface
    spheres"): another sphere of diameter d touches a buried sphere B only with its
    centre inside the open cube of half-width d around B. To get there from outside
    it crosses a lattice face whose four corners are spheres, and at that moment it
    overlaps the nearest corner, a kept sphere, by at least (1 - √2/2) d ≈ 0.293 d.
    So while every sphere-sphere overlap stays below 0.29 d, buried spheres never
    touch anything and the contact forces are those of the full set.

    Pure NumPy: a dense boolean grid over the set's bounding box, eroded by a cube
    of half-width ``layers`` (separable: a running AND along each axis).
    Returns (N,) bool.
    """
    layers = _check_layers(layers)
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    n = c.shape[0]
    keep = np.ones(n, dtype=bool)
    if layers == 0 or n < 27:          # fewer than 27 spheres: none can be buried
        return keep
    d = float(diameter)
    rel = (c - c.min(axis=0)) / d
    ijk = np.rint(rel)
    if np.abs(rel - ijk).max() > _LATTICE_TOL:
        return keep
    ijk = ijk.astype(np.int64) + layers          # pad by `layers` empty sites
    shape = tuple(int(v) for v in ijk.max(axis=0) + layers + 1)
    grid = np.zeros(shape, dtype=bool)
    grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    buried = grid
    for axis in range(3):
        full = buried.copy()
        for s in range(1, layers + 1):
            # site i stays when sites i-s and i+s along this axis are full too
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis], hi[axis] = slice(s, None), slice(None, -s)
            a = np.zeros_like(full)
            a[tuple(lo)] = buried[tuple(hi)]      # a[i] = buried[i - s]
            b = np.zeros_like(full)
            b[tuple(hi)] = buried[tuple(lo)]      # b[i] = buried[i + s]
            full &= a & b
        buried = full
    return ~buried[ijk[:, 0], ijk[:, 1], ijk[:, 2]]


def _cells_mass_properties(centers, diameter):
    """Volume, centre of mass and inertia (unit density, about that COM) of cubes of
    side ``diameter`` centred at ``centers``."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    n = centers.shape[0]
    cell_v = diameter ** 3
    volume = n * cell_v
    com = centers.mean(axis=0) if n else np.zeros(3)
    r = centers - com
    r2 = np.einsum("ij,ij->i", r, r)
    inertia = cell_v * (np.eye(3) * r2.sum() - r.T @ r)
    inertia += n * (cell_v * diameter ** 2 / 6.0) * np.eye(3)
    return volume, com, inertia


def repaired_mesh(vertices, faces):
    """A repaired copy: merged vertices, no degenerate faces, consistent outward normals."""
    import trimesh

    m = trimesh.Trimesh(vertices=vertices.copy(), faces=faces.copy(), process=False)
    m.merge_vertices()
    m.update_faces(m.nondegenerate_faces())
    m.remove_unreferenced_vertices()
    if len(m.faces):
        m.fix_normals()
    return m


def mesh_for_errors(mesh, name=None):
    """The repaired copy of ``mesh`` the builder works on (merged vertices, no
    degenerate faces, outward normals), for measuring a set against it
    (spheres.surface.envelope_errors)."""
    vertices, faces = mesh_arrays(mesh, name)
    return repaired_mesh(vertices, faces)




# ---------------------------------------------------------------------------
# the builder


def _build(vertices, faces, diameter, name, options, digest, key) -> SphereSet:
    # numba's voxelizer and surface sampler load here, when a set is built: a cache hit
    # (`dempipe check` on a cached scene) imports no numba
    from dempipe.mesh.winding import inside_mask
    from dempipe.spheres.surface import surface_centers

    label = mesh_label(name)
    mesh = repaired_mesh(vertices, faces)
    if len(mesh.faces) == 0:
        raise MeshError(f"{label}: mesh has only degenerate faces")
    notes = []
    watertight = bool(mesh.is_watertight)
    lo, hi = mesh.bounds
    cells = lattice_centers(lo, hi, diameter, cell_tolerance(vertices, diameter))
    inside = inside_mask(mesh, cells, options.winding_threshold)
    kept = cells[inside]

    if watertight:
        mp = mesh.mass_properties  # density 1; inertia is about the centre of mass
        volume = float(mp["volume"])
        if not (math.isfinite(volume) and volume > 0.0):
            raise MeshError(f"{label}: mesh encloses no volume (volume {volume:.3g} m^3)")
        com = np.asarray(mp["center_mass"], dtype=np.float64)
        inertia = np.asarray(mp["inertia"], dtype=np.float64)
    else:
        notes.append("not_watertight")
        if len(kept):
            volume, com, inertia = _cells_mass_properties(kept, diameter)
        else:
            # smaller than one cell: sample a finer lattice (16 across) for the
            # mass properties, and tell a tiny body from one that encloses nothing
            fine_d = float(np.max(hi - lo)) / 16.0
            fine = lattice_centers(lo, hi, fine_d)
            fine = fine[inside_mask(mesh, fine, options.winding_threshold)]
            if len(fine) == 0:
                raise MeshError(f"{label}: mesh encloses no volume (no point is inside it); "
                                "a body needs a closed surface")
            volume, com, inertia = _cells_mass_properties(fine, fine_d)

    if options.mode == "surface":
        sc = surface_centers(mesh, diameter, options.spacing,
                             inside=lambda p: inside_mask(mesh, p, options.winding_threshold),
                             lattice=kept)
        kept = sc.centers
        notes.append("surface")
    if len(kept) == 0:
        notes.append("tiny")
        centers = np.zeros((1, 3))
    else:
        centers = kept - com
    return SphereSet(centers=centers, diameter=diameter, volume=volume, com=com,
                     inertia=inertia, mesh_sha256=digest, key=key, notes=tuple(notes))


def _warn_notes(sphere_set: SphereSet, name) -> None:
    label = mesh_label(name)
    if "not_watertight" in sphere_set.notes:
        warnings.warn(f"{label}: mesh is not watertight; inside test by winding number, "
                      "mass properties from the spheres", stacklevel=3)
    if "tiny" in sphere_set.notes:
        warnings.warn(f"{label}: no sphere of diameter {sphere_set.diameter:.6g} m fits "
                      "inside the shape (it is thinner than about one diameter); using one "
                      "sphere at its centre of mass "
                      "(use a smaller sphere_diameter or a higher resolution)", stacklevel=3)


def build_sphere_set_with_info(mesh, diameter, *, name=None, cache=None,
                               options: BuildOptions = DEFAULT_OPTIONS):
    """Like :func:`build_sphere_set`, also returning a :class:`BuildInfo` (cache hit
    or miss, time)."""
    t0 = time.perf_counter()
    d = check_diameter(diameter, name)
    if options is None:
        options = DEFAULT_OPTIONS
    vertices, faces = mesh_arrays(mesh, name)
    digest = mesh_sha256(mesh)
    key = sphere_set_key(mesh, d, options)
    status = "off"
    result = None
    if cache is not None:
        result = cache.get(key)
        status = "hit" if result is not None else "miss"
    if result is None:
        result = _build(vertices, faces, d, name, options, digest, key)
        if cache is not None:
            if not cache.put(key, result):
                status = "off"
    _warn_notes(result, name)
    return result, BuildInfo(cache=status, seconds=time.perf_counter() - t0, key=key)


def build_sphere_set(mesh, diameter, *, name=None, cache=None,
                     options: BuildOptions = DEFAULT_OPTIONS) -> SphereSet:
    """Approximate ``mesh`` (a trimesh.Trimesh in metres) by spheres of ``diameter`` [m].

    ``options.mode`` "lattice": a lattice of pitch ``diameter`` centred on the mesh's
    bounding box; a cell is kept when its centre is inside by the generalized winding
    number. "surface": centres on the surface's inward offset at d/2 and the lattice
    cells deeper than d (dempipe.spheres.surface, docs/spheres.md "Surface mode"). Mass properties from
    the exact mesh when it is watertight (after merging vertices and fixing normals),
    otherwise from the cells, with a warning. A shape smaller than one sphere gets one
    sphere at its centre of mass, with a warning. ``cache``: a :class:`~dempipe.spheres.cache.SphereCache`
    looked up first and filled after building. ``name`` names the mesh in messages.

    Raises MeshError for empty, NaN, flat or volume-less meshes and ShapeError for a
    diameter that is not a positive finite number.
    """
    sphere_set, _ = build_sphere_set_with_info(mesh, diameter, name=name, cache=cache,
                                               options=options)
    return sphere_set









