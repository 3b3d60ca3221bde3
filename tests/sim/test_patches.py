"""Contact patches: a contact between two bodies is one patch, whatever the number of
sphere pairs that make it up (kernels/patches.py).

Closed forms: a box or a cylinder landing flat rebounds with e² of its impact energy
at every resolution and for both laws; the auto step does not depend on the
resolution; edge and corner landings lose energy and a tipped box comes to rest on
a face; a tower of ten boxes stands still and sleeps.
"""

import math

import numpy as np
import pytest

from dempipe.scene.build import build_model
from dempipe.scene.load import parse_scene
from dempipe.sim.simulator import Simulator
from bodies import body_energy, rotation_matrix

G = 9.81
SIZE = 0.1          # the box's edge, the cylinder's diameter and height [m]
SHAPES = {"box": 'builtin = "box"\nsize = [0.1, 0.1, 0.1]',
          "cylinder": 'builtin = "cylinder"\ndiameter = 0.1\nheight = 0.1'}


def scene(shape: str, resolution: int, e: float, *, law="linear", z=0.05, vz=0.0,
          gravity=-G, fps=480, duration=0.5, friction=0.0, rotation="[1.0, 0.0, 0.0, 0.0]",
          sleeping=False, extra=""):
    """One body of ``shape`` (its base at z - 0.05 when upright) over a ground plane,
    wood (700 kg/m³) of restitution e."""
    text = f"""
[output]
fps = {fps}
duration = {duration}
[simulation]
resolution = {resolution}
contact_law = "{law}"
sleeping = {str(sleeping).lower()}
gravity = [0.0, 0.0, {gravity}]
[materials.wood]
density = 700.0
restitution = {e}
friction = {friction}
[shapes.s]
{SHAPES[shape]}
[[bodies]]
name = "b"
shape = "s"
material = "wood"
position = [0.0, 0.0, {z}]
rotation = {rotation}
velocity = [0.0, 0.0, {vz}]
[[colliders]]
type = "plane"
material = "wood"
{extra}"""
    return build_model(parse_scene(text, "patch.toml"))


def thrown_flat(shape, resolution, e, law, phase, v0=1.0):
    """(rebound speed / impact speed)² of a body thrown flat at v0 [m/s] onto the
    plane without gravity (gravity during the contact would take g t_c from the
    rebound, a physical effect the closed form leaves out); it starts ``phase`` of a
    step's travel above touching, so the impact falls at that phase of a step."""
    dt = scene(shape, resolution, e, law=law, vz=-v0, gravity=0.0).dt
    model = scene(shape, resolution, e, law=law, z=0.05 + 1e-6 + phase * v0 * dt,
                  vz=-v0, gravity=0.0)
    assert model.body_mass.shape[0] == 1 and model.dt == dt
    sim = Simulator(model)
    st = model.initial_state()
    for _ in range(2000):
        sim.backend.step(st, 1)
        if st.body_P[0, 2] > 0 and st.body_x[0, 2] >= 0.05:
            break
    sim.backend.step(st, 1)     # the step after the contact ends: its last dashpot impulse
    v = st.body_P[0] / model.body_mass[0]
    assert abs(v[0]) + abs(v[1]) < 1e-9 * v0       # flat: straight back up
    return (v[2] / v0) ** 2


@pytest.mark.parametrize("law", ["linear", "hertz"])
def test_flat_landings_bounce_with_the_asked_restitution(law):
    # A box and a cylinder landing flat on a face of 4², 8² and 16² spheres (lattice:
    # 16, 64 and 256 sphere pairs at once) at e = 0.2, 0.5, 0.8, the moment of impact
    # spread over a step. Asked: e² within 4% mean / 8% worst. Measured (linear /
    # Hertz): mean 0.4% / 0.5%, worst 5.4% / 4.8%, the cylinder at 16 across at e = 0.2
    # (1.6% before its lattice met walls through its mesh's tori: the rings of its side
    # near the cap sit 0.002-0.025 d above it, join the cap's patch late and leave it
    # early, and its dashpot's last impulse is shared over fewer pairs). (Were each pair of a face a whole contact, a face of 64
    # would be one oscillator at ζ = √64 × 0.215, overdamped: no rebound at all.)
    err = []
    k = 0
    for shape in SHAPES:
        for resolution in (4, 8, 16):
            for e in (0.2, 0.5, 0.8):
                phase = (0.37 * k) % 1.0
                k += 1
                err.append(thrown_flat(shape, resolution, e, law, phase) / e ** 2 - 1.0)
    err = np.array(err)
    assert abs(err.mean()) <= 0.04 and np.abs(err).max() <= 0.08, err


