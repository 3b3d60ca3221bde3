"""The CUDA target against the CPU target.

Two kinds of tests:

* Simulator parity (every machine). numba's CUDA simulator
  (``NUMBA_ENABLE_CUDASIM=1``) must be switched on before ``numba.cuda`` is first
  imported, so these checks run in one subprocess (this file run as a script,
  ``python tests/sim/test_cuda.py --sim``) that prints its measurements as JSON; the
  tests below assert on them. The pytest process itself never imports
  ``numba.cuda``. The simulator runs each CUDA thread as a Python thread, so the
  scenes are tiny and the runs short.
* ``@pytest.mark.gpu`` tests: only when a real GPU is present (probed in a
  subprocess without the simulator); parity on thousands of bodies and the
  physics tests of the core on ``Simulator(model, device="cuda")``.

Tolerances. The kernels evaluate the same physics.py formulas in the same
order of summation as the CPU, in float64. The simulator executes the very
same IEEE operations in Python (no FMA, the same libm), so it is bit-identical
to the CPU: asserted separately from the 1e-9 relative tolerance the parity
tests use, which is what a real GPU must meet after one step (its FMA
contraction changes the last bits of a product-sum; see docs/cuda.md).
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cudasim import cuda_env, simulator_results

from dempipe.sim.kernels.layout import grid_table
from dempipe.spheres.inscribed import COVERED

# the simulator runs every thread of a launch in Python: minutes, so not in the fast tier
pytestmark = pytest.mark.slow

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent
ROOT = TESTS.parent
D = 0.01
#: Relative agreement of CPU and CUDA state (of the largest entry of each array).
PARITY_RTOL = 1e-9
#: Steps of the falling-box case in one call (the simulator is slow: keep it short).
FALL_STEPS = 24


# ---------------------------------------------------------------------------
# Scenes (shared by the simulator script and the GPU tests)
# ---------------------------------------------------------------------------

def contact_model(fps=60.0, n_frames=8, seed=0, law="linear"):
    """Six bodies (two box shapes, a ball; two materials) touching each other, a
    box container and a tilted plane at the start: every contact kind in step 1."""
    from bodies import ball_set, box_set
    from dempipe.sim.materials import Material
    from dempipe.sim.builder import ModelBuilder

    rng = np.random.default_rng(seed)
    b = ModelBuilder(D)
    ssa, ma = box_set(2, 2, 1, D)
    ssb, mb = box_set(3, 1, 1, D)
    ssc, mc = ball_set(D)
    shapes = [b.add_shape("a", ma, ssa), b.add_shape("b", mb, ssb), b.add_shape("c", mc, ssc)]
    mats = [b.add_material(Material("m1", density=800, restitution=0.4, friction=0.4)),
            b.add_material(Material("m2", density=2000, restitution=0.7, friction=0.2))]
    pos = [[0, 0, 0.0045], [0.0195, 0, 0.0045], [0.005, 0.0145, 0.0045],
           [0, 0, 0.0140], [0.0195, 0.0095, 0.0045], [0.0295, 0, 0.0140]]
    for i, p in enumerate(pos):
        q = np.array([1.0, 0, 0, 0]) + rng.normal(size=4) * 0.03
        b.add_bodies(f"g{i}", shapes[i % 3], mats[i % 2], [p], rotations=[q / np.linalg.norm(q)],
                     velocities=[rng.normal(size=3) * 0.2],
                     angular_velocities=[rng.normal(size=3) * 3])
    b.add_box([-0.0145, -0.0145, 0], [0.0345, 0.025, 0.1], material=mats[0])
    b.add_plane([0, 0, 0.0005], [0.1, 0, 1], mats[1])
    return b.finalize(fps=fps, n_frames=n_frames, contact_law=law)


def pile_model(n_side=12, layers=4, friction=0.4):
    """n_side² × layers boxes in a container, dropped from just above each other
    (thousands of bodies for the GPU tests)."""
    from bodies import box_set
    from dempipe.sim.materials import Material
    from dempipe.sim.builder import ModelBuilder

    rng = np.random.default_rng(1)
    b = ModelBuilder(D)
    ssa, ma = box_set(2, 2, 1, D)
    ssb, mb = box_set(3, 1, 1, D)
    shapes = [b.add_shape("a", ma, ssa), b.add_shape("b", mb, ssb)]
    mats = [b.add_material(Material("m1", density=800, restitution=0.4, friction=friction)),
            b.add_material(Material("m2", density=2000, restitution=0.7, friction=friction / 2))]
    sp = 0.036
    i = 0
    for z in range(layers):
        for y in range(n_side):
            for x in range(n_side):
                q = rng.normal(size=4)
                b.add_bodies(f"g{i % 2}", shapes[i % 2], mats[i % 2],
                             [[x * sp, y * sp, 0.02 + z * sp]], rotations=[q / np.linalg.norm(q)],
                             velocities=[rng.normal(size=3) * 0.3],
                             angular_velocities=[rng.normal(size=3) * 5])
                i += 1
    ext = n_side * sp
    b.add_box([-0.03, -0.03, 0], [ext + 0.01, ext + 0.01, 1.0], material=mats[0])
    return b.finalize(fps=60, n_frames=4)


def falling_model(v=1.5):
    """A 2×2 box falling (and spinning) onto a 4×4 slab resting on a plane, each of
    its spheres over four of the slab's: no neighbours at the first build, four
    per sphere once within (1 + SKIN) d. Soft (k = 4000 N/m, so a coarse dt): it
    moves SKIN/2 d every few steps and hits the slab after about 16 steps."""
    from bodies import box_set
    from dempipe.sim.materials import Material
    from dempipe.sim.builder import ModelBuilder

    b = ModelBuilder(D)
    ssa, ma = box_set(4, 4, 1, D)
    ssb, mb = box_set(2, 2, 1, D)
    slab, box = b.add_shape("slab", ma, ssa), b.add_shape("box", mb, ssb)
    m1 = b.add_material(Material("m1", density=800, restitution=0.4, friction=0.4,
                                 stiffness=4000.0))
    m2 = b.add_material(Material("m2", density=2000, restitution=0.7, friction=0.2,
                                 stiffness=4000.0))
    b.add_bodies("slab", slab, m1, [[0, 0, 0.5 * D]])
    b.add_bodies("box", box, m2, [[0.5 * D, 0.5 * D, 1.5 * D]], velocities=[[0, 0, -v]],
                 angular_velocities=[[0, 0, 2.0]])
    b.add_plane([0, 0, 0], [0, 0, 1], m1)
    return b.finalize(fps=60, n_frames=2)


def sleepy_model():
    """Two boxes resting on a plane that fall asleep within a few steps (thresholds
    of 1 m/s and 100 rad/s for two steps): the all-asleep shortcut of both targets."""
    from bodies import box_set
    from dempipe.sim.materials import Material
    from dempipe.sim.builder import ModelBuilder

    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 1, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("m", density=800, restitution=0.4, friction=0.4,
                                stiffness=4000.0))
    b.add_bodies("boxes", s, m, [[0, 0, 0.499 * D], [2.0 * D, 0, 0.499 * D]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=60, n_frames=2, sleep=(1.0, 100.0, 1e-9))
    return replace(model, sleep_steps=2)


def prescribed_model():
    """Prescribed motion on both targets: two boxes on a belt (a plane moving along
    itself) inside a pen that slides in (a moving box collider), a kinematic box
    spinning and drifting through them, and a third box emitted on the belt after
    a few steps; sleeping on (a moving surface keeps what it touches awake)."""
    from bodies import box_set
    from dempipe.sim.materials import Material
    from dempipe.sim.builder import ModelBuilder
    from dempipe.sim.motion import Motion

    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 1, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("m", density=800, restitution=0.4, friction=0.4,
                                stiffness=4000.0))
    b.add_bodies("boxes", s, m, [[0, 0, 0.499 * D], [2.0 * D, 0, 0.499 * D]])
    b.add_bodies("spinner", s, m, [[-2.2 * D, 0.0, 0.6 * D]], kinematic=True,
                 motion=Motion(velocity=(0.5, 0.0, 0.0), angular_velocity=(0.0, 0.0, 30.0)))
    b.add_bodies("late", s, m, [[4.0 * D, 0, 0.6 * D]], start_time=0.0)
    b.add_plane([0, 0, 0], [0, 0, 1], m, motion=Motion(velocity=(0.3, 0.0, 0.0)))
    b.add_box([-4 * D, -3 * D, -D], [8 * D, 3 * D, 4 * D], True, m,
              motion=Motion(velocity=(0.4, 0.0, 0.0)))
    model = b.finalize(fps=60, n_frames=2, sleep=(1.0, 100.0, 1e-9))
    # the emitter enters after 3 steps, sleeping after 2 steps at rest
    start = np.array(model.body_start)
    start[3] = 3
    return replace(model, sleep_steps=2, body_start=start)


def _rel(a, b) -> float:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return float(np.abs(a - b).max() / (np.abs(b).max() + 1e-300)) if a.size else 0.0


def inscribed_ball_model():
    """A ball 0.1 m across, a surface set 4 spheres across, rolling on a 20° slope
    (tilted gravity over the plane z = 0) for 3 frames of 8 steps: its shell spheres
    meet the plane through their inscribed balls (spheres/inscribed.py)."""
    from dempipe.mesh.shapes import build_shape
    from dempipe.sim.builder import ModelBuilder
    from dempipe.sim.materials import Material
    from dempipe.spheres.options import BuildOptions
    from dempipe.spheres.sphere_set import build_sphere_set

    d = 0.025
    mesh = build_shape("sphere", diameter=0.1)
    ss = build_sphere_set(mesh, d, name="cuda-ball", options=BuildOptions(mode="surface"))
    th = math.radians(20.0)
    b = ModelBuilder(d, gravity=(9.81 * math.sin(th), 0.0, -9.81 * math.cos(th)))
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("wood", density=700.0, restitution=0.5, friction=0.9,
                                stiffness=2e5))
    low = float(-np.asarray(ss.centers)[:, 2].min()) + 0.5 * d
    b.add_bodies("ball", s, m, [[0.0, 0.0, low - 1e-5]], velocities=[[0.5, 0.0, 0.0]],
                 angular_velocities=[[0.0, 10.0, 0.0]])
    b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    return b.finalize(fps=1.0 / (8 * 5e-5), n_frames=3, dt=5e-5, sleep=None)


def _tipped_model(mesh, d, name, stiffness, speed, mode="lattice"):
    """``mesh`` as a sphere set of diameter ``d`` (``mode``), tipped 30° about x onto the
    plane z = 0 and set moving at ``speed`` along x and turning (wood of ``stiffness``
    [N/m])."""
    from scipy.spatial.transform import Rotation

    from dempipe.sim.builder import ModelBuilder
    from dempipe.sim.materials import Material
    from dempipe.spheres.options import BuildOptions
    from dempipe.spheres.sphere_set import build_sphere_set

    ss = build_sphere_set(mesh, d, name=name, options=BuildOptions(mode=mode))
    b = ModelBuilder(d, gravity=(0.0, 0.0, -9.81))
    s = b.add_shape(name, mesh, ss)
    m = b.add_material(Material("wood", density=700.0, restitution=0.5, friction=0.9,
                                stiffness=stiffness))
    rot = Rotation.from_euler("x", 30.0, degrees=True)
    low = float(-rot.apply(np.asarray(mesh.vertices))[:, 2].min())
    w, x, y, z = np.roll(rot.as_quat(), 1)
    b.add_bodies(name, s, m, [[0.0, 0.0, low - 1e-5]], [[w, x, y, z]],
                 velocities=[[speed, 0.0, 0.0]], angular_velocities=[[0.0, 2.0, 3.0]])
    b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    return b.finalize(fps=1.0 / (8 * 5e-5), n_frames=3, dt=5e-5, sleep=None)


def rim_model():
    """A cylinder 0.1 m across and 0.05 m long, a lattice 8 spheres across, tipped 30°
    onto its rim and set turning: it meets the plane z = 0 through its rim's ring
    (spheres/inscribed.py rims, a tube of radius 0) and the rings of its side."""
    from dempipe.mesh.shapes import build_shape

    return _tipped_model(build_shape("cylinder", diameter=0.1, height=0.05), 0.0125,
                         "cuda-cylinder", 2e5, 0.1)


def band_model():
    """The built-in pawn at 12 spheres to its height, tipped 30° onto its foot's edge and
    set turning: it meets the plane z = 0 through its plinth's band (spheres/inscribed.py
    _bands: a rim's ring swept along its axis) and the rings of its head."""
    from dempipe.mesh.shapes import build_shape

    return _tipped_model(build_shape("pawn"), 0.05 / 12, "cuda-pawn", 2e4, 0.05)


