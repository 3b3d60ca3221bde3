"""How far a bake is from the truth: the measures behind `dempipe report`.

Three kinds of error, each a plain function of arrays (nothing here runs a sweep;
that is report.py):

geometry
    :func:`shape_geometry_error`: a sphere set against its mesh. Volume and inertia
    of the lattice cells against the exact mesh, and a two-sided Hausdorff estimate
    between the mesh surface and the *contact surface* of the sphere union (the part
    of the spheres' surface another sphere of the same diameter can touch).
motion
    :func:`motion_error` and :func:`pile_statistics`: a run's Frames against a
    reference run's. Per body at a short horizon (before chaos takes over), and, for
    piles, the statistics a viewer sees (height, centre of mass, spread, settle time,
    fraction at rest).
physics
    :func:`bounce_error`, :func:`rolling_error`, :func:`incline_rolling_error`,
    :func:`spin_drift`: small ModelBuilder scenes with closed-form answers (rebound
    apex e² h, rolling at 5/7 v0, a ball (or a cylinder on its side) of a sphere-set
    mode rolling down an incline at 5/7 (2/3) g sin θ, conserved |L| and energy of a torque-free spin), run at a given
    dt rule.

Lengths are in metres; every error is dimensionless unless its name says otherwise
(``_deg``, ``_s``).
"""

from __future__ import annotations

import math
import types
from dataclasses import dataclass

import numpy as np

from dempipe.mesh.shapes import build_shape
from dempipe.sim import laws
from dempipe.sim import materials as mat
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.materials import Material
from dempipe.sim.model import world_inertia
from dempipe.sim.simulator import Simulator, kinetic_energy
from dempipe.spheres.options import BuildOptions
from dempipe.spheres.sphere_set import SphereSet, build_sphere_set

#: A body is at rest when it moves less than this fraction of its size per frame
#: (translation, and rotation at its rim): a viewer cannot see the motion.
REST_FRACTION_PER_FRAME = 0.01
#: A pile has settled once this fraction of its bodies is at rest for good.
SETTLED_FRACTION = 0.9
#: Pile height is this percentile of the bodies' centre-of-mass heights (one body
#: balanced on top does not make the pile taller).
HEIGHT_PERCENTILE = 95.0


# --------------------------------------------------------------------------- geometry


















# --------------------------------------------------------------------------- motion


def body_sizes(model) -> np.ndarray:
    """(n_bodies,) each dynamic body's size: its mesh's longest bounding-box extent [m]."""
    per_shape = np.array([float((s.vertices.max(axis=0) - s.vertices.min(axis=0)).max())
                          for s in model.shapes])
    return per_shape[np.asarray(model.body_shape[:model.n_bodies])]


def first_contact_times(frames, model, tol: float = 1e-3) -> np.ndarray:
    """(n_bodies,) when each body first leaves free flight [s] (inf if it never does).

    In free flight symplectic Euler keeps v = v0 + g t to rounding, so a body has
    touched something once its velocity departs from that by more than ``tol``
    (1 mm/s plus ``tol`` of the ballistic speed).
    """
    t = frames.times
    ballistic = frames.v[0][None] + t[:, None, None] * np.asarray(model.gravity)[None, None]
    off = np.linalg.norm(frames.v - ballistic, axis=2) > tol * (
        1.0 + np.linalg.norm(ballistic, axis=2))
    touched = off.any(axis=0)
    first = np.where(touched, t[np.argmax(off, axis=0)], np.inf)
    return first


def quaternion_angle_deg(q, q_ref) -> np.ndarray:
    """Rotation angle between unit quaternions (…, 4), in degrees (q and −q agree)."""
    dot = np.abs(np.einsum("...i,...i->...", q, q_ref))
    return np.degrees(2.0 * np.arccos(np.clip(dot, 0.0, 1.0)))


@dataclass(frozen=True)
class MotionError:
    """A run's bodies against the reference run's at one frame.

    position : RMS over bodies of |x − x_ref| / body size
    orientation_deg : RMS over bodies of the angle between q and q_ref [degrees]
    time_s : the frame's time [s]
    """

    position: float
    orientation_deg: float
    time_s: float


