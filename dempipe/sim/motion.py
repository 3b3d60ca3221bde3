"""Prescribed motion: where a kinematic body or an animated collider is at time t.

A ``Motion`` moves an *anchor frame* (position P, orientation Q, world frame)
through time, by constant rates or by keyframes. What it moves is fixed in that
frame: a body's centre of mass sits at c_a with orientation q_a in the anchor
frame, so at time t

    x(t) = P(t) + Q(t) c_a,     q(t) = Q(t) q_a,
    v(t) = V(t) + W(t) × (x(t) − P(t)),     w(t) = W(t),

and any point y fixed to it moves at the surface velocity V + W × (y − P). A
wall (plane, box face) is given in its anchor frame the same way.

The anchor by form:

- **Rates** (``velocity`` v [m/s], ``angular_velocity`` ω [rad/s], ``pivot`` c
  [m], world frame): P(t) = c + v t, Q(t) = exp(ω t) (a rotation by |ω| t about
  ω/|ω|), V = v, W = ω. At t = 0 the anchor is (c, identity). A conveyor belt is a
  plane with a velocity along itself; a turntable a mesh with ω about its axis.
- **Keys** ((tᵢ, Pᵢ, Qᵢ), tᵢ increasing): the anchor's pose at the key times,
  held before the first and after the last (V = W = 0 there).
  ``interpolation = "linear"``: P linear, Q by slerp (constant V and W over a
  segment: what a DCC's linear keys give). ``"smooth"``: C¹ — P by a cubic Hermite
  with Catmull-Rom tangents, Q by a cubic Hermite of the rotation vector r(s)
  of Q(s) Qᵢ⁻¹, with the keys' angular velocities as tangents (mapped through the
  inverse left Jacobian of SO(3) at the segment's end, so W is continuous at the
  keys); the first and last key have zero velocity, so holding them stays C¹.

The functions below are plain (math only, no numpy): both targets compile them
(``kernels/compile.py``), and ``Motion.anchor`` calls the same code on the host,
so the written pose of a kinematic body equals its key at key times to float
precision. Times are the simulation's [s] (frame f is at (f − first) / fps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dempipe.sim.physics import chord_velocity, quat_rotate, quat_rotate_inv

#: Motion kinds in the packed arrays.
RATES, LINEAR, SMOOTH = 0, 1, 2
INTERPOLATIONS = {"linear": LINEAR, "smooth": SMOOTH}


# ----------------------------------------------------------- formulas (both targets)


def qmul(aw, ax, ay, az, bw, bx, by, bz):
    """Quaternion product a b (w, x, y, z)."""
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def qexp(rx, ry, rz):
    """Unit quaternion of the rotation vector r [rad] (angle |r| about r/|r|)."""
    th = math.sqrt(rx * rx + ry * ry + rz * rz)
    if th < 1e-12:
        # sin(th/2)/th = 1/2 - th²/48 + ...: exact to float64 below 1e-6
        s = 0.5 - th * th / 48.0
        return math.cos(0.5 * th), rx * s, ry * s, rz * s
    s = math.sin(0.5 * th) / th
    return math.cos(0.5 * th), rx * s, ry * s, rz * s


def qlog(qw, qx, qy, qz):
    """Rotation vector [rad] of the unit quaternion q, the shorter way round
    (|r| ≤ π: q and −q give the same r)."""
    if qw < 0.0:
        qw, qx, qy, qz = -qw, -qx, -qy, -qz
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    if n < 1e-12:
        return 2.0 * qx, 2.0 * qy, 2.0 * qz
    th = 2.0 * math.atan2(n, qw)
    s = th / n
    return qx * s, qy * s, qz * s


def jac_left(rx, ry, rz, ux, uy, uz):
    """J_l(r) u: the world-frame angular velocity of exp(r(s)) Q₀ when r moves at
    ṙ = u (J_l = I + (1 − cos θ)/θ² [r]× + (θ − sin θ)/θ³ [r]×², θ = |r|)."""
    th2 = rx * rx + ry * ry + rz * rz
    if th2 < 1e-12:
        a = 0.5 - th2 / 24.0
        b = 1.0 / 6.0 - th2 / 120.0
    else:
        th = math.sqrt(th2)
        a = (1.0 - math.cos(th)) / th2
        b = (th - math.sin(th)) / (th2 * th)
    cx = ry * uz - rz * uy          # r × u
    cy = rz * ux - rx * uz
    cz = rx * uy - ry * ux
    ccx = ry * cz - rz * cy         # r × (r × u)
    ccy = rz * cx - rx * cz
    ccz = rx * cy - ry * cx
    return ux + a * cx + b * ccx, uy + a * cy + b * ccy, uz + a * cz + b * ccz


def jac_left_inv(rx, ry, rz, wx, wy, wz):
    """J_l(r)⁻¹ w: the ṙ that gives the angular velocity w at r
    (J_l⁻¹ = I − ½ [r]× + (1/θ² − (1 + cos θ)/(2 θ sin θ)) [r]×²)."""
    th2 = rx * rx + ry * ry + rz * rz
    if th2 < 1e-12:
        c = 1.0 / 12.0 + th2 / 720.0
    else:
        th = math.sqrt(th2)
        c = 1.0 / th2 - (1.0 + math.cos(th)) / (2.0 * th * math.sin(th))
    cx = ry * wz - rz * wy
    cy = rz * wx - rx * wz
    cz = rx * wy - ry * wx
    ccx = ry * cz - rz * cy
    ccy = rz * cx - rx * cz
    ccz = rx * cy - ry * cx
    return wx - 0.5 * cx + c * ccx, wy - 0.5 * cy + c * ccy, wz - 0.5 * cz + c * ccz


def key_angular_velocity(k, k0, k1, key_t, key_q):
    """Smooth keys: the angular velocity at key k [rad/s], world frame: the rotation
    from key k−1 to key k+1 over their time apart (Catmull-Rom); 0 at the first
    and last key (held there)."""
    if k <= k0 or k >= k1 - 1:
        return 0.0, 0.0, 0.0
    aw, ax, ay, az = key_q[k - 1, 0], key_q[k - 1, 1], key_q[k - 1, 2], key_q[k - 1, 3]
    bw, bx, by, bz = key_q[k + 1, 0], key_q[k + 1, 1], key_q[k + 1, 2], key_q[k + 1, 3]
    dw, dx, dy, dz = qmul(bw, bx, by, bz, aw, -ax, -ay, -az)
    rx, ry, rz = qlog(dw, dx, dy, dz)
    h = key_t[k + 1] - key_t[k - 1]
    return rx / h, ry / h, rz / h


def key_velocity(k, k0, k1, key_t, key_p, axis):
    """Smooth keys: the velocity at key k along ``axis`` [m/s] (Catmull-Rom); 0 at
    the first and last key."""
    if k <= k0 or k >= k1 - 1:
        return 0.0
    return (key_p[k + 1, axis] - key_p[k - 1, axis]) / (key_t[k + 1] - key_t[k - 1])


def anchor_state(t, kind, v, w, pivot, key_t, key_p, key_q, k0, k1):
    """The anchor frame of one motion at time t [s]: (Px, Py, Pz, Qw, Qx, Qy, Qz,
    Vx, Vy, Vz, Wx, Wy, Wz) — position [m], orientation, velocity [m/s], angular
    velocity [rad/s], world frame. ``v``, ``w``, ``pivot``: (3,) rates (kind
    RATES); keys k0..k1-1 of ``key_t`` (K,), ``key_p`` (K, 3), ``key_q`` (K, 4)
    (kinds LINEAR, SMOOTH)."""
    if kind == RATES:
        qw, qx, qy, qz = qexp(w[0] * t, w[1] * t, w[2] * t)
        return (pivot[0] + v[0] * t, pivot[1] + v[1] * t, pivot[2] + v[2] * t,
                qw, qx, qy, qz, v[0], v[1], v[2], w[0], w[1], w[2])
    if t <= key_t[k0] or k1 - k0 == 1:
        k = k0 if t <= key_t[k0] else k1 - 1
        return (key_p[k, 0], key_p[k, 1], key_p[k, 2],
                key_q[k, 0], key_q[k, 1], key_q[k, 2], key_q[k, 3],
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if t >= key_t[k1 - 1]:
        k = k1 - 1
        return (key_p[k, 0], key_p[k, 1], key_p[k, 2],
                key_q[k, 0], key_q[k, 1], key_q[k, 2], key_q[k, 3],
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    a = k0
    while key_t[a + 1] <= t:        # a few keys: a linear search
        a += 1
    b = a + 1
    h = key_t[b] - key_t[a]
    s = (t - key_t[a]) / h
    aw, ax, ay, az = key_q[a, 0], key_q[a, 1], key_q[a, 2], key_q[a, 3]
    bw, bx, by, bz = key_q[b, 0], key_q[b, 1], key_q[b, 2], key_q[b, 3]
    dw, dx, dy, dz = qmul(bw, bx, by, bz, aw, -ax, -ay, -az)        # Q_b Q_a⁻¹
    r1x, r1y, r1z = qlog(dw, dx, dy, dz)
    if kind == LINEAR:
        px = key_p[a, 0] + s * (key_p[b, 0] - key_p[a, 0])
        py = key_p[a, 1] + s * (key_p[b, 1] - key_p[a, 1])
        pz = key_p[a, 2] + s * (key_p[b, 2] - key_p[a, 2])
        vx = (key_p[b, 0] - key_p[a, 0]) / h
        vy = (key_p[b, 1] - key_p[a, 1]) / h
        vz = (key_p[b, 2] - key_p[a, 2]) / h
        ew, ex, ey, ez = qexp(s * r1x, s * r1y, s * r1z)
        qw, qx, qy, qz = qmul(ew, ex, ey, ez, aw, ax, ay, az)
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        return (px, py, pz, qw / n, qx / n, qy / n, qz / n, vx, vy, vz,
                r1x / h, r1y / h, r1z / h)
    # smooth: cubic Hermite in s, tangents scaled by h (d/dt = d/ds / h)
    s2 = s * s
    s3 = s2 * s
    h00 = 2.0 * s3 - 3.0 * s2 + 1.0
    h10 = s3 - 2.0 * s2 + s
    h01 = -2.0 * s3 + 3.0 * s2
    h11 = s3 - s2
    d00 = (6.0 * s2 - 6.0 * s) / h
    d10 = 3.0 * s2 - 4.0 * s + 1.0
    d01 = (-6.0 * s2 + 6.0 * s) / h
    d11 = 3.0 * s2 - 2.0 * s
    px = h00 * key_p[a, 0] + h10 * h * key_velocity(a, k0, k1, key_t, key_p, 0) + \
        h01 * key_p[b, 0] + h11 * h * key_velocity(b, k0, k1, key_t, key_p, 0)
    py = h00 * key_p[a, 1] + h10 * h * key_velocity(a, k0, k1, key_t, key_p, 1) + \
        h01 * key_p[b, 1] + h11 * h * key_velocity(b, k0, k1, key_t, key_p, 1)
    pz = h00 * key_p[a, 2] + h10 * h * key_velocity(a, k0, k1, key_t, key_p, 2) + \
        h01 * key_p[b, 2] + h11 * h * key_velocity(b, k0, k1, key_t, key_p, 2)
    vx = d00 * key_p[a, 0] + d10 * key_velocity(a, k0, k1, key_t, key_p, 0) + \
        d01 * key_p[b, 0] + d11 * key_velocity(b, k0, k1, key_t, key_p, 0)
    vy = d00 * key_p[a, 1] + d10 * key_velocity(a, k0, k1, key_t, key_p, 1) + \
        d01 * key_p[b, 1] + d11 * key_velocity(b, k0, k1, key_t, key_p, 1)
    vz = d00 * key_p[a, 2] + d10 * key_velocity(a, k0, k1, key_t, key_p, 2) + \
        d01 * key_p[b, 2] + d11 * key_velocity(b, k0, k1, key_t, key_p, 2)
    # rotation vector r(s) of Q(s) Q_a⁻¹: r(0) = 0, r(1) = r1, ṙ(0) = W_a,
    # ṙ(1) = J_l(r1)⁻¹ W_b (so that W(1) = W_b)
    wax, way, waz = key_angular_velocity(a, k0, k1, key_t, key_q)
    wbx, wby, wbz = key_angular_velocity(b, k0, k1, key_t, key_q)
    ubx, uby, ubz = jac_left_inv(r1x, r1y, r1z, wbx, wby, wbz)
    rx = h10 * h * wax + h01 * r1x + h11 * h * ubx
    ry = h10 * h * way + h01 * r1y + h11 * h * uby
    rz = h10 * h * waz + h01 * r1z + h11 * h * ubz
    dx = d10 * wax + d01 * r1x + d11 * ubx
    dy = d10 * way + d01 * r1y + d11 * uby
    dz = d10 * waz + d01 * r1z + d11 * ubz
    wx, wy, wz = jac_left(rx, ry, rz, dx, dy, dz)
    ew, ex, ey, ez = qexp(rx, ry, rz)
    qw, qx, qy, qz = qmul(ew, ex, ey, ez, aw, ax, ay, az)
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return px, py, pz, qw / n, qx / n, qy / n, qz / n, vx, vy, vz, wx, wy, wz


def carried_state(Px, Py, Pz, Qw, Qx, Qy, Qz, Vx, Vy, Vz, Wx, Wy, Wz,
                  cx, cy, cz, aw, ax, ay, az):
    """The pose and velocity of a body fixed at (c, a) in an anchor frame (P, Q, V,
    W): (x, y, z, qw, qx, qy, qz, vx, vy, vz) [m, 1, m/s], world frame."""
    rx, ry, rz = quat_rotate(Qw, Qx, Qy, Qz, cx, cy, cz)
    qw, qx, qy, qz = qmul(Qw, Qx, Qy, Qz, aw, ax, ay, az)
    return (Px + rx, Py + ry, Pz + rz, qw, qx, qy, qz,
            Vx + Wy * rz - Wz * ry, Vy + Wz * rx - Wx * rz, Vz + Wx * ry - Wy * rx)


def anchor_local(motion_now, m, x, y, z):
    """The world point (x, y, z) [m] in the frame of anchor m: Q⁻¹ (x − P).
    motion_now (M, 14): each anchor's P, Q, V, W and whether it moves (stage_motion)."""
    return quat_rotate_inv(motion_now[m, 3], motion_now[m, 4], motion_now[m, 5],
                           motion_now[m, 6], x - motion_now[m, 0], y - motion_now[m, 1],
                           z - motion_now[m, 2])


