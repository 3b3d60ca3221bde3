"""The flat-face count (model.flat_face_spheres): how many spheres a plane presses at once.

n contacts pressed together are one oscillator of stiffness n k and damping ratio √n ζ,
so n bounds the step (materials.flat_face_critical_step). The count must hold for both
sphere-set modes: a lattice face and a surface set's flat face press every sphere on
them, a surface set's curved part only the small cap its landing reaches. Checked
against bakes that record every step: the count is never below what a landing
presses (the bound holds), equals it on a flat face (it is tight there), and on a
ball is a few spheres, not the whole band of 0.25 d the count used to take.
"""

import math

import numpy as np
from dempipe.spheres.cache import SphereCache
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.model import flat_face_spheres, quat_to_matrix
from dempipe.mesh.shapes import build_shape
from dempipe.sim.simulator import Simulator
from dempipe.spheres.options import BuildOptions
from dempipe.spheres.sphere_set import build_sphere_set

D = 0.01
G = 9.81


def landing(tmp_path, shape, kw, mode, seconds=0.006):
    """A body landing flat on a plane at √(2 g d) (as from a drop of one diameter),
    one frame per step: (most spheres pressed at once, the count for that landing,
    the count without a landing)."""
    mesh = build_shape(shape, **kw)
    ss = build_sphere_set(mesh, D, cache=SphereCache(tmp_path / "cache"),
                          options=BuildOptions(mode=mode))
    c = np.asarray(ss.centers)
    v0 = math.sqrt(2.0 * G * D)

    def builder():
        b = ModelBuilder(D)
        s = b.add_shape(shape, mesh, ss)
        m = b.add_material(Material("m", density=1000.0, restitution=0.5, friction=0.5))
        b.add_bodies("b", s, m, [[0.0, 0.0, -c[:, 2].min() + 0.501 * D]],
                     velocities=[[0.0, 0.0, -v0]])
        b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
        return b

    dt = builder().finalize(fps=100, n_frames=2).dt
    model = builder().finalize(fps=1.0 / dt, n_frames=int(seconds / dt) + 1, dt=dt)
    fr = Simulator(model).advance(model.initial_state())
    off = np.asarray(model.sphere_offset)
    pressed = max(int(np.count_nonzero(0.5 * D - (x[2] + off @ quat_to_matrix(q)[2]) > 0))
                  for x, q in zip(fr.x[:, 0], fr.q[:, 0]))
    assert fr.v[:, 0, 2].max() > 0 or pressed > 0               # it landed
    # the landing speed: v0 and the fall through 0.001 d, a hair more
    count = flat_face_spheres(c, D, float(model.pair_k[0, 0]), float(model.body_mass[0]),
                              v0 * 1.001, G)
    return pressed, count, flat_face_spheres(c, D)


def test_flat_faces_press_every_sphere_on_them(tmp_path):
    # a box of 4 x 4 x 2 diameters: the lattice's bottom face is its 16 spheres; the
    # surface set's is its offset plane of centres at spacing 0.3 d, several times more
    for mode in ("lattice", "surface"):
        pressed, count, band = landing(tmp_path, "box", dict(size=[0.04, 0.04, 0.02]), mode)
        assert pressed == count, mode                      # tight on a face
        if mode == "lattice":
            assert count == band == 16                      # the lattice count is as before
        else:
            assert count > 3 * 16


def test_a_ball_presses_a_small_cap(tmp_path):
    # a ball of 8 diameters: its surface set presses 1-3 spheres at once; the count
    # stays at or above that and far below the band of 0.25 d (28-35 spheres)
    pressed, count, band = landing(tmp_path, "sphere", dict(diameter=0.08), "surface")
    assert 1 <= pressed <= count
    assert count <= 8 and band >= 3 * count


def test_the_count_solves_the_landing_exactly():
    # centres at heights 0, 0, h, 2h above a plane: a landing whose springs take
    # ½ k Σ (δ - h_i)² = ½ m v² + m g δ at its deepest δ presses those below δ
    from dempipe.sim.model import _pressed

    h = 0.1 * D
    heights = np.array([0.0, 0.0, h, 2 * h])
    k, m = 1e5, 0.01
    for delta, want in ((0.5 * h, 2), (1.5 * h, 3), (3.0 * h, 4)):
        for g in (0.0, G):
            spring = sum(max(delta - z, 0.0) ** 2 for z in heights)
            v2 = (k * spring - 2 * m * g * delta) / m       # the landing that reaches δ
            load = (m * v2 * (1 - 1e-6) / k, m * g / k)
            assert int(_pressed(heights, load, D)[0]) == want, (delta, g)
    assert int(_pressed(heights, None, D)[0]) == 4      # without a landing: all in the band