def motion_error(frames, ref, sizes, frame: int) -> MotionError:
    """Per-body error of ``frames`` against ``ref`` (same bodies) at ``frame``."""
    f = min(frame, frames.n_frames - 1, ref.n_frames - 1)
    dx = np.linalg.norm(frames.x[f] - ref.x[f], axis=1) / sizes
    ang = quaternion_angle_deg(frames.q[f], ref.q[f])
    return MotionError(float(np.sqrt(np.mean(dx * dx))), float(np.sqrt(np.mean(ang * ang))),
                       float(ref.times[f]))


@dataclass(frozen=True)
class PileStatistics:
    """What a viewer sees of a pile at the last frame (and how it got there).

    height : HEIGHT_PERCENTILE-th percentile of the bodies' centre-of-mass height [m]
    com : (3,) centre of mass of all bodies [m]
    spread : RMS horizontal distance of the bodies from that centre [m]
    settle_s : first time from which SETTLED_FRACTION of the bodies stay at rest
        [s]; NaN when the pile has not settled by the last frame
    at_rest : fraction of the bodies at rest at the last frame
    """

    height: float
    com: np.ndarray
    spread: float
    settle_s: float
    at_rest: float


def rest_mask(frames, model, sizes) -> np.ndarray:
    """(F, B) bool: body b moves less than REST_FRACTION_PER_FRAME of its size per frame."""
    limit = REST_FRACTION_PER_FRAME * sizes * model.fps                    # [m/s]
    speed = np.linalg.norm(frames.v, axis=2)
    rim = np.linalg.norm(frames.w, axis=2) * 0.5 * sizes
    return (speed < limit) & (rim < limit)


def pile_statistics(frames, model, sizes) -> PileStatistics:
    """Pile statistics of a run (see :class:`PileStatistics`)."""
    g = np.asarray(model.gravity, dtype=np.float64)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, 1.0])
    x = frames.x[-1]
    mass = np.asarray(model.body_mass[:model.n_bodies])
    com = (mass[:, None] * x).sum(axis=0) / mass.sum()
    rel = x - com
    horiz = rel - np.outer(rel @ up, up)
    rest = rest_mask(frames, model, sizes)
    frac = rest.mean(axis=1)
    settled = frac >= SETTLED_FRACTION
    # the first frame after which the pile never again falls below the fraction
    if settled[-1]:
        last_unsettled = np.flatnonzero(~settled)
        first = last_unsettled[-1] + 1 if len(last_unsettled) else 0
        settle = float(frames.times[first])
    else:
        settle = math.nan
    return PileStatistics(height=float(np.percentile(x @ up, HEIGHT_PERCENTILE)), com=com,
                          spread=float(np.sqrt(np.mean(np.einsum("bi,bi->b", horiz, horiz)))),
                          settle_s=settle, at_rest=float(frac[-1]))


def pile_error(stats: PileStatistics, ref: PileStatistics, size: float) -> dict:
    """Pile statistics against the reference's: lengths in body sizes, settle time in
    seconds (NaN unless both settled), fraction at rest as a difference."""
    both = math.isfinite(stats.settle_s) and math.isfinite(ref.settle_s)
    return dict(
        pile_height=abs(stats.height - ref.height) / size,
        pile_com=float(np.linalg.norm(stats.com - ref.com)) / size,
        pile_spread=abs(stats.spread - ref.spread) / size,
        settle_s=abs(stats.settle_s - ref.settle_s) if both else math.nan,
        at_rest=abs(stats.at_rest - ref.at_rest),
    )


# --------------------------------------------------------------------------- physics


