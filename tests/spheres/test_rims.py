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
    # the base's two edges (the bottom and the band's top), 11.5 mm, then the collar's
    assert [round(r, 5) for _, _, r in pawn[:2]] == [0.01146, 0.01146]
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
