"""Prescribed motion: moving colliders, kinematic bodies, emitters.

Closed forms through real bakes on the CPU target. The scenes are built with the
Python API (scene dataclasses with a ``dempipe.sim.motion.Motion``), the same objects
the scene file's ``[colliders.motion]`` / ``[bodies.motion]`` tables load into.

Tolerances: the contacts are springs (overlap ≈ 2-5 % of d) integrated with an
explicit step, so a closed form for rigid contact holds to a few per cent; each
test says what it allows and why.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dempipe.sim import motion as mo
from dempipe.scene.build import build_model
from dempipe.sim.model import quat_to_matrix
from dempipe.scene.load import parse_scene
from dempipe.sim.simulator import Simulator

G = 9.81

BASE = """
[output]
fps = 50
duration = {duration}
[simulation]
sphere_diameter = 0.05
stiffness_target_overlap = 0.05
gravity = {gravity}
{sleep}
[materials.m]
density = 500.0
restitution = {e}
friction = {mu}
[shapes.box]
builtin = "box"
size = [0.2, 0.2, 0.1]
[shapes.ball]
builtin = "sphere"
diameter = 0.1
[shapes.pebble]
builtin = "sphere"
diameter = 0.05
"""


def scene(bodies: str, colliders: str = "", *, duration=1.0, mu=0.5, gravity=(0, 0, -G),
          sleep="", e=0.2):
    txt = BASE.format(duration=duration, mu=mu, gravity=list(gravity), sleep=sleep, e=e)
    return parse_scene(txt + bodies + colliders)


def with_collider_motion(sc, i, m):
    cols = list(sc.colliders)
    cols[i] = dataclasses.replace(cols[i], motion=m)
    return dataclasses.replace(sc, colliders=tuple(cols))


def with_group(sc, i, **kw):
    groups = list(sc.bodies)
    groups[i] = dataclasses.replace(groups[i], **kw)
    return dataclasses.replace(sc, bodies=tuple(groups))


def bake(sc):
    m = build_model(sc)
    frames = Simulator(m, device="cpu").advance(m.initial_state())
    return m, frames


BOX_ON_PLANE = """
[[bodies]]
name = "parcel"
shape = "box"
material = "m"
position = [0.0, 0.0, 0.05]
"""
PLANE = """
[[colliders]]
type = "plane"
material = "m"
"""


def test_conveyor_box_reaches_belt_speed_after_slipping_closed_form():
    """A box set down on a belt moving at V slides until it moves at V, over
    V²/(2 μ g) of ground (Coulomb friction μ m g the only horizontal force)."""
    V, mu = 1.0, 0.5
    sc = with_collider_motion(scene(BOX_ON_PLANE, PLANE, duration=0.5, mu=mu), 0,
                              mo.Motion(velocity=(V, 0.0, 0.0)))
    m, fr = bake(sc)
    assert m.surface_speed == pytest.approx(V)
    vx = fr.v[:, 0, 0]
    t = fr.times
    slipping = (vx > 0.0) & (vx < 0.97 * V)
    assert slipping.sum() >= 5, vx
    # while it slips, friction accelerates it at μ g (1 %: the spring's creep)
    k = np.flatnonzero(slipping)
    a = np.diff(vx[k]) / np.diff(t[k])
    assert np.allclose(a, mu * G, rtol=0.01), a
    # then it rides at V: no slip, no drift across the belt, still on it. As it
    # sticks, the tangential spring rings with the patch's own damping (one contact's,
    # however many spheres the face has): 2e-4 over V at first, 1e-8 ten frames later
    ride = t > 1.2 * V / (mu * G)
    assert np.allclose(vx[ride], V, rtol=1e-3)
    assert np.allclose(vx[ride][-3:], V, rtol=1e-6)
    # (across the belt: 3e-8 m/s at most while it sticks, falling to 1e-11 m/s)
    assert np.abs(fr.v[:, 0, 1]).max() < 1e-7
    assert np.abs(fr.v[-3:, 0, 1]).max() < 1e-9
    assert np.abs(fr.x[:, 0, 2] - fr.x[0, 0, 2]).max() < 0.05 * m.diameter
    # the belt ran V t under it while it covered x: it slipped V²/(2 μ g) in all
    # (2 %: the box settling onto its springs and the tangential stretch)
    slip = V * t[ride] - (fr.x[ride, 0, 0] - fr.x[0, 0, 0])
    assert np.allclose(slip, V * V / (2 * mu * G), rtol=0.02), slip


#: A turntable as a mesh: a flat cylinder, its top face at z = 0, one layer of lattice
#: spheres whose tops stand up to d/2 above it, so the box rests in their hollows on
#: contacts tilted from the axis.
DISC = """
[[colliders]]
type = "mesh"
builtin = "cylinder"
diameter = 1.0
height = 0.05
position = [0.0, 0.0, -0.025]
material = "m"
"""


def turntable(duration, table=PLANE, z=0.05):
    """A box set down at rest at r = 0.3 m, height z [m], on a table (a plane or a
    mesh) spinning at ω = 2 rad/s about z (μ = 0.6): (ω, r, model, frames)."""
    omega, r, mu = 2.0, 0.3, 0.6
    assert omega * omega * r < mu * G                      # 1.2 < 5.9: it must stay on
    bodies = BOX_ON_PLANE.replace("[0.0, 0.0, 0.05]", f"[{r}, 0.0, {z}]")
    sc = with_collider_motion(scene(bodies, table, duration=duration, mu=mu), 0,
                              mo.Motion(angular_velocity=(0.0, 0.0, omega),
                                        pivot=(0.0, 0.0, 0.0)))
    m, fr = bake(sc)
    return omega, r, m, fr


def test_turntable_carries_box_round_at_omega_r_without_sliding_off():
    """A plane spinning about its normal is a turntable: a box at radius r with
    ω² r < μ g is carried round at ω r (after a short slip from rest) and stays.

    Once it sticks nothing in the contact slips: its speed is ω times the radius
    it sits at and its spin ω, to 1e-5 (the tangential spring's ringing as it
    sticks, 1e-7 by 0.5 s), and that radius holds to 1e-5 r over the next 0.5 s.
    A tangential spring kept in fixed axes, or a table's surface velocity taken
    as the tangent ω × r while the box's is a chord of its step, let it creep
    inwards at (dt/2) ω² r, 3.5e-4 r in that time."""
    omega, r, m, fr = turntable(1.0)
    late = fr.times >= 0.5
    radius = np.linalg.norm(fr.x[late, 0, :2], axis=1)
    speed = np.linalg.norm(fr.v[late, 0, :2], axis=1)
    assert np.allclose(speed, omega * radius, rtol=1e-5)
    assert np.allclose(fr.w[late, 0, 2], omega, rtol=1e-5)
    assert np.abs(fr.w[late, 0, :2]).max() < 1e-5 * omega
    assert np.abs(radius - radius[0]).max() < 1e-5 * r
    # it slipped a little while catching up (ω r / μ g = 0.1 s, along the tangent:
    # outwards, by about (ω r)² / (2 μ g) along it, 1 % of r), never slid off
    assert np.abs(radius - r).max() < 0.02 * r
    # still resting on the table: no creep into or off the surface either
    assert np.abs(fr.x[late, 0, 2] - fr.x[-1, 0, 2]).max() < 1e-6 * m.diameter


@pytest.mark.slow
def test_turntable_holds_the_box_at_its_radius_for_ten_seconds():
    """Static friction holds a carried box where it sits, however long the table
    turns: over 9.5 s after it sticks its radius holds to 1e-5 r (measured 5e-8 r;
    the creep this guards against, (dt/2) ω² r = 2.1e-4 m/s, moved it 6.6e-3 r),
    at speed ω r and spin ω to 1e-5 (measured 6e-8)."""
    omega, r, m, fr = turntable(10.0)
    late = fr.times >= 0.5
    radius = np.linalg.norm(fr.x[late, 0, :2], axis=1)
    speed = np.linalg.norm(fr.v[late, 0, :2], axis=1)
    assert np.abs(radius - radius[0]).max() < 1e-5 * r
    assert np.allclose(speed, omega * radius, rtol=1e-5)
    assert np.allclose(fr.w[late, 0, 2], omega, rtol=1e-5)
    # and round it went: the angle it turned through is the table's, ω t, to 1e-5 rad
    # (plus the lag it took while catching up, fixed once it sticks; measured 1.6e-6
    # rad in 9.5 s, the second-order rest of the chords, about (ω dt)² / 6 of ω t)
    angle = np.unwrap(np.arctan2(fr.x[late, 0, 1], fr.x[late, 0, 0]))
    lag = omega * fr.times[late] - angle
    assert np.abs(lag - lag[0]).max() < 1e-5


@pytest.mark.slow
def test_spinning_mesh_collider_holds_the_box_at_its_radius_for_ten_seconds():
    """The same on a spinning cylinder collider: the box rests on the disc's sphere
    lattice, on contacts tilted about 30° from the axis, so each contact turns
    partly about its normal and partly with it. Over 9.5 s after it sticks its
    radius holds to 1e-5 r (measured 2.7e-6 r; with the contact point a radius out
    from each sphere's centre instead of midway across the overlap it crept inwards
    by 9e-4 r) and its height to 1e-4 d (measured 4e-7 d; it rose by 4e-4 d), at
    speed ω r and spin ω to 1e-4 (measured 1e-5). It rocks on the lattice's
    contacts at their own frequency (about 700 Hz) with an amplitude of 2e-7 rad,
    a tilting rate below 1e-3 ω (measured 5e-4 ω, as it was before the contact
    point moved): ringing, neither growing nor a drift."""
    omega, r, m, fr = turntable(10.0, DISC, z=0.076)
    late = fr.times >= 0.5
    radius = np.linalg.norm(fr.x[late, 0, :2], axis=1)
    speed = np.linalg.norm(fr.v[late, 0, :2], axis=1)
    assert np.abs(radius - radius[0]).max() < 1e-5 * r
    assert np.abs(fr.x[late, 0, 2] - fr.x[late, 0, 2][0]).max() < 1e-4 * m.diameter
    assert np.allclose(speed, omega * radius, rtol=1e-4)
    assert np.allclose(fr.w[late, 0, 2], omega, rtol=1e-4)
    assert np.abs(fr.w[late, 0, :2]).max() < 1e-3 * omega
    # it never slid off its place: within 2 % of r of where it was set down
    assert np.abs(radius - r).max() < 0.02 * r


def test_keyframed_kinematic_body_follows_its_keys_at_every_frame():
    """A kinematic body's written pose is its motion's at every frame: the keys
    themselves at key times (to float precision), the interpolation between."""
    keys = (mo.Key(0.0, (0.0, 0.0, 0.5), (1.0, 0.0, 0.0, 0.0)),
            mo.Key(0.3, (0.2, 0.0, 0.4), (math.cos(0.4), 0.0, 0.0, math.sin(0.4))),
            mo.Key(0.6, (0.2, 0.3, 0.6), (math.cos(0.9), math.sin(0.9), 0.0, 0.0)))
    bodies = BOX_ON_PLANE.replace("[0.0, 0.0, 0.05]", "[0.0, 0.0, 0.5]")
    for interp in ("linear", "smooth"):
        motion = mo.Motion(keys=keys, interpolation=interp)
        sc = with_group(scene(bodies, PLANE, duration=0.8), 0, kinematic=True, motion=motion)
        m, fr = bake(sc)
        assert m.body_kinematic[0] and m.body_static[0]
        com = m.shapes[m.body_shape[0]].com
        for k, t in enumerate(fr.times):
            P, Q, V, W = motion.anchor(t)
            x = P + quat_to_matrix(Q) @ com
            assert np.allclose(fr.x[k, 0], x, atol=1e-12), (interp, t)
            assert abs(abs(float(np.dot(fr.q[k, 0], Q))) - 1.0) < 1e-12
            assert np.allclose(fr.v[k, 0], V + np.cross(W, x - P), atol=1e-12)
            assert np.allclose(fr.w[k, 0], W, atol=1e-12)
        # at the key times themselves: the keys
        for key in keys:
            k = int(round(key.time * m.fps))
            assert np.allclose(fr.x[k, 0] - quat_to_matrix(key.rotation) @ com, key.position,
                               atol=1e-12)


@pytest.mark.slow
def test_kinematic_pusher_changes_momentum_only_while_touching():
    """Without gravity, a kinematic one-sphere pebble at V runs into a resting one:
    the dynamic pebble's momentum is 0 until they touch and constant once they
    part, at (1 + e) V (a bounce off an infinite mass moving at V); the pusher
    follows its motion whatever it hits (never pushed)."""
    bodies = """
