"""Glue bonds on the CUDA target against the CPU target, under numba's CUDA simulator.

As tests/sim/test_cuda.py: the simulator must be switched on before ``numba.cuda`` is
first imported, so the runs happen in one subprocess (this file run as a script,
``python tests/sim/test_cuda_glue.py --sim``) that prints its measurements as JSON,
and the tests below assert on them. The simulator executes the same IEEE operations
as the compiled CPU code, so the two targets agree bit for bit: the glue passes
(kernels/glue.py) are the CPU's own functions, each bond computed by one thread and
each body's sum in its bonds' order, no atomics.

The scene is small (the simulator runs every CUDA thread in Python): four glued
cubes of 2 x 2 x 2 spheres standing on the ground and spinning about the vertical,
so that in the few steps compared the bonds carry tension and shear and turn with
their pieces, two of them break, and the pieces touch the ground (with friction) and,
once broken apart, each other.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from cudasim import simulator_results

# the simulator runs every thread of a launch in Python: not in the fast tier
pytestmark = pytest.mark.slow

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent
ROOT = TESTS.parent
D = 0.02
RHO = 1000.0
#: Steps compared in one call, then in calls of STEPS_SPLIT (the State on and off the
#: device between calls, and a checkpoint's arrays carried into a new backend).
STEPS = 20
STEPS_SPLIT = (3, 7, 10)
#: The block spins about the vertical at 20 rad/s: each horizontal bond (p0-p1, p2-p3)
#: carries the centripetal load m ω² r = 0.51 N (m = 8 d³ ρ, r = d) on 4 pairs, 0.13 N
#: a pair, σ d² at σ = 320 Pa, and overshoots it as the bond stretches from rest; at
#: σ = 200 Pa both break at step 9-10 (measured on the CPU), while the vertical bonds,
#: pressed by the upper pieces' weight and sheared by the ground's friction on the
#: lower pieces (and twisting about their normals with the spin), hold.
SPIN = (0.0, 0.0, 20.0)
GLUE_STRENGTH = 200.0
STATE = ("body_x", "body_q", "body_P", "body_L", "body_rest", "bond_broken", "bond_shear")


def glued_model(fps=None, n_frames=2):
    """Four 2 x 2 x 2 cubes of one lattice, glued (a 2 x 2 block in the x-z plane,
    its lowest spheres touching a plane), spinning rigidly about SPIN.
    ``fps`` None: the scene's own; else a few steps per frame."""
    from test_glue import box_piece
    from dempipe.sim.builder import ModelBuilder
    from dempipe.sim.materials import Material

    b = ModelBuilder(D, gravity=(0.0, 0.0, -9.81))
    m = b.add_material(Material("glued", density=RHO, friction=0.5, restitution=0.3,
                                glue_strength=GLUE_STRENGTH))
    mid = np.array([2.0 * D, D, 2.0 * D])                   # the block's centre
    for k, (ix, iz) in enumerate([(0, 0), (1, 0), (0, 1), (1, 1)]):
        mesh, ss = box_piece((2 * ix, 0, 2 * iz), (2 * ix + 2, 2, 2 * iz + 2))
        s = b.add_shape(f"p{k}", mesh, ss)
        v = np.cross(SPIN, ss.com - mid)                     # a rigid spin about mid
        b.add_bodies(f"p{k}", s, m, [[0.0, 0.0, 0.0]], velocities=[v],
                     angular_velocities=[list(SPIN)], glue=[0])
    b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    model = b.finalize(fps=24 if fps is None else fps, n_frames=n_frames)
    return model


# ---------------------------------------------------------------------------
# The simulator script (runs in a subprocess with NUMBA_ENABLE_CUDASIM=1)
# ---------------------------------------------------------------------------

