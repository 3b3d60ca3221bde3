"""Leave out what a scene does not need.

4. Sparse output: a body that never moves gets its transform once, with no time
   samples; a run of identical samples keeps only its first and last. Whatever is
   left out, the stage must read back (pxr, at every frame) the same transforms as
   the dense stage (``sparse=False``) and as the Frames, in both layouts.
5. Empty space costs nothing: the CPU backend's grid memory follows the number of
   spheres, not the bounding box of the scene.
6. Imports: the CLI's light commands import neither pxr nor numba (nor
   numba.cuda), and ``import dempipe`` compiles nothing. (Already tested
   elsewhere, not repeated here: ``dempipe check`` with a warm sphere cache
   (tests/cli/test_cli_check.py), ``dempipe spheres`` (tests/cli/test_cli_spheres.py),
   ``import dempipe`` + a CPU bake without numba.cuda (tests/sim/test_cuda.py).)
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import numpy as np
import pytest
import trimesh

pxr = pytest.importorskip("pxr")
from pxr import Usd, UsdGeom  # noqa: E402

from bodies import ball_set, box_set  # noqa: E402
from dempipe.usd.animation import write_usd  # noqa: E402
from dempipe.sim.frames import Frames  # noqa: E402
from dempipe.sim.materials import Material  # noqa: E402
from dempipe.sim.builder import ModelBuilder  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
D = 0.01
LAYOUTS = ("instancer", "xforms")

# PointInstancer orientations are quath: a rotation error up to ~1e-3 rad (see
# tests/usd/test_animation.py). The xforms layout writes quatf (~1e-7 per component),
# but USD turns an orient op into a matrix through an angle 2 acos(w): for a body
# turned by a small angle, w is within a few float32 ulps of 1 and the angle
# read back is off by up to ~2.4e-4 rad (measured: 0.0003 rad reads as 0).
ROT_TOL = {"instancer": 2e-3, "xforms": 5e-4}


# ------------------------------------------------------------------ helpers


def quat_matrix(q):
    """(..., 4) quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices (column vectors)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def body_paths(model):
    names = model.group_names
    return [f"/World/Bodies/{names[g]}/{names[g]}_{i}"
            for g, i in zip(model.body_group, model.body_group_index)]


def read_transforms(path, model, times, layout):
    """(T, B, 4, 4) body-to-world matrices (USD row-vector convention) read back
    with pxr at each time code of ``times``: PointInstancer.
    ComputeInstanceTransformsAtTime (which moves a sample on by its velocities, as
    a renderer does for motion blur), or the body Xform's local-to-world transform."""
    stage = Usd.Stage.Open(str(path))
    out = np.zeros((len(times), model.n_bodies, 4, 4))
    paths = body_paths(model)
    for k, time in enumerate(times):
        t = Usd.TimeCode(float(time))
        if layout == "instancer":
            pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
            mats = pi.ComputeInstanceTransformsAtTime(t, t)
            out[k] = np.array([np.array(m) for m in mats])
        else:
            cache = UsdGeom.XformCache(t)
            for b, p in enumerate(paths):
                out[k, b] = np.array(cache.GetLocalToWorldTransform(stage.GetPrimAtPath(p)))
    return out


def read_attributes(path, frames, layout, model):
    """Every animated attribute's value at every frame time: {name: (F, ...) array}."""
    stage = Usd.Stage.Open(str(path))
    times = [Usd.TimeCode(float(fn)) for fn in frames.frame_numbers]
    if layout == "instancer":
        prim = stage.GetPrimAtPath("/World/Bodies")
        names = ("positions", "orientations", "velocities", "angularVelocities", "extent")
        return {n: np.array([np.array(prim.GetAttribute(n).Get(t), dtype=np.float64)
                             for t in times]) for n in names}
    out = {}
    for b, p in enumerate(body_paths(model)):
        prim = stage.GetPrimAtPath(p)
        out[f"{p}.translate"] = np.array([tuple(prim.GetAttribute("xformOp:translate").Get(t))
                                          for t in times])
        out[f"{p}.orient"] = np.array([
            [q.GetReal(), *q.GetImaginary()] for q in
            (prim.GetAttribute("xformOp:orient").Get(t) for t in times)])
    return out


