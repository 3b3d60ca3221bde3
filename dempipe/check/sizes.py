"""Sizes: what a bake needs in memory and in steps, and the sizes refused before the work.

    memory_estimate(model)                 # bytes: Model, CPU scratch, State, Frames
    preflight_scene(scene, meshes, d)      # before any sphere set: lattices, bodies
    check_run_time(model, "scene.toml")    # after the Model: steps, frames, USD layer

A setting off by orders of magnitude is refused at once, naming the key to
change, rather than after hours of voxelizing or when memory runs out.
docs/stability.md, "Sizes refused before the work", gives the limits and why.
Everything here is computed from sizes; nothing is allocated. No numba, no pxr.
"""

from __future__ import annotations

import math
from dataclasses import fields

import numpy as np

from dempipe.errors import StabilityError
from dempipe.sim.kernels.layout import cpu_scratch, layout_bytes
from dempipe.sim.model import Features, Model
from dempipe.sim.state import CONTACT_SLOTS


def memory_estimate(model: Model) -> dict:
    """Bytes of the Model's arrays, the CPU backend's scratch, one State and the Frames.

    Computed from sizes (nothing is allocated); the scratch is the sum of
    ``kernels.layout.cpu_scratch``, the layout ``CpuBackend`` allocates from.
    """
    seen = set()
    model_bytes = 0

    def add(a):
        nonlocal model_bytes
        if isinstance(a, np.ndarray) and id(a) not in seen:
            seen.add(id(a))
            model_bytes += a.nbytes

    for f in fields(model):
        add(getattr(model, f.name))
    for s in model.shapes:
        for a in (s.vertices, s.faces, s.com, s.sphere_set.centers):
            add(np.asarray(a))
    for m in model.static_meshes:
        add(m.vertices)
        add(m.faces)
    for b in model.boxes:
        add(b.lo)
        add(b.hi)
    nb = int(model.body_mass.shape[0])
    ns = model.n_spheres
    f8, i8, i4 = 8, 8, 4
    scratch = layout_bytes(cpu_scratch(model, model.features.friction))
    state = nb * (3 + 4 + 3 + 3) * f8 + nb * i4        # x, q, P, L; body_rest
    if model.features.friction:   # contact histories (static friction), see State
        state += ns * CONTACT_SLOTS * (i4 + 3 * f8)
    frames = model.n_frames * (i8 + f8 + model.n_bodies * (3 + 4 + 3 + 3) * f8)
    return dict(model=int(model_bytes), cpu_scratch=int(scratch), state=int(state),
                frames=int(frames), total=int(model_bytes + scratch + state + frames))


# ----------------------------------------------------------------- preflight: size

#: A bake is refused when its total work passes this many sphere-steps (about
#: three years at 10 M sphere-steps/s, a CPU's pace), or a frame needs more than
#: MAX_STEPS_PER_FRAME steps: both mean a setting is off by orders of magnitude.
MAX_SPHERE_STEPS = 1e15
MAX_STEPS_PER_FRAME = 10_000_000
#: Frames in one bake at most (11.6 hours of animation at 24 fps), and the frame rate
#: above which a frame count that passes it is blamed on output.fps.
MAX_FRAMES = 1_000_000
MAX_FPS = 10_000
#: Bytes of USD layer per body and frame when all move (positions, orientations,
#: velocities, angular velocities as float32/half, and Sdf's bookkeeping).
USD_SAMPLE_BYTES = 64
#: Share of the memory available that a bake may plan to use.
MEMORY_SHARE = 0.8
#: Bytes per cell of the voxelization lattice while a sphere set is built
#: (centres, winding numbers, masks: spheres.lattice_centers and inside_mask).
LATTICE_BYTES = 64