def anchor_surface(motion_now, m, nx, ny, nz, x, y, z, dist, h):
    """A moving wall at a sphere: its normal (nx, ny, nz), given in anchor m's frame,
    in the world, and the surface velocity at p, the sphere's centre (x, y, z) moved
    ``dist`` [m] along the normal onto the surface: V + W × (p − P) [m/s] as the
    chord of the step h [s] (physics.chord_velocity)."""
    wnx, wny, wnz = quat_rotate(motion_now[m, 3], motion_now[m, 4], motion_now[m, 5],
                                motion_now[m, 6], nx, ny, nz)
    vx, vy, vz = chord_velocity(
        motion_now[m, 7], motion_now[m, 8], motion_now[m, 9], motion_now[m, 10],
        motion_now[m, 11], motion_now[m, 12], x - wnx * dist - motion_now[m, 0],
        y - wny * dist - motion_now[m, 1], z - wnz * dist - motion_now[m, 2], h)
    return wnx, wny, wnz, vx, vy, vz


#: The functions above in dependency order, for kernels/compile.py (which compiles
#: them after physics.py's: quat_rotate and quat_rotate_inv are physics.py's).
FORMULAS = ("qmul", "qexp", "qlog", "jac_left", "jac_left_inv", "key_angular_velocity",
            "key_velocity", "anchor_state", "carried_state", "anchor_local", "anchor_surface")