def sample_times(path, attr_path):
    stage = Usd.Stage.Open(str(path))
    prop = stage.GetAttributeAtPath(attr_path)
    return [float(t) for t in prop.GetTimeSamples()]


def assert_same_as_frames(mats, model, frames, layout):
    """Matrices read back against the Frames: centre of mass and rotation."""
    mpu = float(model.meters_per_unit)
    np.testing.assert_allclose(mats[..., 3, :3], frames.x / mpu, rtol=1e-6, atol=1e-7)
    # USD: p' = p M, so the upper 3×3 is Rᵀ.
    rot = np.swapaxes(mats[..., :3, :3], -1, -2)
    err = np.abs(rot - quat_matrix(frames.q)).max()
    assert err < ROT_TOL[layout], err


def assert_sparse_reads_like_dense(tmp_path, model, frames, layout, ext=".usdc"):
    """Write sparse and dense; both read back the same transforms and attribute
    values at every frame, and the same as the Frames. Between frames (where a
    renderer samples motion blur) sparse and dense agree too. Returns the infos."""
    sparse = write_usd(tmp_path / f"sparse_{layout}{ext}", frames, model, layout=layout)
    dense = write_usd(tmp_path / f"dense_{layout}{ext}", frames, model, layout=layout,
                      sparse=False)
    assert sparse.n_time_samples <= dense.n_time_samples
    fn = frames.frame_numbers.astype(np.float64)
    times = np.concatenate([fn, fn[:-1] + 0.25, fn[:-1] + 0.5])
    m_sparse = read_transforms(sparse.path, model, times, layout)
    m_dense = read_transforms(dense.path, model, times, layout)
    # Between two equal samples a translation's lerp is exact; a quaternion's slerp
    # renormalizes in its own precision: float rounding of the stored type.
    np.testing.assert_allclose(m_sparse, m_dense, rtol=0,
                               atol=1e-3 if layout == "instancer" else 1e-6)
    # translations: a PointInstancer moves a kept sample on by the velocity of that
    # sample, which for a body at rest is float noise (~1e-13 m/s): nothing visible
    np.testing.assert_allclose(m_sparse[..., 3, :3], m_dense[..., 3, :3], rtol=0, atol=1e-9)
    n = frames.n_frames
    assert_same_as_frames(m_sparse[:n], model, frames, layout)
    assert_same_as_frames(m_dense[:n], model, frames, layout)
    a_sparse = read_attributes(sparse.path, frames, layout, model)
    a_dense = read_attributes(dense.path, frames, layout, model)
    assert a_sparse.keys() == a_dense.keys()
    # Reading between two equal samples interpolates, (1 - a) x + a x: one ulp off
    # (the documented "exact" holds to the last bit of the stored type).
    for name in a_dense:
        if name == "orientations":                             # quath: 2^-11 near 1
            tol = dict(rtol=0, atol=2.0**-11)
        elif name.endswith("orient"):                          # quatf
            tol = dict(rtol=0, atol=1e-7)
        elif name.endswith("translate"):                       # double
            tol = dict(rtol=4e-16, atol=1e-300)
        else:                                                  # float32
            tol = dict(rtol=2.4e-7, atol=1e-30)
        np.testing.assert_allclose(a_sparse[name], a_dense[name], err_msg=name, **tol)
    if layout == "instancer":
        assert_rates_aligned(sparse.path)
    return sparse, dense


