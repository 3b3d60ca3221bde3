"""The paper's formulas as plain scalar functions (Harada et al. 2007, eq. 2-21).

Nothing here imports numba. Each function takes and returns Python floats (or
tuples of them), so tests can call it directly against closed forms, and the
kernels compile the very same source for each target::

    # kernels/cpu/stages.py                          # kernels/cuda/backend.py
    numba.njit(inline="always")(f)            numba.cuda.jit(device=True, inline=True)(f)

Conventions: SI units; quaternions (w, x, y, z), body to world; vectors are
passed as three scalars because that is what both targets compile best.
"""

from math import cos, sin, sqrt

# The contact law's normal force (laws/linear.py); compile_formulas replaces it by
# the scene's law compiled for the target. Plain-Python callers get the linear one.
from dempipe.sim.laws.linear import normal_force

# ---------------------------------------------------------------------------
# Quaternions and rotation (eq. 7-10, 19)
# ---------------------------------------------------------------------------

def quat_rotate(qw, qx, qy, qz, vx, vy, vz):
    """Rotate vector v by the unit quaternion q: q v q* (eq. 19).

    Uses v' = v + 2w (u × v) + 2 u × (u × v) with u = (qx, qy, qz), which needs
    no 3×3 matrix and is exact for unit q up to rounding.
    """
    tx = 2.0 * (qy * vz - qz * vy)
    ty = 2.0 * (qz * vx - qx * vz)
    tz = 2.0 * (qx * vy - qy * vx)
    return (
        vx + qw * tx + (qy * tz - qz * ty),
        vy + qw * ty + (qz * tx - qx * tz),
        vz + qw * tz + (qx * ty - qy * tx),
    )


def quat_rotate_inv(qw, qx, qy, qz, vx, vy, vz):
    """Rotate v by the conjugate of q (world to body): q* v q."""
    return quat_rotate(qw, -qx, -qy, -qz, vx, vy, vz)


def quat_integrate(qw, qx, qy, qz, wx, wy, wz, dt):
    """Advance orientation q by angular velocity w over dt (eq. 7-10).

    dq = [cos(θ/2), a sin(θ/2)] with a = w/|w| (eq. 8), θ = |w| dt (eq. 9), and
    q(t+dt) = dq ⊗ q(t) (eq. 10): the increment is a world-frame rotation, so it
    multiplies from the left. The result is renormalized so rounding cannot
    accumulate into a non-unit quaternion.
    """
    wn = sqrt(wx * wx + wy * wy + wz * wz)
    half = 0.5 * wn * dt
    if wn > 0.0:
        s = sin(half) / wn
    else:
        s = 0.5 * dt  # limit of sin(|w|dt/2)/|w|; the increment is the identity anyway
    dw = cos(half)
    dx = wx * s
    dy = wy * s
    dz = wz * s
    # Hamilton product dq ⊗ q
    nw = dw * qw - dx * qx - dy * qy - dz * qz
    nx = dw * qx + dx * qw + dy * qz - dz * qy
    ny = dw * qy - dx * qz + dy * qw + dz * qx
    nz = dw * qz + dx * qy - dy * qx + dz * qw
    inv = 1.0 / sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    return nw * inv, nx * inv, ny * inv, nz * inv


def sym_mat_vec(axx, ayy, azz, axy, axz, ayz, vx, vy, vz):
    """Product of a symmetric 3×3 matrix, given by its six entries, with v."""
    return (
        axx * vx + axy * vy + axz * vz,
        axy * vx + ayy * vy + ayz * vz,
        axz * vx + ayz * vy + azz * vz,
    )


def angular_velocity(qw, qx, qy, qz, ixx, iyy, izz, ixy, ixz, iyz, lx, ly, lz):
    """w = I(t)⁻¹ L with I(t)⁻¹ = R I(0)⁻¹ Rᵀ (eq. 5-6).

    ``i..`` are the six entries of the inverse inertia tensor in the body frame
    [1/(kg m²)]; L is the angular momentum in the world frame [kg m²/s].
    Evaluated as R (I(0)⁻¹ (Rᵀ L)) so no matrix is formed.
    """
    bx, by, bz = quat_rotate_inv(qw, qx, qy, qz, lx, ly, lz)
    bx, by, bz = sym_mat_vec(ixx, iyy, izz, ixy, ixz, iyz, bx, by, bz)
    return quat_rotate(qw, qx, qy, qz, bx, by, bz)


