"""CUDA target: the paper's eight stages as numba.cuda kernels, and their backend.

Imported only when the CUDA device is used (``simulator.make_backend``); it
imports nothing from ``kernels/cpu/stages.py`` (that would compile the CPU kernels),
only the shared constants of ``kernels/neighbours.py``. The formulas come from
physics.py, compiled as device functions (cuda/device.py); the kernels live by
stage (cuda/grid.py: stages 1-3; cuda/stages.py: stages 4-8;
stages 5-8 and sleep), each mirroring its CPU stage, with the loop header
``cuda.grid(1)`` instead of ``prange``. This module holds the host side: the
specialized variants (``kernels``), the layout and memory checks, and
``CudaBackend``. See docs/cuda.md.

Neighbour lists (kernels/neighbours.py): the grid, the sort and the 27-cell
search run only at a rebuild, as on the CPU; a small device control array
(``ctl``, see CTL_*) says whether this step rebuilds, so the rebuild kernels
are always launched and return at once when it does not: a step is a fixed
sequence of launches with no host synchronisation (``CudaBackend.step_once``).

Determinism: the only atomics are integer adds (bucket counts, slot claims,
the count of spheres that moved, the count of overflowing lists), an integer
max (the longest list) and a float max (exact, commutative); integer atomics
give the same totals whatever the order. The slots a bucket's spheres land in
depend on thread timing, so each bucket is then sorted by sphere index: the
sorted order is exactly the CPU's stable counting sort. Each slot's thread
builds its own list, inserting partners in sphere-index order: the CPU's
lists. Contacts gather (each sphere sums its own list in that order, then the
walls), bodies sum their spheres in index order. Results are bit-identical
run to run on one GPU, and do not depend on when the lists were rebuilt.

Everything of a Model and of the State being stepped lives on the device; the
host State is updated once per ``step`` call (once per output frame).
"""

from __future__ import annotations

import math
import types

import numpy as np
from numba import cuda

from dempipe.sim.control import drive, split_at
from dempipe.errors import DeviceError
from dempipe.sim.laws.linear import DAMP_TERMS
from dempipe.sim.state import CONTACT_SLOTS
from dempipe.sim.backend import copy_matching, skip_idle_call
from dempipe.sim.kernels.compile import compile_contacts, compile_formulas, compile_glue
from dempipe.sim.kernels.pairing import PAIR_COLS, WALL_SLACK
from dempipe.sim.kernels.patches import BODY_PATCHES
from dempipe.sim.kernels.layout import (
    CUDA_LAYOUT, FLAGS, GENERAL, ContactScratch, BodyScratch, GlueModel, GlueScratch,
    body_model, layout_bytes, contact_model, fit_grid, glue_model, grid_table, run_flags,
    scene_features, static_extent)
from dempipe.sim.kernels.neighbours import NEIGHBOURS, SKIN, cell_size
# The device side, by stage (each module's docstring says what it holds); the kernels
# are imported here by name, so that the backend's launches read them from this
# module (benchmarks/cuda_compile_table.py records launches by these names).
from dempipe.sim.kernels.cuda.device import (
    CONTACT_THREADS, CTL_DONE, CTL_FORCE, CTL_IDLE_STEPS, CTL_MAXN,
    CTL_OVER, CTL_REBUILDS, CTL_SIZE, F, P, SCAN_B, SCAN_CHUNK,
    TABLE_BLOCKS, THREADS, device_jit, compile_body_stage)
from dempipe.sim.kernels.cuda.grid import (
    k_bucket_sort, k_gather, k_neighbours, k_scan_add, k_scan_blocks, k_scatter, k_spheres,
    k_spheres_sorted, k_unsort, k_zero_buckets)
from dempipe.sim.kernels.cuda.stages import (
    k_begin_call, k_body_velocities, k_driven, k_fill, k_idle_check, k_load_pairs, k_motion,
    k_pair_mirror, k_pair_slots, k_save_pairs, k_take_max)
# SPECIALIZED, GLUE_KERNELS: kernels() looks them up through globals()
from dempipe.sim.kernels.cuda.stages import (  # noqa: F401
    k_bodies, k_body_glue, k_body_patches, k_bond_contacts, k_bond_forces, k_pair_forces,
    k_sphere_forces)
from dempipe.sim.kernels.cuda import stages as _stages


# ---------------------------------------------------------------------------
# Host side
# ---------------------------------------------------------------------------

#: The kernels compiled per feature set (FLAGS); the others read no flag.
SPECIALIZED = ("k_body_patches", "k_pair_forces", "k_sphere_forces", "k_bodies")
#: The glue passes (kernels/glue.py), in a scene with bonds only: compiled per feature
#: set as SPECIALIZED, and k_bodies then adds the bonds' sums (GLUE).
GLUE_KERNELS = ("k_bond_forces", "k_bond_contacts", "k_body_glue")
_VARIANTS: dict = {}


def variant_tag(flags) -> str:
    """'F1R0S0W1': the flags (FLAGS' order) of a variant, as in its kernels' names."""
    return "".join(f"{n[0].upper()}{int(f)}" for n, f in zip(FLAGS, flags))