def assert_rates_aligned(path):
    """USD uses a PointInstancer's velocities (angular velocities) only where they
    have samples at the same times as its positions (orientations); anywhere else
    it ignores them (no motion blur from them) and warns."""
    for moving, rate in (("positions", "velocities"), ("orientations", "angularVelocities")):
        t_moving = sample_times(path, f"/World/Bodies.{moving}")
        if t_moving:
            assert sample_times(path, f"/World/Bodies.{rate}") == t_moving, (moving, rate)


# ---------------------------------------------- 4a. sparse output, exact motion


def _shape(name, mesh):
    return types.SimpleNamespace(name=name, vertices=np.asarray(mesh.vertices - mesh.center_mass),
                                 faces=np.asarray(mesh.faces))


FIRST = 101         # time codes need not start at 0
N_FRAMES = 14

# What each body of the analytic scene does, frame by frame (True = moves into this frame).
STATIC = 0          # never moves, identity orientation, placed on the axes (x = y = 0)
STATIC_TILTED = 1   # never moves, tilted
SETTLES = 2         # moves, then rests from frame 5 to the end
PAUSES = 3          # moves, rests over frames 4..9, moves again
STARTS_LATE = 4     # rests over frames 0..7, then moves
MOVES = 5           # moves every frame
WOBBLES = 6         # rests in place, but only turns (orientation samples, no translation ones)


def analytic_model():
    cone = trimesh.creation.cone(radius=0.04, height=0.12)        # COM off the mesh origin
    shapes = (_shape("brick", trimesh.creation.box(extents=(0.10, 0.06, 0.04))),
              _shape("cone", cone))
    n = 7
    return types.SimpleNamespace(
        shapes=shapes, n_bodies=n, body_shape=np.array([0, 1, 0, 1, 0, 1, 0]),
        body_group=np.array([0, 0, 0, 1, 1, 1, 1]), group_names=("still", "busy"),
        body_group_index=np.array([0, 1, 2, 0, 1, 2, 3]),
        plane_point=np.zeros((1, 3)), plane_normal=np.array([[0.0, 0.0, 1.0]]),
        boxes=(), static_meshes=(), fps=24.0, up_axis="Z", meters_per_unit=1.0)


def analytic_frames():
    """Bodies that never move, settle, pause, start late, always move, only turn.

    Resting stretches repeat the previous sample bit for bit (as the simulator's
    state does once increments fall below the rounding of the position), and a
    resting body has zero velocity.
    """
    rng = np.random.default_rng(8)
    n, F = 7, N_FRAMES
    moving = np.ones((F, n), dtype=bool)
    moving[0] = False                                  # frame 0 is where motion starts
    moving[:, [STATIC, STATIC_TILTED, WOBBLES]] = False
    moving[5:, SETTLES] = False
    moving[4:10, PAUSES] = False
    moving[:8, STARTS_LATE] = False
    turning = moving.copy()
    turning[1:, WOBBLES] = True
    turning[1:4, WOBBLES] = False                       # its first frames: at rest
    vel = rng.uniform(-1, 1, (n, 3))
    omega = rng.uniform(-5, 5, (n, 3))
    x = np.zeros((F, n, 3))
    q = np.zeros((F, n, 4))
    x[0] = rng.uniform(0.1, 0.9, (n, 3))
    x[0, STATIC] = [0.0, 0.0, 0.3]
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = rng.uniform(0.3, 3.0, n)
    q[0] = np.concatenate([np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None] * axis], 1)
    q[0, STATIC] = [1.0, 0.0, 0.0, 0.0]
    dt = 1 / 24
    for f in range(1, F):
        x[f] = np.where(moving[f][:, None], x[f - 1] + vel * dt, x[f - 1])
        half = 0.5 * np.linalg.norm(omega, axis=1) * dt
        dq = np.concatenate([np.cos(half)[:, None],
                             np.sin(half)[:, None] * omega / np.linalg.norm(omega, axis=1)[:, None]],
                            1)
        w0, v0 = dq[:, :1], dq[:, 1:]
        w1, v1 = q[f - 1, :, :1], q[f - 1, :, 1:]
        turned = np.concatenate([w0 * w1 - np.sum(v0 * v1, 1, keepdims=True),
                                 w0 * v1 + w1 * v0 + np.cross(v0, v1)], 1)
        q[f] = np.where(turning[f][:, None], turned, q[f - 1])
    v = np.where(moving[..., None], vel[None], 0.0)
    w = np.where(turning[..., None], omega[None], 0.0)
    fn = np.arange(FIRST, FIRST + F, dtype=np.int64)
    return Frames(fn, (fn - FIRST) / 24.0, x, q, v, w)


