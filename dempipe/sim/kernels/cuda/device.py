"""Device functions and constants of the CUDA target: the formulas (physics.py,
the contact law) and the shared kernels' code (neighbours.py, contacts.py, the glue
passes of glue.py) compiled as device functions, the grid's cell functions, the
control array's slots (CTL_*) and the launch sizes. The kernels live by stage in cuda/grid.py,
cuda/stages.py; the backend in cuda.py. See docs/cuda.md.
"""

from __future__ import annotations

import inspect
import math

from numba import cuda, int64
from numba.core import config

from dempipe.sim.kernels import bodies, prescribed
from dempipe.sim.kernels.compile import (
    compile_chain,
    compile_contacts,
    compile_formulas,
    compile_glue,
    compile_pairing,
    compile_slot_store,
    compile_walk,
)
from dempipe.sim.kernels.layout import CUDA_LAYOUT


def device_jit():
    """Device-function decorator that inlines: numba-cuda's ``forceinline``
    (NVVM ``alwaysinline``), or the built-in target's ``inline``."""
    try:
        params = inspect.signature(cuda.jit).parameters
    except (TypeError, ValueError):
        params = {}
    if "forceinline" in params:
        return cuda.jit(device=True, forceinline=True)
    return cuda.jit(device=True, inline=True)


F = compile_formulas(device_jit())
angular_velocity = F.angular_velocity
sphere_kinematics = F.sphere_kinematics
sphere_pair_force = F.sphere_pair_force
sphere_wall_force = F.sphere_wall_force
rolling_torque = F.rolling_torque
rolling_scale = F.rolling_scale
body_step = F.body_step
history_recall = F.history_recall
history_store = F.history_store
rest_steps = F.rest_steps

SIMULATOR = bool(config.ENABLE_CUDASIM)
#: Threads per block. The simulator runs each CUDA thread as a Python thread,
#: so it gets small blocks; the algorithm does not depend on the block size.
THREADS = 32 if SIMULATOR else 256
CONTACT_THREADS = 32 if SIMULATOR else 128      # register-heavy: smaller blocks
SCAN_B = 8 if SIMULATOR else 256                # threads per block of the prefix sum
SCAN_ITEMS = 32 if SIMULATOR else 8            # elements per thread of the prefix sum
SCAN_CHUNK = SCAN_B * SCAN_ITEMS                # elements per block of the prefix sum
#: Kernels over the bucket table loop with a grid stride over at most this many blocks.
TABLE_BLOCKS = 1 if SIMULATOR else 4096

# Same packing as kernels/cpu/stages.py: 21 bits per axis.
_CELL_BITS = 21
_CELL_OFF = 1 << (_CELL_BITS - 1)
_CELL_MAX = (1 << _CELL_BITS) - 1
_INT64_LIMIT = 9.2e18

# The control array ``ctl`` (int32, CTL_SIZE words on the device): how the steps
# of one ``step`` call decide, on the device, whether to rebuild the neighbour
# lists, and what the host reads back once at the end of the call.
#: 1: rebuild at this step (set for the first step of a call by k_begin_call).
CTL_FORCE = 0
#: Spheres that moved SKIN/2 d or more since the last build (k_spheres_sorted).
CTL_MOVED = 1
#: Lists that did not fit into nbr in this call (k_neighbours): 0 = all fitted.
CTL_OVER = 2
#: Longest list found by an overflowing build in this call (integer atomic max).
CTL_MAXN = 3
#: Rebuilds done in this call (counted by k_bodies' thread 0 as it closes a step).
CTL_REBUILDS = 4
#: Steps done in this call (k_bodies' thread 0; not counted once CTL_OVER is set:
#: from the overflowing step on, nothing of the State changes).
CTL_DONE = 5
#: Bodies awake after the last body stage (k_bodies, integer atomic adds; reset by
#: k_idle_check at the start of each step, 1 after k_begin_call).
CTL_AWAKE = 6
#: 1: every body sleeps, so the rest of the call's steps are no-ops (set by
#: k_idle_check; the CPU target skips them the same way). Counted in CTL_IDLE_STEPS.
CTL_IDLE = 7
CTL_IDLE_STEPS = 8
#: The number of the step being run (k_begin_call sets the call's first step
#: less one, k_idle_check adds one as each step begins): the time of the
#: prescribed motions and the emitters' start steps read it on the device.
CTL_STEP = 9
CTL_SIZE = 10


