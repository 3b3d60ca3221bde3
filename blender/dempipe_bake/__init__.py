"""dempipe Bake: Blender's rigid-body world baked by dempipe, on the user's own objects.

The extension never imports dempipe or numba: it writes the scene (export.py),
runs the `dempipe` executable as a child process (runner.py, operators.py) and
keys the baked USD onto the objects (apply.py). docs/blender.md describes it.
"""

from __future__ import annotations

import bpy

from . import operators, ui

_CLASSES = ui.CLASSES + operators.CLASSES


def register():
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.dempipe = bpy.props.PointerProperty(type=ui.DempipeSettings)


def unregister():
    for job in list(operators.JOBS.values()):
        job.cancel()
    del bpy.types.Scene.dempipe
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
