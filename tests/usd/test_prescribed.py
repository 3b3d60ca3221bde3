"""Animated colliders and emitted bodies in the USD output (usd/prescribed.py,
usd/animation.py), read back with pxr.

The model is test_export_usd's SimpleNamespace with the two fields of prescribed motion
added: ``collider_motions`` (kind, index, motion, ref_p, ref_q, origin, rotation)
and ``body_start_time``. Expected poses are written out independently of
dempipe.sim.motion: a rotation about a pivot by ω t plus v t, and the keys' own poses
at key times.
"""

from __future__ import annotations

import types

import numpy as np
import pytest
from pxr import Usd, UsdGeom
from test_animation import FIRST, FPS, _apply, _quat_matrix, make_frames, make_model, \
    validation_issues

from dempipe.usd.prescribed import collider_xforms, first_shown_frame, plane_xforms
from dempipe.usd.animation import write_usd
from dempipe.sim.motion import Key, Motion, reference_anchor


def _rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _moving(kind, index, motion, origin, rotation=(1.0, 0.0, 0.0, 0.0)):
    """A ColliderMotion stand-in, with the anchor's reference pose as the builder
    computes it (motion.reference_anchor, pivot filled with the owner's point)."""
    motion = motion.with_pivot(origin)
    ref_p, ref_q = reference_anchor(motion, origin, rotation)
    return types.SimpleNamespace(kind=kind, index=index, motion=motion, ref_p=ref_p, ref_q=ref_q,
                                 origin=np.asarray(origin, float),
                                 rotation=np.asarray(rotation, float))


def _world_points(stage, path, code):
    prim = stage.GetPrimAtPath(path)
    pts = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(), dtype=np.float64)
    m = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode(code))
    return _apply(m, pts)


# Collider transforms are authored in double precision; the mesh points are
# float32 (relative 6e-8 of coordinates ≤ 2 m): 1e-6 m.
TOL = 1e-6


def test_keys_reached_at_key_times():
    # a mesh authored at (origin, rotation) keyed to two absolute poses
    origin, rot = np.array([1.0, 2.0, 0.5]), np.array([np.cos(0.3), 0.0, 0.0, np.sin(0.3)])
    q1 = np.array([np.cos(0.6), np.sin(0.6), 0.0, 0.0])
    m = Motion(keys=(Key(0.5, tuple(origin), tuple(rot)), Key(1.5, (0.0, 0.0, 2.0), tuple(q1))),
               interpolation="smooth")
    ref = reference_anchor(m, origin, rot)
    y = origin + np.array([0.2, -0.1, 0.3])               # a point of the mesh
    tr, ori = collider_xforms(m, ref, origin, rot, [0.0, 0.5, 1.5, 2.0])
    moved = [_quat_matrix(o) @ y + t for t, o in zip(tr, ori)]
    np.testing.assert_allclose(moved[0], y, atol=1e-12)  # held before the first key
    np.testing.assert_allclose(moved[1], y, atol=1e-12)  # the first key is the authored pose
    # at the last key the mesh frame is the key's pose: y's offset turned by q1 rot⁻¹
    expect = np.array([0.0, 0.0, 2.0]) + _quat_matrix(q1) @ _quat_matrix(rot).T @ (y - origin)
    np.testing.assert_allclose(moved[2], expect, atol=1e-12)
    np.testing.assert_allclose(moved[3], expect, atol=1e-12)  # held after


def test_plane_moving_along_itself_stays_put_tipping_plane_tips():
    point, normal, centre = np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([0.3, 0.4, 0.0])
    times = np.linspace(0.0, 1.0, 5)
    belt = Motion(velocity=(2.0, 1.0, 0.0)).with_pivot(point)
    tr, ori = plane_xforms(belt, reference_anchor(belt, point), point, normal, centre, times)
    np.testing.assert_allclose(tr, 0.0, atol=1e-15)
    np.testing.assert_allclose(ori, [[1.0, 0.0, 0.0, 0.0]] * 5, atol=1e-15)
    # lifted and tipped about the x axis through the origin: the quad's centre goes to
    # its projection onto the moved plane, its normal turns with the plane
    lift = Motion(velocity=(0.0, 0.0, 0.5), angular_velocity=(0.4, 0.0, 0.0)).with_pivot(point)
    tr, ori = plane_xforms(lift, reference_anchor(lift, point), point, normal, centre, times)
    for t, d, o in zip(times, tr, ori):
        r = np.array([[1, 0, 0], [0, np.cos(0.4 * t), -np.sin(0.4 * t)],
                      [0, np.sin(0.4 * t), np.cos(0.4 * t)]])
        np.testing.assert_allclose(_quat_matrix(o), r, atol=1e-12)
        c_t = _quat_matrix(o) @ centre + d
        p_t, n_t = np.array([0.0, 0.0, 0.5 * t]), r @ normal
        assert abs(np.dot(c_t - p_t, n_t)) < 1e-12        # on the moved plane
        np.testing.assert_allclose(c_t - np.dot(c_t - centre, n_t) * n_t, centre, atol=1e-12)