# ---------------------------------------------------------------------------
# Stage 1: sphere state from the body (eq. 19-21)
# ---------------------------------------------------------------------------

def chord_velocity(Vx, Vy, Vz, Wx, Wy, Wz, rx, ry, rz, h):
    """The velocity [m/s] of a point at r [m] from an anchor moving at V [m/s] and
    turning at W [rad/s], as the chord of its last step h [s]: V + W × r −
    (h/2) W × (W × r), to second order in h (h = 0: the tangent V + W × r).

    Every contact point's velocity is such a chord (sphere_kinematics, and a moving
    wall's or kinematic body's surface): a dynamic body's V = P/M is exactly the
    chord of its centre's last step (body_step moves X by V h). With tangents
    instead, two surfaces turning together do not agree: a box carried round by a
    turntable at ω sees the table's point beneath it slip by (h/2) ω² r every step
    and creeps inwards at that speed (2e-4 m/s at ω = 2 rad/s, r = 0.3 m, h = 3.5e-4
    s), and each of its points slips outwards from its centre at (h/2) ω² r'."""
    cx = Wy * rz - Wz * ry
    cy = Wz * rx - Wx * rz
    cz = Wx * ry - Wy * rx
    a = 0.5 * h
    return (Vx + cx - a * (Wy * cz - Wz * cy), Vy + cy - a * (Wz * cx - Wx * cz),
            Vz + cz - a * (Wx * cy - Wy * cx))


def sphere_kinematics(X, Y, Z, qw, qx, qy, qz, VX, VY, VZ, WX, WY, WZ, ox, oy, oz, h):
    """Sphere centre, velocity and world-frame offset from its body (eq. 19-21).

    (ox, oy, oz) is the sphere's offset from the centre of mass in the body frame.
    Returns (x, y, z, vx, vy, vz, rx, ry, rz) with r' = R r (eq. 19),
    x = X + r' (eq. 20) and v = V + W × r' (eq. 21) taken as the chord of the last
    step h [s] (chord_velocity: V is one; h = 0 gives eq. 21 as written).
    """
    rx, ry, rz = quat_rotate(qw, qx, qy, qz, ox, oy, oz)
    vx, vy, vz = chord_velocity(VX, VY, VZ, WX, WY, WZ, rx, ry, rz, h)
    return X + rx, Y + ry, Z + rz, vx, vy, vz, rx, ry, rz


def static_body(inv_mass):
    """Whether a body takes no part in the body stage: a collider (static mesh) or,
    later, a kinematic body moved by Control. Its 1/m is 0: an infinite mass to
    every contact. The one test of "static" every kernel uses (Model.body_static
    on the host)."""
    return inv_mass == 0.0


# ---------------------------------------------------------------------------
# Stage 4: contact force between two spheres, or a sphere and a wall (eq. 11-14)
# ---------------------------------------------------------------------------

def carry_stretch(nx, ny, nz, sx, sy, sz, spin, dt):
    """A tangential stretch s [m] carried one step dt [s] with the contact or bond
    it belongs to, as if fixed to it (Luding 2008's objective spring): turned by
    spin dt about the unit normal n, spin [rad/s] being the two sides' mean
    angular velocity along n, then projected into the current tangent plane (the
    plane normal to n), its length kept. The projection turns it with the
    normal's own rotation; the turn about n, with a pair twisting about its
    normal. Returns the carried s, world frame [m].

    The turn is to first order (s + spin dt n × s); the rescaling restores the
    length, leaving an angle atan(spin dt), short by a third of (spin dt)² of it.
    Kept in fixed axes instead, the spring of a pair turning at ω about its normal
    lags by ω s per unit time, and only a slip ω × s keeps it pointing where the
    force must: a box carried on a turntable creeps, a glued piece twisting about
    its bond keeps its shear in stale axes. Odd in (n, s, spin) together: the other
    side's carry is the exact negation (contact_force, glue_force)."""
    s2 = sx * sx + sy * sy + sz * sz
    a = spin * dt
    rx = a * (ny * sz - nz * sy)
    ry = a * (nz * sx - nx * sz)
    rz = a * (nx * sy - ny * sx)
    sx += rx
    sy += ry
    sz += rz
    sn = sx * nx + sy * ny + sz * nz
    sx -= sn * nx
    sy -= sn * ny
    sz -= sn * nz
    p2 = sx * sx + sy * sy + sz * sz
    if p2 > 0.0:
        keep = sqrt(s2 / p2)
        sx *= keep
        sy *= keep
        sz *= keep
    return sx, sy, sz


