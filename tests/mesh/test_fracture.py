"""Fracture geometry: a closed mesh cut into Voronoi pieces (dempipe.mesh.fracture).

The pieces must be closed, fill the parent exactly once (volumes sum to it, no two
overlap), flag their cut faces, and be a function of the seed alone.
"""

import manifold3d
import numpy as np
import pytest

from dempipe.errors import MeshError, ShapeError
from dempipe.mesh.fracture import (
    FractureSpec,
    fracture_seeds,
    pieces_digest,
    to_piece,
    voronoi_cells,
)
from dempipe.mesh.shapes import build_shape


def _cut(mesh, spec):
    cells, pid = voronoi_cells(mesh, fracture_seeds(mesh, spec))
    return cells, [to_piece(s, pid) for c in cells for s in c]


@pytest.fixture(scope="module")
def rook():
    """A non-convex, revolved mesh (crenels): cells can meet it more than once."""
    return build_shape("rook")


@pytest.fixture(scope="module")
def rook_pieces(rook):
    return _cut(rook, FractureSpec(pieces=10, seed=4))[1]


def _solid(p):
    return manifold3d.Manifold(manifold3d.Mesh64(
        vert_properties=np.array(p.vertices, np.float64), tri_verts=np.ascontiguousarray(p.faces, np.uint64)))


def test_pieces_are_watertight_and_fill_the_parent(rook, rook_pieces):
    assert len(rook_pieces) >= 10
    for p in rook_pieces:
        tm = p.trimesh()
        assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
        assert p.inside.any() and (~p.inside).any()     # a cut face and some of the skin
    # Voronoi cells tile space, so the volumes add up to the parent's up to the
    # rounding of the cut vertices: 1e-9 relative is ~1e4 float64 ulps of slack for
    # a sum of ~10 divergence-theorem volumes of a few hundred triangles each.
    total = sum(p.volume for p in rook_pieces)
    assert total == pytest.approx(rook.volume, rel=1e-9)
    assert sum(p.trimesh().volume for p in rook_pieces) == pytest.approx(rook.volume, rel=1e-9)


def test_no_two_pieces_overlap(rook, rook_pieces):
    solids = [_solid(p) for p in rook_pieces]
    for i in range(len(solids)):
        for j in range(i + 1, len(solids)):
            # pieces share faces only: their intersection has no volume (1e-12 of
            # the parent's: boolean rounding on coplanar faces, far below any piece)
            assert (solids[i] ^ solids[j]).volume() <= 1e-12 * rook.volume


def test_the_cut_faces_are_flagged_and_lie_on_bisecting_planes():
    box = build_shape("box", size=[0.2, 0.2, 0.2])
    spec = FractureSpec(pieces=6, seed=1)
    seeds = fracture_seeds(box, spec)
    cells, pid = voronoi_cells(box, seeds)
    for i, cell in enumerate(cells):
        for s in cell:
            p = to_piece(s, pid)
            centroid = p.vertices[p.faces].mean(axis=1)
            # an inside face is equidistant (1e-9 m, float64 cut vertices) from its
            # seed and some other seed; a skin face lies on the box (|x| = 0.1 m)
            dist = np.linalg.norm(centroid[:, None, :] - seeds[None], axis=2)
            own = dist[:, i]
            others = np.delete(dist, i, axis=1)
            on_bisector = np.abs(others - own[:, None]).min(axis=1) < 1e-9
            on_skin = np.isclose(np.abs(centroid), 0.1, atol=1e-12).any(axis=1)
            assert np.all(on_bisector[p.inside]) and np.all(on_skin[~p.inside])


def test_same_seed_same_pieces_other_seed_other_pieces(rook, rook_pieces):
    again = _cut(rook, FractureSpec(pieces=10, seed=4))[1]
    other = _cut(rook, FractureSpec(pieces=10, seed=5))[1]
    assert pieces_digest(again) == pieces_digest(rook_pieces)
    assert pieces_digest(other) != pieces_digest(rook_pieces)


def test_seeds_near_the_impact_give_smaller_pieces():
    box = build_shape("box", size=[0.4, 0.2, 0.2])
    impact = (0.18, 0.0, 0.0)
    spec = FractureSpec(pieces=24, seed=2, impact=impact, impact_share=0.5, impact_radius=0.03)
    seeds = fracture_seeds(box, spec)
    cells, pid = voronoi_cells(box, seeds)
    vol = np.array([sum(s.volume() for s in c) for c in cells])
    near = np.arange(len(seeds)) < 12            # the first round(0.5 * 24) seeds
    # 12 seeds within ~0.03 m of the impact crowd a corner, 12 share the rest of the
    # 0.016 m^3: a typical (median) near cell is a few times smaller than a far one,
    # though the cells on the cluster's rim reach out into the bulk (their mean is
    # closer). A factor 2 on the medians leaves room for any seed draw.
    assert np.median(vol[near]) * 2 < np.median(vol[~near])
    assert vol.sum() == pytest.approx(0.4 * 0.2 * 0.2, rel=1e-9)
    # and the piece holding the impact point is smaller than the median
    at = np.argmin(np.linalg.norm(seeds - np.array(impact), axis=1))
    assert vol[at] < np.median(vol)


@pytest.mark.parametrize("kw, word", [
    (dict(pieces=1), "pieces"), (dict(pieces=True), "pieces"), (dict(pieces=10**6), "pieces"),
    (dict(pieces=4, seed=-1), "seed"), (dict(pieces=4, impact=(0, 1)), "impact"),
    (dict(pieces=4, impact=(0, 0, 0), impact_share=1.5), "impact_share"),
    (dict(pieces=4, impact_radius=0.0), "impact_radius"),
])
def test_bad_specs_are_refused_naming_the_field(kw, word):
    with pytest.raises(ShapeError, match=word):
        FractureSpec(**kw)


def test_an_open_mesh_is_refused():
    box = build_shape("box", size=[0.2, 0.2, 0.2])
    box.update_faces(np.arange(len(box.faces)) != 0)     # one triangle gone: open
    with pytest.raises(MeshError, match="closed, manifold mesh"):
        voronoi_cells(box, fracture_seeds(build_shape("box", size=[0.2, 0.2, 0.2]),
                                          FractureSpec(pieces=3)))