def covered_box_model():
    """A cube 0.1 m across, a surface set 8 spheres across, tipped 30° onto an edge and
    set turning: most spheres of its flat faces meet no wall, their neighbours covering
    them (spheres/inscribed.py wall_cover)."""
    from dempipe.mesh.shapes import build_shape

    return _tipped_model(build_shape("box", size=(0.1, 0.1, 0.1)), 0.0125, "cuda-box",
                         2e5, 0.1, mode="surface")


# ---------------------------------------------------------------------------
# The simulator script (runs in a subprocess with NUMBA_ENABLE_CUDASIM=1)
# ---------------------------------------------------------------------------

def _sim_main() -> dict:
    assert os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
    from numba import cuda

    import dempipe.sim.kernels.cuda.backend as kcu
    from dempipe.sim.kernels.cpu.backend import CpuBackend
    from dempipe.errors import DeviceError
    from dempipe.sim.simulator import Simulator

    out: dict = {}
    BODY = ("body_x", "body_q", "body_P", "body_L")

    # grid_table is repeated in cuda.py: it must be the CPU's function
    cases = [(n, e) for n in (0, 1, 7, 100, 5000, 10**6)
             for e in (None, (3.0, 3.0, 3.0), (1000.0, 2.0, 50.0), (1e7, 1e7, 1e7))]
    out["grid_table_same"] = all(np.array_equal(grid_table(n, e), kcu.grid_table(n, e))
                                 for n, e in cases)

    # prefix sum: default chunk (1-2 levels), and tiny chunks (4 levels) by
    # shrinking the simulator's compile-time constants (read at run time there)
    scan_ok = []
    rng = np.random.default_rng(0)
    for n in (1, 255, 257, 1000):
        a = rng.integers(0, 5, n).astype(np.int64)
        sizes, sums = kcu.scan_buffers(n)
        d = cuda.to_device(a)
        kcu.device_scan(d, sizes, sums)
        scan_ok.append(bool(np.array_equal(d.copy_to_host(), np.cumsum(a))))
    # the host side (kernels/cuda/backend.py) and the scan kernels (kernels/cuda/grid.py) both
    import dempipe.sim.kernels.cuda.grid as kgrid
    names = ("SCAN_B", "SCAN_ITEMS", "SCAN_CHUNK")
    saved = [(m, n, getattr(m, n)) for m in (kcu, kgrid) for n in names if hasattr(m, n)]
    for m, n, _ in saved:
        setattr(m, n, {"SCAN_B": 2, "SCAN_ITEMS": 2, "SCAN_CHUNK": 4}[n])
    try:
        a = rng.integers(0, 5, 150).astype(np.int64)
        sizes, sums = kcu.scan_buffers(150)
        d = cuda.to_device(a)
        kcu.device_scan(d, sizes, sums)
        scan_ok.append(bool(np.array_equal(d.copy_to_host(), np.cumsum(a))))
        out["scan_levels_small_chunk"] = len(sizes) - 1
    finally:
        for m, n, v in saved:
            setattr(m, n, v)
    out["scan_ok"] = scan_ok

    # memory estimate and its error
    model = contact_model()
    # this case runs the kernels specialized to its scene, as a bake does; the others
    # run the general ones (the suite's default, conftest.py): on each target a
    # specialized kernel gives the general one's frames (tests/sim/test_specialize.py)
    be = kcu.CudaBackend(model, specialize=True)
    out["memory_needed"] = kcu.memory_needed(model)
    out["memory_allocated"] = int(sum(a.nbytes for a in be.d.values()))
    try:
        kcu.check_memory(10 * 2**30, 2 * 2**30, 80 * 2**30)
        out["memory_error"] = None
    except DeviceError as exc:
        out["memory_error"] = str(exc)

    # stage by stage: stages 1-4 from the same state
    out["features"] = {"rolling": bool(model.features.rolling),
                       "friction": bool(model.features.friction)}
    st0 = model.initial_state()
    cpu = CpuBackend(model, specialize=True)
    out["flags"] = [list(cpu.flags), list(be.flags)]
    cpu.probe(st0)
    be.probe(st0)
    nb5 = int(cpu.grid[5])
    out["probe"] = {
        "grid_equal": bool(np.array_equal(cpu.grid, be.grid)),
        "bucket_start_equal": bool(np.array_equal(cpu.bucket_start[:nb5 + 1],
                                                  be.bucket_start[:nb5 + 1])),
        # CUDA's slots are the grid; the CPU's are in body order, its grid through grid_slot
        "sorted_idx_equal": bool(np.array_equal(cpu.grid_idx, be.sorted_idx)),
        "max_force": float(np.abs(cpu.sphere_f).max()),
        "max_overlap": float(cpu.sphere_overlap.max() / D),
        "rel": {n: _rel(getattr(be, n), getattr(cpu, n))
                for n in ("sphere_x", "sphere_r", "sphere_f", "sphere_t", "sphere_overlap")},
        "identical": {n: bool(np.array_equal(getattr(be, n), getattr(cpu, n)))
                      for n in ("sphere_x", "sphere_r", "sphere_f", "sphere_t", "sphere_overlap")},
    }

    # one step, then 20 more in calls of 1, 4, 15 steps (residency, grid refits)
    a, b = st0.copy(), st0.copy()
    cpu.step(a, 1)
    be.step(b, 1)
    out["step1"] = {"rel": {n: _rel(getattr(b, n), getattr(a, n)) for n in BODY},
                    "identical": all(np.array_equal(getattr(b, n), getattr(a, n)) for n in BODY)}
    for n_steps in (4, 15):
        cpu.step(a, n_steps)
        be.step(b, n_steps)
    va, wa = cpu.velocities(a)
    vb, wb = be.velocities(b)
    out["step20"] = {"rel": {n: _rel(getattr(b, n), getattr(a, n)) for n in BODY},
                     "rel_v": _rel(vb, va), "rel_w": _rel(wb, wa),
                     "identical": all(np.array_equal(getattr(b, n), getattr(a, n)) for n in BODY),
                     "moved": float(np.abs(a.body_x - st0.body_x).max() / D),
                     "overlap_cpu": cpu.take_max_overlap(), "overlap_cuda": be.take_max_overlap(),
                     "overlap_reset": be.take_max_overlap()}

    # a new State object is uploaded (not the resident one stepped further)
    c, e = st0.copy(), st0.copy()
    cpu.step(c, 2)
    be.step(e, 2)
    out["new_state_identical"] = all(np.array_equal(getattr(e, n), getattr(c, n)) for n in BODY)

    # the Hertz law: its own variant of the contact passes on each target, the same bits
    mh = contact_model(law="hertz")
    c, e = mh.initial_state(), mh.initial_state()
    CpuBackend(mh).step(c, 12)
    kcu.CudaBackend(mh).step(e, 12)
    out["hertz"] = {"identical": all(np.array_equal(getattr(e, n), getattr(c, n)) for n in BODY),
                    "moved": float(np.abs(c.body_x - mh.initial_state().body_x).max() / D)}

    # run to run on the CUDA target (in-bucket sort after the atomic scatter)
    r1, r2 = st0.copy(), st0.copy()
    kcu.CudaBackend(model).step(r1, 6)
    kcu.CudaBackend(model).step(r2, 6)
    out["run_to_run_identical"] = all(np.array_equal(getattr(r1, n), getattr(r2, n))
                                      for n in BODY)

    # neighbour lists that overflow at a call's first step: lists shrunk to one
    # entry; the steps are relaunched with grown lists, bit for bit the CPU's
    def one_entry(backend):
        backend.d["nbr"] = cuda.to_device(np.zeros((backend.model.n_spheres, 1), dtype=np.int32))
        return backend

    g, h = st0.copy(), st0.copy()
    CpuBackend(model).step(g, 3)
    small = one_entry(kcu.CudaBackend(model))
    small.step(h, 3)
    out["overflow_first_step"] = {
        "identical": all(np.array_equal(getattr(h, n), getattr(g, n)) for n in BODY),
        "redos": small.redos, "cap": int(small.d["nbr"].shape[1]),
        "longest": int(small.nbr_n.max()),
        "histories_identical": True,
    }
    if model.features.friction:          # nothing changed from the overflowing step on
        small.download(h, contacts=True)
        out["overflow_first_step"]["histories_identical"] = bool(
            np.array_equal(h.contact_partner, g.contact_partner)
            and np.array_equal(h.contact_spring, g.contact_spring))
    small_probe = one_entry(kcu.CudaBackend(model))
    small_probe.probe(st0)
    cpu_probe = CpuBackend(model)
    cpu_probe.probe(st0)
    out["overflow_probe"] = {
        "identical": all(bool(np.array_equal(getattr(small_probe, n), getattr(cpu_probe, n)))
                         for n in ("sphere_f", "sphere_t", "sphere_overlap")),
        "cap": int(small_probe.d["nbr"].shape[1]), "longest": int(small_probe.nbr_n.max())}

    # a falling box: no neighbours at the first build, so the lists overflow at a
    # rebuild in the middle of the call (one entry each), and several rebuilds in
    # one call as it falls; contact with the slab before the end
    fall = falling_model()
    f_cpu_be = CpuBackend(fall)
    f_cpu_be.probe(fall.initial_state())
    first_longest = int(f_cpu_be.nbr_n.max())
    p, q = fall.initial_state(), fall.initial_state()
    f_cu_be = one_entry(kcu.CudaBackend(fall))
    f_cpu_be.step(p, FALL_STEPS)
    f_cu_be.step(q, FALL_STEPS)
    out["falling"] = {
        "identical": all(np.array_equal(getattr(q, n), getattr(p, n)) for n in BODY),
        "rel": {n: _rel(getattr(q, n), getattr(p, n)) for n in BODY},
        "first_longest": first_longest, "longest": int(f_cu_be.nbr_n.max()),
        "rebuilds": f_cu_be.rebuilds, "redos": f_cu_be.redos,
        "cap": int(f_cu_be.d["nbr"].shape[1]),
        "box_drop": float((fall.initial_x[1, 2] - p.body_x[1, 2]) / D),
        "box_force": float(np.abs(f_cpu_be.sphere_f[16:20]).max()),
        "sphere_x_identical": bool(np.array_equal(f_cu_be.sphere_x, f_cpu_be.sphere_x)),
        "sphere_f_identical": bool(np.array_equal(f_cu_be.sphere_f, f_cpu_be.sphere_f)),
    }
    # and on from there (the lists are long enough now: no redo)
    f_cpu_be.step(p, 6)
    f_cu_be.step(q, 6)
    out["falling"]["more_identical"] = all(np.array_equal(getattr(q, n), getattr(p, n))
                                           for n in BODY)
    out["falling"]["redos_after"] = f_cu_be.redos

    # every body asleep: both targets skip the rest of a call's steps (no-ops), and
    # go on computing when a later call starts; bit for bit, histories included
    nap = sleepy_model()
    n_cpu, n_cu = CpuBackend(nap), kcu.CudaBackend(nap)
    u, w_ = nap.initial_state(), nap.initial_state()
    for n_steps in (12, 5):
        n_cpu.step(u, n_steps)
        n_cu.step(w_, n_steps)
    n_cu.download(w_, contacts=True)
    out["asleep"] = {
        "identical": all(np.array_equal(getattr(w_, n), getattr(u, n))
                         for n in BODY + ("body_rest", "contact_partner", "contact_spring")),
        "all_asleep": bool(u.asleep(nap.sleep_steps)[: nap.n_bodies].all()),
        "skipped_cpu": n_cpu.steps_skipped, "skipped_cuda": n_cu.steps_skipped,
    }

    # prescribed motion: a belt, a sliding pen, a spinning kinematic box, an
    # emitter; in calls of 2, 5 and 7 steps (the emitter's start inside the second)
    pm = prescribed_model()
    p_cpu, p_cu = CpuBackend(pm), kcu.CudaBackend(pm)
    u, w_ = pm.initial_state(), pm.initial_state()
    for n_steps in (2, 5, 7):
        p_cpu.step(u, n_steps)
        p_cu.step(w_, n_steps)
    p_cu.download(w_, contacts=True)
    vu, ww = p_cpu.velocities(u), p_cu.velocities(w_)
    out["prescribed"] = {
        "identical": all(np.array_equal(getattr(w_, n), getattr(u, n))
                         for n in BODY + ("body_rest", "contact_partner", "contact_spring")),
        "velocities_identical": bool(np.array_equal(vu[0], ww[0])
                                     and np.array_equal(vu[1], ww[1])),
        "kinematic_moved": float(u.body_x[2, 0] - pm.initial_x[2, 0]),
        "boxes_moved": float(np.abs(u.body_x[:2, 0] - pm.initial_x[:2, 0]).max()),
    }

    # a surface ball rolling down a slope: its wall contacts through inscribed balls
    ball = inscribed_ball_model()
    i_cpu = Simulator(ball, device="cpu").advance(ball.initial_state())
    i_cu = Simulator(ball, device="cuda").advance(ball.initial_state())
    out["inscribed"] = {
        "balls": int(np.count_nonzero(ball.sphere_inscribed[:, 10] > 0.5 * ball.diameter)),
        "identical": all(np.array_equal(getattr(i_cu, n), getattr(i_cpu, n))
                         for n in ("x", "q", "v", "w")),
        "rolled": float(i_cpu.x[-1, 0, 0] - i_cpu.x[0, 0, 0]),
    }

    # a lattice cylinder on its rim: its wall contacts through the rim's ring
    rim = rim_model()
    r_cpu = Simulator(rim, device="cpu").advance(rim.initial_state())
    r_cu = Simulator(rim, device="cuda").advance(rim.initial_state())
    t = rim.sphere_inscribed
    out["rims"] = {
        "rims": int(np.count_nonzero((t[:, 9] > 0.0) & (t[:, 10] == 0.0))),
        "identical": all(np.array_equal(getattr(r_cu, n), getattr(r_cpu, n))
                         for n in ("x", "q", "v", "w")),
    }

    # a lattice pawn tipped onto its foot: its wall contacts through its plinth's band
    band = band_model()
    b_cpu = Simulator(band, device="cpu").advance(band.initial_state())
    b_cu = Simulator(band, device="cuda").advance(band.initial_state())
    out["bands"] = {
        "bands": int(np.count_nonzero(band.sphere_inscribed[:, 12] > 0.0)),
        "identical": all(np.array_equal(getattr(b_cu, n), getattr(b_cpu, n))
                         for n in ("x", "q", "v", "w")),
    }

    # a surface box tipped onto an edge: the spheres its neighbours cover meet no wall
    box = covered_box_model()
    c_cpu = Simulator(box, device="cpu").advance(box.initial_state())
    c_cu = Simulator(box, device="cuda").advance(box.initial_state())
    out["covered"] = {
        "covered": int(np.count_nonzero(box.sphere_inscribed[:, COVERED])),
        "spheres": int(box.sphere_inscribed.shape[0]),
        "identical": all(np.array_equal(getattr(c_cu, n), getattr(c_cpu, n))
                         for n in ("x", "q", "v", "w")),
    }

    # the whole Simulator path on device="cuda": a few steps per frame
    fast = contact_model(fps=1.0 / (4 * model.dt), n_frames=4)
    f_cpu = Simulator(fast, device="cpu")
    f_cu = Simulator(fast, device="cuda")
    fa = f_cpu.advance(fast.initial_state())
    fb = f_cu.advance(fast.initial_state())
    out["simulator"] = {
        "backend": type(f_cu.backend).__name__, "steps_per_frame": fast.steps_per_frame,
        "rel": {n: _rel(getattr(fb, n), getattr(fa, n)) for n in ("x", "q", "v", "w")},
        "identical": all(np.array_equal(getattr(fb, n), getattr(fa, n))
                         for n in ("x", "q", "v", "w")),
        "overlap_same": f_cpu.stats.max_overlap == f_cu.stats.max_overlap,
    }
    return out


