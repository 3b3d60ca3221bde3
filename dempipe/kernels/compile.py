"""Compile physics.py's plain functions for a target.

physics.py's functions call one another through their module's globals
(``angular_velocity`` calls ``quat_rotate``). A target's compiler can only call
functions compiled for that same target, so each function is re-created with
globals that point at the already-compiled versions of its callees, then
compiled. The source stays written once, with no decorator.
"""

from __future__ import annotations

import types

from .. import physics

#: physics.py functions in dependency order (callees before callers).
FORMULAS = (
    "quat_rotate",
    "quat_rotate_inv",
    "quat_integrate",
    "sym_mat_vec",
    "angular_velocity",
    "sphere_kinematics",
    "damping_coefficient",
    "contact_force",
    "sphere_pair_force",
    "sphere_wall_force",
    "body_step",
)


def compile_formulas(jit) -> types.SimpleNamespace:
    """Return a namespace of every formula compiled with ``jit`` (a decorator)."""
    compiled: dict[str, object] = {}
    for name in FORMULAS:
        py = getattr(physics, name)
        glb = dict(py.__globals__)
        glb.update(compiled)
        fn = types.FunctionType(py.__code__, glb, py.__name__, py.__defaults__, py.__closure__)
        fn.__doc__ = py.__doc__
        compiled[name] = jit(fn)
    return types.SimpleNamespace(**compiled)
