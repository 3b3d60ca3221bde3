"""Inscribed balls: a surface set meets a wall through the largest ball its surface's
curvature allows at each shell sphere, and a lattice set through its mesh's
(spheres/inscribed.py, contacts.inscribed_wall).

What must hold: the balls are the body's own surface where it is round (a ball's are
the ball), stay inside the mesh where it is flat or has edges, and a body dropped on
its edges, rims and round parts never gains energy through them; a ball then rolls
at 5/7 g sin θ past the speed where its envelope's bumps made it hop (tests/sim/
test_rolling.py, docs/spheres.md "Rolling").
"""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dempipe.mesh.shapes import build_shape
from dempipe.scene.build import build_model
from dempipe.scene.load import parse_scene
from dempipe.sim.simulator import Simulator
from dempipe.spheres.inscribed import (COVERED, SHRINK_SLACK, WALL_SPACING, WALL_TOLERANCE,
                                       inscribed_tori, lattice_tori, wall_cover,
                                       wall_tori)
from dempipe.spheres.options import BuildOptions
from dempipe.spheres.sphere_set import build_sphere_set, diameter_for_resolution
from bodies import body_energy

G = 9.81


def _balls(name, across, **params):
    mesh = build_shape(name, **params)
    size = float((mesh.bounds[1] - mesh.bounds[0]).max())
    d = size / across
    ss = build_sphere_set(mesh, d, name=f"inscribed-{name}", options=BuildOptions(mode="surface"))
    verts = np.asarray(mesh.vertices) - ss.com
    ins = inscribed_tori(ss.centers, d, verts, mesh.faces)
    return mesh, ss, d, ins


def _torus_points(ss, ins, rows, n=24):
    """Points on the tori of ``rows`` (body frame): n around the circle by n around the
    tube, the circle's at radius a about the axis through the torus's centre."""
    c = np.asarray(ss.centers)[rows]
    o = c + ins[rows, 0:3]
    t = ins[rows, 3:6]
    u = ins[rows, 6:9]
    a = ins[rows, 9][:, None, None]
    b = ins[rows, 10][:, None, None]
    ring = np.linalg.norm(t, axis=1) > 0.5
    # a ball's rows have no axis: any frame
    t = np.where(ring[:, None], t, [[0.0, 0.0, 1.0]])
    u = np.where(ring[:, None], u, [[1.0, 0.0, 0.0]])
    w = np.cross(t, u)
    phi = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    circle = o[:, None, :] + a * (np.cos(phi)[None, :, None] * u[:, None, :]
                                  + np.sin(phi)[None, :, None] * w[:, None, :])
    # the tube: a ball of radius b about each circle point, sampled along the axes
    dirs = np.concatenate([np.eye(3), -np.eye(3)])
    return (circle[:, :, None, :] + b[..., None] * dirs[None, None, :, :]).reshape(-1, 3)


@pytest.mark.parametrize("across", [8, 16])
def test_a_balls_inscribed_tori_are_the_ball(across):
    # the built-in ball (an icosphere of 5,120 faces, 0.1 m across): most shell spheres
    # carry the ball, or where the fitted curvatures differ a little a torus close to
    # it: the tube's centre under the sphere within the tube's shortfall (+0.1 d) of
    # the ball's centre, so the torus touches the mesh where its sphere does and stays
    # inside it, and the torus's outer radius a + b (its curvature along the circle)
    # near the ball's. Measured: 89 % / 77 % of the set at 8 / 16 across, a + b within
    # 3 % / 4 % (median); asked 60 % and 10 %
    mesh, ss, d, ins = _balls("sphere", across, diameter=0.1)
    grown = np.any(ins[:, 0:3] != 0.0, axis=1)
    assert grown.mean() > 0.6
    a, b = ins[grown, 9], ins[grown, 10]
    assert np.median(a + b) == pytest.approx(0.05, rel=0.1)
    tube = np.asarray(ss.centers)[grown] + ins[grown, 0:3] + a[:, None] * ins[grown, 6:9]
    assert np.all(np.linalg.norm(tube, axis=1) <= 0.05 - b + 0.1 * d)


