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
``step`` call (per output frame) moves the collider at that granularity. What
the next issue adds on this: the pose and velocity per step inside the kernels,
and the surface velocity (v + w × r of the controlled body) in the contact's
dashpot and friction, for kinematic bodies, animated colliders and belts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _empty(*shape):
    return np.zeros((0,) + shape)


@dataclass
class Control:
    """Prescribed poses and velocities of K controlled bodies (world frame).

    body : (K,) int32, indices of the controlled bodies (each one static:
        Model.body_static)
    x : (K, 3) centre of mass [m];  q : (K, 4) orientation (w, x, y, z), body to world
    v : (K, 3) velocity [m/s];  w : (K, 3) angular velocity [rad/s] (carried for the
        contacts' surface velocity; not read by the kernels yet)
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