def midpoint_velocity(dvx, dvy, dvz, wsx, wsy, wsz, nx, ny, nz, arm, dt):
    """The velocity [m/s] of j's side relative to i's at the point midway between two
    spheres, arm = dist/2 [m] from each centre along the unit normal n (i to j):
    dv = v_j - v_i [m/s] (centre velocities, chords of the step dt [s]), ws = W_i +
    W_j [rad/s]. Each side's W × (±arm n) is taken as the chord of the step too
    (chord_velocity), with each side's W as their mean ws/2:
    u = dv - arm (ws × n) + (dt/4) arm ws × (ws × n). Exact for two bodies turning
    together, whose u is then 0 (a point a radius out on each side would slip:
    the two are the overlap apart), and second order in their spins' difference
    otherwise. Negated exactly when n and dv are (the other side's view)."""
    cx = wsy * nz - wsz * ny
    cy = wsz * nx - wsx * nz
    cz = wsx * ny - wsy * nx
    a = 0.25 * dt * arm
    return (dvx - arm * cx + a * (wsy * cz - wsz * cy),
            dvy - arm * cy + a * (wsz * cx - wsx * cz),
            dvz - arm * cz + a * (wsx * cy - wsy * cx))


def contact_force(nx, ny, nz, overlap, ux, uy, uz, k, eta, kt, ks, mu, sx, sy, sz, spin, dt,
                  vc=0.0):
    """Force on sphere i from one contact (eq. 11-14), with a Coulomb cap and a
    tangential spring for static friction (Cundall and Strack 1979).

    n : unit normal from i towards the other body.
    overlap : d - |r_ij| for two spheres, radius - distance for a wall [m]; > 0, or
      ≤ 0 in the step after a contact ends (laws.linear.normal_force).
    u : velocity of the other body's contact point relative to i's [m/s].
    k : normal spring [N/m]; eta : normal dashpot [N s/m];
    kt : tangential dashpot [N s/m]; ks : tangential spring [N/m] (0: none);
    mu : Coulomb friction; s : the contact's tangential spring stretch [m] from
    the last step (0 for a new contact); spin : the rate [rad/s] at which the
    contact turns about n, the two sides' mean angular velocity along n
    (ω_i + ω_j)/2 · n; dt : the step [s]; vc : the onset speed
    [m/s] (the law's normal_force: a contact that begins or ends slower is resting).
    Returns (fx, fy, fz, sx, sy, sz): the force [N] and the new stretch.

    Normal: the contact law's normal_force, for the linear law spring -k δ n
    (eq. 11) plus a dashpot on the *normal* relative
    velocity only, η (u·n) n — the paper's eq. 12 damps the full relative
    velocity, which would also act as friction on frictionless materials.
    Tangential: the paper's viscous kt u_t (eq. 13) plus a spring ks s, where
    s integrates the tangential slip u_t dt while the contact lasts. The spring
    is what holds a box on a slope: a viscous force vanishes with the speed,
    so it can only slow a creep, never stop it. Each step s is first carried
    with the contact, as if fixed to it (carry_stretch: turned by spin dt about
    n, then into the current tangent plane, length kept), and only then grown
    by u_t dt; in fixed world axes a box carried on a turntable would creep.
    The sum is capped by Coulomb |f_t| ≤ μ |f_n| with |f_n| the compressive
    part of the normal force; when the cap binds the contact slides, and s is
    reset to what the capped force needs, so the spring never stores more than
    μ |f_n| / ks.

    Antisymmetric in IEEE arithmetic: swapping i and j negates n, u, s and
    spin and gives exactly the negated force and stretch, so gathered sums conserve
    momentum and both sides' histories stay exact opposites.
    """
    un = ux * nx + uy * ny + uz * nz
    fn = normal_force(k, eta, overlap, un, dt, vc)   # along n; negative pushes i away (the law's)
    fx = fn * nx
    fy = fn * ny
    fz = fn * nz
    if mu > 0.0:
        tx = ux - un * nx
        ty = uy - un * ny
        tz = uz - un * nz
        cap = -mu * fn if fn < 0.0 else 0.0
        if ks > 0.0 and cap > 0.0:
            sx, sy, sz = carry_stretch(nx, ny, nz, sx, sy, sz, spin, dt)
            sx += tx * dt
            sy += ty * dt
            sz += tz * dt
            ftx = ks * sx + kt * tx
            fty = ks * sy + kt * ty
            ftz = ks * sz + kt * tz
        else:
            sx = 0.0
            sy = 0.0
            sz = 0.0
            ftx = kt * tx
            fty = kt * ty
            ftz = kt * tz
        ft2 = ftx * ftx + fty * fty + ftz * ftz
        if ft2 > cap * cap:
            if ft2 > 0.0:
                c = cap / sqrt(ft2)
                ftx *= c
                fty *= c
                ftz *= c
            if ks > 0.0 and cap > 0.0:   # sliding: the stretch the capped force needs
                sx = (ftx - kt * tx) / ks
                sy = (fty - kt * ty) / ks
                sz = (ftz - kt * tz) / ks
        fx += ftx
        fy += fty
        fz += ftz
    else:
        sx = 0.0
        sy = 0.0
        sz = 0.0
    return fx, fy, fz, sx, sy, sz


