"""Error against steps per contact, both contact laws: bounce, rolling, a settled pile.

    python benchmarks/steps_per_contact.py                  # 8 10 12 16 (+32 reference)
    python benchmarks/steps_per_contact.py --quick          # fewer balls, shorter

What dt="auto"'s steps per contact (laws.*.STEPS_PER_CONTACT) buys and costs, per
law, with the real simulator on the CPU target:

* bounce: one-sphere balls thrown at a plane without gravity, at PHASES contact
  phases spread over a step: mean and worst |(rebound/impact)² / e² − 1| for
  e = 0.1 (the hardest) and 0.5 (restitution_vs_dt.py has every e);
* rolling: accuracy.rolling_error, a ball launched sliding that ends rolling at
  5/7 v0 and then slows under rolling friction (closed form, accuracy.sliding_ball);
* pile: BALLS one-sphere balls (friction 0.5, rolling friction 0.01, e = 0.3)
  dropped from a loose jittered lattice into a box BOX diameters square, PILE_SECONDS simulated. Closed
  forms do not exist for a pile, so it is measured against itself and against the
  run at REFERENCE steps per contact: the height of the pile (95th percentile of
  the centres) and its spread, the fraction at rest and when 90 % came to rest
  (accuracy.pile_statistics), the deepest overlap left at the end (balls and walls,
  in diameters), the kinetic energy left, and the most the mechanical energy
  (kinetic + potential, frames) ever rose above its start (it must not: the only
  source is the drop). A pile is chaotic: two runs that differ in the last bit end
  with balls in other places, so its statistics, not its balls, are compared, and
  the last row of each law is the chaos floor: the reference again with one ball
  moved by NUDGE diameters before the drop.
* cost: steps per simulated second and the wall time of the pile (kernels
  compiled beforehand).

Flat-faced bodies of 3 × 3 spheres a face get their step from the flat-face bound
(materials.flat_face_critical_step), not from steps per contact, below about 14
steps per contact: for them this setting changes nothing, so the pile is of balls.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
from bodies import ball_set  # noqa: E402
from restitution_vs_dt import rebound  # noqa: E402

import numba  # noqa: E402

from dempipe.report import accuracy as acc  # noqa: E402
from dempipe.sim.builder import ModelBuilder  # noqa: E402
from dempipe.sim.materials import Material  # noqa: E402
from dempipe.sim.simulator import Simulator  # noqa: E402

D = 0.01
G = 9.81
PHASES = 8
REFERENCE = 32
NUDGE = 1e-9
BALLS = 343
PILE_SECONDS = 1.5
FPS = 60.0
BOX = 8


def material():
    return Material("m", density=2500, restitution=0.3, friction=0.5, rolling_friction=0.01)


def bounce(law, spc, e):
    errs = [(rebound(e, spc, p, law) / e) ** 2 - 1 for p in np.linspace(0.03, 0.97, PHASES)]
    return float(np.mean(errs)), float(np.max(np.abs(errs)))


def law_stiffness(law):
    """The auto stiffness the rolling case's ball gets in ``law`` (its own units)."""
    b, s, m = acc._ball_scene(material(), D, None)
    b.add_bodies("ball", s, m, [[0.0, 0.0, D]], velocities=[[1.0, 0.0, 0.0]])
    b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    return float(b.finalize(fps=100, n_frames=2, contact_law=law).pair_k[0, 0])


