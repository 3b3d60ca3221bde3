"""The CPU target's device functions: physics.py's, motion.py's and the contact
law's formulas compiled with ``numba.njit(inline="always")`` (``F``), contacts.py's
pairing bookkeeping (``P``), the grid's cell keys, and the neighbour walk. What the
stage drivers (kernels/cpu/stages.py, kernels/cpu/grid.py) call; the CUDA target's twin is
kernels/cuda/device.py.
"""

from __future__ import annotations

import numba
import numpy as np

from dempipe.sim.kernels import neighbours
from dempipe.sim.kernels.compile import (
    compile_chain,
    compile_formulas,
    compile_pairing,
    compile_slot_store,
    compile_walk,
    invalidate_stale_cache,
)
from dempipe.sim.kernels.layout import CPU_LAYOUT

invalidate_stale_cache(__file__)
F = compile_formulas(numba.njit(inline="always", cache=False))
quat_rotate = F.quat_rotate
quat_rotate_inv = F.quat_rotate_inv
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
glue_force = F.glue_force
contact_coefficients = F.contact_coefficients
closing = F.closing
static_body = F.static_body
anchor_state = F.anchor_state
carried_state = F.carried_state
anchor_local = F.anchor_local
anchor_surface = F.anchor_surface
chord_velocity = F.chord_velocity
sqrt = np.sqrt
P = compile_pairing(numba.njit(inline="always", cache=False), F)
entry_range = P.entry_range
wall_reach = P.wall_reach
owns = P.owns
pair_count = P.pair_count
pair_slots = P.pair_slots
pair_mirror = P.pair_mirror
rows_to_pairs = P.rows_to_pairs
pairs_to_rows = P.pairs_to_rows
# contacts.py's data layout on this target (layout.CPU_LAYOUT says what each means)
HIST_BY_SLOT = CPU_LAYOUT["HIST_BY_SLOT"]
PAIR_ROWS = CPU_LAYOUT["PAIR_ROWS"]
WALL_ROWS = CPU_LAYOUT["WALL_ROWS"]
LIST_ROWS = CPU_LAYOUT["LIST_ROWS"]
# Cell coordinates are packed into one int64 key, 21 bits per axis, so the world
# spans ±2^20 cells per axis (cells of at least (1 + SKIN_MIN_DENSE) d: ±11 km at
# 1 cm spheres, ±1.1 km at 1 mm; stability.FAR_CELLS counts in diameters,
# conservatively). Beyond that a sphere is clamped into the outermost cell but
# one: still correct (distances are exact), only slow; `dempipe check` warns
# (stability.py, "far-from-origin").
_CELL_BITS = 21

_CELL_OFF = 1 << (_CELL_BITS - 1)
_CELL_MAX = (1 << _CELL_BITS) - 1


@numba.njit(inline="always", cache=True)
def cell_coord(x, inv_cell):
    # Clamped one cell inside the key range, so that a row's neighbours c ± 1
    # are still valid keys: a sphere beyond ±2^20 cells lands in the outermost
    # cell with everything else out there, found by the neighbour search (slow
    # but correct), not lost through a key overflowing into the next axis.
    c = np.int64(np.floor(x * inv_cell)) + _CELL_OFF
    if c < 1:
        c = 1
    elif c > _CELL_MAX - 1:
        c = _CELL_MAX - 1
    return c


@numba.njit(inline="always", cache=True)
def cell_key(cx, cy, cz):
    return (cx << 42) | (cy << 21) | cz


@numba.njit(inline="always", cache=True)
def cell_hash(cx, cy, cz, grid):
    """Bucket of a cell: its coordinates wrapped into a 2^bx × 2^by × 2^bz table.

    A wrapped grid, not a scrambling hash: cells next to each other in x land in
    consecutive buckets, so a row of three neighbour cells is one contiguous run
    of grid positions (cache friendly). Far-apart cells that wrap onto the same bucket are told apart by
    their keys. grid = (bx, by, mask_x, mask_y, mask_z).
    """
    return ((cz & grid[4]) << (grid[0] + grid[1])) | ((cy & grid[3]) << grid[0]) | (cx & grid[2])


@numba.njit(inline="always", cache=True)
def spread_bits(v):
    """The 21 low bits of v spread to every third bit (bit k to bit 3k)."""
    v &= 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


@numba.njit(inline="always", cache=True)
def morton_key(cx, cy, cz):
    """A cell's place on the Z-order curve (21 bits per axis interleaved): cells
    near each other in all three axes get keys near each other."""
    return (spread_bits(cz) << 2) | (spread_bits(cy) << 1) | spread_bits(cx)


_slots = compile_slot_store(numba.njit(inline="always", cache=False))
slot_place = _slots.slot_place
slot_store = _slots.slot_store
_skins = compile_chain(neighbours, ("shrink_skin", "adapt_skin"),
                       numba.njit(inline="always", cache=False), {})
adapt_skin = _skins.adapt_skin
shrink_skin = _skins.shrink_skin
neighbour_list = compile_walk(numba.njit(inline="always", cache=False), F, cell_coord, cell_key,
                              cell_hash, True)