@pytest.mark.parametrize("ext", [".usdc", ".usda"])
@pytest.mark.parametrize("layout", LAYOUTS)
def test_sparse_reads_back_like_dense_and_frames(tmp_path, layout, ext):
    model, frames = analytic_model(), analytic_frames()
    sparse, dense = assert_sparse_reads_like_dense(tmp_path, model, frames, layout, ext)
    if layout == "xforms":          # per body; the instancer's arrays all move here
        assert sparse.n_time_samples < dense.n_time_samples
        assert sparse.bytes < dense.bytes


def test_xforms_samples_left_out(tmp_path):
    """Per body: no samples when it never moves; only the ends of each resting run."""
    model, frames = analytic_model(), analytic_frames()
    path = write_usd(tmp_path / "s.usda", frames, model, layout="xforms").path
    paths = body_paths(model)
    T = [float(FIRST + f) for f in range(N_FRAMES)]
    last = N_FRAMES - 1

    def kept(body, op):
        return sample_times(path, f"{paths[body]}.xformOp:{op}")

    def frames_kept(*ranges):
        return [T[f] for r in ranges for f in r]

    for body in (STATIC, STATIC_TILTED):                  # the transform once, as a default
        stage = Usd.Stage.Open(str(path))
        prim = stage.GetPrimAtPath(paths[body])
        for op in ("translate", "orient"):
            assert kept(body, op) == []
            assert prim.GetAttribute(f"xformOp:{op}").HasAuthoredValue()
    # rests from frame 4 (the last move lands there) to the end: keep 4 and the last
    for op in ("translate", "orient"):
        assert kept(SETTLES, op) == frames_kept(range(0, 5), [last])
        # rests over 3..9 (last move lands at 3, next move leaves after 9)
        assert kept(PAUSES, op) == frames_kept(range(0, 4), [9], range(10, N_FRAMES))
        # rests over 0..7, moves from 8 on
        assert kept(STARTS_LATE, op) == frames_kept([0, 7], range(8, N_FRAMES))
        assert kept(MOVES, op) == T
    # only turns: the translation is a default, the orientation keeps the run ends
    assert kept(WOBBLES, "translate") == []
    assert kept(WOBBLES, "orient") == frames_kept([0, 3], range(4, N_FRAMES))


def resting_tail(frames, rest=9, noise=False):
    """``frames`` with every body at rest from frame ``rest`` on; with ``noise``, the
    float noise a simulator leaves on bodies at rest (speeds of 1e-13 m/s and
    spins of 1e-14 rad/s that change every frame)."""
    keep = np.minimum(np.arange(frames.n_frames), rest)
    still = (np.arange(frames.n_frames) >= rest)[:, None, None]
    v = np.where(still, 0.0, frames.v[keep])
    w = np.where(still, 0.0, frames.w[keep])
    if noise:
        rng = np.random.default_rng(1)
        v = v + still * rng.normal(scale=1e-13, size=v.shape)
        w = w + still * rng.normal(scale=1e-14, size=w.shape)
    return Frames(frames.frame_numbers, frames.times, frames.x[keep], frames.q[keep], v, w)


