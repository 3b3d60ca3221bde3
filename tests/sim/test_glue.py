"""Glue bonds between fractured pieces (sim/glue.py, kernels/glue.py,
physics.glue_force) against closed forms and conservation laws.

The pieces are cut from one box lattice by hand (``bar``): each piece a box of
whole lattice cells, its spheres the parent's, so the spheres of two pieces
facing each other across a cut touch at exactly d, as fracture leaves them.
"""

import math

import numpy as np
import pytest
import trimesh

from dempipe.errors import SceneError
from dempipe.scene.load import parse_scene
from dempipe.sim import glue, physics
from dempipe.sim import motion as mo
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.materials import Material
from dempipe.sim.model import quat_to_matrix, world_inertia
from dempipe.sim.simulator import Simulator
from dempipe.spheres.sphere_set import SphereSet

D = 0.02
RHO = 1000.0
G = 9.81


def box_piece(lo, hi):
    """(mesh, SphereSet) of the lattice cells lo..hi (integer cell corners) of a parent
    lattice of pitch D with a cell corner at the origin, in the parent's coordinates."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    mesh = trimesh.creation.box(bounds=[lo * D, hi * D])
    cells = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"),
                     -1).reshape(-1, 3)
    mp = mesh.mass_properties
    com = np.asarray(mp["center_mass"], np.float64)
    key = f"box{tuple(lo)}{tuple(hi)}"
    return mesh, SphereSet(centers=(cells + 0.5) * D - com, diameter=D,
                           volume=float(mp["volume"]), com=com,
                           inertia=np.asarray(mp["inertia"], np.float64), mesh_sha256=key,
                           key=key, notes=("piece",))


def add_piece(b, name, lo, hi, material, glue_id=0, **kw):
    mesh, ss = box_piece(lo, hi)
    s = b.add_shape(name, mesh, ss)
    b.add_bodies(name, s, material, [[0.0, 0.0, 0.0]], glue=[glue_id], **kw)
    return ss


def hanging_bar(factor, law, frames):
    """A 2 x 2 x 6 bar cut in the middle: the upper half kinematic (held still),
    the lower glued under it with glue_strength = factor W / (n d²), W the lower
    half's weight and n = 4 the bond's sphere pairs. Returns (model, state, frames)."""
    n_pairs = 4
    weight = RHO * 12 * D ** 3 * G
    b = ModelBuilder(D, gravity=(0.0, 0.0, -G))
    m = b.add_material(Material("glued", density=RHO, friction=0.5,
                                glue_strength=factor * weight / (n_pairs * D * D)))
    add_piece(b, "anchor", (0, 0, 3), (2, 2, 6), m, kinematic=True,
              motion=mo.Motion(velocity=(0.0, 0.0, 0.0)))
    add_piece(b, "low", (0, 0, 0), (2, 2, 3), m)
    model = b.finalize(fps=24, n_frames=frames + 3, contact_law=law)
    state = model.initial_state()
    out = Simulator(model).advance(state, frames)
    return model, state, out


@pytest.mark.parametrize("law", ["linear", "hertz"])
def test_hanging_bar_holds_above_its_weight_and_breaks_below(law):
    # The bond carries the lower half's weight W, shared by its 4 pairs. At the
    # default glue_damping 0.7 the load applied at once overshoots W by 4.6 %
    # (glue.GLUE_DAMPING), so 10 % more strength holds it: it hangs still at the
    # spring's stretch W / K (to 1 %: the pairs share W equally, the half's centre of
    # mass is under the bond's centre; the dashpot has damped the rest by frame 11).
    model, state, out = hanging_bar(1.1, law, frames=12)
    assert model.n_bonds == 1 and model.bonds.n_pairs == 4
    assert state.bond_broken[0] == 0
    K = model.bonds.bond_k[0] * 4
    weight = RHO * 12 * D ** 3 * G
    sag = out.x[0, 1, 2] - out.x[-1, 1, 2]
    assert sag == pytest.approx(weight / K, rel=0.01)
    # 10 % under: the load reaches the strength within a few of the bond's periods
    # (milliseconds), within the first frame; from then on the half falls free: at
    # frame 3 its speed is g (t - t_break), t_break within the first frame
    model, state, out = hanging_bar(0.9, law, frames=2)      # frames 0 and 1
    assert state.bond_broken[0] == 1
    out = Simulator(model).advance(state, 3)
    t = out.times[-1]
    assert G * (t - 1 / 24) < -out.v[-1, 1, 2] < G * t


def test_pairs_are_the_touching_spheres_across_the_cut():
    b = ModelBuilder(D)
    m = b.add_material(Material("glued", density=RHO, glue_strength=1e4))
    add_piece(b, "a", (0, 0, 0), (3, 2, 2), m)
    add_piece(b, "b", (3, 0, 0), (5, 2, 2), m)
    add_piece(b, "c", (0, 0, 2), (5, 2, 4), m, glue_id=1)    # another object: no bond
    model = b.finalize(fps=24, n_frames=2)
    bonds = model.bonds
    assert bonds.n_bonds == 1 and tuple(bonds.bond_body[0]) == (0, 1)
    assert bonds.n_pairs == 4                      # the 2 x 2 face
    assert np.allclose(bonds.pair_rest, D, rtol=1e-12)
    assert np.allclose(bonds.bond_limit, 1e4 * D * D)


def test_overlapping_glued_pieces_are_refused():
    b = ModelBuilder(D)
    m = b.add_material(Material("glued", density=RHO, glue_strength=1e4))
    mesh, ss = box_piece((0, 0, 0), (2, 2, 2))
    s = b.add_shape("p", mesh, ss)
    b.add_bodies("p", s, m, [[0, 0, 0], [0.5 * D, 0, 0]], glue=[0, 0])
    with pytest.raises(SceneError, match="glued pieces overlap"):
        b.finalize(fps=24, n_frames=2)


def test_glue_needs_a_strength():
    b = ModelBuilder(D)
    m = b.add_material(Material("plain", density=RHO))
    add_piece(b, "a", (0, 0, 0), (2, 2, 2), m)
    add_piece(b, "b", (2, 0, 0), (4, 2, 2), m)
    with pytest.raises(SceneError, match=r"materials\.plain\.glue_strength"):
        b.finalize(fps=24, n_frames=2)


def test_glue_force_is_antisymmetric_and_keeps_angular_momentum():
    # From j's side every input is negated (r, dv, s) or the same (ws): the force
    # comes out exactly negated and the torque about each centre exactly equal; with
    # the bond point at the midpoint, r_i x f + r_j x (-f) + 2 t = 0 to round-off.
    rng = np.random.default_rng(3)
    for _ in range(50):
        r = rng.normal(size=3) * D
        dv = rng.normal(size=3)
        ws = rng.normal(size=3) * 10
        s = rng.normal(size=3) * 1e-4
        dist = float(np.linalg.norm(r))
        a = physics.glue_force(*r, dist, D, *dv, *ws, 1e4, 3.0, *s, 1e-4)
        b_ = physics.glue_force(*(-r), dist, D, *(-dv), *ws, 1e4, 3.0, *(-s), 1e-4)
        assert a[0:3] == tuple(-v for v in b_[0:3])
        assert a[3:6] == b_[3:6]
        assert a[6:9] == tuple(-v for v in b_[6:9])
        f = np.array(a[0:3])
        L = np.cross(-r, f) + 2 * np.array(a[3:6])       # about x_i: r_j x (-f) + 2 t
        assert np.linalg.norm(L) <= 1e-12 * np.linalg.norm(f) * dist + 1e-300


def test_load_is_the_springs_tension_and_shear():
    # stretched by 1 % of d at rest: load k (dist - rest); compressed: no load
    k = 1e4
    out = physics.glue_force(0, 0, 1.01 * D, 1.01 * D, D, 0, 0, 0, 0, 0, 0, k, 5.0,
                             0, 0, 0, 1e-4)
    assert out[2] == pytest.approx(k * 0.01 * D) and out[9] == pytest.approx(k * 0.01 * D)
    out = physics.glue_force(0, 0, 0.99 * D, 0.99 * D, D, 0, 0, 0, 0, 0, 0, k, 5.0,
                             3e-5, 0, 0, 1e-4)
    assert out[2] == pytest.approx(-k * 0.01 * D)
    assert out[9] == pytest.approx(k * 3e-5)          # the shear spring only


def _momenta(model, state):
    """Total linear momentum and angular momentum about the origin of the dynamic
    bodies [kg m/s], [kg m²/s]."""
    n = model.n_bodies
    P = state.body_P[:n].sum(axis=0)
    L = (state.body_L[:n] + np.cross(state.body_x[:n], state.body_P[:n])).sum(axis=0)
    return P, L


def _energy(model, state):
    """Kinetic energy plus the bonds' elastic energy [J] (no gravity)."""
    n = model.n_bodies
    e = 0.0
    for b in range(n):
        e += 0.5 * state.body_P[b] @ state.body_P[b] / model.body_mass[b]
        inv = np.linalg.inv(world_inertia(state.body_q[b], model.body_inv_inertia[b]))
        e += 0.5 * state.body_L[b] @ inv @ state.body_L[b]
    R = np.stack([quat_to_matrix(q) for q in state.body_q])
    x = state.body_x[model.sphere_body] + np.einsum("sij,sj->si", R[model.sphere_body],
                                                    model.sphere_offset)
    return e + glue.bond_energy(model.bonds, state, x)