def ball_pile(law, spc, n, seconds, nudge=0.0):
    """n balls from a lattice 1.5 d apart, jittered by up to 0.15 d, into a box
    BOX d square; the first ball moved ``nudge`` [m] along x."""
    b = ModelBuilder(D, gravity=(0.0, 0.0, -G))
    ss, mesh = ball_set(D)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(material())
    side, pitch = 5, 1.5 * D
    k = np.arange(n)
    pos = np.stack([(k % side) * pitch, (k // side % side) * pitch,
                    (k // (side * side)) * pitch], 1)
    pos += [0.5 * (BOX * D - (side - 1) * pitch), 0.5 * (BOX * D - (side - 1) * pitch), D]
    pos[:, :2] += np.random.default_rng(7).uniform(-0.15 * D, 0.15 * D, (n, 2))
    pos[0, 0] += nudge
    b.add_bodies("balls", s, m, pos)
    b.add_box([0.0, 0.0, 0.0], [BOX * D, BOX * D, 1.0], material=m)
    return b.finalize(fps=FPS, n_frames=int(seconds * FPS) + 1, steps_per_contact=spc,
                      contact_law=law)


def deepest_overlap(model, x):
    """Largest overlap [m] of two balls, or of a ball and the box's floor and sides."""
    r = 0.5 * D
    gap = np.linalg.norm(x[:, None] - x[None], axis=2) + np.eye(len(x)) * 1e9
    walls = np.concatenate([x[:, 0] - r, BOX * D - x[:, 0] - r, x[:, 1] - r,
                            BOX * D - x[:, 1] - r, x[:, 2] - r])
    return max(float(D - gap.min()), float(-walls.min()), 0.0)


def pile(law, spc, n, seconds, nudge=0.0):
    model = ball_pile(law, spc, n, seconds, nudge)
    sim = Simulator(model)
    sim.backend.step(model.initial_state(), 2)              # compile outside the timing
    t0 = time.perf_counter()
    fr = sim.advance(model.initial_state())
    wall = time.perf_counter() - t0
    mass = model.body_mass[:model.n_bodies][None, :]
    inertia = 0.4 * mass * (0.5 * D) ** 2                    # a solid ball's, isotropic
    ke = 0.5 * (mass * (fr.v ** 2).sum(2) + inertia * (fr.w ** 2).sum(2)).sum(1)
    energy = ke + (mass * G * fr.x[:, :, 2]).sum(1)
    sizes = np.full(model.n_bodies, D)
    st = acc.pile_statistics(fr, model, sizes)
    return dict(model=model, stats=st, wall=wall, ke=float(ke[-1]),
                rise=float((energy - energy[0]).max()),
                overlap=deepest_overlap(model, fr.x[-1]) / D)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, nargs="+", default=[8, 10, 12, 16])
    ap.add_argument("--laws", nargs="+", default=["linear", "hertz"])
    ap.add_argument("--quick", action="store_true",
                    help=f"a pile of 98 balls for 0.5 s (else {BALLS} for {PILE_SECONDS} s)")
    a = ap.parse_args(argv)
    n, seconds = (98, 0.5) if a.quick else (BALLS, PILE_SECONDS)
    print(f"# steps per contact: {platform.machine()}, {os.cpu_count()} cores, numba "
          f"{numba.__version__}, {numba.get_num_threads()} threads; pile of {n} balls, "
          f"{seconds} s; bounce at {PHASES} phases; pile against {REFERENCE} steps per contact")
    print("| law | steps per contact | dt [µs] | e²: e = 0.1 mean / worst | e = 0.5 mean / worst "
          "| rolling | pile Δheight [d] | Δspread [d] | at rest | 90 % at rest by [s] "
          "| deepest overlap [d] | KE left [J] | energy rise [J] | pile wall [s] (ratio) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for law in a.laws:
        k = law_stiffness(law)
        ref = pile(law, REFERENCE, n, seconds)
        rs = ref["stats"]
        for spc in [*a.steps, REFERENCE, None]:
            if spc is None:                 # the chaos floor: nothing but the pile
                p, label, cases = pile(law, REFERENCE, n, seconds, NUDGE * D), \
                    f"{REFERENCE}, one ball moved {NUDGE:g} d", "| | | "
            else:
                b1, b5 = bounce(law, spc, 0.1), bounce(law, spc, 0.5)
                roll = acc.rolling_error(material(), D, k,
                                         acc.DtRule(steps_per_contact=spc, law=law))
                p = ref if spc == REFERENCE else pile(law, spc, n, seconds)
                label = str(spc)
                cases = f"| {b1[0]:+.1%} / {b1[1]:.1%} | {b5[0]:+.1%} / {b5[1]:.1%} | {roll:.1e} "
            st = p["stats"]
            print(f"| {law} | {label} | {p['model'].dt * 1e6:.1f} {cases}"
                  f"| {abs(st.height - rs.height) / D:.2f} | {abs(st.spread - rs.spread) / D:.2f} "
                  f"| {st.at_rest:.0%} | {st.settle_s:.2f} | {p['overlap']:.1e} "
                  f"| {p['ke']:.1e} | {p['rise']:.1e} "
                  f"| {p['wall']:.1f} ({p['wall'] / ref['wall']:.2f}) |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