@pytest.mark.parametrize("noise", [False, True], ids=["exact", "noise"])
def test_instancer_arrays_stop_when_every_body_rests(tmp_path, noise):
    """Instancer: the arrays are left out only while every body is still; here
    every body rests from frame 9 on, so each animated array ends with one run."""
    model = analytic_model()
    frames = resting_tail(analytic_frames(), noise=noise)
    sparse, _ = assert_sparse_reads_like_dense(tmp_path, model, frames, "instancer")
    T = [float(FIRST + f) for f in range(N_FRAMES)]
    for name in ("positions", "orientations", "velocities", "angularVelocities", "extent"):
        assert sample_times(sparse.path, f"/World/Bodies.{name}") == T[:10] + [T[-1]], name
    stage = Usd.Stage.Open(str(sparse.path))
    pi = stage.GetPrimAtPath("/World/Bodies")
    for name in ("protoIndices", "ids"):
        assert pi.GetAttribute(name).GetNumTimeSamples() == 0
    for name in ("velocities", "angularVelocities"):                # noise written as 0
        assert not np.any(np.array(pi.GetAttribute(name).Get(T[-1])))


def test_float_noise_at_rest_is_left_out(tmp_path):
    """A body at rest carries float noise far below what the file can hold: a
    coordinate of 1e-22 m on an axis, quaternion components of 1e-18 on a box
    lying flat. That noise is not motion: the body still gets no samples."""
    model, frames = analytic_model(), analytic_frames()
    x, q = frames.x.copy(), frames.q.copy()
    noise = 1e-22 * np.arange(N_FRAMES)
    x[:, STATIC, 0] = noise                                 # drifts around x = 0
    q[:, STATIC_TILTED] = [0.0, -0.06027, -0.99818, 0.0]    # lying flat, turned over
    q[:, STATIC_TILTED, 0] = -5e-18 - 1e-20 * np.arange(N_FRAMES)
    q[:, STATIC_TILTED, 3] = -1.7e-18 - 2e-21 * np.arange(N_FRAMES)
    frames = Frames(frames.frame_numbers, frames.times, x, q, frames.v, frames.w)
    for layout in LAYOUTS:
        assert_sparse_reads_like_dense(tmp_path, model, frames, layout)
    path = write_usd(tmp_path / "noise.usda", frames, model, layout="xforms").path
    for body in (STATIC, STATIC_TILTED):
        for op in ("translate", "orient"):
            assert sample_times(path, f"{body_paths(model)[body]}.xformOp:{op}") == []


def test_instancer_rates_are_kept_where_motion_is_sampled(tmp_path, capfd):
    """Free flight without gravity: every body drifts and spins at a constant
    rate, so velocities and angular velocities never change while positions and
    orientations do. The rates still get a sample at every frame: that is where a
    renderer looks for them (motion blur between frames)."""
    model = analytic_model()
    rng = np.random.default_rng(5)
    n, F = model.n_bodies, N_FRAMES
    fn = np.arange(FIRST, FIRST + F, dtype=np.int64)
    t = (fn - FIRST) / 24.0
    vel, omega = rng.uniform(-1, 1, (n, 3)), rng.uniform(-5, 5, (n, 3))
    x = rng.uniform(-1, 1, (n, 3))[None] + t[:, None, None] * vel[None]
    rate = np.linalg.norm(omega, axis=1)
    half = 0.5 * t[:, None] * rate[None]                    # spin about a fixed world axis
    q = np.concatenate([np.cos(half)[..., None],
                        np.sin(half)[..., None] * (omega / rate[:, None])[None]], -1)
    frames = Frames(fn, t, x, q, np.broadcast_to(vel, (F, n, 3)).copy(),
                    np.broadcast_to(omega, (F, n, 3)).copy())
    sparse, _ = assert_sparse_reads_like_dense(tmp_path, model, frames, "instancer")
    T = [float(f) for f in fn]
    for name in ("positions", "orientations", "velocities", "angularVelocities"):
        assert sample_times(sparse.path, f"/World/Bodies.{name}") == T, name
    # half-way between frames the instances are moved on by their velocities
    mats = read_transforms(sparse.path, model, fn[:-1] + 0.5, "instancer")
    np.testing.assert_allclose(mats[..., 3, :3], x[:-1] + vel * (0.5 / 24), rtol=1e-6, atol=1e-6)
    assert "not aligned" not in capfd.readouterr().err


