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
    apex e² h, rolling at 5/7 v0, a ball of a sphere-set mode rolling down an incline
    at 5/7 g sin θ, conserved |L| and energy of a torque-free spin), run at a given
    dt rule.

Lengths are in metres; every error is dimensionless unless its name says otherwise
(``_deg``, ``_s``).
"""

from __future__ import annotations

import math
import types
from dataclasses import dataclass

import numpy as np

from . import laws
from . import materials as mat

#: Points sampled on the mesh surface (area-weighted, seeded) for the Hausdorff estimate.
MESH_SAMPLES = 2000
#: Directions sampled on each sphere (Fibonacci lattice) for the sphere-union surface;
#: neighbouring samples are ~0.11 d apart.
SPHERE_DIRECTIONS = 256
#: At most this many sphere-surface samples are measured against the mesh triangles.
SURFACE_SAMPLES = 2000
#: A body is at rest when it moves less than this fraction of its size per frame
#: (translation, and rotation at its rim): a viewer cannot see the motion.
REST_FRACTION_PER_FRAME = 0.01
#: A pile has settled once this fraction of its bodies is at rest for good.
SETTLED_FRACTION = 0.9
#: Pile height is this percentile of the bodies' centre-of-mass heights (one body
#: balanced on top does not make the pile taller).
HEIGHT_PERCENTILE = 95.0


# --------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class GeometryError:
    """One shape's sphere set against its mesh.

    spheres : sphere count
    volume : (N d³ − V) / V, the lattice cells against the mesh volume
    inertia : relative Frobenius error of the cells' inertia against the mesh's
    hausdorff : largest surface distance, either direction, / the shape's size
    mesh_to_spheres, spheres_to_mesh : the two one-sided parts of ``hausdorff``
    size : the shape's size, the longest extent of its bounding box [m]
    """

    spheres: int
    volume: float
    inertia: float
    hausdorff: float
    mesh_to_spheres: float
    spheres_to_mesh: float
    size: float


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (golden-angle spiral)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sample_surface(vertices, faces, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points on a triangle mesh, uniform by area (seeded, reproducible)."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    f = rng.choice(len(tri), size=n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1.0                      # fold the square onto the triangle
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[f]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def contact_surface(centers, diameter: float, n_dirs: int = SPHERE_DIRECTIONS) -> np.ndarray:
    """Points of the sphere union's surface that another sphere of diameter d can touch.

    Sphere sets are lattices of pitch d, so neighbouring spheres only touch: every
    sphere's whole surface belongs to the union, the buried ones included. What a
    contact sees is less: the point c + r n is touchable when a probe sphere at
    c + d n overlaps no other sphere. Only the 26 lattice neighbours can block it.
    Returns (P, 3) points [m].
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    d = float(diameter)
    dirs = fibonacci_directions(n_dirs)
    offs = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) != (0, 0, 0)], dtype=np.float64)
    # blocked[o, k]: a neighbour at lattice offset o stops a probe in direction k
    blocked = np.linalg.norm(dirs[None, :, :] - offs[:, None, :], axis=2) < 1.0 - 1e-9
    ijk = np.round((c - c.min(axis=0)) / d).astype(np.int64)
    occupied = {tuple(p) for p in ijk}
    has = np.array([[(p[0] + o[0], p[1] + o[1], p[2] + o[2]) in occupied for o in offs.astype(int)]
                    for p in ijk], dtype=bool)                               # (S, 26)
    free = ~(has.astype(np.int64) @ blocked.astype(np.int64)).astype(bool)  # (S, n_dirs)
    s, k = np.nonzero(free)
    return c[s] + 0.5 * d * dirs[k]


def point_mesh_distance(points, vertices, faces, chunk: int = 64) -> np.ndarray:
    """Unsigned distance from each point to a triangle mesh (exact) [m].

    For each triangle: the distance to its plane when the projection falls inside,
    else to the nearest of its three edges. Points go in chunks of ``chunk`` (pass
    them spatially ordered); a chunk only visits the triangles whose bounding box
    lies within its points' distance bound (the nearest vertex or edge midpoint).
    """
    p_all = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    verts = np.asarray(vertices, dtype=np.float64)
    tri_all = verts[np.asarray(faces, dtype=np.int64)]
    tri_lo, tri_hi = tri_all.min(axis=1), tri_all.max(axis=1)
    anchors = np.concatenate([verts, 0.5 * (tri_all + np.roll(tri_all, 1, axis=1)).reshape(-1, 3)])
    bound = _nearest_distance(p_all, anchors)
    out = np.empty(len(p_all))
    for s in range(0, len(p_all), chunk):
        p = p_all[s:s + chunk]
        r = bound[s:s + chunk].max() * (1.0 + 1e-9)
        near = np.all((tri_lo <= p.max(axis=0) + r) & (tri_hi >= p.min(axis=0) - r), axis=1)
        out[s:s + chunk] = _points_triangles(p, tri_all[near])
    return out