def test_spun_bar_breaks_keeping_momentum_and_never_gaining_energy():
    # Two 2 x 2 x 3 halves glued end to end, spinning about a transverse axis in zero
    # gravity: the bond carries the centripetal load m w² (L/2), L = 3 d between the
    # halves' centres. Its strength is half that: the bond breaks within the first
    # steps and the halves fly apart. Momentum: each force acts on both halves, equal
    # and opposite (exactly: physics.glue_force is antisymmetric in IEEE arithmetic),
    # so P stays to round-off (1e-12 of m v); L about the origin to 1e-9 (the body
    # stage's midpoint rotation). Energy, kinetic plus the bonds' elastic, never rises
    # from frame to frame by more than 1e-9 of itself: the dashpot takes energy out,
    # a break drops the bond's stored energy.
    w = 40.0
    m_half = RHO * 12 * D ** 3
    tension = m_half * w * w * 1.5 * D
    b = ModelBuilder(D, gravity=(0.0, 0.0, 0.0))
    mat = b.add_material(Material("glued", density=RHO, friction=0.5,
                                  glue_strength=0.5 * tension / (4 * D * D)))
    for name, lo, hi in (("low", (0, 0, 0), (2, 2, 3)), ("up", (0, 0, 3), (2, 2, 6))):
        mesh, ss = box_piece(lo, hi)
        s = b.add_shape(name, mesh, ss)
        centre = ss.com - np.array([D, D, 3 * D])
        v = np.cross([0.0, w, 0.0], centre)          # rigid rotation about the middle
        b.add_bodies(name, s, mat, [[0.0, 0.0, 0.0]], velocities=[v],
                     angular_velocities=[[0.0, w, 0.0]], glue=[0])
    model = b.finalize(fps=240, n_frames=21)
    state = model.initial_state()
    P0, L0 = _momenta(model, state)
    e = [_energy(model, state)]
    sim = Simulator(model)
    broke_at = None
    for f in range(20):
        sim.advance(state, 2)                       # this frame and the next
        e.append(_energy(model, state))
        if broke_at is None and state.bond_broken[0]:
            broke_at = f
    assert broke_at is not None and broke_at < 2
    P1, L1 = _momenta(model, state)
    scale = m_half * w * 1.5 * D
    assert np.abs(P1 - P0).max() <= 1e-12 * scale
    assert np.abs(L1 - L0).max() <= 1e-9 * np.abs(L0).max()
    e = np.array(e)
    assert (np.diff(e) <= 1e-9 * e[:-1]).all()


