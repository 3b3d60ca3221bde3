"""The CPU backend: owns a Model's scratch arrays (``layout.cpu_scratch``, by name)
and advances States with the stage drivers of kernels/cpu/stages.py (``run_steps``),
compiled for the scene's features (``kernels(flags)``).
"""

from __future__ import annotations

import numpy as np

from dempipe.sim.backend import copy_matching, skip_idle_call
from dempipe.sim.control import drive, split_at
from dempipe.sim.kernels.cpu.broadphase import (
    BROADPHASE_SPHERES,
    body_bounds,
    stage_near_others,
)
from dempipe.sim.kernels.cpu.grid import (
    stage_grid_gather,
    stage_grid_sort,
    stage_neighbours,
    stage_pairs,
    stage_rows_to_pairs,
    stage_wall_reach,
)
from dempipe.sim.kernels.cpu.spheres import stage_listed_from
from dempipe.sim.kernels.cpu.stages import (
    KEEP_MOVE,
    KEEP_SLOTS_SHARE,
    QUIET_SHARE,
    kernels,
    stage_busy,
)
from dempipe.sim.kernels.layout import (
    ContactScratch,
    StepState,
    contact_model,
    cpu_scratch,
    fit_grid,
    glue_model,
    glue_scratch,
    grid_table,
    run_flags,
    scene_features,
    scratch_of,
    static_extent,
    step_model,
)
from dempipe.sim.kernels.neighbours import REST_SKIN, SKIN, cell_size, skin_range
from dempipe.sim.kernels.pairing import LIST_COLS, PAIR_COLS
from dempipe.spheres.inscribed import all_own