def memory_available() -> int:
    """Bytes of memory this process may still use: MemAvailable (Linux), else the
    physical memory."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import os

        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB" if n < 2**70 else f"{n:.3g} bytes"


def lattice_cells(extents, diameter: float) -> float:
    """Cells of the voxelization lattice of a shape of ``extents`` [m] (a float:
    it may be far beyond any integer type)."""
    # floats throughout: numpy multiplies Python ints as int64, which wraps to 0 at
    # 2e12 cells an axis (then no size would be refused)
    return float(np.prod([max(1.0, float(math.ceil(float(e) / diameter - 1e-9)))
                          for e in np.asarray(extents, dtype=np.float64)]))


def check_lattice(mesh, diameter: float, key: str, fix: str, what: str = "shape",
                  available: int | None = None) -> None:
    """Refuse (StabilityError naming ``key``) a sphere set whose voxelization lattice
    would not fit in memory."""
    cells = lattice_cells(mesh.extents, diameter)
    need = cells * LATTICE_BYTES
    have = memory_available() if available is None else available
    if need > MEMORY_SHARE * have:
        most = (MEMORY_SHARE * have / LATTICE_BYTES) ** (1.0 / 3.0)
        raise StabilityError(
            f"{key}: spheres of d = {diameter:.3g} m put {cells:.3g} lattice cells in the "
            f"{what} ({'×'.join(f'{e:.3g}' for e in mesh.extents)} m), which needs about "
            f"{_gib(need)} to voxelize; this machine has {_gib(have)} available. {fix} "
            f"(about {most:.0f} spheres across at most)")


def preflight_scene(scene, meshes: dict, diameter: float, available: int | None = None) -> None:
    """Before any sphere set is built or body placed: refuse a scene whose sphere
    sets, bodies or frames cannot fit in memory, naming the key responsible.

    meshes : the shapes' meshes by name; diameter : the sphere diameter [m].
    Spheres per body are estimated from each shape's lattice and its share of
    its bounding box; the bytes per sphere and per body come from
    :func:`memory_for` (the CPU backend's arrays, the State, the Model).
    """
    have = memory_available() if available is None else available
    src = scene.path.name if scene.path else "<scene>"
    res_key = ("simulation.sphere_diameter" if scene.simulation.sphere_diameter is not None
               else "simulation.resolution")
    res_fix = ("raise simulation.sphere_diameter" if res_key.endswith("diameter")
               else "lower simulation.resolution")
    spheres_of = {}
    for name, mesh in meshes.items():
        check_lattice(mesh, diameter, f"{src}: {res_key}", f"Fix: {res_fix}",
                      f"shape '{name}'", have)
        box = float(np.prod(np.maximum(mesh.extents, 1e-300)))
        fill = min(1.0, abs(float(getattr(mesh, "volume", box))) / box) if box > 0 else 1.0
        spheres_of[name] = max(1.0, lattice_cells(mesh.extents, diameter) * fill)
    friction = any(m.friction for m in scene.materials.values()) if scene.materials else True
    per_group = []
    for i, g in enumerate(scene.bodies):
        shapes = [g.shape] if isinstance(g.shape, str) else list(g.shape)
        per_body = max(spheres_of.get(s, 1.0) for s in shapes)
        # a fractured shape's body is its pieces: as many bodies, the same spheres
        pieces = max(getattr(scene.shapes[s].fracture, "pieces", 1) if s in scene.shapes
                     else 1 for s in shapes)
        per_group.append((i, float(g.count), float(g.count) * per_body, float(pieces)))
    n_bodies = sum(c * p for _, c, _, p in per_group)
    n_spheres = sum(s for _, _, s, _ in per_group)
    need = memory_for(n_spheres, n_bodies, friction)["total"]
    if need > MEMORY_SHARE * have and per_group:
        i, count, spheres, _ = max(per_group, key=lambda r: r[2])
        raise StabilityError(
            f"{src}: bodies[{i}].count = {int(count)}: {n_bodies:.3g} bodies of about "
            f"{n_spheres:.3g} spheres need about {_gib(need)}; this machine has "
            f"{_gib(have)} available. Fix: lower bodies[{i}].count (or {res_fix})")


def memory_for(n_spheres: float, n_bodies: float, friction: bool) -> dict:
    """Bytes a bake of this many spheres and bodies needs, before the Model exists:
    memory_estimate's accounting for a stand-in of these sizes (float counts, so
    that absurd sizes do not overflow)."""
    ns, nb = float(n_spheres), float(n_bodies)
    # the CPU scratch, State and Model bytes per sphere and per body, from the same
    # accounting as memory_estimate (its terms divided out at a reference size)
    ref = _per_item_bytes(friction)
    total = ns * ref["sphere"] + nb * ref["body"]
    return dict(total=total, per_sphere=ref["sphere"], per_body=ref["body"])


_PER_ITEM: dict = {}


def _per_item_bytes(friction: bool) -> dict:
    """Bytes per sphere and per body of memory_estimate, measured on two stand-in
    sizes (so any change of the layout carries over)."""
    if friction in _PER_ITEM:
        return _PER_ITEM[friction]
    from dataclasses import make_dataclass


    def stand_in(ns, nb):
        z = np.zeros
        arrays = dict(
            body_mass=z(nb), sphere_body=z(ns, dtype=np.int32), sphere_offset=z((ns, 3)),
            body_sphere_start=z(nb + 1, dtype=np.int32), body_inv_mass=z(nb),
            body_inv_inertia=z((nb, 6)), body_material=z(nb, dtype=np.int32),
            body_radius=z(nb), initial_x=z((nb, 3)), initial_q=z((nb, 4)),
            initial_v=z((nb, 3)), initial_w=z((nb, 3)), body_shape=z(nb, dtype=np.int32),
            body_group=z(nb, dtype=np.int32), body_group_index=z(nb, dtype=np.int32))
        cls = make_dataclass("StandIn", list(arrays))
        m = cls(**arrays)
        m.n_bodies, m.n_spheres, m.n_frames, m.n_static = nb, ns, 1, 0
        m.features = Features(friction=friction, rotation=True, walls=True,
                              static_spheres=False, gravity=True, sleeping=True)
        m.shapes, m.static_meshes, m.boxes = (), (), ()
        return m

    a = _estimate_stand_in(stand_in(1000, 100))
    b = _estimate_stand_in(stand_in(2000, 100))
    c = _estimate_stand_in(stand_in(1000, 200))
    per_sphere = (b - a) / 1000.0
    per_body = (c - a) / 100.0
    _PER_ITEM[friction] = dict(sphere=max(per_sphere, 1.0), body=max(per_body, 1.0))
    return _PER_ITEM[friction]


def _estimate_stand_in(m) -> float:
    """memory_estimate of a stand-in model (its Model fields as plain arrays)."""
    e = memory_estimate(m)
    return float(e["total"] - e["frames"])


def check_run_time(model, src: str, scene=None) -> None:
    """Refuse (StabilityError naming the key) a bake whose steps are beyond reason:
    more than MAX_STEPS_PER_FRAME steps per frame, or MAX_SPHERE_STEPS in all."""
    spf = float(model.steps_per_frame)
    frames = float(model.n_frames - 1)
    if spf > MAX_STEPS_PER_FRAME:
        raise StabilityError(
            f"{src}: simulation.dt = {model.dt:.3g} s needs {spf:.3g} steps per frame at "
            f"{model.fps:g} fps (at most {MAX_STEPS_PER_FRAME:.0e}): the contacts are far too "
            f"stiff for the speeds (check simulation.gravity, the bodies' velocity and "
            f"simulation.stiffness_target_overlap) or dt is far too small. Fix: bring those "
            f"to physical values, or set materials' stiffness")
    if scene is not None:
        out = scene.output
        key = "output.fps" if out.fps > MAX_FPS else "output.duration"
    else:
        key = "output.duration"
    if frames + 1 > MAX_FRAMES:
        raise StabilityError(
            f"{src}: {key}: {frames + 1:.3g} frames at {model.fps:g} fps (at most "
            f"{MAX_FRAMES:.0e} in one bake). Fix: lower {key}, or bake the animation in "
            f"parts with --frames")
    # the USD layer holds every kept sample while it is written (usd/animation.py): about
    # USD_SAMPLE_BYTES per body and frame when every body moves at every frame
    need = (frames + 1) * float(model.n_bodies) * USD_SAMPLE_BYTES
    have = memory_available()
    if need > MEMORY_SHARE * have:
        raise StabilityError(
            f"{src}: {key}: {frames + 1:.3g} frames of {model.n_bodies} bodies may need about "
            f"{_gib(need)} to write as USD; this machine has {_gib(have)} available. Fix: "
            f"lower {key}, or bake in parts with --frames")
    work = spf * frames * float(max(model.n_spheres, 1))
    if work > MAX_SPHERE_STEPS:
        key = "output.duration" if frames * spf > 1e9 else "simulation.resolution"
        if scene is not None and scene.output.fps * scene.output.duration > 1e6:
            key = "output.fps" if scene.output.fps > 1000 else "output.duration"
        raise StabilityError(
            f"{src}: {key}: {frames:.3g} frames of {spf:.3g} steps over {model.n_spheres} "
            f"spheres are {work:.3g} sphere-steps, years of computing (at most "
            f"{MAX_SPHERE_STEPS:.0e}). Fix: lower {key}")
