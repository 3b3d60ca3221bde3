"""dempipe's own attributes on a UsdPhysics stage: fracture and glue (namespace ``dempipe:``).

UsdPhysics has no fracture and no glue, so a stage carries them as custom attributes,
named in the schema's style (a namespace, then camelCase):

* on a body prim (``PhysicsRigidBodyAPI``): ``int dempipe:fracture:pieces`` (2..MAX_PIECES),
  ``int dempipe:fracture:seed`` (>= 0), ``point3d dempipe:fracture:impact`` (the body's
  local space, stage units), ``double dempipe:fracture:impactShare`` (in [0, 1]),
  ``double dempipe:fracture:impactRadius`` (stage units, > 0), ``bool dempipe:glue``;
* on a physics material (``PhysicsMaterialAPI``): ``double dempipe:glueStrength`` [Pa],
  ``double dempipe:glueStiffness`` [N/m], ``double dempipe:glueDamping`` [1].

Points and lengths are in the prim's own space (picked on the geometry, as a DCC shows
it); the glue's strength and stiffness are material constants in SI, whatever the
stage's units, as in a TOML scene. Every bad value is one SceneError naming the file,
the prim, the attribute and the fix. docs/usd-input.md, "Fracture and glue".
"""

from __future__ import annotations

import math

import numpy as np

from dempipe.errors import SceneError, ShapeError
from dempipe.mesh.fracture import MAX_PIECES, FractureSpec

__all__ = ["BODY_ATTRIBUTES", "MATERIAL_ATTRIBUTES", "fracture_and_glue", "fracture_of",
           "glue_of", "glue_material"]

NAMESPACE = "dempipe:"
FRACTURE = "dempipe:fracture:"
#: The dempipe: attributes a body prim may carry, and their USD value types.
BODY_ATTRIBUTES = {
    "dempipe:fracture:pieces": "int",
    "dempipe:fracture:seed": "int",
    "dempipe:fracture:impact": "point3d",
    "dempipe:fracture:impactShare": "double",
    "dempipe:fracture:impactRadius": "double",
    "dempipe:glue": "bool",
}
#: The dempipe: attributes a physics material may carry, and their USD value types.
MATERIAL_ATTRIBUTES = {
    "dempipe:glueStrength": "double",
    "dempipe:glueStiffness": "double",
    "dempipe:glueDamping": "double",
}
#: Largest glue strength [Pa] and stiffness [N/m] read: beyond any rock or steel by
#: orders of magnitude, so a larger value is a slip of the exponent.
MAX_GLUE = 1e15

_INTS = {"int", "int64", "uint", "uint64", "uchar"}
_REALS = {"double", "float", "half"}
_POINTS = {"point3d", "point3f", "vector3d", "vector3f", "double3", "float3", "position3d"}


def _authored(prim, known: dict, where: str) -> dict:
    """{name: attribute} of the authored ``dempipe:`` attributes on ``prim``; an
    unknown name in the namespace (a typo) is refused."""
    out = {}
    for a in prim.GetAttributes():
        name = a.GetName()
        if not name.startswith(NAMESPACE) or not a.HasAuthoredValue():
            continue
        if name not in known:
            hint = ", ".join(known)
            raise SceneError(f"{where}: {name}: not a dempipe attribute of this prim "
                             f"(known here: {hint}; docs/usd-input.md)")
        out[name] = a
    return out


def _value(attr, where: str, kinds: set, example: str):
    """The attribute's value at its default time, refused unless its type is one of
    ``kinds`` (USD type names) and it holds a value."""
    t = str(attr.GetTypeName())
    if t not in kinds:
        raise SceneError(f"{where}: {attr.GetName()} is a {t}; author it as {example}")
    v = attr.Get()
    if v is None:
        raise SceneError(f"{where}: {attr.GetName()} holds no value; author it as {example}")
    return v


