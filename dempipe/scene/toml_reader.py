"""A TOML scene's tables, validated into the frozen records of
:mod:`dempipe.scene.data`; errors name the key path (:mod:`dempipe.scene.keys`).

The format is documented key by key in ``docs/scene-format.md``. Conventions:
SI units; positions place the mesh's own origin (not the centre of mass);
quaternions are (w, x, y, z); the up axis is "Z" (default) or "Y".

This module imports neither numba nor pxr.
"""

from __future__ import annotations

import difflib
import math
from typing import Any

from dempipe.mesh.fracture import MAX_PIECES, FractureSpec
from dempipe.scene.data import (
    BodyGroup,
    BoxCollider,
    Collider,
    MaterialSpec,
    MeshCollider,
    PlaneCollider,
    Scene,
    ShapeSpec,
)
from dempipe.scene.keys import SceneKeys, describe_value, known_names, suggestion
from dempipe.scene.settings import parse_output, parse_simulation, surface_spacing
from dempipe.sim.motion import Key, Motion
from dempipe.spheres.options import SCENE_MODES

# ------------------------------------------------------------------------- tables


#: The top-level tables of a scene file.
TOP_KEYS = ("output", "simulation", "materials", "shapes", "bodies", "colliders", "usd")
_MATERIAL_KEYS = ("density", "restitution", "friction", "stiffness", "young_modulus",
                  "poisson_ratio", "rolling_friction", "glue_strength", "glue_stiffness",
                  "glue_damping")
_BODY_COMMON = ("name", "shape", "material", "count", "layout", "rotation", "velocity",
                "angular_velocity", "kinematic", "motion", "start_time", "glue")
_LAYOUT_KEYS = {
    "single": ("position",),
    "grid": ("origin", "dims", "spacing"),
    "random": ("region_min", "region_max"),
    "emit": ("region_min", "region_max", "rate"),
}
_COLLIDER_KEYS = {
    "plane": ("type", "name", "material", "point", "normal", "motion"),
    "box": ("type", "name", "material", "min", "max", "open_top", "thickness", "motion"),
    "mesh": ("type", "name", "material", "mesh", "builtin", "scale", "position", "rotation",
             "motion"),
}
_MOTION_KEYS = ("velocity", "angular_velocity", "pivot", "keys", "interpolation")
_MOTION_RATES = ("velocity", "angular_velocity", "pivot")
_KEY_KEYS = ("time", "position", "rotation")
_INTERPOLATIONS = ("linear", "smooth")     # motion.INTERPOLATIONS


def _load_shape_registry():
    """The built-in shapes (``dempipe.mesh.shapes.SHAPES``); imported when a scene is
    read, since it loads trimesh and manifold3d."""
    from dempipe.mesh.shapes import SHAPES

    return SHAPES