@pytest.mark.parametrize("name, params", [
    ("box", dict(size=[0.1, 0.06, 0.04])),
    ("cylinder", dict(diameter=0.1, height=0.05)),
])
def test_balls_and_rings_stay_inside_flat_faces_and_edges(name, params):
    # the box's balls and the cylinder's balls and rings reach no further out of the
    # mesh than 0.1 d: SHRINK_SLACK d (the slack the fit over a faceted offset surface
    # is given) and the bulge of a ball held off centres a spacing h apart between
    # them (measured 0.08 d on the cylinder, 8 across; a wall contact never takes more
    # than REACH = 0.05 d beyond the sphere's own): points all round each
    # torus against the mesh's bounds, and for the cylinder from its axis
    mesh, ss, d, ins = _balls(name, 8, **params)
    grown = np.flatnonzero(np.any(ins[:, 0:3] != 0.0, axis=1))
    assert grown.size > 0.1 * len(ins)
    pts = _torus_points(ss, ins, grown)
    lo, hi = mesh.bounds - ss.com
    slack = 2.0 * SHRINK_SLACK * d
    assert np.all(pts >= lo - slack) and np.all(pts <= hi + slack)
    if name == "cylinder":
        assert np.linalg.norm(pts[:, :2], axis=1).max() <= 0.05 + slack
        # the side's spheres near a cap roll on rings about the axis
        assert np.count_nonzero(ins[:, 9] > 0.0) > 0


def _wall_reach(c, ins, d, u):
    """How far each sphere's wall contact reaches along each direction u (N, K) [m]: its
    torus's support, at most its own sphere's plus its reach (contacts.inscribed_wall)."""
    au = ins[:, 3:6] @ u.T
    torus = (c + ins[:, 0:3]) @ u.T + ins[:, 9, None] * np.sqrt(
        np.clip(1.0 - au * au, 0.0, None)) + ins[:, 10, None]
    return np.minimum(torus, c @ u.T + 0.5 * d + ins[:, 11, None])


@pytest.mark.parametrize("name, across, share", [
    ("box", 8, 0.6), ("box", 16, 0.55), ("sphere", 8, 0.5), ("sphere", 16, 0.5),
    ("cylinder", 8, 0.5), ("cylinder", 16, 0.5), ("pawn", 16, 0.45), ("torus", 16, 0.45)])
def test_spheres_left_out_of_walls_leave_the_envelope_walls_meet(name, across, share):
    # a plane in any of 4,000 random directions (not those wall_cover tested) is reached
    # as deep by the spheres kept as by all of them, within 3 WALL_TOLERANCE = 0.006 d:
    # wall_cover tests finitely many directions, and a sphere's reach peaks between
    # them by up to 0.004 d (measured: the torus at 16 across, a cylinder at 4; 0-0.003
    # d elsewhere), under the 0.013 d dips of a bare surface envelope (a ball 8 across)
    # that the tori are there to remove
    mesh, ss, d, ins = _balls(name, across)
    c = np.asarray(ss.centers)
    covered = wall_cover(c, ins, d, np.asarray(mesh.vertices) - ss.com, mesh.faces) > 0.0
    u = np.random.default_rng(7).normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    reach = _wall_reach(c, ins, d, u)
    assert (reach.max(axis=0) - reach[~covered].max(axis=0)).max() <= 3 * WALL_TOLERANCE * d
    # most of a flat or gently curved shell is left out (measured: 0.49-0.69)
    assert covered.mean() >= share
    # and a wall of any extent still finds a kept sphere within 2 WALL_SPACING d
    gap, _ = cKDTree(c[~covered]).query(c[covered])
    assert gap.max() <= 2.0 * WALL_SPACING * d