def sphere_pair_force(rx, ry, rz, dist, diameter, dvx, dvy, dvz, wsx, wsy, wsz,
                      k, eta, kt, ks, mu, sx, sy, sz, dt, vc=0.0):
    """Force on sphere i from sphere j, its torque about i's centre, and the new
    tangential stretch of the contact.

    r = x_j - x_i with |r| = dist < diameter; dv = v_j - v_i (centre velocities);
    ws = W_i + W_j, the sum of the two bodies' angular velocities, which gives the
    contact-point velocities: the contact point c lies midway across the overlap,
    dist/2 from each centre, and each side's velocity there is the chord of the
    step dt [s] (midpoint_velocity):
    u = dv - (dist/2) (ws × n) + (dt/8) dist ws × (ws × n). So two bodies turning
    together do not slip at a contact tilted from their spin axis (a point a
    radius out on each side would: the two are the overlap apart). The contact
    turns about n at ws·n / 2 (the mean spin: contact_force). s : the stretch
    from the last step [m].
    Returns (fx, fy, fz, tx, ty, tz, sx, sy, sz): the torque (dist/2) n × f is
    what the force adds about the sphere's own centre (the paper's eq. 16 uses
    the centre only, which cannot make a single sphere roll; see docs/physics.md);
    the same on both sides, so the pair keeps angular momentum exactly.
    """
    if dist > 0.0:
        inv = 1.0 / dist
        nx = rx * inv
        ny = ry * inv
        nz = rz * inv
    else:  # coincident centres: any direction is as good; pick +z deterministically
        nx = 0.0
        ny = 0.0
        nz = 1.0
    arm = 0.5 * dist
    ux, uy, uz = midpoint_velocity(dvx, dvy, dvz, wsx, wsy, wsz, nx, ny, nz, arm, dt)
    spin = 0.5 * (wsx * nx + wsy * ny + wsz * nz)
    fx, fy, fz, sx, sy, sz = contact_force(nx, ny, nz, diameter - dist, ux, uy, uz,
                                           k, eta, kt, ks, mu, sx, sy, sz, spin, dt, vc)
    return (fx, fy, fz,
            arm * (ny * fz - nz * fy), arm * (nz * fx - nx * fz), arm * (nx * fy - ny * fx),
            sx, sy, sz)