@pytest.fixture(scope="module")
def sim():
    return simulator_results(__file__, timeout=900)


def test_sim_grid_table_is_the_cpus(sim):
    assert sim["grid_table_same"]


def test_sim_prefix_sum(sim):
    assert all(sim["scan_ok"]), sim["scan_ok"]
    assert sim["scan_levels_small_chunk"] >= 3          # the recursive path was exercised


def test_sim_memory_estimate_and_error(sim):
    assert sim["memory_needed"] == sim["memory_allocated"]
    msg = sim["memory_error"]
    assert msg and "10.00 GiB" in msg and "2.00 GiB" in msg and "--device cpu" in msg


def test_sim_stages_1_to_4_match_cpu(sim):
    p = sim["probe"]
    assert p["max_force"] > 0 and p["max_overlap"] > 0     # contacts were exercised
    assert p["grid_equal"] and p["bucket_start_equal"] and p["sorted_idx_equal"]
    for name, rel in p["rel"].items():
        assert rel < PARITY_RTOL, (name, rel)


def test_sim_one_step_and_twenty_match_cpu(sim):
    for name, rel in sim["step1"]["rel"].items():
        assert rel < PARITY_RTOL, ("1 step", name, rel)
    s = sim["step20"]
    assert s["moved"] > 0.01                                # things happened
    for name, rel in s["rel"].items():
        assert rel < PARITY_RTOL, ("20 steps", name, rel)
    assert s["rel_v"] < PARITY_RTOL and s["rel_w"] < PARITY_RTOL
    assert s["overlap_cuda"] == pytest.approx(s["overlap_cpu"], rel=PARITY_RTOL)
    assert s["overlap_cuda"] > 0 and s["overlap_reset"] == 0.0