def _sim_main() -> dict:
    assert os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
    import dempipe.sim.kernels.cuda.backend as kcu
    from dempipe.pipeline.checkpoint import PERSISTENT
    from dempipe.sim.kernels.cpu.backend import CpuBackend
    from dempipe.sim.simulator import Simulator

    out: dict = {}
    model = glued_model()
    out["bonds"] = int(model.n_bonds)
    out["pairs"] = int(model.bonds.n_pairs)
    out["features"] = {"friction": bool(model.features.friction),
                       "rotation": bool(model.features.rotation),
                       "walls": bool(model.features.walls)}
    be = kcu.CudaBackend(model)
    out["memory_needed"] = kcu.memory_needed(model)
    out["memory_allocated"] = int(sum(a.nbytes for a in be.d.values()))

    def same(a, b, names=STATE):
        return {n: bool(np.array_equal(getattr(a, n), getattr(b, n))) for n in names}

    # one call of STEPS steps
    st0 = model.initial_state()
    cpu = CpuBackend(model)
    a, b = st0.copy(), st0.copy()
    cpu.step(a, STEPS)
    be.step(b, STEPS)
    be.download(b, contacts=True)
    out["one_call"] = {
        "identical": same(a, b, STATE + ("contact_partner", "contact_spring")),
        "broken": int(a.bond_broken.sum()),
        "shear": float(np.abs(a.bond_shear).max()),
        "moved": float(np.abs(a.body_x - st0.body_x).max() / D),
        "contact_force": float(np.abs(cpu.sphere_f).max()),
        "sphere_f_identical": bool(np.array_equal(be.sphere_f, cpu.sphere_f)),
    }
    # the kernels specialized to the scene (its own flags, glue passes compiled with
    # them), as a bake runs them; the cases above run the general ones (conftest.py)
    c, e = st0.copy(), st0.copy()
    cpu_s, be_s = CpuBackend(model, specialize=True), kcu.CudaBackend(model, specialize=True)
    cpu_s.step(c, STEPS)
    be_s.step(e, STEPS)
    out["specialized"] = {"flags": [list(cpu_s.flags), list(be_s.flags)],
                          "identical": same(c, e), "same_as_general": same(c, a)}

    # the steps at which bonds broke, on the CPU (how early the comparison sees a break)
    c = st0.copy()
    first = None
    for k in range(STEPS):
        cpu.step(c, 1)
        if first is None and c.bond_broken.any():
            first = k + 1
    out["first_break_step"] = first

    # in calls of STEPS_SPLIT; after the second, a checkpoint's arrays (the State's
    # and the backend's PERSISTENT ones) go into a fresh backend and a fresh State
    c, e = st0.copy(), st0.copy()
    cpu2, be2 = CpuBackend(model), kcu.CudaBackend(model)
    for k, n in enumerate(STEPS_SPLIT):
        cpu2.step(c, n)
        be2.step(e, n)
        if k == 1:
            saved = be2.save_arrays(e, PERSISTENT)
            e2 = model.initial_state()
            for name in STATE + ("contact_partner", "contact_spring"):
                setattr(e2, name, getattr(e, name).copy())
            e2.step, e2.time = e.step, e.time
            be2 = kcu.CudaBackend(model)
            be2.load_arrays(e2, saved)
            e = e2
    be2.download(e, contacts=True)
    out["split_resumed"] = same(c, e, STATE + ("contact_partner", "contact_spring"))
    out["split_vs_one_call"] = same(c, a)

    # the Simulator on device="cuda": frames of a few steps, bonds broken per frame
    fast = glued_model(fps=1.0 / (4 * model.dt), n_frames=4)
    s_cpu, s_cu = Simulator(fast, device="cpu"), Simulator(fast, device="cuda")
    p, q = fast.initial_state(), fast.initial_state()
    fa, fb = s_cpu.advance(p), s_cu.advance(q)
    out["simulator"] = {
        "backend": type(s_cu.backend).__name__, "steps_per_frame": fast.steps_per_frame,
        "frames_identical": {n: bool(np.array_equal(getattr(fa, n), getattr(fb, n)))
                             for n in ("x", "q", "v", "w")},
        "state_identical": same(p, q),
        "bonds_broken": [s_cpu.stats.bonds_broken, s_cu.stats.bonds_broken],
    }
    return out


@pytest.fixture(scope="module")
def sim():
    return simulator_results(__file__, timeout=1800)


def test_sim_scene_exercises_bonds_contacts_and_breaks(sim):
    assert sim["features"] == {"friction": True, "rotation": True, "walls": True}
    assert sim["bonds"] == 4 and sim["pairs"] == 16
    o = sim["one_call"]
    assert 0 < o["broken"] < sim["bonds"], o          # some broke, some held
    assert sim["first_break_step"] <= STEPS - 5        # steps compared after the break
    assert o["shear"] > 0 and o["contact_force"] > 0 and o["moved"] > 0.01, o


def test_sim_glue_is_bit_identical_to_cpu(sim):
    o = sim["one_call"]
    assert all(o["identical"].values()), o["identical"]
    assert o["sphere_f_identical"]


def test_sim_specialized_glue_kernels_are_bit_identical_to_cpu(sim):
    s = sim["specialized"]
    assert s["flags"][0] == s["flags"][1] != [True] * 4
    assert all(s["identical"].values()), s["identical"]
    assert all(s["same_as_general"].values()), s["same_as_general"]


def test_sim_glue_state_carries_across_calls_and_a_checkpoint(sim):
    # bond_broken and bond_shear go up and down with the rest of the State; a new
    # backend given a checkpoint's arrays carries on bit for bit
    assert all(sim["split_resumed"].values()), sim["split_resumed"]
    assert all(sim["split_vs_one_call"].values()), sim["split_vs_one_call"]


def test_sim_simulator_device_cuda_glue_matches_cpu(sim):
    s = sim["simulator"]
    assert s["backend"] == "CudaBackend" and s["steps_per_frame"] >= 2
    assert all(s["frames_identical"].values()), s["frames_identical"]
    assert all(s["state_identical"].values()), s["state_identical"]
    assert s["bonds_broken"][0] == s["bonds_broken"][1] and s["bonds_broken"][0][-1] > 0, s


def test_memory_estimate_counts_the_bonds(sim):
    assert sim["memory_needed"] == sim["memory_allocated"]


if __name__ == "__main__":
    if sys.argv[1:] == ["--sim"]:
        sys.path[:0] = [str(HERE), str(TESTS), str(ROOT)]
        print(json.dumps(_sim_main()))
    else:
        sys.exit("usage: NUMBA_ENABLE_CUDASIM=1 python tests/sim/test_cuda_glue.py --sim")
