"""A scene file read by its suffix: a TOML scene, the TOML settings of a USD stage
(``[usd] stage = ...``), or a UsdPhysics stage itself.

:func:`load_scene` reads a file, :func:`parse_scene` a TOML string; both return a
:class:`~dempipe.scene.data.Scene` or raise :class:`~dempipe.errors.SceneError` with a
one-line message ``"<file>: <key.path>: <problem> (<fix or known values>)"``.
"""

from __future__ import annotations

import re
from pathlib import Path

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

from dempipe.errors import SceneError
from dempipe.scene.data import Scene
from dempipe.scene.keys import SceneKeys
from dempipe.scene.toml_reader import TOP_KEYS, read_tables
from dempipe.scene.usd_reader import load_usd_scene, load_usd_settings

#: Scene files read as USD stages (dempipe.scene.usd_reader) rather than TOML.
USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")

# where tomllib's messages say the error is, taken out into the message's key path
_TOML_POS = re.compile(r"\s*\(at line (\d+), column (\d+)\)\s*$")
_TOML_EOF = re.compile(r"\s*\(at end of document\)\s*$")


def parse_scene(text: str, path: str | Path | None = None) -> Scene:
    """Parse and validate scene TOML ``text``.

    ``path`` names the file in error messages and is the base of relative mesh
    paths (the current directory when None). Raises SceneError on any problem.
    """
    p = Path(path).expanduser().resolve() if path is not None else None
    ctx = SceneKeys(p, p.name if p is not None else "<scene>")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        msg = str(exc)
        lineno = getattr(exc, "lineno", None)
        colno = getattr(exc, "colno", None)
        m = _TOML_POS.search(msg)
        if m:
            lineno, colno = int(m.group(1)), int(m.group(2))
            msg = msg[: m.start()]
        elif _TOML_EOF.search(msg):
            lineno = max(1, len(text.splitlines()))
            msg = _TOML_EOF.sub("", msg) + " at end of document"
        where = f"line {lineno}" if lineno else "TOML syntax"
        raise ctx.error(where, msg.strip(),
                        f"column {colno}" if colno else "fix the TOML syntax") from None
    if "usd" in data:
        # settings for a USD stage: the scene itself comes from the stage
        ctx.check_keys(data, "", TOP_KEYS, what="section")
        return load_usd_settings(ctx, data)
    return read_tables(ctx, data)


def load_scene(path: str | Path) -> Scene:
    """Read, parse and validate the scene file at ``path``: a TOML scene, or a USD
    stage (.usd, .usda, .usdc, .usdz) with UsdPhysics (docs/usd-input.md). Raises a
    SceneError (a ShapeError or MeshError for a shape) naming the file, the key and
    the fix."""
    p = Path(path).expanduser()
    if p.suffix.lower() in USD_EXTENSIONS:
        return load_usd_scene(p)
    if p.suffix.lower() not in ("", ".toml"):
        from dempipe.mesh.shapes import MESH_EXTENSIONS   # (trimesh: only for odd names)

        if p.suffix.lower() in MESH_EXTENSIONS:
            raise SceneError(
                f"{p.name}: a mesh, not a scene: give a scene file (.toml, or a UsdPhysics "
                f"stage .usd/.usda/.usdc/.usdz) whose [shapes.NAME] table has mesh = "
                f"\"{p.name}\" (docs/scene-format.md)")
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SceneError(f"{p.name}: file not found") from None
    except IsADirectoryError:
        raise SceneError(f"{p.name}: is a folder, not a scene file") from None
    except UnicodeDecodeError as exc:
        raise SceneError(f"{p.name}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise SceneError(f"{p.name}: cannot read ({exc.strerror})") from None
    return parse_scene(text, p)
