"""`dempipe scene export`: a TOML scene as a UsdPhysics stage a DCC opens, and, beside
it, the settings TOML that holds what a stage cannot (docs/usd-input.md)."""

from __future__ import annotations

from pathlib import Path

from dempipe.errors import ExportError
from dempipe.pipeline.checkpoint import atomic_write
from dempipe.scene.load import load_scene
from dempipe.scene.settings import settings_toml
from dempipe.usd.physics_stage import write_physics_stage


def settings_path(stage_path) -> Path:
    """Where export_scene writes a stage's settings TOML: NAME.settings.toml beside it."""
    stage_path = Path(stage_path)
    return stage_path.with_name(f"{stage_path.stem}.settings.toml")


def export_scene(scene_path, out_path) -> tuple[Path, Path | None]:
    """Write the TOML scene ``scene_path`` as a UsdPhysics stage at ``out_path`` and,
    when its ``[simulation]`` has keys other than the defaults (resolution, stiffness
    target, seed, ...: a stage cannot hold them), the settings TOML that names the
    stage (settings_path). Baking that file gives the TOML scene's motion; baking the
    stage alone takes the default settings. Returns (stage, settings TOML or None)."""
    scene = load_scene(scene_path)
    stage = write_physics_stage(scene, out_path)
    text = settings_toml(scene.simulation, stage.name)
    target = settings_path(stage)
    if text is None:
        return stage, None
    try:
        atomic_write(target, lambda fh: fh.write(text.encode("utf-8")))
    except OSError as exc:
        raise ExportError(f"{target}: cannot write the stage's settings "
                          f"({exc.strerror or exc})") from None
    return stage, target
