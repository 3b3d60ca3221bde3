"""dempipe: rigid bodies as sets of equal spheres, stepped by the eight stages of
Harada, Tanaka, Koshizuka and Kawaguchi (2007), baked to USD.

The public API is re-exported here lazily: ``import dempipe`` imports neither
pxr nor numba.cuda and compiles no kernel.
"""

from importlib import import_module as _import_module

__version__ = "0.1.0"

from .errors import (  # noqa: F401  (cheap, no heavy imports)
    DempipeError,
    ShapeError,
    MeshError,
    SceneError,
    CacheError,
    StabilityError,
    DeviceError,
    ExportError,
)

# name -> module that defines it; resolved on first attribute access (PEP 562).
_LAZY = {
    "SphereSet": "spheres",
    "build_sphere_set": "spheres",
    "SphereCache": "cache",
    "build_shape": "shapes",
    "load_mesh": "shapes",
    "Scene": "scene",
    "load_scene": "scene",
    "Material": "materials",
    "Model": "model",
    "build_model": "build",
    "State": "state",
    "Simulator": "simulator",
    "Frames": "frames",
    "write_usd": "export.usd",
    "load_usd_scene": "usd_scene",
    "write_overlay": "export.overlay",
    "write_physics_stage": "export.physics_stage",
}


def __getattr__(name):
    try:
        module = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'dempipe' has no attribute {name!r}") from None
    value = getattr(_import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