def test_rates_without_a_pivot_turn_about_the_collider_origin():
    # a Motion as parsed (pivot None) gives the same transform as one with its pivot
    # filled in: the exporter does not depend on the builder having filled it
    origin, m = np.array([1.0, 2.0, 0.0]), Motion(angular_velocity=(0.0, 0.0, 1.0))
    ref = reference_anchor(m, origin)
    a = collider_xforms(m, ref, origin, (1.0, 0.0, 0.0, 0.0), [0.0, 0.7])
    b = collider_xforms(m.with_pivot(origin), ref, origin, (1.0, 0.0, 0.0, 0.0), [0.0, 0.7])
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_allclose(_quat_matrix(a[1][1]) @ origin + a[0][1], origin, atol=1e-12)


def test_first_shown_frame():
    times = np.arange(5) / 24.0
    got = first_shown_frame([0.0, 1.0 / 24.0, 0.05, 9.0, 2.0 / 24.0 + 1e-12], times)
    assert got.tolist() == [0, 1, 2, 5, 2]


@pytest.mark.parametrize("layout", ["instancer", "xforms"])
def test_animated_colliders_and_emitters_in_usd(tmp_path, layout):
    model, frames = make_model(), make_frames()
    mesh_origin = np.array([1.5, 0.0, 0.3])            # the ramp's centre
    spin = Motion(velocity=(0.0, 0.0, 0.2), angular_velocity=(0.0, 0.0, 1.5))
    lift = Motion(keys=(Key(0.1, (0.0, 0.0, 0.5)), Key(0.3, (0.0, 0.0, 0.8))))
    model.collider_motions = (
        _moving("mesh", 0, spin, mesh_origin),
        _moving("box", 0, lift, (0.0, 0.0, 0.5)),
        _moving("plane", 0, Motion(velocity=(1.0, 0.0, 0.0)), (0.0, 0.0, 0.0)),   # a belt
    )
    start = np.zeros(model.n_bodies)
    start[2], start[4] = 3.0 / FPS, 100.0                # frame 3; never within the frames
    model.body_start_time = start
    path = write_usd(tmp_path / f"{layout}.usda", frames, model, layout=layout).path
    stage = Usd.Stage.Open(str(path))

    ramp0 = np.asarray(model.static_meshes[0].vertices, dtype=np.float64)
    box0 = _world_points(stage, "/World/Colliders/box_0", FIRST)
    for f, t in enumerate(frames.times):
        code = float(frames.frame_numbers[f])
        expect = mesh_origin + (ramp0 - mesh_origin) @ _rot_z(1.5 * t).T + [0.0, 0.0, 0.2 * t]
        np.testing.assert_allclose(_world_points(stage, "/World/Colliders/ramp_1", code), expect,
                                   atol=TOL)
        dz = 0.3 * np.clip((t - 0.1) / 0.2, 0.0, 1.0)     # linear keys, held outside
        np.testing.assert_allclose(_world_points(stage, "/World/Colliders/box_0", code),
                                   box0 + [0.0, 0.0, dz], atol=TOL)
    # the belt's quad does not move (a default transform, no samples)
    belt = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Colliders/plane_0"))
    assert all(op.GetAttr().GetNumTimeSamples() == 0 for op in belt.GetOrderedXformOps())
    # the box is sampled sparsely: held before 0.1 s and after 0.3 s
    box_t = stage.GetPrimAtPath("/World/Colliders/box_0").GetAttribute("xformOp:translate")
    assert 2 < box_t.GetNumTimeSamples() < len(frames.times)

    for f in range(len(frames.times)):
        code = Usd.TimeCode(float(frames.frame_numbers[f]))
        if layout == "instancer":
            pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
            shown = np.array(pi.ComputeMaskAtTime(code) or [True] * model.n_bodies)
        else:
            shown = np.array([UsdGeom.Imageable(stage.GetPrimAtPath(
                f"/World/Bodies/{model.group_names[model.body_group[b]]}/"
                f"{model.group_names[model.body_group[b]]}_{model.body_group_index[b]}"))
                .ComputeVisibility(code) != UsdGeom.Tokens.invisible
                for b in range(model.n_bodies)])
        expect = np.ones(model.n_bodies, bool)
        expect[2], expect[4] = f >= 3, False
        assert shown.tolist() == expect.tolist(), f
    errors, warnings = validation_issues(path)
    assert errors == [] and warnings == []