[[bodies]]
name = "pusher"
shape = "pebble"
material = "m"
position = [-0.3, 0.0, 0.0]
[[bodies]]
name = "target"
shape = "pebble"
material = "m"
position = [0.0, 0.0, 0.0]
"""
    V, e = 2.0, 0.8
    sc = with_group(scene(bodies, "", duration=0.3, gravity=(0, 0, 0), mu=0.0, e=e), 0,
                    kinematic=True, motion=mo.Motion(velocity=(V, 0.0, 0.0)))
    m, fr = bake(sc)
    assert m.n_spheres == 2
    p = fr.v[:, 1] * m.body_mass[1]
    gap = fr.x[:, 1, 0] - fr.x[:, 0, 0] - m.diameter        # surface to surface
    # the pusher moved at V from start to end, untouched by what it hit
    assert np.allclose(fr.x[:, 0, 0], -0.3 + V * fr.times, atol=1e-12)
    assert np.all(fr.v[:, 0, 0] == V)
    # before they touch: nothing changes the target's momentum
    assert np.all(p[gap > 0.0][:3] == 0.0) and gap[0] > 0
    before = fr.times < (0.3 - m.diameter) / V - 1e-9
    assert np.all(p[before] == 0.0)
    # once parted, constant: (1 + e) V, e within 2 % (the linear law at e = 0.8, the
    # automatic step: docs/physics.md)
    apart = fr.times > (0.3 - m.diameter) / V + 2.0 * m.contact_time
    assert apart.sum() >= 5
    assert np.all(p[apart] == p[apart][0])
    assert fr.v[apart, 1, 0][0] == pytest.approx((1.0 + e) * V, rel=0.02 * e / (1 + e))


def test_emitted_group_is_absent_until_its_start_then_falls():
    """An emitter's body neither moves nor is touched before its start time: a ball
    dropped through where it waits falls freely (closed form); from the start time
    the emitted box falls from its initial pose."""
    t0 = 0.3
    bodies = """
