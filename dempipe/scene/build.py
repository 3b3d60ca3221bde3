"""build_model(scene): a scene file's description turned into a Model.

This is the one place that joins the scene file (scene.py), the shapes
(shapes.py), the sphere sets and their cache (spheres.py, cache.py) and the
model builder (model.py). ``overrides`` let `dempipe report` vary resolution,
stiffness and dt without editing the scene.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from dempipe.check.sizes import check_lattice, preflight_scene
from dempipe.errors import MeshError, SceneError, ShapeError
from dempipe.mesh.shapes import build_shape, load_mesh
from dempipe.scene.placement import (
    collider_frame,
    expand_bodies,
    group_frame,
    split_into_pieces,
)
from dempipe.sim import laws
from dempipe.sim.builder import ModelBuilder
from dempipe.sim.model import Model, quat_to_matrix
from dempipe.spheres.fidelity import auto_mode
from dempipe.spheres.options import DEFAULT_MODE, DEFAULT_SPACING, BuildOptions
from dempipe.spheres.pieces import build_pieces
from dempipe.spheres.sphere_set import (
    build_sphere_set_with_info,
    diameter_for_resolution,
)


@dataclass(frozen=True)
class Overrides:
    """Settings that replace the scene file's (None: keep the scene's).

    diameter [m] or resolution (spheres across the smallest shape's longest extent);
    stiffness_factor multiplies every material's stiffness (auto included);
    dt [s] or dt_factor (times the auto step); duration [s]; sleeping on/off;
    contact_layers (0: every sphere takes part in contacts); spheres: the sphere-set
    mode of every shape and mesh collider ("lattice" or "surface"); contact_law: the
    contact force law ("linear" or "hertz", laws.LAWS).
    """

    diameter: float | None = None
    resolution: int | None = None
    stiffness_factor: float = 1.0
    dt: float | str | None = None
    dt_factor: float = 1.0
    duration: float | None = None
    sleeping: bool | None = None
    contact_layers: int | None = None
    spheres: str | None = None
    contact_law: str | None = None


def _named(where: str, build, *args, **kwargs):
    """``build(*args, **kwargs)``, its ShapeError or MeshError prefixed with ``where``
    (the scene file and key: 'scene.toml: shapes.b: shape 'torus': minor_radius ...')."""
    try:
        return build(*args, **kwargs)
    except (ShapeError, MeshError) as exc:
        raise type(exc)(f"{where}: {exc}") from None


def shape_mesh(spec, where: str):
    """The mesh of a scene's shape (a copy of its file's, or its built-in shape built);
    ``where`` names the shape in error messages."""
    if spec.mesh is not None:
        return spec.mesh.copy()
    if spec.builtin is not None:
        return _named(where, build_shape, spec.builtin, **dict(spec.params))
    return _named(where, load_mesh, spec.mesh_path, scale=spec.scale)


def with_center_of_mass(ss, com):
    """``ss`` with its centre of mass moved to ``com`` (mesh coordinates [m]): sphere
    centres re-expressed about it and the inertia per unit density moved there by
    the parallel-axis theorem (a MassAPI centerOfMass given without an inertia)."""
    com = np.asarray(com, dtype=np.float64)
    d = com - np.asarray(ss.com)
    inertia = np.asarray(ss.inertia) + ss.volume * (float(d @ d) * np.eye(3) - np.outer(d, d))
    return replace(ss, centers=np.asarray(ss.centers) - d, com=com, inertia=inertia,
                   key=f"{ss.key}:com{com.tolist()}")


def collider_mesh(c, where: str):
    """A mesh collider's mesh moved into the world: scale, rotate, translate."""
    if c.mesh is not None:
        mesh = c.mesh.copy()
        if c.scale != 1.0:
            mesh.apply_scale(c.scale)
    elif c.builtin is not None:
        mesh = _named(where, build_shape, c.builtin, **dict(c.params))
        if c.scale != 1.0:
            mesh.apply_scale(c.scale)
    else:
        mesh = _named(where, load_mesh, c.mesh_path, scale=c.scale)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(np.asarray(c.rotation, dtype=np.float64))
    T[:3, 3] = c.position
    mesh.apply_transform(T)
    return mesh


def sphere_options(scene, shape: str | None = None, overrides: Overrides | None = None,
                   mesh=None):
    """The sphere builder's options for a shape of the scene (None: a mesh collider):
    the override's mode, else the shape's ``spheres``, else the scene's, else
    spheres.DEFAULT_MODE. "auto" becomes ``mesh``'s own (fidelity.auto_mode). A
    fractured shape's pieces share one lattice: it keeps the lattice whatever the scene
    or an override asks (the shape's own "surface" is refused when the scene is read).
    The surface spacing
    likewise: the shape's ``surface_spacing``, else the scene's, else
    spheres.DEFAULT_SPACING (a lattice ignores it)."""
    mode = overrides.spheres if overrides is not None else None
    if mode is None and shape is not None:
        mode = scene.shapes[shape].spheres
    if mode is None:
        mode = getattr(scene.simulation, "spheres", None) or DEFAULT_MODE
    if shape is not None and scene.shapes[shape].fracture is not None:
        mode = "lattice"
    elif mode == "auto":
        mode = auto_mode(mesh.vertices, mesh.faces)
    spacing = scene.shapes[shape].surface_spacing if shape is not None else None
    if spacing is None:
        spacing = getattr(scene.simulation, "surface_spacing", None) or DEFAULT_SPACING
    return BuildOptions(mode=mode, spacing=spacing)