def _parse_materials(ctx: SceneKeys, d: Any) -> dict[str, MaterialSpec]:
    d = ctx.table(d, "materials")
    out = {"default": MaterialSpec("default")}
    for name, m in d.items():
        key = f"materials.{name}"
        ctx.usd_name(name, key)
        m = ctx.table(m, key)
        ctx.check_keys(m, key, _MATERIAL_KEYS)
        kw: dict[str, Any] = {}
        if "density" in m:
            kw["density"] = ctx.number(m["density"], f"{key}.density", lo=0.0, lo_open=True,
                                       unit="kg/m^3")
        if "restitution" in m:
            kw["restitution"] = ctx.number(m["restitution"], f"{key}.restitution",
                                           lo=0.0, hi=1.0)
        if "friction" in m:
            kw["friction"] = ctx.number(m["friction"], f"{key}.friction", lo=0.0)
        if "rolling_friction" in m:
            kw["rolling_friction"] = ctx.number(m["rolling_friction"],
                                                f"{key}.rolling_friction", lo=0.0)
        if "stiffness" in m:
            v = m["stiffness"]
            if isinstance(v, str):
                kw["stiffness"] = ctx.string(v, f"{key}.stiffness", ("auto",),
                                             or_number="a stiffness in N/m, e.g. 2e4")
            else:
                kw["stiffness"] = ctx.number(v, f"{key}.stiffness", lo=0.0, lo_open=True,
                                             unit='N/m, or "auto"')
        if "young_modulus" in m:
            kw["young_modulus"] = ctx.number(m["young_modulus"], f"{key}.young_modulus",
                                             lo=0.0, lo_open=True, unit="Pa")
            if kw.get("stiffness", "auto") != "auto":
                raise ctx.error(key, "both stiffness and young_modulus are given",
                                "keep one: young_modulus sets the Hertz constant K")
        if "poisson_ratio" in m:
            if "young_modulus" not in m:
                raise ctx.error(f"{key}.poisson_ratio", "given without young_modulus",
                                "add young_modulus in Pa, or remove poisson_ratio")
            kw["poisson_ratio"] = ctx.number(m["poisson_ratio"], f"{key}.poisson_ratio",
                                             lo=0.0, hi=0.4999)
        if "glue_strength" in m:
            kw["glue_strength"] = ctx.number(m["glue_strength"], f"{key}.glue_strength",
                                             lo=0.0, lo_open=True, unit="Pa")
        if "glue_stiffness" in m:
            v = m["glue_stiffness"]
            if isinstance(v, str):
                kw["glue_stiffness"] = ctx.string(v, f"{key}.glue_stiffness", ("auto",),
                                                  or_number="a stiffness in N/m, e.g. 2e4")
            else:
                kw["glue_stiffness"] = ctx.number(v, f"{key}.glue_stiffness", lo=0.0,
                                                  lo_open=True, unit='N/m, or "auto"')
        if "glue_damping" in m:
            kw["glue_damping"] = ctx.number(m["glue_damping"], f"{key}.glue_damping", lo=0.0)
        for k in ("glue_stiffness", "glue_damping"):
            if k in m and "glue_strength" not in m:
                raise ctx.error(f"{key}.{k}", "given without glue_strength",
                                "add glue_strength in Pa (the glue's tensile strength), "
                                f"or remove {k}")
        out[name] = MaterialSpec(name, **kw)
    return out


def _check_builtin(ctx: SceneKeys, key: str, builtin: str, params: dict, registry) -> dict:
    """Check a built-in shape's name, parameter names and values against ``SHAPES``.

    Returns the parameters with values normalized by kind (float lengths, tuples of
    three floats, ints) where the registry says the kind.
    """
    for k, v in params.items():
        if isinstance(v, float) and not math.isfinite(v):
            raise ctx.error(f"{key}.{k}", f"expected a finite number, got {v!r}")
        if isinstance(v, dict):
            raise ctx.error(f"{key}.{k}", f"expected a parameter value, got {describe_value(v)}")
    if registry is None:
        return dict(params)
    if builtin not in registry:
        raise ctx.error(f"{key}.builtin", f"unknown built-in shape {builtin!r}",
                        suggestion(builtin, sorted(registry)))
    known = getattr(registry[builtin], "params", None)
    if known is None:
        return dict(params)
    out = {}
    for k, v in params.items():
        if k not in known:
            close = difflib.get_close_matches(k, list(known), n=1, cutoff=0.6)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ctx.error(f"{key}.{k}", f"unknown parameter for {builtin!r}",
                            f"{hint}known: {known_names(known)}")
        kind = getattr(known[k], "kind", None)
        if kind == "length":
            v = ctx.number(v, f"{key}.{k}", lo=0.0, lo_open=True, unit="metres")
        elif kind == "vector3":
            v = ctx.vector(v, f"{key}.{k}")
            for j, x in enumerate(v):
                if x <= 0:
                    raise ctx.error(f"{key}.{k}[{j}]", f"{x:g} is out of range",
                                    "expected a number > 0 (metres)")
        elif kind == "int":
            lo, hi = getattr(known[k], "low", None), getattr(known[k], "high", None)
            v = ctx.integer(v, f"{key}.{k}", lo=lo, what="an integer")
            if hi is not None and v > hi:
                raise ctx.error(f"{key}.{k}", f"{v} is out of range",
                                f"expected an integer in {lo} .. {hi}")
        out[k] = v
    return out