def _points_triangles(p, tri) -> np.ndarray:
    """Distance from each point of p (P, 3) to the nearest of the triangles (F, 3, 3)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, bc = b - a, c - a, c - b
    n = np.cross(ab, ac)
    nn = np.einsum("fi,fi->f", n, n)
    good = nn > 1e-30
    n_unit = np.where(good[:, None], n / np.sqrt(np.where(good, nn, 1.0))[:, None], 0.0)
    d00 = np.einsum("fi,fi->f", ab, ab)
    d01 = np.einsum("fi,fi->f", ab, ac)
    d11 = np.einsum("fi,fi->f", ac, ac)
    den = np.where(good, d00 * d11 - d01 * d01, 1.0)

    def seg(ap, e):
        ee = np.einsum("fi,fi->f", e, e)
        t = np.clip(np.einsum("pfi,fi->pf", ap, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
        return np.linalg.norm(ap - t[..., None] * e, axis=2)

    ap = p[:, None, :] - a[None]
    d20 = np.einsum("pfi,fi->pf", ap, ab)
    d21 = np.einsum("pfi,fi->pf", ap, ac)
    v = (d11 * d20 - d01 * d21) / den       # barycentric coordinates of the projection
    w = (d00 * d21 - d01 * d20) / den
    inside = good & (v >= 0) & (w >= 0) & (v + w <= 1)
    plane = np.abs(np.einsum("pfi,fi->pf", ap, n_unit))
    edge = np.minimum(np.minimum(seg(ap, ab), seg(ap, ac)), seg(p[:, None, :] - b[None], bc))
    return np.where(inside, plane, edge).min(axis=1)


def _nearest_distance(p, q, chunk: int = 256) -> np.ndarray:
    """Distance from each point of p to the nearest point of q (brute force)."""
    out = np.empty(len(p))
    qq = np.einsum("ij,ij->i", q, q)
    for s in range(0, len(p), chunk):
        x = p[s:s + chunk]
        d2 = np.einsum("ij,ij->i", x, x)[:, None] - 2.0 * x @ q.T + qq[None, :]
        out[s:s + chunk] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
    return out


def shape_geometry_error(sphere_set, vertices, faces, *, seed: int = 0) -> GeometryError:
    """Errors of ``sphere_set`` against its mesh (``vertices`` in the body frame, i.e.
    mesh coordinates minus the centre of mass, as ``ShapeInstance.vertices``).

    Hausdorff estimate, both directions, as a fraction of the shape's size:
      mesh → spheres: MESH_SAMPLES area-weighted points on the mesh; a point outside
        every sphere is min |p − c| − r from the union (exact); one inside is taken
        to the nearest sample of the contact surface (:func:`contact_surface`).
      spheres → mesh: up to SURFACE_SAMPLES samples of the contact surface, exact
        distance to the mesh triangles.
    Sampling makes both a slight underestimate of a true maximum, and the inside
    points' distance an overestimate of at most half the sample spacing (~0.06 d).
    """
    verts = np.asarray(vertices, dtype=np.float64)
    c = np.asarray(sphere_set.centers, dtype=np.float64).reshape(-1, 3)
    d = float(sphere_set.diameter)
    size = float((verts.max(axis=0) - verts.min(axis=0)).max())
    surf = contact_surface(c, d)
    pts = sample_surface(verts, faces, MESH_SAMPLES, seed)
    outside = _nearest_distance(pts, c) - 0.5 * d
    to_surface = _nearest_distance(pts, surf) if len(surf) else np.full(len(pts), np.inf)
    a = np.where(outside > 0.0, outside, to_surface)
    rng = np.random.default_rng(seed + 1)
    if len(surf) > SURFACE_SAMPLES:     # sorted back: chunks stay spatially compact
        surf = surf[np.sort(rng.choice(len(surf), SURFACE_SAMPLES, replace=False))]
    pick = surf
    b = point_mesh_distance(pick, verts, faces) if len(pick) else np.zeros(1)
    return GeometryError(
        spheres=int(c.shape[0]), volume=float(sphere_set.sphere_volume_error),
        inertia=float(sphere_set.inertia_error), hausdorff=float(max(a.max(), b.max()) / size),
        mesh_to_spheres=float(a.max() / size), spheres_to_mesh=float(b.max() / size), size=size)


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
    from .spheres import SphereSet

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

    from .builder import ModelBuilder

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
    from .simulator import Simulator

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
    through the slide whatever the friction law, so it comes out exact. NaN for a
    frictionless material.
    """
    from .simulator import Simulator

    mu = material.friction
    if mu <= 0:
        return math.nan
    b, s, m = _ball_scene(material, diameter, stiffness)
    v0 = math.sqrt(2.0 * 9.81 * BOUNCE_HEIGHT * diameter)
    mass = material.density * math.pi / 6.0 * diameter ** 3
    weight = mass * 9.81
    # start at the resting overlap: w / k (linear), (w / K)^(2/3) (Hertz)
    rest = (weight / stiffness) ** (2.0 / 3.0) if rule.law == "hertz" else weight / stiffness
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
#: seconds (the 0.1 mm drop onto the slope has rung out) to INCLINE_SECONDS.
INCLINE_BALL = 0.1
INCLINE_DEGREES = 20.0
INCLINE_FIT_FROM = 0.03
INCLINE_SECONDS = 0.12