def test_glued_wall_stands_still_and_sleeps():
    # A wall of 3 x 3 glued pieces (each 2 x 2 x 2 spheres) on the ground, 10 s: no
    # bond breaks (the glue is 10x the weight the lowest bonds carry), after settling
    # (from 1 s on) no piece moves more than 1e-3 d, and all are asleep at the end.
    b = ModelBuilder(D, gravity=(0.0, 0.0, -G))
    weight_over_bottom = RHO * 2 * 2 * 2 * D ** 3 * G * 2      # two pieces above
    m = b.add_material(Material("glued", density=RHO, friction=0.6, restitution=0.2,
                                glue_strength=10 * weight_over_bottom / (4 * D * D)))
    for ix in range(3):
        for iz in range(3):
            add_piece(b, f"p{ix}{iz}", (2 * ix, 0, 2 * iz), (2 * ix + 2, 2, 2 * iz + 2), m)
    b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    model = b.finalize(fps=24, n_frames=241, sleep=(None, None, None))
    assert model.n_bonds == 12
    state = model.initial_state()
    sim = Simulator(model)
    sim.advance(state, 25)                          # frames 0 .. 24
    x1 = state.body_x[: model.n_bodies].copy()
    sim.advance(state, 217)
    assert not state.bond_broken.any()
    drift = np.linalg.norm(state.body_x[: model.n_bodies] - x1, axis=1).max()
    assert drift < 1e-3 * D
    assert state.asleep(model.sleep_steps)[: model.n_bodies].all()


