"""Fracture: a closed mesh cut into Voronoi pieces with manifold3d.

    spec = FractureSpec(pieces=12, seed=3, impact=(0, 0, 0.1), impact_share=0.5)
    seeds = fracture_seeds(mesh, spec)          # (N, 3) mesh coordinates [m]
    cells, pid = voronoi_cells(mesh, seeds)     # solids per seed; to_piece(solid, pid)

Each seed's Voronoi cell is the intersection of the half-spaces closer to it than to
every other seed; a cell's piece is the mesh trimmed by those planes (manifold3d
``trim_by_plane``), so pieces are closed, watertight and share their cut faces
exactly. A cell that cuts a non-convex mesh in several places gives several
components, each its own piece. Faces that come from a cutting plane, not from the
parent's surface, are flagged ``inside`` (manifold3d keeps each triangle's source
mesh id), so a renderer can give the broken faces their own material.

Everything is in the parent mesh's own coordinates, so the pieces of one object are
placed with the object's pose. manifold3d is imported when a mesh is cut.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np

from dempipe.errors import MeshError, ShapeError

#: Bumped whenever the pieces for the same input could change; part of cache keys.
FRACTURE_VERSION = 1

#: Largest number of pieces one shape may be cut into: each piece is a body, and the
#: cut costs N^2 plane trims.
MAX_PIECES = 500

# Seeds are drawn in batches inside the bounding box and kept when inside the mesh;
# a mesh filling less than 1/_MAX_DRAWS of its box gives up with a message.
_SEED_BATCH = 256
_MAX_DRAWS = 2000


@dataclass(frozen=True)
class FractureSpec:
    """How a shape is cut (``[shapes.X] fracture = {...}``).

    pieces: number of Voronoi seeds N (2..MAX_PIECES); the result may have more
        pieces (a cell meeting a non-convex shape twice) or fewer (a piece too
        small for any lattice sphere is joined to a neighbour).
    seed: random seed of the seed points; the same seed gives the same pieces.
    impact: a point in the shape's own coordinates [m] near which more seeds are
        drawn (smaller pieces there), or None: seeds uniform in the volume.
    impact_share: fraction of the seeds drawn near ``impact``, in [0, 1].
    impact_radius: standard deviation of the seeds drawn near ``impact`` [m];
        None: 0.15 of the shape's longest bounding-box extent.
    """

    pieces: int
    seed: int = 0
    impact: tuple | None = None
    impact_share: float = 0.5
    impact_radius: float | None = None

    def __post_init__(self):
        n = self.pieces
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 2 <= n <= MAX_PIECES:
            raise ShapeError(f"fracture pieces must be an integer from 2 to {MAX_PIECES}, got {n!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ShapeError(f"fracture seed must be an integer >= 0, got {self.seed!r}")
        if self.impact is not None:
            p = self.impact
            if (not isinstance(p, (tuple, list)) or len(p) != 3
                    or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                               and math.isfinite(v) for v in p)):
                raise ShapeError(f"fracture impact must be a point [x, y, z] in metres, got {p!r}")
            object.__setattr__(self, "impact", tuple(float(v) for v in p))
        s = self.impact_share
        if isinstance(s, bool) or not isinstance(s, (int, float)) or not 0.0 <= s <= 1.0:
            raise ShapeError(f"fracture impact_share must be a fraction in [0, 1], got {s!r}")
        r = self.impact_radius
        if r is not None and (isinstance(r, bool) or not isinstance(r, (int, float))
                              or not (math.isfinite(r) and r > 0)):
            raise ShapeError(f"fracture impact_radius must be a positive length in metres, got {r!r}")
        object.__setattr__(self, "pieces", int(n))
        object.__setattr__(self, "seed", int(self.seed))
        object.__setattr__(self, "impact_share", float(s))

    def key_text(self) -> str:
        """Every field and FRACTURE_VERSION, for cache keys."""
        return repr((FRACTURE_VERSION, self.pieces, self.seed, self.impact,
                     repr(self.impact_share), None if self.impact_radius is None
                     else repr(float(self.impact_radius))))


@dataclass(frozen=True, eq=False)
class MeshPiece:
    """One closed piece of a fractured mesh, in the parent mesh's coordinates.

    vertices: (V, 3) float64 [m]; faces: (F, 3) int64, outward winding;
    inside: (F,) bool, True for a face on a cutting plane (the broken surface);
    volume: enclosed volume [m^3].
    """

    vertices: np.ndarray
    faces: np.ndarray
    inside: np.ndarray
    volume: float

    def trimesh(self):
        """The piece as a ``trimesh.Trimesh`` (no processing: vertices kept)."""
        import trimesh

        return trimesh.Trimesh(vertices=self.vertices.copy(), faces=self.faces.copy(),
                               process=False)


def _manifold(mesh, label="mesh"):
    """The mesh as a manifold3d.Manifold with its own source id (vertices merged)."""
    import manifold3d
    import trimesh

    m = trimesh.Trimesh(vertices=np.asarray(mesh.vertices, np.float64),
                        faces=np.asarray(mesh.faces, np.int64), process=False)
    m.merge_vertices()
    m.update_faces(m.nondegenerate_faces())
    m.remove_unreferenced_vertices()
    solid = manifold3d.Manifold(manifold3d.Mesh64(
        vert_properties=np.ascontiguousarray(m.vertices, np.float64),
        tri_verts=np.ascontiguousarray(m.faces, np.uint64)))
    if solid.status() != manifold3d.Error.NoError or solid.is_empty():
        raise MeshError(f"{label}: fracture needs a closed, manifold mesh "
                        f"(manifold3d: {solid.status().name}); repair the mesh or do not fracture it")
    return solid.as_original()


def to_piece(solid, parent_id) -> MeshPiece:
    """A solid of :func:`voronoi_cells` (or a union of them) as a MeshPiece: faces
    whose source is not the parent (``parent_id``) are the inside faces. A union
    (``a + b``) keeps each face's source, so joined pieces keep their flags."""
    g = solid.to_mesh64()
    verts = np.array(np.asarray(g.vert_properties, dtype=np.float64)[:, :3], copy=True)
    faces = np.asarray(g.tri_verts, dtype=np.int64).reshape(-1, 3)
    run_index = np.asarray(g.run_index, dtype=np.int64)
    run_id = np.asarray(g.run_original_id, dtype=np.int64)
    tri_id = np.repeat(run_id, np.diff(run_index) // 3)
    return MeshPiece(vertices=np.ascontiguousarray(verts), faces=faces,
                     inside=tri_id != parent_id, volume=float(solid.volume()))



def fracture_seeds(mesh, spec: FractureSpec) -> np.ndarray:
    """(N, 3) seed points inside ``mesh`` [m, mesh coordinates]: round(impact_share N)
    normally distributed about ``spec.impact``, the rest uniform in the volume.
    Deterministic for ``spec.seed``."""
    from dempipe.mesh.winding import inside_mask

    rng = np.random.default_rng(spec.seed)
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    n_near = int(round(spec.impact_share * spec.pieces)) if spec.impact is not None else 0
    radius = spec.impact_radius or 0.15 * float(np.max(hi - lo))

    def draw(count, sample):
        got, draws = [], 0
        while sum(len(g) for g in got) < count:
            if draws >= _MAX_DRAWS:
                raise ShapeError("fracture: could not place seed points inside the shape "
                                 "(is it closed? is the impact point inside or near it?)")
            p = sample(_SEED_BATCH)
            got.append(p[inside_mask(mesh, p)])
            draws += 1
        return np.concatenate(got)[:count]

    near = draw(n_near, lambda k: np.asarray(spec.impact) + rng.normal(0.0, radius, (k, 3))) \
        if n_near else np.zeros((0, 3))
    far = draw(spec.pieces - n_near, lambda k: rng.uniform(lo, hi, (k, 3)))
    return np.concatenate([near, far])


def _components(solid):
    """The connected parts of a manifold, largest volume first (ties by centroid)."""
    parts = solid.decompose() if solid.num_tri() else []
    parts = [p for p in parts if p.volume() > 0]
    if len(parts) <= 1:
        return parts

    def order(p):
        g = np.asarray(p.to_mesh64().vert_properties)[:, :3]
        return (-p.volume(), *np.round(g.mean(axis=0), 12))
    return sorted(parts, key=order)


def voronoi_cells(mesh, seeds, *, label="mesh"):
    """For each seed, the solids (manifold3d.Manifold, maybe none) of ``mesh`` inside
    its Voronoi cell, and the parent's source id: ``(cells, parent_id)``. Together
    the solids partition the mesh; :func:`to_piece` turns one into a MeshPiece."""
    seeds = np.asarray(seeds, dtype=np.float64).reshape(-1, 3)
    parent = _manifold(mesh, label)
    cells = []
    for i, s in enumerate(seeds):
        cell = parent
        # nearest seeds first: they cut most, so later trims work on less
        for j in np.argsort(np.linalg.norm(seeds - s, axis=1), kind="stable"):
            if j == i:
                continue
            n = s - seeds[j]
            length = float(np.linalg.norm(n))
            if length == 0.0:
                raise ShapeError(f"{label}: two fracture seeds coincide; choose another seed")
            n = n / length
            cell = cell.trim_by_plane(tuple(n), float(n @ (0.5 * (s + seeds[j]))))
            if cell.is_empty():
                break
        cells.append(_components(cell))
    return cells, parent.original_id()


def pieces_digest(pieces) -> str:
    """sha256 of the pieces' vertices, faces and inside flags, in order."""
    h = hashlib.sha256()
    for p in pieces:
        h.update(np.ascontiguousarray(p.vertices, np.float64).tobytes())
        h.update(np.ascontiguousarray(p.faces, np.int64).tobytes())
        h.update(np.ascontiguousarray(p.inside, bool).tobytes())
    return h.hexdigest()