def incline_rolling_error(material, resolution: int, mode: str, rule: DtRule,
                          cache=None) -> float:
    """A ball of ``resolution`` spheres across, built in sphere-set ``mode``
    ("lattice" or "surface"), released on an incline (tilted gravity over a plane)
    in ``material``: |a / a_closed − 1| for its acceleration down the slope, fitted
    to x(t). The closed form is rolling, 5/7 g (sin θ − μ_r cos θ) (I = 2/5 m r², μ_r
    the material's rolling friction), when the friction holds it
    (μ ≥ 2/7 tan θ + 5/7 μ_r), else sliding, g (sin θ − μ cos θ).

    Unlike :func:`rolling_error` (one sphere, the contact law alone), this measures
    what the sphere set does to rolling: a lattice ball is a polyhedron that tips from
    facet to facet (about 0.2–0.5 of the closed form at 8 across), a surface set rolls
    within a few per cent (docs/spheres.md, "Rolling"). The material's density,
    restitution and friction with automatic stiffness for the ball's mass (a scene's
    own stiffness is for its bodies), dt by ``rule``. NaN for a frictionless material.
    """
    from dataclasses import replace

    from .builder import ModelBuilder
    from .shapes import build_shape
    from .simulator import Simulator
    from .spheres import BuildOptions, build_sphere_set

    mu = material.friction
    if mu <= 0:
        return math.nan
    theta = math.radians(INCLINE_DEGREES)
    g = 9.81
    mesh = build_shape("sphere", diameter=INCLINE_BALL)
    d = INCLINE_BALL / float(resolution)
    ss = build_sphere_set(mesh, d, name="incline-ball", cache=cache,
                          options=BuildOptions(mode=mode))
    b = ModelBuilder(d, gravity=(g * math.sin(theta), 0.0, -g * math.cos(theta)))
    s = b.add_shape("ball", mesh, ss)
    m = b.add_material(replace(material, name="incline", stiffness=None))
    low = float(-np.asarray(ss.centers)[:, 2].min()) + 0.5 * d
    b.add_bodies("ball", s, m, [[0.0, 0.0, low + 1e-3 * d]])
    b.add_plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], m)
    fps = 400.0
    model = b.finalize(fps=fps, n_frames=int(INCLINE_SECONDS * fps) + 1, sleep=None,
                       **rule.finalize_args(fps))
    fr = Simulator(model).advance(model.initial_state())
    t = fr.times
    sel = t >= INCLINE_FIT_FROM
    a = 2.0 * float(np.polyfit(t[sel], fr.x[sel, 0, 0], 2)[0])
    mu_r = material.rolling_friction
    if mu >= 2.0 / 7.0 * math.tan(theta) + 5.0 / 7.0 * mu_r:
        # rolling, held back by the rolling friction's torque μ_r r m g cos θ
        closed = 5.0 / 7.0 * g * (math.sin(theta) - mu_r * math.cos(theta))
    else:
        closed = g * (math.sin(theta) - mu * math.cos(theta))
    return abs(a / closed - 1.0)


def spin_drift(shape, dt: float, seconds: float = 0.2) -> tuple[float, float]:
    """A shape (a ShapeInstance) tumbling torque-free at step ``dt``: the largest relative
    drift of |L| and of the kinetic energy. |L| is integrated directly (eq. 4) and
    must stay exact; the energy drift measures the orientation update at this dt.

    The spin, 4 rad/s about a skew axis scaled to rim speed 1 m/s at most, tumbles
    (the axis is not principal), so every term of the update is exercised.
    """
    from .materials import Material
    from .builder import ModelBuilder
    from .model import _world_inertia
    from .simulator import Simulator, kinetic_energy

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
    L = np.array([_world_inertia(q, model.body_inv_inertia[0]) @ wv
                  for q, wv in zip(fr.q[:, 0], fr.w[:, 0])])
    Ln = np.linalg.norm(L, axis=1)
    ke = kinetic_energy(model, fr)
    return float(np.abs(Ln / Ln[0] - 1).max()), float(np.abs(ke / ke[0] - 1).max())
