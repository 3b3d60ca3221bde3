"""`dempipe report SCENE -o DIR`: error against run time over a sweep of settings.

Parses the sweep, calls dempipe.report.runs.run_report, prints a line per run. The
sweep lists are checked by the library (one-line errors, cli/main.py).
"""

from __future__ import annotations

import click

from dempipe_cli.params import Number


@click.command("report")
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False),
              help="Folder for report.md, report.csv and the PNG plots (created).")
@click.option("--resolutions", default=None, metavar="LIST",
              help="Spheres across the smallest shape, e.g. 4,6,8 [default: the scene's "
                   "resolution times 2/3, 5/6 and 1].")
@click.option("--dt-factors", default="1,0.5", show_default=True, metavar="LIST",
              help="Multiples of the scene's time step (auto: of its step per contact).")
@click.option("--stiffness-factors", default="0.3,1", show_default=True, metavar="LIST",
              help="Multiples of every material's contact stiffness.")
@click.option("--duration", type=Number(lo=0, lo_open=True), default=None, metavar="S",
              help="Simulated seconds per run [default: the scene's, at most 0.5].")
@click.option("--horizon", type=Number(lo=0, lo_open=True), default=None, metavar="S",
              help="When the per-body motion error is taken [default: 0.1 s after the "
                   "reference's median first contact].")
@click.option("--tolerance", type=Number(lo=0, lo_open=True), default=0.02, show_default=True,
              help="Largest error (in body sizes) a recommended setting may have.")
@click.option("--bodies", type=click.IntRange(min=1), default=None, metavar="N",
              help="Bake only the first N bodies of the scene (a quick look at a big one).")
@click.option("--device", type=click.Choice(["cpu", "cuda", "auto"]), default=None,
              help="Compute device (default: the scene's simulation.device).")
@click.option("--threads", type=click.IntRange(min=1), default=None,
              help="CPU threads (default: all cores).")
@click.option("--workers", type=click.IntRange(min=1), default=None, metavar="N",
              help="Bake the runs side by side on a local Dask cluster of N workers, each "
                   "with --threads threads (needs dempipe[farm]; docs/farm.md).")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Bake the runs on a running Dask scheduler's workers (docs/farm.md).")
@click.option("--cache-dir", type=click.Path(file_okay=False), default=None,
              help="Sphere-set cache folder (default: $DEMPIPE_CACHE_DIR or the user cache).")
@click.option("--spheres", "sphere_modes", default=None, metavar="LIST",
              help="Sphere-set modes to sweep, e.g. lattice,surface (the reference takes "
                   "the last). Default: the scene's own, no mode axis.")
@click.option("--rolling-tolerance", type=Number(lo=0, lo_open=True), default=None, metavar="X",
              help="Largest incline rolling error (a ball of each run's resolution and "
                   "sphere mode against 5/7 g sin θ) a recommended setting may have "
                   "[default: not a condition; it is measured and shown].")
@click.option("--laws", "contact_laws", default=None, metavar="LIST",
              help="Contact laws to sweep, e.g. linear,hertz (the reference takes the "
                   "last). Default: the scene's own, no law axis.")
@click.option("--no-plots", is_flag=True, help="Skip the PNG plots (no matplotlib needed).")
@click.option("--quiet", "-q", is_flag=True, help="No line per run.")
def report(scene, output, resolutions, dt_factors, stiffness_factors, duration, horizon,
           tolerance, bodies, device, threads, workers, scheduler, cache_dir, no_plots, quiet,
           sphere_modes, rolling_tolerance, contact_laws):
    """Bake SCENE at every combination of resolution, dt and stiffness factors; write
    the error of each run against its run time to OUTPUT (report.md, report.csv, PNGs).

    Errors: geometry (sphere sets against meshes), motion (against the finest run),
    physics (closed-form bounce, rolling, spin against dt). See docs/accuracy.md.
    """
    from dempipe.spheres.cache import SphereCache
    from dempipe.report.results import ReportError
    from dempipe.report.runs import Sweep, parse_values, run_report

    if duration is not None and not duration > 0:
        raise ReportError(f"--duration: {duration:g} must be greater than 0")
    if not tolerance > 0:
        raise ReportError(f"--tolerance: {tolerance:g} must be greater than 0")
    if rolling_tolerance is not None and not rolling_tolerance > 0:
        raise ReportError(f"--rolling-tolerance: {rolling_tolerance:g} must be greater than 0")
    sweep = Sweep(
        resolutions=parse_values(resolutions, "--resolutions", int) if resolutions else None,
        dt_factors=parse_values(dt_factors, "--dt-factors"),
        stiffness_factors=parse_values(stiffness_factors, "--stiffness-factors"),
        duration=duration, horizon=horizon, tolerance=tolerance, bodies=bodies, device=device,
        threads=threads, plots=not no_plots, rolling_tolerance=rolling_tolerance,
        sphere_modes=tuple(m.strip() for m in sphere_modes.split(",") if m.strip())
        if sphere_modes else None,
        contact_laws=tuple(m.strip() for m in contact_laws.split(",") if m.strip())
        if contact_laws else None)
    from dempipe.pipeline.bake import check_writable

    check_writable(output, "report folder")     # before any bake, not after all of them
    cache = SphereCache(cache_dir, strict=True) if cache_dir else None
    say = (lambda line: None) if quiet else (lambda line: click.echo(line, err=True))
    if workers is None and scheduler is None:
        result = run_report(scene, output, sweep, cache=cache, progress=say)
    else:
        # Run times measured side by side share the machine's memory bandwidth: compare
        # them with each other, not with a lone bake (docs/farm.md).
        from dempipe.farm.cluster import connect

        with connect(workers=workers, scheduler=scheduler, threads=threads,
                     what="dempipe report --workers/--scheduler") as farm:
            if farm.dashboard:
                say(f"Dask dashboard: {farm.dashboard}")
            result = run_report(scene, output, sweep, cache=cache, progress=say, farm=farm)
    rec = result.recommended
    click.echo(f"wrote {', '.join(str(p) for p in result.files)} ({len(result.runs)} runs, "
               f"{result.wall_s:.0f} s)")
    if rec is not None:
        click.echo(f"recommended: {rec.label} (error {rec.error:.3g}, {rec.wall_s:.3g} s; "
                   f"reference {result.reference.wall_s:.3g} s)")
    else:
        click.echo(f"no run but the reference ({result.reference.label}) is within the "
                   f"tolerance {tolerance:g}")
