"""Specialized kernels: the CPU stage drivers are compiled per feature
set, and a kernel carrying a feature the scene does not use gives the same frames,
bit for bit, as the kernel built without it."""

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bodies import ball_set, box_set
from dempipe.sim.materials import Material
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.simulator import Simulator

D = 0.01
HERE = Path(__file__).parent


@pytest.fixture(autouse=True)
def specialized(monkeypatch):
    """These tests are about the specialized kernels: the suite's default of one general
    kernel for every scene (conftest.py) is switched back for them."""
    monkeypatch.setenv("DEMPIPE_KERNELS", "specialized")


def test_general_by_environment_gives_the_same_frames(monkeypatch):
    m = ball_pile(n=9, n_frames=3)
    own = Simulator(m)
    assert own.backend.flags != (True, True, True, True)
    monkeypatch.setenv("DEMPIPE_KERNELS", "general")
    general = Simulator(m)
    assert general.backend.flags == (True, True, True, True)
    assert Simulator(m, specialize=True).backend.flags == own.backend.flags   # asked: kept
    a, b = own.advance(m.initial_state()), general.advance(m.initial_state())
    for name in ("x", "q", "v", "w"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_unknown_kernel_choice_names_the_variable(monkeypatch):
    from dempipe.errors import DeviceError

    monkeypatch.setenv("DEMPIPE_KERNELS", "fast")
    with pytest.raises(DeviceError, match="DEMPIPE_KERNELS='fast'.*'specialized'.*'general'"):
        Simulator(ball_pile(n=9, n_frames=2))


def ball_pile(n=27, plane=True, gravity=(0.0, 0.0, -9.81), sleep=None, n_frames=5):
    """n one-sphere balls, frictionless, in a jittered lattice dropped onto a plane
    (contacts at every angle, so any stray torque would show)."""
    b = ModelBuilder(D, gravity=gravity)
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("glass", density=2500, restitution=0.5, friction=0.0))
    rng = np.random.default_rng(7)
    pos = [[(i % 3) * 0.0105 + rng.uniform(-1e-3, 1e-3),
            (i // 3 % 3) * 0.0105 + rng.uniform(-1e-3, 1e-3),
            0.006 + (i // 9) * 0.0102] for i in range(n)]
    vel = None if plane else [[0.0, 0.0, -0.2 * (i // 9)] for i in range(n)]
    b.add_bodies("balls", s, m, pos, velocities=vel)
    if plane:
        b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=24, n_frames=n_frames, sleep=sleep)


def box_pile(mu=0.0, n_frames=5):
    """Six 2×2×2-sphere boxes stacked askew onto a plane (they tip and turn)."""
    b = ModelBuilder(D)
    ss, mesh = box_set(2, 2, 2, D)
    s = b.add_shape("box", mesh, ss)
    m = b.add_material(Material("wood", density=700, restitution=0.3, friction=mu))
    pos = [[(i % 2) * 0.023, 0.004 * i, 0.011 + 0.022 * (i // 2)] for i in range(6)]
    b.add_bodies("boxes", s, m, pos)
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    return b.finalize(fps=24, n_frames=n_frames)


def frames_of(model, **kw):
    sim = Simulator(model, **kw)
    frames = sim.advance(model.initial_state())
    return frames, sim


def assert_same(fa, fb):
    for name in ("x", "q", "v", "w"):
        assert np.array_equal(getattr(fa, name), getattr(fb, name)), name


def test_features_of_the_test_scenes():
    f = ball_pile().features
    assert not f.friction and not f.rotation and f.walls and not f.sleeping
    f = box_pile().features
    assert not f.friction and f.rotation
    assert box_pile(mu=0.5).features.friction


@pytest.mark.slow
def test_one_sphere_bodies_without_rotation_match_the_rotation_kernel():
    model = ball_pile()
    fa, sim = frames_of(model)
    assert sim.backend.flags == (False, False, False, True)
    assert sim.stats.max_overlap > 0.0                        # the balls do touch
    fb, sim_b = frames_of(model, features=replace(model.features, rotation=True))
    assert sim_b.backend.flags[1]
    assert_same(fa, fb)
    assert np.all(fa.w == 0.0) and np.all(fa.q == fa.q[0])    # exactly unturned
    fg, sim_g = frames_of(model, specialize=False)           # the general kernel
    assert sim_g.backend.flags == (True, True, True, True)
    assert_same(fa, fg)


def test_friction_zero_through_the_friction_kernel_matches_the_frictionless_one():
    model = box_pile(mu=0.0)
    fa, sim = frames_of(model)
    assert sim.backend.flags[:2] == (False, True)
    fb, sim_b = frames_of(model, features=replace(model.features, friction=True))
    assert sim_b.backend.flags[0]
    assert not np.array_equal(fa.q[-1], fa.q[0])              # the boxes did turn
    assert_same(fa, fb)
    fg, _ = frames_of(model, specialize=False)
    assert_same(fa, fg)


def test_frictionless_balls_through_the_friction_kernel():
    model = ball_pile()
    fa, _ = frames_of(model)
    fb, _ = frames_of(model, features=replace(model.features, friction=True, rotation=True))
    assert_same(fa, fb)


@pytest.mark.slow
def test_sleeping_kernel_with_sleeping_off_matches():
    model = ball_pile()
    assert model.sleep_steps == 0
    fa, _ = frames_of(model)
    fb, sim_b = frames_of(model, features=replace(model.features, sleeping=True))
    assert sim_b.backend.flags[2]
    assert_same(fa, fb)


def test_wall_kernel_without_walls_matches():
    # no plane, no gravity: the balls are thrown at one another
    model = ball_pile(plane=False, gravity=(0.0, 0.0, 0.0))
    assert not model.features.walls
    fa, sim = frames_of(model)
    assert sim.backend.flags[3] is False
    assert sim.stats.max_overlap > 0.0
    fb, _ = frames_of(model, features=replace(model.features, walls=True))
    assert_same(fa, fb)


def test_an_override_cannot_switch_a_used_feature_off():
    model = box_pile(mu=0.5)
    with pytest.raises(ValueError, match="friction"):
        Simulator(model, features=replace(model.features, friction=False))


def test_a_one_sphere_body_off_its_centre_of_mass_keeps_rotation():
    from dempipe.sim.kernels.layout import kernel_flags, scene_features

    model = ball_pile(n=2)
    off = replace(model, sphere_offset=model.sphere_offset + [0.001, 0.0, 0.0])
    assert not scene_features(model).rotation
    assert kernel_flags(scene_features(off))[1]


def test_each_variant_is_loaded_from_the_disk_cache_in_a_new_process():
    # the in-process runs above compiled (or loaded) the variants; a fresh
    # process must find every one of them on disk, not compile again
    code = (
        "import sys\n"
        f"sys.path[:0] = [{str(HERE)!r}, {str(HERE.parent)!r}]\n"
        "from dataclasses import replace\n"
        "from test_specialize import ball_pile\n"
        "from dempipe.sim.simulator import Simulator\n"
        "from dempipe.sim.kernels.cpu import stages as cpu\n"
        "m = ball_pile(n=9, n_frames=2)\n"
        "for f in (m.features, replace(m.features, rotation=True)):\n"
        "    Simulator(m, features=f).advance(m.initial_state())\n"
        "for flags, k in cpu._VARIANTS.items():\n"
        "    s = k.run_steps.stats\n"
        "    print(flags, sum(s.cache_hits.values()), sum(s.cache_misses.values()))\n"
    )
    frames_of(ball_pile(n=9, n_frames=2))      # make sure both are cached
    frames_of(ball_pile(n=9, n_frames=2),
              features=replace(ball_pile(n=9, n_frames=2).features, rotation=True))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=600, env=dict(os.environ, NUMBA_DISABLE_JIT="0",
                                                DEMPIPE_KERNELS="specialized"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 2, proc.stdout
    for line in lines:
        hits, misses = line.rsplit(" ", 2)[1:]
        assert (int(hits), int(misses)) == (1, 0), line