def sphere_wall_force(nx, ny, nz, overlap, radius, vx, vy, vz, wx, wy, wz, Wx, Wy, Wz,
                      k, eta, kt, ks, mu, sx, sy, sz, dt, vc=0.0):
    """Force on a sphere from a wall, its torque about the sphere's centre, and
    the new tangential stretch (as sphere_pair_force).

    n : unit normal from the sphere towards the wall (minus the wall's outward normal).
    v : the sphere's centre velocity relative to the wall's surface under it [m/s]
    (its own for a still wall); w : its body's angular velocity [rad/s]; W : the
    wall's angular velocity [rad/s] (0 for a still wall). The contact point is on
    the wall's surface, a = radius - overlap from the sphere's centre along n,
    where the wall's velocity is taken (motion.anchor_surface): the relative
    contact velocity is u = -(v + w × (a n)), as the chord of the step dt
    (chord_velocity), the torque is a n × f, and the contact turns about n at
    (w + W)·n / 2 (the mean spin: contact_force).
    """
    arm = radius - overlap
    ux, uy, uz = chord_velocity(vx, vy, vz, wx, wy, wz, arm * nx, arm * ny, arm * nz, dt)
    spin = 0.5 * ((wx + Wx) * nx + (wy + Wy) * ny + (wz + Wz) * nz)
    fx, fy, fz, sx, sy, sz = contact_force(nx, ny, nz, overlap, -ux, -uy, -uz,
                                           k, eta, kt, ks, mu, sx, sy, sz, spin, dt, vc)
    return (fx, fy, fz,
            arm * (ny * fz - nz * fy), arm * (nz * fx - nx * fz), arm * (nx * fy - ny * fx),
            sx, sy, sz)


#: Below a relative rolling of ROLLING_FLOOR × vc × (1/R_i + 1/R_j) [rad/s] (its rim
#: speed a thousandth of the onset speed vc, the speed below which a contact counts as
#: resting: Model.onset_speed) the rolling-resistance torque falls off in proportion to
#: the rolling instead of keeping its full size. A body that slides without rolling has
#: a relative spin of round-off, whose direction is noise; at full size the torque
#: turned that noise into a spin about any axis (a box on a conveyor drifted across the
#: belt at 6e-7 m/s). Relative to the scene's own speeds and sizes, so a scene scaled
#: in size moves the same (tests/sim/test_extremes.py); a ball's stopping distance changes
#: by (floor / ω0)², below 1e-9 in the tests.
ROLLING_FLOOR = 1e-3


def rolling_torque(wx, wy, wz, nx, ny, nz, n2, fn, mu_r, inv_r, vc):
    """Rolling resistance on a sphere of a contact: a constant torque μ_r R* |F·n̂|
    against the relative rolling (the "constant directional torque" model, Ai, Chen,
    Rotter and Ooi 2011, model A; LIGGGHTS' rolling_friction cdt). Returns the
    torque [N m] on this side; the partner's is exactly its negation (every input
    comes out the same or negated from its side). The body stage limits the sum of
    a body's rolling torques so that it never more than stops the body's spin in a
    step (rolling_scale).

    w : relative angular velocity ω_self − ω_partner [rad/s] (a wall: minus its
    own); n : the contact's normal, either sign, of squared length n2 > 0 (the line
    of centres as it is, or a wall's unit normal). Rolling is w less its component
    along n (a spin about the normal, twisting, is not resisted). fn : F·n, the
    contact force along n [N m] (|F·n̂| |n|); mu_r : the pair's coefficient [1];
    inv_r : 1/R_i + 1/R_j, the inverse rolling radius of the two bodies [1/m] (a
    wall, static or kinematic partner: 1/R_i); vc : the onset speed [m/s], which
    sets the spin below which the torque fades (ROLLING_FLOOR).

    Why a constant torque: it is the model with the closed form a user can check (a
    ball rolling at v0 on a plane stops after 7 v0² / (10 μ_r g)) and, limited, it
    brings rolling to rest without the oscillation of the unlimited model; the
    spring-dashpot rolling models (Ai's model C) add a stiffness and a damping per
    contact that the time step would have to resolve as well.
    """
    # u = n2 w_r (w_r = w less its part along n), so that no division is needed for it
    wn = wx * nx + wy * ny + wz * nz
    ux = n2 * wx - wn * nx
    uy = n2 * wy - wn * ny
    uz = n2 * wz - wn * nz
    u2 = ux * ux + uy * uy + uz * uz
    if u2 == 0.0:
        return 0.0, 0.0, 0.0
    # below the floor the torque falls off in proportion to the rolling (|u| =
    # n2 |w_r|): where the relative rolling is round-off, so is its direction
    wf = ROLLING_FLOOR * vc * inv_r
    floor = n2 * n2 * (wf * wf)
    c = -mu_r * abs(fn) / (inv_r * sqrt(n2 * (u2 if u2 > floor else floor)))
    return c * ux, c * uy, c * uz


