"""A mesh's rims and axis of revolution (spheres/inscribed.py rims, revolution_axis):
what a lattice set's wall contacts take beside its tori. Exact for the built-in
shapes, whose circles are polygons (mesh/shapes.py CIRCULAR_SEGMENTS; a cylinder's
twice as many)."""

import math

import numpy as np
import pytest
import trimesh

from dempipe.mesh.shapes import CIRCULAR_SEGMENTS, build_shape
from dempipe.spheres.inscribed import revolution_axis, rims


def test_a_cylinder_has_two_rims_inscribed_in_its_polygons():
    found = rims(build_shape("cylinder", diameter=0.1, height=0.05))
    assert len(found) == 2
    inscribed = 0.05 * math.cos(math.pi / (2 * CIRCULAR_SEGMENTS))
    for centre, axis, radius in found:
        assert radius == pytest.approx(inscribed, rel=1e-9)
        assert abs(axis[2]) == pytest.approx(1.0)
        assert centre[:2] == pytest.approx([0.0, 0.0], abs=1e-12)
    assert sorted(c[2] for c, _, _ in found) == pytest.approx([0.0, 0.05], abs=1e-12)


def test_a_pawn_has_its_base_and_collar_rims_and_a_rook_no_crown():
    pawn = sorted(rims(build_shape("pawn", height=0.05)), key=lambda f: -f[2])
    # the base's two edges (the bottom and the band's top), on the circle of 12.21 mm
    # inscribed in its 40-gon, then the collar's
    assert [round(r, 5) for _, _, r in pawn[:2]] == [0.01221, 0.01221]
    assert all(r < 0.008 for _, _, r in pawn[2:])
    # the rook's crown is notched: its top edge is no whole circle
    rook = rims(build_shape("rook", height=0.056))
    assert rook and max(c[2] for c, _, _ in rook) < 0.045


def test_no_rims_on_a_box_a_ball_or_a_rock():
    assert rims(build_shape("box", size=[0.1, 0.1, 0.05])) == []
    assert rims(build_shape("sphere", diameter=0.1)) == []
    rock = trimesh.creation.icosphere(subdivisions=5)
    rock.vertices *= (1.0 + 0.2 * np.random.default_rng(1).random(len(rock.vertices)))[:, None]
    assert rims(rock) == []


def test_the_axis_of_revolution():
    point, axis = revolution_axis(build_shape("cylinder", diameter=0.1, height=0.05))
    assert abs(axis[2]) == pytest.approx(1.0)
    assert point == pytest.approx([0.0, 0.0, 0.025], abs=1e-9)
    point, axis = revolution_axis(build_shape("pawn", height=0.05))
    assert abs(axis[2]) == pytest.approx(1.0)
    # every axis alike, or none: no axis
    assert revolution_axis(build_shape("sphere", diameter=0.1)) is None
    assert revolution_axis(build_shape("box", size=[0.1, 0.1, 0.1])) is None
    assert revolution_axis(build_shape("box", size=[0.1, 0.2, 0.3])) is None
    # equal moments without revolution (a square prism): an axis, whose rings the
    # lattice keeps only where they stay inside the mesh (lattice_tori)
    assert revolution_axis(build_shape("box", size=[0.1, 0.1, 0.05])) is not None


def test_two_rims_closer_than_a_sphere_are_one_band():
    # The pawn's plinth is a band 1.96 mm tall, under half a sphere at the default 12
    # to its height: one layer of lattice spheres lies along both of its edges. They
    # hold it as one band, the lower rim swept up to the upper (column 12), whose lower
    # edge meets a wall: the upper when the pawn lies on its side, the lower when it is
    # tipped onto its foot (tests/sim/test_rolling.py).
    from dempipe.spheres.inscribed import lattice_tori
    from dempipe.spheres.sphere_set import build_sphere_set, diameter_for_resolution

    pawn = build_shape("pawn", height=0.05)
    d = diameter_for_resolution(pawn, 12)
    s = build_sphere_set(pawn, d)
    t = lattice_tori(s.centers, d, np.asarray(pawn.vertices) - s.com, pawn.faces)
    band = t[:, 12] > 0.0
    edges = sorted(c[2] for c, _, r in rims(pawn) if r > 0.01)
    assert band.sum() >= 12                        # the circle all round, 30° apart
    assert np.all((t[band, 9] > 0.0) & (t[band, 10] == 0.0))
    assert t[band, 12] == pytest.approx(edges[1] - edges[0], rel=1e-9)
    assert (s.centers + t[:, 0:3] + s.com)[band, 2] == pytest.approx(edges[0], abs=1e-9)
    assert t[band, 5] == pytest.approx(1.0)          # its axis up, towards the upper edge
    # rims far apart stay two (a cylinder's)
    cyl = build_shape("cylinder", diameter=0.1, height=0.05)
    s = build_sphere_set(cyl, 0.1 / 16)
    t = lattice_tori(s.centers, 0.1 / 16, np.asarray(cyl.vertices) - s.com, cyl.faces)
    assert np.count_nonzero((t[:, 9] > 0.0) & (t[:, 10] == 0.0)) > 20
    assert np.all(t[:, 12] == 0.0)
