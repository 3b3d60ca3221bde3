"""`dempipe blender-extension -o dempipe_bake.zip`: the Blender extension as a zip.

The extension (blender/dempipe_bake/ in the repository, installed beside the CLI
as ``dempipe_cli.blender_extension``) runs inside Blender and never imports
dempipe; this only zips its files with ``blender_manifest.toml`` at the archive's
root, what Blender's "Install from Disk" reads (``blender --command extension
build`` needs the Blender program; this does not).
"""

from __future__ import annotations

import zipfile
from importlib.util import find_spec
from pathlib import Path

import click


def extension_dir() -> Path:
    """The extension's source folder: installed beside the CLI, else the checkout's."""
    spec = find_spec("dempipe_cli.blender_extension")      # finds, does not import (bpy)
    if spec is not None and spec.submodule_search_locations:
        return Path(list(spec.submodule_search_locations)[0])
    return Path(__file__).resolve().parents[1] / "blender" / "dempipe_bake"


def build_zip(out: Path) -> list[str]:
    """Zip the extension to ``out``; returns the archive's names."""
    src = extension_dir()
    if not (src / "blender_manifest.toml").is_file():
        raise click.ClickException(f"the Blender extension is not installed here ({src} has "
                                   f"no blender_manifest.toml)")
    files = sorted(p for p in src.rglob("*") if p.is_file() and "__pycache__" not in p.parts
                   and p.suffix in (".py", ".toml"))
    out.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for p in files:
            z.write(p, p.relative_to(src).as_posix())
    return [p.relative_to(src).as_posix() for p in files]


@click.command("blender-extension")
@click.option("-o", "--output", default="dempipe_bake.zip", show_default=True,
              type=click.Path(dir_okay=False), help="The zip to write.")
def blender_extension(output):
    """Write the Blender extension (Bake with dempipe from Blender's Physics
    properties) as a zip for Edit > Preferences > Get Extensions > Install from Disk."""
    names = build_zip(Path(output))
    click.echo(f"wrote {output}: {len(names)} files; install it in Blender with "
               f"Install from Disk (docs/blender.md)", err=True)
