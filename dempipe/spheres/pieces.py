"""The pieces of a fractured shape and their sphere sets, which tile the parent's.

    fractured, info = build_pieces(mesh, diameter, FractureSpec(pieces=12, seed=3))
    fractured.pieces[k]        # MeshPiece: closed mesh, inside-face flags
    fractured.sphere_sets[k]   # SphereSet of that piece

The parent is voxelized once, exactly as ``build_sphere_set`` does in lattice mode
(same lattice origin and pitch), and each of its spheres goes to the piece whose
Voronoi cell holds its centre (the nearest seed; within a cell cut into several
parts, the part whose winding number at the centre is largest). So the pieces'
spheres partition one lattice: two spheres of different pieces are at least one
diameter apart, touching with zero overlap across a cut, and their union is the
parent's set. A piece too small to hold a sphere is joined to a neighbour (the one
whose vertices come nearest and whose union with it is connected), so every piece is
a body with spheres and the pieces' volumes still sum to the parent's.

Mass properties of each piece come from its own closed mesh. Everything is in the
parent mesh's coordinates: ``sphere_sets[k].com`` is the piece's centre of mass
there, so a piece is placed with the parent's pose. Cached as one entry per
(mesh, diameter, options, fracture spec, FRACTURE_VERSION).
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass

import numpy as np

from dempipe.errors import MeshError, ShapeError
from dempipe.mesh.fracture import (
    FractureSpec,
    MeshPiece,
    fracture_seeds,
    to_piece,
    voronoi_cells,
)
from dempipe.spheres.options import DEFAULT_OPTIONS, BuildOptions
from dempipe.spheres.sphere_set import (
    BuildInfo,
    SphereSet,
    check_diameter,
    mesh_label,
    mesh_arrays,
    repaired_mesh,
    cell_tolerance,
    lattice_centers,
    mesh_sha256,
    sphere_set_key,
)


@dataclass(frozen=True, eq=False)
class Fractured:
    """A shape cut into pieces: ``pieces`` (MeshPiece, parent coordinates) and one
    ``sphere_sets`` entry per piece (lattice spheres, body frame at the piece's
    centre of mass, ``com`` in parent coordinates); ``key`` the cache key."""

    pieces: tuple
    sphere_sets: tuple
    key: str

    @property
    def count(self) -> int:
        """Number of pieces."""
        return len(self.pieces)


def fracture_key(mesh, diameter, spec: FractureSpec,
                 options: BuildOptions = DEFAULT_OPTIONS) -> str:
    """sha256 over the parent's sphere-set key (mesh, diameter, options, builder
    version) and the fracture spec (with FRACTURE_VERSION)."""
    h = hashlib.sha256()
    h.update(b"dempipe-fracture\0")
    h.update(sphere_set_key(mesh, diameter, options).encode())
    h.update(spec.key_text().encode())
    return h.hexdigest()


def parent_lattice(mesh, diameter, options: BuildOptions = DEFAULT_OPTIONS, name=None):
    """The parent's lattice sphere centres in mesh coordinates, (N, 3), as
    ``build_sphere_set`` keeps them (before subtracting the centre of mass)."""
    from dempipe.mesh.winding import inside_mask

    vertices, faces = mesh_arrays(mesh, name)
    rep = repaired_mesh(vertices, faces)
    lo, hi = rep.bounds
    cells = lattice_centers(lo, hi, diameter, cell_tolerance(vertices, diameter))
    return cells[inside_mask(rep, cells, options.winding_threshold)]


def _assign(points, seeds, cells):
    """Index into the flat solid list of the solid holding each point."""
    from dempipe.mesh.winding import winding_numbers

    flat_start = np.cumsum([0] + [len(c) for c in cells])
    d2 = ((points[:, None, :] - seeds[None, :, :]) ** 2).sum(axis=2)
    cell = np.argmin(d2, axis=1)                 # ties: the lower seed index
    owner = flat_start[cell].copy()
    for i, solids in enumerate(cells):
        at = np.flatnonzero(cell == i)
        if len(solids) < 2 or not len(at):
            continue
        w = []
        for s in solids:
            g = s.to_mesh64()
            v = np.asarray(g.vert_properties, np.float64)[:, :3]
            tris = v[np.asarray(g.tri_verts, np.int64).reshape(-1, 3)]
            w.append(np.abs(winding_numbers(points[at], np.ascontiguousarray(tris))))
        owner[at] = flat_start[i] + np.argmax(np.stack(w, axis=1), axis=1)
    return owner


def _min_vertex_distance(a, b) -> float:
    va = np.asarray(a.to_mesh64().vert_properties, np.float64)[:, :3]
    vb = np.asarray(b.to_mesh64().vert_properties, np.float64)[:, :3]
    return float(np.sqrt(((va[:, None, :] - vb[None, :, :]) ** 2).sum(axis=2).min()))


def _join_empty(solids, members):
    """Join every solid without spheres to a neighbour (in place)."""
    while True:
        empty = [k for k, m in enumerate(members) if len(m) == 0]
        if not empty:
            return
        e = empty[0]
        others = [k for k in range(len(solids)) if k != e]
        if not others:
            raise ShapeError("fracture: no piece holds a sphere; use smaller spheres")
        others.sort(key=lambda k: (_min_vertex_distance(solids[e], solids[k]), k))
        target = others[0]
        for k in others:
            if len((solids[e] + solids[k]).decompose()) == 1:
                target = k
                break
        solids[target] = solids[target] + solids[e]
        del solids[e], members[e]


def _build(mesh, d, spec, options, name, key) -> Fractured:
    label = mesh_label(name)
    points = parent_lattice(mesh, d, options, name)
    if len(points) < 2:
        raise ShapeError(f"{label}: fracture needs at least two spheres in the shape; "
                         "use smaller spheres (a higher resolution)")
    seeds = fracture_seeds(mesh, spec)
    cells, parent_id = voronoi_cells(mesh, seeds, label=label)
    solids = [s for c in cells for s in c]
    owner = _assign(points, seeds, cells)
    members = [np.flatnonzero(owner == k) for k in range(len(solids))]
    _join_empty(solids, members)
    pieces, sets = [], []
    for k, (solid, idx) in enumerate(zip(solids, members)):
        piece = to_piece(solid, parent_id)
        tm = piece.trimesh()
        if not tm.is_watertight:
            raise MeshError(f"{label}: fracture piece {k} is not watertight; "
                            "repair the mesh or choose another fracture seed")
        mp = tm.mass_properties
        com = np.asarray(mp["center_mass"], np.float64)
        pieces.append(piece)
        sets.append(SphereSet(centers=points[idx] - com, diameter=d, volume=float(mp["volume"]),
                              com=com, inertia=np.asarray(mp["inertia"], np.float64),
                              mesh_sha256=mesh_sha256(tm), key=f"{key}:{k}", notes=("piece",)))
    return Fractured(tuple(pieces), tuple(sets), key)


def _to_arrays(f: Fractured) -> dict:
    def cat(arrs, width, dtype):
        return np.concatenate([np.asarray(a, dtype).reshape(-1, width) for a in arrs]) \
            if arrs else np.zeros((0, width), dtype)

    def starts(arrs):
        return np.cumsum([0] + [len(a) for a in arrs]).astype(np.int64)

    P, S = f.pieces, f.sphere_sets
    return dict(
        vertices=cat([p.vertices for p in P], 3, np.float64), vert_start=starts([p.vertices for p in P]),
        faces=cat([p.faces for p in P], 3, np.int64), face_start=starts([p.faces for p in P]),
        inside=np.concatenate([p.inside for p in P]).astype(bool),
        piece_volume=np.array([p.volume for p in P], np.float64),
        centers=cat([s.centers for s in S], 3, np.float64), center_start=starts([s.centers for s in S]),
        diameter=np.float64(S[0].diameter), volume=np.array([s.volume for s in S], np.float64),
        com=np.array([s.com for s in S], np.float64).reshape(-1, 3),
        inertia=np.array([s.inertia for s in S], np.float64).reshape(-1, 3, 3),
        mesh_sha256=np.array([s.mesh_sha256 for s in S], dtype="U64"))


def _from_arrays(a: dict, key: str) -> Fractured:
    vs, fs, cs = a["vert_start"], a["face_start"], a["center_start"]
    pieces, sets = [], []
    for k in range(len(a["volume"])):
        pieces.append(MeshPiece(a["vertices"][vs[k]:vs[k + 1]], a["faces"][fs[k]:fs[k + 1]],
                                a["inside"][fs[k]:fs[k + 1]], float(a["piece_volume"][k])))
        sets.append(SphereSet(centers=a["centers"][cs[k]:cs[k + 1]], diameter=float(a["diameter"]),
                              volume=float(a["volume"][k]), com=a["com"][k],
                              inertia=a["inertia"][k], mesh_sha256=str(a["mesh_sha256"][k]),
                              key=f"{key}:{k}", notes=("piece",)))
    return Fractured(tuple(pieces), tuple(sets), key)


def build_pieces(mesh, diameter, spec: FractureSpec, *, name=None, cache=None,
                 options: BuildOptions = DEFAULT_OPTIONS):
    """Cut ``mesh`` (trimesh, metres) into pieces by ``spec`` and give each piece its
    share of the parent's lattice spheres of ``diameter`` [m]: ``(Fractured,
    BuildInfo)``. ``cache``: a SphereCache looked up first and filled after.
    Lattice mode only (the partition needs one lattice). Raises ShapeError or
    MeshError naming ``name``."""
    t0 = time.perf_counter()
    d = check_diameter(diameter, name)
    if options.mode != "lattice":
        raise ShapeError(f"{mesh_label(name)}: a fractured shape needs spheres = \"lattice\" "
                         f"(got {options.mode!r}): its pieces share one lattice")
    key = fracture_key(mesh, d, spec, options)
    status, result = "off", None
    if cache is not None:
        arrays = cache.get_arrays(key)
        status = "miss"
        if arrays is not None:
            try:
                result = _from_arrays(arrays, key)
                status = "hit"
            except (KeyError, IndexError, ValueError):
                result = None
    if result is None:
        result = _build(mesh, d, spec, options, name, key)
        if cache is not None and not cache.put_arrays(key, _to_arrays(result)):
            status = "off"
    return result, BuildInfo(cache=status, seconds=time.perf_counter() - t0, key=key)
