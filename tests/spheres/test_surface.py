"""Surface-following sphere sets, and float32 meshes.

Geometry only, no bakes (those are in test_rolling.py): where the centres go, the
envelope's errors against closed forms, determinism and the cache key, the scene key,
and exact lattice counts of boxes read back from STL and PLY files.
"""

import hashlib
import json
import math

import numpy as np
import pytest
import trimesh

from dempipe.scene.build import Overrides, build_model, sphere_options
from dempipe.spheres.cache import SphereCache
from dempipe.errors import SceneError, ShapeError
from dempipe.scene.load import parse_scene
from dempipe.mesh.shapes import build_shape, load_mesh
from dempipe.spheres.options import DEFAULT_MODE, BuildOptions
from dempipe.spheres.sphere_set import build_sphere_set, cell_tolerance, mesh_for_errors
from dempipe.spheres.options import DEFAULT_SPACING
from dempipe.spheres.surface import MeshQueries, envelope_errors
from processes import run_python

SURFACE = BuildOptions(mode="surface")


# ------------------------------------------------------------------ float32 meshes


@pytest.mark.parametrize("fmt", ["stl", "ply"])
@pytest.mark.parametrize("extents, d, count", [((0.4, 0.3, 0.2), 0.1, 24),
                                               ((0.4, 0.3, 0.2), 0.05, 192),
                                               ((0.7, 0.3, 0.1), 0.1, 21)])
def test_float32_boxes_tile_exactly(tmp_path, fmt, extents, d, count):
    box = trimesh.creation.box(extents=extents)
    box.apply_translation([1.3, -0.6, 0.1])     # coordinates of several magnitudes
    path = tmp_path / f"box.{fmt}"
    box.export(path)
    mesh = load_mesh(path)
    v = np.asarray(mesh.vertices)
    # the case of the issue: float32 coordinates put an extent just past whole cells
    assert np.array_equal(v.astype(np.float32).astype(np.float64), v)
    assert (np.ptp(v, axis=0) / d - np.round(np.ptp(v, axis=0) / d)).max() > 1e-9
    s = build_sphere_set(mesh, d)
    assert s.count == count
    assert s.sphere_volume_error == pytest.approx(0.0, abs=1e-5)


def test_cell_tolerance_follows_the_precision():
    v64 = np.array([[0.0, 0.0, 0.0], [0.4, 0.3, 0.2]]) + 1e-12
    assert cell_tolerance(v64, 0.1) == 1e-9
    v32 = np.array([[0.0, 0.0, 0.0], [0.4, 0.3, 0.2]], dtype=np.float32).astype(np.float64)
    tol = cell_tolerance(v32, 0.1)
    # 4 float32 ulps of 0.4 m, in cells of 0.1 m: ~1.9e-6, far below a real layer
    assert tol == pytest.approx(4 * np.finfo(np.float32).eps * 0.4 / 0.1, rel=1e-6)
    # an extent a true millionth of a cell longer than 4 cells still gets its 5th layer
    # from a float64 mesh
    box = trimesh.creation.box(extents=(0.4 + 1e-7, 0.3, 0.2))
    assert build_sphere_set(box, 0.1).count == 5 * 3 * 2