def build_model(scene, *, cache=None, overrides: Overrides | None = None,
                force: bool = False) -> Model:
    """The Model of a loaded Scene (see scene.load_scene).

    cache : a SphereCache, or None for no caching.
    force : accept a user dt above the critical step (see ModelBuilder.finalize).
    The returned Model's ``build_info`` holds sphere-set build time and cache hits.
    """
    o = overrides or Overrides()
    src = scene.path.name if scene.path else "<scene>"
    sim = scene.simulation
    out = scene.output
    used = []
    for g in scene.bodies:
        used += [g.shape] if isinstance(g.shape, str) else list(g.shape)
    names = list(dict.fromkeys(used))
    meshes = {n: shape_mesh(scene.shapes[n], f"{src}: shapes.{n}") for n in names}

    if o.diameter is not None:
        d = float(o.diameter)
    elif o.resolution is None and sim.sphere_diameter is not None:
        d = float(sim.sphere_diameter)
    else:
        res = o.resolution or sim.resolution
        # "spheres across the longest extent of the smallest shape"
        d = min(diameter_for_resolution(meshes[n], res) for n in names)

    # sizes checked before anything is allocated: lattices, bodies (one line naming
    # the key that makes a scene too big for this machine)

    preflight_scene(scene, meshes, d)
    t0 = time.perf_counter()
    hits = []
    layers = sim.contact_layers if o.contact_layers is None else o.contact_layers
    b = ModelBuilder(d, gravity=sim.gravity, contact_layers=layers, cache=cache)
    material_index = {}
    for name, spec in scene.materials.items():
        m = spec.to_material()
        if o.stiffness_factor != 1.0 and m.stiffness is not None:
            m = replace(m, stiffness=m.stiffness * o.stiffness_factor)
        if o.stiffness_factor != 1.0 and m.young_modulus is not None:     # K ∝ E
            m = replace(m, young_modulus=m.young_modulus * o.stiffness_factor)
        material_index[name] = b.add_material(m)
    shape_index = {}
    pieces = {}     # fractured shape -> [(piece shape name, com, volume)]
    for n in names:
        if scene.shapes[n].fracture is not None:
            try:
                fractured, info = build_pieces(meshes[n], d, scene.shapes[n].fracture,
                                               name=n, cache=cache,
                                               options=sphere_options(scene, n, o, meshes[n]))
            except ShapeError as e:         # (MeshError too) the key that asked for it
                why = str(e).removeprefix(f"{n}: ")
                raise SceneError(f"{src}: shapes.{n}.fracture: {why}") from None
            hits.append((n, info.cache, info.seconds,
                         sum(ps.count for ps in fractured.sphere_sets)))
            pieces[n] = []
            for k, (piece, ps) in enumerate(zip(fractured.pieces, fractured.sphere_sets)):
                pn = f"{n}_piece_{k:02d}"
                shape_index[pn] = b.add_shape(pn, piece.trimesh(), ps, inside_faces=piece.inside)
                pieces[n].append((pn, ps.com, ps.volume))
            continue
        ss, info = build_sphere_set_with_info(meshes[n], d, name=f"{src}: shapes.{n}",
                                              cache=cache,
                                              options=sphere_options(scene, n, o, meshes[n]))
        hits.append((n, info.cache, info.seconds, ss.count))
        if scene.shapes[n].center_of_mass is not None:
            ss = with_center_of_mass(ss, scene.shapes[n].center_of_mass)
        shape_index[n] = b.add_shape(n, meshes[n], ss)
    glue_next = 0
    for gi, (g, placement) in enumerate(zip(scene.bodies, expand_bodies(scene))):
        split = split_into_pieces(placement, pieces, glue_start=glue_next)
        glue_next = int(split.glue.max()) + 1 if (split.glue >= 0).any() else glue_next
        placement = split.placement
        n_g = len(placement.positions)
        if g.inertia is not None and len(split.labels) != g.count:
            raise SceneError(f"{src}: bodies[{gi}].inertia: not for a fractured shape "
                             "(remove it: each piece's inertia comes from its mesh)")
        b.add_bodies(placement.name, [shape_index[n] for n in placement.body_shapes()],
                     material_index[placement.material], placement.positions,
                     placement.rotations, placement.velocities, placement.angular_velocities,
                     masses=None if g.mass is None else float(g.mass) * split.mass_share,
                     inertias=(None if g.inertia is None
                               else np.broadcast_to(np.asarray(g.inertia, float), (n_g, 3, 3))),
                     asleep=np.full(n_g, bool(g.starts_asleep)),
                     kinematic=g.kinematic, motion=g.motion,
                     start_time=(placement.start_times if placement.start_times is not None
                                 else g.start_time),
                     group_frame=g.layout != "single",
                     frame=group_frame(g, placement) if g.kinematic else None,
                     labels=split.labels,
                     # the pieces of one fractured instance share a glue id (-1: whole)
                     glue=split.glue if g.glue else None)
    up = out.up_index
    for c in scene.colliders:
        kind = type(c).__name__
        mi = material_index[c.material]
        if kind == "PlaneCollider":
            b.add_plane(c.point, c.normal, mi, motion=c.motion)
        elif kind == "BoxCollider":
            b.add_box(c.min, c.max, c.open_top, mi, c.thickness, up=up,
                      motion=c.motion)
        else:
            mesh = collider_mesh(c, f"{src}: colliders.{c.name}")
            check_lattice(mesh, d, f"{src}: colliders.{c.name}",
                          "Fix: scale the collider down or use a plane or box collider",
                          f"collider '{c.name}'")
            ss, info = build_sphere_set_with_info(mesh, d, name=f"{src}: colliders.{c.name}",
                                                  cache=cache,
                                                  options=sphere_options(scene, None, o, mesh))
            hits.append((c.name, info.cache, info.seconds, ss.count))
            b.add_static_mesh(c.name, mesh, ss, mi, motion=c.motion,
                              frame=collider_frame(c))
    build_seconds = time.perf_counter() - t0

    fps = out.fps
    duration = out.duration if o.duration is None else o.duration
    n_frames = int(round(duration * fps)) + 1
    if n_frames < 2:        # frame 0 alone: a file with nothing animated
        key = "output.duration" if o.duration is None else "duration (the override)"
        raise SceneError(f"{src}: {key}: {duration:g} s is less than half a frame at {fps} "
                         f"fps, so the bake would write frame 0 alone (give at least "
                         f"{1.0 / fps:.4g} s, one frame)")
    dt = o.dt if o.dt is not None else sim.dt
    target = sim.stiffness_target_overlap or 0.02
    law_name = o.contact_law or sim.contact_law
    # dt_factor 0.5: twice the steps
    steps_per_contact = laws.law(law_name).STEPS_PER_CONTACT / o.dt_factor
    if o.stiffness_factor != 1.0:
        # auto stiffness scales through the target overlap (the law says how)
        target = laws.law(law_name).overlap_for_stiffness_factor(target, o.stiffness_factor)
    model = b.finalize(fps=fps, n_frames=n_frames, first_frame=out.start_frame, dt=dt,
                       target_overlap=target, steps_per_contact=steps_per_contact,
                       up_axis=out.up_axis, meters_per_unit=out.meters_per_unit,
                       where=f"{src}: simulation.dt", force=force, contact_law=law_name,
                       sleep=((sim.sleep.linear_speed, sim.sleep.angular_speed, sim.sleep.time)
                              if (o.sleeping if o.sleeping is not None else sim.sleeping)
                              else None))
    return replace(model, build_info=dict(sphere_build_seconds=build_seconds, shapes=hits,
                                          source=str(scene.path) if scene.path else None))


