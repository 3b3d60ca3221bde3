"""shapes.py: built-in shapes against their parameters and closed forms; mesh files."""

import math
import warnings

import numpy as np
import pytest
import trimesh

from dempipe.errors import MeshError, ShapeError
from dempipe.mesh.shapes import SHAPES, build_shape, list_shapes, load_mesh, mesh_digest

PIECES = ["pawn", "rook", "knight", "bishop", "queen", "king"]
ALL = sorted(SHAPES)


# ---------------------------------------------------------------- every built-in shape


@pytest.mark.parametrize("name", ALL)
def test_builtin_is_a_closed_solid(name):
    mesh = build_shape(name)
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.is_volume
    assert mesh.volume > 0
    assert mesh.body_count == 1
    assert np.isfinite(mesh.vertices).all()
    # small enough to voxelize and export quickly
    assert len(mesh.faces) <= 6000


@pytest.mark.parametrize("name", ALL)
def test_registry_entry_is_complete(name):
    spec = SHAPES[name]
    assert spec.name == name
    assert spec.doc and "\n" not in spec.doc
    assert spec.params
    for key, p in spec.params.items():
        assert p.kind in ("length", "vector3", "int")
        assert "[m]" in p.doc or p.kind == "int", f"{name}.{key} doc lacks a unit"
    assert [s.name for s in list_shapes()] == sorted(SHAPES)


@pytest.mark.parametrize("name", ALL)
def test_build_returns_a_fresh_mesh(name):
    a = build_shape(name)
    a.apply_translation([1.0, 0.0, 0.0])
    b = build_shape(name)
    assert mesh_digest(a) != mesh_digest(b)
    assert mesh_digest(b) == mesh_digest(build_shape(name))  # deterministic


# ---------------------------------------------------------------- chess pieces


@pytest.mark.parametrize("name", PIECES)
@pytest.mark.parametrize("height", [None, 0.05, 0.12])
def test_piece_height_and_foot(name, height):
    params = {} if height is None else {"height": height}
    mesh = build_shape(name, **params)
    h = SHAPES[name].params["height"].default if height is None else height
    lo, hi = mesh.bounds
    assert lo[2] == 0.0  # stands on z = 0
    assert hi[2] == pytest.approx(h, rel=1e-6)
    # axis on +z: the round foot is centred on the origin
    foot = mesh.vertices[mesh.vertices[:, 2] < 1e-9]
    assert np.allclose(foot[:, :2].mean(axis=0), 0.0, atol=1e-3 * h)
    # a piece is taller than it is wide
    assert mesh.extents[0] < h and mesh.extents[1] < h


@pytest.mark.parametrize("name", PIECES)
def test_piece_base_diameter(name):
    mesh = build_shape(name, height=0.06, base_diameter=0.03)
    foot = mesh.vertices[mesh.vertices[:, 2] < 1e-9]
    radius = np.linalg.norm(foot[:, :2], axis=1).max()
    assert 2 * radius == pytest.approx(0.03, rel=1e-6)
    assert mesh.bounds[1, 2] == pytest.approx(0.06, rel=1e-6)


def test_pawn_proportions():
    mesh = build_shape("pawn")
    h = mesh.bounds[1, 2]
    assert h == pytest.approx(0.05, rel=1e-6)
    # a Staunton pawn: its base about half its height across, its head a ball about a
    # third, so that on its side it rolls in a circle (tests/sim/test_rolling.py)
    foot = mesh.vertices[mesh.vertices[:, 2] < 1e-9]
    d = 2 * np.linalg.norm(foot[:, :2], axis=1).max()
    assert 0.45 * h <= d <= 0.6 * h
    head = mesh.vertices[mesh.vertices[:, 2] > 0.65 * h]
    head_d = 2 * np.linalg.norm(head[:, :2], axis=1).max()
    assert 0.33 * h <= head_d <= 0.4 * h and head_d < d - 0.1 * h


def test_pieces_scale_like_staunton_set():
    heights = {n: build_shape(n).bounds[1, 2] for n in PIECES}
    assert max(heights, key=heights.get) == "king"
    assert min(heights, key=heights.get) == "pawn"
    assert heights["queen"] > heights["bishop"] > heights["rook"] > heights["pawn"]


def test_pieces_differ_at_equal_height():
    vols = {n: build_shape(n, height=0.05).volume for n in PIECES}
    assert len({round(v, 12) for v in vols.values()}) == len(PIECES)
    for name in PIECES:  # all share the height parameter exactly
        assert build_shape(name, height=0.05).bounds[1, 2] == pytest.approx(0.05, rel=1e-6)