@dataclass(frozen=True)
class DtRule:
    """How a closed-form case picks its step, mirroring the run it stands for.

    steps_per_contact : dt = (its own contact time) / this, as dt="auto" does
    dt : a fixed step [s] instead (a scene that gives simulation.dt)
    law : the contact law of the run (laws.LAWS); a case's stiffness is that law's
    """

    steps_per_contact: float = mat.STEPS_PER_CONTACT
    dt: float | None = None
    law: str = laws.DEFAULT

    def finalize_args(self, fps: float) -> dict:
        if self.dt is None:
            return dict(dt="auto", steps_per_contact=self.steps_per_contact,
                        contact_law=self.law)
        spf = max(1, round(1.0 / (fps * self.dt)))
        return dict(dt=1.0 / (fps * spf), contact_law=self.law)


def _ball(diameter: float):
    """An exact solid ball as a one-sphere set (no mesh needed)."""
    V = math.pi / 6.0 * diameter ** 3
    ss = SphereSet(centers=np.zeros((1, 3)), diameter=diameter, volume=V, com=np.zeros(3),
                   inertia=np.eye(3) * 0.4 * V * (0.5 * diameter) ** 2, mesh_sha256="",
                   key=f"ball-{diameter!r}")
    h = 0.5 * diameter
    mesh = types.SimpleNamespace(vertices=np.array([[-h, -h, -h], [h, h, h], [h, -h, h]]),
                                 faces=np.array([[0, 1, 2]]))
    return ss, mesh


def _ball_scene(material, diameter: float, stiffness: float, gravity: float = 9.81):
    from dataclasses import replace


    b = ModelBuilder(diameter, gravity=(0.0, 0.0, -gravity))
    ss, mesh = _ball(diameter)
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(replace(material, stiffness=stiffness))
    return b, s, m


#: Drop height of the bounce case [sphere diameters]. The linear contact's restitution
#: does not depend on the impact speed, so a low drop (a short run) measures the
#: same error as a high one.
BOUNCE_HEIGHT = 4.0
#: Balls dropped side by side, their impacts spread evenly over one step: the
#: rebound error depends on where in a step the contact begins and ends, and the
#: mean over evenly spread phases is the error a pile sees on average.
BOUNCE_PHASES = 16


def bounce_error(material, diameter: float, stiffness: float, rule: DtRule) -> float:
    """Balls of the scene's material dropped onto a plane of it: the mean over
    BOUNCE_PHASES impact phases of |apex / (e² h) − 1| after the first bounce
    (the closed form: apex = e² h). NaN when e is too small to see a rebound."""
    e = material.restitution
    if e <= 0.05:
        return math.nan
    fps = 2000.0
    g = 9.81
    probe, s, m = _ball_scene(material, diameter, stiffness, g)
    probe.add_bodies("ball", s, m, [[0.0, 0.0, diameter]])
    probe.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    dt = probe.finalize(fps=fps, n_frames=2, **rule.finalize_args(fps)).dt
    t0 = math.sqrt(2.0 * BOUNCE_HEIGHT * diameter / g)
    t = t0 + dt * np.arange(BOUNCE_PHASES) / BOUNCE_PHASES
    h = 0.5 * g * t * t
    b, s, m = _ball_scene(material, diameter, stiffness, g)
    pos = np.stack([np.arange(len(h)) * 3.0 * diameter, np.zeros(len(h)), h + 0.5 * diameter], 1)
    b.add_bodies("balls", s, m, pos)
    b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    t_end = (1.0 + e) * t.max() * 1.3
    model = b.finalize(fps=fps, n_frames=int(t_end * fps) + 2, **rule.finalize_args(fps))
    fr = Simulator(model).advance(model.initial_state())
    errs = []
    for i in range(len(h)):
        # frames are coarser than a contact: find the bounce by the velocity turning up
        up = np.flatnonzero(fr.v[:, i, 2] > 0)
        if len(up) == 0:
            return math.nan
        apex = fr.x[up[0]:, i, 2].max() - 0.5 * diameter
        errs.append(abs(apex / (e * e * h[i]) - 1.0))
    return float(np.mean(errs))