# ----------------------------------------------------------------------- host side


@dataclass(frozen=True)
class Key:
    """One keyframe: the anchor's pose at ``time`` [s]: ``position`` [m] and
    ``rotation`` (w, x, y, z, unit), world frame."""

    time: float
    position: tuple
    rotation: tuple = (1.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Motion:
    """A prescribed motion of an anchor frame (see the module doc).

    velocity [m/s], angular_velocity [rad/s], pivot [m] (world frame): the rates
    form; pivot None means the owner's reference point (a collider's position or
    point, a body group's mesh origin), filled in by the model builder.
    keys: the keyed form (times strictly increasing; rates must then be zero);
    interpolation: "linear" or "smooth".
    """

    velocity: tuple = (0.0, 0.0, 0.0)
    angular_velocity: tuple = (0.0, 0.0, 0.0)
    pivot: tuple | None = None
    keys: tuple = ()
    interpolation: str = "linear"

    def __post_init__(self):
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"Motion.interpolation: {self.interpolation!r}, expected one of "
                             f"{sorted(INTERPOLATIONS)}")
        if self.keys:
            if any(x != 0.0 for x in tuple(self.velocity) + tuple(self.angular_velocity)):
                raise ValueError("Motion: give keys or rates (velocity, angular_velocity), "
                                 "not both")
            ts = [k.time for k in self.keys]
            if any(b <= a for a, b in zip(ts, ts[1:])):
                raise ValueError("Motion.keys: times must be strictly increasing")
            for k in self.keys:
                if abs(math.sqrt(sum(c * c for c in k.rotation)) - 1.0) > 1e-6:
                    raise ValueError(f"Motion.keys: the rotation at t = {k.time:g} is not a "
                                     f"unit quaternion")

    @property
    def keyed(self) -> bool:
        return bool(self.keys)

    @property
    def kind(self) -> int:
        return INTERPOLATIONS[self.interpolation] if self.keyed else RATES

    def with_pivot(self, pivot) -> "Motion":
        """This motion with ``pivot`` filled in where none was given."""
        if self.pivot is not None or self.keyed:
            return self
        return Motion(self.velocity, self.angular_velocity, tuple(float(c) for c in pivot),
                      self.keys, self.interpolation)

    def rest_anchor(self):
        """The anchor's pose at t = 0, ((3,), (4,)): what an owner's authored pose is
        measured against (rates: (pivot, identity); keys: the pose at t = 0)."""
        a = self.anchor(0.0)
        return a[0], a[1]

    def max_speed(self, offsets=None, t0: float = 0.0, t1: float | None = None,
                  samples: int = 256) -> float:
        """Largest speed of the points ``offsets`` ((N, 3) [m], in the anchor frame:
        the points of what it carries, relative to its anchor) [m/s]:
        max |V + W × Q r|. Rates: |v| + max |ω × r| (a rotation about ω keeps each
        point's distance to the axis; exact when v is along ω or zero). Keys:
        sampled over [t0, t1] and at the keys' segment midpoints."""
        r = np.zeros((1, 3)) if offsets is None else np.asarray(offsets, float).reshape(-1, 3)
        if not self.keyed:
            w = np.asarray(self.angular_velocity, dtype=np.float64)
            return float(np.linalg.norm(self.velocity)
                         + np.linalg.norm(np.cross(w, r), axis=1).max())
        ts = [k.time for k in self.keys]
        lo = ts[0] if t1 is None else max(ts[0], t0)
        hi = ts[-1] if t1 is None else min(ts[-1], t1)
        grid = list(np.linspace(lo, hi, samples)) if hi > lo else []
        grid += [0.5 * (a + b) for a, b in zip(ts, ts[1:])] + ts
        best = 0.0
        for t in grid:
            _, q, v, w = self.anchor(float(t))
            qw, qv = q[0], q[1:]
            # Q r for every point (r + 2 qw (qv × r) + 2 qv × (qv × r))
            c = np.cross(qv, r)
            rr = r + 2.0 * qw * c + 2.0 * np.cross(qv, c)
            best = max(best, float(np.linalg.norm(v + np.cross(w, rr), axis=1).max()))
        return best

    def arrays(self):
        """(v (3,), w (3,), pivot (3,), key_t (K,), key_p (K, 3), key_q (K, 4)) float64."""
        piv = self.pivot if self.pivot is not None else (0.0, 0.0, 0.0)
        if self.keyed:
            kt = np.array([k.time for k in self.keys], dtype=np.float64)
            kp = np.array([k.position for k in self.keys], dtype=np.float64).reshape(-1, 3)
            kq = np.array([k.rotation for k in self.keys], dtype=np.float64).reshape(-1, 4)
            kq /= np.linalg.norm(kq, axis=1)[:, None]
            # one hemisphere along the keys: slerp and the Hermite go the short way
            for i in range(1, len(kq)):
                if np.dot(kq[i], kq[i - 1]) < 0.0:
                    kq[i] = -kq[i]
        else:
            kt, kp, kq = np.zeros(1), np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0, 0.0]])
        return (np.asarray(self.velocity, dtype=np.float64),
                np.asarray(self.angular_velocity, dtype=np.float64),
                np.asarray(piv, dtype=np.float64), kt, kp, kq)

    def anchor(self, t: float):
        """The anchor at time ``t`` [s]: (P (3,), Q (4,), V (3,), W (3,)), world frame
        (the same code the kernels compile)."""
        v, w, p, kt, kp, kq = self.arrays()
        r = anchor_state(float(t), self.kind, v, w, p, kt, kp, kq, 0, len(kt))
        return (np.array(r[0:3]), np.array(r[3:7]), np.array(r[7:10]), np.array(r[10:13]))