def test_piece_volume_scales_with_cube_of_height():
    v1 = build_shape("queen", height=0.05).volume
    v2 = build_shape("queen", height=0.10).volume
    assert v2 / v1 == pytest.approx(8.0, rel=1e-6)


def test_piece_features_were_cut():
    # Each finishing boolean shows up in the mesh: notches lower the rook's volume below
    # its uncut turret, the king's cross is the only thing above its dome, etc.
    rook = build_shape("rook", height=1.0)
    top = rook.vertices[rook.vertices[:, 2] > 0.999]
    angles = np.degrees(np.arctan2(top[:, 1], top[:, 0])) % 60.0
    # merlon tops never lie inside a notch (centred on multiples of 60 degrees)
    assert (np.minimum(angles, 60 - angles) > 5).all()
    king = build_shape("king", height=1.0)
    upper = king.vertices[king.vertices[:, 2] > 0.86]
    assert np.abs(upper[:, 1]).max() == pytest.approx(0.025, rel=1e-6)  # box cross
    assert np.abs(upper[:, 0]).max() == pytest.approx(0.07, rel=1e-6)


# ---------------------------------------------------------------- simple solids


def test_box_extents_and_centre():
    mesh = build_shape("box", size=[0.1, 0.2, 0.3])
    assert np.array_equal(mesh.extents, [0.1, 0.2, 0.3])
    assert np.allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-15)
    assert mesh.volume == pytest.approx(0.006, rel=1e-12)
    assert np.array_equal(build_shape("box").extents, [0.04, 0.04, 0.04])


def test_sphere_volume_and_centre():
    mesh = build_shape("sphere")
    r = 0.02
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * r**3, rel=0.02)
    assert np.allclose(mesh.bounds, [[-r] * 3, [r] * 3], atol=1e-12)
    assert len(build_shape("sphere", subdivisions=1).faces) == 80
    big = build_shape("sphere", diameter=0.1)
    assert big.extents.max() == pytest.approx(0.1, rel=1e-9)


def test_torus_volume_and_axis():
    big_r, small_r = 0.02, 0.008
    mesh = build_shape("torus")
    assert mesh.volume == pytest.approx(2 * math.pi**2 * big_r * small_r**2, rel=0.02)
    assert np.allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-12)
    # axis +z: thickness along z is the tube diameter
    assert mesh.extents[2] == pytest.approx(2 * small_r, rel=1e-6)
    assert mesh.extents[0] == pytest.approx(2 * (big_r + small_r), rel=1e-6)
    thin = build_shape("torus", major_radius=0.05, minor_radius=0.001)
    assert thin.is_volume
    assert thin.volume == pytest.approx(2 * math.pi**2 * 0.05 * 0.001**2, rel=0.02)


def test_cylinder_volume_and_foot():
    mesh = build_shape("cylinder", diameter=0.03, height=0.07)
    assert mesh.volume == pytest.approx(math.pi * 0.015**2 * 0.07, rel=0.02)
    assert mesh.bounds[0, 2] == 0.0
    assert mesh.bounds[1, 2] == pytest.approx(0.07, rel=1e-12)
    assert np.allclose(mesh.bounds[:, :2].mean(axis=0), 0.0, atol=1e-12)


def test_capsule_volume_and_foot():
    d, h = 0.02, 0.05
    mesh = build_shape("capsule", diameter=d, height=h)
    r = d / 2
    exact = math.pi * r**2 * (h - d) + 4 / 3 * math.pi * r**3
    assert mesh.volume == pytest.approx(exact, rel=0.02)
    assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-12)
    assert mesh.bounds[1, 2] == pytest.approx(h, rel=1e-9)
    assert mesh.extents[0] == pytest.approx(d, rel=1e-9)
    # height == diameter is a sphere
    assert build_shape("capsule", diameter=d, height=d).is_volume


# ---------------------------------------------------------------- errors


def test_unknown_shape_lists_known_and_suggests():
    with pytest.raises(ShapeError) as err:
        build_shape("pwn")
    msg = str(err.value)
    assert "unknown shape 'pwn'" in msg
    assert "known: " + ", ".join(sorted(SHAPES)) in msg
    assert "did you mean 'pawn'?" in msg
    with pytest.raises(ShapeError, match="known: bishop"):
        build_shape("zzzzzz")


def test_unknown_parameter():
    with pytest.raises(ShapeError) as err:
        build_shape("pawn", heigth=0.05)
    msg = str(err.value)
    assert "shape 'pawn': unknown parameter 'heigth' (known: height, base_diameter)" in msg
    assert "did you mean 'height'?" in msg