def _parse_shapes(ctx: SceneKeys, d: Any, registry) -> dict[str, ShapeSpec]:
    d = ctx.table(d, "shapes")
    out = {}
    for name, s in d.items():
        key = f"shapes.{name}"
        ctx.usd_name(name, key)
        s = ctx.table(s, key)
        mode = None
        if "spheres" in s:
            mode = ctx.string(s["spheres"], f"{key}.spheres", SCENE_MODES)
            s = {k: v for k, v in s.items() if k != "spheres"}
        spacing = None
        if "surface_spacing" in s:
            spacing = surface_spacing(ctx, s["surface_spacing"], f"{key}.surface_spacing")
            s = {k: v for k, v in s.items() if k != "surface_spacing"}
        fracture = None
        if "fracture" in s:
            if mode == "surface":
                raise ctx.error(f"{key}.fracture", "a fractured shape needs lattice spheres",
                                "remove spheres = \"surface\": the pieces share one lattice")
            fracture = _parse_fracture(ctx, s["fracture"], f"{key}.fracture")
            s = {k: v for k, v in s.items() if k != "fracture"}
        has_b, has_m = "builtin" in s, "mesh" in s
        if has_b and has_m:
            raise ctx.error(key, "both builtin and mesh are given", "give only one of them")
        if not (has_b or has_m):
            hint = "add builtin = \"<shape>\" or mesh = \"<file>\""
            if registry is not None:
                hint += f"; built-in shapes: {known_names(sorted(registry))}"
            raise ctx.error(key, "needs builtin or mesh", hint)
        if has_m:
            ctx.check_keys(s, key, ("mesh", "scale"))
            scale = 1.0
            if "scale" in s:
                scale = ctx.number(s["scale"], f"{key}.scale", lo=0.0, lo_open=True)
            path = ctx.mesh_file(s["mesh"], f"{key}.mesh")
            out[name] = ShapeSpec(name=name, builtin=None, params={}, mesh_path=path, scale=scale,
                                  spheres=mode, surface_spacing=spacing,
                                  fracture=fracture)
        else:
            builtin = ctx.string(s["builtin"], f"{key}.builtin")
            params = {k: v for k, v in s.items() if k != "builtin"}
            if "scale" in params and (registry is None or builtin not in registry
                                      or "scale" not in getattr(registry[builtin], "params", {})):
                raise ctx.error(f"{key}.scale", "scale applies to mesh files only",
                                "set the built-in shape's size parameters instead")
            params = _check_builtin(ctx, key, builtin, params, registry)
            out[name] = ShapeSpec(name=name, builtin=builtin, params=params, mesh_path=None,
                                  scale=1.0, spheres=mode, surface_spacing=spacing,
                                  fracture=fracture)
    return out


_FRACTURE_KEYS = ("pieces", "seed", "impact", "impact_share", "impact_radius")


def _parse_fracture(ctx: SceneKeys, f: Any, key: str) -> FractureSpec:
    """``fracture = { pieces = N, seed = S, impact = [x, y, z], impact_share = f,
    impact_radius = r }`` -> a FractureSpec (docs/scenes.md, "Fracture")."""
    f = ctx.table(f, key)
    ctx.check_keys(f, key, _FRACTURE_KEYS)
    if "pieces" not in f:
        raise ctx.error(key, "needs pieces", f"e.g. {key.rsplit('.', 1)[-1]} = {{ pieces = 12 }}")
    kw: dict[str, Any] = dict(
        pieces=ctx.integer(f["pieces"], f"{key}.pieces", lo=2, hi=MAX_PIECES))
    if "seed" in f:
        kw["seed"] = ctx.integer(f["seed"], f"{key}.seed", lo=0)
    if "impact" in f:
        kw["impact"] = ctx.vector(f["impact"], f"{key}.impact")
    if "impact_share" in f:
        if "impact" not in f:
            raise ctx.error(f"{key}.impact_share", "given without impact",
                            "add impact = [x, y, z] (the shape's own coordinates, m)")
        kw["impact_share"] = ctx.number(f["impact_share"], f"{key}.impact_share", lo=0.0, hi=1.0)
    if "impact_radius" in f:
        kw["impact_radius"] = ctx.number(f["impact_radius"], f"{key}.impact_radius", lo=0.0,
                                         lo_open=True, unit="m")
    return FractureSpec(**kw)