@dataclass(frozen=True)
class MotionTable:
    """Motions packed for the kernels (``Model.motion_*``): motion m's rates in row
    m, its keys in rows key_start[m]..key_start[m+1]-1."""

    kind: np.ndarray        # (M,) int32: RATES, LINEAR or SMOOTH
    v: np.ndarray           # (M, 3) [m/s]
    w: np.ndarray           # (M, 3) [rad/s]
    pivot: np.ndarray       # (M, 3) [m]
    key_start: np.ndarray   # (M + 1,) int32
    key_t: np.ndarray       # (K,) [s]
    key_p: np.ndarray       # (K, 3) [m]
    key_q: np.ndarray       # (K, 4)


def pack(motions) -> MotionTable:
    """The kernels' arrays for a list of Motions (at least one key row, so the
    arrays are never empty)."""
    kinds, vs, ws, ps, starts, kts, kps, kqs = [], [], [], [], [0], [], [], []
    for m in motions:
        v, w, p, kt, kp, kq = m.arrays()
        kinds.append(m.kind)
        vs.append(v)
        ws.append(w)
        ps.append(p)
        kts.append(kt)
        kps.append(kp)
        kqs.append(kq)
        starts.append(starts[-1] + len(kt))
    if not kts:
        kts, kps, kqs = [np.zeros(1)], [np.zeros((1, 3))], [np.array([[1.0, 0, 0, 0]])]
    return MotionTable(
        kind=np.array(kinds, dtype=np.int32),
        v=np.array(vs, dtype=np.float64).reshape(-1, 3),
        w=np.array(ws, dtype=np.float64).reshape(-1, 3),
        pivot=np.array(ps, dtype=np.float64).reshape(-1, 3),
        key_start=np.array(starts, dtype=np.int32),
        key_t=np.concatenate(kts), key_p=np.concatenate(kps), key_q=np.concatenate(kqs))