class CpuBackend:
    """Owns the scratch arrays of one Model and advances States with ``run_steps``.

    features : run as if the scene used these (default: the model's; see
      scene_features). specialize : compile out the features not used (True);
      False runs the general kernel, every feature compiled in; None (default):
      as $DEMPIPE_KERNELS says (layout.run_flags).
    """

    name = "cpu"

    def __init__(self, model, features=None, specialize: bool | None = None):
        self.model = model
        #: Steps skipped because every body slept (counted as done, not computed).
        self.steps_skipped = 0
        self.features = scene_features(model, features)
        self.flags = run_flags(self.features, specialize)
        self.k = kernels(self.flags, model.contact_law, glue=model.n_bonds > 0,
                         inscribed=not all_own(model.sphere_inscribed, model.diameter))
        #: The glue bonds as the kernels read them (layout.GlueModel).
        self.glue_model = glue_model(model)
        # every array, by name (layout.cpu_scratch: what memory_estimate counts and a
        # checkpoint walks), zeroed; then the ones that start otherwise
        for name, (shape, dtype) in cpu_scratch(model, self.features.friction).items():
            setattr(self, name, np.zeros(shape, dtype=dtype))
        self.grid = grid_table(model.n_spheres)
        lo, hi = skin_range(model)
        self.skin_ctl[:] = (lo, 0.0, hi, 0.0, lo)
        self.body_still[model.n_bodies:] = 1     # static colliders never move
        # each body's farthest sphere from its centre (stage_spheres_busy's bound) and
        # the box of its spheres (the broadphase's)
        body_bounds(model.sphere_offset, model.body_sphere_start, self.body_reach,
                    self.body_box)
        self.offset_t[:] = model.sphere_offset.T
        #: Whether a call with every body asleep and nothing moving skips its steps
        #: outright (backend.nothing_moves); False: the kernels find it (the same State).
        self.skip_idle = True
        #: Share of quiet bodies from which the contact passes skip the quiet slots
        #: (stage_active); above 1, never (the same State: benchmarks/sleeping_pile.py).
        self.quiet_share = QUIET_SHARE
        #: Spheres per dynamic body from which a rebuild searches only the spheres
        #: another body can reach (broadphase.py); 0: always (the same State).
        self.broadphase_spheres = BROADPHASE_SPHERES
        #: Largest share of moved spheres at which a rebuild keeps the slots and
        #: searches only the lists that can change (run_steps); 0: never (the same State).
        self.keep_share = KEEP_SLOTS_SHARE
        #: At such a rebuild, the share of half the skin a body must have moved for its
        #: lists to be searched again (run_steps); 0: any move (the same State).
        self.keep_move = KEEP_MOVE
        #: A body at rest's skin [d] (neighbours.REST_SKIN: its rebuild distance is half
        #: this, run_steps); at or above the largest skin, none is narrowed (the same State).
        self.rest_skin = REST_SKIN
        if not self.features.friction:   # the histories in sorted-slot order, within a call
            self.hist_partner, self.hist_spring = self._no_partner, self._no_spring
        #: What a step reads of the Model (layout.StepModel), one structured argument.
        self.step_model = step_model(model, self.features.friction)
        #: The prescribed inputs as the kernels read them (control.Drive).
        self.drive = drive(model)
        self._starts = np.unique(self.drive.body_start[self.drive.body_start > 0])
        self.static_box = static_extent(model)
        if self.static_box is not None:
            self.static_lo[:], self.static_hi[:] = self.static_box

    def fit_grid(self, state) -> None:
        """Fit the grid's bits to where the bodies are now (once per call of step,
        ``layout.fit_grid``)."""
        if self.model.body_mass.shape[0]:
            self.grid = fit_grid(self.model, state.body_x, self.static_box)

    def step(self, state, n_steps: int, control=None) -> None:
        """Advance ``state`` in place by ``n_steps`` steps (and its step count and time).
        ``control`` (dempipe.sim.control.Control): the controlled bodies' poses, put into
        the State before the first step (whose rebuild places their spheres)."""
        prescribed = control is not None and not control.empty
        if control is not None:
            control.apply(state)
        # an emitter's start step begins a call (whose first step rebuilds the lists)
        for n in split_at(int(state.step), int(n_steps), self._starts):
            if skip_idle_call(self, state, n, prescribed):
                continue
            self._advance(state, n)

    def _advance(self, state, n_steps: int) -> None:
        m = self.model
        self.fit_grid(state)
        partner, spring = self.contacts(state)
        left = int(n_steps)
        while left > 0:
            done, computed = self.k.run_steps(
                left, int(state.step), self.grid, float(self.quiet_share),
                float(self.keep_share), float(self.keep_move), float(self.rest_skin),
                int(self.broadphase_spheres),
                self.step_model,
                StepState(state.body_x, state.body_q, state.body_P, state.body_L,
                          self.rest(state), partner, spring),
                self._scratch(), self.drive, self.glue_model, glue_scratch(state, self))
            state.step += int(done)
            state.time = state.step * m.dt
            left -= int(done)
            self.steps_skipped += int(done) - int(computed)
            if left > 0:
                self.grow_neighbours()

    def _scratch(self):
        """The scratch arrays as run_steps takes them (layout.Scratch): the current
        ones (the lists may have grown, a test may have replaced one)."""
        self._pidx()
        return scratch_of(self)

    def grow_neighbours(self) -> None:
        """Room for the longest neighbour list the last rebuild found (nbr_n), doubled
        at least: a pile that grows denser rarely needs a second growth; or, when
        the lists fitted, for the pairs it found (pair_start[-1]), 1.5 times."""
        cap = self.nbr.shape[1]
        need = int(self.nbr_n.max())
        if need > cap:
            while cap < need:
                cap *= 2
            self.nbr = np.zeros((self.model.n_spheres, cap), dtype=np.int32)
            return
        entries = int(self.list_start[-1])
        if entries > self.list_e.shape[0]:
            self.list_e = np.zeros((entries + entries // 2, LIST_COLS), dtype=np.int32)
        walls = int(self.wall_start[-1])
        if walls > self.wall_s.shape[0]:
            self.wall_s = np.zeros((walls + walls // 2, 4))
        pairs = int(self.pair_start[-1])
        if pairs > self.pair_f.shape[0]:
            self.pair_f = np.zeros((pairs + pairs // 2, PAIR_COLS))
            self.pair_e = np.zeros(self.pair_f.shape[0], dtype=np.int32)

    def _pidx(self):
        """The pair indices, shaped as the lists (which grow, or a test replaces)."""
        if self.pidx.shape != self.nbr.shape:
            self.pidx = np.zeros(self.nbr.shape, dtype=np.int32)
        return self.pidx

    def rest(self, state):
        """The State's rest counts (sleeping), allocated on first use."""
        state.ensure_rest(self.model.body_mass.shape[0])
        return state.body_rest

    def contacts(self, state):
        """The State's contact histories, allocated on first use when friction is on
        (a 1-slot dummy otherwise: frictionless kernels never touch them)."""
        if not self.features.friction:
            return self._no_partner, self._no_spring
        state.ensure_contacts(self.model.n_spheres)
        return state.contact_partner, state.contact_spring

    def probe(self, state) -> None:
        """Stages 1-4 without moving anything: fills sphere_f, sphere_overlap.

        Reads the contact histories but does not change the State's."""
        m = self.model
        self.fit_grid(state)
        self.k.stage_body_velocities(m.n_bodies, state.body_P, state.body_L, state.body_q,
                                     m.body_inv_mass, m.body_inv_inertia, self.body_v,
                                     self.body_w)
        self._drive_now(state)
        self.k.stage_spheres(m.sphere_body, m.sphere_offset, state.body_x, state.body_q,
                             self.body_v, self.body_w, m.dt, 1.0 / cell_size(m.diameter),
                             self.grid,
                             self.sphere_x, self.sphere_v, self.sphere_r, self.sphere_key,
                             self.sphere_hash)
        stage_near_others(self.broadphase_spheres, cell_size(m.diameter), self.offset_t,
                          state.body_x, state.body_q, m.body_sphere_start, self.body_reach,
                          self.body_box, m.body_inv_mass, self.drive.body_start,
                          int(state.step), self.sphere_hash)
        stage_grid_sort(self.sphere_hash, state.body_x, 1.0 / cell_size(m.diameter), self.grid,
                        m.body_sphere_start, self.bucket_start, self.bucket_blocks, self.body_key,
                        self.sorted_idx, self.slot_of, self.grid_idx, self.grid_slot)
        stage_grid_gather(self.sorted_idx, self.grid_idx, self.bucket_start[self.grid[5]],
                          self.sphere_x, self.sphere_v, self.sphere_key, m.sphere_body,
                          self.sorted_x, self.sorted_v, self.sorted_body, self.grid_x,
                          self.grid_key, self.grid_body)
        self.body_half[:] = 0.5 * SKIN * m.diameter
        while (stage_neighbours(m.diameter, SKIN, self.grid, self.bucket_start, self.grid_idx,
                                self.grid_x, self.grid_key, self.grid_body, self.grid_slot,
                                self.sorted_idx, self.sorted_x, self.sorted_body,
                                m.body_inv_mass, self.built_x, self.nbr, self.nbr_n,
                                self.drive.body_start, int(state.step), self.sphere_hash) > 0
               or stage_pairs(self.nbr, self.nbr_n, self.sorted_idx, self.sorted_body,
                              m.body_inv_mass, self.pair_start, self._pidx(), self.pair_e,
                              self.pair_f.shape[0], self.list_start, self.list_e) > 0
               or stage_wall_reach(m.diameter, self.body_half, self.sorted_x, m.wall_normal,
                                   m.wall_offset, m.wall_lo, m.wall_hi, m.wall_depth,
                                   self.wall_mask, self.wall_start,
                                   self.hist_partner.shape[1] if self.features.friction else 0,
                                   self.wall_s.shape[0], self.drive.wall_motion,
                                   self.sorted_body, self.drive.body_start,
                                   int(state.step), self.sorted_idx, m.sphere_inscribed) > 0):
            self.grow_neighbours()
        self.sphere_overlap[:] = 0.0
        partner, spring = self.contacts(state)
        # copies in sorted-slot order, as the contact stage reads them
        slots = self.sorted_idx if self.features.friction else np.zeros(1, dtype=np.int32)
        partner, spring = partner[slots], spring[slots]
        if self.features.friction:
            stage_rows_to_pairs(self.nbr, self.nbr_n, self.pidx, self.sorted_idx,
                                self.sorted_body, m.body_inv_mass, self.wall_mask, partner,
                                spring, self.pair_f, self.wall_start, self.wall_s)
        # the copied histories, and a copy of the wake flags: a probe wakes nothing
        cm, cs = self.contact_args(state, hist_partner=partner, hist_spring=spring,
                                   body_wake=self.body_wake.copy())
        self.sphere_engaged[:] = 1              # every busy slot (contacts.engaged)
        n_busy = stage_busy(self.nbr_n, self.wall_mask, self.sorted_idx, self.sorted_body,
                            m.body_inv_mass, self.chunk_n, self.busy, self.sphere_f,
                            self.sphere_t, self.sphere_tr)
        stage_listed_from(m.body_sphere_start, self.slot_of, self.busy, n_busy, self.busy_from)
        self.k.stage_patches(cm, cs, self.drive.motion_now, m.body_sphere_start, self.slot_of,
                             self.busy, n_busy, self.busy_from)
        self.k.stage_contacts(cm, cs, self.drive.motion_now, state.step & 1, self.busy, n_busy)
        self.k.stage_sums(cm, cs, self.busy, n_busy)

    def contact_args(self, state, **given):
        """(layout.ContactModel, layout.ContactScratch) of the contact passes for
        ``state``, as run_steps builds them: the backend's arrays and the State's rest
        counts, but for the arrays ``given`` by name (the probe's copies)."""
        given.setdefault("body_rest", self.rest(state))
        given.setdefault("body_q", state.body_q)
        cs = ContactScratch(*(given[n] if n in given else getattr(self, n)
                              for n in ContactScratch._fields))
        return contact_model(self.model, self.features.friction, self.drive.wall_motion), cs

    def velocities(self, state):
        """(V, W) of the dynamic bodies for ``state`` [m/s], [rad/s], world frame."""
        m = self.model
        self.k.stage_body_velocities(m.n_bodies, state.body_P, state.body_L, state.body_q,
                              m.body_inv_mass, m.body_inv_inertia, self.body_v, self.body_w)
        self._drive_now(state)      # the kinematic bodies' prescribed velocities
        return self.body_v[: m.n_bodies].copy(), self.body_w[: m.n_bodies].copy()

    def _drive_now(self, state) -> None:
        """The prescribed motions at the State's time: the carried bodies' poses and
        velocities (as the kernels put them at a step's start)."""
        d = self.drive
        if d.motion_now.shape[0]:
            self.k.stage_motion(int(state.step) * self.model.dt, d.motion_kind, d.motion_v,
                                d.motion_w, d.motion_pivot, d.key_start, d.key_t, d.key_p,
                                d.key_q, d.motion_now)
            self.k.stage_driven(d.driven_body, d.body_motion, d.body_anchor_c,
                                d.body_anchor_q, d.motion_now, state.body_x, state.body_q,
                                self.body_v, self.body_w, self.rest(state), self.body_still,
                                0.0)

    def save_arrays(self, state, names) -> dict:
        """The arrays ``names`` this backend has (Backend.save_arrays)."""
        return {n: np.asarray(a) for n in names if (a := getattr(self, n, None)) is not None}

    def load_arrays(self, state, arrays: dict) -> None:
        """Copy ``arrays`` into this backend's arrays of the same names and shapes."""
        copy_matching(self, arrays)

    def take_max_overlap(self) -> float:
        """Largest overlap since the last call [m], then reset."""
        v = float(self.sphere_overlap.max()) if self.sphere_overlap.size else 0.0
        self.sphere_overlap[:] = 0.0
        return v