def rolling_scale(wx, wy, wz, dwx, dwy, dwz, tx, ty, tz):
    """The share s in [0, 1] of a body's summed rolling torque T [N m] that it takes
    this step: s = 1, or the share that leaves it the least spin energy where the
    whole would overshoot, -(ω·T) / (Δω·T), with Δω = I⁻¹ T dt the spin change the
    whole would make [rad/s] and ω the spin the body would have after this step's
    other torques [rad/s] (I⁻¹ (L + T_other dt)). So rolling resistance never leaves
    a body with more spin energy than the step would without it, and against still
    partners it stops a rolling body instead of reversing it, whatever the number
    of its contacts. (Taken from the spin before the step, ω·T of a body at rest
    among flickering contacts is that of its last step's reversal, and the share
    works against this step's friction torques: a settled pile kept 3e-9 J of
    jitter, tests/sim/test_restitution.py.)"""
    wt = wx * tx + wy * ty + wz * tz
    dt_ = dwx * tx + dwy * ty + dwz * tz        # = dt Tᵀ I⁻¹ T > 0 for T ≠ 0
    if dt_ <= 0.0:
        return 1.0
    if wt >= 0.0:
        return 0.0                              # it would only add spin: none
    s = -wt / dt_
    return 1.0 if s > 1.0 else s


# ---------------------------------------------------------------------------
# Glue: a bond between two sphere pieces (sim/glue.py finds them)
# ---------------------------------------------------------------------------

def glue_force(rx, ry, rz, dist, rest, dvx, dvy, dvz, wsx, wsy, wsz, k, eta, sx, sy, sz, dt):
    """Force on sphere i from its glue bond with sphere j, its torque about i's
    centre, the bond's new shear stretch, and its elastic load.

    r = x_j - x_i [m] with |r| = dist > 0; rest : the bond's rest length [m] (the
    distance at which it was glued); dv = v_j - v_i [m/s] (centre velocities); ws =
    W_i + W_j [rad/s]. The bond point is the midpoint, half the distance from each
    centre, so its relative velocity is u = dv - (dist/2) (ws × n) + (dt/8) dist
    ws × (ws × n), the chord of the step (midpoint_velocity).
    k : the bond's spring [N/m], normal and shear alike; eta : its dashpot [N s/m];
    s : the shear stretch from the last step [m] (0 when glued); dt : the step [s].

    Normal: k (dist - rest) n + eta (u·n) n, in tension and compression. Shear:
    the stretch s, carried with the bond (carry_stretch: turned by the pair's mean
    spin about n, (W_i + W_j)·n / 2 = ws·n / 2, then into the current tangent
    plane, length kept) and grown by u_t dt, gives k s + eta u_t, with no Coulomb
    cap (glue does not slide).
    Returns (fx, fy, fz, tx, ty, tz, sx, sy, sz, load): the torque (dist/2) n × f
    and load = |max(k (dist - rest), 0) n + k s| [N], the spring's force without the
    dashpot and without compression: what sim/glue.py compares with σ d² (glue
    breaks in tension and shear; crushing is not modelled).

    Antisymmetric in IEEE arithmetic, as contact_force: from j's side r, dv and s
    are negated, so the force is exactly negated and the torque equal; with the
    bond point at the midpoint, the pair keeps angular momentum too.
    """
    inv = 1.0 / dist
    nx = rx * inv
    ny = ry * inv
    nz = rz * inv
    half = 0.5 * dist
    ux, uy, uz = midpoint_velocity(dvx, dvy, dvz, wsx, wsy, wsz, nx, ny, nz, half, dt)
    un = ux * nx + uy * ny + uz * nz
    tx = ux - un * nx
    ty = uy - un * ny
    tz = uz - un * nz
    spin = 0.5 * (wsx * nx + wsy * ny + wsz * nz)
    sx, sy, sz = carry_stretch(nx, ny, nz, sx, sy, sz, spin, dt)
    sx += tx * dt
    sy += ty * dt
    sz += tz * dt
    fe = k * (dist - rest)
    fn = fe + eta * un
    ftx = k * sx + eta * tx
    fty = k * sy + eta * ty
    ftz = k * sz + eta * tz
    pull = fe if fe > 0.0 else 0.0
    lx = pull * nx + k * sx
    ly = pull * ny + k * sy
    lz = pull * nz + k * sz
    load = sqrt(lx * lx + ly * ly + lz * lz)
    return (fn * nx + ftx, fn * ny + fty, fn * nz + ftz,
            half * (ny * ftz - nz * fty), half * (nz * ftx - nx * ftz),
            half * (nx * fty - ny * ftx), sx, sy, sz, load)