TOML = """
[output]
fps = 24
duration = 0.1
[materials.stone]
density = 2400.0
{glue_strength}
[shapes.column]
builtin = "box"
size = [0.1, 0.1, 0.3]
{fracture}
[[bodies]]
name = "column"
shape = "column"
material = "stone"
glue = true
"""


def test_scene_glue_key_is_refused_where_it_cannot_apply():
    frac = "fracture = { pieces = 3, seed = 1 }"
    with pytest.raises(SceneError, match=r"bodies\[0\]\.glue: shape 'column' is not fractured"):
        parse_scene(TOML.format(glue_strength="glue_strength = 1e5", fracture=""), "s.toml")
    with pytest.raises(SceneError, match=r"bodies\[0\]\.glue: material 'stone' has no "
                                         r"glue_strength"):
        parse_scene(TOML.format(glue_strength="", fracture=frac), "s.toml")
    with pytest.raises(SceneError, match=r"materials\.stone\.glue_damping: given without"):
        parse_scene(TOML.format(glue_strength="glue_damping = 0.5", fracture=frac), "s.toml")
    scene = parse_scene(TOML.format(glue_strength="glue_strength = 1e5", fracture=frac),
                        "s.toml")
    assert scene.bodies[0].glue
    assert scene.materials["stone"].glue_strength == 1e5


def test_a_checkpoint_resumes_bit_identical(tmp_path):
    # The State's bond_broken and bond_shear go into a checkpoint (pipeline/checkpoint.py
    # STATE_ARRAYS): a run stopped after frame 4 and resumed from its last checkpoint
    # (frame 3) ends bit for bit where the uninterrupted run does. The scene: a 2 x 2
    # block of glued cubes dropped spinning onto the ground (its bonds shear), and a
    # bar whose lower half tears off its anchor in the first frame (a broken bond).
    from dempipe.pipeline.checkpoint import BakeStore

    def model():
        b = ModelBuilder(D, gravity=(0.0, 0.0, -G))
        m = b.add_material(Material("glued", density=RHO, friction=0.6, glue_strength=1e6))
        weak = b.add_material(Material("weak", density=RHO, friction=0.6,
                                       glue_strength=0.9 * RHO * 12 * D ** 3 * G / (4 * D * D)))
        for k, (ix, iz) in enumerate([(0, 0), (1, 0), (0, 1), (1, 1)]):
            add_piece(b, f"p{k}", (2 * ix, 0, 2 * iz + 1), (2 * ix + 2, 2, 2 * iz + 3), m,
                      angular_velocities=[[0.0, 3.0, 1.0]])
        add_piece(b, "anchor", (10, 0, 6), (12, 2, 9), weak, glue_id=1, kinematic=True,
                  motion=mo.Motion(velocity=(0.0, 0.0, 0.0)))
        add_piece(b, "low", (10, 0, 3), (12, 2, 6), weak, glue_id=1)
        b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
        return b.finalize(fps=24, n_frames=10)

    mdl = model()
    ref = mdl.initial_state()
    Simulator(mdl).advance(ref, 9)
    assert ref.bond_broken.tolist() == [0, 0, 0, 0, 1]
    assert np.abs(ref.bond_shear).max() > 0.0

    class Stop(Exception):
        pass

    out = tmp_path / "out.usda"
    store = BakeStore(out, "glue", {}, mdl.n_bodies, chunk_frames=2)
    store.create()
    sim = Simulator(mdl)
    state = mdl.initial_state()

    def after(k, st):
        if store.due():
            store.checkpoint(sim, st)
        if k == 4:
            raise Stop

    with pytest.raises(Stop):
        sim.run(state, 9, store.add, after_frame=after)
    store = BakeStore(out, "glue", {}, mdl.n_bodies, chunk_frames=2)
    store.open()
    sim = Simulator(mdl)
    state = mdl.initial_state()
    point = store.restore(sim, state)
    assert point.frames_done == 4
    sim.run(state, 9, store.add, resume=point,
            after_frame=lambda k, st: store.due() and store.checkpoint(sim, st))
    for name in ("body_x", "body_q", "body_P", "body_L", "bond_broken", "bond_shear"):
        np.testing.assert_array_equal(getattr(state, name), getattr(ref, name), err_msg=name)