def initial_overlap(model: Model, state=None):
    """Largest overlap at the start, as (fraction of the diameter, body index or -1).

    Runs stages 1-4 once on the CPU (no step is taken), so it sees sphere-sphere
    and sphere-wall overlaps exactly as the first step will.
    """
    from dempipe.sim.kernels.cpu.backend import CpuBackend

    if model.n_spheres == 0:
        return 0.0, -1
    st = state or model.initial_state()
    be = CpuBackend(model)
    be.probe(st)
    ov = be.sphere_overlap
    i = int(np.argmax(ov))
    body = int(model.sphere_body[i]) if ov[i] > 0 else -1
    return float(ov[i] / model.diameter), body


def full_sphere_model(scene, model: Model, *, cache=None) -> Model | None:
    """The scene's Model with every sphere of every set taking part in contacts, or
    None when ``model`` already has them all (contact_layers 0).

    Surface spheres (docs/spheres.md) leave out the spheres no contact reaches while
    overlaps stay small; a body placed wholly inside another at frame 0 touches only
    those, so frame-0 overlaps are checked against this Model as well.
    """
    if not getattr(model, "contact_layers", 0):
        return None
    # the model's own step (it divides a frame exactly): the same dt whatever the
    # scene asked for, so a dt that was refused and replaced by "auto" stays replaced
    return build_model(scene, cache=cache,
                       overrides=Overrides(contact_layers=0, dt=float(model.dt)), force=True)


def initial_overlap_all_spheres(scene, model: Model, *, cache=None):
    """``initial_overlap`` of ``model`` and of its full-sphere twin (full_sphere_model),
    whichever is larger: (fraction of the diameter, body index or -1)."""
    overlap, body = initial_overlap(model)
    full = full_sphere_model(scene, model, cache=cache)
    if full is not None:
        o2, b2 = initial_overlap(full)
        if o2 > overlap:
            overlap, body = o2, b2
    return overlap, body