def test_sim_simulator_device_cuda_matches_cpu(sim):
    s = sim["simulator"]
    assert s["backend"] == "CudaBackend" and s["steps_per_frame"] >= 2
    for name, rel in s["rel"].items():
        assert rel < PARITY_RTOL, (name, rel)
    assert s["overlap_same"]


def test_sim_is_bit_identical_to_cpu(sim):
    # Same formulas, same order of summation, float64, and the simulator runs the
    # same IEEE operations as the compiled CPU code (no FMA contraction on either,
    # libm's sin/cos/sqrt): bit for bit. A real GPU is not (FMA), see docs/cuda.md.
    # (the scene has friction and rolling resistance: both passes' torques compared)
    assert sim["features"] == {"rolling": True, "friction": True}
    assert sim["flags"][0] == sim["flags"][1] != [True] * 4      # specialized, both targets
    assert all(sim["probe"]["identical"].values()), sim["probe"]["identical"]
    assert sim["step1"]["identical"] and sim["step20"]["identical"]
    assert sim["new_state_identical"] and sim["simulator"]["identical"]


def test_sim_inscribed_wall_contacts_are_bit_identical_to_cpu(sim):
    # a surface ball rolling on a plane: every shell sphere's wall contact goes through
    # its inscribed ball on both targets
    s = sim["inscribed"]
    assert s["balls"] > 50
    assert s["rolled"] > 0.0
    assert s["identical"]


