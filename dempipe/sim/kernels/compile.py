"""Compile physics.py's plain functions for a target.

physics.py's functions call one another through their module's globals
(``angular_velocity`` calls ``quat_rotate``). A target's compiler can only call
functions compiled for that same target, so each function is re-created with
globals that point at the already-compiled versions of its callees, then
compiled. The source stays written once, with no decorator.
"""

from __future__ import annotations

import glob
import hashlib
import os
import types

from dempipe.sim import laws, motion, physics
from dempipe.sim.kernels import contacts, glue, neighbours, pairing, patches

#: physics.py functions in dependency order (callees before callers).
FORMULAS = (
    "quat_rotate",
    "quat_rotate_inv",
    "quat_integrate",
    "sym_mat_vec",
    "angular_velocity",
    "chord_velocity",
    "sphere_kinematics",
    "static_body",
    "carry_stretch",
    "midpoint_velocity",
    "contact_force",
    "sphere_pair_force",
    "sphere_wall_force",
    "rolling_torque",
    "rolling_scale",
    "glue_force",
    "body_step",
    "history_recall",
    "history_store",
    "rest_steps",
)


def compile_chain(module, names, jit, given: dict) -> types.SimpleNamespace:
    """``module``'s functions ``names`` (callees first), each re-created with its
    module's globals overlaid by ``given`` and by the ones compiled before it,
    then compiled with ``jit``. Returns them (and ``given``) as a namespace."""
    compiled = dict(given)
    for name in names:
        py = getattr(module, name)
        glb = dict(py.__globals__)
        glb.update(compiled)
        fn = types.FunctionType(py.__code__, glb, py.__name__, py.__defaults__, py.__closure__)
        fn.__doc__ = py.__doc__
        compiled[name] = jit(fn)
    return types.SimpleNamespace(**compiled)


def compile_walk(jit, formulas, cell_coord, cell_key, cell_hash, grid_slots: bool):
    """neighbours.neighbour_list compiled with ``jit``, calling the target's own
    (already compiled) grid cell functions and ``formulas.static_body``;
    ``grid_slots``: the grid holds slots
    through grid_slot (the CPU's body-ordered slots) rather than being the slots."""
    return compile_chain(neighbours, ("neighbour_list",), jit,
                         dict(cell_coord=cell_coord, cell_key=cell_key,
                              cell_hash=cell_hash, GRID_SLOTS=grid_slots,
                              static_body=formulas.static_body)).neighbour_list


def compile_slot_store(jit) -> types.SimpleNamespace:
    """neighbours.slot_place and slot_store compiled with ``jit``."""
    return compile_chain(neighbours, ("slot_place", "slot_store"), jit, {})


def compile_pairing(jit, formulas) -> types.SimpleNamespace:
    """pairing.py's bookkeeping (entry_range, wall_reach, owns, pair_count,
    pair_slots, pair_mirror, walls_to_front, wall_column, rows_to_pairs,
    pairs_to_rows), each compiled with ``jit``, calling ``formulas`` (the target's
    compile_formulas); they read no flags, so they need no variants."""
    return compile_chain(pairing, ("entry_range", "wall_reach", "owns", "pair_count",
                                    "pair_slots", "pair_mirror", "walls_to_front", "wall_column",
                                    "rows_to_pairs", "pairs_to_rows"), jit,
                         dict(history_recall=formulas.history_recall,
                              static_body=formulas.static_body))


def compile_contacts(jit, formulas, pairing, constants: dict) -> types.SimpleNamespace:
    """contacts.pair_forces and contacts.sphere_forces, and patches.py's passes that
    count each contact patch before them, compiled with ``jit``, calling
    ``formulas`` (the target's compile_formulas) and ``pairing``'s entry_range (its
    compile_pairing), and reading ``constants`` (the
    flags FRICTION, ROTATION, SLEEPING, WALLS, HIST_BY_SLOT, and sqrt) as globals.
    The CPU compiles its variants with compile.specialize instead."""
    given = dict(history_recall=formulas.history_recall, history_store=formulas.history_store,
                 entry_range=pairing.entry_range,
                 contact_coefficients=formulas.contact_coefficients,
                 closing=formulas.closing,
                 static_body=formulas.static_body,
                 sphere_pair_force=formulas.sphere_pair_force,
                 sphere_wall_force=formulas.sphere_wall_force,
                 rolling_torque=formulas.rolling_torque,
                 anchor_local=formulas.anchor_local, anchor_surface=formulas.anchor_surface,
                 quat_rotate=formulas.quat_rotate,
                 RING_TIE=contacts.RING_TIE, RIM_TIE=contacts.RIM_TIE, INSCRIBED=True)
    given.update(constants)
    c = compile_chain(contacts, ("wall_gap", "pair_ended", "inscribed_wall", "engaged"), jit,
                      given)
    given.update(wall_gap=c.wall_gap, pair_ended=c.pair_ended,
                 inscribed_wall=c.inscribed_wall, engaged=c.engaged)
    pt = compile_chain(patches, patches.KERNEL, jit, given)
    given.update(vars(pt))
    return compile_chain(contacts, ("pair_forces", "sphere_forces"), jit, given)