def kernels(flags, law: str = "linear", glue: bool = False) -> types.SimpleNamespace:
    """The SPECIALIZED kernels (and with ``glue`` the GLUE_KERNELS) compiled for
    ``flags`` (friction, rotation, sleeping, walls), created on first use
    (numba-cuda compiles each at its first launch): contacts.pair_forces /
    sphere_forces and glue.py's passes compiled with those flags as constants, and
    the kernels re-created with their modules' globals overlaid by them and by the
    flags (compile.specialize's rebinding, for cuda.jit). ``GENERAL`` gives the
    module's own kernels (with ``glue``, k_bodies re-created to add the bonds'
    sums: the module's own leaves them out). With ``glue`` the contact passes are
    the unglued variant's own objects (one compile for both); a ``law`` other than the linear one
    (laws.LAWS) has its formulas compiled into the contact passes."""
    flags = tuple(bool(f) for f in flags)
    names = SPECIALIZED + (GLUE_KERNELS if glue else ())
    general = flags == GENERAL and law == "linear"
    if general and not glue:
        return types.SimpleNamespace(**{n: globals()[n] for n in names})
    key = (flags, law, bool(glue))
    if key not in _VARIANTS:
        # the contact passes know nothing of glue: a glued scene shares them with the
        # unglued variant of its flags, compiled once (only k_bodies adds the bonds)
        shared = kernels(flags, law) if glue else None
        consts = {n.upper(): f for n, f in zip(FLAGS, flags)}
        formulas = F if law == "linear" else compile_formulas(device_jit(), law)
        layout = dict(consts, sqrt=math.sqrt, **CUDA_LAYOUT)
        c = compile_contacts(device_jit(), formulas, P, layout)
        g = compile_glue(device_jit(), formulas, P, layout) if glue else None
        body_update, _, _ = compile_body_stage(dict(consts, GLUE=bool(glue)))
        out = {}
        for name in names:
            if general and name != "k_bodies":
                out[name] = globals()[name]
                continue
            if shared is not None and name in SPECIALIZED and name != "k_bodies":
                out[name] = getattr(shared, name)
                continue
            py = getattr(_stages, name).py_func
            glb = dict(py.__globals__)
            glb.update(consts)
            glb.update(pair_forces=c.pair_forces, sphere_forces=c.sphere_forces,
                       body_patches=c.body_patches,
                       body_update=body_update)
            if glue:
                glb.update(bond_forces=g.bond_forces, bond_contacts=g.bond_contacts,
                           body_glue_sum=g.body_glue_sum)
            fn = types.FunctionType(py.__code__, glb, py.__name__, py.__defaults__,
                                    py.__closure__)
            fn.__qualname__ = f"{name}__{variant_tag(flags)}" + \
                ("" if law == "linear" else f"_{law}") + ("_glue" if glue else "")
            fn.__doc__ = py.__doc__
            out[name] = cuda.jit(fn)
        _VARIANTS[key] = types.SimpleNamespace(**out)
    return _VARIANTS[key]


