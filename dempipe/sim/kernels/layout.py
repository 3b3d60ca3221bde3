"""Host-side layout of the kernels' data, for both targets; imports no numba.

What the backends allocate and how the grid is sized, in one place, so that
what is allocated and what is estimated (``sizes.memory_estimate``, `dempipe
check`) cannot drift apart:

* ``grid_table`` / ``fit_grid``: the wrapped grid's bits (kernels/neighbours.py);
* ``cpu_scratch``: every array ``kernels.cpu.backend.CpuBackend`` allocates, by name
  (the CPU's persistent arrays: a checkpoint or a memory estimate walks this);
* ``layout_bytes``: the bytes of such a layout.

The CUDA backend's layout (``kernels.cuda.backend.scratch_layout``) uses grid_table from
here; its scan buffers depend on the device's block sizes, so it stays there.
"""

from __future__ import annotations

import os
from typing import Any, NamedTuple

import numpy as np

from dempipe.errors import DeviceError
from dempipe.sim.kernels.contacts import CONTACT_CHUNK
from dempipe.sim.kernels.neighbours import NEIGHBOURS, cell_size
from dempipe.sim.kernels.pairing import LIST_COLS, LIST_PER_SPHERE, PAIR_COLS, PAIRS_PER_SPHERE
from dempipe.sim.kernels.patches import BODY_PATCHES
from dempipe.sim.state import CONTACT_SLOTS

#: Most buckets per sphere the grid may use: its table has 2^k >= this × spheres
#: buckets (memory follows the spheres, never the bounding box).
BUCKETS_PER_SPHERE = 8

#: Buckets per block of the CPU's counting sort (kernels/cpu/grid.py bucket_sort):
#: each block's running sum is one thread's, after a serial sum over the blocks.
BUCKET_BLOCK = 4096


def grid_table(n_spheres: int, extent_cells=None) -> np.ndarray:
    """Table layout (bx, by, mask_x, mask_y, mask_z, n_buckets) for the grid.

    The budget is 2^k >= BUCKETS_PER_SPHERE × spheres buckets, so memory follows
    the spheres whatever the scene's size. Within it, each axis gets the bits
    that cover the occupied extent (``extent_cells``, cells per axis): a compact
    pile then gets a dense grid and no two occupied cells share a bucket. When the
    extent needs more bits than the budget, the widest axes give bits up and far
    cells alias (still correct, only slower).
    """
    # At least 2 bits (4 buckets) per axis: with 1, a row's cells cx-1 and cx+1
    # share a bucket and its spheres would be visited twice (contact counted twice).
    k = 6
    while (1 << k) < BUCKETS_PER_SPHERE * max(n_spheres, 1):
        k += 1
    if extent_cells is None:
        bx = (k + 2) // 3
        by = (k - bx + 1) // 2
        bits = [bx, by, k - bx - by]
    else:
        bits = [max(2, int(np.ceil(np.log2(max(e, 1.0) + 3.0)))) for e in extent_cells]
        while sum(bits) > k:
            i = int(np.argmax(bits))
            bits[i] -= 1
    bx, by, bz = bits
    return np.array([bx, by, (1 << bx) - 1, (1 << by) - 1, (1 << bz) - 1, 1 << (bx + by + bz)],
                    dtype=np.int64)


def grid_buckets(n_spheres: int) -> int:
    """The grid's bucket budget (the most any fitted grid uses)."""
    return int(grid_table(n_spheres)[5])


def static_extent(model):
    """(lo, hi) of the static pseudo-bodies' spheres grown by a diameter [m], or None."""
    if not model.n_static:
        return None
    first = model.body_sphere_start[model.n_bodies]
    pts = model.sphere_offset[first:] + model.initial_x[model.sphere_body[first:]]
    return pts.min(axis=0) - model.diameter, pts.max(axis=0) + model.diameter