def sliding_ball(v0: float, mu: float, mu_r: float, t: float, g: float = 9.81):
    """Speed [m/s] and distance [m] at time t [s] of a ball (I = 2/5 m r²) launched
    sliding at v0 without spin on a level plane of friction μ and rolling
    friction μ_r (physics.rolling_torque; μ_r < μ): it slides, slowing at μ g and
    spinning up at (5/2)(μ − μ_r) g / r, until it rolls at
    t_r = v0 / (g (μ + (5/2)(μ − μ_r))), then rolls slowing at (5/7) μ_r g until it
    stops. With μ_r = 0 it ends rolling at 5/7 v0."""
    t_r = v0 / (g * (mu + 2.5 * (mu - mu_r)))
    ts = min(t, t_r)
    v = v0 - mu * g * ts
    x = v0 * ts - 0.5 * mu * g * ts * ts
    if t > t_r:
        a = 5.0 / 7.0 * mu_r * g
        tt = t - t_r if a == 0.0 else min(t - t_r, v / a)
        x += v * tt - 0.5 * a * tt * tt
        v -= a * tt
    return v, x


def rolling_error(material, diameter: float, stiffness: float, rule: DtRule) -> float:
    """A ball launched sliding at v0 on a plane ends rolling at 5/7 v0 (I = 2/5 m r²),
    then slows under the material's rolling friction (:func:`sliding_ball`).

    Returns the larger of |v_end / v_closed − 1| and the error of the distance
    travelled against the closed form, relative to that distance. The end speed
    alone cannot show dt: the angular momentum about the contact point is conserved
    through the slide whatever the friction law, so it comes out exact but for the
    contact point's place (on the plane, r − δ from the centre with δ the resting
    overlap: 5/7 v0 less about 0.57 δ/r of it). NaN for a
    frictionless material.
    """
    mu = material.friction
    if mu <= 0:
        return math.nan
    b, s, m = _ball_scene(material, diameter, stiffness)
    v0 = math.sqrt(2.0 * 9.81 * BOUNCE_HEIGHT * diameter)
    mass = material.density * math.pi / 6.0 * diameter ** 3
    weight = mass * 9.81
    # start at the resting overlap: w / k (linear), (w / K)^(2/3) (Hertz)
    rest = laws.law(rule.law).rest_overlap(weight, stiffness)
    sink = min(rest, 0.1 * diameter)
    b.add_bodies("ball", s, m, [[0.0, 0.0, 0.5 * diameter - sink]], velocities=[[v0, 0, 0]])
    b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    fps = 500.0
    t_end = 3.0 * 2.0 * v0 / (7.0 * mu * 9.81) + 0.02        # three times the slide
    model = b.finalize(fps=fps, n_frames=int(t_end * fps) + 2, **rule.finalize_args(fps))
    fr = Simulator(model).advance(model.initial_state())
    v_end, travel = sliding_ball(v0, mu, min(material.rolling_friction, mu), fr.times[-1])
    speed_err = abs(fr.v[-1, 0, 0] / v_end - 1.0)
    return float(max(speed_err, abs((fr.x[-1, 0, 0] - fr.x[0, 0, 0]) / travel - 1.0)))


#: The incline case (:func:`incline_rolling_error`): a ball of INCLINE_BALL metres
#: across on a slope of INCLINE_DEGREES, its x(t) fitted from INCLINE_FIT_FROM
#: seconds (the 0.1 mm drop onto the slope has rung out) to INCLINE_SECONDS, by when
#: it rolls at about 1.2 m/s. A surface set loses more the faster it rolls: from about
#: √(g R cos θ) (0.7 m/s here) it hops from bump to bump of its envelope and each
#: landing loses what the restitution takes (docs/spheres.md, "Rolling"). A fit that
#: ends at 0.12 s (0.3 m/s) showed 0.06 % where one to 0.5 s shows 6 % (8 across,
#: e = 0.5, μ_r = 0).
INCLINE_BALL = 0.1
INCLINE_DEGREES = 20.0
INCLINE_FIT_FROM = 0.03
INCLINE_SECONDS = 0.5
#: The bodies the incline rolls, INCLINE_BALL across: (built-in shape, its parameters,
#: rotation about x [degrees] that lays it on the slope rolling along x, I / (m R²)
#: about the rolling axis). The cylinder is as long as it is across, on its side.
INCLINE_SHAPES = {
    "ball": ("sphere", {"diameter": INCLINE_BALL}, 0.0, 0.4),
    "cylinder": ("cylinder", {"diameter": INCLINE_BALL, "height": INCLINE_BALL}, 90.0, 0.5),
}


