"""Prescribed motion in the output: where an animated collider's prim stands at each
frame, and from which frame an emitted body is shown.

Animated colliders. A collider's geometry is authored in world
coordinates at its *authored* pose T_a = (origin, rotation) (a mesh collider's
position and rotation, a plane's point, a box's centre). Its motion carries that
frame to T(t) = ``motion.carry(motion, ref, origin, rotation, t)``, so the prim's
transform at time t is

    D(t) = T(t) · T_a⁻¹:     y ↦ R(t) y + d(t),   R = q(t) rotation⁻¹,
                              d = x(t) − R(t) origin,

written as ``xformOp:translate`` d and ``xformOp:orient`` R (translate first in
the op order, so a point goes through the rotation, then the translation). At
key times this is the key's pose to float precision (the same formulas as the
kernels, dempipe.sim.motion).

A plane is infinite and drawn as a finite quad under the bodies: its motion
along itself (a conveyor belt) changes nothing that can be drawn, so the quad is
turned by R(t) and moved only across the plane (its centre projected onto the
moved plane): a belt's quad stays still under its parcels, a tipping or lifting
plane tips or lifts.

Emitters: a body with start time s > 0 is shown from the first frame whose time
is ≥ s (less 1 ns of float slack); before it, it does not exist (usd.py hides it).
"""

from __future__ import annotations

import numpy as np

from dempipe.sim.motion import carry, qmul
from dempipe.sim.physics import quat_rotate

__all__ = ["collider_xforms", "plane_xforms", "first_shown_frame"]

#: Float slack on "frame time ≥ start time" [s]: frame times are f / fps in float64.
START_SLACK = 1e-9


def _rotate(q, v):
    """The vector v (3,) rotated by the unit quaternion q (w, x, y, z)."""
    return np.array(quat_rotate(*q, *v))


def collider_xforms(motion, ref, origin, rotation, times):
    """The prim transform D(t) = T(t) · T_a⁻¹ of a collider authored at (``origin``
    (3,) [m], ``rotation`` (4,) w, x, y, z), world frame, whose frame the Motion
    ``motion`` carries from the anchor pose ``ref`` ((P (3,), Q (4,)),
    motion.reference_anchor) — at each of ``times`` (F,) [s, simulation time].

    Returns (translate (F, 3) [m], orient (F, 4) unit (w, x, y, z)), float64.
    """
    origin = np.asarray(origin, dtype=np.float64)
    motion = motion.with_pivot(origin)      # rates without a pivot turn about the origin
    rot = np.asarray(rotation, dtype=np.float64)
    rot = rot / np.linalg.norm(rot)
    inv = (rot[0], -rot[1], -rot[2], -rot[3])
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    trans = np.empty((len(times), 3))
    orient = np.empty((len(times), 4))
    for f, t in enumerate(times):
        x, q, _, _ = carry(motion, ref, origin, rot, float(t))
        r = np.array(qmul(*q, *inv))
        r /= np.linalg.norm(r)
        if r[0] < 0.0:          # one hemisphere: w ≥ 0 (q and -q are the same rotation)
            r = -r
        orient[f] = r
        trans[f] = x - _rotate(r, origin)
    return trans, orient


def plane_xforms(motion, ref, point, normal, centre, times):
    """The transform of a plane's stand-in quad centred at ``centre`` (3,) [m] (on
    the authored plane through ``point`` with ``normal``): turned by R(t) about its
    centre, whose new place is the centre's projection onto the moved plane (a
    motion along the plane moves nothing). Returns (translate (F, 3) [m], orient
    (F, 4) (w, x, y, z)) as collider_xforms (whose D(t) it shares for R(t))."""
    point = np.asarray(point, dtype=np.float64)
    n0 = np.asarray(normal, dtype=np.float64)
    n0 = n0 / np.linalg.norm(n0)
    c = np.asarray(centre, dtype=np.float64)
    trans, orient = collider_xforms(motion, ref, point, (1.0, 0.0, 0.0, 0.0), times)
    for f in range(len(trans)):
        r = orient[f]
        p_t = trans[f] + _rotate(r, point)          # the moved plane's point
        n_t = _rotate(r, n0)
        c_t = c - np.dot(c - p_t, n_t) * n_t
        trans[f] = c_t - _rotate(r, c)
    return trans, orient


def first_shown_frame(start_time, times) -> np.ndarray:
    """(n,) int: the index into ``times`` (F,) [s] of the first frame each body is
    shown at (its start time ``start_time`` (n,) [s] reached); F where never."""
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    start = np.asarray(start_time, dtype=np.float64).reshape(-1)
    return np.searchsorted(times, start - START_SLACK, side="left")

