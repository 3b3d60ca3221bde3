"""`dempipe wedge SCENE -o DIR`: variants of a bake (seeds, any scene key) as Dask tasks.

Parses the options, calls dempipe.farm.wedge.wedge, prints a line per finished variant
and the total on stderr. Dask is imported by the library only when the wedge runs,
so `dempipe wedge --help` works without it.
"""

from __future__ import annotations

import click


@click.command("wedge")
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False),
              help="Folder for the variants' scene files, USD files and wedge.csv (created).")
@click.option("--seeds", type=click.IntRange(min=1), default=None, metavar="N",
              help="N variants of simulation.seed: the scene's seed and the N-1 after it.")
@click.option("--vary", multiple=True, metavar="KEY=V1,V2,...",
              help="Values of a scene key by its dotted path, e.g. "
                   "materials.wood.restitution=0.2,0.5 or bodies[0].count=50,100; "
                   "repeat for a grid.")
@click.option("--workers", type=click.IntRange(min=1), default=None, metavar="N",
              help="Local Dask workers (the default: one per core, at most one per variant).")
@click.option("--threads", type=click.IntRange(min=1), default=None, metavar="N",
              help="Threads of each local worker's bake (default: the cores shared out).")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="A running Dask scheduler (tcp://host:8786) whose workers bake "
                   "(docs/farm.md).")
@click.option("--device", type=click.Choice(["cpu", "cuda", "auto"]), default=None,
              help="Compute device (default: the scene's simulation.device).")
@click.option("--layout", type=click.Choice(["instancer", "xforms"]), default="instancer",
              show_default=True, help="One PointInstancer, or one Xform per body.")
@click.option("--format", "fmt", type=click.Choice(["usdc", "usda", "usd"]), default="usdc",
              show_default=True, help="The variants' USD files.")
@click.option("--cache-dir", type=click.Path(file_okay=False), default=None,
              help="Sphere-set cache folder every worker can use (default: each worker's "
                   "$DEMPIPE_CACHE_DIR or user cache).")
@click.option("--force", is_flag=True,
              help="Bake variants that `dempipe check` refuses (see `dempipe bake --force`).")
@click.option("--contact-sheet", is_flag=True,
              help="Also draw OUTPUT/contact_sheet.png: every finished variant's last frame "
                   "(needs dempipe[preview]; docs/preview.md).")
@click.option("--quiet", "-q", is_flag=True, help="No line per variant.")
def wedge(scene, output, seeds, vary, workers, threads, scheduler, device, layout, fmt,
          cache_dir, force, contact_sheet, quiet):
    """Bake variants of SCENE, each a task on Dask, into OUTPUT.

    Every combination of --seeds and the --vary values is one variant: its scene
    file OUTPUT/v000.toml (bake it again with `dempipe bake`) and its bake
    OUTPUT/v000.usdc. OUTPUT/wedge.csv has a row per variant (values, status,
    output, wall time, worker), rewritten as each finishes. A failed variant fails
    its row only; run again, the wedge skips the variants already done.
    Needs Dask: pip install "dempipe[farm]". Farms: docs/farm.md.
    """
    from dempipe.farm.wedge import WedgeFailed, wedge as run_wedge
    from dempipe.farm.wedge import contact_sheet as draw_sheet

    if contact_sheet:       # before any bake: a missing extra is said at once
        from dempipe.preview import require

        require()

    def say(line):
        if not quiet:
            click.echo(line, err=True)

    def warn(line):
        click.echo(f"warning: {line}", err=True)

    result = run_wedge(scene, output, seeds=seeds, vary=vary, workers=workers,
                       scheduler=scheduler, threads=threads, device=device, layout=layout,
                       suffix=f".{fmt}", force=force, cache_dir=cache_dir, progress=say,
                       warn=warn)
    if contact_sheet and result.ok:
        say(f"contact sheet: {draw_sheet(result)}")
    failed = result.failed
    if failed:
        first = failed[0]
        raise WedgeFailed(f"{len(failed)} of {len(result.variants)} variants failed "
                          f"(first, {first.name}: {first.status[len('failed: '):]}); "
                          + ("none was written" if len(failed) == len(result.variants)
                             else "the others were written") + f"; see {result.csv}")