def test_a_foot_meets_walls_through_its_outer_polygon():
    # a rook at the chess example's resolution (6 spheres across a pawn's height): its
    # flat foot stands on the spheres wall_cover keeps under it, and each is a contact
    # at every step the piece stands. The foot's outer polygon must stay (the
    # footprint the piece tips over); its middle needs only what a finite wall needs.
    # Measured: 9 of the 27 spheres under the foot, where one greedy round in the
    # set's order kept 17 (four in the middle, then the polygon its neighbours could
    # not cover)
    from scipy.spatial import ConvexHull

    mesh = build_shape("rook")
    d = diameter_for_resolution(build_shape("pawn"), 6)
    ss = build_sphere_set(mesh, d, name="foot-rook", options=BuildOptions(mode="surface"))
    c = np.asarray(ss.centers)
    verts = np.asarray(mesh.vertices) - ss.com
    covered = wall_cover(c, inscribed_tori(c, d, verts, mesh.faces), d, verts,
                         mesh.faces) > 0.0
    foot = c[:, 2] < c[:, 2].min() + 0.005 * d
    assert np.count_nonzero(foot) == 27
    kept = foot & ~covered
    assert np.count_nonzero(kept) <= 10
    # the footprint: the kept spheres' polygon is the foot's outer one (measured: seven
    # of its octagon's eight, 94.9 % of its area), not the middle's (the spheres
    # within 0.8 d of the axis: 59 %)
    area = ConvexHull(c[foot, :2]).volume
    assert ConvexHull(c[kept, :2]).volume >= 0.93 * area


def test_a_body_lists_the_spheres_walls_meet_first():
    # a body's slots follow its spheres' order, so the Model puts the spheres walls
    # meet first (then those wall_cover leaves out, each part in the set's order):
    # a resting face's contacts then lie together in memory. The same spheres, the
    # tori rows moved with them
    text = SLIDE.format(mode="surface").replace('builtin = "sphere"\ndiameter = 0.1',
                                                'builtin = "rook"\nheight = 0.05')
    model = build_model(parse_scene(text, "rook.toml"))
    shape = model.shapes[0]
    ins = np.asarray(model.sphere_inscribed)
    assert 0 < np.count_nonzero(ins[:, COVERED]) < ins.shape[0]
    assert np.all(np.diff(ins[:, COVERED]) >= 0.0)      # 0 (meets walls), then 1
    assert np.array_equal(model.sphere_offset, shape.contact_centers)
    # the same spheres and rows as the set's order, moved together
    c = np.asarray(shape.sphere_set.centers)
    assert c.shape[0] == ins.shape[0]                   # a shell: every sphere in contact
    rows = wall_tori(c, model.diameter, shape.vertices, shape.faces, surface=True)
    first = np.argsort(rows[:, COVERED], kind="stable")
    assert np.array_equal(model.sphere_offset, c[first])
    assert np.array_equal(ins, rows[first])


def test_edges_and_corners_keep_their_own_spheres():
    # a box's edge and corner spheres (closest mesh point on an edge: a quadric fitted
    # over two faces is no surface) carry nothing: every grown sphere's ball centre is
    # inward along a face's normal, within a few degrees
    mesh, ss, d, ins = _balls("box", 8, size=[0.1, 0.1, 0.1])
    grown = np.any(ins[:, 0:3] != 0.0, axis=1)
    a = ins[grown, 0:3]
    n = -a / np.linalg.norm(a, axis=1)[:, None]
    assert np.abs(n).max(axis=1).min() > math.cos(math.radians(12.0))


def _support(ins, centers, m):
    """The farthest any row's torus reaches along the unit direction m (body frame [m]):
    o·m + a |m across the axis| + b (a ball's rows have a = 0)."""
    o = centers + ins[:, 0:3]
    mt = ins[:, 3:6] @ m
    across = np.sqrt(np.maximum(0.0, 1.0 - mt * mt))
    return float(np.max(o @ m + ins[:, 9] * across + ins[:, 10]))