def test_a_box_dropped_flat_rebounds_to_e_squared_of_its_height():
    # A 10 cm wooden cube dropped flat from 0.5 m, e = 0.5,
    # resolution 8, gravity, 480 fps: rebound height / drop height = e² = 0.25
    # (measured 0.2493; gravity acting during the 0.5 ms contact costs ~1e-3).
    # Tolerance 4%, the flat landings' mean above.
    model = scene("box", 8, 0.5, z=0.55, duration=0.7)
    frames = Simulator(model).advance(model.initial_state())
    z = frames.x[:, 0, 2]
    dz = np.diff(z)
    land = int(np.argmax(dz > 0))                   # the first frame rising
    apex = land + int(np.argmax(dz[land:] <= 0))
    rest = 0.05
    ratio = (z[apex] - rest) / (z[0] - rest)
    assert ratio == pytest.approx(0.25, rel=0.04)


@pytest.mark.parametrize("shape", list(SHAPES))
def test_the_auto_step_does_not_depend_on_the_resolution(shape):
    # Each contact is one patch with the material's stiffness, chosen for the bodies
    # (materials.patch_scale): the auto step is the same at 4, 8 and 16 spheres across.
    # (asked: within 1.5x; measured: the same step at the three)
    dts = [scene(shape, r, 0.5, z=0.55).dt for r in (4, 8, 16)]
    assert max(dts) / min(dts) <= 1.5, dts


@pytest.mark.parametrize("law", ["linear", "hertz"])
def test_edge_and_corner_landings_lose_energy_and_come_to_rest_on_a_face(law):
    # A box dropped from 0.3 m turned 35° about x and 20° about y (lands on a corner,
    # tips onto an edge, falls flat), e = 0.5, friction 0.5. Its energy (kinetic +
    # potential; the springs' is left out, so it dips during a contact and comes back)
    # never rises above what it had before (tolerance 1e-6 of the drop's energy per
    # frame: the elastic energy still stored at a frame's end), and it ends at rest with
    # a face down: a body axis within 0.5° of the vertical, its centre at half its size.
    a, b = math.radians(35.0), math.radians(20.0)
    qa = np.array([math.cos(a / 2), math.sin(a / 2), 0.0, 0.0])
    qb = np.array([math.cos(b / 2), 0.0, math.sin(b / 2), 0.0])
    q = _qmul(qb, qa)
    model = scene("box", 6, 0.5, law=law, z=0.35, duration=2.0, fps=60, friction=0.5,
                  rotation="[" + ", ".join(repr(float(c)) for c in q) + "]")
    frames = Simulator(model).advance(model.initial_state())
    energy = body_energy(model, frames, G)
    drop = energy[0] - float(model.body_mass[0]) * G * 0.05
    assert np.all(np.diff(np.maximum.accumulate(energy)) <= 1e-6 * drop)
    assert np.all(energy[1:] <= energy[0] + 1e-6 * drop)
    assert np.linalg.norm(frames.v[-1, 0]) < 1e-3 and np.linalg.norm(frames.w[-1, 0]) < 1e-2
    R = rotation_matrix(frames.q[-1, 0])
    assert 1.0 - np.abs(R[2]).max() < 1 - math.cos(math.radians(0.5))   # a body axis up
    assert frames.x[-1, 0, 2] == pytest.approx(0.05, abs=0.01 * model.diameter)


