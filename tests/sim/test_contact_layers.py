"""Surface spheres for contact: which spheres are buried, the
overlap bound that makes leaving them out exact, and that the motion does not change.
"""

import itertools
import math
import textwrap

import numpy as np
import pytest

from bodies import box_set
from dempipe.errors import SceneError, ShapeError
from dempipe.sim.materials import Material
from dempipe.sim.model import CONTACT_LAYERS
from dempipe.sim.builder import ModelBuilder
from dempipe.spheres.sphere_set import SphereSet, surface_mask
from dempipe.scene.load import load_scene, parse_scene
from dempipe.pipeline.check import analyze_scene

D = 0.01
NEIGHBOURS = np.array([o for o in itertools.product((-1, 0, 1), repeat=3) if any(o)])


def lattice(shape, d=D, offset=(0.0031, -0.0017, 0.0005)):
    """Centres of a solid nx × ny × nz block, lattice order (x fastest)."""
    nx, ny, nz = shape
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], 1) * d + np.asarray(offset)


def brute_force_buried(centers, d, layers):
    """Reference: a sphere is buried when every site within Chebyshev `layers` is a sphere."""
    ijk = {tuple(v) for v in np.rint(centers / d).astype(int)}
    rng = range(-layers, layers + 1)
    offsets = [o for o in itertools.product(rng, rng, rng) if any(o)]
    return np.array([all((i + a, j + b, k + c) in ijk for a, b, c in offsets)
                     for i, j, k in np.rint(centers / d).astype(int)])


# --------------------------------------------------------------------- counts


@pytest.mark.parametrize("layers, kept", [(0, 216), (1, 216 - 4 ** 3), (2, 216 - 2 ** 3), (3, 216)])
def test_solid_block_counts(layers, kept):
    c = lattice((6, 6, 6))
    assert int(surface_mask(c, D, layers).sum()) == kept


def test_thin_and_tiny_sets_keep_everything():
    for shape in [(1, 1, 1), (2, 2, 2), (2, 9, 9), (3, 3, 2), (9, 9, 2)]:
        c = lattice(shape)
        assert surface_mask(c, D, 1).all(), shape
    c = lattice((3, 3, 3))                       # exactly one buried sphere: the centre
    assert np.flatnonzero(~surface_mask(c, D, 1)).tolist() == [13]


@pytest.mark.parametrize("layers", [1, 2])
def test_random_solids_match_brute_force(layers):
    # removed spheres have all 26 (or 124) neighbours; every kept one misses at least one
    rng = np.random.default_rng(3)
    for trial in range(4):
        occ = rng.random((9, 8, 7)) < 0.85
        c = np.argwhere(occ).astype(float) * D + 0.0004
        rng.shuffle(c)                           # any order: the mask follows it
        keep = surface_mask(c, D, layers)
        np.testing.assert_array_equal(~keep, brute_force_buried(c, D, layers))
        if layers == 1:
            ijk = {tuple(v) for v in np.rint(c / D).astype(int)}
            for v in np.rint(c[~keep] / D).astype(int):
                assert all(tuple(v + o) in ijk for o in NEIGHBOURS)


def test_off_lattice_centres_are_all_kept():
    c = lattice((5, 5, 5))
    c[7] += 0.1 * D
    assert surface_mask(c, D, 1).all()


@pytest.mark.parametrize("bad", [-1, 1.5, True, "1"])
def test_bad_layers(bad):
    with pytest.raises(ShapeError, match="contact layers"):
        surface_mask(lattice((3, 3, 3)), D, bad)


# --------------------------------------------------------------------- SphereSet


def block_sphere_set(n=6):
    c = lattice((n, n, n), offset=(0, 0, 0))
    c = c - c.mean(axis=0)
    V = (n * D) ** 3
    a = n * D
    return SphereSet(centers=c, diameter=D, volume=V, com=np.zeros(3),
                     inertia=V * a * a / 6.0 * np.eye(3), mesh_sha256="x" * 64, key="k" * 64)


def test_surface_sphere_set_keeps_mass_properties_and_order():
    full = block_sphere_set(6)
    surf = full.surface(1)
    assert (full.count, surf.count) == (216, 152)
    assert surf.volume == full.volume and surf.diameter == full.diameter
    np.testing.assert_array_equal(surf.com, full.com)
    np.testing.assert_array_equal(surf.inertia, full.inertia)
    assert surf.mesh_sha256 == full.mesh_sha256
    assert surf.key == full.key + ":surface1" and surf.key != full.key
    assert "surface1" in surf.notes
    # lattice order kept: the surface set is a subsequence of the full one
    np.testing.assert_array_equal(surf.centers, full.centers[surface_mask(full.centers, D, 1)])
    assert full.surface(0) is full
    assert full.surface(2).count == 216 - 8