def test_sim_covered_spheres_are_left_out_alike_on_both_targets(sim):
    # a surface box tipped onto its edge: the spheres of its faces that their neighbours
    # cover meet no wall, on both targets (pairing.wall_reach)
    s = sim["covered"]
    assert s["covered"] > s["spheres"] // 3
    assert s["identical"]


def test_sim_rim_contacts_are_bit_identical_to_cpu(sim):
    # a lattice cylinder tipped onto its rim: its contact goes through the rim's ring
    # (a tube of radius 0, pairing.RIM_TIE) on both targets
    s = sim["rims"]
    assert s["rims"] > 10
    assert s["identical"]


def test_sim_band_contacts_are_bit_identical_to_cpu(sim):
    # a lattice pawn tipped onto its foot: its contact goes through its plinth's band
    # (a rim swept along its axis, its lower edge) on both targets
    s = sim["bands"]
    assert s["bands"] > 10
    assert s["identical"]


def test_sim_hertz_law_is_bit_identical_to_cpu(sim):
    # The contact law is a compile-time axis of the contact passes on both targets
    # (laws/hertz.py compiled into pair_forces): the same formulas, the same bits.
    assert sim["hertz"]["identical"], sim["hertz"]
    assert sim["hertz"]["moved"] > 0.01          # the bodies moved (and touched)


