"""`dempipe scene export SCENE.toml -o SCENE.usda`: a TOML scene as a UsdPhysics stage."""

from __future__ import annotations

import click


@click.group("scene")
def scene():
    """Convert scene files."""


@scene.command("export")
@click.argument("scene_file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="The stage to write: .usda, .usdc or .usd.")
def export(scene_file, output):
    """Write SCENE_FILE (a .toml scene) as a UsdPhysics stage a DCC opens, and the
    scene's [simulation] settings, which a stage cannot hold, as NAME.settings.toml
    beside it: bake that file to get the scene's motion (docs/usd-input.md)."""
    from dempipe.pipeline.export import export_scene

    stage, settings = export_scene(scene_file, output)
    click.echo(f"wrote {stage}" + ("" if settings is None else
                                   f" and {settings} (its [simulation] settings: bake this "
                                   f"file for the scene's motion)"))