[[bodies]]
name = "ball"
shape = "ball"
material = "m"
position = [0.0, 0.0, 1.0]
[[bodies]]
name = "late"
shape = "box"
material = "m"
position = [0.0, 0.0, 0.8]
"""
    sc = with_group(scene(bodies, "", duration=0.5, mu=0.0), 1, start_time=t0)
    m, fr = bake(sc)
    assert m.body_start_time[1] == t0 and m.body_start[1] == math.ceil(t0 / m.dt - 1e-9)
    t = fr.times
    # the ball falls through the waiting box as if it were not there: the free fall
    # of the symplectic step, z0 - g t (t + dt) / 2 (to rounding)
    assert np.allclose(fr.x[:, 0, 2], 1.0 - 0.5 * G * t * (t + m.dt), atol=1e-9)
    wait = t <= t0 + 1e-12
    assert np.all(fr.x[wait, 1] == fr.x[0, 1])
    # then it falls freely from its start step's time ts: the same, in t - ts
    ts = m.body_start[1] * m.dt
    late = t > ts
    s = t[late] - ts
    assert np.allclose(fr.x[0, 1, 2] - fr.x[late, 1, 2], 0.5 * G * s * (s + m.dt), atol=1e-9)


def test_sleeping_body_wakes_when_a_moving_collider_reaches_it():
    """A box asleep on the ground is pushed by a moving wall (a box collider's side
    sweeping in): it wakes and moves, and does not fall asleep while pushed."""
    bodies = BOX_ON_PLANE
    # box colliders' walls face inward: the parcel sits inside a pen that slides
    # +x at 0.5 m/s, so the pen's -x wall comes up behind it
    walls = PLANE + """