# ---------------------------------------- 4b. sparse output of a real simulation


@pytest.fixture(scope="module")
def simulated():
    """A short bake mixing a static collider, bodies that come to rest and one that
    keeps moving: cubes dropped (randomly turned) onto a plane, a cube sliding to
    a stop, a ball rolling across the plane, and a static mesh slab."""
    from dempipe.sim.simulator import Simulator

    b = ModelBuilder(D)
    cube_set, cube_mesh = box_set(3, 3, 2, D)
    ball_s, ball_mesh = ball_set(D)
    cube = b.add_shape("cube", cube_mesh, cube_set)
    ball = b.add_shape("ball", ball_mesh, ball_s)
    m = b.add_material(Material("wood", density=1000, restitution=0.2, friction=0.8))
    rng = np.random.default_rng(3)
    rot = rng.normal(size=(3, 4))
    b.add_bodies("cubes", cube, m, [[0.11, 0.13, 0.03], [0.21, 0.23, 0.05], [-0.12, 0.17, 0.03]],
                 rotations=rot / np.linalg.norm(rot, axis=1, keepdims=True),
                 velocities=[[0, 0, 0], [0, 0, 0], [0.4, 0.1, 0]])
    b.add_bodies("balls", ball, m, [[-0.31, -0.17, D / 2]], velocities=[[0.5, 0.2, 0]])
    slab_set, slab_mesh = box_set(6, 6, 2, D)
    centre = np.array([0.5, 0.5, 0.01])
    slab_set.com = centre              # the builder places the set's centres about its com
    slab_mesh.vertices = slab_mesh.vertices + centre
    b.add_static_mesh("slab", slab_mesh, slab_set, m)
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    # 1.5 s: the cubes, landing with e = 0.2 on whole faces (one contact patch each),
    # are at rest by about 1.1 s
    model = b.finalize(fps=24, n_frames=37, target_overlap=0.05)
    frames = Simulator(model).advance(model.initial_state())
    return model, frames


@pytest.mark.parametrize("layout", LAYOUTS)
def test_simulated_scene_sparse_reads_back_like_dense(tmp_path, simulated, layout):
    model, frames = simulated
    sparse, dense = assert_sparse_reads_like_dense(tmp_path, model, frames, layout)
    assert sparse.bytes <= dense.bytes
    stage = Usd.Stage.Open(str(sparse.path))
    colliders = stage.GetPrimAtPath("/World/Colliders")
    assert colliders and [c.GetName() for c in colliders.GetChildren()] == ["plane_0", "slab"]
    for prim in Usd.PrimRange(colliders):                  # static geometry: never sampled
        for attr in prim.GetAttributes():
            assert attr.GetNumTimeSamples() == 0, attr.GetPath()


def test_simulated_bodies_at_rest_stop_producing_samples(tmp_path, simulated):
    """xforms layout: each cube that comes to rest stops producing samples (its
    run of identical frames keeps only its ends); the rolling ball never rests."""
    model, frames = simulated
    path = write_usd(tmp_path / "s.usda", frames, model, layout="xforms").path
    paths = body_paths(model)
    n = frames.n_frames
    speeds = np.linalg.norm(frames.v[-1], axis=1)
    assert speeds[3] > 0.1 and speeds[:3].max() < 1e-9          # ball rolls, cubes rest
    last = [float(f) for f in frames.frame_numbers[-3:]]
    for b in range(3):
        for op in ("translate", "orient"):
            kept = sample_times(path, f"{paths[b]}.xformOp:{op}")
            assert kept[-1] == last[-1] and last[0] not in kept and last[1] not in kept, (b, op)
    for op in ("translate", "orient"):
        assert len(sample_times(path, f"{paths[3]}.xformOp:{op}")) == n