def test_glued_pieces_do_not_depend_on_the_thread_count():
    # Each glue pass writes only its own rows (a bond, a body) and sums in a fixed
    # order: one thread and two give the same State bit for bit.
    def run(threads):
        b = ModelBuilder(D, gravity=(0.0, 0.0, -G))
        strong = b.add_material(Material("strong", density=RHO, friction=0.6,
                                         glue_strength=1e6))
        weak = b.add_material(Material("weak", density=RHO, friction=0.6, glue_strength=2e3))
        for k, (ix, iz) in enumerate([(0, 0), (1, 0), (2, 0), (0, 1), (1, 1), (2, 1)]):
            add_piece(b, f"p{k}", (2 * ix, 0, 2 * iz + 1), (2 * ix + 2, 2, 2 * iz + 3),
                      strong if k < 3 else weak,
                      angular_velocities=[[0.0, 6.0, 2.0]], velocities=[[0.0, 0.0, -1.0]])
        b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], strong)
        model = b.finalize(fps=24, n_frames=7)
        state = model.initial_state()
        Simulator(model, threads=threads).advance(state, 7)
        return state

    one, two = run(1), run(2)
    assert 0 < one.bond_broken.sum() < one.bond_broken.size    # the weak broke, not all
    for name in ("body_x", "body_q", "body_P", "body_L", "bond_broken", "bond_shear"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name), err_msg=name)


def test_a_compressed_bond_is_not_also_a_contact():
    # The upper half of a 2 x 2 x 6 bar glued onto its kinematic lower half: its weight
    # W presses the bond's 4 pairs together, which then overlap. The bond alone carries
    # it (glue.bond_contacts cancels their contacts): it settles W / K lower, to 1 %
    # (with the contacts too it would settle W / (K + k) lower, half as far at the
    # default K = k).
    weight = RHO * 12 * D ** 3 * G
    b = ModelBuilder(D, gravity=(0.0, 0.0, -G))
    m = b.add_material(Material("glued", density=RHO, friction=0.5, glue_strength=1e6))
    add_piece(b, "anchor", (0, 0, 0), (2, 2, 3), m, kinematic=True,
              motion=mo.Motion(velocity=(0.0, 0.0, 0.0)))
    add_piece(b, "up", (0, 0, 3), (2, 2, 6), m)
    model = b.finalize(fps=24, n_frames=13)
    state = model.initial_state()
    out = Simulator(model).advance(state, 13)
    K = model.bonds.bond_k[0] * 4
    assert out.x[0, 1, 2] - out.x[-1, 1, 2] == pytest.approx(weight / K, rel=0.01)


def cantilever(factor, frames=13):
    """A 2 x 2-sphere beam sticking out along +x from a kinematic root piece: three
    glued 2 x 2 x 2 pieces, each of weight w at 1, 3 and 5 d from the root's cut. The
    root bond carries V = 3 w and M = 9 w d (statically determinate); its pairs sit at
    ±d/2 about the neutral axis, so the top two carry the tension F = M / (2 d) and
    each pair a quarter of V: load √(F² + (V/4)²). Strength: ``factor`` × that / d²."""
    w = RHO * 8 * D ** 3 * G
    load = math.hypot(9 * w * D / (2 * D), 3 * w / 4)
    b = ModelBuilder(D, gravity=(0.0, 0.0, -G))
    m = b.add_material(Material("glued", density=RHO, friction=0.5,
                                glue_strength=factor * load / (D * D)))
    add_piece(b, "root", (-2, 0, 0), (0, 2, 2), m, kinematic=True,
              motion=mo.Motion(velocity=(0.0, 0.0, 0.0)))
    for k in range(3):
        add_piece(b, f"p{k}", (2 * k, 0, 0), (2 * k + 2, 2, 2), m)
    model = b.finalize(fps=24, n_frames=frames + 1)
    state = model.initial_state()
    Simulator(model).advance(state, frames)
    return model, state