[[colliders]]
type = "box"
name = "pen"
min = [-0.6, -1.0, -0.5]
max = [0.6, 1.0, 1.0]
material = "m"
"""
    sc = scene(bodies, walls, duration=1.5, mu=0.3, sleep="sleeping = true")
    sc = with_collider_motion(sc, 1, mo.Motion(velocity=(0.5, 0.0, 0.0)))
    sc = with_group(sc, 0, starts_asleep=True)
    m, fr = bake(sc)
    assert m.sleep_steps > 0
    x = fr.x[:, 0, 0]
    # asleep and still until the pen's left wall (at -0.6 + 0.5 t) reaches the box's
    # left face (-0.1): t = 1.0 s
    early = fr.times < 0.95
    assert np.all(x[early] == x[0])
    late = fr.times > 1.1
    assert np.all(x[late] > x[0] + 0.02)
    # pushed along at the wall's speed (it never dozed off against the moving wall)
    assert np.allclose(fr.v[fr.times > 1.2, 0, 0], 0.5, rtol=0.05)


ROOT = __import__("pathlib").Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("example, moving", [("conveyor.toml", "roller0"),
                                             ("wrecking_ball.toml", None),
                                             ("wall_breach.toml", None)])
def test_examples_bake_a_short_range(tmp_path, example, moving):
    """The README's prescribed-motion examples bake (a real subprocess, the first
    frames) to a stage that validates, with the moving colliders animated."""
    import subprocess
    import sys

    from pxr import Usd, UsdGeom, UsdValidation

    out = tmp_path / "out.usda"
    proc = subprocess.run([sys.executable, "-c", "from dempipe_cli.main import main; main()",
                           "bake", str(ROOT / "examples" / example), "-o", str(out),
                           "--frames", "0:2", "-q", "--layout", "xforms"],
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr
    stage = Usd.Stage.Open(str(out))
    reg = UsdValidation.ValidationRegistry()
    ctx = UsdValidation.ValidationContext(reg.GetOrLoadAllValidators())
    errors = [e for e in ctx.Validate(stage)
              if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert not errors, [e.GetMessage() for e in errors]
    if moving:
        prim = next(p for p in stage.Traverse() if p.GetName() == moving)
        xf = UsdGeom.Xformable(prim)
        a = xf.ComputeLocalToWorldTransform(0.0)
        b = xf.ComputeLocalToWorldTransform(2.0)
        assert a != b                          # a roller turns


HAIL = """
[[bodies]]
name = "hail"
shape = "pebble"
material = "m"
layout = "emit"
count = 5
region_min = [-0.5, -0.5, 1.0]
region_max = [0.5, 0.5, 1.2]
"""


def test_emit_layout_releases_bodies_at_its_rate():
    """layout = "emit": count bodies, body i entering at start_time + i / rate at a
    seeded random place in the region; each waits unmoved, then falls freely."""
    bodies = HAIL + "rate = 20.0\nstart_time = 0.1\n"
    sc = scene(bodies, "", duration=0.5, mu=0.0)
    m, fr = bake(sc)
    starts = 0.1 + np.arange(5) / 20.0
    assert np.allclose(m.body_start_time, starts)
    assert np.array_equal(m.body_start, np.ceil(starts / m.dt - 1e-9).astype(np.int64))
    t = fr.times
    for b in range(5):
        ts = m.body_start[b] * m.dt
        wait = t <= ts + 1e-12
        assert np.all(fr.x[wait, b] == fr.x[0, b])
        s = t[t > ts] - ts
        drop = fr.x[0, b, 2] - fr.x[t > ts, b, 2]
        assert np.allclose(drop, 0.5 * G * s * (s + m.dt), atol=1e-9)


@pytest.mark.parametrize("extra, key, words", [
    ("rate = 0.0\n", "rate", "out of range"),
    ("", "rate", "missing"),
    ("rate = 5.0\nkinematic = true\n", "kinematic", "cannot be kinematic"),
])
def test_emit_layout_bad_values_name_the_key(extra, key, words):
    from dempipe.errors import SceneError

    bodies = HAIL + extra
    with pytest.raises(SceneError) as err:
        scene(bodies, "")
    assert f"bodies[0].{key}" in str(err.value) and words in str(err.value), str(err.value)


EMITTED_BOX = """
[[bodies]]
name = "waiting"
shape = "box"
material = "m"
position = [0.0, 0.0, 0.05]