def compile_glue(jit, formulas, pairing, constants: dict) -> types.SimpleNamespace:
    """kernels/glue.py's passes (bond_forces, bond_contacts, body_glue_sum) compiled
    with ``jit``, calling ``formulas`` (the target's compile_formulas: glue_force,
    static_body) and ``pairing``'s entry_range (its compile_pairing), and reading
    ``constants`` (the flags ROTATION, SLEEPING, PAIR_ROWS, and sqrt) as globals.
    The CPU compiles them with compile.specialize instead."""
    given = dict(glue_force=formulas.glue_force, static_body=formulas.static_body,
                 entry_range=pairing.entry_range)
    given.update(constants)
    return compile_chain(glue, ("bond_forces", "bond_contacts", "body_glue_sum"), jit, given)


def compile_formulas(jit, law: str = laws.DEFAULT) -> types.SimpleNamespace:
    """Return a namespace of every formula compiled with ``jit`` (a decorator): the
    contact law's kernel functions (``laws.law(law).KERNEL``: contact_coefficients,
    normal_force), then physics.py's, which call them, then motion.py's (prescribed
    motion), which call physics.py's rotations."""
    lw = laws.law(law)
    given = vars(compile_chain(lw, lw.KERNEL, jit, {}))
    given = vars(compile_chain(physics, FORMULAS, jit, given))
    return compile_chain(motion, motion.FORMULAS, jit, given)


def specialize(functions, jits: dict, constants: dict, tag: str,
               module_globals: dict | None = None) -> types.SimpleNamespace:
    """Compile one variant of the plain functions ``functions`` (callees first).

    ``module_globals``: the globals they all run with (default: the first one's
    module's), so that functions written in other modules (contacts.py) see the
    driver module's compiled callees and constants.

    Each function is re-created with globals in which ``constants`` (e.g.
    ``FRICTION = False``) and the variant's own compiled callees replace the
    module's, and jitted with ``jits[name]``. numba freezes global values at
    compile time, so ``if FRICTION:`` is a constant branch and LLVM drops the
    dead side: the variant contains no code for a feature it was built without.

    Why globals, not a closure or literal arguments: numba's disk cache keys a
    function on its file, ``__qualname__`` and line, then on the signature (and
    the values in a closure, pickled; a closure over other dispatchers pickles
    differently in every process and would never hit). Globals are not part of
    the key, so each variant gets its own ``__qualname__`` (``run_steps__F1R0S0W1``)
    and hence its own cache file. ``numba.literally`` would make one function
    dispatch on Literal[bool] types, but leaves branch pruning to each callee's
    typing and multiplies signatures in one index instead.
    """
    first = next(iter(functions))
    glb = dict(first.__globals__ if module_globals is None else module_globals)
    glb.update(constants)
    out: dict[str, object] = {}
    for py in functions:
        fn = types.FunctionType(py.__code__, glb, py.__name__, py.__defaults__, py.__closure__)
        fn.__qualname__ = f"{py.__qualname__}__{tag}"
        fn.__doc__ = py.__doc__
        fn.__module__ = py.__module__
        out[py.__name__] = glb[py.__name__] = jits[py.__name__](fn)
    return types.SimpleNamespace(**out)


def invalidate_stale_cache(module_file: str) -> None:
    """Drop numba's on-disk cache of ``module_file`` when physics.py changed.

    numba keys a cached function on its own file's timestamp only, but the
    formulas it inlines live in physics.py: edit a formula and the stale
    compiled kernel would silently keep running. We stamp the cache folder
    with a hash of every source that goes into the kernels and clear the
    module's entries when it differs.
    """
    here = os.path.dirname(os.path.abspath(module_file))
    # every source a kernel may inline or link: the formulas (physics, motion), the laws, and all of
    # kernels/ (a driver links the stages it calls, wherever they are written)
    sources = [physics.__file__, motion.__file__,
               *sorted(glob.glob(os.path.join(os.path.dirname(laws.__file__), "*.py"))),
               *sorted(glob.glob(os.path.join(os.path.dirname(__file__), "**", "*.py"),
                                recursive=True))]
    sha = hashlib.sha256()
    for f in sources:
        with open(f, "rb") as fh:
            sha.update(fh.read())
    digest = sha.hexdigest()[:16]
    stem = os.path.splitext(os.path.basename(module_file))[0]
    folders = [os.path.join(here, "__pycache__")]
    if os.environ.get("NUMBA_CACHE_DIR"):
        folders.append(os.environ["NUMBA_CACHE_DIR"])
    for folder in folders:
        stamp = os.path.join(folder, f"{stem}.sources-{digest}")
        if not os.path.isdir(folder) or os.path.exists(stamp):
            continue
        try:
            for f in glob.glob(os.path.join(folder, "**", f"{stem}.*.nb[ic]"), recursive=True):
                os.remove(f)
            for f in glob.glob(os.path.join(folder, f"{stem}.sources-*")):
                os.remove(f)
            open(stamp, "w").close()
        except OSError:
            pass  # a read-only install: its cache was built from its own sources