# --------------------------------------------------------------------- the bound


def test_overlap_bound_of_one_layer():
    """Push a probe sphere (diameter d) straight into a solid 6×6×6 block along x,
    on a grid of (y, z) lines. Before its centre comes within d of a buried sphere,
    its largest overlap with a kept sphere has reached (1 - √2/2) d; at a face centre
    (y, z on half-cells) that value is reached exactly, so the bound is tight."""
    c = lattice((6, 6, 6), offset=(0, 0, 0))
    keep = surface_mask(c, D, 1)
    kept, buried = c[keep], c[~keep]
    bound = (1.0 - math.sqrt(0.5)) * D
    xs = np.linspace(-1.0 * D, 3.0 * D, 801)
    worst = math.inf
    for y in np.linspace(1.0, 4.0, 13) * D:
        for z in np.linspace(1.0, 4.0, 13) * D:
            p = np.stack([xs, np.full_like(xs, y), np.full_like(xs, z)], 1)
            dk = np.linalg.norm(p[:, None] - kept[None], axis=2).min(axis=1)
            db = np.linalg.norm(p[:, None] - buried[None], axis=2).min(axis=1)
            touch = np.flatnonzero(db < D)
            if len(touch) == 0:
                continue
            before = D - dk[: touch[0] + 1]
            worst = min(worst, float(before.max()))
    assert worst >= bound - 2e-3 * D            # sampling along x: 0.005 d steps
    assert worst <= bound + 2e-3 * D            # tight: reached through a face centre


def test_a_buried_sphere_never_touches_a_plane_first():
    # a block tilted any way: the deepest sphere below a plane is a kept one, and by
    # the time a buried sphere touches the plane a kept one is more than d deep
    rng = np.random.default_rng(5)
    c = lattice((6, 6, 6), offset=(0, 0, 0))
    keep = surface_mask(c, D, 1)
    for _ in range(50):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        h = c @ n
        assert keep[np.argmin(h)]                                # deepest: kept
        assert h[~keep].min() - h.min() >= D - 1e-12             # by d or more


# --------------------------------------------------------------------- model