def _material_ref(ctx: SceneKeys, v: Any, key: str, materials) -> str:
    v = ctx.string(v, key)
    if v not in materials:
        raise ctx.error(key, f"unknown material {v!r}", suggestion(v, list(materials)))
    return v


def _parse_motion(ctx: SceneKeys, m: Any, key: str, origin, rotation, owner: str) -> Motion:
    """``[<key>]`` (``[colliders.motion]``, ``[bodies.motion]``) -> a Motion.

    ``origin`` [m] and ``rotation`` (w, x, y, z, or None where unknown at parse
    time: a randomly rotated body) are the owner's authored frame: what a key's
    ``position`` and ``rotation`` default to. ``owner`` names it in messages."""
    m = ctx.table(m, key)
    ctx.check_keys(m, key, _MOTION_KEYS)
    rates = [k for k in _MOTION_RATES if k in m]
    if "keys" in m and rates:
        raise ctx.error(f"{key}.{rates[0]}", "given with keys",
                        "give keys (absolute poses over time) or rates (velocity, "
                        "angular_velocity, pivot), not both")
    if "keys" not in m:
        if "interpolation" in m:
            raise ctx.error(f"{key}.interpolation", "applies to keys only",
                            "remove it, or give keys = [{ time = 0.0, position = [...] }, ...]")
        if "velocity" not in m and "angular_velocity" not in m:
            raise ctx.error(key, "no motion given",
                            "give velocity = [vx, vy, vz] (m/s) and/or angular_velocity = "
                            "[wx, wy, wz] (rad/s), or keys = [{ time = 0.0, position = [...] }, "
                            "...]")
        kw: dict[str, Any] = {}
        for k in _MOTION_RATES:
            if k in m:
                kw[k] = ctx.vector(m[k], f"{key}.{k}")
        return Motion(**kw)
    raw = m["keys"]
    if not isinstance(raw, list) or not raw:
        what = "an empty array" if isinstance(raw, list) else describe_value(raw)
        raise ctx.error(f"{key}.keys", f"expected an array of one or more keys, got {what}",
                        "e.g. keys = [{ time = 0.0, position = [0, 0, 1] }, "
                        "{ time = 1.0, position = [1, 0, 1] }]")
    keys = []
    for j, k in enumerate(raw):
        kk = f"{key}.keys[{j}]"
        if not isinstance(k, dict):
            raise ctx.error(kk, f"expected a table, got {describe_value(k)}",
                            "write each key as { time = 0.0, position = [x, y, z], "
                            "rotation = [w, x, y, z] }")
        ctx.check_keys(k, kk, _KEY_KEYS)
        t = ctx.number(ctx.require(k, kk, "time", "e.g. time = 0.0 (seconds)"), f"{kk}.time",
                       unit="seconds")
        if keys and t <= keys[-1].time:
            prev = keys[-1].time
            problem = (f"time {t:g} repeats keys[{j - 1}]" if t == prev else
                       f"time {t:g} is before keys[{j - 1}].time = {prev:g}")
            raise ctx.error(f"{kk}.time", problem,
                            "key times must be strictly increasing: sort the keys by time")
        pos = ctx.vector(k["position"], f"{kk}.position") if "position" in k \
            else tuple(float(c) for c in origin)
        if "rotation" in k:
            rot = ctx.quaternion(k["rotation"], f"{kk}.rotation")     # normalized
        elif rotation is None:
            raise ctx.error(kk, f'no rotation, and {owner} has rotation = "random"',
                            "give rotation = [w, x, y, z] in every key, or a fixed rotation")
        else:
            rot = tuple(float(c) for c in rotation)
        keys.append(Key(time=t, position=pos, rotation=rot))
    interp = "linear"
    if "interpolation" in m:
        interp = ctx.string(m["interpolation"], f"{key}.interpolation", _INTERPOLATIONS)
    return Motion(keys=tuple(keys), interpolation=interp)


