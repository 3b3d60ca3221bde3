"""`dempipe check SCENE`: predict stability problems of a scene without simulating.

Prints dempipe.check.stability's report (text, or ``--json``) on stdout. Exit 0 when the
scene is safe to bake, 1 when bake would refuse it or the bake would fail (an
error finding); scene and mesh errors are one line and exit 2 (cli/main.py).
Imports neither pxr nor numba.cuda; numba itself only to voxelize a shape that
is not in the sphere-set cache yet.
"""

from __future__ import annotations

import json
import sys

import click

from dempipe_cli.params import Number


@click.command("check")
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
@click.option("--cache-dir", type=click.Path(file_okay=False), default=None,
              help="Sphere-set cache folder (default: $DEMPIPE_CACHE_DIR or the user cache).")
@click.option("--resolution", type=click.IntRange(min=1), default=None,
              help="Spheres across the smallest shape (overrides the scene's, as in bake).")
@click.option("--sphere-diameter", type=Number(lo=0, lo_open=True), default=None,
              metavar="M", help="Sphere diameter in metres (instead of --resolution).")
def check(scene, as_json, cache_dir, resolution, sphere_diameter):
    """Check SCENE (a .toml scene file or a UsdPhysics stage): time step against the
    critical step, speeds against the sphere size, frame-0 overlaps, mass ratios, tiny
    shapes."""
    from dempipe.spheres.cache import SphereCache
    from dempipe.pipeline.check import analyze_scene

    from dempipe.errors import DempipeError

    if resolution is not None and sphere_diameter is not None:
        raise click.UsageError("give --resolution or --sphere-diameter, not both")
    simulation = {k: v for k, v in (("resolution", resolution),
                                    ("sphere_diameter", sphere_diameter)) if v is not None}
    try:
        cache = SphereCache(cache_dir, strict=True) if cache_dir else None
        report = analyze_scene(scene, cache=cache, simulation=simulation)
    except DempipeError as exc:
        if not as_json:
            raise
        # --json promises JSON on stdout, for scripts: the error too
        click.echo(json.dumps(dict(scene=scene, ok=False, error=str(exc),
                                   kind=type(exc).__name__), indent=2))
        sys.exit(exc.exit_code)
    if as_json:
        click.echo(report.to_json(indent=2))
    else:
        click.echo(report.format())
    if not report.ok:
        sys.exit(1)