def pile(layers):
    b = ModelBuilder(D, contact_layers=layers)
    ss, mesh = box_set(5, 5, 5, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("m", density=500, restitution=0.3, friction=0.5))
    rng = np.random.default_rng(1)
    q = rng.normal(size=(3, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[0] = [1, 0, 0, 0]
    # a box at rest on the floor; one dropped on it, tilted, and one thrown into it
    b.add_bodies("box", s, m, [[0.0, 0.0, 0.025], [0.01, 0.005, 0.1], [-0.085, 0.0, 0.05]],
                 rotations=q, velocities=[[0, 0, 0], [0, 0, -0.5], [0.8, 0, 0]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=100, n_frames=5)


def test_model_mass_and_step_do_not_depend_on_contact_layers():
    full, surf = pile(0), pile(1)
    assert CONTACT_LAYERS == 1 and ModelBuilder(D).contact_layers == 1
    assert (full.n_spheres, surf.n_spheres) == (3 * 125, 3 * (125 - 27))
    assert (full.contact_layers, surf.contact_layers) == (0, 1)
    for f in ("body_mass", "body_inv_inertia", "body_radius", "initial_x", "initial_q",
              "pair_k", "pair_zeta"):
        np.testing.assert_array_equal(getattr(full, f), getattr(surf, f), err_msg=f)
    assert full.dt == surf.dt and full.omega_max == surf.omega_max
    assert len(surf.shapes[0].sphere_set.centers) == 125 and surf.shapes[0].contact_count == 98
    bs = surf.body_sphere_start
    np.testing.assert_array_equal(np.diff(bs), [98, 98, 98])
    np.testing.assert_array_equal(surf.sphere_offset[bs[0]:bs[1]], surf.shapes[0].contact_centers)


def test_static_mesh_spheres_are_thinned_too():
    b = ModelBuilder(D, contact_layers=1)
    ss, mesh = box_set(6, 6, 6, D)
    b.add_static_mesh("block", mesh, ss)
    model = b.finalize(fps=24, n_frames=2)
    assert model.n_static == 1 and model.n_spheres == 152


def test_bad_builder_layers():
    with pytest.raises(SceneError, match="contact_layers"):
        ModelBuilder(D, contact_layers=-1)


def test_pile_moves_the_same_with_surface_spheres():
    """Buried spheres never touch anything here (the largest overlap stays near 1% of
    d, far below the 29% bound), so they add exact zeros to their body's force and
    torque sums. Tolerance 1e-12 m / 1e-12 (observed: bit-identical on the CPU); a
    backend that ordered its per-sphere sums by grid bucket could differ in the last
    bits, which 0.04 s of a three-body pile does not amplify past 1e-12."""
    from dempipe.sim.simulator import Simulator

    runs = []
    for layers in (0, 1):
        model = pile(layers)
        sim = Simulator(model)
        runs.append((sim.advance(model.initial_state()), sim.stats.max_overlap / D))
    (full, ov_full), (surf, ov_surf) = runs
    assert ov_full < 0.05 and ov_surf == pytest.approx(ov_full, abs=1e-9)
    assert np.abs(full.x[-1] - full.x[0]).max() > 0.01        # things did move
    for f in ("x", "q", "v", "w"):
        np.testing.assert_allclose(getattr(surf, f), getattr(full, f), rtol=0, atol=1e-12,
                                   err_msg=f)


# --------------------------------------------------------------------- scene


def parse(sim_lines):
    text = textwrap.dedent(f"""
        [simulation]
        {sim_lines}
        [shapes.box]
        builtin = "box"
        [[bodies]]
        name = "b"
        shape = "box"
        """)
    return parse_scene(text, "/tmp/scene.toml")


def test_scene_default_and_values():
    assert parse("").simulation.contact_layers == 1
    assert parse("contact_layers = 2").simulation.contact_layers == 2
    assert parse("contact_layers = 0").simulation.contact_layers == 0
    assert parse('contact_layers = "all"').simulation.contact_layers == 0


@pytest.mark.parametrize("line, expect", [
    ("contact_layers = -1", "simulation.contact_layers: -1 is out of range"),
    ("contact_layers = 1.5", "simulation.contact_layers: expected an integer >= 0"),
    ("contact_layers = true", "simulation.contact_layers: expected an integer >= 0"),
    ('contact_layers = "every"', "simulation.contact_layers: unknown value 'every'"),
    ("contact_layer = 1", "simulation.contact_layer: unknown key (did you mean 'contact_layers'?"),
])
def test_scene_errors(line, expect):
    with pytest.raises(SceneError) as e:
        parse(line)
    assert str(e.value).startswith("scene.toml: " + expect)


def test_build_model_applies_contact_layers(tmp_path):
    from dempipe.scene.build import Overrides, build_model

    text = textwrap.dedent("""
        [output]
        duration = 0.05
        [simulation]
        resolution = 6
        [shapes.box]
        builtin = "box"
        [[bodies]]
        name = "b"
        shape = "box"
        position = [0.0, 0.0, 0.05]
        [[colliders]]
        type = "plane"
        """)
    scene = parse_scene(text, tmp_path / "s.toml")
    default = build_model(scene)
    every = build_model(scene, overrides=Overrides(contact_layers=0))
    assert default.contact_layers == 1 and every.contact_layers == 0
    assert (every.n_spheres, default.n_spheres) == (216, 152)
    assert default.shapes[0].sphere_set.count == 216          # geometry: the full set
    np.testing.assert_array_equal(default.body_mass, every.body_mass)
    np.testing.assert_array_equal(default.body_inv_inertia, every.body_inv_inertia)
    assert default.dt == every.dt


INSIDE = """
[output]
duration = 0.05
[simulation]
resolution = 2
[shapes.crate]
builtin = "box"
size = [0.1, 0.1, 0.1]
[shapes.pebble]
builtin = "box"
size = [0.02, 0.02, 0.02]
[[bodies]]
name = "crate"
shape = "crate"
layout = "single"
position = [0.0, 0.0, 0.06]
[[bodies]]
name = "pebble"
shape = "pebble"
layout = "single"
position = [0.0, 0.0, 0.06]
[[colliders]]
type = "plane"
"""


def test_a_body_inside_another_at_frame_0_is_seen_with_surface_spheres(tmp_path):
    # A 2×2×2 pebble at the centre of a 10×10×10 crate (d = 1 cm) touches only the
    # crate's buried spheres, which surface spheres leave out: the contact spheres
    # alone see no overlap, so the frame-0 checks also look with every sphere
    # (build.full_sphere_model). The pebble's spheres sit on the crate's lattice
    # points: an overlap of a whole diameter, so check reports an error and bake
    # refuses without --force.
    from dempipe.pipeline.bake import bake
    from dempipe.scene.build import build_model, initial_overlap, initial_overlap_all_spheres
    from dempipe.errors import StabilityError

    path = tmp_path / "inside.toml"
    path.write_text(INSIDE)
    scene = load_scene(path)
    model = build_model(scene)
    assert model.contact_layers == 1
    assert initial_overlap(model)[0] == 0.0                     # the blind spot
    overlap, body = initial_overlap_all_spheres(scene, model)
    assert overlap > 0.9 and body >= 0
    report = analyze_scene(path)
    codes = {f.code: f.level for f in report.findings}
    assert codes.get("frame0-overlap") == "error" and not report.ok
    with pytest.raises(StabilityError, match="overlaps another body"):
        bake(path, tmp_path / "out.usda")
