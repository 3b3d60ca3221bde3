"""Restitution error against steps per contact, measured with the real simulator.

    python benchmarks/restitution_vs_dt.py

One ball thrown head-on onto a plane (no gravity during the contact, so the
rebound speed over the impact speed is exactly the restitution the material
asks for). The contact begins and ends anywhere in a step, so each setting is
run at 16 contact phases; printed: the mean and the worst relative error of e²,
and the cost (steps per contact). dt="auto" takes materials.STEPS_PER_CONTACT.
"""

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
from bodies import ball_set  # noqa: E402

from dempipe.sim.materials import Material  # noqa: E402
from dempipe.sim.builder import ModelBuilder  # noqa: E402
from dempipe.sim.simulator import Simulator  # noqa: E402

D = 0.01


def rebound(e, spc, phase, law="linear"):
    k = 1e4 if law == "linear" else None      # Hertz: auto K (its own units)
    b = ModelBuilder(D, gravity=(0, 0, 0))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=e, friction=0.0, stiffness=k))
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    b.add_bodies("ball", s, m, [[0, 0, D / 2 + 1e-9]], velocities=[[0, 0, -1.0]])
    model_probe = b.finalize(fps=100, n_frames=2, steps_per_contact=spc, contact_law=law)
    # start `phase` of a step before touching, so contacts begin anywhere in a step
    b2 = ModelBuilder(D, gravity=(0, 0, 0))
    s = b2.add_shape("ball", mesh, ss)
    m = b2.add_material(Material("m", density=1000, restitution=e, friction=0.0, stiffness=k))
    b2.add_plane([0, 0, 0], [0, 0, 1], m)
    b2.add_bodies("ball", s, m, [[0, 0, D / 2 + phase * model_probe.dt * 1.0]],
                  velocities=[[0, 0, -1.0]])
    model = b2.finalize(fps=100, n_frames=2, steps_per_contact=spc, contact_law=law)
    sim = Simulator(model)
    st = model.initial_state()
    sim.backend.step(st, int(3 * model.contact_time / model.dt) + 10)
    return st.body_P[0, 2] / model.body_mass[0]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--e", type=float, nargs="+", default=[0.1, 0.2, 0.5, 0.8, 0.9])
    ap.add_argument("--steps", type=int, nargs="+", default=[8, 10, 12, 16, 32])
    ap.add_argument("--law", default="linear", help="contact law (laws.LAWS)")
    a = ap.parse_args(argv)
    print("| e | steps per contact | mean error of e² | worst error of e² |")
    print("|---:|---:|---:|---:|")
    for e in a.e:
        for spc in a.steps:
            errs = [(rebound(e, spc, p, a.law) / e) ** 2 - 1
                    for p in np.linspace(0.03, 0.97, 16)]
            print(f"| {e} | {spc} | {np.mean(errs):+.1%} | {np.max(np.abs(errs)):.1%} |",
                  flush=True)


if __name__ == "__main__":
    main()
