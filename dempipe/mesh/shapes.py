"""Built-in shapes and mesh loading: everything that turns a name or a file into a mesh.

Every function here returns a :class:`trimesh.Trimesh` in metres, in the shape's own
mesh frame (the frame the scene file places):

* chess pieces (pawn, rook, knight, bishop, queen, king), ``cylinder`` and ``capsule``
  stand on z = 0 with their axis on +z, so a DCC user places a piece by its foot;
* ``box``, ``sphere`` and ``torus`` are centred on the origin (torus axis +z).

Chess pieces are 2-D (r, z) profiles revolved with manifold3d, then finished with
boolean operations (rook notches, bishop slit, queen crown balls, king cross, knight
head). manifold3d guarantees closed, oriented 2-manifold output, so every built-in
shape is watertight with positive volume; the tests check it for each one.

Profiles are drawn at unit height (z from 0 to 1) and scaled at the end: the booleans
run at a scale where manifold3d's tolerances are comfortable, and a piece's height is
then exactly its ``height`` parameter.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import math
import os
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import manifold3d
import numpy as np
import trimesh

from dempipe.errors import MeshError, ShapeError

__all__ = [
    "Param",
    "ShapeSpec",
    "SHAPES",
    "MESH_EXTENSIONS",
    "list_shapes",
    "build_shape",
    "load_mesh",
    "mesh_digest",
]

# Segments around a revolved circle. 40 keeps a chess piece at a few thousand triangles
# while the polygonal error in volume stays below 0.5 %.
CIRCULAR_SEGMENTS = 40


@dataclasses.dataclass(frozen=True)
class Param:
    """One parameter of a built-in shape.

    ``kind`` is ``"length"`` (a positive finite number in metres), ``"vector3"``
    (three positive finite lengths in metres) or ``"int"`` (an integer in
    ``[low, high]``). A ``default`` of ``None`` means "derived from the other
    parameters", as ``doc`` says.
    """

    default: Any
    doc: str
    kind: str = "length"
    low: int | None = None
    high: int | None = None


@dataclasses.dataclass(frozen=True)
class ShapeSpec:
    """A built-in shape: its name, a one-line ``doc``, its parameters and its builder.

    ``builder(**params)`` takes every parameter (validated, defaults filled in) and
    returns a watertight ``trimesh.Trimesh`` in metres.
    """

    name: str
    doc: str
    params: dict[str, Param]
    builder: Callable[..., trimesh.Trimesh] = dataclasses.field(repr=False)


# --------------------------------------------------------------------------- helpers


def _to_trimesh(m: manifold3d.Manifold) -> trimesh.Trimesh:
    """Convert a manifold3d solid to trimesh (float64 vertices where available)."""
    # to_mesh64 (manifold3d >= 3) keeps the double-precision vertices; to_mesh rounds
    # them to float32, which is still far inside the tests' 1e-6 tolerance.
    mesh = m.to_mesh64() if hasattr(m, "to_mesh64") else m.to_mesh()
    vertices = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    faces = np.asarray(mesh.tri_verts, dtype=np.int64)
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=True)


def _arc(cx: float, cz: float, r: float, deg0: float, deg1: float, n: int = 8) -> list:
    """Points of a circular arc in the (r, z) profile plane, ``n`` segments, ends included."""
    t = np.radians(np.linspace(deg0, deg1, n + 1))
    return [(cx + r * math.cos(a), cz + r * math.sin(a)) for a in t]


def _revolve(profile: list) -> manifold3d.Manifold:
    """Revolve a closed (r, z) profile about the z axis.

    manifold3d revolves about the cross-section's y axis and makes it the z axis, so
    profile (r, z) maps straight to (radius, height).
    """
    pts = np.asarray(profile, dtype=np.float64)
    pts[:, 0] = np.maximum(pts[:, 0], 0.0)  # float noise of arcs ending on the axis
    return manifold3d.CrossSection([pts]).revolve(CIRCULAR_SEGMENTS)


def _box(size: Sequence[float], center: Sequence[float]) -> manifold3d.Manifold:
    """An axis-aligned manifold box of ``size`` centred at ``center``."""
    return manifold3d.Manifold.cube(tuple(size), True).translate(tuple(center))


def _base(b: float, bead: float = 1.0) -> list:
    """Foot of a Staunton piece with base radius ``b`` (unit height): plinth and bead.

    Runs from the axis at z = 0 out to the rim and up over a half-round bead that
    reaches ``bead`` x b from the axis, ending at (0.70 b, 0.56 b) where each piece's
    stem begins.
    """
    return [
        (0.0, 0.0),
        (b, 0.0),
        (b, 0.16 * b),
        *_arc((bead - 0.14) * b, 0.32 * b, 0.14 * b, -60.0, 90.0, 8),
        (0.70 * b, 0.56 * b),
    ]


# Staunton proportions (after the No. 6 tournament pattern): default height relative
# to the pawn's 50 mm and base diameter as a fraction of the piece's height.
_PIECE_HEIGHT = {
    "pawn": 0.050, "rook": 0.056, "knight": 0.062,
    "bishop": 0.072, "queen": 0.084, "king": 0.095,
}  # fmt: skip
_PIECE_BASE = {
    "pawn": 0.49, "rook": 0.58, "knight": 0.55,
    "bishop": 0.45, "queen": 0.44, "king": 0.42,
}  # fmt: skip


def _pawn_unit(b: float) -> manifold3d.Manifold:
    # Stem tapering to a collar, then a ball head 0.36 of the height across whose top
    # is exactly z = 1. The head is narrower than the base and the bead stays inside
    # the plinth's rim, so a pawn on its side rests on that rim and its head and rolls
    # in a circle, as a real one does.
    profile = [
        *_base(b, bead=0.90),
        (0.13, 0.19), (0.115, 0.28), (0.095, 0.40), (0.085, 0.50),
        (0.155, 0.52), (0.16, 0.555), (0.145, 0.575), (0.07, 0.59),
        *_arc(0.0, 0.82, 0.18, -70.0, 90.0, 16),
    ]  # fmt: skip
    return _revolve(profile)


def _rook_unit(b: float) -> manifold3d.Manifold:
    # A thick tower flaring into a turret; crenellations are cut afterwards.
    profile = [
        *_base(b),
        (0.19, 0.22), (0.175, 0.40), (0.165, 0.55),
        (0.225, 0.58), (0.225, 0.62), (0.19, 0.64),
        (0.20, 0.67), (0.235, 0.72), (0.235, 1.0), (0.0, 1.0),
    ]  # fmt: skip
    tower = _revolve(profile)
    # A shallow bowl in the top and six notches (three boxes through the axis): the
    # merlons keep the full height, so the piece is still exactly one unit tall.
    cut = manifold3d.Manifold.cylinder(0.2, 0.155, -1.0, CIRCULAR_SEGMENTS).translate((0, 0, 0.92))
    for angle in (0.0, 60.0, 120.0):
        cut = cut + _box((0.7, 0.075, 0.2), (0.0, 0.0, 1.0)).rotate((0.0, 0.0, angle))
    return tower - cut


def _bishop_unit(b: float) -> manifold3d.Manifold:
    # Slender stem, double collar, an egg-shaped mitre drawn to a point, a small ball.
    profile = [
        *_base(b),
        (0.13, 0.18), (0.10, 0.30), (0.085, 0.45), (0.08, 0.55),
        (0.15, 0.57), (0.155, 0.60), (0.10, 0.62),
        (0.125, 0.635), (0.125, 0.655), (0.075, 0.67),
        *_arc(0.0, 0.78, 0.14, -52.0, 0.0, 6),
        (0.137, 0.82), (0.125, 0.855), (0.10, 0.885), (0.065, 0.91), (0.03, 0.925),
        *_arc(0.0, 0.965, 0.035, -45.0, 90.0, 8),
    ]  # fmt: skip
    body = _revolve(profile)
    # The mitre's slit: a thin box from just past the axis out through the +x side,
    # tilted 30 degrees so it rises toward the front. It stops past the axis, so the
    # mitre stays in one piece.
    slit = _box((0.30, 0.40, 0.035), (0.12, 0.0, 0.0)).rotate((0.0, -30.0, 0.0))
    return body - slit.translate((0.0, 0.0, 0.80))


def _queen_unit(b: float) -> manifold3d.Manifold:
    # Tall stem, double collar, a coronet flaring to a rim, a dome and a top ball.
    profile = [
        *_base(b),
        (0.125, 0.18), (0.095, 0.30), (0.075, 0.45), (0.065, 0.58),
        (0.13, 0.60), (0.135, 0.63), (0.085, 0.65),
        (0.11, 0.665), (0.11, 0.685), (0.07, 0.70),
        (0.09, 0.75), (0.13, 0.82), (0.165, 0.86), (0.165, 0.875),
        (0.10, 0.885), (0.06, 0.90), (0.03, 0.915),
        *_arc(0.0, 0.955, 0.045, -48.0, 90.0, 10),
    ]  # fmt: skip
    body = _revolve(profile)
    # Eight small balls around the rim; each is half sunk into it so the union is one
    # solid, and they stay well below the top ball.
    ball = manifold3d.Manifold.sphere(0.028, 12)
    for i in range(8):
        a = 2.0 * math.pi * i / 8
        body = body + ball.translate((0.155 * math.cos(a), 0.155 * math.sin(a), 0.885))
    return body


def _king_unit(b: float) -> manifold3d.Manifold:
    # Like the queen, lower crown closed by a dome, and a cross of two boxes on top.
    profile = [
        *_base(b),
        (0.12, 0.17), (0.09, 0.30), (0.07, 0.45), (0.06, 0.56),
        (0.12, 0.58), (0.125, 0.61), (0.08, 0.63),
        (0.10, 0.645), (0.10, 0.665), (0.065, 0.68),
        (0.085, 0.72), (0.12, 0.77), (0.145, 0.795), (0.145, 0.81),
        (0.10, 0.825), (0.06, 0.84), (0.0, 0.85),
    ]  # fmt: skip
    body = _revolve(profile)
    upright = _box((0.05, 0.05, 0.18), (0.0, 0.0, 0.91))  # z 0.82 .. 1.0
    bar = _box((0.14, 0.05, 0.045), (0.0, 0.0, 0.925))
    return body + upright + bar


def _knight_unit(b: float) -> manifold3d.Manifold:
    # A low revolved base with a collar, and a horse head: the side profile (x forward,
    # z up) extruded across y, rounded by intersecting it with an ellipsoid so the
    # muzzle and the neck's back taper like a carved head.
    base = _revolve([
        *_base(b),
        (0.15, 0.16), (0.18, 0.19), (0.18, 0.22), (0.13, 0.245), (0.0, 0.245),
    ])  # fmt: skip
    head_profile = np.array([
        (-0.16, 0.20), (0.16, 0.20), (0.15, 0.30), (0.10, 0.42), (0.08, 0.50),
        (0.14, 0.56), (0.26, 0.60), (0.31, 0.64), (0.32, 0.69), (0.28, 0.74),
        (0.16, 0.80), (0.10, 0.87), (0.07, 0.94), (0.04, 1.00), (0.00, 0.95),
        (-0.04, 0.93), (-0.10, 0.90), (-0.17, 0.80), (-0.21, 0.66), (-0.22, 0.50),
        (-0.20, 0.36), (-0.17, 0.26),
    ])  # fmt: skip
    thickness = 0.26
    slab = manifold3d.CrossSection([head_profile]).extrude(thickness)
    # Rotating +90 degrees about x maps profile (x, y) to world (x, z) and the
    # extrusion direction to -y; centre the slab on y = 0.
    slab = slab.translate((0.0, 0.0, -thickness / 2)).rotate((90.0, 0.0, 0.0))
    rounding = manifold3d.Manifold.sphere(1.0, 32).scale((0.42, 0.16, 0.6)).translate((0.03, 0, 0.6))
    # The ellipsoid reaches z = 1.2, so the ear tip (z = 1) keeps its full height.
    return base + (slab ^ rounding)


def _piece_builder(name: str, unit: Callable[[float], manifold3d.Manifold]):
    ratio = _PIECE_BASE[name]

    def build(height: float, base_diameter: float | None) -> trimesh.Trimesh:
        if base_diameter is None:
            base_diameter = ratio * height
        lo, hi = 0.2 * height, 1.2 * height
        if not lo <= base_diameter <= hi:
            raise ShapeError(
                f"shape {name!r}: base_diameter must be between 0.2 and 1.2 x height "
                f"({lo:.6g} .. {hi:.6g} m for height {height:.6g} m), got {base_diameter:.6g}"
            )
        mesh = _to_trimesh(unit(ratio / 2))
        # The unit profile has base diameter `ratio`; stretch radially for a custom one.
        radial = base_diameter / ratio
        mesh.apply_scale([radial, radial, height])
        return mesh

    build.__name__ = f"build_{name}"
    return build


def _build_box(size: Sequence[float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=np.asarray(size, dtype=np.float64))


def _build_sphere(diameter: float, subdivisions: int) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=diameter / 2)


def _build_torus(major_radius: float, minor_radius: float) -> trimesh.Trimesh:
    if minor_radius >= major_radius:
        raise ShapeError(
            f"shape 'torus': minor_radius must be smaller than major_radius "
            f"(0 < minor_radius < {major_radius:.6g} m), got {minor_radius:.6g}"
        )
    # Built at unit major radius for the same tolerance reason as the pieces.
    r = minor_radius / major_radius
    tube = manifold3d.CrossSection.circle(r, 32).translate((1.0, 0.0))
    mesh = _to_trimesh(tube.revolve(2 * CIRCULAR_SEGMENTS))
    mesh.apply_scale(major_radius)
    return mesh


def _build_cylinder(diameter: float, height: float) -> trimesh.Trimesh:
    m = manifold3d.Manifold.cylinder(1.0, 0.5, -1.0, 2 * CIRCULAR_SEGMENTS)
    mesh = _to_trimesh(m)
    mesh.apply_scale([diameter, diameter, height])
    return mesh


def _build_capsule(diameter: float, height: float) -> trimesh.Trimesh:
    if height < diameter:
        raise ShapeError(
            f"shape 'capsule': height is the total length including both caps and must be "
            f">= diameter ({diameter:.6g} m), got {height:.6g}"
        )
    r = diameter / 2
    profile = [
        *_arc(0.0, r, r, -90.0, 0.0, 12),
        *_arc(0.0, height - r, r, 0.0, 90.0, 12),
    ]
    # Build in a unit frame (diameter 1) so tolerances do not depend on the size.
    unit = [(x / diameter, z / diameter) for x, z in profile]
    mesh = _to_trimesh(_revolve(unit))
    mesh.apply_scale(diameter)
    return mesh


# --------------------------------------------------------------------------- registry


def _piece_spec(name: str, doc: str, unit) -> ShapeSpec:
    h = _PIECE_HEIGHT[name]
    ratio = _PIECE_BASE[name]
    return ShapeSpec(
        name=name,
        doc=f"{doc}; stands on z = 0, axis +z",
        params={
            "height": Param(h, "total height [m]"),
            "base_diameter": Param(None, f"diameter of the foot [m]; default {ratio} x height"),
        },
        builder=_piece_builder(name, unit),
    )


SHAPES: dict[str, ShapeSpec] = {
    spec.name: spec
    for spec in sorted(
        [
            _piece_spec("pawn", "Staunton pawn: ball head on a collar", _pawn_unit),
            _piece_spec("rook", "Staunton rook: turret with six crenels", _rook_unit),
            _piece_spec("knight", "Staunton knight: horse head on a round base", _knight_unit),
            _piece_spec("bishop", "Staunton bishop: mitre with a slit", _bishop_unit),
            _piece_spec("queen", "Staunton queen: coronet of eight balls", _queen_unit),
            _piece_spec("king", "Staunton king: crown with a cross", _king_unit),
            ShapeSpec(
                "box",
                "rectangular box centred on the origin",
                {"size": Param((0.04, 0.04, 0.04), "edge lengths x, y, z [m]", "vector3")},
                _build_box,
            ),
            ShapeSpec(
                "sphere",
                "icosphere centred on the origin",
                {
                    "diameter": Param(0.04, "diameter [m]"),
                    "subdivisions": Param(4, "icosphere subdivisions (faces = 20 x 4^n)", "int", 0, 5),
                },
                _build_sphere,
            ),
            ShapeSpec(
                "torus",
                "torus centred on the origin, axis +z",
                {
                    "major_radius": Param(0.02, "radius from the axis to the tube centre [m]"),
                    "minor_radius": Param(0.008, "radius of the tube [m]; < major_radius"),
                },
                _build_torus,
            ),
            ShapeSpec(
                "cylinder",
                "cylinder standing on z = 0, axis +z",
                {"diameter": Param(0.03, "diameter [m]"), "height": Param(0.04, "height [m]")},
                _build_cylinder,
            ),
            ShapeSpec(
                "capsule",
                "capsule (cylinder with hemispherical caps) standing on z = 0, axis +z",
                {
                    "diameter": Param(0.02, "diameter [m]"),
                    "height": Param(0.05, "total height including both caps [m]; >= diameter"),
                },
                _build_capsule,
            ),
        ],
        key=lambda s: s.name,
    )
}


def list_shapes() -> list[ShapeSpec]:
    """All built-in shapes, sorted by name."""
    return [SHAPES[k] for k in sorted(SHAPES)]


def did_you_mean(word: str, known: Sequence[str]) -> str:
    """'; did you mean 'X'?' for the closest of ``known`` to ``word``, or ''."""
    close = difflib.get_close_matches(str(word).lower(), list(known), n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def _is_real(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))


def _check_param(shape: str, key: str, p: Param, value: Any) -> Any:
    """Validate one parameter value; return it normalised (float, tuple of floats, int)."""
    where = f"shape {shape!r}: {key}"
    if p.kind == "length":
        if value is None and p.default is None:
            return None
        if not _is_real(value) or not math.isfinite(float(value)) or float(value) <= 0:
            raise ShapeError(f"{where} must be a positive finite length in metres (> 0), got {value!r}")
        return float(value)
    if p.kind == "vector3":
        try:
            vec = [float(v) for v in value if _is_real(v)]
            ok = len(vec) == len(value) == 3
        except TypeError:
            ok = False
        if not ok or not all(math.isfinite(v) and v > 0 for v in vec):
            raise ShapeError(
                f"{where} must be 3 positive finite lengths [x, y, z] in metres "
                f"(each > 0), got {value!r}"
            )
        return tuple(vec)
    if p.kind == "int":
        if (not _is_real(value)) or int(value) != value or not p.low <= int(value) <= p.high:
            raise ShapeError(f"{where} must be an integer in {p.low} .. {p.high}, got {value!r}")
        return int(value)
    raise AssertionError(f"unknown parameter kind {p.kind!r}")  # a registry bug, not user input


def build_shape(name: str, **params: Any) -> trimesh.Trimesh:
    """Build a built-in shape by name.

    ``params`` override the defaults in ``SHAPES[name].params`` (lengths in metres).
    Returns a new closed, manifold ``trimesh.Trimesh`` in metres; see the module
    docstring for each shape's origin and axis. Raises :class:`ShapeError` for an
    unknown shape or parameter, or an out-of-range value, naming the valid range.
    """
    spec = SHAPES.get(name) if isinstance(name, str) else None
    if spec is None:
        known = ", ".join(sorted(SHAPES))
        raise ShapeError(f"unknown shape {name!r} (known: {known}){did_you_mean(name, SHAPES)}")
    for key in params:
        if key not in spec.params:
            known = ", ".join(spec.params)
            raise ShapeError(
                f"shape {name!r}: unknown parameter {key!r} (known: {known})"
                f"{did_you_mean(key, spec.params)}"
            )
    values = {
        key: _check_param(name, key, p, params.get(key, p.default)) for key, p in spec.params.items()
    }
    return spec.builder(**values)


# --------------------------------------------------------------------------- mesh files

# Formats trimesh reads without optional dependencies.
MESH_EXTENSIONS = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf")


def _load_scene(path: str) -> trimesh.Scene:
    # load_scene (trimesh >= 4.6) always gives a Scene; older trimesh.load may give a
    # Trimesh for single-mesh formats. process=False: trimesh's processing would drop
    # NaN vertices silently, and we want to report them.
    loader = getattr(trimesh, "load_scene", None) or trimesh.load
    loaded = loader(path, process=False)
    if isinstance(loaded, trimesh.Trimesh):
        return trimesh.Scene(loaded)
    return loaded


def _orient_faces(mesh: trimesh.Trimesh) -> None:
    """Make the winding consistent within each connected patch, then point it outward.

    trimesh.repair.fix_normals does the same but needs networkx, which dempipe does
    not depend on. Only edges shared by exactly two faces connect faces here, so a
    non-manifold or open mesh is oriented patch by patch.
    """
    faces = np.array(mesh.faces)
    n = len(faces)
    adj = mesh.face_adjacency
    e0, e1 = np.asarray(mesh.face_adjacency_edges).T

    def runs_forward(f: np.ndarray) -> np.ndarray:  # does face f run its shared edge e0 -> e1?
        tri = faces[f]
        nxt = np.roll(tri, -1, axis=1)
        return ((tri == e0[:, None]) & (nxt == e1[:, None])).any(axis=1)

    # Two neighbours are consistent when they run their shared edge in opposite directions.
    inconsistent = runs_forward(adj[:, 0]) == runs_forward(adj[:, 1])
    src = np.concatenate([adj[:, 0], adj[:, 1]])
    order = np.argsort(src, kind="stable")
    dst = np.concatenate([adj[:, 1], adj[:, 0]])[order].tolist()
    rel = np.concatenate([inconsistent, inconsistent])[order].tolist()
    start = np.searchsorted(src[order], np.arange(n + 1)).tolist()
    flip = [False] * n
    label = [-1] * n
    for seed in range(n):  # depth-first flood fill; each face is visited once
        if label[seed] >= 0:
            continue
        label[seed] = seed
        stack = [seed]
        while stack:
            f = stack.pop()
            for k in range(start[f], start[f + 1]):
                g = dst[k]
                if label[g] < 0:
                    label[g] = seed
                    flip[g] = flip[f] ^ rel[k]
                    stack.append(g)
    flip_arr = np.array(flip)
    faces[flip_arr] = faces[flip_arr][:, ::-1]

    # Outward: a patch whose signed volume about its own centroid is negative is inside out.
    _, comp = np.unique(np.array(label), return_inverse=True)
    tri = np.asarray(mesh.vertices)[faces]
    count = np.bincount(comp)
    centre = np.stack([np.bincount(comp, tri[:, :, i].mean(axis=1)) for i in range(3)], axis=1)
    tri = tri - (centre / count[:, None])[comp][:, None, :]
    vol = np.bincount(comp, np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])))
    inside_out = (vol < 0)[comp]
    faces[inside_out] = faces[inside_out][:, ::-1]
    mesh.faces = faces


def load_mesh(path: str | os.PathLike, scale: float = 1.0) -> trimesh.Trimesh:
    """Read a mesh file into one ``trimesh.Trimesh``, multiplied by ``scale``.

    Reads OBJ, STL, PLY, OFF, GLB and glTF (``MESH_EXTENSIONS``). Coordinates are the
    file's own, times ``scale`` (use it to convert the file's units to metres, e.g.
    0.001 for millimetres); the origin and axes are kept as they are. A file holding
    several meshes (a scene) is merged into one body with its scene-graph transforms
    applied, and a warning says so.

    The mesh is lightly repaired (duplicate vertices merged, degenerate faces dropped,
    winding and normals made consistent) but may stay open: the sphere builder uses a
    winding-number inside test that tolerates small holes.

    Raises :class:`MeshError` naming the file if it is missing, unreadable, of an
    unsupported format, empty, has non-finite vertices, or is flat (no volume), and
    if ``scale`` is not a positive finite number.
    """
    where = os.fspath(path)
    if not _is_real(scale) or not math.isfinite(float(scale)) or float(scale) <= 0:
        raise MeshError(f"{where}: scale must be a positive finite number, got {scale!r}")
    if not os.path.exists(where):
        raise MeshError(f"{where}: file not found")
    if os.path.isdir(where):
        raise MeshError(f"{where}: is a folder, not a mesh file")
    supported = ", ".join(MESH_EXTENSIONS)
    ext = os.path.splitext(where)[1].lower()
    if ext not in MESH_EXTENSIONS:
        raise MeshError(f"{where}: unsupported mesh format {ext or '(no extension)'!r} (supported: {supported})")
    if os.path.getsize(where) == 0:
        raise MeshError(f"{where}: file is empty (export the mesh again)")

    if ext == ".stl":
        _check_binary_stl(where)
    try:
        scene = _load_scene(where)
    except Exception as exc:  # trimesh raises many types for bad files
        raise MeshError(
            f"{where}: cannot read as {ext[1:].upper()} ({type(exc).__name__}: {exc}); "
            f"supported: {supported}"
        ) from exc
    if not isinstance(scene, trimesh.Scene):
        raise MeshError(f"{where}: not a triangle mesh (supported: {supported})")

    # dump() applies each instance's scene-graph transform; keep only triangle meshes
    # (a PLY point cloud or an OBJ polyline is not a solid).
    parts = [g for g in scene.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not parts:
        raise MeshError(f"{where}: contains no triangles (an empty mesh, or not a {ext[1:].upper()} file)")
    if len(parts) > 1:
        warnings.warn(f"{where}: {len(parts)} meshes merged into one body", stacklevel=2)
        mesh = trimesh.util.concatenate(parts)
    else:
        mesh = parts[0].copy()

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.isfinite(vertices).all():
        bad = int((~np.isfinite(vertices)).any(axis=1).sum())
        raise MeshError(f"{where}: {bad} vertices have non-finite coordinates (NaN or inf)")
    mesh = trimesh.Trimesh(vertices=vertices * float(scale), faces=mesh.faces, process=False)

    # Light repair only; a non-watertight mesh is accepted (see docstring).
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise MeshError(f"{where}: all triangles are degenerate (empty mesh)")
    _orient_faces(mesh)

    extents = mesh.extents
    size = float(extents.max())
    if size <= 0 or float(extents.min()) <= 1e-9 * size:
        raise MeshError(
            f"{where}: mesh is flat (bounding box {' x '.join(f'{e:.6g}' for e in extents)} m): "
            f"it encloses no volume"
        )
    # Signed volume about the box centre: for a closed mesh it is the volume, for an open
    # one it is still far from zero unless the surface is degenerate (two coincident
    # sheets, a folded plane), which no inside test can make solid.
    centred = mesh.vertices - mesh.bounds.mean(axis=0)
    tri = centred[mesh.faces]
    volume = float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()) / 6.0
    if abs(volume) <= 1e-6 * float(np.prod(extents)):
        raise MeshError(
            f"{where}: mesh encloses (almost) no volume ({abs(volume):.3g} m^3 in a "
            f"{' x '.join(f'{e:.6g}' for e in extents)} m box)"
        )
    return mesh


def mesh_digest(mesh: trimesh.Trimesh) -> str:
    """Content hash of a mesh: sha256 hex of its vertices (float64, C order) then faces (int64).

    Two meshes with the same digest have bit-identical geometry; the sphere-set cache
    keys on it.
    """
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()


def _check_binary_stl(where: str) -> None:
    """A binary STL whose size does not match its triangle count is damaged (cut
    short, or not an STL): say so, rather than what trimesh's text fallback then
    fails on (a missing text-encoding module)."""
    size = os.path.getsize(where)
    with open(where, "rb") as fh:
        head = fh.read(84)
    if size >= 84:
        n = int.from_bytes(head[80:84], "little")
        if size == 84 + 50 * n:
            return                                   # a whole binary STL
    if head.lstrip()[:5].lower() == b"solid":
        try:
            with open(where, "rb") as fh:
                fh.read(4096).decode("ascii")
            return                                   # text: trimesh reads it
        except UnicodeDecodeError:
            pass
    n = int.from_bytes(head[80:84], "little") if size >= 84 else 0
    raise MeshError(f"{where}: damaged binary STL: its header counts {n} triangles, "
                    f"{84 + 50 * n} bytes, but the file has {size} bytes (cut short, or "
                    f"not an STL file); export it again")
