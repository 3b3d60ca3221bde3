"""The CPU's broadphase at a rebuild (kernels/cpu/broadphase.py): which bodies can be
in reach of each other, and which spheres can have a partner at all.

It may only leave out what the 27-cell search would find nothing for: the body pairs
are checked against every pair, and each left-out sphere against every sphere of
the other bodies. test_neighbours' oracle checks the lists it leads to.
"""

import numpy as np

from bodies import box_set
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.kernels.cpu.backend import CpuBackend
from dempipe.sim.kernels.cpu.broadphase import PAD, body_partners, stage_near_others
from dempipe.sim.kernels.neighbours import cell_size
from dempipe.sim.materials import Material
from test_contacts import boxes_on_static_slab
from test_neighbours import dense_blocks
from test_simulation import cluster_model

D = 0.01


def rods(n=40, seed=5):
    """Long thin bodies (8 x 1 x 1 spheres) turned at random and thrown at each other
    in a box, no gravity, some entering later (an emitter): a bounding sphere holds
    them loosely, so the box test decides."""
    rng = np.random.default_rng(seed)
    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = box_set(8, 1, 1, D)
    s = b.add_shape("rod", mesh, ss)
    m = b.add_material(Material("m", density=900, restitution=0.5, friction=0.4))
    q = rng.normal(size=(n, 4))
    pos = rng.uniform(0.05, 0.15, size=(n, 3))
    b.add_bodies("rods", s, m, pos[: n // 2], rotations=q[: n // 2] / np.linalg.norm(
        q[: n // 2], axis=1)[:, None], velocities=rng.normal(size=(n // 2, 3)) * 0.3,
        angular_velocities=rng.normal(size=(n // 2, 3)) * 4)
    b.add_bodies("late", s, m, pos[n // 2:], rotations=q[n // 2:] / np.linalg.norm(
        q[n // 2:], axis=1)[:, None], start_time=0.05)
    b.add_box([0, 0, 0], [0.2, 0.2, 0.2], material=m)
    return b.finalize(fps=60, n_frames=6)


def brute_partners(be, model, x, reach, step):
    """Every pair of bodies the broadphase must pair, by testing each pair."""
    nb = model.body_sphere_start.shape[0] - 1
    r = be.body_reach[:nb]
    live = (np.diff(model.body_sphere_start) > 0) & (be.drive.body_start[:nb] <= step)
    static = model.body_inv_mass[:nb] == 0
    out = set()
    for a in range(nb):
        for b in range(a + 1, nb):
            if not (live[a] and live[b]) or (static[a] and static[b]):
                continue
            if np.linalg.norm(x[a] - x[b]) <= (r[a] + r[b] + reach) * (1 + PAD):
                out.add((a, b))
    return out


def test_body_pairs_are_every_pair_whose_bounds_are_in_reach():
    for model in (rods(), cluster_model(n=20), boxes_on_static_slab()):
        be = CpuBackend(model)
        st = model.initial_state()
        reach = cell_size(model.diameter)
        for k in range(3):
            if k:
                be.step(st, model.steps_per_frame)
            step = int(st.step)
            start, other = body_partners(reach, st.body_x, be.body_reach,
                                         model.body_sphere_start, model.body_inv_mass,
                                         be.drive.body_start, step)
            got = set()
            for a in range(start.shape[0] - 1):
                for b in other[start[a]:start[a + 1]]:
                    got.add((min(a, b), max(a, b)))
                    assert a in other[start[b]:start[b + 1]]      # both ways
            assert got == brute_partners(be, model, st.body_x, reach, step)
            assert len(other) == 2 * len(got)                     # each once per side


def left_out(be, model, st, reach):
    """The spheres stage_near_others leaves out from the State, and the spheres
    with a sphere of another body within ``reach`` (brute force)."""
    be.probe(st)                           # every sphere placed (sphere_x)
    hashes = np.zeros_like(be.sphere_hash)
    n_out = stage_near_others(0, reach, be.offset_t, st.body_x, st.body_q,
                              model.body_sphere_start, be.body_reach, be.body_box,
                              model.body_inv_mass, be.drive.body_start, int(st.step), hashes)
    out = hashes < 0
    assert n_out == out.sum()
    x, body = be.sphere_x, model.sphere_body
    started = be.drive.body_start[body] <= int(st.step)
    d2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    near = (d2 < reach * reach) & (body[:, None] != body[None, :]) & started[None, :]
    return out, near.any(axis=1)


def test_a_left_out_sphere_has_no_sphere_of_another_body_in_reach():
    seen_out = 0
    for model in (rods(), cluster_model(n=20), dense_blocks(), boxes_on_static_slab()):
        be = CpuBackend(model)
        st = model.initial_state()
        reach = cell_size(model.diameter)
        for k in range(4):
            if k:
                be.step(st, max(1, model.steps_per_frame // 2))
            out, has_partner = left_out(be, model, st, reach)
            assert not np.any(out & has_partner)
            static = model.body_inv_mass[model.sphere_body] == 0
            assert not np.any(out & static)        # static spheres are always in the grid
            seen_out += int(out.sum())
    # and it does leave spheres out (a filter that keeps everything would pass above)
    assert seen_out > 0


def test_the_box_test_is_sharp():
    # With the boxes grown by half the reach instead of all of it, spheres with a
    # partner in reach are lost: the test above would catch such a broadphase.
    model = rods()
    be = CpuBackend(model)
    st = model.initial_state()
    be.step(st, model.steps_per_frame)
    reach = cell_size(model.diameter)
    out, has_partner = left_out(be, model, st, reach)
    assert not np.any(out & has_partner)
    be.body_box[:, 3:] -= 0.5 * reach
    out, has_partner = left_out(be, model, st, reach)
    assert np.any(out & has_partner)


def test_the_frames_are_the_same_with_the_broadphase_and_without():
    # The broadphase changes which spheres are searched, never a list: the State is
    # the same bit for bit whether it runs at every rebuild or never (run_steps reads
    # CpuBackend.broadphase_spheres), over calls of many steps with their rebuilds.
    from dempipe.sim.simulator import Simulator

    for model in (rods(), dense_blocks(), boxes_on_static_slab()):
        states = []
        for min_spheres in (0, 10 ** 9):
            st = model.initial_state()
            be = Simulator(model).backend
            be.broadphase_spheres = min_spheres
            for _ in range(3):
                be.step(st, model.steps_per_frame)
            states.append(st)
        for name in ("body_x", "body_q", "body_P", "body_L", "contact_partner",
                     "contact_spring"):
            assert np.array_equal(getattr(states[0], name), getattr(states[1], name)), name
