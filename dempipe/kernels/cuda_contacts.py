"""Stage 4 on the device: the pairs at a rebuild (pair rows, walls in reach, the
histories in and out) and the two contact passes (contacts.py, compiled by
cuda_device; specialized per feature set by kernels.cuda.kernels).

Imported by kernels/cuda.py (the backend launches them); see docs/cuda.md.
"""

from __future__ import annotations

from numba import cuda

from .cuda_device import (CTL_FORCE, CTL_IDLE, CTL_MOVED, CTL_OVER, CTL_STEP, pair_forces,
                          pair_mirror, pair_slots, pairs_to_rows, rebuilding, rows_to_pairs,
                          sphere_forces, wall_reach)


@cuda.jit
def k_save_pairs(at_end, friction, nbr, nbr_n, pidx, sorted_idx, contact_partner,
                 contact_spring, pair_f, ctl):
    """With friction: the touching pairs' stretches back into their owners' history
    rows (contacts.pairs_to_rows), while
    the lists they were read from still stand: at a rebuild that is not a
    call's first step (before the re-sort), and (``at_end``, launched by the
    host) after a call's last step."""
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0] or not friction:
        return
    if not at_end and (ctl[CTL_FORCE] != 0 or ctl[CTL_MOVED] == 0 or ctl[CTL_OVER] != 0):
        return
    pairs_to_rows(s, sorted_idx[s], nbr, nbr_n, pidx, sorted_idx, contact_partner,
                  contact_spring, pair_f)


@cuda.jit
def k_pair_slots(nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx, ctl):
    """Rebuild: the pair index of each list entry a slot owns: row s * cap + k of
    pair_f for its k-th (no scan: every list entry has a row)."""
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0] or not rebuilding(ctl) or ctl[CTL_OVER] != 0:
        return
    pair_slots(s, s * nbr.shape[1], nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx)


@cuda.jit
def k_pair_mirror(radius, margin, nbr, nbr_n, sorted_idx, sorted_x, sorted_body,
                  body_inv_mass, wall_normal, wall_offset, wall_lo, wall_hi, wall_depth,
                  wall_motion, body_start, wall_mask, pidx, ctl):
    """Rebuild, after k_pair_slots: the entries the partner owns
    (contacts.pair_mirror) and the walls in reach (contacts.wall_reach)."""
    s = cuda.grid(1)
    if s >= sorted_idx.shape[0] or not rebuilding(ctl) or ctl[CTL_OVER] != 0:
        return
    pair_mirror(s, nbr, nbr_n, sorted_idx, sorted_body, body_inv_mass, pidx)
    wall_reach(s, radius, margin, sorted_x, wall_normal, wall_offset, wall_lo, wall_hi,
               wall_depth, wall_motion, wall_mask)
    if body_start[sorted_body[s]] > ctl[CTL_STEP]:
        wall_mask[s] = 0                    # not emitted yet: no wall either


@cuda.jit
def k_load_pairs(friction, nbr, nbr_n, pidx, sorted_idx, sorted_body, body_inv_mass,
                 wall_mask, contact_partner, contact_spring, pair_f, ctl):
    """Rebuild, with friction, after k_pair_mirror: the owned pairs' stretches from the
    history rows into pair_f; the rows keep the walls in reach (contacts.rows_to_pairs)."""
    s = cuda.grid(1)
    n = sorted_idx.shape[0]
    if s >= n or not friction or not rebuilding(ctl) or ctl[CTL_OVER] != 0:
        return
    rows_to_pairs(s, sorted_idx[s], n, nbr, nbr_n, pidx, sorted_idx, sorted_body,
                  body_inv_mass, wall_mask, contact_partner, contact_spring, pair_f)


@cuda.jit
def k_pair_forces(cm, cs, motion_now, parity, ctl):
    """Stages 3-4, first pass (contacts.pair_forces, one thread per sorted slot): each
    contact computed once, by its owner, and each sphere's walls. After an overflow
    in this call (ctl[CTL_OVER]) or once every body sleeps it returns at once.
    cm, cs: layout.ContactModel, ContactScratch (the CPU's packed rows in cs are
    stand-ins here: PAIR_ROWS, WALL_ROWS, LIST_ROWS are off)."""
    s = cuda.grid(1)
    if s >= cs.sorted_idx.shape[0] or ctl[CTL_OVER] != 0 or ctl[CTL_IDLE] != 0:
        return
    pair_forces(s, s + 1, cm, cs, motion_now, parity)


@cuda.jit
def k_sphere_forces(cm, cs, ctl):
    """Stage 4, second pass (contacts.sphere_forces): each sphere's sum over its list
    in its partners' index order, then its walls; the CPU's order and sums."""
    s = cuda.grid(1)
    if s >= cs.sorted_idx.shape[0] or ctl[CTL_OVER] != 0 or ctl[CTL_IDLE] != 0:
        return
    sphere_forces(s, s + 1, cm, cs)