def _real(attr, where: str, lo: float, hi: float, lo_open: bool, unit: str, example: str) -> float:
    v = float(_value(attr, where, _REALS, example))
    if not (math.isfinite(v) and (v > lo if lo_open else v >= lo) and v <= hi):
        rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise SceneError(f"{where}: {attr.GetName()} = {v:g} is out of range (expected a "
                         f"number in {rng}{unit}, e.g. {example})")
    return v


def fracture_of(prim, where: str, stretch: np.ndarray, mpu: float) -> FractureSpec | None:
    """The FractureSpec a body prim's ``dempipe:fracture:*`` attributes ask for, in the
    body's stretched local frame [m] (where its collision mesh is built), or None.

    stretch : (3, 3) the body's S of ``A = S R`` (row convention); mpu : metres per unit.
    """
    attrs = _authored(prim, BODY_ATTRIBUTES, where)
    frac = {k[len(FRACTURE):]: a for k, a in attrs.items() if k.startswith(FRACTURE)}
    if not frac:
        return None
    if "pieces" not in frac:
        given = ", ".join(FRACTURE + k for k in frac)
        raise SceneError(f"{where}: {given} without {FRACTURE}pieces (add "
                         f"int {FRACTURE}pieces = 8, the number of pieces)")
    kw = {}
    for key in ("pieces", "seed"):
        if key not in frac:
            continue
        example = f"int {FRACTURE}{key} = {8 if key == 'pieces' else 0}"
        v = _value(frac[key], where, _INTS, example)
        lo, hi = (2, MAX_PIECES) if key == "pieces" else (0, 2 ** 63 - 1)
        if not lo <= int(v) <= hi:
            raise SceneError(f"{where}: {FRACTURE}{key} = {v} is out of range (expected an "
                             f"integer from {lo} to {hi}, e.g. {example})")
        kw[key] = int(v)
    S = np.asarray(stretch, np.float64)
    if "impact" in frac:
        example = f"point3d {FRACTURE}impact = (0, 0, 0)"
        p = np.asarray(_value(frac["impact"], where, _POINTS, example), np.float64)
        if not np.isfinite(p).all():
            raise SceneError(f"{where}: {FRACTURE}impact = {tuple(p)} is not finite "
                             f"(author a point in the body's local space, e.g. {example})")
        # the body's local space -> its stretched frame -> metres, as its mesh
        kw["impact"] = tuple(float(x) for x in (p @ S) * mpu)
    if "impactShare" in frac:
        kw["impact_share"] = _real(frac["impactShare"], where, 0.0, 1.0, False, "",
                                   f"double {FRACTURE}impactShare = 0.5")
    if "impactRadius" in frac:
        r = _real(frac["impactRadius"], where, 0.0, 1e12, True, " stage units",
                  f"double {FRACTURE}impactRadius = 0.1")
        # a length in the body's local space: its stretch's mean scale, then metres
        kw["impact_radius"] = r * abs(float(np.linalg.det(S))) ** (1.0 / 3.0) * mpu
    if ("impactShare" in frac or "impactRadius" in frac) and "impact" not in frac:
        raise SceneError(f"{where}: {FRACTURE}impactShare / impactRadius without "
                         f"{FRACTURE}impact (add point3d {FRACTURE}impact, the point in the "
                         "body's local space where the pieces are smaller)")
    try:
        return FractureSpec(**kw)
    except ShapeError as exc:         # defensive: every field was checked above
        raise SceneError(f"{where}: {exc}") from None


def glue_of(prim, where: str) -> bool:
    """Whether a body prim's ``dempipe:glue`` is true (False when not authored)."""
    attrs = _authored(prim, BODY_ATTRIBUTES, where)
    if "dempipe:glue" not in attrs:
        return False
    return bool(_value(attrs["dempipe:glue"], where, {"bool"}, "bool dempipe:glue = true"))