# ---------------------------------------------------------------------------
# Contact history (static friction): each sphere remembers its own contacts
# ---------------------------------------------------------------------------

def history_recall(contact_partner, contact_spring, i, code):
    """(slot, sx, sy, sz): where sphere i remembers its contact with partner
    ``code`` and that contact's tangential stretch [m]; (-1, 0, 0, 0) for a new
    contact, which starts unstretched.

    contact_partner[i, h] holds 2 code + parity (see State), 0 when empty.
    """
    for h in range(contact_partner.shape[1]):
        if (contact_partner[i, h] >> 1) == code:
            return h, contact_spring[i, h, 0], contact_spring[i, h, 1], contact_spring[i, h, 2]
    return -1, 0.0, 0.0, 0.0


def history_store(contact_partner, contact_spring, i, slot, code, parity, sx, sy, sz):
    """Remember contact ``code`` of sphere i with stretch s, touched at ``parity``.

    A new contact (slot < 0) takes the first empty slot; with none free it is
    not remembered, and its friction is only the viscous part this step.
    """
    if slot < 0:
        for h in range(contact_partner.shape[1]):
            if contact_partner[i, h] == 0:
                slot = h
                break
        if slot < 0:
            return
    contact_partner[i, slot] = (code << 1) | parity
    contact_spring[i, slot, 0] = sx
    contact_spring[i, slot, 1] = sy
    contact_spring[i, slot, 2] = sz


# ---------------------------------------------------------------------------
# Sleeping: bodies at rest leave the integration until something moving touches them
# ---------------------------------------------------------------------------

def rest_steps(rest, vx, vy, vz, wx, wy, wz, v_sleep, w_sleep):
    """Steps a body has been at rest, after this step: one more when its speed
    |V| < v_sleep [m/s] and spin |W| < w_sleep [rad/s], else 0."""
    if (vx * vx + vy * vy + vz * vz < v_sleep * v_sleep
            and wx * wx + wy * wy + wz * wz < w_sleep * w_sleep):
        return rest + 1
    return 0


# ---------------------------------------------------------------------------
# Stages 5-8: body momentum, position, orientation (eq. 2-10, 15-16)
# ---------------------------------------------------------------------------

def body_step(X, Y, Z, qw, qx, qy, qz, PX, PY, PZ, LX, LY, LZ,
              FX, FY, FZ, TX, TY, TZ, inv_mass,
              ixx, iyy, izz, ixy, ixz, iyz, dt):
    """One explicit step of a rigid body (symplectic Euler).

    P += F dt (eq. 2), L += T dt (eq. 4), V = P/M, X += V dt (eq. 3),
    W = I(t)⁻¹ L (eq. 5-6), q ← dq(W dt) ⊗ q (eq. 7-10).
    Momenta first, then positions: the order that keeps the spring-mass
    system stable below its critical step.

    One departure from eq. 7-10: W is evaluated at the orientation half a step
    ahead (explicit midpoint). With W from the start of the step, a freely
    tumbling asymmetric body gains a few % of kinetic energy per 10⁴ steps;
    the midpoint makes the error second order for one more I⁻¹L per body.
    Returns the 13 new values (X, q, P, L).
    """
    PX += FX * dt
    PY += FY * dt
    PZ += FZ * dt
    LX += TX * dt
    LY += TY * dt
    LZ += TZ * dt
    X += PX * inv_mass * dt
    Y += PY * inv_mass * dt
    Z += PZ * inv_mass * dt
    wx, wy, wz = angular_velocity(qw, qx, qy, qz, ixx, iyy, izz, ixy, ixz, iyz, LX, LY, LZ)
    hw, hx, hy, hz = quat_integrate(qw, qx, qy, qz, wx, wy, wz, 0.5 * dt)
    wx, wy, wz = angular_velocity(hw, hx, hy, hz, ixx, iyy, izz, ixy, ixz, iyz, LX, LY, LZ)
    qw, qx, qy, qz = quat_integrate(qw, qx, qy, qz, wx, wy, wz, dt)
    return X, Y, Z, qw, qx, qy, qz, PX, PY, PZ, LX, LY, LZ