def test_cantilever_root_breaks_at_the_beam_load():
    # The root bond's outer pairs carry the beam's bending load (the outer-fibre
    # rule): 10 % less strength and the root bond breaks. Gravity is applied at once,
    # and the beam's bending mode is lightly damped (the bonds' dashpots act on the
    # pairs' small lever arms, the beam's inertia is large): the load overshoots,
    # at most twice the static one for a damped linear system, so 2.2 times the
    # strength holds it (measured: 1.1 times does not; the hanging bar's translation,
    # damped at glue_damping, holds at 1.1).
    model, state = cantilever(2.2)
    assert not state.bond_broken.any()
    model, state = cantilever(0.9, frames=3)
    root = [n for n, (a, b_) in enumerate(model.bonds.bond_body) if 0 in (a, b_)]
    assert state.bond_broken[root].all()


def test_cantilever_tip_sags_as_the_jointed_beam_formula():
    """A glued cantilever is rigid pieces on elastic joints: a beam whose bending and
    shear compliance sit at the cuts. Each joint's four pairs act at the cut (the bond
    point is the midpoint), at ±d/2 about the neutral axis, so a joint turns by
    θ_j = M_j / (k d²) and shears by V_j / (4 k), with M_j and V_j the moment and
    shear of the pieces beyond it (statically determinate). The last piece's centre
    sinks Σ_j θ_j (x_tip - x_j) + V_j / (4 k): 59.5 w/k for three pieces.

    Within 1 % of it from 1.5 s on (measured 0.1 %; gravity is applied at once and
    the bending mode rings at its light damping: 57 % over at 0.1 s, 0.5 % by 1 s),
    and the piece's pitch within 1 % of Σ θ_j. The continuum's Euler-Bernoulli and
    Timoshenko formula with EI = k d² ℓ and GA = 4 k ℓ (ℓ = 2 d, a piece) is this
    sum's limit: the jointed beam sags more by about 2/N for N pieces, its
    compliance lumped at each piece's root end (1.82× at N = 3, 1.04× at N = 48)."""
    n, fps, seconds = 3, 24, 2.0
    frames = int(fps * seconds)
    b = ModelBuilder(D, gravity=(0.0, 0.0, -G))
    m = b.add_material(Material("glued", density=RHO, friction=0.5, glue_strength=1e9))
    add_piece(b, "root", (-2, 0, 0), (0, 2, 2), m, kinematic=True,
              motion=mo.Motion(velocity=(0.0, 0.0, 0.0)))
    for k in range(n):
        add_piece(b, f"p{k}", (2 * k, 0, 0), (2 * k + 2, 2, 2), m)
    model = b.finalize(fps=fps, n_frames=frames + 1)
    state = model.initial_state()
    out = Simulator(model).advance(state, frames)
    assert not state.bond_broken.any()
    k = model.bonds.bond_k[0]
    assert np.all(model.bonds.bond_k == k)
    w = RHO * 8 * D ** 3 * G
    tip = (2 * n - 1) * D                       # the last piece's centre, from the root cut
    sag = turn = 0.0
    for j in range(n):
        xj = 2 * D * j                          # joint j's cut
        M = sum(w * ((2 * i + 1) * D - xj) for i in range(j, n))
        V = w * (n - j)
        sag += M / (k * D * D) * (tip - xj) + V / (4 * k)
        turn += M / (k * D * D)
    late = out.times >= 1.5
    z = out.x[0, -1, 2] - out.x[late, -1, 2]
    assert np.allclose(z, sag, rtol=0.01), z / sag
    R = np.array([quat_to_matrix(q) for q in out.q[late, -1]])
    pitch = np.arctan2(R[:, 2, 0], R[:, 0, 0])  # the piece's x axis, tipped down
    assert np.allclose(-pitch, turn, rtol=0.01), -pitch / turn