def _parse_body(ctx: SceneKeys, i: int, b: Any, shapes, materials) -> BodyGroup:
    key = f"bodies[{i}]"
    b = ctx.table(b, key)
    layout = "single"
    if "layout" in b:
        layout = ctx.string(b["layout"], f"{key}.layout", tuple(_LAYOUT_KEYS))
    allowed = _BODY_COMMON + _LAYOUT_KEYS[layout]
    for k in b:
        if k not in allowed:
            other = [lay for lay, ks in _LAYOUT_KEYS.items() if k in ks]
            if other:
                raise ctx.error(f"{key}.{k}", f"only used with layout = {other[0]!r}",
                                f"this group has layout = {layout!r}")
            raise ctx.error(f"{key}.{k}", "unknown key", suggestion(k, allowed))
    name = ctx.usd_name(ctx.require(b, key, "name", 'e.g. name = "pawns"'), f"{key}.name")
    raw = ctx.require(b, key, "shape", f"known: {known_names(shapes)}")
    if isinstance(raw, list):
        # a mixed group: body i takes shape[i % len(shape)] (a chess set in one group)
        if not raw:
            raise ctx.error(f"{key}.shape", "empty list of shapes", f"known: {known_names(shapes)}")
        names = [ctx.string(x, f"{key}.shape[{j}]") for j, x in enumerate(raw)]
        for j, n in enumerate(names):
            if n not in shapes:
                raise ctx.error(f"{key}.shape[{j}]", f"unknown shape {n!r}",
                                suggestion(n, list(shapes)))
        shape = names[0] if len(names) == 1 else tuple(names)
    else:
        shape = ctx.string(raw, f"{key}.shape")
        if shape not in shapes:
            raise ctx.error(f"{key}.shape", f"unknown shape {shape!r}",
                            suggestion(shape, list(shapes)))
    kw: dict[str, Any] = {"name": name, "shape": shape, "layout": layout}
    if "material" in b:
        kw["material"] = _material_ref(ctx, b["material"], f"{key}.material", materials)
    count = None
    if "count" in b:
        count = ctx.integer(b["count"], f"{key}.count", lo=1, what="a positive integer")

    if layout == "single":
        if count is not None and count != 1:
            raise ctx.error(f"{key}.count", f"layout 'single' places one body, got count = {count}",
                            'remove count, or use layout = "grid" or "random"')
        count = 1
        kw["position"] = (ctx.vector(b["position"], f"{key}.position") if "position" in b
                          else (0.0, 0.0, 0.0))
    elif layout == "grid":
        kw["origin"] = (ctx.vector(b["origin"], f"{key}.origin") if "origin" in b
                        else (0.0, 0.0, 0.0))
        dims_v = ctx.require(b, key, "dims", "e.g. dims = [4, 4, 2]")
        if not isinstance(dims_v, list) or len(dims_v) != 3:
            raise ctx.error(f"{key}.dims", "expected an array of 3 integers, got "
                            f"{describe_value(dims_v)}", "e.g. dims = [4, 4, 2]")
        dims = tuple(ctx.integer(x, f"{key}.dims[{j}]", lo=1, what="a positive integer")
                     for j, x in enumerate(dims_v))
        kw["dims"] = dims
        sp = ctx.require(b, key, "spacing", "e.g. spacing = 0.06 (metres)")
        if isinstance(sp, list):
            spacing = ctx.vector(sp, f"{key}.spacing")
            for j, s in enumerate(spacing):
                if s <= 0:
                    raise ctx.error(f"{key}.spacing[{j}]", f"{s:g} is out of range",
                                    "expected a number > 0 (metres)")
        else:
            s = ctx.number(sp, f"{key}.spacing", lo=0.0, lo_open=True, unit="metres")
            spacing = (s, s, s)
        kw["spacing"] = spacing
        cap = dims[0] * dims[1] * dims[2]
        if count is None:
            count = cap
        elif count > cap:
            raise ctx.error(f"{key}.count",
                            f"count = {count} is larger than dims = {list(dims)} holds ({cap})",
                            "enlarge dims or lower count")
    else:  # random, emit
        lo = ctx.vector(ctx.require(b, key, "region_min", "e.g. region_min = [-1, -1, 0]"),
                        f"{key}.region_min")
        hi = ctx.vector(ctx.require(b, key, "region_max", "e.g. region_max = [1, 1, 2]"),
                        f"{key}.region_max")
        for j in range(3):
            if lo[j] > hi[j]:
                raise ctx.error(f"{key}.region_max[{j}]",
                                f"{hi[j]:g} is below region_min[{j}] = {lo[j]:g}",
                                "region_max must be >= region_min on every axis")
        kw["region_min"], kw["region_max"] = lo, hi
        if count is None:
            raise ctx.error(f"{key}.count", "missing required key",
                            f'layout = "{layout}" needs count, e.g. count = 100')
        if layout == "emit":
            kw["rate"] = ctx.number(ctx.require(b, key, "rate", "e.g. rate = 20 (bodies per "
                                                "second)"), f"{key}.rate", lo=0.0,
                                    lo_open=True, unit="bodies per second")
    kw["count"] = count

    if "rotation" in b:
        r = b["rotation"]
        if isinstance(r, str):
            kw["rotation"] = ctx.string(r, f"{key}.rotation", ("identity", "random"))
        elif isinstance(r, list):
            kw["rotation"] = ctx.quaternion(r, f"{key}.rotation")
        else:
            raise ctx.error(f"{key}.rotation", f"expected \"identity\", \"random\" or [w, x, y, z], "
                            f"got {describe_value(r)}", "e.g. rotation = [1.0, 0.0, 0.0, 0.0]")
    if "velocity" in b:
        kw["velocity"] = ctx.vector(b["velocity"], f"{key}.velocity")
    if "angular_velocity" in b:
        kw["angular_velocity"] = ctx.vector(b["angular_velocity"], f"{key}.angular_velocity")
    if "start_time" in b:
        kw["start_time"] = ctx.number(b["start_time"], f"{key}.start_time", lo=0.0,
                                      unit="seconds")
    if "glue" in b and ctx.boolean(b["glue"], f"{key}.glue"):
        for n in ((shape,) if isinstance(shape, str) else shape):
            if shapes[n].fracture is None:
                raise ctx.error(f"{key}.glue", f"shape {n!r} is not fractured: only the "
                                "pieces of a fractured shape are glued",
                                f"add fracture = {{ pieces = 8 }} to [shapes.{n}], or "
                                "remove glue")
        mat = materials[kw.get("material", "default")]
        if mat.glue_strength is None:
            raise ctx.error(f"{key}.glue", f"material {mat.name!r} has no glue_strength",
                            f"add glue_strength in Pa to [materials.{mat.name}], e.g. "
                            "glue_strength = 2.0e5")
        kw["glue"] = True
    kinematic = "kinematic" in b and ctx.boolean(b["kinematic"], f"{key}.kinematic")
    if kinematic and layout == "emit":
        raise ctx.error(f"{key}.kinematic", 'a group with layout = "emit" cannot be kinematic',
                        "emit dynamic bodies; move a kinematic group by its [bodies.motion]")
    if "motion" in b and not kinematic:
        raise ctx.error(f"{key}.motion", "a dynamic group cannot follow a motion",
                        "add kinematic = true to this group to move it by [bodies.motion]; "
                        "for a dynamic group's initial velocity use velocity and "
                        "angular_velocity")
    if kinematic:
        for k in ("velocity", "angular_velocity"):
            if k in b:
                raise ctx.error(f"{key}.{k}", "given on a kinematic group",
                                "a kinematic group's velocity comes from [bodies.motion]: "
                                "remove it, or set it there (velocity, angular_velocity)")
        if "motion" not in b:
            raise ctx.error(f"{key}.motion", "a kinematic group needs a motion",
                            "add [bodies.motion] with velocity/angular_velocity or keys, "
                            "e.g. [bodies.motion] velocity = [1, 0, 0]")
        if layout == "single":
            origin = kw["position"]
        elif layout == "grid":
            origin = kw["origin"]
        else:
            origin = tuple(0.5 * (a + c) for a, c in zip(kw["region_min"], kw["region_max"]))
        rot = kw.get("rotation", "identity")
        if layout != "single" or rot == "identity":
            rot = (1.0, 0.0, 0.0, 0.0)
        elif rot == "random":
            rot = None
        kw["kinematic"] = True
        kw["motion"] = _parse_motion(ctx, b["motion"], f"{key}.motion", origin, rot, key)
    return BodyGroup(**kw)


