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
@click.option("--debug", is_flag=True, hidden=True, help="Show full tracebacks on errors.")
def export(scene_file, output, debug):
    """Write SCENE_FILE (a .toml scene) as a UsdPhysics stage a DCC opens; bake the
    stage with `dempipe bake` (docs/usd-input.md)."""
    from dempipe.usd.physics_stage import write_physics_stage
    from dempipe.scene.load import load_scene

    path = write_physics_stage(load_scene(scene_file), output)
    click.echo(f"wrote {path}")