def incline_rolling_error(material, resolution: int, mode: str, rule: DtRule,
                          cache=None, shape: str = "ball",
                          spacing: float | None = None) -> float:
    """A round body (INCLINE_SHAPES: ``"ball"`` or a ``"cylinder"`` on its side) of
    ``resolution`` spheres across, built in sphere-set ``mode`` ("lattice" or
    "surface"; a surface set's ``spacing`` in diameters, None: the default), released on
    an incline (tilted gravity over a plane) in ``material``: |a / a_closed − 1| for its
    acceleration down the slope, fitted to x(t) (:func:`incline_run`).

    Unlike :func:`rolling_error` (one sphere, the contact law alone), this measures
    what the sphere set does to rolling: a lattice ball is a polyhedron that tips from
    facet to facet or stays on one (off by 0.34 at 4 across, 1.0 at 8: it does not
    roll), a surface set rolls within about 6 % at 8 and at 16 across at e = 0.5, less
    with a livelier material (its envelope's bumps make it hop: INCLINE_SECONDS).
    NaN for a frictionless material.
    """
    if material.friction <= 0:
        return math.nan
    run = incline_run(material, resolution, mode, rule, cache, shape, spacing)
    return abs(run.accel / run.closed - 1.0)


#: The slab a body rolls on with ``floor="body"`` (incline_run): long, wide and thick
#: enough [m] for the INCLINE_SECONDS of rolling from x = 0 (0.3 m at 5/7 g sin θ).
INCLINE_SLAB = (0.5, 0.16, 0.04)


def incline_run(material, resolution: int, mode: str, rule: DtRule, cache=None,
                shape: str = "ball", spacing: float | None = None,
                floor: str = "plane") -> types.SimpleNamespace:
    """The incline case of :func:`incline_rolling_error`, run: a namespace of ``accel``
    (fitted from INCLINE_FIT_FROM to INCLINE_SECONDS) and ``closed`` [m/s²], ``frames``,
    ``spheres`` (the set's count) and ``rest_z`` (the centre's height at release [m]).

    The closed form is rolling, g (sin θ − μ_r cos θ) / (1 + κ) with κ = I / (m R²)
    (a = 5/7 g sin θ for the ball, 2/3 g sin θ for the cylinder at μ_r = 0; μ_r the
    material's rolling friction), when the friction μ holds it
    (μ ≥ (κ tan θ + μ_r) / (1 + κ)), else sliding, g (sin θ − μ cos θ). The material's
    density, restitution and friction with automatic stiffness for the body's mass (a
    scene's own stiffness is for its bodies), dt by ``rule``.

    ``floor``: "plane", a wall (what the body's inscribed balls and rings meet), or
    "body", a static box of INCLINE_SLAB whose top face is the plane z = 0, made of
    spheres in the same mode and spacing: spheres against spheres, as a body rolls on
    another.
    """
    from dataclasses import replace

    import trimesh

    mu = material.friction
    name, params, tilt, kappa = INCLINE_SHAPES[shape]
    theta = math.radians(INCLINE_DEGREES)
    g = 9.81
    mesh = build_shape(name, **params)
    if tilt:
        mesh.apply_translation(-mesh.center_mass)
        mesh.apply_transform(trimesh.transformations.rotation_matrix(math.radians(tilt),
                                                                     [1.0, 0.0, 0.0]))
    d = INCLINE_BALL / float(resolution)
    options = BuildOptions(mode=mode) if spacing is None else BuildOptions(mode=mode,
                                                                           spacing=spacing)
    ss = build_sphere_set(mesh, d, name=f"incline-{shape}", cache=cache, options=options)
    b = ModelBuilder(d, gravity=(g * math.sin(theta), 0.0, -g * math.cos(theta)))
    s = b.add_shape(shape, mesh, ss)
    m = b.add_material(replace(material, name="incline", stiffness=None))
    # resting on the lower of its spheres and its mesh (a lattice's round parts meet the
    # plane through the mesh's inscribed tori: spheres/inscribed.py)
    low = max(float(-np.asarray(ss.centers)[:, 2].min()) + 0.5 * d,
              float(ss.com[2] - np.asarray(mesh.vertices)[:, 2].min()))
    top = 0.0
    if floor == "body":
        slab = trimesh.creation.box(extents=INCLINE_SLAB)
        slab.apply_translation([0.5 * INCLINE_SLAB[0] - 0.1, 0.0, -0.5 * INCLINE_SLAB[2]])
        slab_set = build_sphere_set(slab, d, name="incline-slab", cache=cache,
                                    options=options)
        # the slab's spheres reach up to r over its top face (a lattice's rows may end
        # short of it): the body is released onto them
        top = float((np.asarray(slab_set.centers) + slab_set.com)[:, 2].max()) + 0.5 * d
        b.add_static_mesh("slab", slab, slab_set, m)
    elif floor == "plane":
        b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    else:
        raise ValueError(f"floor must be 'plane' or 'body', got {floor!r}")
    b.add_bodies(shape, s, m, [[0.0, 0.0, top + low + 1e-3 * d]])
    fps = 400.0
    model = b.finalize(fps=fps, n_frames=int(INCLINE_SECONDS * fps) + 1, sleep=None,
                       **rule.finalize_args(fps))
    fr = Simulator(model).advance(model.initial_state())
    t = fr.times
    sel = t >= INCLINE_FIT_FROM
    a = 2.0 * float(np.polyfit(t[sel], fr.x[sel, 0, 0], 2)[0])
    mu_r = material.rolling_friction
    if mu >= (kappa * math.tan(theta) + mu_r) / (1.0 + kappa):
        # rolling, held back by the rolling friction's torque μ_r R m g cos θ
        closed = g * (math.sin(theta) - mu_r * math.cos(theta)) / (1.0 + kappa)
    else:
        closed = g * (math.sin(theta) - mu * math.cos(theta))
    return types.SimpleNamespace(accel=a, closed=closed, frames=fr, spheres=len(ss.centers),
                                 rest_z=top + low)