[[bodies]]
name = "parcel"
shape = "box"
material = "m"
position = [0.0, 0.0, 0.4]
"""

FLOORS = {
    "plane": PLANE,
    "box collider": """
[[colliders]]
type = "box"
min = [-1.0, -1.0, 0.0]
max = [1.0, 1.0, 2.0]
material = "m"
""",
    "static mesh": """
[[colliders]]
type = "mesh"
builtin = "box"
size = [1.0, 1.0, 0.1]
position = [0.0, 0.0, -0.05]
material = "m"
""",
    "moving mesh": """
[[colliders]]
type = "mesh"
builtin = "box"
size = [1.0, 1.0, 0.1]
position = [0.0, 0.0, -0.05]
material = "m"
[colliders.motion]
angular_velocity = [0.0, 0.0, 0.5]
""",
}


@pytest.mark.parametrize("sleeping", [True, False], ids=["sleeping", "no sleeping"])
@pytest.mark.parametrize("floor", list(FLOORS))
def test_an_emitted_body_meets_what_is_there_from_its_first_step(floor, sleeping):
    """A box emitted at 0.1 s above another resting on the floor (a plane, a box
    collider's floor, a static mesh, a mesh turning slowly) lands on it and rests
    there, with sleeping on and off: from its first step its spheres move with it
    and every contact sees it (a parked body's spheres are kept still until it
    starts, and then must follow it whatever the sleeping)."""
    sleep = "sleeping = true" if sleeping else "sleeping = false"
    sc = scene(EMITTED_BOX, FLOORS[floor], duration=1.5, mu=0.5, sleep=sleep)
    sc = with_group(sc, 1, start_time=0.1)
    m, fr = bake(sc)
    assert m.body_start[1] > 0
    # waiting until 0.1 s exactly where it was placed, then falling
    early = fr.times < 0.1 - 1e-9
    assert np.all(fr.x[early, 1] == fr.x[0, 1])
    # at the end: on the lower box (its base at the lower box's top, 0.1 m) and at rest,
    # the lower box on the floor; within 5% of d (the contacts' overlap under the load)
    assert fr.x[-1, 0, 2] == pytest.approx(0.05, abs=0.05 * m.diameter)
    assert fr.x[-1, 1, 2] == pytest.approx(0.15, abs=0.05 * m.diameter)
    if floor != "moving mesh":
        assert np.linalg.norm(fr.v[-1], axis=-1).max() < 1e-3
