"""Where a CPU step goes: each of the eight stages timed on its own.

    python benchmarks/profile_stages.py                  # dense pile (~25k spheres) + quickstart
    python benchmarks/profile_stages.py --steps 50 --threads 1
    python benchmarks/profile_stages.py --chess 4096 --at 0.6 --steps 300   # chess pile, busy phase

The backend's own compiled stage functions (the ones ``run_steps`` calls in
a loop) are called one at a time from Python on a scene, ``--steps`` times
each, and timed with perf_counter. Stage order and arguments are
``kernels.cpu.stages.run_steps``'s (the rebuild stages only when run_steps would rebuild
the neighbour lists, at the fixed skin SKIN: run_steps' adaptive skin is held
there for the profile), so the state advances as in a bake. Printed per
scene: microseconds per step of each stage averaged over all steps (a rebuild
stage's figure is its cost times how often it runs), its share of the sum, and the sum
against ``run_steps`` itself timed over the same number of steps in the same run
(the baseline: the difference is the cost of calling from Python and of the
parallel regions' start-up).

Scenes: the dense pile of benchmarks/cpu_bench.py (cubes of 3×3×3 spheres packed
face to face, friction on) and examples/quickstart.toml 0.3 s into its bake
(pieces landing in the tray); with ``--chess N``, instead, examples/chess.toml
with N pieces (the scene of benchmarks/vs_bullet.py) ``--at`` seconds into its
bake, where the upper layers are still falling onto the lower ones.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numba
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

from cpu_bench import dense_pile  # noqa: E402

from dempipe.sim.kernels.cpu import stages as cpu  # noqa: E402
from dempipe.sim.kernels.layout import BodyScratch, body_model, glue_scratch  # noqa: E402
from dempipe.sim.kernels.neighbours import REST_SKIN, REST_STEPS, SKIN, cell_size  # noqa: E402
from dempipe.sim.simulator import Simulator  # noqa: E402

STAGES = ("1 body velocities (eq. 5-6)", "1 sphere positions into sorted slots (eq. 19-21)",
          "2 rebuild: sphere positions + cell keys",
          "3 rebuild: broadphase (bodies in reach, their spheres near another)",
          "2 rebuild: counting sort",
          "2 rebuild: gather into sorted order",
          "2 rebuild: contact histories between sphere and slot order",
          "3 rebuild: neighbour lists (27 cells), pair indices, walls in reach",
          "3 rebuild: the busy slots (a neighbour or a wall in reach)",
          "3 rebuild: contact histories between rows and pairs",
          "4 contact patches: each body's contacts per partner (patches.py)",
          "3-4 contact forces, each computed once (its owner) + walls",
          "4 each sphere's sum over its list", "5-8 body momenta, positions, quaternions")


def stage_times(sim, state, steps: int) -> tuple[np.ndarray, int]:
    """(seconds per step of each stage, rebuilds), called one by one as run_steps does:
    the rebuild stages only at the first step and when a sphere has moved SKIN/2 d."""
    b, m = sim.backend, sim.model
    k = b.k
    b.fit_grid(state)
    partner, spring = b.contacts(state)
    fr = b.features.friction
    # within a call the contact stage reads the histories in sorted-slot order (as run_steps)
    hp, hs = (b.hist_partner, b.hist_spring) if fr else (partner, spring)
    rest = b.rest(state)
    inv_cell = 1.0 / cell_size(m.diameter)
    half = 0.5 * SKIN * m.diameter
    t = np.zeros(len(STAGES))
    rebuilds = 0
    busy = [0]          # how many slots the contact passes visit (stage_busy)

    def find_busy():
        busy[0] = cpu.stage_busy(b.nbr_n, b.wall_mask, b.sorted_idx, b.sorted_body,
                                 m.body_inv_mass, b.chunk_n, b.busy, b.sphere_f, b.sphere_t,
                                 b.sphere_tr)
        cpu.stage_listed_from(m.body_sphere_start, b.slot_of, b.busy, busy[0], b.busy_from)
        cpu.stage_note_built(state.body_x, state.body_q, b.built_bx, b.built_bq, b.seen_bx,
                             b.seen_bq, m.body_sphere_start, b.slot_of, b.slot_mark, False)
    held = np.zeros(0, dtype=np.int32)      # the spheres whose rows the last build left busy
    known = [False]     # as run_steps: after the first re-sort, only held's rows are copied

    def rows_to_pairs(s):
        """As run_steps: every row at a call's first build, later the busy ones."""
        if s == state.step:
            return cpu.stage_rows_to_pairs(b.nbr, b.nbr_n, b.pidx, b.sorted_idx, b.sorted_body,
                                           m.body_inv_mass, b.wall_mask, hp, hs, b.pair_f,
                                           b.wall_start, b.wall_s)
        slots = b.slot_of[held].astype(np.int32)
        return cpu.stage_rows_to_pairs_busy(b.busy, busy[0], slots, slots.shape[0], b.nbr,
                                            b.nbr_n, b.pidx, b.sorted_idx, b.sorted_body,
                                            m.body_inv_mass, b.wall_mask, hp, hs, b.pair_f,
                                            b.wall_start, b.wall_s)
    for s in range(state.step, state.step + steps):
        def sorted_positions():
            return k.stage_spheres_busy(m.body_sphere_start, b.slot_of, m.sphere_body,
                                        m.sphere_offset, state.body_x, state.body_q, b.body_v,
                                        b.body_w, m.dt, b.body_still, m.body_inv_mass,
                                        b.built_bx, b.built_bq, b.body_reach, b.seen_bx,
                                        b.seen_bq, b.busy, busy[0], b.busy_from, b.built_x,
                                        b.body_half, b.sorted_x, b.sorted_v, b.sphere_r)
        every = (
            lambda: k.stage_body_velocities(m.n_bodies, state.body_P, state.body_L, state.body_q,
                                            m.body_inv_mass, m.body_inv_inertia, b.body_v,
                                            b.body_w),
            sorted_positions,
        )
        rebuild = (
            lambda: k.stage_spheres(m.sphere_body, m.sphere_offset, state.body_x, state.body_q,
                                    b.body_v, b.body_w, m.dt, inv_cell, b.grid, b.sphere_x,
                                    b.sphere_v, b.sphere_r, b.sphere_key, b.sphere_hash),
            lambda: cpu.stage_near_others(b.broadphase_spheres, (1.0 + SKIN) * m.diameter,
                                          b.offset_t, state.body_x, state.body_q,
                                          m.body_sphere_start, b.body_reach, b.body_box,
                                          m.body_inv_mass, b.drive.body_start, s,
                                          b.sphere_hash),
            lambda: cpu.stage_grid_sort(b.sphere_hash, state.body_x, inv_cell, b.grid,
                                        m.body_sphere_start, b.bucket_start, b.bucket_blocks,
                                        b.body_key, b.sorted_idx, b.slot_of, b.grid_idx,
                                        b.grid_slot),
            lambda: cpu.stage_grid_gather(b.sorted_idx, b.grid_idx, b.bucket_start[b.grid[5]],
                                          b.sphere_x, b.sphere_v, b.sphere_key, m.sphere_body,
                                          b.sorted_x, b.sorted_v, b.sorted_body, b.grid_x,
                                          b.grid_key, b.grid_body),
            lambda: fr and (cpu.stage_history_in(held, held.shape[0], b.slot_of, partner,
                                                 spring, hp, hs) if known[0] else
                            cpu.stage_history_to_slots(b.sorted_idx, partner, spring, hp, hs)),
            lambda: (cpu.stage_neighbours(m.diameter, SKIN, b.grid, b.bucket_start,
                                          b.grid_idx, b.grid_x, b.grid_key, b.grid_body,
                                          b.grid_slot, b.sorted_idx, b.sorted_x, b.sorted_body,
                                          m.body_inv_mass, b.built_x, b.nbr, b.nbr_n,
                                          b.drive.body_start, s, b.sphere_hash)
                     or cpu.stage_pairs(b.nbr, b.nbr_n, b.sorted_idx, b.sorted_body,
                                        m.body_inv_mass, b.pair_start, b._pidx(), b.pair_e,
                                        b.pair_f.shape[0], b.list_start, b.list_e)
                     or cpu.stage_rest_half(b.body_v, b.body_w, b.body_reach,
                                            m.body_inv_mass, m.body_sphere_start, b.slot_of,
                                            b.slot_mark, False, half,
                                            0.5 * REST_SKIN * m.diameter, REST_STEPS * m.dt,
                                            b.body_half)
                     or cpu.stage_wall_reach(m.diameter, b.body_half, b.sorted_x,
                                             m.wall_normal, m.wall_offset, m.wall_lo, m.wall_hi,
                                             m.wall_depth, b.wall_mask, b.wall_start,
                                             hp.shape[1] if fr else 0, b.wall_s.shape[0],
                                             b.drive.wall_motion, b.sorted_body,
                                             b.drive.body_start, s, b.sorted_idx,
                                             m.sphere_inscribed)),
            find_busy,
            lambda: fr and rows_to_pairs(s),
        )
        t0 = time.perf_counter()
        every[0]()
        t[0] += time.perf_counter() - t0
        moved = 1
        if s > state.step:
            t0 = time.perf_counter()
            moved = every[1]()
            t[1] += time.perf_counter() - t0
        if moved:
            rebuilds += 1
            if fr and s > state.step:      # histories back to sphere order before the sort
                t0 = time.perf_counter()
                cpu.stage_pairs_to_rows_busy(b.busy, busy[0], b.nbr, b.nbr_n, b.pidx,
                                             b.sorted_idx, hp, hs, b.pair_f, b.wall_mask,
                                             b.wall_start, b.wall_s)
                prev = held
                held = b.sorted_idx[b.busy[:busy[0]]]
                t1 = time.perf_counter()
                if known[0]:
                    cpu.stage_history_out(b.busy, busy[0], prev, prev.shape[0], b.slot_of,
                                          b.sorted_idx, b.nbr_n, b.wall_mask, b.sorted_body,
                                          m.body_inv_mass, hp, hs, partner, spring)
                else:
                    cpu.stage_history_to_spheres(b.sorted_idx, hp, hs, partner, spring)
                t[9] += t1 - t0
                t[6] += time.perf_counter() - t1
            for i, call in enumerate(rebuild):
                t0 = time.perf_counter()
                over = call()
                while i == 5 and over:  # a list overflowed: grow, as CpuBackend.step does
                    b.grow_neighbours()
                    over = call()
                t[2 + i] += time.perf_counter() - t0
            known[0] = fr and s > state.step
        # after any rebuild: a list that grew is a new array
        cm, cs = b.contact_args(state, hist_partner=hp, hist_spring=hs)
        bm = body_model(m, b.drive.body_start, fr)
        bs = BodyScratch(b.sphere_f, b.sphere_t, b.sphere_tr, b.sphere_r, state.body_x,
                         state.body_q, state.body_P, state.body_L, rest, b.body_wake,
                         b.body_still, glue_scratch(state, b).body_glue, b.sphere_engaged)
        after = (
            lambda: k.stage_patches(cm, cs, b.drive.motion_now, m.body_sphere_start, b.slot_of,
                                    b.busy, busy[0], b.busy_from),
            lambda: k.stage_contacts(cm, cs, b.drive.motion_now, s & 1, b.busy, busy[0]),
            lambda: k.stage_sums(cm, cs, b.busy, busy[0]),
            lambda: k.stage_bodies(m.n_bodies, bm, bs, s, b.slot_of, b.busy, busy[0],
                                   b.busy_from),
        )
        for i, call in enumerate(after):
            t0 = time.perf_counter()
            call()
            t[10 + i] += time.perf_counter() - t0
    if fr:
        cpu.stage_pairs_to_rows_busy(b.busy, busy[0], b.nbr, b.nbr_n, b.pidx, b.sorted_idx,
                                     hp, hs, b.pair_f, b.wall_mask, b.wall_start, b.wall_s)
        cpu.stage_history_to_spheres(b.sorted_idx, hp, hs, partner, spring)
    state.step += steps
    state.time = state.step * m.dt
    return t / steps, rebuilds