@pytest.mark.parametrize("name, params, across, axis", [
    ("sphere", dict(diameter=0.1), 8, None),
    ("cylinder", dict(diameter=0.1, height=0.1), 8, 2),
    ("cylinder", dict(diameter=0.1, height=0.05), 8, 2),
    ("torus", dict(major_radius=0.035, minor_radius=0.015), 16, 2),
], ids=["ball", "cylinder", "disc", "torus"])
def test_a_lattice_meets_walls_as_its_mesh(name, params, across, axis):
    # a lattice set's spheres stick out of its mesh (up to 0.41 d on these) and dip
    # under it between them; what each meets a wall with (lattice_tori: the mesh's
    # torus where the sphere is outermost, else the ball of its own depth) stays inside
    # the mesh in every direction, and reaches it in every direction the body rolls
    # (across its axis). Support functions over 400 directions against the mesh's:
    # measured out of it at most -0.0002 d, short of it at most 0.006 d (ball, cylinder,
    # disc) and 0.041 d (the torus's rim); asked 0.01 d (the facets) and 0.05 d (REACH)
    mesh = build_shape(name, **params)
    d = float((mesh.bounds[1] - mesh.bounds[0]).max()) / across
    ss = build_sphere_set(mesh, d, name=f"lattice-{name}")
    c = np.asarray(ss.centers)
    v = np.asarray(mesh.vertices) - ss.com
    ins = lattice_tori(c, d, v, mesh.faces)
    assert np.count_nonzero(np.any(ins[:, 0:3] != 0.0, axis=1)) > 0.15 * len(c)
    dirs = np.random.default_rng(1).normal(size=(400, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    assert max(np.max(c @ m) + 0.5 * d - np.max(v @ m) for m in dirs) > 0.25 * d
    assert max(_support(ins, c, m) - np.max(v @ m) for m in dirs) < 0.01 * d
    roll = dirs.copy()
    if axis is not None:
        roll[:, axis] = 0.0
        roll /= np.linalg.norm(roll, axis=1)[:, None]
    assert max(np.max(v @ m) - _support(ins, c, m) for m in roll) < 0.05 * d


def test_a_lattice_with_no_round_surface_keeps_its_spheres():
    # the quickstart's pawn at 6 spheres across its height: no fit follows a surface so
    # coarse, and the set meets walls with its own spheres, bit for bit as before
    mesh = build_shape("pawn", height=0.05)
    d = 0.05 / 6
    ss = build_sphere_set(mesh, d, name="lattice-pawn")
    ins = lattice_tori(ss.centers, d, np.asarray(mesh.vertices) - ss.com, mesh.faces)
    assert np.all(ins[:, 0:10] == 0.0) and np.all(ins[:, 10] == 0.5 * d)


SLIDE = """
[output]
fps = 200
duration = 0.3
[simulation]
sphere_diameter = 0.0125
sleeping = false
spheres = "{mode}"
[materials.ice]
density = 900.0
restitution = 0.5
friction = 0.0
[shapes.ball]
builtin = "sphere"
diameter = 0.1
[[bodies]]
name = "b"
shape = "ball"
material = "ice"
position = [0.0, 0.0, 0.06]
velocity = [0.5, 0.0, -0.5]
rotation = [0.9238795325112867, 0.0, 0.3826834323650898, 0.0]
[[colliders]]
type = "plane"
material = "ice"
"""


@pytest.mark.parametrize("mode", ["lattice", "surface"])
def test_a_frictionless_ball_bounces_without_spinning(mode):
    # a frictionless ball (the kernels without friction) lands turned, sliding at
    # 0.5 m/s: its wall forces act at its tori's lowest points, along lines through
    # the ball's centre, so they turn it (almost) not at all. The torque each force
    # has about its sphere's centre (its torus's arm) must reach the body: without it
    # the same ball spun up to 6.7 rad/s (lattice) and 1.5 rad/s (surface). Measured
    # 0.054 and 0.057 rad/s (its balls' centres are off the body's by the mesh's
    # facets); asked 0.2 rad/s, against 10 rad/s for a ball rolling at 0.5 m/s
    model = build_model(parse_scene(SLIDE.format(mode=mode), "slide.toml"))
    assert model.sphere_inscribed.shape[0] > 0
    sim = Simulator(model, specialize=True)         # the kernels without friction
    assert not sim.backend.flags[0]
    fr = sim.advance(model.initial_state())
    assert fr.x[:, 0, 2].min() < 0.0501             # it reached the plane
    assert np.abs(fr.w[:, 0]).max() < 0.2


DROP = """
[output]
fps = 240
duration = {duration}
[simulation]
{sets}
sleeping = false
[materials.wood]
density = 700.0
restitution = 0.5
friction = 0.6
rolling_friction = 0.0
[shapes.s]
{shape}
[[bodies]]
name = "b"
shape = "s"
material = "wood"
position = [0.0, 0.0, {z}]
rotation = {rotation}
velocity = [0.4, 0.2, 0.0]
angular_velocity = [3.0, -5.0, 2.0]
[[colliders]]
type = "plane"
material = "wood"
"""


PAWN = 'builtin = "pawn"\nheight = 0.05'
CYLINDER = 'builtin = "cylinder"\ndiameter = 0.1\nheight = 0.05'
SURFACE = 'resolution = 8\nspheres = "surface"'


@pytest.mark.parametrize("sets, shape", [
    (SURFACE.replace("8", "12"), PAWN),      # at 8 its head (2.9 d) has no fit
    *((SURFACE, shape) for shape in (
        'builtin = "knight"\nheight = 0.06', CYLINDER,
        'builtin = "torus"\nmajor_radius = 0.03\nminor_radius = 0.02',
        'builtin = "sphere"\ndiameter = 0.1')),
    *(("", shape) for shape in (PAWN, 'builtin = "rook"\nheight = 0.056', CYLINDER)),
], ids=["surface-pawn", "surface-knight", "surface-cylinder", "surface-torus",
        "surface-ball", "default-pawn", "default-rook", "default-cylinder"])
def test_dropped_spinning_bodies_never_gain_energy(tmp_path, sets, shape):
    # dropped from 0.1 m above its size, turned 40° about a tilted axis, sliding and
    # spinning: it lands on rims, edges and round parts, tumbles and rolls on the plane
    # for 1.5 s. Its energy (kinetic + potential; the springs' is left out, so it dips
    # in a contact and comes back) never rises above the most it had before, to 1e-6 of
    # the drop's energy per frame (the elastic energy still stored at a frame's end).
    # Surface sets 8 across (the pawn 12), and the defaults (a lattice, 12 across), where these shapes
    # meet the plane through their tori and their rims' rings (inscribed.rims), held by
    # many spheres each, which take their lowest point or, a rim lying flat, the point
    # under themselves (pairing.RIM_TIE). Measured: no rise at the defaults
    a = math.radians(40.0)
    axis = np.array([1.0, 0.6, 0.2]) / np.linalg.norm([1.0, 0.6, 0.2])
    q = [math.cos(a / 2)] + list(math.sin(a / 2) * axis)
    text = DROP.format(sets=sets, duration=1.5, shape=shape, z=0.15,
                       rotation="[" + ", ".join(repr(float(c)) for c in q) + "]")
    model = build_model(parse_scene(text, tmp_path / "drop.toml"))
    t = model.sphere_inscribed
    assert t.shape[0] > 0
    if not sets:
        assert np.count_nonzero((t[:, 9] > 0.0) & (t[:, 10] == 0.0)) > 10    # rim holders
    frames = Simulator(model).advance(model.initial_state())
    energy = body_energy(model, frames, G)
    scale = energy[0] - energy.min()
    assert np.all(np.diff(np.maximum.accumulate(energy)) <= 1e-6 * scale)
    assert energy[-1] < energy[0]
