"""dempipe: rigid bodies as sets of equal spheres, stepped by the eight stages of
Harada, Tanaka, Koshizuka and Kawaguchi (2007), baked to USD.

The public API is re-exported here lazily: ``import dempipe`` imports neither
pxr nor numba and compiles no kernel.
"""

from importlib import import_module as _import_module

from dempipe.errors import (
    CacheError,
    DempipeError,
    DeviceError,
    ExportError,
    MeshError,
    SceneError,
    ShapeError,
    StabilityError,
)

from .version import __version__

# name -> module that defines it; resolved on first attribute access (PEP 562).
_LAZY = {
    "bake": "pipeline.bake",
    "BakeResult": "pipeline.bake",
    "analyze_scene": "pipeline.check",
    "SphereSet": "spheres.sphere_set",
    "build_sphere_set": "spheres.sphere_set",
    "SphereCache": "spheres.cache",
    "build_shape": "mesh.shapes",
    "load_mesh": "mesh.shapes",
    "Scene": "scene.data",
    "load_scene": "scene.load",
    "load_usd_scene": "scene.usd_reader",
    "build_model": "scene.build",
    "Material": "sim.materials",
    "Model": "sim.model",
    "ModelBuilder": "sim.builder",
    "State": "sim.state",
    "Control": "sim.control",
    "Simulator": "sim.simulator",
    "Frames": "sim.frames",
    "write_usd": "usd.animation",
    "write_overlay": "usd.overlay",
    "write_physics_stage": "usd.physics_stage",
}

__all__ = ["__version__", "DempipeError", "ShapeError", "MeshError", "SceneError", "CacheError",
           "StabilityError", "DeviceError", "ExportError", *_LAZY]


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