def test_cli_counts_an_stl_box(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from dempipe_cli.main import app

    monkeypatch.setenv("DEMPIPE_CACHE_DIR", str(tmp_path / "cache"))
    trimesh.creation.box(extents=(0.4, 0.3, 0.2)).export(tmp_path / "box.stl")
    result = CliRunner().invoke(app, ["spheres", str(tmp_path / "box.stl"), "--diameter", "0.1",
                                      "--mode", "lattice", "--json", "--no-errors"],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)[0]["count"] == 24


def test_cli_shows_both_modes_with_their_errors(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from dempipe_cli.main import app

    monkeypatch.setenv("DEMPIPE_CACHE_DIR", str(tmp_path / "cache"))
    args = ["spheres", "sphere", "--resolution", "6", "--mode", "both"]
    result = CliRunner().invoke(app, args + ["--json"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    rows = {r["mode"]: r for r in json.loads(result.stdout)}
    assert set(rows) == {"lattice", "surface"}
    lat, sur = rows["lattice"], rows["surface"]
    assert sur["count"] > lat["count"] and sur["bump"] < lat["bump"]
    assert 0 < sur["hausdorff"] <= lat["hausdorff"] and sur["build_seconds"] >= 0
    text = CliRunner().invoke(app, args, catch_exceptions=False).stdout.splitlines()
    assert len(text) == 2 and all("Hausdorff" in t and "bump" in t for t in text)
    assert "(surface)" in text[1] and "cache hit" in text[1]
    bad = CliRunner().invoke(app, args + ["-o", str(tmp_path / "x.npz")])
    assert bad.exit_code != 0 and "{mode}" in bad.output
    # --spacing: a wider shell, fewer spheres and a higher bump; the lattice ignores it
    wide = CliRunner().invoke(app, args + ["--spacing", "0.5", "--json"], catch_exceptions=False)
    rows_w = {r["mode"]: r for r in json.loads(wide.stdout)}
    assert rows_w["surface"]["spacing"] == 0.5 and sur["spacing"] == DEFAULT_SPACING
    assert rows_w["surface"]["count"] < sur["count"] and rows_w["surface"]["bump"] > sur["bump"]
    assert rows_w["lattice"]["count"] == lat["count"] and rows_w["lattice"]["spacing"] is None
    bad = CliRunner().invoke(app, args + ["--spacing", "2"])
    assert bad.exit_code == 2 and "--spacing" in bad.output
    # given to a lattice alone (the default mode), it would change nothing: refused
    alone = CliRunner().invoke(app, ["spheres", "sphere", "--resolution", "6", "--spacing", "0.5"])
    assert alone.exit_code == 2 and "--mode surface" in alone.output


# ------------------------------------------------------------------ surface sets


def depth_of(mesh, points, d):
    dist, _ = MeshQueries(mesh.vertices, mesh.faces, d).closest(points)
    return dist


TURNS = {"as built": None, "on its side": (90.0, [1.0, 0.0, 0.0]),
         "turned": (37.0, [0.3, 0.8, 0.5])}


@pytest.mark.parametrize("turn", list(TURNS))
@pytest.mark.parametrize("name", ["sphere", "cylinder", "torus", "box"])
def test_shell_centres_touch_the_surface_from_inside(name, turn):
    # also with the mesh turned: a thin-part ray from a square edge, inwards along one
    # face's normal, runs in the other face's plane, and rounding once made it hit that
    # face at once, putting a "medial" centre on the surface (a cylinder on its side
    # had 4 spheres sticking out by r, which kicked it off the ground as it rolled)
    mesh = build_shape(name)
    if TURNS[turn] is not None:
        angle, axis = TURNS[turn]
        mesh.apply_transform(trimesh.transformations.rotation_matrix(math.radians(angle), axis))
    d = float(mesh.extents.max()) / 8
    s = build_sphere_set(mesh, d, options=SURFACE)
    assert "surface" in s.notes and s.diameter == d
    c = s.centers + s.com
    dist = depth_of(mesh, c, d)
    # every centre is at least r deep (no sphere pokes out); the shell is at exactly r
    shell = np.abs(dist - 0.5 * d) <= 1e-3 * 0.5 * d
    assert np.all(~np.isfinite(dist) | (dist >= 0.5 * d * (1 - 1e-3)))
    assert shell.sum() > 0.6 * s.count
    # evenly spread: no two shell centres closer than the spacing
    sc = c[shell]
    gap = np.linalg.norm(sc[:, None] - sc[None], axis=2) + np.eye(len(sc)) * 1e9
    assert gap.min() >= DEFAULT_SPACING * d * (1 - 1e-9)
    # mass properties are the exact mesh's, whatever the mode
    lat = build_sphere_set(mesh, d)
    assert s.volume == lat.volume
    np.testing.assert_array_equal(s.inertia, lat.inertia)


def test_surface_sets_are_deterministic_and_cached_under_their_own_key(tmp_path):
    mesh = build_shape("pawn")
    d = float(mesh.extents.max()) / 8
    a = build_sphere_set(mesh, d, options=SURFACE)
    b = build_sphere_set(mesh, d, options=SURFACE)
    assert a.key == b.key and a.centers.tobytes() == b.centers.tobytes()
    lattice = build_sphere_set(mesh, d)
    assert lattice.key != a.key
    # the lattice keys are those of before the mode existed (caches stay valid)
    assert BuildOptions().key_text() == repr([("winding_threshold", "0.5")])
    assert BuildOptions(mode="surface", spacing=0.2).key_text() != SURFACE.key_text()
    # the same centres whatever the kernels' thread count: built again with 1 and 2
    out = run_python("""
import hashlib, numba
from dempipe.mesh.shapes import build_shape
from dempipe.spheres.options import BuildOptions
from dempipe.spheres.sphere_set import build_sphere_set
mesh = build_shape("pawn")
for n in (1, 2):
    numba.set_num_threads(n)
    s = build_sphere_set(mesh, float(mesh.extents.max()) / 8, options=BuildOptions(mode="surface"))
    print(hashlib.sha256(s.centers.tobytes()).hexdigest())
""", threads=2)
    assert out.split() == [hashlib.sha256(a.centers.tobytes()).hexdigest()] * 2
    cache = SphereCache(tmp_path)
    build_sphere_set(mesh, d, options=SURFACE, cache=cache)
    hit = build_sphere_set(mesh, d, options=SURFACE, cache=cache)
    assert hit.centers.tobytes() == a.centers.tobytes() and hit.notes == a.notes


@pytest.mark.parametrize("bad", [dict(mode="voxel"), dict(mode="surface", spacing=0.0),
                                 dict(mode="surface", spacing=2.0), dict(spacing=True)])
def test_bad_options(bad):
    with pytest.raises(ShapeError):
        BuildOptions(**bad)


def test_thin_plate_gets_one_row_on_its_medial_plane():
    plate = trimesh.creation.box(extents=(0.1, 0.08, 0.004))     # thinner than d
    d = 0.01
    s = build_sphere_set(plate, d, options=SURFACE)
    c = s.centers + s.com
    assert np.abs(c[:, 2]).max() < 1e-9
    assert np.abs(c[:, :2]).max(axis=0) == pytest.approx([0.05, 0.04], abs=0.5 * d)
    gap = np.linalg.norm(c[:, None] - c[None], axis=2) + np.eye(len(c))
    assert gap.min() >= DEFAULT_SPACING * d * (1 - 1e-9)


def _overlapping_boxes():
    """Two closed boxes 40 mm across overlapping by half, one mesh (trimesh calls it
    watertight): inside both, a ray crosses an even number of faces."""
    a = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    b = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    b.apply_translation([0.02, 0.01, 0.005])
    return trimesh.util.concatenate([a, b])


def _open_box():
    """A box with one face's two triangles gone: not closed."""
    m = trimesh.creation.box(extents=(0.04, 0.03, 0.02))
    return trimesh.Trimesh(m.vertices, m.faces[2:], process=False)


@pytest.mark.parametrize("name", ["rook", "king", "torus", "overlapping boxes", "open box"])
def test_inside_is_the_winding_numbers(name):
    # MeshQueries.inside against the generalized winding number, on a lattice of points
    # through and around the body (off its surface) and far outside its grid: crossings
    # nearly parallel to the ray count (the rook's crenels), each triangle once though
    # it is binned in several cells, each with its sign (two overlapping parts: inside
    # both is inside), and a mesh with a hole is asked the winding number itself.
    from dempipe.mesh.winding import inside_mask

    mesh = {"overlapping boxes": _overlapping_boxes, "open box": _open_box}.get(
        name, lambda: build_shape(name))()
    d = float(mesh.extents.max()) / 12
    lo, hi = mesh.bounds[0] - d, mesh.bounds[1] + d
    axes = [np.arange(a, b, 0.37 * d) for a, b in zip(lo, hi)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    pts = np.vstack([pts, mesh.bounds[1] + 10 * d, mesh.bounds[0] - 10 * d,
                     [mesh.bounds[0][0], mesh.bounds[0][1], mesh.bounds[1][2] + 10 * d]])
    q = MeshQueries(mesh.vertices, mesh.faces, d)
    assert q.closed == (name != "open box")
    near, _ = q.closest(pts, d)
    pts = pts[~(near < 1e-6 * d)]
    assert len(pts) > 2000
    inside = q.inside(pts)
    np.testing.assert_array_equal(inside, inside_mask(mesh, pts))
    assert 0.05 < inside.mean() < 0.95


def _edge_body(angle):
    """A thick body with an edge of inside ``angle`` [°]: a prism on an isosceles
    triangle (its apex angle, 50 mm legs, 50 mm long), or for 78.7° a frustum (radii
    25 and 15 mm, 50 mm long: its base rim's inside angle); d = 50 mm / 12."""
    import manifold3d

    if angle < 75.0:
        a = math.radians(angle)
        tri = [[0.0, 0.0], [0.05, 0.0], [0.05 * math.cos(a), 0.05 * math.sin(a)]]
        m = manifold3d.CrossSection([tri]).extrude(0.05).to_mesh()
    else:
        m = manifold3d.Manifold.cylinder(0.05, 0.025, 0.015, 40).to_mesh()
    return trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts))


@pytest.mark.parametrize("angle", [30.0, 45.0, 60.0, 78.7])
def test_an_acute_edge_takes_whichever_spheres_err_less(angle):
    # The balls of d inside a thick part leave an edge of inside angle θ uncovered by
    # r (1/sin(θ/2) - 1): 0.29 d at 78.7°, r at 60°, 0.8 d at 45°. A medial sphere at
    # the edge, where the ray inwards meets the next face within d, covers it but sticks
    # out of the mesh by up to r. The set takes the smaller error: at the frustum's base
    # rim no sphere sticks out (one that did would start a frustum laid on its side up
    # to half a sphere deep in the ground), and no edge or corner is further than r from
    # the spheres: the 30° and 45° edges take medial spheres, and the 60° prism's
    # corners, where its edges meet the caps r(√5 - 1) = 0.62 d from the offset's
    # balls, take them too. Both up to the bumps between neighbours (SURFACE_BUMP).
    # Measured, the largest error: 30°, 45° 0.50 d; 60° 0.54 d; 78.7° 0.35 d.
    mesh = _edge_body(angle)
    d = 0.05 / 12
    r = 0.5 * d
    s = build_sphere_set(mesh, d, options=SURFACE)
    c = s.centers + s.com
    from dempipe.mesh.winding import inside_mask

    depth, _ = MeshQueries(mesh.vertices, mesh.faces, d).closest(c, d)
    depth = np.where(np.isfinite(depth), depth, d)                # (beyond d: d)
    poke = np.where(inside_mask(mesh, c), r - depth, r + depth)   # past the surface
    rounding = r * (1.0 / math.sin(math.radians(0.5 * angle)) - 1.0)
    if rounding < r:
        assert poke.max() < 1e-3 * d
    e = envelope_errors(mesh, c, d)
    assert e.hausdorff <= min(rounding, r) + SURFACE_BUMP * d


@pytest.mark.parametrize("name", ["pawn", "bishop", "rook", "knight", "queen", "king"])
def test_a_chess_piece_stands_on_its_foot_at_the_examples_resolution(name):
    # At 6 spheres across the pawn's height (the examples'), a piece's plinth is a lip
    # about 0.2 d tall: medial spheres on it would reach 0.31-0.38 d below the foot
    # and stand the piece that far above the floor in every frame; the offset leaves
    # the lip's edge about as far uncovered, and is taken (offset_points). The lowest
    # sphere is on the foot's plane. (At 12 across the pawn's plinth, 0.48 d tall, is
    # thin enough that its medial row errs less: 0.25 d below.)
    mesh = build_shape(name)
    d = 0.05 / 6
    s = build_sphere_set(mesh, d, options=SURFACE)
    lowest = float((s.centers[:, 2] + s.com[2]).min()) - 0.5 * d
    assert lowest == pytest.approx(float(mesh.vertices[:, 2].min()), abs=1e-3 * d)


# ------------------------------------------------------------------ envelope errors


def test_envelope_errors_of_an_exact_lattice_box():
    # 4 x 4 x 4 spheres tiling a cube: the corner sphere is sqrt(3) r from the corner,
    # so the Hausdorff distance is r (sqrt(3) - 1) = 0.366 d; no sphere pokes out, and
    # the ideal envelope (balls of radius r inside the cube) rounds the corner the same
    d = 0.01
    box = trimesh.creation.box(extents=(4 * d, 4 * d, 4 * d))
    s = build_sphere_set(box, d)
    e = envelope_errors(mesh_for_errors(box), s.centers + s.com, d)
    assert e.hausdorff == pytest.approx(0.5 * d * (math.sqrt(3) - 1), rel=1e-6)
    # (the ideal's balls come from samples EDGE_INSET off the edges: a few 1e-6 of it)
    assert e.rounding == pytest.approx(0.5 * d * (math.sqrt(3) - 1), rel=1e-5)
    # the faces' dips: a face point above the middle of 4 spheres is sqrt(r^2 + d^2/2)
    # from their centres, r (sqrt(3) - 1) from the spheres, all of it a bump (sampled)
    assert 0.3 * d < e.bump <= 0.5 * d * (math.sqrt(3) - 1) * (1 + 1e-6)


def test_envelope_errors_of_one_ball():
    ball = build_shape("sphere", diameter=0.01, subdivisions=4)
    e = envelope_errors(mesh_for_errors(ball), np.zeros((1, 3)), 0.01)
    # the icosphere's facets are within 0.1 % of its radius: one sphere is the ball
    assert e.hausdorff < 2e-3 * 0.01 and e.bump < 2e-3 * 0.01


#: Bump bound of the surface mode at the default spacing, as a fraction of d: the
#: envelope between neighbours dips by r - sqrt(r^2 - rho^2) ~ rho^2 / d for a hole of
#: radius rho <= spacing (0.3 d: 0.09 d), plus the sampled mesh's facets.
SURFACE_BUMP = 0.15


@pytest.mark.parametrize("name", ["sphere", "cylinder", "torus", "box"])
def test_surface_mode_is_closer_to_the_mesh(name):
    mesh = build_shape(name)
    d = float(mesh.extents.max()) / 8
    rm = mesh_for_errors(mesh)
    lat = build_sphere_set(mesh, d)
    sur = build_sphere_set(mesh, d, options=SURFACE)
    el = envelope_errors(rm, lat.centers + lat.com, d)
    es = envelope_errors(rm, sur.centers + sur.com, d)
    assert es.bump <= SURFACE_BUMP * d
    assert es.bump < 0.5 * el.bump
    assert es.hausdorff <= el.hausdorff + 1e-12


# ------------------------------------------------------------------ scene key


SCENE = """
[simulation]
sphere_diameter = 0.004
{sim}
[shapes.ball]
builtin = "sphere"
{shape}
[shapes.brick]
builtin = "box"
[[bodies]]
name = "b"
shape = ["ball", "brick"]
count = 2
layout = "grid"
origin = [0.0, 0.0, 0.05]
dims = [2, 1, 1]
spacing = [0.1, 0.1, 0.1]
[[colliders]]
type = "plane"
"""


def test_scene_key_per_scene_and_per_shape(tmp_path):
    sc = parse_scene(SCENE.format(sim="", shape=""), tmp_path / "s.toml")
    assert sc.simulation.spheres is None and sphere_options(sc, "ball").mode == DEFAULT_MODE
    sc = parse_scene(SCENE.format(sim='spheres = "surface"', shape='spheres = "lattice"'),
                     tmp_path / "s.toml")
    assert sphere_options(sc, "ball").mode == "lattice"
    assert sphere_options(sc, "brick").mode == "surface"
    assert sphere_options(sc, "ball", Overrides(spheres="surface")).mode == "surface"
    model = build_model(sc)
    notes = {s.name: s.sphere_set.notes for s in model.shapes}
    assert "surface" in notes["brick"] and "surface" not in notes["ball"]


def test_surface_spacing_per_scene_and_per_shape(tmp_path):
    # the scene's surface_spacing reaches every surface set, a shape's own wins; the
    # sets are those the library builds with that spacing (wider: fewer spheres,
    # every centre at least the spacing from the next), and a lattice ignores it
    sc = parse_scene(SCENE.format(sim='spheres = "surface"\nsurface_spacing = 0.5',
                                  shape="surface_spacing = 0.35"), tmp_path / "s.toml")
    assert sphere_options(sc, "ball").spacing == 0.35
    assert sphere_options(sc, "brick").spacing == 0.5
    cache = SphereCache(tmp_path / "cache")
    model = build_model(sc, cache=cache)
    sets = {s.name: s.sphere_set for s in model.shapes}
    for name, spacing in (("ball", 0.35), ("brick", 0.5)):
        mesh = build_shape("sphere" if name == "ball" else "box")
        want = build_sphere_set(mesh, 0.004, cache=cache,
                                options=BuildOptions(mode="surface", spacing=spacing))
        np.testing.assert_array_equal(sets[name].centers, want.centers)
        default = build_sphere_set(mesh, 0.004, cache=cache,
                                   options=BuildOptions(mode="surface"))
        assert len(want.centers) < 0.8 * len(default.centers)
    # (the interior's lattice cells are d apart and deeper than d: r from the shell)
    c = sets["brick"].centers
    gaps = np.linalg.norm(c[:, None] - c[None], axis=2) + np.eye(len(c))
    assert gaps.min() >= 0.5 * 0.004 * (1 - 1e-9)
    sc = parse_scene(SCENE.format(sim="surface_spacing = 0.5", shape=""), tmp_path / "s.toml")
    lattice = {s.name: s.sphere_set for s in build_model(sc, cache=cache).shapes}["brick"]
    plain = build_sphere_set(build_shape("box"), 0.004, cache=cache)
    np.testing.assert_array_equal(lattice.centers, plain.centers)


def test_auto_gives_round_shapes_surface_sets_and_boxes_lattices(tmp_path):
    # spheres = "auto": the ball (99 % of its area off the lattice's axes) gets a
    # surface set and rolls, the brick (0 %) keeps its lattice; a shape's own key wins.
    sc = parse_scene(SCENE.format(sim='spheres = "auto"', shape=""), tmp_path / "s.toml")
    model = build_model(sc)
    notes = {s.name: s.sphere_set.notes for s in model.shapes}
    assert "surface" in notes["ball"] and "surface" not in notes["brick"]
    sc = parse_scene(SCENE.format(sim='spheres = "auto"', shape='spheres = "lattice"'),
                     tmp_path / "s.toml")
    assert "surface" not in {s.name: s.sphere_set.notes for s in build_model(sc).shapes}["ball"]
    sc = parse_scene(SCENE.format(sim="", shape='spheres = "auto"'), tmp_path / "s.toml")
    assert "surface" in {s.name: s.sphere_set.notes for s in build_model(sc).shapes}["ball"]


@pytest.mark.parametrize("sim", ['spheres = "auto"', 'spheres = "surface"'])
def test_a_fractured_shape_keeps_its_lattice(tmp_path, sim):
    # a fractured shape's pieces share one lattice: the scene's "auto" or "surface"
    # (or an override's, as `dempipe report --spheres` gives) leaves it that, where the
    # shape's own "surface" is refused (tests/cli/test_cli_fracture.py); the shape
    # beside it takes the scene's
    text = SCENE.format(sim=sim, shape="fracture = { pieces = 3 }")
    sc = parse_scene(text, tmp_path / "s.toml")
    assert sphere_options(sc, "ball").mode == "lattice"
    assert sphere_options(sc, "ball", Overrides(spheres="surface")).mode == "lattice"
    if "surface" in sim:
        assert sphere_options(sc, "brick").mode == "surface"


@pytest.mark.parametrize("sim, shape, where", [
    ('spheres = "round"', "", "simulation.spheres"),
    ("spheres = 1", "", "simulation.spheres"),
    ("", 'spheres = "voxels"', "shapes.ball.spheres"),
    ("surface_spacing = 0.01", "", "simulation.surface_spacing"),
    ("", "surface_spacing = 2", "shapes.ball.surface_spacing"),
    ('surface_spacing = "wide"', "", "simulation.surface_spacing"),
])
def test_scene_key_errors(tmp_path, sim, shape, where):
    with pytest.raises(SceneError) as exc:
        parse_scene(SCENE.format(sim=sim, shape=shape), tmp_path / "s.toml")
    msg = str(exc.value)
    assert where in msg and "s.toml" in msg
    assert "surface" in msg or "lattice" in msg or "fraction of the sphere diameter" in msg


# ------------------------------------------------------------------ report sweep


REPORT_SCENE = """
[output]
fps = 24
duration = 0.1
[simulation]
resolution = 4
[shapes.ball]
builtin = "sphere"
[[bodies]]
name = "balls"
shape = "ball"
layout = "grid"
origin = [0.0, 0.0, 0.03]
dims = [2, 1, 1]
spacing = 0.06
velocity = [0.2, 0.0, 0.0]
[[colliders]]
type = "plane"
"""


@pytest.mark.slow
def test_report_sweeps_the_mode(tmp_path):
    import csv

    from dempipe.report.results import ReportError
    from dempipe.report.runs import Sweep, recommend, run_report

    scene = tmp_path / "balls.toml"
    scene.write_text(REPORT_SCENE)
    sweep = Sweep(resolutions=(4,), dt_factors=(1.0,), stiffness_factors=(1.0,), duration=0.1,
                  plots=False, sphere_modes=("lattice", "surface"))
    result = run_report(scene, tmp_path / "out", sweep, cache=SphereCache(tmp_path / "c"))
    assert result.reference.mode == "surface"
    with open(tmp_path / "out" / "report.csv", newline="") as f:
        table = {r["sphere_mode"]: r for r in csv.DictReader(f)}
    assert set(table) == {"lattice", "surface"}
    lat, sur = table["lattice"], table["surface"]
    assert int(sur["spheres"]) > int(lat["spheres"])
    assert float(sur["envelope_bump_d"]) < float(lat["envelope_bump_d"])
    md = (tmp_path / "out" / "report.md").read_text()
    assert "## Sphere-set modes" in md and "r4 dt×1 k×1 lattice" in md
    # the incline: a ball of 4 spheres across rolls down 20° within 2 % of 5/7 g
    # (sin θ − μ_r cos θ) in both modes, its wall contacts through its mesh's inscribed
    # balls (docs/spheres.md "Rolling"; measured 0.0014 surface, 0.0088 lattice: before
    # them the lattice ball, a polyhedron, was off by 0.32)
    assert float(sur["incline"]) < 0.02 and float(lat["incline"]) < 0.02
    assert "incline roll" in md
    runs = {u.mode: u for u in result.runs}
    runs["surface"].reference = False            # as if a finer run were the reference
    assert recommend(result.runs, tolerance=1e9) is min(runs.values(), key=lambda u: u.wall_s)
    # a rolling tolerance between the two rules the lattice out
    assert recommend(result.runs, tolerance=1e9, rolling_tolerance=0.005) is runs["surface"]
    with pytest.raises(ReportError, match="--spheres"):
        run_report(scene, tmp_path / "o2", Sweep(plots=False, sphere_modes=("voxel",)))