def _parse_collider(ctx: SceneKeys, i: int, c: Any, materials, registry, up_axis: str) -> Collider:
    key = f"colliders[{i}]"
    c = ctx.table(c, key)
    ctype = ctx.string(ctx.require(c, key, "type", 'one of: "plane", "box", "mesh"'),
                       f"{key}.type", tuple(_COLLIDER_KEYS))
    kw: dict[str, Any] = {}
    if "material" in c:
        kw["material"] = _material_ref(ctx, c["material"], f"{key}.material", materials)
    kw["name"] = ctx.usd_name(c["name"], f"{key}.name") if "name" in c else f"{ctype}{i}"
    if ctype == "plane":
        ctx.check_keys(c, key, _COLLIDER_KEYS["plane"])
        if "point" in c:
            kw["point"] = ctx.vector(c["point"], f"{key}.point")
        if "normal" in c:
            n = ctx.vector(c["normal"], f"{key}.normal")
        else:
            n = (0.0, 0.0, 1.0) if up_axis == "Z" else (0.0, 1.0, 0.0)
        norm = math.sqrt(sum(x * x for x in n))
        if norm < 1e-12:
            raise ctx.error(f"{key}.normal", "zero normal",
                            "give a non-zero direction pointing into the free side, "
                            "e.g. normal = [0, 0, 1]")
        kw["normal"] = tuple(x / norm for x in n)
        _collider_motion(ctx, c, key, kw, kw.get("point", (0.0, 0.0, 0.0)))
        return PlaneCollider(**kw)
    if ctype == "box":
        ctx.check_keys(c, key, _COLLIDER_KEYS["box"])
        lo = ctx.vector(ctx.require(c, key, "min", "e.g. min = [-1, -1, 0]"), f"{key}.min")
        hi = ctx.vector(ctx.require(c, key, "max", "e.g. max = [1, 1, 1]"), f"{key}.max")
        for j in range(3):
            if not lo[j] < hi[j]:
                raise ctx.error(f"{key}.max[{j}]", f"{hi[j]:g} is not above min[{j}] = {lo[j]:g}",
                                "max must be > min on every axis")
        kw["min"], kw["max"] = lo, hi
        if "open_top" in c:
            kw["open_top"] = ctx.boolean(c["open_top"], f"{key}.open_top")
        if "thickness" in c:
            kw["thickness"] = ctx.number(c["thickness"], f"{key}.thickness", lo=0.0,
                                         lo_open=True, unit="metres")
        _collider_motion(ctx, c, key, kw, tuple(0.5 * (a + b) for a, b in zip(lo, hi)))
        return BoxCollider(**kw)
    # mesh
    has_b, has_m = "builtin" in c, "mesh" in c
    if has_b and has_m:
        raise ctx.error(key, "both builtin and mesh are given", "give only one of them")
    if not (has_b or has_m):
        raise ctx.error(key, "a mesh collider needs builtin or mesh",
                        'add mesh = "<file>" or builtin = "<shape>"')
    if has_m:
        ctx.check_keys(c, key, _COLLIDER_KEYS["mesh"])
        kw["mesh_path"] = ctx.mesh_file(c["mesh"], f"{key}.mesh")
    else:
        builtin = ctx.string(c["builtin"], f"{key}.builtin")
        params = {k: v for k, v in c.items() if k not in _COLLIDER_KEYS["mesh"]}
        params = _check_builtin(ctx, key, builtin, params, registry)
        kw["builtin"], kw["params"] = builtin, params
    if "scale" in c:
        kw["scale"] = ctx.number(c["scale"], f"{key}.scale", lo=0.0, lo_open=True)
    if "position" in c:
        kw["position"] = ctx.vector(c["position"], f"{key}.position")
    if "rotation" in c:
        r = c["rotation"]
        if r == "identity":
            kw["rotation"] = (1.0, 0.0, 0.0, 0.0)
        else:
            kw["rotation"] = ctx.quaternion(r, f"{key}.rotation")
    _collider_motion(ctx, c, key, kw, kw.get("position", (0.0, 0.0, 0.0)),
                     kw.get("rotation", (1.0, 0.0, 0.0, 0.0)))
    return MeshCollider(**kw)