def profile(name: str, model, warm_steps: int, steps: int) -> None:
    m = model
    sim = Simulator(model, device="cpu")
    state = model.initial_state()
    sim.backend.step(state, warm_steps)                 # compile, reach contacts
    # the stage loop below rebuilds at the fixed skin SKIN: hold run_steps' adaptive
    # skin (neighbours.adapt_skin) there too, so the two are timed alike
    sim.backend.skin_ctl[0] = sim.backend.skin_ctl[2] = sim.backend.skin_ctl[4] = SKIN
    stage_times(sim, state, 2)                          # compile the per-stage entry points
    b, none = sim.backend, sim.backend.busy[:0]         # and the later re-sorts' copies
    if b.features.friction:
        hp, hs, cp, cs = b.hist_partner, b.hist_spring, *b.contacts(state)
        cpu.stage_history_out(b.busy, 0, none, 0, b.slot_of, b.sorted_idx, b.nbr_n,
                              b.wall_mask, b.sorted_body, m.body_inv_mass, hp, hs, cp, cs)
        cpu.stage_history_in(none, 0, b.slot_of, cp, cs, hp, hs)
    per, rebuilds = stage_times(sim, state, steps)
    t0 = time.perf_counter()
    sim.backend.step(state, steps)
    whole = (time.perf_counter() - t0) / steps
    total = per.sum()
    print(f"\n### {name}: {model.n_bodies:,} bodies, {model.n_spheres:,} spheres, "
          f"features {sim.backend.flags} (friction, rotation, sleeping, walls)\n")
    print("| stage | µs/step | share | ns per sphere |")
    print("|---|---:|---:|---:|")
    for label, s in zip(STAGES, per):
        print(f"| {label} | {s * 1e6:.0f} | {s / total:.0%} | {s / model.n_spheres * 1e9:.1f} |")
    print(f"| sum of the stages | {total * 1e6:.0f} | 100% | {total / model.n_spheres * 1e9:.1f} |")
    print(f"| run_steps (baseline, same steps) | {whole * 1e6:.0f} | {whole / total:.2f}x of "
          f"the sum | {whole / model.n_spheres * 1e9:.1f} |")
    print(f"\n{model.n_spheres / whole / 1e6:.2f} M sphere-steps/s in run_steps")
    print(f"neighbour lists rebuilt at {rebuilds} of {steps} steps (skin {SKIN} d)")
    cand, near = candidates(sim, state)
    b = sim.backend
    moving = m.body_inv_mass[b.sorted_body] > 0
    n_list = b.nbr_n[moving].mean() if moving.any() else 0.0
    touching = np.count_nonzero(b.sphere_overlap > 0)
    print(f"neighbour search at a rebuild: {cand:.1f} candidates visited per sphere, "
          f"{near:.1f} of them in its 27 cells (the rest share aliased buckets); "
          f"{n_list:.1f} per list (spheres of other bodies within {1 + SKIN:g} d); "
          f"{touching / m.n_spheres:.0%} of the spheres touch something")