# ------------------------------------------------------ 5. empty space is free


def _balls_model(centres):
    """One-sphere balls at ``centres`` (no gravity, touching in pairs when asked)."""
    b = ModelBuilder(D, gravity=(0.0, 0.0, 0.0))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.0,
                                stiffness=1e3))
    b.add_bodies("balls", s, m, centres)
    return b.finalize(fps=24, n_frames=2)


def _pairs(anchors):
    """Two balls per anchor, overlapping by 10% of a diameter along x."""
    a = np.repeat(np.asarray(anchors, dtype=np.float64), 2, axis=0)
    a[1::2, 0] += 0.9 * D
    return a


def _compact_and_spread(n_pairs, seed=0):
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.cbrt(n_pairs)))
    ijk = np.stack(np.unravel_index(np.arange(n_pairs), (side, side, side)), -1)
    compact = _pairs(ijk * 3 * D)                                # a 3-diameter lattice
    spread = _pairs(rng.uniform(-500.0, 500.0, (n_pairs, 3)))    # over a kilometre cube
    return _balls_model(compact), _balls_model(spread)


def _array_bytes(backend):
    """Bytes of every NumPy array a CpuBackend holds: {name: nbytes}."""
    return {k: v.nbytes for k, v in vars(backend).items() if isinstance(v, np.ndarray)}


GRID_ARRAYS = ("bucket_start", "bucket_blocks")


def test_grid_memory_follows_spheres_not_extent():
    from dempipe.sim.kernels.layout import BUCKETS_PER_SPHERE
    from dempipe.sim.kernels.cpu.backend import CpuBackend

    compact, spread = _compact_and_spread(500)
    assert compact.n_spheres == spread.n_spheres == 1000
    extent = lambda m: np.ptp(m.initial_state().body_x[: m.n_bodies], axis=0)
    assert extent(compact).max() < 0.5 and extent(spread).min() > 900.0
    be_c, be_s = CpuBackend(compact), CpuBackend(spread)
    bytes_c, bytes_s = _array_bytes(be_c), _array_bytes(be_s)
    assert bytes_c == bytes_s                                  # every array, grid or not
    for name in GRID_ARRAYS:
        assert name in bytes_s
    # the budget: the smallest power of two >= 8 buckets per sphere, 8 bytes each
    budget = 2 * BUCKETS_PER_SPHERE * spread.n_spheres
    assert be_s.bucket_start.size <= budget + 1
    # a dense grid over the spread scene's box would need (1000 m / 1 cm)^3 cells
    dense_cells = np.prod(np.ceil(extent(spread) / D))
    assert dense_cells > 1e9 * be_s.bucket_start.size

    # fitting the grid to the scene never asks for more buckets than were allocated
    for be, model in ((be_c, compact), (be_s, spread)):
        be.fit_grid(model.initial_state())
        assert 0 < be.grid[5] < be.bucket_start.size


def test_grid_memory_scales_with_sphere_count():
    from dempipe.sim.kernels.cpu.backend import CpuBackend

    small = sum(_array_bytes(CpuBackend(_compact_and_spread(250)[1])).values())
    large = sum(_array_bytes(CpuBackend(_compact_and_spread(4000)[1])).values())
    # 16× the spheres: 16× the memory, within the power-of-two rounding of the table
    assert 8 < large / small < 32


def test_spread_scene_finds_the_same_contacts():
    """Cells a kilometre apart share buckets; contacts are still told apart by
    their keys: every pair feels the same force as in the compact scene."""
    from dempipe.sim.kernels.cpu.backend import CpuBackend

    compact, spread = _compact_and_spread(200)
    forces = []
    for model in (compact, spread):
        be = CpuBackend(model)
        state = model.initial_state()
        be.probe(state)
        forces.append(be.sphere_f[: model.n_spheres].copy())
    f_c, f_s = forces
    assert np.all(np.abs(f_c[:, 0]) > 0)                       # every ball touches its partner
    np.testing.assert_allclose(f_s, f_c, rtol=1e-6, atol=1e-9 * np.abs(f_c).max())
    np.testing.assert_allclose(f_c[0::2], -f_c[1::2], rtol=1e-12)   # and nothing else


