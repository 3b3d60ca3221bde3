"""The Sdf pieces every USD writer here authors with: value types, attribute specs,
valid prim names, sparse time samples and the quaternion layout.

Everything is authored with the Sdf API on a layer (no stage change processing
per edit). Sparse output leaves out what linear interpolation restores: an
attribute that never changes gets a default value only (``constant_columns``), and
inside a run of identical samples only the first and the last are kept
(``kept_samples``); ``flush_tiny`` first zeroes the float noise of bodies at
rest, which would otherwise make every sample differ. dempipe quaternions are
(w, x, y, z); GfQuat memory layout is (x, y, z, w) (``quat_xyzw``).
"""

from __future__ import annotations

import numpy as np
from pxr import Sdf, Tf

SDF_TYPES = Sdf.ValueTypeNames
SPEC_DEF = Sdf.SpecifierDef
SPEC_CLASS = Sdf.SpecifierClass
_UNIFORM = Sdf.VariabilityUniform


def unique_names(names) -> list[str]:
    """Valid, unique prim names, in order (``Tf.MakeValidIdentifier`` + suffixes)."""
    out, seen = [], set()
    for name in names:
        base = Tf.MakeValidIdentifier(str(name)) or "_"
        cand, k = base, 1
        while cand in seen:
            cand = f"{base}_{k}"
            k += 1
        seen.add(cand)
        out.append(cand)
    return out


def author_attr(prim, name, type_name, default=None, *, uniform=False):
    spec = Sdf.AttributeSpec(prim, name, type_name, _UNIFORM if uniform else Sdf.VariabilityVarying)
    if default is not None:
        spec.default = default
    return spec


def kept_samples(values: np.ndarray) -> np.ndarray:
    """(F, K...) samples -> (F, K) bool: which to write so that linear
    interpolation reproduces every sample. Inside a run of equal consecutive
    samples only the first and the last are kept. Comparison is exact."""
    n = values.shape[0]
    keep = np.ones(values.shape[:2], dtype=bool)
    if n > 2:
        same = np.all(values[1:] == values[:-1], axis=tuple(range(2, values.ndim)))
        keep[1:-1] = ~(same[:-1] & same[1:])
    return keep


def constant_columns(values: np.ndarray) -> np.ndarray:
    """(F, K...) -> (K,) bool: True where all samples equal the first."""
    return np.all(values == values[:1], axis=(0,) + tuple(range(2, values.ndim)))


#: float32's resolution, 2^-24. Written as 0: a component of a position or a
#: quaternion below this fraction of the vector's largest component (flush_tiny),
#: a velocity that moves a body by less than this fraction of the scene's largest
#: coordinate in one frame, an angular velocity that turns it by less than this
#: many radians in one frame. What is left out is float noise of bodies at rest.
TINY = 2.0**-24


def flush_tiny(a: np.ndarray) -> np.ndarray:
    """(..., K) float64 -> the same with every component below ``TINY`` times its
    vector's largest component set to 0 (in place).

    A body at rest still carries float noise around zero: a quaternion component
    of 1e-18 on a box lying flat, a coordinate of 1e-22 m on a body placed on an
    axis. Written as is, that noise makes every sample differ from the previous
    one and sparse output keeps them all. Each vector changes by less than
    float32's rounding of its largest component.
    """
    big = np.abs(a).max(axis=-1, keepdims=True)
    a[np.abs(a) < TINY * big] = 0.0
    return a


def quat_xyzw(q_wxyz: np.ndarray, dtype) -> np.ndarray:
    """dempipe (w, x, y, z) -> GfQuat memory layout (x, y, z, w), unit length."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    q = flush_tiny(q / np.where(norm > 0, norm, 1.0))
    return np.ascontiguousarray(q[..., [1, 2, 3, 0]], dtype=dtype)