def _qmul(p, q):
    w1, x1, y1, z1 = p
    w2, x2, y2, z2 = q
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def test_a_tower_of_ten_boxes_stands_still_and_sleeps():
    # Ten 10 cm boxes stacked face to face on the ground, touching at frame 0, e = 0.3,
    # friction 0.5, sleeping on. Each face between two boxes is one patch of 36 sphere
    # pairs (resolution 6). Asked: energy never rises, no creep (every box within 1e-3 d
    # of its column's axis and no tilt past 0.01°), every box asleep by the end (exactly
    # still), no overlap past the target: the bottom face carries ten boxes' weight,
    # 10 m g / K, below the overlap target (stiffness_target_overlap × ℓ).
    boxes = "\n".join(f"""
[[bodies]]
name = "b{i}"
shape = "s"
material = "wood"
position = [0.0, 0.0, {0.05 + 0.1 * i!r}]""" for i in range(1, 10))
    model = scene("box", 6, 0.3, friction=0.5, duration=3.0, fps=24, sleeping=True,
                  extra=boxes)
    assert model.n_bodies == 10
    sim = Simulator(model)
    frames = sim.advance(model.initial_state())
    m = model.body_mass[:10]
    ke = 0.5 * (m[None, :] * (frames.v ** 2).sum(-1)).sum(-1)
    pe = (m[None, :] * G * frames.x[:, :, 2]).sum(-1)
    energy = ke + pe
    # (the springs' energy is left out: settling onto them at frame 0 takes 1.4e-3 J
    # into the contacts, which ring it back and forth, ±2e-4 J, until it is damped)
    assert np.all(energy[1:] < energy[0])
    late = frames.times > 1.0
    assert np.all(np.diff(energy[late]) <= 0.0)
    assert np.abs(frames.x[:, :, :2]).max() < 1e-3 * model.diameter
    tilt = 2.0 * np.degrees(np.arcsin(np.clip(np.linalg.norm(frames.q[:, :, 1:], axis=-1),
                                              0, 1)))
    assert tilt.max() < 0.01
    assert np.all(frames.v[-1] == 0.0) and np.all(frames.w[-1] == 0.0)     # asleep: exact
    target = 0.02 * model.patch_scale       # the default stiffness_target_overlap
    assert sim.stats.max_overlap < target, (sim.stats.max_overlap, target)


@pytest.mark.parametrize("tray_first", [True, False])
def test_a_crowded_body_keeps_each_contact_its_own_patch(tray_first):
    # A dynamic tray on the ground carrying 25 one-sphere balls, each resting on one of
    # its spheres: 26 partners, more than a body's row holds (patches.BODY_PATCHES =
    # 16). The tray owns its pairs with the balls when it comes first (lower index);
    # each pair then takes the ball's share (patches.pair_share), so each ball rests on
    # its own patch in either order. Asked: each ball's overlap with the tray sphere
    # under it that of one contact carrying one ball, m g / k, within 1% (measured in
    # the tray's own frame; a share of all 26 would be 25x deeper).
    from bodies import ball_set, box_set
    from dempipe.sim.builder import ModelBuilder
    from dempipe.sim.materials import Material
    from dempipe.sim.model import quat_to_matrix
    D = 0.01
    b = ModelBuilder(D)
    bs, bm = ball_set(D)
    ts, tm = box_set(10, 10, 1, D)
    ball, tray = b.add_shape("ball", bm, bs), b.add_shape("tray", tm, ts)
    m = b.add_material(Material("m", density=1000, restitution=0.3, friction=0.5))
    grid = np.stack(np.meshgrid(np.arange(5), np.arange(5), indexing="ij"), -1).reshape(-1, 2)
    balls = np.column_stack([(grid - 2) * 2 * D + 0.5 * D, np.full(25, 1.5 * D)])
    groups = [("tray", tray, [[0.0, 0.0, 0.5 * D]]), ("balls", ball, balls)]
    for name, shape, pos in (groups if tray_first else groups[::-1]):
        b.add_bodies(name, shape, m, pos)
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=60, n_frames=31)
    frames = Simulator(model).advance(model.initial_state())
    t = 0 if tray_first else 25
    ball_idx = [i for i in range(26) if i != t]
    sl = slice(model.body_sphere_start[t], model.body_sphere_start[t + 1])
    under = frames.x[-1, t] + model.sphere_offset[sl] @ quat_to_matrix(frames.q[-1, t]).T
    x = frames.x[-1, ball_idx]
    dist = np.linalg.norm(x[:, None, :] - under[None, :, :], axis=-1).min(axis=1)
    overlap = D - dist
    load = float(model.body_mass[ball_idx[0]]) * G / float(model.pair_k[m, m])
    assert np.allclose(overlap, load, rtol=0.01), (overlap / load)
