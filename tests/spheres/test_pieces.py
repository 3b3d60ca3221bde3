"""The pieces' sphere sets tile the parent's lattice (dempipe.spheres.pieces).

Glue across a cut relies on this: spheres of two pieces are exactly one diameter
apart across a cut face (touching, no overlap), and no sphere is lost or doubled.
"""

import numpy as np
import pytest

from dempipe.errors import ShapeError
from dempipe.mesh.fracture import FractureSpec
from dempipe.mesh.shapes import build_shape
from dempipe.spheres.cache import SphereCache
from dempipe.spheres.options import BuildOptions
from dempipe.spheres.pieces import build_pieces, parent_lattice
from dempipe.spheres.sphere_set import build_sphere_set, diameter_for_resolution


@pytest.fixture(scope="module")
def rook():
    return build_shape("rook")


@pytest.fixture(scope="module")
def rook_d(rook):
    return diameter_for_resolution(rook, 16)


@pytest.fixture(scope="module")
def fractured(rook, rook_d):
    return build_pieces(rook, rook_d, FractureSpec(pieces=12, seed=7))[0]


def _lattice_index(points, origin, d):
    """Integer lattice coordinates of points on the lattice through ``origin``, and
    the largest distance from a site [in d]."""
    rel = (points - origin) / d
    ijk = np.rint(rel)
    return ijk.astype(np.int64), float(np.abs(rel - ijk).max())


def test_the_pieces_partition_the_parents_lattice(rook, rook_d, fractured):
    d = rook_d
    parent = build_sphere_set(rook, d)
    world_parent = parent.centers + parent.com
    origin = world_parent[0]
    pi, off = _lattice_index(world_parent, origin, d)
    assert off < 1e-9
    pieces = [ss.centers + ss.com for ss in fractured.sphere_sets]
    union = np.concatenate(pieces)
    ui, off = _lattice_index(union, origin, d)
    # centres re-expressed about each piece's centre of mass and back: a few ulps of
    # the coordinates (~1e-16 m here), far below the 1e-9 d the glue relies on
    assert off < 1e-9
    as_set = lambda a: set(map(tuple, a))
    assert len(as_set(ui)) == len(ui)                        # no sphere twice
    assert as_set(ui) == as_set(pi)                          # and none lost
    assert sum(ss.count for ss in fractured.sphere_sets) == parent.count
    # across pieces: every pair at least d apart (1e-9 d: the re-expression above)
    from scipy.spatial import cKDTree
    owner = np.repeat(np.arange(len(pieces)), [len(p) for p in pieces])
    pairs = cKDTree(union).query_pairs(d * (1 - 1e-9), output_type="ndarray")
    assert not np.any(owner[pairs[:, 0]] != owner[pairs[:, 1]])
    # and the pieces touch: some cross pairs at exactly one diameter
    touching = cKDTree(union).query_pairs(d * (1 + 1e-9), output_type="ndarray")
    cross = touching[owner[touching[:, 0]] != owner[touching[:, 1]]]
    dist = np.linalg.norm(union[cross[:, 0]] - union[cross[:, 1]], axis=1)
    assert len(cross) > 0 and np.allclose(dist, d, rtol=1e-9, atol=0)


def test_each_piece_has_spheres_and_its_own_mass_properties(rook, fractured):
    vols = np.array([ss.volume for ss in fractured.sphere_sets])
    # the pieces' volumes add up to the parent's (1e-9: the cut's rounding, see
    # tests/mesh/test_fracture.py); their centres of mass to the parent's
    assert vols.sum() == pytest.approx(rook.volume, rel=1e-9)
    coms = np.array([ss.com for ss in fractured.sphere_sets])
    np.testing.assert_allclose((vols[:, None] * coms).sum(0) / vols.sum(),
                               rook.center_mass, atol=1e-9 * rook.scale)
    for piece, ss in zip(fractured.pieces, fractured.sphere_sets):
        assert ss.count >= 1
        tm = piece.trimesh()
        assert ss.volume == pytest.approx(tm.volume, rel=1e-12)
        np.testing.assert_allclose(ss.com, tm.center_mass, atol=1e-12)
        # body frame at the piece's centre of mass: inertia symmetric positive definite
        assert np.all(np.linalg.eigvalsh(ss.inertia) > 0)


def test_pieces_too_small_for_a_sphere_join_a_neighbour(rook):
    # 40 seeds at 6 spheres across: many cells hold no lattice centre
    d = diameter_for_resolution(rook, 6)
    f, _ = build_pieces(rook, d, FractureSpec(pieces=40, seed=1))
    assert 2 <= f.count < 40
    assert all(ss.count >= 1 for ss in f.sphere_sets)
    assert all(p.trimesh().is_watertight for p in f.pieces)
    assert sum(ss.volume for ss in f.sphere_sets) == pytest.approx(rook.volume, rel=1e-9)
    assert sum(ss.count for ss in f.sphere_sets) == len(parent_lattice(rook, d))


def test_second_build_is_a_cache_hit_with_the_same_pieces(tmp_path, rook, rook_d, fractured):
    cache = SphereCache(tmp_path)
    spec = FractureSpec(pieces=12, seed=7)
    a, info_a = build_pieces(rook, rook_d, spec, cache=cache)
    b, info_b = build_pieces(rook, rook_d, spec, cache=cache)
    assert (info_a.cache, info_b.cache) == ("miss", "hit")
    for x, y, z in zip(a.sphere_sets, b.sphere_sets, fractured.sphere_sets):
        np.testing.assert_array_equal(x.centers, y.centers)
        np.testing.assert_array_equal(x.centers, z.centers)
        np.testing.assert_array_equal(x.inertia, y.inertia)
    for x, y in zip(a.pieces, b.pieces):
        np.testing.assert_array_equal(x.vertices, y.vertices)
        np.testing.assert_array_equal(x.inside, y.inside)
    # another fracture spec is another entry
    _, info_c = build_pieces(rook, rook_d, FractureSpec(pieces=12, seed=8), cache=cache)
    assert info_c.cache == "miss"
    # a garbled entry is a warned miss, rebuilt
    cache.path_for(info_a.key).write_bytes(b"not a zip")
    with pytest.warns(UserWarning, match="corrupt"):
        _, info_d = build_pieces(rook, rook_d, spec, cache=cache)
    assert info_d.cache == "miss"


def test_surface_mode_is_refused(rook, rook_d):
    with pytest.raises(ShapeError, match="lattice"):
        build_pieces(rook, rook_d, FractureSpec(pieces=3), options=BuildOptions(mode="surface"))