def glue_material(prim, where: str) -> dict:
    """A physics material's glue, as MaterialSpec keywords (``glue_strength`` [Pa],
    ``glue_stiffness`` [N/m], ``glue_damping`` [1]); {} when it has none."""
    attrs = _authored(prim, MATERIAL_ATTRIBUTES, where)
    kw = {}
    if "dempipe:glueStrength" in attrs:
        kw["glue_strength"] = _real(attrs["dempipe:glueStrength"], where, 0.0, MAX_GLUE, True,
                                    " Pa", "double dempipe:glueStrength = 2e5")
    if "dempipe:glueStiffness" in attrs:
        kw["glue_stiffness"] = _real(attrs["dempipe:glueStiffness"], where, 0.0, MAX_GLUE,
                                     True, " N/m", "double dempipe:glueStiffness = 1e6")
    if "dempipe:glueDamping" in attrs:
        kw["glue_damping"] = _real(attrs["dempipe:glueDamping"], where, 0.0, 1e3, False, "",
                                   "double dempipe:glueDamping = 0.7")
    if kw and "glue_strength" not in kw:
        given = ", ".join(a for a in attrs)
        raise SceneError(f"{where}: {given} without dempipe:glueStrength (add double "
                         "dempipe:glueStrength, the glue's tensile strength in Pa, e.g. 2e5)")
    return kw


def fracture_and_glue(prim, where: str, stretch, mpu: float, instanced: bool, material,
                      material_path: str | None, shapes=()):
    """(FractureSpec | None, glue) of a body prim, refused where its pieces could not be
    written back or glued.

    instanced : the prim is a PointInstancer's prototype; material : the body's
    MaterialSpec (its contacts' and glue's), bound at ``material_path`` (None: dempipe's
    default material, no binding); shapes : its collision prims, where a body's
    attribute put on the shape instead (a DCC's habit) is refused, not ignored.
    """
    from pxr import Usd, UsdPhysics

    for c in shapes:
        stray = [a.GetName() for a in c.GetAttributes() if c != prim
                 and a.GetName() in BODY_ATTRIBUTES and a.HasAuthoredValue()]
        if stray:
            raise SceneError(f"{where}: {stray[0]} is on its collision shape {c.GetPath()}, "
                             f"not on the body (move it to {prim.GetPath()}, the prim with "
                             "PhysicsRigidBodyAPI)")
    spec = fracture_of(prim, where, stretch, mpu)
    glue = glue_of(prim, where)
    if spec is None:
        if glue:
            raise SceneError(f"{where}: dempipe:glue = true on a body that is not fractured: "
                             "only the pieces of a fractured body are glued (add int "
                             "dempipe:fracture:pieces = 8, or remove dempipe:glue)")
        return None, False
    if instanced:
        raise SceneError(f"{where}: dempipe:fracture:* on a PointInstancer's prototype "
                         f"({prim.GetPath()}): not supported (make the body a prim of its "
                         "own, or remove the fracture attributes)")
    if UsdPhysics.RigidBodyAPI(prim).GetKinematicEnabledAttr().Get():
        raise SceneError(f"{where}: dempipe:fracture:* on a kinematic body: its pieces would "
                         "not move apart (remove the fracture attributes or "
                         "physics:kinematicEnabled)")
    nested = [str(p.GetPath()) for p in Usd.PrimRange(prim)
              if p != prim and p.HasAPI(UsdPhysics.RigidBodyAPI)]
    if nested:
        raise SceneError(f"{where}: a fractured body holds another body ({nested[0]}): its "
                         "pieces replace the whole prim in the overlay (move the nested body "
                         "out from under it)")
    if glue and material.glue_strength is None:
        fix = (f"add double dempipe:glueStrength (Pa, e.g. 2e5) to {material_path}"
               if material_path else "bind a physics material with dempipe:glueStrength "
               "(Pa, e.g. 2e5) to its collision shapes")
        raise SceneError(f"{where}: dempipe:glue = true, but its material has no glue "
                         f"strength ({fix})")
    return spec, glue