@pytest.mark.parametrize(
    "name, params, needle",
    [
        ("pawn", {"height": 0.0}, "height"),
        ("pawn", {"height": -0.05}, "height"),
        ("pawn", {"height": float("nan")}, "height"),
        ("pawn", {"height": float("inf")}, "height"),
        ("pawn", {"height": "tall"}, "height"),
        ("pawn", {"height": True}, "height"),
        ("king", {"base_diameter": 0.2}, "base_diameter"),
        ("king", {"base_diameter": -1.0}, "base_diameter"),
        ("box", {"size": [0.1, 0.1]}, "size"),
        ("box", {"size": [0.1, 0.1, 0.1, 0.1]}, "size"),
        ("box", {"size": [0.1, 0.0, 0.1]}, "size"),
        ("box", {"size": [0.1, float("nan"), 0.1]}, "size"),
        ("box", {"size": 0.1}, "size"),
        ("sphere", {"diameter": 0}, "diameter"),
        ("sphere", {"subdivisions": -1}, "subdivisions"),
        ("sphere", {"subdivisions": 99}, "subdivisions"),
        ("sphere", {"subdivisions": 2.5}, "subdivisions"),
        ("torus", {"minor_radius": 0.02}, "minor_radius"),
        ("torus", {"major_radius": 0.005}, "minor_radius"),
        ("capsule", {"diameter": 0.03, "height": 0.02}, "height"),
        ("cylinder", {"height": -1}, "height"),
    ],
)
def test_bad_values_name_parameter_and_range(name, params, needle):
    with pytest.raises(ShapeError) as err:
        build_shape(name, **params)
    msg = str(err.value)
    assert f"shape '{name}'" in msg
    assert needle in msg
    # says what would be valid
    assert any(word in msg for word in ("> 0", "..", "<", ">=")), msg


def test_accepts_numpy_and_int_values():
    assert build_shape("box", size=np.array([0.01, 0.02, 0.03])).extents[2] == pytest.approx(0.03)
    assert build_shape("sphere", diameter=np.float32(0.05), subdivisions=np.int64(2)).is_volume
    assert build_shape("cylinder", diameter=1, height=2).bounds[1, 2] == pytest.approx(2.0)


# ---------------------------------------------------------------- load_mesh


@pytest.mark.parametrize("ext", ["obj", "stl", "ply", "off", "glb", "gltf"])
def test_load_round_trip(tmp_path, ext):
    mesh = build_shape("queen")
    path = tmp_path / f"queen.{ext}"
    mesh.export(path)
    loaded = load_mesh(path)
    assert isinstance(loaded, trimesh.Trimesh)
    assert loaded.is_watertight
    assert loaded.volume == pytest.approx(mesh.volume, rel=1e-6)
    assert np.allclose(loaded.bounds, mesh.bounds, rtol=0, atol=1e-7)


def test_load_applies_scale(tmp_path):
    mesh = build_shape("box", size=[10.0, 20.0, 30.0])  # "millimetres"
    path = tmp_path / "box.stl"
    mesh.export(path)
    loaded = load_mesh(str(path), scale=0.001)
    assert np.allclose(loaded.extents, [0.01, 0.02, 0.03], rtol=1e-6)
    assert loaded.volume == pytest.approx(6e-6, rel=1e-6)


@pytest.mark.parametrize("scale", [0, -1.0, float("nan"), float("inf"), "1"])
def test_load_rejects_bad_scale(tmp_path, scale):
    path = tmp_path / "box.stl"
    build_shape("box").export(path)
    with pytest.raises(MeshError, match="scale"):
        load_mesh(path, scale=scale)


def test_load_merges_scene_with_warning(tmp_path):
    scene = trimesh.Scene()
    box = build_shape("box")
    ball = build_shape("sphere")
    scene.add_geometry(box, node_name="box")
    scene.add_geometry(ball, node_name="ball", transform=trimesh.transformations.translation_matrix([0.1, 0, 0]))
    path = tmp_path / "two.glb"
    scene.export(path)
    with pytest.warns(UserWarning, match=r"two\.glb: 2 meshes merged into one body"):
        merged = load_mesh(path)
    assert merged.volume == pytest.approx(box.volume + ball.volume, rel=1e-6)
    # the scene-graph transform was applied: the ball sits at x = 0.1
    assert merged.bounds[1, 0] == pytest.approx(0.12, rel=1e-6)
    assert merged.bounds[0, 0] == pytest.approx(-0.02, rel=1e-6)