def _blocks(n: int, threads: int) -> int:
    return max(1, (int(n) + threads - 1) // threads)


def _table_blocks(n: int) -> int:
    return min(_blocks(n, THREADS), TABLE_BLOCKS)


def _scan_levels(n: int) -> list[int]:
    """Lengths of the arrays of a multi-level scan of ``n`` elements."""
    sizes = [int(n)]
    while sizes[-1] > SCAN_CHUNK:
        sizes.append(_blocks(sizes[-1], SCAN_CHUNK))
    sizes.append(1)              # the last level's single block total (unused)
    return sizes


def scan_buffers(n: int):
    """(sizes, sums): level sizes and the device arrays of block totals for ``device_scan``."""
    sizes = _scan_levels(n)
    return sizes, [cuda.to_device(np.zeros(m, dtype=np.int64)) for m in sizes[1:]]


_ALWAYS = []


def _always():
    """A control array that says "rebuild": for a scan outside the step sequence."""
    if not _ALWAYS:
        a = np.zeros(CTL_SIZE, dtype=np.int32)
        a[CTL_FORCE] = 1
        _ALWAYS.append(cuda.to_device(a))
    return _ALWAYS[0]


def device_scan(data, sizes, sums, level: int = 0, ctl=None) -> None:
    """Inclusive prefix sum of the int64 device array ``data`` in place: each
    chunk is scanned, the chunks' totals are scanned (recursively), then added
    back. A fixed sequence of launches for a given size. With ``ctl`` (the
    backend's control array) the launches do nothing unless the step rebuilds."""
    if ctl is None:
        ctl = _always()
    n = sizes[level]
    k_scan_blocks[_blocks(n, SCAN_CHUNK), SCAN_B](data, sums[level], ctl)
    if n > SCAN_CHUNK:
        device_scan(sums[level], sizes, sums, level + 1, ctl)
        k_scan_add[_table_blocks(n), THREADS](data, sums[level], ctl)


def scratch_layout(model, friction=None) -> dict:
    """name -> (shape, dtype) of every device array a CudaBackend allocates."""
    nb = int(model.body_mass.shape[0])
    ns = model.n_spheres
    nw = model.n_walls
    nm = int(model.pair_k.shape[0])
    table = int(grid_table(ns)[5])       # the budget: the most a fitted grid may use
    f8, i8, i4 = np.float64, np.int64, np.int32
    lay = {
        # Model
        "sphere_body": ((ns,), i4), "sphere_offset": ((ns, 3), f8),
        "body_sphere_start": ((nb + 1,), i4), "body_mass": ((nb,), f8),
        "body_inv_mass": ((nb,), f8), "body_inv_inertia": ((nb, 6), f8),
        "body_material": ((nb,), i4), "pair_k": ((nm, nm), f8),
        "pair_damp": ((nm, nm, DAMP_TERMS), f8),
        "pair_mu": ((nm, nm), f8), "pair_rolling": ((nm, nm), f8),
        "body_inv_radius": ((nb,), f8),
        "sphere_inscribed": (model.sphere_inscribed.shape, f8),
        "wall_normal": ((nw, 3), f8), "wall_offset": ((nw,), f8),
        "wall_lo": ((nw, 3), f8), "wall_hi": ((nw, 3), f8), "wall_depth": ((nw,), f8),
        "wall_material": ((nw,), i4), "gravity": ((3,), f8), "grid": ((6,), i8),
        # State
        "body_x": ((nb, 3), f8), "body_q": ((nb, 4), f8), "body_P": ((nb, 3), f8),
        "body_L": ((nb, 3), f8),
        # scratch
        "body_v": ((nb, 3), f8), "body_w": ((nb, 3), f8),
        "sphere_x": ((ns, 3), f8), "sphere_v": ((ns, 3), f8), "sphere_r": ((ns, 3), f8),
        "sphere_key": ((ns,), i8), "sphere_hash": ((ns,), i8),
        "bucket_start": ((table + 1,), i8), "bucket_fill": ((table,), i8),
        "sorted_idx": ((ns,), i4), "slot_of": ((ns,), i4),
        "sorted_x": ((ns, 3), f8), "sorted_v": ((ns, 3), f8),
        "sorted_key": ((ns,), i8), "sorted_body": ((ns,), i4),
        # neighbour lists (NEIGHBOURS entries to start with; CudaBackend.grow_neighbours)
        "built_x": ((ns, 3), f8), "nbr": ((ns, NEIGHBOURS), i4), "nbr_n": ((ns,), i4),
        # each contact computed once (kernels/contacts.py): a row of pair_f per list entry
        "pidx": ((ns, NEIGHBOURS), i4), "pair_f": ((ns * NEIGHBOURS, PAIR_COLS), f8),
        "wall_mask": ((ns,), i8), "wall_f": ((ns, 10), f8),
        "ctl": ((CTL_SIZE,), i4),
        "sphere_f": ((ns, 3), f8), "sphere_t": ((ns, 3), f8), "sphere_overlap": ((ns,), f8),
        "sphere_tr": ((ns, 3), f8),
        # each body's contacts this step per partner (kernels/patches.py)
        "body_patch": ((nb, BODY_PATCHES + 1, 3), f8),
        "max_out": ((1,), f8),
    }
    # contact histories (static friction) live only on the device, and only with friction
    if friction is None:
        friction = model.features.friction
    slots = CONTACT_SLOTS if friction else 1
    nh = ns if friction else 1
    lay["contact_partner"] = ((nh, slots), i4)
    lay["contact_spring"] = ((nh, slots, 3), f8)
    lay["body_rest"] = ((nb,), i4)
    lay["body_wake"] = ((nb,), i4)
    lay["body_still"] = ((nb,), i4)     # written by the shared body stage (the CPU reads it)
    # the prescribed inputs (control.Drive): what the scene's motions and emitters need
    for name, a in drive(model)._asdict().items():
        if name != "moving_walls":
            lay[name] = (a.shape, a.dtype)
    for lvl, n in enumerate(_scan_levels(table + 1)[1:]):
        lay[f"scan_{lvl + 1}"] = ((n,), i8)
    if model.n_bonds:
        # the bonds (layout.GlueModel: the Model's), the State's bond_broken and
        # bond_shear, and what the glue passes write (layout.GlueScratch)
        for name, a in glue_model(model)._asdict().items():
            lay[name] = (a.shape, a.dtype)
        n_pairs = int(model.bonds.n_pairs)
        lay["bond_broken"] = ((int(model.n_bonds),), i4)
        lay["bond_shear"] = ((n_pairs, 3), f8)
        lay["glue_f"] = ((n_pairs, 9), f8)
        lay["body_glue"] = ((nb, 6), f8)
    return lay


def memory_needed(model, friction=None) -> int:
    """Bytes of device memory a CudaBackend for ``model`` allocates (all its arrays,
    the neighbour lists at their initial NEIGHBOURS entries per sphere; a scene
    whose lists overflow grows them, see CudaBackend.grow_neighbours)."""
    return layout_bytes(scratch_layout(model, friction))


#: Left free for the CUDA context, kernels' code and local memory.
MEMORY_MARGIN = 256 * 2**20


def check_memory(needed: int, free: float, total: float | None = None) -> None:
    """Raise DeviceError when ``needed`` bytes do not fit into ``free`` (less a margin)."""
    if needed + MEMORY_MARGIN > free:
        of = f" of {total / 2**30:.1f} GiB" if total and math.isfinite(total) else ""
        raise DeviceError(
            f"scene needs {needed / 2**30:.2f} GiB of GPU memory (+{MEMORY_MARGIN / 2**20:.0f} "
            f"MiB working margin) but only {free / 2**30:.2f} GiB{of} is free: use fewer "
            f"bodies or larger spheres (lower simulation.resolution), or --device cpu")


class CudaBackend:
    """Owns the device arrays of one Model and advances States on the GPU.

    The interface of ``kernels.cpu.backend.CpuBackend``. The State being stepped is
    resident on the device; it is uploaded when ``step``/``velocities``/``probe``
    see a State (or state arrays) other than the resident one, and its
    body_x, body_q, body_P, body_L are copied back into the host arrays at the
    end of every ``step`` call. Changing the host arrays in place between calls
    is not seen: call ``upload(state)`` after doing that.
    """

    name = "cuda"

    def __init__(self, model, features=None, specialize: bool | None = None):
        # As CpuBackend: the contact and body kernels compiled for the features the
        # scene uses (``kernels(flags)``), or with specialize=False the general ones.
        self.model = model
        #: Whether the scene has glue bonds: the glue passes run (GLUE_KERNELS).
        self.glue = model.n_bonds > 0
        self.features = scene_features(model, features)
        self.flags = run_flags(self.features, specialize)
        self.k = kernels(self.flags, model.contact_law, glue=self.glue)
        layout = scratch_layout(model, self.features.friction)
        ctx = cuda.current_context()
        free, total = ctx.get_memory_info()
        check_memory(layout_bytes(layout), free, total)
        self.grid = grid_table(model.n_spheres)
        self.static_box = static_extent(model)
        self.table = layout["bucket_fill"][0][0]
        self.scan_sizes = _scan_levels(self.table + 1)
        d = {}
        model_fields = ("sphere_body", "sphere_offset", "body_sphere_start", "body_mass",
                        "body_inv_mass", "body_inv_inertia", "body_material", "pair_k",
                        "pair_damp", "pair_mu", "pair_rolling", "body_inv_radius",
                        "sphere_inscribed", "wall_normal", "wall_offset", "wall_lo",
                        "wall_hi", "wall_depth", "wall_material", "gravity")
        for name in model_fields:
            shape, dt = layout[name]
            a = np.ascontiguousarray(getattr(model, name), dtype=dt).reshape(shape)
            d[name] = cuda.to_device(a)
        d["grid"] = cuda.to_device(self.grid)
        if self.glue:                   # the bonds (layout.GlueModel), as the CPU's
            for name, a in glue_model(model)._asdict().items():
                d[name] = cuda.to_device(np.ascontiguousarray(a))
        # the prescribed inputs (control.Drive, as the CPU's)
        self.drive = drive(model)
        self._starts = np.unique(self.drive.body_start[self.drive.body_start > 0])
        for name, a in self.drive._asdict().items():
            if name != "moving_walls":
                d[name] = cuda.to_device(np.ascontiguousarray(a))
        for name, (shape, dt) in layout.items():
            if name not in d:
                d[name] = cuda.to_device(np.zeros(shape, dtype=dt))
        self.d = d
        self.scan_sums = [d[f"scan_{lvl + 1}"] for lvl in range(len(self.scan_sizes) - 1)]
        self._resident = None            # (state, body_x, body_q, body_P, body_L) on device
        self.rebuilds = 0                # neighbour-list rebuilds done (all calls)
        self.redos = 0                   # relaunches after a list overflow
        self.steps_skipped = 0           # steps that were no-ops: every body asleep
        #: Whether a call with every body asleep and nothing moving skips its steps
        #: outright (backend.nothing_moves); False: the kernels find it (the same State).
        self.skip_idle = True

    # -- state residency -------------------------------------------------------
    def upload(self, state) -> None:
        """Copy ``state``'s body arrays to the device and make it the resident State."""
        for name in ("body_x", "body_q", "body_P", "body_L"):
            self.d[name].copy_to_device(np.ascontiguousarray(getattr(state, name),
                                                             dtype=np.float64))
        if self.features.friction:
            state.ensure_contacts(self.model.n_spheres)
            self.d["contact_partner"].copy_to_device(state.contact_partner)
            self.d["contact_spring"].copy_to_device(state.contact_spring)
        state.ensure_rest(int(self.model.body_mass.shape[0]))
        self.d["body_rest"].copy_to_device(state.body_rest)
        if self.glue:
            for name in ("bond_broken", "bond_shear"):
                self.d[name].copy_to_device(np.ascontiguousarray(getattr(state, name)))
        self.d["body_wake"].copy_to_device(np.zeros_like(state.body_rest))
        self._resident = (state, state.body_x, state.body_q, state.body_P, state.body_L)

    def _ensure_resident(self, state) -> None:
        r = self._resident
        if (r is None or r[0] is not state or r[1] is not state.body_x
                or r[2] is not state.body_q or r[3] is not state.body_P
                or r[4] is not state.body_L):
            self.upload(state)

    def download(self, state, contacts: bool = False) -> None:
        """Copy the device body arrays into ``state``'s host arrays, and the bonds'
        state (bond_broken, bond_shear: the Simulator counts the broken bonds of
        each frame).

        The contact histories (S x 12 slots, the largest arrays) stay on the
        device between calls; ``contacts=True`` copies them back too, for a
        checkpoint or a comparison."""
        names = ["body_x", "body_q", "body_P", "body_L", "body_rest"]
        if self.glue:
            names += ["bond_broken", "bond_shear"]
        if contacts and self.features.friction:
            names += ["contact_partner", "contact_spring"]
        for name in names:
            host = getattr(state, name)
            if host.flags.c_contiguous and host.dtype == self.d[name].dtype:
                self.d[name].copy_to_host(host)
            else:
                host[...] = self.d[name].copy_to_host()

    def fit(self, state) -> None:
        """Fit the grid to where the bodies are (once per ``step`` call, as on the CPU):
        host arithmetic on the host State, then a 48-byte upload."""
        self.grid = fit_grid(self.model, state.body_x, self.static_box)
        self.d["grid"].copy_to_device(self.grid)

    # -- launches ----------------------------------------------------------------
    def _begin_call(self, first_step: int = 0):
        """Arm the control array for a call: rebuild at its first step."""
        k_begin_call[1, 1](self.d["ctl"], int(first_step))

    def _drive(self, t: float = -1.0):
        """The prescribed motions at the step being run (t < 0) or at time t [s], and
        the carried bodies where they put them (nothing when there are none)."""
        d = self.d
        n_m = int(self.drive.motion_now.shape[0])
        if n_m == 0:
            return
        k_motion[_blocks(n_m, THREADS), THREADS](
            float(t), self.model.dt, d["motion_kind"], d["motion_v"], d["motion_w"],
            d["motion_pivot"], d["key_start"], d["key_t"], d["key_p"], d["key_q"],
            d["motion_now"], d["ctl"])
        n_k = int(self.drive.driven_body.shape[0])
        if n_k:
            k_driven[_blocks(n_k, THREADS), THREADS](
                d["driven_body"], d["body_motion"], d["body_anchor_c"], d["body_anchor_q"],
                d["motion_now"], d["body_x"], d["body_q"], d["body_v"], d["body_w"],
                d["body_rest"], d["body_still"], self.model.dt if t < 0.0 else 0.0)

    def _idle_check(self):
        # a moving wall may wake a sleeper: no step is idle while one moves
        k_idle_check[1, 1](self.d["ctl"], self.model.sleep_steps
                           if int(self.drive.moving_walls) == 0 else 0)

    def _velocities(self):
        m, d = self.model, self.d
        k_body_velocities[_blocks(m.n_bodies, THREADS), THREADS](
            m.n_bodies, d["body_P"], d["body_L"], d["body_q"], d["body_inv_mass"],
            d["body_inv_inertia"], d["body_v"], d["body_w"])

    def _spheres_sorted(self):
        """Stage 1 into the sorted slots of the last build and the count of spheres
        that moved SKIN/2 d since (nothing at a call's first step)."""
        m, d = self.model, self.d
        half_skin = 0.5 * SKIN * m.diameter
        k_spheres_sorted[_blocks(m.n_spheres, THREADS), THREADS](
            d["sorted_idx"], d["sphere_body"], d["sphere_offset"], d["body_x"], d["body_q"],
            d["body_v"], d["body_w"], m.dt, d["built_x"], half_skin * half_skin, d["sorted_x"],
            d["sorted_v"], d["sphere_r"], d["ctl"])

    def _spheres(self):
        """Rebuild: stage 1 in sphere order and each sphere's cell; also counts the
        spheres per bucket."""
        m, d = self.model, self.d
        k_zero_buckets[_table_blocks(self.table + 1), THREADS](d["bucket_start"],
                                                              d["bucket_fill"], d["ctl"])
        k_spheres[_blocks(m.n_spheres, THREADS), THREADS](
            d["sphere_body"], d["sphere_offset"], d["body_x"], d["body_q"], d["body_v"],
            d["body_w"], m.dt, 1.0 / cell_size(m.diameter), d["grid"], d["sphere_x"],
            d["sphere_v"],
            d["sphere_r"], d["sphere_key"], d["sphere_hash"], d["bucket_start"], d["ctl"])

    def _grid_sort(self):
        """Rebuild, stage 2: scan of the counts, scatter, sort of each bucket by
        sphere index."""
        d = self.d
        ns = self.model.n_spheres
        self._scan(d["bucket_start"], 0)
        k_scatter[_blocks(ns, THREADS), THREADS](d["sphere_hash"], d["bucket_start"],
                                                 d["bucket_fill"], d["sorted_idx"], d["ctl"])
        k_bucket_sort[_table_blocks(self.table), THREADS](d["bucket_start"], d["sorted_idx"],
                                                          d["ctl"])

    def _gather(self):
        d = self.d
        k_gather[_blocks(self.model.n_spheres, THREADS), THREADS](
            d["sorted_idx"], d["sphere_x"], d["sphere_v"], d["sphere_key"], d["sphere_body"],
            d["sorted_x"], d["sorted_v"], d["sorted_key"], d["sorted_body"], d["slot_of"],
            d["ctl"])

    def _neighbours(self):
        """Rebuild, stages 2-3: every sorted slot's neighbour list."""
        m, d = self.model, self.d
        cutoff = cell_size(m.diameter)          # (1 + SKIN) d: the lists' reach
        k_neighbours[_blocks(m.n_spheres, THREADS), THREADS](
            cutoff * cutoff, 1.0 / cutoff, d["grid"], d["bucket_start"], d["sorted_idx"],
            d["sorted_x"], d["sorted_key"], d["sorted_body"], d["body_inv_mass"],
            d["built_x"], d["nbr"], d["nbr_n"], d["body_start"], d["ctl"])

    def _save_pairs(self, at_end: bool = False):
        """With friction, before a rebuild's re-sort (or ``at_end`` of a call): the
        pairs' stretches back into the history rows (k_save_pairs)."""
        m, d = self.model, self.d
        k_save_pairs[_blocks(m.n_spheres, THREADS), THREADS](
            at_end, bool(self.features.friction), d["nbr"], d["nbr_n"], d["pidx"],
            d["sorted_idx"], d["contact_partner"], d["contact_spring"], d["pair_f"], d["ctl"])

    def _pairs(self, partner=None, spring=None):
        """Rebuild: pair indices, walls in reach, the pairs' stretches from the rows."""
        m, d = self.model, self.d
        blocks = _blocks(m.n_spheres, THREADS)
        k_pair_slots[blocks, THREADS](d["nbr"], d["nbr_n"], d["sorted_idx"], d["sorted_body"],
                                      d["body_inv_mass"], d["pidx"], d["ctl"])
        k_pair_mirror[blocks, THREADS](
            0.5 * m.diameter, WALL_SLACK * 0.5 * SKIN * m.diameter,
            d["nbr"], d["nbr_n"],
            d["sorted_idx"], d["sorted_x"], d["sorted_body"], d["body_inv_mass"],
            d["wall_normal"], d["wall_offset"], d["wall_lo"], d["wall_hi"], d["wall_depth"],
            d["wall_motion"], d["body_start"], d["sphere_inscribed"], d["wall_mask"],
            d["pidx"], d["ctl"])
        k_load_pairs[blocks, THREADS](
            bool(self.features.friction), d["nbr"], d["nbr_n"], d["pidx"], d["sorted_idx"],
            d["sorted_body"], d["body_inv_mass"], d["wall_mask"],
            d["contact_partner"] if partner is None else partner,
            d["contact_spring"] if spring is None else spring, d["pair_f"], d["ctl"])

    def _scan(self, data, level):
        device_scan(data, self.scan_sizes, self.scan_sums, level, self.d["ctl"])

    def _contacts(self, parity: int = 0, partner=None, spring=None, wake=None,
                  bonds: bool = True):
        """Stage 4: the contact patches, the contact passes and, between them, the
        glue passes 1-2 of a scene with bonds (unless ``bonds`` is False: the
        probe's contacts move nothing, bonds included)."""
        m, d = self.model, self.d
        cm = contact_model(m, self.features.friction, d["wall_motion"], arrays=d)
        # the CPU's packed rows (PAIR_ROWS, WALL_ROWS, LIST_ROWS are off here): stand-ins
        # of the same array kinds, unread, so that the kernels type either way
        cs = ContactScratch(
            nbr=d["nbr"], nbr_n=d["nbr_n"], pidx=d["pidx"], pair_start=d["nbr_n"],
            pair_e=d["nbr_n"], wall_start=d["nbr_n"], wall_s=d["pair_f"],
            list_start=d["nbr_n"], list_e=d["nbr"], sorted_idx=d["sorted_idx"],
            sorted_x=d["sorted_x"], sorted_v=d["sorted_v"], sorted_body=d["sorted_body"],
            body_w=d["body_w"], body_rest=d["body_rest"],
            body_wake=d["body_wake"] if wake is None else wake, wall_mask=d["wall_mask"],
            hist_partner=d["contact_partner"] if partner is None else partner,
            hist_spring=d["contact_spring"] if spring is None else spring,
            pair_f=d["pair_f"], wall_f=d["wall_f"], sphere_f=d["sphere_f"],
            sphere_t=d["sphere_t"], sphere_tr=d["sphere_tr"],
            sphere_overlap=d["sphere_overlap"], body_patch=d["body_patch"], body_q=d["body_q"],
            slot_touch=d["nbr_n"], sphere_engaged=d["nbr_n"])
        self.k.k_body_patches[_blocks(d["body_patch"].shape[0], THREADS), THREADS](
            cm, cs, d["motion_now"], d["body_sphere_start"], d["slot_of"], d["ctl"])
        self.k.k_pair_forces[_blocks(m.n_spheres, CONTACT_THREADS), CONTACT_THREADS](
            cm, cs, d["motion_now"], parity, d["ctl"])
        if self.glue and bonds:
            gm, gs = self._glue_args()
            n = int(m.n_bonds)
            self.k.k_bond_forces[_blocks(n, THREADS), THREADS](
                gm, gs, d["sphere_body"], d["slot_of"], d["sorted_x"], d["sorted_v"],
                d["body_w"], d["body_inv_mass"], d["body_rest"], d["body_wake"],
                int(m.sleep_steps), float(m.dt), d["ctl"])
            self.k.k_bond_contacts[_blocks(n, THREADS), THREADS](
                gm, gs, d["slot_of"], d["sorted_body"], d["body_inv_mass"], d["nbr"],
                d["nbr_n"], d["pidx"], d["pair_f"], d["ctl"])
        self.k.k_sphere_forces[_blocks(m.n_spheres, THREADS), THREADS](cm, cs, d["ctl"])

    def _glue_args(self):
        """(layout.GlueModel, GlueScratch) of the device's bonds."""
        d = self.d
        return (GlueModel(*(d[n] for n in GlueModel._fields)),
                GlueScratch(*(d[n] for n in GlueScratch._fields)))

    def _bodies(self):
        """Stages 5-8 (k_bodies), after glue pass 3 (k_body_glue) in a scene with bonds."""
        m, d = self.model, self.d
        if self.glue:
            gm, gs = self._glue_args()
            self.k.k_body_glue[_blocks(m.n_bodies, THREADS), THREADS](
                m.n_bodies, gm, gs, d["sphere_body"], d["sphere_r"], d["ctl"])
            body_glue = d["body_glue"]
        else:
            body_glue = d["wall_f"]     # GLUE off: a stand-in, unread
        bs = BodyScratch(*(d[n] for n in BodyScratch._fields[:-2]), body_glue=body_glue,
                         sphere_engaged=d["nbr_n"])
        self.k.k_bodies[_blocks(m.n_bodies, THREADS), THREADS](
            m.n_bodies, body_model(m, d["body_start"], self.features.friction, arrays=d), bs,
            d["ctl"])

    def _unsort(self):
        d = self.d
        k_unsort[_blocks(self.model.n_spheres, THREADS), THREADS](
            d["sorted_idx"], d["sorted_x"], d["sphere_x"])

    #: The launch groups of one step, in order (benchmarks time each; each takes
    #: no argument).
    STAGES = ("_idle_check", "_velocities", "_spheres_sorted", "_save_pairs", "_spheres",
              "_grid_sort", "_gather", "_neighbours", "_pairs", "_contacts", "_bodies")

    def step_once(self, parity: int = 0) -> None:
        """One step of the eight stages on the resident State: a fixed sequence of
        launches with fixed sizes and arguments, no host synchronisation (so the
        sequences of an even and an odd step can be captured once into a CUDA
        graph and replayed). ``parity``: the step number's lowest bit, which the
        contact histories use to tell contacts that ended.

        Launch sequence (ctl: the device control array, CTL_*):

        0. k_idle_check (one thread): with sleeping on and no body awake after
           the last step (ctl[CTL_AWAKE] == 0), set ctl[CTL_IDLE]: this and the
           call's remaining steps are no-ops (k_spheres_sorted, the contact kernels and
           k_bodies return at once; the rebuild kernels have nothing to do);
           then zero ctl[CTL_AWAKE] for this step's body stage to count into.
        1. k_body_velocities: V, W of each body.
        2. k_spheres_sorted: unless ctl[CTL_FORCE] (a call's first step), stage 1
           straight into the sorted slots of the last build, and
           ctl[CTL_MOVED] += 1 (integer atomic) per sphere that moved SKIN/2 d
           or more since that build.
        3. The rebuild, each kernel returning at once unless ctl[CTL_FORCE] or
           ctl[CTL_MOVED] is set (both are stable while they run):
           k_save_pairs (with friction, not at a call's first step: the pairs'
           stretches back into the history rows while the old lists stand),
           k_zero_buckets, k_spheres (stage 1 in sphere order, cells, bucket
           counts), k_scan_blocks / k_scan_add (one or more levels), k_scatter,
           k_bucket_sort, k_gather, k_neighbours (the lists, built_x; an
           overflow adds to ctl[CTL_OVER] and maxes ctl[CTL_MAXN]); then, unless
           a list overflowed, k_pair_slots, k_pair_mirror (pair indices, walls
           in reach) and k_load_pairs (the stretches from the rows).
        4. k_body_patches (each body's contacts per partner: the share each pair
           takes, kernels/patches.py), k_pair_forces (each contact once, by its
           owner, and the walls), with glue bonds k_bond_forces (each bond's
           pairs, shear and break) and k_bond_contacts (a holding bond's pairs'
           contact rows zeroed), then k_sphere_forces (each sphere's sum), all
           returning at once once ctl[CTL_OVER] is set: the host carries on from
           there.
        5. with glue bonds k_body_glue (each body's bonds summed), then k_bodies: stages 5-8 (nothing once ctl[CTL_OVER] or ctl[CTL_IDLE] is
           set), each body awake for the next step adding 1 to ctl[CTL_AWAKE];
           its thread 0 counts the rebuild (ctl[CTL_REBUILDS]), the step done
           (ctl[CTL_DONE], unless overflowed) and an idle one
           (ctl[CTL_IDLE_STEPS]) and clears ctl[CTL_FORCE] and ctl[CTL_MOVED]
           for the next step.

        ``step`` arms ctl (k_begin_call) before a call's first step.
        """
        self._idle_check()
        self._velocities()
        self._drive()
        self._spheres_sorted()
        self._save_pairs()
        self._spheres()
        self._grid_sort()
        self._gather()
        self._neighbours()
        self._pairs()
        self._contacts(parity)
        self._bodies()

    def grow_neighbours(self, need: int) -> None:
        """Room for ``need`` partners per sphere (the longest list an overflowing
        build found), doubling the capacity at least: a pile that grows denser
        rarely needs a second growth. The lists' contents are not kept (the
        steps that follow start with a rebuild)."""
        ns = self.model.n_spheres
        old = int(self.d["nbr"].shape[1])
        cap = max(old, 1)
        while cap < need:
            cap *= 2
        if cap == old:
            return
        free, total = cuda.current_context().get_memory_info()
        check_memory(ns * (cap - old) * (8 + 8 * PAIR_COLS), free, total)
        for name in ("nbr", "pidx", "pair_f"):
            del self.d[name]
        self.d["nbr"] = cuda.to_device(np.zeros((ns, cap), dtype=np.int32))
        self.d["pidx"] = cuda.to_device(np.zeros((ns, cap), dtype=np.int32))
        self.d["pair_f"] = cuda.to_device(np.zeros((ns * cap, PAIR_COLS)))

    # -- CpuBackend interface ----------------------------------------------------
    def step(self, state, n_steps: int, control=None) -> None:
        """Advance ``state`` by ``n_steps`` steps; its host arrays are updated at the end.
        ``control``: as ``CpuBackend.step`` (the controlled poses uploaded first).

        The steps are launched back to back; the control array is read once at
        the end. If a neighbour list overflowed, the State stopped changing at
        that step (CTL_DONE counts the steps before it): the lists are grown and
        the remaining steps launched again from there. Nothing is copied aside.
        """
        self._ensure_resident(state)
        prescribed = control is not None and not control.empty
        if prescribed:
            control.apply(state)
            for name in ("body_x", "body_q"):
                self.d[name].copy_to_device(np.ascontiguousarray(getattr(state, name)))
        # an emitter's start step begins a call (whose first step rebuilds the lists)
        for n in split_at(int(state.step), int(n_steps), self._starts):
            # (the host's rest counts are the resident State's: download after each call)
            if skip_idle_call(self, state, n, prescribed):
                continue
            self._advance(state, n)

    def _advance(self, state, n_steps: int) -> None:
        self.fit(state)
        left = int(n_steps)
        stepped = False
        while left > 0:
            self._begin_call(state.step)
            for step in range(state.step, state.step + left):
                self.step_once(step & 1)
            ctl = self.d["ctl"].copy_to_host()
            done = int(ctl[CTL_DONE])
            self.rebuilds += int(ctl[CTL_REBUILDS])
            self.steps_skipped += int(ctl[CTL_IDLE_STEPS])
            state.step += done
            left -= done
            stepped = stepped or done > 0
            if ctl[CTL_OVER] != 0:
                # the stretches went back into the rows before the overflowing build
                self.redos += 1
                self.grow_neighbours(int(ctl[CTL_MAXN]))   # room (may raise DeviceError)
            elif done > 0:
                self._save_pairs(at_end=True)
        if stepped:
            self._unsort()
        self._drive(state.step * self.model.dt)    # the carried bodies at the State's time
        self.download(state)
        state.time = state.step * self.model.dt

    def probe(self, state) -> None:
        """Stages 1-4 without moving anything: fills sphere_f, sphere_overlap.

        Builds the neighbour lists (growing them until they fit), then the
        contact stage on copies of the contact histories: reads them but does
        not change the resident State's."""
        self._ensure_resident(state)
        self.fit(state)
        self._velocities()
        self._drive(state.step * self.model.dt)
        while True:
            # ctl[CTL_STEP] is the step being run: no k_idle_check counts it in here
            self._begin_call(state.step + 1)
            self._spheres()
            self._grid_sort()
            self._gather()
            self._neighbours()
            ctl = self.d["ctl"].copy_to_host()
            if ctl[CTL_OVER] == 0:
                break
            self.grow_neighbours(int(ctl[CTL_MAXN]))
        d = self.d
        k_fill[_blocks(self.model.n_spheres, THREADS), THREADS](d["sphere_overlap"], 0.0)
        copies = {}
        for name in ("contact_partner", "contact_spring", "body_wake"):
            copies[name] = cuda.device_array_like(d[name])
            copies[name].copy_to_device(d[name])          # device to device
        self._pairs(copies["contact_partner"], copies["contact_spring"])
        self._contacts(state.step & 1, copies["contact_partner"], copies["contact_spring"],
                       copies["body_wake"], bonds=False)

    def velocities(self, state):
        """(V, W) of the dynamic bodies for ``state`` [m/s], [rad/s], world frame."""
        self._ensure_resident(state)
        self._velocities()
        self._drive(state.step * self.model.dt)
        nb = self.model.n_bodies
        return (self.d["body_v"].copy_to_host()[:nb].copy(),
                self.d["body_w"].copy_to_host()[:nb].copy())

    def take_max_overlap(self) -> float:
        """Largest overlap since the last call [m], then reset."""
        if self.model.n_spheres == 0:
            return 0.0
        d = self.d
        k_fill[1, 1](d["max_out"], 0.0)
        blocks = min(_blocks(self.model.n_spheres, THREADS), 1024)
        k_take_max[blocks, THREADS](d["sphere_overlap"], d["max_out"])
        return float(d["max_out"].copy_to_host()[0])

    def save_arrays(self, state, names) -> dict:
        """Host copies of the device arrays ``names`` (Backend.save_arrays), after
        copying the State and its contact histories back into ``state``."""
        self.download(state, contacts=True)
        return {n: self.host(n) for n in names if n in self.d}

    def load_arrays(self, state, arrays: dict) -> None:
        """Copy ``arrays`` into the host arrays of the same names and shapes, then make
        ``state`` the resident State (Backend.load_arrays)."""
        copy_matching(self, arrays)
        self.upload(state)

    # -- host copies of scratch (tests, diagnostics) -----------------------------
    def host(self, name: str) -> np.ndarray:
        """A host copy of the device array ``name`` (see ``scratch_layout``)."""
        return self.d[name].copy_to_host()

    sphere_x = property(lambda self: self.host("sphere_x"))
    sphere_f = property(lambda self: self.host("sphere_f"))
    sphere_t = property(lambda self: self.host("sphere_t"))
    sphere_r = property(lambda self: self.host("sphere_r"))
    sphere_overlap = property(lambda self: self.host("sphere_overlap"))
    sorted_idx = property(lambda self: self.host("sorted_idx"))
    nbr = property(lambda self: self.host("nbr"))
    nbr_n = property(lambda self: self.host("nbr_n"))
    built_x = property(lambda self: self.host("built_x"))
    bucket_start = property(lambda self: self.host("bucket_start"))