def relative_pose(anchor_p, anchor_q, x, q):
    """(c, a): the poses (x, q) expressed in the anchor frame (anchor_p, anchor_q), so
    that carried_state gives back (x, q) at that anchor: c = Q⁻¹ (x − P), a = Q⁻¹ q.
    Arrays (n, 3), (n, 4) or single poses; returns (n, 3), (n, 4)."""
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    Qw, Qx, Qy, Qz = (float(c) for c in anchor_q)
    d = x - np.asarray(anchor_p, dtype=np.float64)
    # the formulas are plain arithmetic: they take the columns whole
    c = np.stack(quat_rotate_inv(Qw, Qx, Qy, Qz, d[:, 0], d[:, 1], d[:, 2]), axis=1)
    a = np.stack(qmul(Qw, -Qx, -Qy, -Qz, q[:, 0], q[:, 1], q[:, 2], q[:, 3]), axis=1)
    return c, a


def reference_anchor(motion: Motion, origin, rotation=(1.0, 0.0, 0.0, 0.0), *,
                     group: bool = False):
    """The anchor pose (P (3,), Q (4,)) at which an owner stands at its authored pose.

    ``origin``, ``rotation``: the owner's authored frame (a mesh's or a single
    body's mesh origin and orientation, a plane's point, a box's centre) [m],
    world frame. Rates: (pivot, identity), the pivot defaulting to ``origin``.
    Keys: the owner's frame itself, so the keys are absolute poses of it; for a
    group of many bodies (``group``: grid or random layouts) the anchor at the
    first key, so the group stands as laid out when the keys are at their first
    and moves rigidly with them."""
    if not motion.keyed:
        piv = motion.pivot if motion.pivot is not None else origin
        return np.asarray(piv, dtype=np.float64), np.array([1.0, 0.0, 0.0, 0.0])
    if group:
        k = motion.keys[0]
        q = np.asarray(k.rotation, dtype=np.float64)
        return np.asarray(k.position, dtype=np.float64), q / np.linalg.norm(q)
    q = np.asarray(rotation, dtype=np.float64)
    return np.asarray(origin, dtype=np.float64), q / np.linalg.norm(q)


def carry(motion: Motion, ref, x, q, t: float):
    """Pose at time ``t`` [s] of a frame that stands at (x (3,), q (4,)) when the
    anchor is at ``ref`` (reference_anchor): (x (3,), q (4,), v (3,), w (3,)),
    world frame — what a moving collider's or kinematic body's prim is written at."""
    c, a = relative_pose(ref[0], ref[1], x, q)
    P, Q, V, W = motion.anchor(t)
    r = carried_state(*P, *Q, *V, *W, *c[0], *a[0])
    return np.array(r[0:3]), np.array(r[3:7]), np.array(r[7:10]), W