def test_single_mesh_loads_without_warning(tmp_path):
    path = tmp_path / "one.glb"
    build_shape("pawn").export(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_mesh(path)


def test_load_missing_file(tmp_path):
    path = tmp_path / "nope.obj"
    with pytest.raises(MeshError, match=r"nope\.obj: file not found"):
        load_mesh(path)


def test_load_empty_file(tmp_path):
    path = tmp_path / "empty.stl"
    path.write_bytes(b"")
    with pytest.raises(MeshError, match=r"empty\.stl"):
        load_mesh(path)


@pytest.mark.parametrize("ext", ["obj", "stl", "ply", "off", "glb"])
def test_load_garbage_file(tmp_path, ext):
    path = tmp_path / f"garbage.{ext}"
    path.write_bytes(b"this is not a mesh \x00\x01\x02 at all\n" * 3)
    with pytest.raises(MeshError, match=rf"garbage\.{ext}"):
        load_mesh(path)


def test_load_unsupported_extension(tmp_path):
    path = tmp_path / "model.fbx"
    path.write_bytes(b"whatever")
    with pytest.raises(MeshError) as err:
        load_mesh(path)
    msg = str(err.value)
    assert "model.fbx" in msg
    for ext in (".obj", ".stl", ".ply", ".off", ".glb", ".gltf"):
        assert ext in msg


def test_load_flat_mesh(tmp_path):
    square = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    path = tmp_path / "square.obj"
    square.export(path)
    with pytest.raises(MeshError, match=r"square\.obj: .*flat"):
        load_mesh(path)


def test_load_zero_volume_mesh(tmp_path):
    # A square covered on both sides plus a two-sided fin standing on it: the bounding
    # box is not flat, but the surface encloses nothing.
    path = tmp_path / "sheets.obj"
    path.write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 0.5 1\n"
        "f 1 2 3\nf 1 3 4\nf 1 3 2\nf 1 4 3\nf 1 2 5\nf 1 5 2\n"
    )
    with pytest.raises(MeshError, match=r"sheets\.obj: .*volume"):
        load_mesh(path)


def test_load_non_finite_vertices(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 nan\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 3 1 4\n")
    with pytest.raises(MeshError, match=r"nan\.obj: .*non-finite"):
        load_mesh(path)


def test_load_keeps_open_mesh_and_repairs_winding(tmp_path):
    # A box with its top missing and one face flipped: accepted (not watertight), the
    # flip repaired, duplicate vertices merged.
    box = build_shape("box")
    faces = box.faces[box.face_normals[:, 2] < 0.5].copy()
    faces[0] = faces[0][::-1]
    unmerged = trimesh.Trimesh(box.vertices[faces].reshape(-1, 3), np.arange(len(faces) * 3).reshape(-1, 3), process=False)
    path = tmp_path / "open.ply"
    unmerged.export(path)
    loaded = load_mesh(path)
    assert not loaded.is_watertight
    assert loaded.is_winding_consistent
    assert len(loaded.vertices) == 8


def test_load_orients_inverted_and_scrambled_faces(tmp_path):
    # One body inside out, another with random faces flipped: both come back outward.
    rng = np.random.default_rng(0)
    king = build_shape("king")
    king.invert()
    torus = build_shape("torus")
    torus.apply_translation([0.2, 0, 0])
    faces = torus.faces.copy()
    flipped = rng.random(len(faces)) < 0.3
    faces[flipped] = faces[flipped][:, ::-1]
    torus = trimesh.Trimesh(torus.vertices, faces, process=False)
    scene = trimesh.Scene([king, torus])
    path = tmp_path / "messy.glb"
    scene.export(path)
    with pytest.warns(UserWarning, match="2 meshes merged"):
        loaded = load_mesh(path)
    assert loaded.is_winding_consistent and loaded.is_volume
    expected = build_shape("king").volume + build_shape("torus").volume
    assert loaded.volume == pytest.approx(expected, rel=1e-6)


# ---------------------------------------------------------------- mesh_digest


def test_mesh_digest_is_content_hash():
    a = build_shape("pawn")
    b = build_shape("pawn")
    assert mesh_digest(a) == mesh_digest(b)
    assert len(mesh_digest(a)) == 64
    b.vertices[0, 0] += 1e-12
    assert mesh_digest(a) != mesh_digest(b)
    # dtype-independent: float32 copies of the same values hash the same as float64
    c = trimesh.Trimesh(a.vertices.astype(np.float64), a.faces.astype(np.int32), process=False)
    assert mesh_digest(c) == mesh_digest(a)