def fit_grid(model, body_x, static_box) -> np.ndarray:
    """The grid fitted to where the bodies are (once per ``step`` call, both targets).

    The extent is the dynamic bodies' bounding box grown by their radii (and the
    static spheres' box, ``static_extent``), plus two cells; bodies that leave it
    during the call still collide correctly, only through aliased buckets.
    """
    m = model
    if m.body_mass.shape[0] == 0:
        return grid_table(m.n_spheres)
    r = m.body_radius
    lo = (body_x[: m.n_bodies] - r[: m.n_bodies, None]).min(axis=0) if m.n_bodies else None
    hi = (body_x[: m.n_bodies] + r[: m.n_bodies, None]).max(axis=0) if m.n_bodies else None
    if static_box is not None:
        lo = static_box[0] if lo is None else np.minimum(lo, static_box[0])
        hi = static_box[1] if hi is None else np.maximum(hi, static_box[1])
    return grid_table(m.n_spheres, (hi - lo) / cell_size(m.diameter) + 2.0)


def cpu_scratch(model, friction: bool) -> dict:
    """name -> (shape, dtype) of every array ``CpuBackend`` allocates (its
    attributes of the same names), the growable ones at their initial sizes
    (the neighbour lists, packed rows and wall rows grow when a rebuild needs
    more). ``friction``: the backend keeps contact histories."""
    nb = int(model.body_mass.shape[0])
    ns = model.n_spheres
    table = grid_buckets(ns)
    f8, i8, i4 = np.float64, np.int64, np.int32
    n_chunks = (max(ns, 1) + CONTACT_CHUNK - 1) // CONTACT_CHUNK
    lay = {
        "grid": ((6,), i8),
        "body_v": ((nb, 3), f8), "body_w": ((nb, 3), f8),
        "sphere_x": ((ns, 3), f8), "sphere_v": ((ns, 3), f8), "sphere_r": ((ns, 3), f8),
        "sphere_key": ((ns,), i8), "sphere_hash": ((ns,), i8),
        "bucket_start": ((table + 1,), i8),
        "bucket_blocks": ((table // BUCKET_BLOCK + 1,), i8),
        "body_key": ((nb,), i8),                 # each body's bucket (the slots' order)
        # the grid (stage_grid_sort): each position's sphere, slot, position, cell, body
        "grid_idx": ((ns,), i4), "grid_slot": ((ns,), i4), "grid_x": ((ns, 3), f8),
        "grid_key": ((ns,), i8), "grid_body": ((ns,), i4),
        "sorted_idx": ((ns,), i4), "slot_of": ((ns,), i4),
        # the lists' skin [d] (neighbours.adapt_skin), steps since the last rebuild,
        # the largest skin allowed, rebuilds so far, the smallest skin allowed
        "skin_ctl": ((5,), f8),
        "sorted_x": ((ns, 3), f8), "sorted_v": ((ns, 3), f8), "sorted_body": ((ns,), i4),
        "built_x": ((ns, 3), f8), "nbr": ((ns, NEIGHBOURS), i4), "nbr_n": ((ns,), i4),
        # each contact computed once (contacts.py): pair indices, rows of pair forces
        "pidx": ((ns, NEIGHBOURS), i4), "pair_start": ((ns + 1,), i8),
        "pair_f": ((max(PAIRS_PER_SPHERE * ns, 1), PAIR_COLS), f8),
        "pair_e": ((max(PAIRS_PER_SPHERE * ns, 1),), i4),     # each row's list entry
        # the lists packed for the second pass (contacts.py LIST_ROWS): partner slot,
        # pair index, and whether the pair touches this step (patches.body_patches)
        "list_start": ((ns + 1,), i8),
        "list_e": ((max(LIST_PER_SPHERE * ns, 1), LIST_COLS), i4),
        "wall_mask": ((ns,), i8),                # walls within reach (contacts.py)
        # with friction, the walls' stretches while stepping (contacts.py WALL_ROWS):
        # an eighth of the spheres to start with (a pile in a box: 15 % touch a wall)
        "wall_start": ((ns + 1,), i8),
        "wall_s": (((max(ns // 8, 1) if friction else 1), 4), f8),
        # each slot's walls: force, torque, overlap, rolling torque
        "wall_f": ((ns, 10), f8),
        "sphere_f": ((ns, 3), f8), "sphere_t": ((ns, 3), f8), "sphere_overlap": ((ns,), f8),
        "sphere_tr": ((ns, 3), f8),              # rolling torques (bodies.body_update)
        # each body's contacts this step per partner (patches.py)
        "body_patch": ((nb, BODY_PATCHES + 1, 3), f8),
        "body_wake": ((nb,), i4),
        "body_still": ((nb,), i4),               # static colliders: stage 1 keeps them
        # stage 1 between rebuilds (kernels/cpu/stages.py stage_spheres_busy): each
        # body's position and orientation at the last rebuild and at the last step,
        # and the farthest of its spheres from its centre [m]
        "built_bx": ((nb, 3), f8), "built_bq": ((nb, 4), f8),
        "seen_bx": ((nb, 3), f8), "seen_bq": ((nb, 4), f8), "body_reach": ((nb,), f8),
        # how far its spheres may move from where their lists were built before a
        # rebuild [m] (cpu/grid.py stage_rest_half)
        "body_half": ((nb,), f8),
        # and the box of its sphere centres in its frame, centre and half-extent [m];
        # the spheres' offsets by coordinate (kernels/cpu/broadphase.py)
        "body_box": ((nb, 6), f8), "offset_t": ((3, ns), f8),
        # glue (kernels/glue.py): each bonded pair's force, torque, shear stretch; each
        # body's sum of them
        "glue_f": ((max(getattr(getattr(model, "bonds", None), "n_pairs", 0), 1), 9), f8),
        "body_glue": ((nb, 6), f8),
        # the contact passes' work (kernels/cpu/stages.py): the slots with a neighbour
        # or a wall (busy), or those of them a sleeping pile leaves to do (active),
        # found in blocks of CONTACT_CHUNK (each block's count in chunk_n)
        "chunk_n": ((n_chunks,), i8),
        "busy": ((ns,), i4), "active": ((ns,), i4),
        # whether each slot touches anything this step, each sphere at its last visit
        # (contacts.engaged: the passes leave out the others)
        "slot_touch": ((ns,), np.int8), "sphere_engaged": ((ns,), np.int8),
        "span_ctl": ((3,), i8),
        # a rebuild that keeps the slots: which lists it searches again (stage_slot_marks)
        "slot_mark": ((ns,), np.int8),
        # with friction, the spheres whose State history rows can hold anything within
        # a call (grid.stage_history_out): the busy ones of the last re-sort
        "state_rows": (((ns if friction else 1),), i4),
        # each body's first entry in busy and in active (spheres.stage_listed_from)
        "busy_from": ((nb,), i8), "active_from": ((nb,), i8),
        # the frictionless stand-in histories, and with friction the histories in
        # sorted-slot order within a call
        "_no_partner": ((1, 1), i4), "_no_spring": ((1, 1, 3), f8),
    }
    if friction:
        lay["hist_partner"] = ((ns, CONTACT_SLOTS), i4)
        lay["hist_spring"] = ((ns, CONTACT_SLOTS, 3), f8)
    if model.n_static:
        lay["static_lo"] = ((3,), f8)
        lay["static_hi"] = ((3,), f8)
    return lay


def layout_bytes(layout: dict) -> int:
    """Bytes of the arrays of a layout (name -> (shape, dtype))."""
    return int(sum(int(np.prod(shape)) * np.dtype(dt).itemsize for shape, dt in layout.values()))


# ---------------------------------------------------------------------------
# What the kernels are compiled for: features and each target's data layout
# ---------------------------------------------------------------------------

#: Feature flags the specialized kernels are compiled for, in this order (both
#: targets: kernels.cpu.stages.kernels, kernels.cuda.backend.kernels).
FLAGS = ("friction", "rotation", "sleeping", "walls")

#: The general kernel: every feature compiled in (each also checked at run time).
GENERAL = (True, True, True, True)

#: Where the two targets lay contacts.py's data out differently, and why. Each is a
#: constant of the contact passes (compile time), the rest of the code is shared.
#:
#: HIST_BY_SLOT: the contact-history rows are in sorted-slot order within a call
#:   (the CPU re-sorts them at each rebuild: its passes then read them in slot
#:   order); CUDA keeps them in sphere order (its threads read any row anyway).
#: PAIR_ROWS: the first pass walks each slot's own pairs as a run of packed rows
#:   (pair_start, pair_e: each row's entry of list_e) instead of its list: 128 bytes
#:   a sphere less to read on a CPU core's cache; CUDA walks the list (one thread per
#:   slot, no scan needed).
#: WALL_ROWS: the walls' stretches in packed rows (wall_s) while stepping, so the
#:   few spheres near a wall read consecutive memory (CPU); CUDA keeps them in the
#:   history row.
#: LIST_ROWS: the second pass walks packed (partner, pair, touching) entries (list_e),
#:   12 bytes an entry instead of two 64-byte rows a sphere (CPU); CUDA walks the
#:   list. The patches pass, which tests every entry first, marks the ones touching
#:   (or in the step after) in the third column, so both later passes skip the rest
#:   without reading where their partners are.
#: The same pairs in the same order either way: the targets stay bit-identical.
CPU_LAYOUT = dict(HIST_BY_SLOT=True, PAIR_ROWS=True, WALL_ROWS=True, LIST_ROWS=True)
CUDA_LAYOUT = dict(HIST_BY_SLOT=False, PAIR_ROWS=False, WALL_ROWS=False, LIST_ROWS=False)


def scene_features(model, features=None):
    """The Features to run ``model`` with: ``features`` (default the model's).

    An override may switch features on (to run a scene through a kernel that
    carries code it does not need, as tests and benchmarks do), never off.
    One-sphere bodies whose sphere is off their centre of mass turn under
    contact forces, so they need rotation whatever the features say.
    """
    from dataclasses import fields, replace

    mf = model.features
    if features is None:
        features = mf
    for f in fields(mf):
        if getattr(mf, f.name) and not getattr(features, f.name):
            raise ValueError(f"features.{f.name}: the scene uses it; an override may only "
                             f"switch features on")
    if not features.rotation and np.any(model.sphere_offset != 0.0):
        features = replace(features, rotation=True)
    return features


def kernel_flags(features) -> tuple:
    """Flags (FLAGS) of the specialized kernels for ``features``."""
    return (bool(features.friction), bool(features.rotation), bool(features.sleeping),
            bool(features.walls))


#: Which kernels a backend runs when its caller does not say: "specialized" (the
#: default: each feature set's own kernel, the features a scene does not use compiled
#: out) or "general" (every scene through the one general kernel: a kernel takes about
#: a minute to compile on one core, and one compile then serves every scene, at the
#: cost of steps that check at run time what a specialized kernel leaves out). The
#: frames are the same bit for bit either way (tests/sim/test_specialize.py).
KERNELS_ENV = "DEMPIPE_KERNELS"


def run_flags(features, specialize: bool | None = None) -> tuple:
    """The flags of the kernel a backend runs for ``features``: their own
    (kernel_flags) when specializing, GENERAL otherwise; ``specialize`` None follows
    $DEMPIPE_KERNELS (DeviceError naming it when it is neither value)."""
    if specialize is None:
        choice = os.environ.get(KERNELS_ENV, "specialized")
        if choice not in ("specialized", "general"):
            raise DeviceError(f"{KERNELS_ENV}={choice!r}: not a kernel choice (set it to "
                              f"'specialized', the default, or 'general')")
        specialize = choice == "specialized"
    return kernel_flags(features) if specialize else GENERAL


# ---------------------------------------------------------------------------
# Structured launch arguments of the CPU's step driver (kernels/cpu/stages.py run_steps)
# ---------------------------------------------------------------------------

class StepModel(NamedTuple):
    """What a step reads of the Model (frozen): constants and arrays, as
    ``step_model`` takes them from a Model (see Model's docstring for units)."""

    dt: Any
    onset_speed: Any
    diameter: Any
    n_bodies: Any
    gravity: Any
    sphere_body: Any
    sphere_offset: Any
    body_sphere_start: Any
    body_mass: Any
    body_inv_mass: Any
    body_inv_inertia: Any
    body_material: Any
    pair_k: Any
    pair_damp: Any
    pair_mu: Any
    kt_ratio: Any
    ks_ratio: Any
    friction: Any
    sleep_steps: Any
    v_sleep: Any
    w_sleep: Any
    wall_normal: Any
    wall_offset: Any
    wall_lo: Any
    wall_hi: Any
    wall_depth: Any
    wall_material: Any
    rolling: Any
    pair_rolling: Any
    body_inv_radius: Any
    sphere_inscribed: Any


class StepState(NamedTuple):
    """The State's arrays a step changes (the contact histories: the State's, or a
    one-slot stand-in without friction)."""

    body_x: Any
    body_q: Any
    body_P: Any
    body_L: Any
    body_rest: Any
    contact_partner: Any
    contact_spring: Any


class Scratch(NamedTuple):
    """The backend's scratch arrays a step uses (``cpu_scratch``, by name): rebuilt
    by the backend when one is replaced (the lists grow)."""

    hist_partner: Any
    hist_spring: Any
    body_wake: Any
    body_still: Any
    built_bx: Any
    built_bq: Any
    seen_bx: Any
    seen_bq: Any
    body_reach: Any
    body_box: Any
    offset_t: Any
    body_v: Any
    body_w: Any
    sphere_x: Any
    sphere_v: Any
    sphere_r: Any
    sphere_key: Any
    sphere_hash: Any
    bucket_start: Any
    bucket_blocks: Any
    body_key: Any
    grid_slot: Any
    sorted_idx: Any
    slot_of: Any
    sorted_x: Any
    sorted_v: Any
    sorted_body: Any
    grid_idx: Any
    grid_x: Any
    grid_key: Any
    grid_body: Any
    built_x: Any
    nbr: Any
    nbr_n: Any
    pidx: Any
    pair_start: Any
    pair_e: Any
    pair_f: Any
    list_start: Any
    list_e: Any
    wall_mask: Any
    wall_start: Any
    wall_s: Any
    wall_f: Any
    sphere_f: Any
    sphere_t: Any
    sphere_tr: Any
    sphere_overlap: Any
    body_patch: Any
    skin_ctl: Any
    chunk_n: Any
    busy: Any
    active: Any
    span_ctl: Any
    slot_mark: Any
    state_rows: Any
    busy_from: Any
    active_from: Any
    slot_touch: Any
    sphere_engaged: Any
    body_half: Any


class ContactModel(NamedTuple):
    """What the contact passes (contacts.pair_forces, sphere_forces) read of the
    Model (frozen) and the Control's layout: contact constants, the pair table,
    the walls. Built once per call: on the CPU by run_steps from its StepModel,
    on CUDA and in a probe by ``contact_model``.

    diameter [m], dt [s], onset_speed [m/s] (laws.*.normal_force), body_inv_mass
    [1/kg], body_material, the pair table pair_k / pair_damp / pair_mu (the law's
    units), kt_ratio, ks_ratio, friction (the backend keeps histories),
    sleep_steps, the walls (wall_normal, wall_offset [m], wall_lo, wall_hi [m],
    wall_depth [m], wall_material) and each wall's motion (wall_motion, -1: fixed;
    control.Drive); rolling resistance (rolling: Features.rolling and friction, the
    pair table pair_rolling [1], body_inv_radius [1/m]: physics.rolling_torque);
    sphere_inscribed: the Model's, no rows for none (contacts.inscribed_wall)."""

    diameter: Any
    dt: Any
    onset_speed: Any
    body_inv_mass: Any
    body_material: Any
    pair_k: Any
    pair_damp: Any
    pair_mu: Any
    kt_ratio: Any
    ks_ratio: Any
    friction: Any
    sleep_steps: Any
    wall_normal: Any
    wall_offset: Any
    wall_lo: Any
    wall_hi: Any
    wall_depth: Any
    wall_material: Any
    wall_motion: Any
    rolling: Any
    pair_rolling: Any
    body_inv_radius: Any
    sphere_inscribed: Any


class ContactScratch(NamedTuple):
    """The arrays the contact passes read and write, in sorted-slot order: the
    lists and pair indices (nbr, nbr_n, pidx), the CPU's packed rows (pair_start,
    pair_e, wall_start, wall_s, list_start, list_e: contacts.py PAIR_ROWS,
    WALL_ROWS, LIST_ROWS; CUDA passes stand-ins of the same kinds, unread), the
    slots' spheres (sorted_idx, sorted_x [m], sorted_v [m/s], sorted_body), the
    bodies' spin body_w [rad/s] and rest counts, the wake flags, the walls in
    reach, the contact histories (hist_partner, hist_spring) and what the passes
    write: pair_f, wall_f, sphere_f [N], sphere_t [N m], sphere_overlap [m]; and the
    contact patches' sums per body (body_patch: patches.py); the bodies'
    orientations body_q (w, x, y, z), which turn the inscribed balls; and (the CPU,
    LIST_ROWS) whether each slot touches anything this step (slot_touch, by
    patches.body_patches) and each sphere touched anything at its last visit
    (sphere_engaged), with which the passes leave out the slots they would write
    nothing new for (contacts.engaged; CUDA passes stand-ins, unread)."""

    nbr: Any
    nbr_n: Any
    pidx: Any
    pair_start: Any
    pair_e: Any
    wall_start: Any
    wall_s: Any
    list_start: Any
    list_e: Any
    sorted_idx: Any
    sorted_x: Any
    sorted_v: Any
    sorted_body: Any
    body_w: Any
    body_rest: Any
    body_wake: Any
    wall_mask: Any
    hist_partner: Any
    hist_spring: Any
    pair_f: Any
    wall_f: Any
    sphere_f: Any
    sphere_t: Any
    sphere_tr: Any
    sphere_overlap: Any
    body_patch: Any
    body_q: Any
    slot_touch: Any
    sphere_engaged: Any


class BodyModel(NamedTuple):
    """What the body stage (bodies.body_update) reads of the Model: dt [s], gravity
    (3,) [m/s²], body_sphere_start, body_mass [kg], body_inv_mass [1/kg],
    body_inv_inertia (B, 6) [1/(kg m²)], sleeping (sleep_steps, v_sleep [m/s],
    w_sleep [rad/s]), each body's start step (body_start: control.Drive's) and
    whether rolling resistance runs (rolling: ContactModel's)."""

    dt: Any
    gravity: Any
    body_sphere_start: Any
    body_mass: Any
    body_inv_mass: Any
    body_inv_inertia: Any
    sleep_steps: Any
    v_sleep: Any
    w_sleep: Any
    body_start: Any
    rolling: Any


class BodyScratch(NamedTuple):
    """What the body stage reads and writes: the spheres' forces [N], torques about
    their centres [N m] and offsets from the centre of mass in the world [m]
    (sphere_r), their rolling torques [N m] (sphere_tr: summed, then limited per
    body), the State's x, q, P, L and rest counts, the wake flags and body_still
    (the backend's), and each body's glue force and torque about its centre of
    mass (body_glue (B, 6) [N], [N m]: kernels/glue.py; read only by a kernel
    compiled with GLUE, a stand-in otherwise); and (the CPU) whether each sphere
    touched anything at this step's contact passes (sphere_engaged, contacts.engaged:
    the others' forces are zero; CUDA passes a stand-in, unread)."""

    sphere_f: Any
    sphere_t: Any
    sphere_tr: Any
    sphere_r: Any
    body_x: Any
    body_q: Any
    body_P: Any
    body_L: Any
    body_rest: Any
    body_wake: Any
    body_still: Any
    body_glue: Any
    sphere_engaged: Any


def body_model(model, body_start, friction: bool, arrays=None) -> BodyModel:
    """The BodyModel of ``model`` (``friction``, ``arrays``: as contact_model)."""
    a = (lambda n: getattr(model, n)) if arrays is None else arrays.__getitem__
    return BodyModel(dt=float(model.dt), gravity=a("gravity"),
                     body_sphere_start=a("body_sphere_start"), body_mass=a("body_mass"),
                     body_inv_mass=a("body_inv_mass"), body_inv_inertia=a("body_inv_inertia"),
                     sleep_steps=int(model.sleep_steps), v_sleep=float(model.sleep_linear),
                     w_sleep=float(model.sleep_angular), body_start=body_start,
                     rolling=bool(model.features.rolling and friction))


def contact_model(model, friction: bool, wall_motion, arrays=None) -> ContactModel:
    """The ContactModel of ``model``; ``friction``: the backend's feature;
    ``wall_motion``: control.Drive's; ``arrays``: where to take the Model's
    arrays from by name (a CUDA backend's device copies), default the Model."""
    a = (lambda n: getattr(model, n)) if arrays is None else arrays.__getitem__
    return ContactModel(
        diameter=float(model.diameter), dt=float(model.dt),
        onset_speed=float(model.onset_speed), body_inv_mass=a("body_inv_mass"),
        body_material=a("body_material"), pair_k=a("pair_k"), pair_damp=a("pair_damp"),
        pair_mu=a("pair_mu"), kt_ratio=float(model.kt_ratio), ks_ratio=float(model.ks_ratio),
        friction=bool(friction), sleep_steps=int(model.sleep_steps),
        wall_normal=a("wall_normal"), wall_offset=a("wall_offset"), wall_lo=a("wall_lo"),
        wall_hi=a("wall_hi"), wall_depth=a("wall_depth"), wall_material=a("wall_material"),
        wall_motion=wall_motion, rolling=bool(model.features.rolling and friction),
        pair_rolling=a("pair_rolling"), body_inv_radius=a("body_inv_radius"),
        sphere_inscribed=a("sphere_inscribed"))


def step_model(model, friction: bool) -> StepModel:
    """The StepModel of ``model``; ``friction``: the backend's feature (its
    histories are kept)."""
    return StepModel(
        dt=float(model.dt), onset_speed=float(model.onset_speed),
        diameter=float(model.diameter), n_bodies=int(model.n_bodies),
        gravity=model.gravity, sphere_body=model.sphere_body, sphere_offset=model.sphere_offset,
        body_sphere_start=model.body_sphere_start, body_mass=model.body_mass,
        body_inv_mass=model.body_inv_mass, body_inv_inertia=model.body_inv_inertia,
        body_material=model.body_material, pair_k=model.pair_k, pair_damp=model.pair_damp,
        pair_mu=model.pair_mu, kt_ratio=float(model.kt_ratio), ks_ratio=float(model.ks_ratio),
        friction=bool(friction), sleep_steps=int(model.sleep_steps),
        v_sleep=float(model.sleep_linear), w_sleep=float(model.sleep_angular),
        wall_normal=model.wall_normal, wall_offset=model.wall_offset, wall_lo=model.wall_lo,
        wall_hi=model.wall_hi, wall_depth=model.wall_depth, wall_material=model.wall_material,
        rolling=bool(model.features.rolling and friction), pair_rolling=model.pair_rolling,
        body_inv_radius=model.body_inv_radius, sphere_inscribed=model.sphere_inscribed)


def scratch_of(backend) -> Scratch:
    """The Scratch of a backend holding ``cpu_scratch``'s arrays as attributes."""
    return Scratch(*(getattr(backend, n) for n in Scratch._fields))


# ---------------------------------------------------------------------------
# Glue (kernels/glue.py): the bonds as the glue passes read them
# ---------------------------------------------------------------------------

class GlueModel(NamedTuple):
    """The Model's bonds (sim.glue.Bonds, same names and units): pair_i, pair_j,
    pair_rest [m], bond_start, bond_body, bond_k [N/m], bond_eta [N s/m],
    bond_limit [N], body_bond_start, body_bond."""
    pair_i: Any
    pair_j: Any
    pair_rest: Any
    bond_start: Any
    bond_body: Any
    bond_k: Any
    bond_eta: Any
    bond_limit: Any
    body_bond_start: Any
    body_bond: Any


class GlueScratch(NamedTuple):
    """What the glue passes write: the State's bond_broken and bond_shear [m], and
    the backend's glue_f (per pair: force on pair_i [N], its torque about pair_i's
    centre [N m], the new shear stretch [m]) and body_glue (per body: force [N],
    torque about its centre of mass [N m])."""
    bond_broken: Any
    bond_shear: Any
    glue_f: Any
    body_glue: Any


def glue_model(model) -> GlueModel:
    """The GlueModel of ``model`` (empty arrays of the right kinds without glue)."""
    from dempipe.sim.glue import no_bonds
    b = model.bonds if model.bonds is not None else no_bonds(model.body_mass.shape[0])
    return GlueModel(*(getattr(b, n) for n in GlueModel._fields))


def glue_scratch(state, backend) -> GlueScratch:
    """The GlueScratch of ``state`` and a backend holding cpu_scratch's arrays (one-row
    stand-ins for a State without glue)."""
    broken = state.bond_broken if state.bond_broken is not None else np.zeros(1, np.int32)
    shear = state.bond_shear if state.bond_shear is not None else np.zeros((1, 3))
    return GlueScratch(broken, shear, backend.glue_f, backend.body_glue)
