"""dempipe against Bullet (pybullet): the same chess pieces settling in a box, side by side.

    python benchmarks/vs_bullet.py                         # 256 and 1,024 pieces, 3 s each
    python benchmarks/vs_bullet.py --n 256,1024,4096       # the issue's three sizes (4,096 is long)
    python benchmarks/vs_bullet.py --n 256 --duration 0.5 --threads 2 --json out.json

The scene is examples/chess.toml with ``count`` = N: the piece mix of one chess set
repeated, on its 32 × 32 × 16 lattice filled a layer at a time, falling into its
box (felt) and settling for ``--duration`` simulated seconds. dempipe builds it
from scene TOML at its default settings for that scene (resolution 6,
stiffness_target_overlap 0.05, dt "auto") and bakes it on the CPU with
``build_model`` + ``Simulator``. Bullet gets the same bodies from that Model:

* each piece is the convex hull of the same mesh, with the same mass, principal
  inertia, centre of mass, start position and orientation;
* the box is five static boxes (floor and walls; the walls reach far above the box
  top, as dempipe's open-top walls do);
* friction and restitution: Bullet multiplies the two bodies' coefficients,
  dempipe takes their geometric mean, so Bullet gets √μ and √e per material and
  every pair then has the same coefficient in both engines;
* Blender's defaults: 24 fps × 10 substeps = 240 Hz, 10 solver iterations, split
  impulse off, deactivation off, damping 0.04 (linear) and 0.1 (angular); the
  collision margin is pybullet's (1 mm; Blender's default 4 cm margin cannot be
  embedded in pieces this small, and Blender then uses none).

Timed: the stepping only (Bullet: the stepSimulation calls; dempipe: the frames of
``Simulator.advance``, after a warm-up step that loads or compiles the kernels).
Baseline, measured in the same run: Bullet on the same N. pybullet steps on one
core; dempipe on ``--threads`` numba threads.

At the end both are judged the same way: pieces inside the box (centre of mass
inside it), pieces at rest (no point of the piece faster than REST_SPEED, about
1 mm per frame at 24 fps), pile height (highest point of any piece's hull) and the
largest interpenetration at the end and over the run (dempipe: the largest sphere
overlap, also as a fraction of the sphere diameter d; Bullet: the most negative
contact distance of getContactPoints, sampled once per frame). A result is a
plausible settled pile when every piece is finite and inside the box, at least
REST_FRACTION of them are at rest and the interpenetration at the end is below
MAX_PENETRATION_FRACTION of the smallest piece's width. The speed comparison only
counts when both engines pass.

Without pybullet the script says so and exits with status 2
(pip install pybullet, or pip install 'dempipe[bench]').
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib.util
import json
import math
import os
import platform
import sys
import tempfile
import time

import numpy as np

#: A piece is at rest when no point of it moves faster than this [m/s]:
#: |v| + |w| r_max, about 1 mm per frame at 24 fps.
REST_SPEED = 0.025
#: A pile counts as settled when at least this fraction of pieces is at rest.
REST_FRACTION = 0.95
#: Largest interpenetration at the end that still looks right, as a fraction of
#: the smallest piece's smallest width (the pawn's foot, 23 mm: 2.3 mm).
MAX_PENETRATION_FRACTION = 0.10
#: A piece stands upright when its axis is within this angle of vertical [deg]
#: (not part of the verdict: it shows whether both piles have the same character).
UPRIGHT_DEGREES = 30.0
#: Blender's rigid-body defaults (BKE_rigidbody_create_object / the world settings).
BLENDER_FPS = 24
BLENDER_SUBSTEPS = 10
BLENDER_SOLVER_ITERATIONS = 10
BLENDER_LINEAR_DAMPING = 0.04
BLENDER_ANGULAR_DAMPING = 0.1
#: Thickness of Bullet's floor and wall boxes [m], and how far the walls reach
#: above the box top (dempipe's open-top walls reach up without end) [m].
WALL_THICKNESS = 0.05
WALL_EXTRA_HEIGHT = 2.0

LATTICE = 32 * 32 * 16

#: The scene: the example itself, with its piece count set per run.
CHESS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "examples",
                     "chess.toml")


def log(msg: str) -> None:
    print(f"# {msg}", file=sys.stderr, flush=True)


@contextlib.contextmanager
def quiet_stdout():
    """Send what C code prints to stdout (pybullet's banners) to stderr, so stdout
    holds only the table."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


# --------------------------------------------------------------------- geometry


def quat_matrices(q: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotation matrices of (n, 4) unit quaternions (w, x, y, z)."""
    w, x, y, z = (q[:, i] for i in range(4))
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def matrix_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    t = np.trace(R)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a ⊗ b of (n, 4) and (4,) quaternions (w, x, y, z)."""
    aw, ax, ay, az = (a[:, i] for i in range(4))
    bw, bx, by, bz = b
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], -1)