def candidates(sim, state, sample: int = 2000) -> tuple[float, float]:
    """(spheres visited per sphere by the neighbour search, of them in the 27 cells),
    averaged over the first ``sample`` spheres: the buckets of the 27 cells as
    kernels.cpu.device.cell_hash lays them out, counted from the grid the last step built."""
    b = sim.backend
    b.probe(state)
    g = b.grid
    counts = np.diff(b.bucket_start[: g[5] + 1])
    c = np.floor(b.sphere_x / cell_size(sim.model.diameter)).astype(np.int64)
    n = min(sample, c.shape[0])
    visited = near = 0
    for i in range(n):
        for dz in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    cx, cy, cz = c[i, 0] + dx, c[i, 1] + dy, c[i, 2] + dz
                    visited += counts[(cx & g[2]) | ((cy & g[3]) << g[0])
                                      | ((cz & g[4]) << (g[0] + g[1]))]
        near += np.count_nonzero(np.all(np.abs(c - c[i]) <= 1, axis=1))
    return visited / n, near / n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=100, help="timed steps per scene")
    ap.add_argument("--threads", type=int, default=None, help="numba threads (default: all)")
    ap.add_argument("--spheres", type=int, default=30_000, help="size of the dense pile")
    ap.add_argument("--chess", type=int, default=None, metavar="N",
                    help="profile examples/chess.toml with N pieces instead (vs_bullet's scene)")
    ap.add_argument("--at", type=float, default=0.6, metavar="SECONDS",
                    help="with --chess: how far into the bake to profile (default 0.6 s)")
    args = ap.parse_args()
    if args.threads:
        numba.set_num_threads(args.threads)
    print(f"# {platform.machine()}, {os.cpu_count()} cores, numba {numba.__version__}, "
          f"{numba.get_num_threads()} threads, {args.steps} steps per scene")

    from dempipe.scene.build import build_model
    from dempipe.scene.load import load_scene

    if args.chess:
        from vs_bullet import dempipe_model

        from dempipe.spheres.cache import SphereCache

        model = dempipe_model(args.chess, args.at + 1.0, SphereCache())
        warm = int(round(args.at / model.dt))
        profile(f"chess, {args.chess:,} pieces, at t = {warm * model.dt:.2f} s", model, warm,
                args.steps)
        return 0
    profile("dense pile (benchmarks/cpu_bench.py)", dense_pile(args.spheres), 20, args.steps)

    model = build_model(load_scene(os.path.join(HERE, "..", "examples", "quickstart.toml")))
    warm = int(0.3 / model.dt)
    profile(f"quickstart at t = {warm * model.dt:.2f} s", model, warm, args.steps)
    return 0


if __name__ == "__main__":
    sys.exit(main())
