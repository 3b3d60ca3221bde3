"""Exceptions a user can act on.

Every error dempipe raises on bad input is a :class:`DempipeError` whose message
names the file and/or key at fault and says how to fix it. The CLI prints the
message on one line and exits non-zero; tracebacks appear only with ``--debug``.
"""


class DempipeError(Exception):
    """Base class of all user-facing errors (bad input, unstable settings, ...)."""

    exit_code = 2


class ShapeError(DempipeError):
    """A built-in shape name or parameter is wrong, or a mesh file is unusable."""


class MeshError(ShapeError):
    """A mesh is empty, flat, degenerate, non-finite or cannot be made solid."""


class SceneError(DempipeError):
    """A scene file is malformed: syntax, unknown key, bad type or value."""


class CacheError(DempipeError):
    """The sphere-set cache folder cannot be used."""


class StabilityError(DempipeError):
    """Settings that would make the explicit integrator unstable, or a bake that blew up."""

    exit_code = 3


class DeviceError(DempipeError):
    """The requested compute device (e.g. CUDA) is not usable here."""


class ExportError(DempipeError):
    """The output file cannot be written."""