def hull_vertices(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Vertices of the convex hull of a mesh (all vertices when scipy is missing:
    pybullet then drops the interior ones itself)."""
    try:
        import trimesh

        return np.asarray(trimesh.Trimesh(vertices, faces, process=False).convex_hull.vertices)
    except Exception:  # pragma: no cover - trimesh's hull needs scipy
        return np.asarray(vertices)


class Pieces:
    """The pieces of a Model in a form both engines are judged by.

    Per body: its shape, radius (farthest hull vertex from the centre of mass)
    and, per shape, its hull vertices about the centre of mass in dempipe's body
    frame (mesh axes) and in the principal frame Bullet uses (``principal``:
    v_mesh = principal @ v_bullet).
    """

    def __init__(self, model):
        nb = model.n_bodies
        self.n = nb
        self.shape = np.asarray(model.body_shape[:nb])
        self.hull = [hull_vertices(np.asarray(s.vertices), np.asarray(s.faces)) for s in model.shapes]
        r = np.array([np.linalg.norm(h, axis=1).max() for h in self.hull])
        self.radius = r[self.shape]
        self.min_width = min(float(np.ptp(h[:, :2], axis=0).min()) for h in self.hull)
        self.principal = []
        self.inertia_diag = np.zeros((nb, 3))
        for s in range(len(model.shapes)):
            bodies = np.flatnonzero(self.shape == s)
            if bodies.size == 0:
                self.principal.append(np.eye(3))
                continue
            # every body of a shape shares its principal frame (uniform density)
            _, vec = np.linalg.eigh(_inertia(model.body_inv_inertia[bodies[0]]))
            if np.linalg.det(vec) < 0:
                vec[:, 2] = -vec[:, 2]
            self.principal.append(vec)
            for b in bodies:
                self.inertia_diag[b] = np.linalg.eigvalsh(_inertia(model.body_inv_inertia[b]))

    def tops(self, x: np.ndarray, q: np.ndarray, frame: str) -> np.ndarray:
        """Highest point of each piece's hull [m]; q in dempipe's (frame 'mesh') or
        Bullet's principal frame (frame 'principal'), both (w, x, y, z)."""
        top = np.empty(self.n)
        R = quat_matrices(q)
        for s, h in enumerate(self.hull):
            bodies = np.flatnonzero(self.shape == s)
            if bodies.size == 0:
                continue
            v = h if frame == "mesh" else h @ self.principal[s]   # v_bullet = P^T v_mesh
            top[bodies] = x[bodies, 2] + (R[bodies, 2, :] @ v.T).max(axis=1)
        return top

    def upright(self, q: np.ndarray, frame: str) -> np.ndarray:
        """Cosine between each piece's own up axis (mesh +z) and world +z."""
        R = quat_matrices(q)
        up = np.empty(self.n)
        for s in range(len(self.hull)):
            bodies = np.flatnonzero(self.shape == s)
            axis = np.array([0.0, 0.0, 1.0]) if frame == "mesh" else self.principal[s][2]
            up[bodies] = R[bodies, 2, :] @ axis
        return up


def _inertia(inv6) -> np.ndarray:
    """Inertia tensor [kg m²] from dempipe's inverse (xx, yy, zz, xy, xz, yz)."""
    a = np.asarray(inv6, dtype=np.float64)
    inv = np.array([[a[0], a[3], a[4]], [a[3], a[1], a[5]], [a[4], a[5], a[2]]])
    return np.linalg.inv(inv)


def judge(pieces: Pieces, box, x, q, v, w, frame: str, pen_end: float) -> dict:
    """What a result looks like at the end (see the module docstring)."""
    finite = bool(np.isfinite(x).all() and np.isfinite(q).all() and np.isfinite(v).all()
                  and np.isfinite(w).all())
    lo, hi = np.asarray(box.lo), np.asarray(box.hi)
    inside = int(np.all((x >= lo) & (x <= hi), axis=1).sum()) if finite else 0
    speed = np.linalg.norm(v, axis=1) + np.linalg.norm(w, axis=1) * pieces.radius
    at_rest = int((speed < REST_SPEED).sum()) if finite else 0
    top = pieces.tops(x, q, frame) if finite else np.full(pieces.n, np.nan)
    upright = int((pieces.upright(q, frame) > math.cos(math.radians(UPRIGHT_DEGREES))).sum()) \
        if finite else 0
    limit = MAX_PENETRATION_FRACTION * pieces.min_width
    reasons = []
    if not finite:
        reasons.append("non-finite state")
    if inside < pieces.n:
        reasons.append(f"{pieces.n - inside} outside the box")
    if at_rest < REST_FRACTION * pieces.n:
        reasons.append(f"only {at_rest / pieces.n:.0%} at rest")
    if not pen_end <= limit:
        reasons.append(f"interpenetration {pen_end * 1e3:.2f} mm > {limit * 1e3:.1f} mm")
    return dict(
        finite=finite, inside=inside, at_rest=at_rest, upright=upright,
        median_speed=float(np.median(speed)) if finite else math.nan,
        pile_top=float(np.max(top)) if finite else math.nan,
        mean_com_z=float(np.mean(x[:, 2])) if finite else math.nan,
        penetration_end=float(pen_end), penetration_limit=limit,
        plausible=not reasons, why=", ".join(reasons) or "settled pile",
    )


# ---------------------------------------------------------------------- dempipe


def dempipe_model(count: int, duration: float, cache):
    """examples/chess.toml with ``count`` pieces, ``duration`` seconds long."""
    import re

    from dempipe.scene.build import Overrides, build_model
    from dempipe.scene.load import parse_scene

    with open(CHESS) as f:
        text, n = re.subn(r"(?m)^count = \d+", f"count = {count}", f.read())
    if n != 1:
        raise SystemExit(f"vs_bullet: {CHESS} has no single 'count = N' line to set")
    return build_model(parse_scene(text, CHESS), cache=cache,
                       overrides=Overrides(duration=duration))


def run_dempipe(model, pieces: Pieces, threads: int) -> dict:
    from dempipe.sim.simulator import Simulator

    # load (or compile) the kernels on a throw-away state, outside the timing
    t0 = time.perf_counter()
    Simulator(model, device="cpu", threads=threads).backend.step(model.initial_state(), 1)
    warm = time.perf_counter() - t0
    sim = Simulator(model, device="cpu", threads=threads)
    # The largest sphere overlap of each frame: the Simulator keeps only the run's
    # largest (RunStats.max_overlap: a streamed bake keeps no per-frame list), so collect what it takes from the backend once per frame.
    overlaps = []
    take = sim.backend.take_max_overlap

    def take_and_keep():
        overlap = take()
        overlaps.append(overlap)
        return overlap

    sim.backend.take_max_overlap = take_and_keep
    state = model.initial_state()
    n_frames = model.n_frames
    every = max(1, (n_frames - 1) // 10)

    last = [0, 0.0]                      # frame and wall time of the last line

    def progress(k, n, stats):
        if k and (k % every == 0 or k == n - 1):
            eta = stats.wall_seconds / k * (n - 1 - k)
            per = (stats.wall_seconds - last[1]) / (k - last[0])
            last[:] = [k, stats.wall_seconds]
            asleep = int(state.asleep(model.sleep_steps)[: model.n_bodies].sum())
            log(f"dempipe {pieces.n}: frame {k}/{n - 1}, {stats.wall_seconds:.0f} s, "
                f"~{eta:.0f} s left; {per:.1f} s per frame since the last line, "
                f"{asleep:,} of {model.n_bodies:,} pieces asleep")

    from dempipe.sim.simulator import BakeFailure

    failure = None
    try:
        frames = sim.advance(state, n_frames=n_frames, progress=progress)
    except BakeFailure as exc:           # judged like any other result: not plausible
        failure = str(exc)
        frames = exc.frames
    sim_seconds = (frames.n_frames - 1) / model.fps
    f = frames.n_frames - 1
    pen_end = overlaps[-1] if overlaps and failure is None else math.inf
    out = judge(pieces, model.boxes[0], frames.x[f], frames.q[f], frames.v[f], frames.w[f],
                "mesh", pen_end)
    if failure:
        out["plausible"], out["why"] = False, f"bake stopped: {failure}"
    out.update(
        engine="dempipe", threads=threads, steps=sim.stats.steps,
        steps_skipped_asleep=sim.stats.steps_skipped,
        steps_per_sim_second=1.0 / model.dt, dt=model.dt,
        wall_seconds=sim.stats.wall_seconds, sim_seconds=sim_seconds,
        ms_per_step=sim.stats.wall_seconds / max(sim.stats.steps, 1) * 1e3,
        penetration_worst=float(max(overlaps)) if overlaps else 0.0,
        sphere_diameter=model.diameter, spheres=model.n_spheres, warmup_seconds=warm,
    )
    return out


# ----------------------------------------------------------------------- Bullet


def bullet_world(p, model, pieces: Pieces):
    """A pybullet DIRECT world holding the Model's box and pieces; returns (client, ids)."""
    cid = p.connect(p.DIRECT)
    dt = 1.0 / (BLENDER_FPS * BLENDER_SUBSTEPS)
    p.setGravity(*map(float, model.gravity), physicsClientId=cid)
    p.setPhysicsEngineParameter(fixedTimeStep=dt, numSubSteps=0,
                                numSolverIterations=BLENDER_SOLVER_ITERATIONS,
                                useSplitImpulse=0, physicsClientId=cid)
    mats = model.materials
    top = float(np.max(model.initial_x[:model.n_bodies, 2]) + pieces.radius.max())
    for box in model.boxes:
        lo, hi = np.asarray(box.lo, float), np.asarray(box.hi, float)
        t = WALL_THICKNESS
        z_top = max(hi[2], top) + WALL_EXTRA_HEIGHT
        slabs = [(np.array([lo[0] - t, lo[1] - t, lo[2] - t]), np.array([hi[0] + t, hi[1] + t, lo[2]]))]
        if not box.open_top:
            slabs.append((np.array([lo[0] - t, lo[1] - t, hi[2]]),
                          np.array([hi[0] + t, hi[1] + t, hi[2] + t])))
            z_top = hi[2]
        slabs += [
            (np.array([lo[0] - t, lo[1] - t, lo[2] - t]), np.array([lo[0], hi[1] + t, z_top])),
            (np.array([hi[0], lo[1] - t, lo[2] - t]), np.array([hi[0] + t, hi[1] + t, z_top])),
            (np.array([lo[0], lo[1] - t, lo[2] - t]), np.array([hi[0], lo[1], z_top])),
            (np.array([lo[0], hi[1], lo[2] - t]), np.array([hi[0], hi[1] + t, z_top])),
        ]
        m = mats[box.material]
        for a, b in slabs:
            shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=list((b - a) / 2),
                                           physicsClientId=cid)
            body = p.createMultiBody(0, shape, basePosition=list((a + b) / 2), physicsClientId=cid)
            p.changeDynamics(body, -1, lateralFriction=math.sqrt(m.friction),
                             restitution=math.sqrt(m.restitution), physicsClientId=cid)
    shapes = [p.createCollisionShape(p.GEOM_MESH, vertices=(h @ P).tolist(), physicsClientId=cid)
              for h, P in zip(pieces.hull, pieces.principal)]
    q_principal = [matrix_quat(P) for P in pieces.principal]
    ids = []
    x0 = np.asarray(model.initial_x[:pieces.n])
    q0 = np.asarray(model.initial_q[:pieces.n])
    for b in range(pieces.n):
        s = pieces.shape[b]
        qb = quat_mul(q0[b:b + 1], q_principal[s])[0]          # R_bullet = R_mesh · P
        body = p.createMultiBody(float(model.body_mass[b]), shapes[s], basePosition=list(x0[b]),
                                 baseOrientation=[qb[1], qb[2], qb[3], qb[0]],
                                 useMaximalCoordinates=True, physicsClientId=cid)
        m = mats[model.body_material[b]]
        # mass again: pybullet zeroes it when localInertiaDiagonal comes alone
        p.changeDynamics(body, -1, mass=float(model.body_mass[b]),
                         lateralFriction=math.sqrt(m.friction),
                         restitution=math.sqrt(m.restitution),
                         linearDamping=BLENDER_LINEAR_DAMPING,
                         angularDamping=BLENDER_ANGULAR_DAMPING,
                         localInertiaDiagonal=list(pieces.inertia_diag[b]),
                         activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING,
                         physicsClientId=cid)
        ids.append(body)
    return cid, ids


def bullet_penetration(p, cid) -> float:
    """Deepest interpenetration among all current contacts [m] (0 when none)."""
    pts = p.getContactPoints(physicsClientId=cid)
    if not pts:
        return 0.0
    return max(0.0, -min(c[8] for c in pts))


def bullet_profile(p, cid, steps: int) -> dict:
    """Share of Bullet's step spent in each phase, from pybullet's profiler."""
    import re
    from collections import Counter

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "timings")
        log_id = p.startStateLogging(p.STATE_LOGGING_PROFILE_TIMINGS, path, physicsClientId=cid)
        for _ in range(steps):
            p.stepSimulation(physicsClientId=cid)
        with quiet_stdout():
            p.stopStateLogging(log_id, physicsClientId=cid)
        files = [os.path.join(tmp, f) for f in os.listdir(tmp)]
        total = Counter()
        for fname in files:
            with open(fname) as f:
                events = json.load(f)["traceEvents"]
            begin = {}
            for e in events:
                if e.get("ph") == "B":
                    begin[e["name"]] = e["ts"]
                elif e.get("ph") == "E" and e["name"] in begin:
                    total[re.sub(r"\d+$", "", e["name"])] += e["ts"] - begin.pop(e["name"])
    step = total["internalSingleStepSimulation"] or 1.0
    collide = total["performDiscreteCollisionDetection"]    # AABBs, broadphase, narrowphase
    narrow = total["dispatchAllCollisionPairs"]             # convex-convex contact generation
    solve = total["processIslands"] or total["solveConstraints"]
    return {"narrowphase": narrow / step, "AABBs+broadphase": (collide - narrow) / step,
            "solver": solve / step, "other": max(0.0, 1.0 - (collide + solve) / step),
            "ms_per_step": step / 1e3 / steps}