def test_sim_list_overflow_relaunches_bit_identical(sim):
    # Lists shrunk to one entry: the first build overflows, nothing of the State
    # (bodies, rest counts, histories) changes from there, and the steps are
    # relaunched from that step with lists grown to the longest.
    o = sim["overflow_first_step"]
    assert o["redos"] == 1 and o["cap"] >= o["longest"] > 1
    assert o["identical"] and o["histories_identical"]
    p = sim["overflow_probe"]
    assert p["cap"] >= p["longest"] > 1 and p["identical"]


def test_sim_rebuilds_and_overflow_in_the_middle_of_a_call(sim):
    f = sim["falling"]
    assert f["first_longest"] == 0                  # nothing to overflow at the first build
    assert f["redos"] == 1 and f["redos_after"] == 1  # so it overflowed mid-call; once
    assert f["cap"] >= f["longest"] > 1
    assert 2 <= f["rebuilds"] < FALL_STEPS          # rebuilt mid-call, not at every step
    assert f["box_drop"] > 0.2 and f["box_force"] > 0  # it fell and hit the slab
    assert f["identical"] and f["more_identical"], f["rel"]
    assert f["sphere_x_identical"] and f["sphere_f_identical"]


def test_sim_all_asleep_steps_skipped_on_both_targets_bit_identical(sim):
    a = sim["asleep"]
    assert a["all_asleep"] and a["identical"]
    assert a["skipped_cpu"] > 0 and a["skipped_cuda"] == a["skipped_cpu"]