@cuda.jit(device=True)
def cell_coord(x, inv_cell):
    # int64(floor(v)) + offset, clamped, as on the CPU. NaN and |v| >= 2^63 give
    # cell 1 there (x86 float->int conversion yields INT64_MIN); do the same
    # without ever converting them (the simulator's math.floor(nan) raises).
    # Clamped to [1, _CELL_MAX - 1] as on the CPU (see kernels/cpu/stages.py).
    v = x * inv_cell
    if v >= -_CELL_OFF and v < _CELL_OFF:
        c = int64(math.floor(v)) + _CELL_OFF
        if c < 1:
            return int64(1)
        if c > _CELL_MAX - 1:
            return int64(_CELL_MAX - 1)
        return c
    if v >= _CELL_OFF and v < _INT64_LIMIT:
        return int64(_CELL_MAX - 1)
    return int64(1)


@cuda.jit(device=True)
def cell_key(cx, cy, cz):
    return (cx << 42) | (cy << 21) | cz


@cuda.jit(device=True)
def cell_hash(cx, cy, cz, grid):
    """Bucket of a cell in the wrapped 2^bx × 2^by × 2^bz table (see kernels/cpu/stages.py)."""
    return ((cz & grid[4]) << (grid[0] + grid[1])) | ((cy & grid[3]) << grid[0]) | (cx & grid[2])


neighbour_list = compile_walk(device_jit(), F, cell_coord, cell_key, cell_hash, False)
_slots = compile_slot_store(device_jit())
slot_place = _slots.slot_place
slot_store = _slots.slot_store
P = compile_pairing(device_jit(), F)
wall_reach = P.wall_reach
pair_slots = P.pair_slots
pair_mirror = P.pair_mirror
rows_to_pairs = P.rows_to_pairs
pairs_to_rows = P.pairs_to_rows
#: Feature flags the contact and body kernels are compiled for (``kernels(flags)``),
#: as kernels/cpu/stages.py's: a feature that is off is a constant-false branch, its code
#: removed by NVVM. The module's own kernels are the general ones (all on, each
#: feature also checked at run time: friction, sleep_steps > 0, the wall masks).
FRICTION = True
ROTATION = True
SLEEPING = True
WALLS = True
C = compile_contacts(device_jit(), F, P, dict(FRICTION=True, ROTATION=True, SLEEPING=True,
                                             WALLS=True, sqrt=math.sqrt, **CUDA_LAYOUT))
pair_forces = C.pair_forces
sphere_forces = C.sphere_forces
body_patches = C.body_patches
#: The glue passes (kernels/glue.py), general: launched only for a scene with bonds.
G = compile_glue(device_jit(), F, P, dict(FRICTION=True, ROTATION=True, SLEEPING=True,
                                          WALLS=True, sqrt=math.sqrt, **CUDA_LAYOUT))
bond_forces = G.bond_forces
bond_contacts = G.bond_contacts
body_glue_sum = G.body_glue_sum


def compile_body_stage(consts: dict):
    """kernels/bodies.py's body_update and kernels/prescribed.py's motion_row,
    driven_row as device functions with the feature flags ``consts`` (and GLUE: the
    bonds' sum, kernels/glue.py, added to each body's; off unless given; INSCRIBED:
    the spheres' torques without friction, which CUDA's contact passes, holding the
    inscribed tori always, write: compile.compile_contacts)."""
    given = dict(dict(dict(GLUE=False, INSCRIBED=True), **consts), static_body=F.static_body,
                 body_step=F.body_step,
                 angular_velocity=F.angular_velocity, rest_steps=F.rest_steps,
                 rolling_scale=F.rolling_scale,
                 anchor_state=F.anchor_state, carried_state=F.carried_state,
                 chord_velocity=F.chord_velocity)
    b = compile_chain(bodies, ("body_update",), device_jit(), given)
    r = compile_chain(prescribed, ("motion_row", "driven_row"), device_jit(), given)
    return b.body_update, r.motion_row, r.driven_row


body_update, motion_row, driven_row = compile_body_stage(
    dict(FRICTION=True, ROTATION=True, SLEEPING=True, WALLS=True))


@cuda.jit(device=True)
def rebuilding(ctl):
    """Whether this step rebuilds the neighbour lists: the first step of a call
    (CTL_FORCE), or some sphere moved SKIN/2 d since the last build (CTL_MOVED).
    Read by every rebuild kernel; written only by k_begin_call,
    k_spheres_sorted (before any of them runs) and k_bodies (after)."""
    return ctl[CTL_FORCE] != 0 or ctl[CTL_MOVED] != 0