def run_bullet(p, model, pieces: Pieces, duration: float, profile: bool) -> dict:
    t0 = time.perf_counter()
    cid, ids = bullet_world(p, model, pieces)
    setup = time.perf_counter() - t0
    n_frames = int(round(duration * BLENDER_FPS))
    every = max(1, n_frames // 10)
    wall = 0.0
    worst = 0.0
    for k in range(1, n_frames + 1):
        t0 = time.perf_counter()
        for _ in range(BLENDER_SUBSTEPS):
            p.stepSimulation(physicsClientId=cid)
        wall += time.perf_counter() - t0
        pen = bullet_penetration(p, cid)            # sampled once per frame, not timed
        worst = max(worst, pen)
        if k % every == 0 or k == n_frames:
            log(f"bullet {pieces.n}: frame {k}/{n_frames}, {wall:.0f} s, "
                f"~{wall / k * (n_frames - k):.0f} s left")
    x = np.zeros((pieces.n, 3))
    q = np.zeros((pieces.n, 4))
    v = np.zeros((pieces.n, 3))
    w = np.zeros((pieces.n, 3))
    for i, body in enumerate(ids):
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(body, physicsClientId=cid)
        x[i], q[i] = pos, (orn[3], orn[0], orn[1], orn[2])
        v[i], w[i] = lin, ang
    steps = n_frames * BLENDER_SUBSTEPS
    out = judge(pieces, model.boxes[0], x, q, v, w, "principal", pen)
    out.update(
        engine="bullet", threads=1, steps=steps, steps_per_sim_second=BLENDER_FPS * BLENDER_SUBSTEPS,
        dt=1.0 / (BLENDER_FPS * BLENDER_SUBSTEPS), wall_seconds=wall,
        sim_seconds=n_frames / BLENDER_FPS, ms_per_step=wall / steps * 1e3,
        penetration_worst=worst, setup_seconds=setup,
        contacts_end=len(p.getContactPoints(physicsClientId=cid)),
    )
    if profile:
        out["profile"] = bullet_profile(p, cid, BLENDER_SUBSTEPS * 2)
    p.disconnect(physicsClientId=cid)
    return out


# ----------------------------------------------------------------------- report


def machine(threads: int) -> dict:
    import numba

    from importlib.metadata import PackageNotFoundError, version

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        pb = version("pybullet")
    except PackageNotFoundError:
        pb = "?"
    return dict(cpu=cpu, cores=os.cpu_count(), python=platform.python_version(),
                numba=numba.__version__, pybullet=pb, numba_threads=threads,
                date=datetime.date.today().isoformat(), system=platform.system(),
                dempipe=dempipe_revision())


def dempipe_revision() -> str:
    """The git commit of the dempipe being measured, noting uncommitted changes to it."""
    import subprocess

    import dempipe

    where = os.path.dirname(os.path.abspath(dempipe.__file__))
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=where,
                             capture_output=True, text=True, timeout=10)
        if rev.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "."],
                               cwd=where, capture_output=True, text=True, timeout=10)
        return rev.stdout.strip() + (" + local changes" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def fmt_pen(r: dict) -> str:
    end, worst = r["penetration_end"], r["penetration_worst"]
    if not math.isfinite(end):
        return "n/a"
    if r["engine"] == "dempipe":
        d = r["sphere_diameter"]
        return f"{end * 1e3:.2g} mm = {end / d:.2g} d ({worst * 1e3:.2g} mm = {worst / d:.2g} d)"
    return f"{end * 1e3:.2g} mm ({worst * 1e3:.2g} mm)"


def table(rows: list[dict], info: dict, duration: float) -> str:
    lines = [
        f"Chess pieces settling in a box for {duration:g} s (examples/chess.toml), "
        f"{info['cpu']}, {info['cores']} cores, Python {info['python']}, numba {info['numba']} "
        f"({info['numba_threads']} threads), pybullet {info['pybullet']} (1 thread), "
        f"dempipe {info['dempipe']}, {info['date']}, load average {info['load_average'][0]:.1f} "
        f"at the start and {info['load_average'][1]:.1f} at the end. "
        "`python benchmarks/vs_bullet.py`",
        "",
        "| pieces | engine | steps per sim. s | ms/step | wall s per sim. s | speed vs Bullet "
        "| inside box | at rest | upright | pile top | interpenetration at end (worst) | verdict |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in rows:
        base = next(b for b in rows if b["n"] == r["n"] and b["engine"] == "bullet")
        per = r["wall_seconds"] / r["sim_seconds"]
        speed = (base["wall_seconds"] / base["sim_seconds"]) / per
        name = "Bullet (convex hulls, 240 Hz, 10 it.)" if r["engine"] == "bullet" else \
            (f"dempipe CPU ({r['spheres']:,} spheres, d = {r['sphere_diameter'] * 1e3:.1f} mm"
             + (f"; {r['steps_skipped_asleep']:,} of {r['steps']:,} steps skipped, all asleep"
                if r.get("steps_skipped_asleep") else "") + ")")
        lines.append(
            f"| {r['n']:,} | {name} | {r['steps_per_sim_second']:,.0f} | {r['ms_per_step']:.2f} "
            f"| {per:.3g} | {speed:.2f}x | {r['inside']}/{r['n']} | {r['at_rest'] / r['n']:.0%} "
            f"| {r['upright'] / r['n']:.0%} "
            f"| {r['pile_top'] * 1e3:.0f} mm | {fmt_pen(r)} "
            f"| {'plausible' if r['plausible'] else 'NOT plausible'}: {r['why']} |")
    lines += [
        "",
        f"At rest: every point slower than {REST_SPEED * 1e3:.0f} mm/s. Plausible: all finite "
        f"and inside, ≥ {REST_FRACTION:.0%} at rest, interpenetration at the end below "
        f"{MAX_PENETRATION_FRACTION:.0%} of the smallest piece's width. Pile top: highest hull "
        f"point. Upright: axis within {UPRIGHT_DEGREES:.0f}° of vertical. Worst: over the run "
        "(Bullet sampled once per frame).",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", default="256,1024",
                        help="comma-separated piece counts (default 256,1024; the issue's "
                             "sizes are 256,1024,4096)")
    parser.add_argument("--duration", type=float, default=3.0, help="simulated seconds (default 3)")
    parser.add_argument("--threads", type=int, default=None,
                        help="numba threads for dempipe (default: all of NUMBA_NUM_THREADS)")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    parser.add_argument("--profile", action="store_true",
                        help="also print where Bullet's step goes (pybullet's profiler, "
                             "on two frames after the run)")
    args = parser.parse_args(argv)

    if importlib.util.find_spec("pybullet") is None:
        print("vs_bullet: pybullet is not installed, so there is nothing to compare against.\n"
              "vs_bullet: pip install pybullet   (or pip install 'dempipe[bench]')",
              file=sys.stderr)
        return 2
    with quiet_stdout():
        import pybullet as p

    try:
        counts = [int(s) for s in args.n.split(",") if s.strip()]
    except ValueError:
        parser.error(f"--n: expected comma-separated integers, got {args.n!r}")
    if not counts or any(c < 1 or c > LATTICE for c in counts):
        parser.error(f"--n: piece counts must be 1..{LATTICE:,} (the scene's lattice)")
    if not args.duration > 0:
        parser.error("--duration must be positive")
    n_frames = int(round(args.duration * BLENDER_FPS))
    if n_frames < 1:
        parser.error(f"--duration must be at least one frame (1/{BLENDER_FPS} s)")
    duration = n_frames / BLENDER_FPS

    import numba

    threads = args.threads or numba.config.NUMBA_NUM_THREADS
    if not 1 <= threads <= numba.config.NUMBA_NUM_THREADS:
        parser.error(f"--threads must be 1..{numba.config.NUMBA_NUM_THREADS} "
                     "(NUMBA_NUM_THREADS)")

    from dempipe.spheres.cache import SphereCache

    info = machine(threads)
    load_start = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    cache = SphereCache()
    rows = []
    try:
        run_sizes(p, counts, duration, n_frames, threads, args.profile, cache, rows)
    except KeyboardInterrupt:
        log("interrupted: the table holds the sizes that finished")
    done = [n for n in counts if sum(r["n"] == n for r in rows) == 2]
    rows = [r for r in rows if r["n"] in done]
    info["load_average"] = [load_start,
                            os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan]
    print(table(rows, info, duration))
    for r in rows:
        if r.get("profile"):
            prof = dict(r["profile"])
            ms = prof.pop("ms_per_step")
            print(f"# where Bullet's step goes, {r['n']:,} pieces, settled pile ({ms:.1f} ms/step): "
                  + ", ".join(f"{k} {v:.0%}" for k, v in prof.items()))
    verdicts = []
    for n in done:
        rb, rd = (next(r for r in rows if r["n"] == n and r["engine"] == e)
                  for e in ("bullet", "dempipe"))
        speed = (rb["wall_seconds"] / rb["sim_seconds"]) / (rd["wall_seconds"] / rd["sim_seconds"])
        ok = rb["plausible"] and rd["plausible"]
        if speed < 2.0:
            goal = "misses the 2x goal"
        elif ok:
            goal = "meets the 2x goal"
        else:   # fast enough, but one of the two piles is not a settled pile
            goal = "2x on speed, but the goal asks for two settled piles"
        verdicts.append(f"- {n:,} pieces: dempipe is {speed:.2f}x Bullet's speed per simulated "
                        f"second; the comparison {'counts' if ok else 'does not count'} (Bullet: "
                        f"{rb['why']}; dempipe: {rd['why']}); {goal}.")
    print("\n" + "\n".join(verdicts))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(machine=info, duration=duration, rest_speed=REST_SPEED,
                           rest_fraction=REST_FRACTION,
                           max_penetration_fraction=MAX_PENETRATION_FRACTION,
                           bullet=dict(fps=BLENDER_FPS, substeps=BLENDER_SUBSTEPS,
                                       solver_iterations=BLENDER_SOLVER_ITERATIONS,
                                       linear_damping=BLENDER_LINEAR_DAMPING,
                                       angular_damping=BLENDER_ANGULAR_DAMPING),
                           rows=rows), f, indent=2)
        log(f"wrote {args.json}")
    return 0


def run_sizes(p, counts, duration, n_frames, threads, profile, cache, rows) -> None:
    """Bullet, then dempipe, for each piece count; appends a row per engine."""
    for n in counts:
        log(f"{n:,} pieces: building the scene")
        model = dempipe_model(n, duration, cache)
        pieces = Pieces(model)
        log(f"{n:,} pieces: Bullet, {n_frames * BLENDER_SUBSTEPS} steps")
        rb = run_bullet(p, model, pieces, duration, profile)
        rb["n"] = n
        rows.append(rb)
        log(f"{n:,} pieces: dempipe, {(model.n_frames - 1) * model.steps_per_frame:,} steps "
            f"of {model.dt * 1e6:.1f} us")
        rd = run_dempipe(model, pieces, threads)
        rd["n"] = n
        rows.append(rd)
        speed = (rb["wall_seconds"] / rb["sim_seconds"]) / (rd["wall_seconds"] / rd["sim_seconds"])
        counts_ok = rb["plausible"] and rd["plausible"]
        log(f"{n:,} pieces: dempipe {speed:.2f}x Bullet's speed; comparison "
            f"{'counts' if counts_ok else 'does NOT count'} (Bullet: {rb['why']}; "
            f"dempipe: {rd['why']})")


if __name__ == "__main__":
    sys.exit(main())