def spin_drift(shape, dt: float, seconds: float = 0.2) -> tuple[float, float]:
    """A shape (a ShapeInstance) tumbling torque-free at step ``dt``: the largest relative
    drift of |L| and of the kinetic energy. |L| is integrated directly (eq. 4) and
    must stay exact; the energy drift measures the orientation update at this dt.

    The spin, 4 rad/s about a skew axis scaled to rim speed 1 m/s at most, tumbles
    (the axis is not principal), so every term of the update is exercised.
    """
    ss = shape.sphere_set
    b = ModelBuilder(ss.diameter, gravity=(0.0, 0.0, 0.0))
    mesh = types.SimpleNamespace(vertices=np.asarray(shape.vertices) + np.asarray(ss.com),
                                 faces=shape.faces)
    s = b.add_shape(shape.name, mesh, ss)
    m = b.add_material(Material("spin", density=1000.0))
    radius = float(np.linalg.norm(np.asarray(ss.centers), axis=1).max() + ss.radius)
    w = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2]) * min(4.0, 1.0 / radius)
    b.add_bodies("spin", s, m, [[0.0, 0.0, 0.0]], angular_velocities=[w])
    spf = max(1, int(round(0.01 / dt)))
    fps = 1.0 / (dt * spf)
    model = b.finalize(fps=fps, n_frames=int(seconds * fps) + 1, dt=1.0 / (fps * spf))
    fr = Simulator(model).advance(model.initial_state())
    L = np.array([world_inertia(q, model.body_inv_inertia[0]) @ wv
                  for q, wv in zip(fr.q[:, 0], fr.w[:, 0])])
    Ln = np.linalg.norm(L, axis=1)
    ke = kinetic_energy(model, fr)
    return float(np.abs(Ln / Ln[0] - 1).max()), float(np.abs(ke / ke[0] - 1).max())