def test_sim_prescribed_motion_is_bit_identical_to_cpu(sim):
    """Moving walls, a kinematic body and an emitter: the same State on both targets,
    rest counts and contact histories included."""
    p = sim["prescribed"]
    assert p["identical"] and p["velocities_identical"], p
    assert p["kinematic_moved"] > 0 and p["boxes_moved"] > 0, p


def test_sim_run_to_run_identical(sim):
    assert sim["run_to_run_identical"]


def test_import_dempipe_and_cpu_path_do_not_import_numba_cuda():
    code = (
        "import sys\n"
        "import dempipe\n"
        "from dempipe.sim.kernels.cpu import stages as cpu\n"
        "from dempipe.sim.simulator import Simulator\n"
        "from test_simulation import one_ball\n"
        "b, s, m = one_ball(0.5)\n"
        "b.add_bodies('ball', s, m, [[0, 0, 0.02]])\n"
        "b.add_plane([0, 0, 0], [0, 0, 1], m)\n"
        "model = b.finalize(fps=100, n_frames=3)\n"
        "Simulator(model, device='cpu').advance(model.initial_state())\n"
        "print(sorted(k for k in sys.modules if k == 'numba.cuda' or k.startswith('numba.cuda.')"
        " or k == 'dempipe.sim.kernels.cuda.backend'))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], env=cuda_env(sim=False), capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert proc.stdout.strip().splitlines()[-1] == "[]"


# ---------------------------------------------------------------------------
# Real GPU
# ---------------------------------------------------------------------------

_GPU = None


def _gpu_present() -> bool:
    global _GPU
    if _GPU is None:
        if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
            _GPU = False          # this process would get the simulator, far too slow
        else:
            try:
                proc = subprocess.run(
                    [sys.executable, "-c", "from numba import cuda; print(cuda.is_available())"],
                    env=cuda_env(sim=False), capture_output=True, text=True, timeout=120)
                _GPU = proc.returncode == 0 and proc.stdout.strip().endswith("True")
            except (OSError, subprocess.TimeoutExpired):
                _GPU = False
    return _GPU


@pytest.fixture
def gpu():
    if not _gpu_present():
        pytest.skip("no CUDA GPU here (numba.cuda.is_available() is False)")


@pytest.mark.gpu
def test_gpu_parity_on_thousands_of_bodies(gpu):
    # 2,304 bodies, 7,488 spheres in a pile. After one step: 1e-9 relative (same
    # formulas and summation order; only FMA contraction differs). After 100
    # steps the contacts' chaos amplifies last-bit differences; still < 1e-6.
    from dempipe.sim.kernels.cpu.backend import CpuBackend
    from dempipe.sim.kernels.cuda.backend import CudaBackend

    model = pile_model(n_side=24, layers=4)
    assert model.n_bodies >= 2000
    st0 = model.initial_state()
    cpu, gpu_be = CpuBackend(model), CudaBackend(model)
    a = st0.copy()
    cpu.step(a, 200)          # into contact
    b, c = a.copy(), a.copy()
    cpu.step(a, 1)
    gpu_be.step(b, 1)
    for name in ("body_x", "body_q", "body_P", "body_L"):
        assert _rel(getattr(b, name), getattr(a, name)) < PARITY_RTOL, name
    assert np.abs(cpu.sphere_f).max() > 0
    cpu.step(a, 99)
    gpu_be.step(b, 99)
    for name in ("body_x", "body_q"):
        assert _rel(getattr(b, name), getattr(a, name)) < 1e-6, name
    # run to run on the GPU: bit-identical
    r1, r2 = c.copy(), c.copy()
    CudaBackend(model).step(r1, 100)
    CudaBackend(model).step(r2, 100)
    for name in ("body_x", "body_q", "body_P", "body_L"):
        assert np.array_equal(getattr(r1, name), getattr(r2, name)), name


@pytest.mark.gpu
@pytest.mark.parametrize("e", [0.2, 0.5, 0.9])
def test_gpu_bounce_height_is_e_squared(gpu, e):
    from dempipe.sim.simulator import Simulator
    from test_simulation import one_ball

    b, s, m = one_ball(e)
    h0 = 0.1
    b.add_bodies("ball", s, m, [[0, 0, h0 + D / 2]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=2000, n_frames=1000, steps_per_contact=512)
    frames = Simulator(model, device="cuda").advance(model.initial_state())
    z = frames.x[:, 0, 2] - D / 2
    hit = np.argmax(z < 0)
    leave = hit + np.argmax(z[hit:] >= 0)
    apex = z[leave:leave + 800].max()
    assert apex / h0 == pytest.approx(e * e, rel=0.03)       # as tests/sim/test_simulation.py


@pytest.mark.gpu
def test_gpu_head_on_collision_conserves_momentum(gpu):
    from bodies import ball_set
    from dempipe.sim.materials import Material
    from dempipe.sim.builder import ModelBuilder
    from dempipe.sim.simulator import Simulator

    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    light = b.add_material(Material("light", density=500, restitution=0.5, friction=0.3))
    heavy = b.add_material(Material("heavy", density=3000, restitution=0.5, friction=0.3))
    b.add_bodies("a", s, light, [[-0.02, 0, 0]], velocities=[[2.0, 0, 0]])
    b.add_bodies("b", s, heavy, [[0.02, 0.002, 0]], velocities=[[-1.0, 0, 0]])
    model = b.finalize(fps=500, n_frames=40)
    frames = Simulator(model, device="cuda").advance(model.initial_state())
    P = np.einsum("b,fbi->fi", model.body_mass[:2], frames.v)
    scale = np.abs(model.body_mass[:2] * np.linalg.norm(frames.v[0], axis=1)).sum()
    assert np.abs(P - P[0]).max() / scale < 1e-6
    assert frames.v[-1, 1, 0] - frames.v[-1, 0, 0] > 0.5


@pytest.mark.gpu
def test_gpu_sliding_ball_ends_rolling_at_five_sevenths(gpu):
    from dempipe.sim.simulator import Simulator
    from test_simulation import one_ball

    b, s, m = one_ball(e=0.3, mu=0.5)
    b.add_bodies("ball", s, m, [[0, 0, D / 2 - 1e-5]], velocities=[[1.0, 0, 0]])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    model = b.finalize(fps=100, n_frames=31)
    frames = Simulator(model, device="cuda").advance(model.initial_state())
    assert frames.v[-1, 0, 0] == pytest.approx(5 / 7, rel=0.02)
    assert frames.w[-1, 0, 1] * D / 2 == pytest.approx(5 / 7, rel=0.02)


if __name__ == "__main__":
    if sys.argv[1:] == ["--sim"]:
        sys.path[:0] = [str(HERE), str(TESTS), str(ROOT)]
        print(json.dumps(_sim_main()))
    else:
        sys.exit("usage: NUMBA_ENABLE_CUDASIM=1 python tests/sim/test_cuda.py --sim")