# ------------------------------------------------------------------ 6. imports

HEAVY = ("pxr", "numba", "numba.cuda", "dempipe.sim.kernels", "dempipe.sim.kernels.cpu.stages",
         "dempipe.sim.kernels.cuda.backend", "dempipe.usd.animation")


def _run_and_list_modules(body: str, *args, env=None):
    """Run ``body`` in a fresh interpreter, then print which HEAVY modules it imported."""
    code = textwrap.dedent(body) + textwrap.dedent(f"""
        import sys as _sys
        print("IMPORTED", sorted(m for m in {HEAVY!r} if m in _sys.modules), file=_sys.stderr)
    """)
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          timeout=300, env=env or dict(os.environ), cwd=ROOT)
    line = [s for s in proc.stderr.splitlines() if s.startswith("IMPORTED ")]
    assert line, proc.stderr[-3000:]
    return proc, eval(line[-1][len("IMPORTED "):])


CLI = """
    import sys
    from dempipe_cli.main import main
    try:
        main(sys.argv[1:])
    except SystemExit as exc:
        assert not exc.code, exc.code
"""


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["bake", "--help"],
                                  ["check", "--help"], ["spheres", "--help"],
                                  ["cache", "--help"]],
                         ids=" ".join)
def test_help_imports_neither_pxr_nor_numba(argv):
    proc, imported = _run_and_list_modules(CLI, *argv)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert imported == []
    assert "Traceback" not in proc.stderr
    if argv == ["--help"]:
        for cmd in ("bake", "check", "spheres", "cache"):
            assert cmd in proc.stdout


def test_import_dempipe_imports_and_compiles_nothing_heavy():
    proc, imported = _run_and_list_modules("""
        import dempipe
        assert dempipe.__version__
        dempipe.SceneError, dempipe.ExportError                  # cheap names stay cheap
    """)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert imported == []


def test_importing_the_cpu_kernels_compiles_nothing():
    # numba compiles (or loads from its cache) at the first call, never at import:
    # a kernel module costs its import, and a command that never steps never pays.
    proc, imported = _run_and_list_modules("""
        from numba.core.registry import CPUDispatcher
        from dempipe.sim.kernels.cpu import stages as cpu
        from dempipe.sim.simulator import Simulator
        kernels = {k: v for k, v in vars(cpu).items() if isinstance(v, CPUDispatcher)}
        assert kernels, 'no numba kernels found in dempipe.sim.kernels.cpu.stages'
        compiled = {k: v.signatures for k, v in kernels.items() if v.signatures}
        assert not compiled, compiled
    """)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "numba.cuda" not in imported and "pxr" not in imported


def test_check_with_a_cold_sphere_cache_imports_no_pxr_nor_cuda(tmp_path):
    # With the sphere sets cached, `dempipe check` imports no numba at all
    # (tests/cli/test_cli_check.py). On a cache miss it voxelizes the shapes, which
    # needs numba's CPU target, but still neither pxr nor numba.cuda.
    env = dict(os.environ, DEMPIPE_CACHE_DIR=str(tmp_path / "empty-cache"))
    proc, imported = _run_and_list_modules(CLI, "check", str(ROOT / "examples/quickstart.toml"),
                                           env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "quickstart.toml: OK" in proc.stdout
    assert "pxr" not in imported and "numba.cuda" not in imported
    assert "dempipe.sim.kernels.cuda.backend" not in imported and "dempipe.usd.animation" not in imported
    assert list((tmp_path / "empty-cache").glob("*.npz"))        # it did voxelize
