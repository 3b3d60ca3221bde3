"""Control: what changes over time by prescription, beside Model and State.

Model says what the scene IS (frozen), State where the bodies ARE (integrated by
the kernels); Control says where the prescribed bodies MUST BE: poses and
velocities of kinematic bodies and animated colliders, given from outside (a
keyframed USD prim, a conveyor belt), never integrated. The split is Newton's
``sim`` (Model / State / Control); see docs/architecture.md.

A controlled body is one the body stage leaves alone (``Model.body_static``:
1/m = 0, an infinite mass to every contact): today the static mesh colliders,
which are pseudo-bodies after the dynamic ones. The backends' ``step(state, n,
control)`` writes the Control's poses into the State before the call's first
step, whose neighbour-list rebuild places the bodies' spheres there (the CPU
keeps a collider's spheres from the rebuild, ``body_still``), so a pose given per
``step`` call (per output frame) moves the collider at that granularity. Motions
known in advance (the Model's keyframes and constant velocities: kinematic bodies,
animated colliders, belts) are evaluated per step inside the kernels instead
(:class:`Drive`, kernels/prescribed.py), with the surface velocity (v + w × r) in
the contacts' dashpot and friction.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from dempipe.sim.kernels.pairing import WALL_BITS


def _empty(*shape):
    return np.zeros((0,) + shape)


@dataclass
class Control:
    """Prescribed poses and velocities of K controlled bodies (world frame).

    body : (K,) int32, indices of the controlled bodies (each one static:
        Model.body_static)
    x : (K, 3) centre of mass [m];  q : (K, 4) orientation (w, x, y, z), body to world
    v : (K, 3) velocity [m/s];  w : (K, 3) angular velocity [rad/s] (checked and
        carried; :meth:`apply` writes only the poses)
    An empty Control (the default) prescribes nothing.
    """

    body: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    x: np.ndarray = field(default_factory=lambda: _empty(3))
    q: np.ndarray = field(default_factory=lambda: _empty(4))
    v: np.ndarray = field(default_factory=lambda: _empty(3))
    w: np.ndarray = field(default_factory=lambda: _empty(3))

    @property
    def empty(self) -> bool:
        return int(np.asarray(self.body).shape[0]) == 0

    def check(self, model) -> None:
        """ValueError naming the problem when the arrays do not fit ``model``: shapes,
        indices out of range or of a dynamic body (the body stage would integrate
        it), a non-unit quaternion, non-finite values."""
        k = int(np.asarray(self.body).shape[0])
        for name, cols in (("x", 3), ("q", 4), ("v", 3), ("w", 3)):
            a = np.asarray(getattr(self, name))
            if a.shape != (k, cols):
                raise ValueError(f"Control.{name}: shape {a.shape}, expected ({k}, {cols})")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Control.{name}: non-finite values")
        b = np.asarray(self.body)
        nb = int(model.body_mass.shape[0])
        if k and (b.min() < 0 or b.max() >= nb):
            raise ValueError(f"Control.body: indices must be in 0..{nb - 1}")
        if k and not np.all(model.body_static[b]):
            bad = int(b[~model.body_static[b]][0])
            raise ValueError(f"Control.body: body {model.body_name(bad)} is dynamic; only "
                             f"static bodies (colliders) can be controlled")
        if k and np.any(np.abs(np.linalg.norm(self.q, axis=1) - 1.0) > 1e-9):
            raise ValueError("Control.q: quaternions must have unit length")

    def apply(self, state) -> None:
        """Put the controlled bodies where the Control says (State arrays, in place)."""
        if self.empty:
            return
        b = np.asarray(self.body)
        state.body_x[b] = self.x
        state.body_q[b] = self.q


class Drive(NamedTuple):
    """The scene's prescribed inputs as the kernels read them, one structured launch
    argument (both targets): the Model's motions (motion.MotionTable), which bodies
    and walls they carry, the emitters' start steps, and the motions evaluated at
    the current step (``motion_now``, the per-step Control the kernels write).

    motion_now (M, 14): each anchor's P [m], Q, V [m/s], W [rad/s] (world frame)
    and 1 when it moves this step, 0 when it holds still; M = 0 when the scene
    prescribes nothing (the kernels then skip the motion stages).
    moving_walls: bit w set for each moving wall (-1 when walls are too many for
    a mask), so stage_active visits the slots a moving wall may reach.
    """

    motion_kind: np.ndarray
    motion_v: np.ndarray
    motion_w: np.ndarray
    motion_pivot: np.ndarray
    key_start: np.ndarray
    key_t: np.ndarray
    key_p: np.ndarray
    key_q: np.ndarray
    motion_now: np.ndarray
    driven_body: np.ndarray
    body_motion: np.ndarray
    body_anchor_c: np.ndarray
    body_anchor_q: np.ndarray
    wall_motion: np.ndarray
    body_start: np.ndarray
    moving_walls: np.int64


def drive(model) -> Drive:
    """The Drive of ``model`` (ModelBuilder.finalize's prescription), with a fresh
    motion_now (host arrays)."""
    t = model.motion_table
    wall_motion = np.ascontiguousarray(model.wall_motion, dtype=np.int32)
    mask = 0
    for w in np.flatnonzero(wall_motion >= 0):
        mask = -1 if wall_motion.shape[0] > WALL_BITS else mask | (1 << int(w))
    f = np.ascontiguousarray
    return Drive(
        motion_kind=f(t.kind, dtype=np.int32), motion_v=f(t.v), motion_w=f(t.w),
        motion_pivot=f(t.pivot), key_start=f(t.key_start, dtype=np.int32), key_t=f(t.key_t),
        key_p=f(t.key_p), key_q=f(t.key_q), motion_now=np.zeros((len(model.motions), 14)),
        driven_body=f(model.driven_body, dtype=np.int32),
        body_motion=f(model.body_motion, dtype=np.int32), body_anchor_c=f(model.body_anchor_c),
        body_anchor_q=f(model.body_anchor_q), wall_motion=wall_motion,
        body_start=f(model.body_start, dtype=np.int64), moving_walls=np.int64(mask))


def split_at(step: int, n: int, starts) -> list:
    """``n`` steps from ``step`` cut so that each start step in ``starts`` (sorted)
    begins a piece: the lengths of the pieces."""
    out = []
    end = step + n
    for e in starts:
        e = int(e)
        if step < e < end:
            out.append(e - step)
            step = e
    if end > step:
        out.append(end - step)
    return out