def _collider_motion(ctx: SceneKeys, c: dict, key: str, kw: dict, origin,
                     rotation=(1.0, 0.0, 0.0, 0.0)) -> None:
    """``[colliders.motion]`` into ``kw["motion"]``, if given (``origin``,
    ``rotation``: the collider's frame, scene.collider_frame)."""
    if "motion" in c:
        kw["motion"] = _parse_motion(ctx, c["motion"], f"{key}.motion", origin, rotation, key)


def _array_of_tables(ctx: SceneKeys, v: Any, key: str) -> list:
    if isinstance(v, dict):
        raise ctx.error(key, "expected an array of tables, got a single table",
                        f"write each entry as [[{key}]]")
    if not isinstance(v, list):
        raise ctx.error(key, f"expected an array of tables, got {describe_value(v)}",
                        f"write each entry as [[{key}]]")
    return v


def read_tables(ctx: SceneKeys, data: dict) -> Scene:
    """The Scene of a TOML scene's decoded tables (SceneError naming the key)."""
    ctx.check_keys(data, "", TOP_KEYS, what="section")
    output = parse_output(ctx, data.get("output", {}))
    simulation = parse_simulation(ctx, data.get("simulation", {}), output.up_axis)
    materials = _parse_materials(ctx, data.get("materials", {}))
    registry = _load_shape_registry()
    shapes = _parse_shapes(ctx, data.get("shapes", {}), registry)
    if "bodies" not in data:
        raise ctx.error("bodies", "no body groups", "add at least one [[bodies]] table")
    bodies_raw = _array_of_tables(ctx, data["bodies"], "bodies")
    if not bodies_raw:
        raise ctx.error("bodies", "no body groups", "add at least one [[bodies]] table")
    bodies = []
    seen: dict[str, int] = {}
    for i, b in enumerate(bodies_raw):
        g = _parse_body(ctx, i, b, shapes, materials)
        if g.start_time > output.duration:
            raise ctx.error(f"bodies[{i}].start_time",
                            f"{g.start_time:g} s is after the end of the animation "
                            f"(output.duration = {output.duration:g} s)",
                            "the group would never appear: lower start_time or lengthen "
                            "output.duration")
        if g.name in seen:
            raise ctx.error(f"bodies[{i}].name", f"duplicate group name {g.name!r}",
                            f"already used by bodies[{seen[g.name]}]; names must be unique")
        seen[g.name] = i
        bodies.append(g)
    colliders = []
    if "colliders" in data:
        seen_c: dict[str, int] = {}
        for i, c in enumerate(_array_of_tables(ctx, data["colliders"], "colliders")):
            col = _parse_collider(ctx, i, c, materials, registry, output.up_axis)
            if col.name in seen_c:
                raise ctx.error(f"colliders[{i}].name", f"duplicate collider name {col.name!r}",
                                f"already used by colliders[{seen_c[col.name]}]")
            seen_c[col.name] = i
            colliders.append(col)
    for name, m in materials.items():
        if m.young_modulus is not None and simulation.contact_law != "hertz":
            raise ctx.error(f"materials.{name}.young_modulus",
                            f"applies to the Hertz law only, and the scene's contact_law is "
                            f"{simulation.contact_law!r}",
                            'set [simulation] contact_law = "hertz", or give stiffness in N/m')
    return Scene(path=ctx.path, output=output, simulation=simulation, materials=materials,
                 shapes=shapes, bodies=tuple(bodies), colliders=tuple(colliders))






