"""`dempipe bake SCENE -o OUT.usd`: simulate a scene and write the animation to USD."""

from __future__ import annotations

import sys
import threading
import time

import click

from dempipe_cli.params import Number


#: Seconds without a first frame after which the bar says why: a machine's first bake
#: compiles the kernels of the scene's features (docs/performance.md, "Startup and
#: compile time"), and a new shape's sphere set is built before its first step.
SLOW_START = 10.0


class Progress:
    """One line on stderr: frames done, simulated time, steps per second, ETA; and,
    when the first frame takes longer than SLOW_START, a line saying why."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self.t0 = time.perf_counter()
        self.last = -1.0
        self.timer = None
        if not quiet:
            self.timer = threading.Timer(SLOW_START, self.slow_start)
            self.timer.daemon = True
            self.timer.start()

    def slow_start(self):
        click.echo(f"still on the first frame after {SLOW_START:.0f} s: a machine's first "
                   "bake of a scene with these features compiles its simulation kernels "
                   "(1-2 minutes, once; later bakes load them in a second)", err=True)

    def close(self):
        """Stop waiting for the first frame (the bake ended or failed)."""
        if self.timer is not None:
            self.timer.cancel()

    def __call__(self, k, n, stats):
        self.close()
        if self.quiet:
            return
        now = time.perf_counter()
        done = k + 1
        if self.tty is False and done < n and now - self.last < 5.0:
            return      # in a log: a line every 5 s, not a flood of carriage returns
        self.last = now
        rate = stats.steps / stats.wall_seconds if stats.wall_seconds else 0.0
        eta = (stats.wall_seconds / k) * (n - 1 - k) if k else 0.0
        width = 24
        bar = "#" * int(width * done / n)
        line = (f"[{bar:<{width}}] frame {done}/{n}  {rate:,.0f} steps/s  "
                f"ETA {eta:5.0f} s")
        end = "\r" if self.tty and done < n else "\n"
        click.echo(line, err=True, nl=False)
        click.echo(end, err=True, nl=False)


def _device_text(r) -> str:
    if r["device"] == "cpu":
        import numba

        n = r.get("threads") or numba.get_num_threads()
        return f"the CPU ({n} thread{'s' if n != 1 else ''})"
    return "the CUDA GPU"


def clamp_threads(threads, warn):
    """--threads above what numba may use here is lowered to it, with a note."""
    if threads is None:
        return None
    import numba

    most = int(numba.config.NUMBA_NUM_THREADS)
    if threads > most:
        warn(f"--threads {threads}: only {most} available here (cores or NUMBA_NUM_THREADS); "
             f"using {most}")
        return most
    return threads


@click.command("bake")
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Output stage: .usd, .usdc (binary) or .usda (text).")
@click.option("--device", type=click.Choice(["cpu", "cuda", "auto"]), default=None,
              help="Compute device (default: the scene's simulation.device).")
@click.option("--layout", type=click.Choice(["instancer", "xforms"]), default="instancer",
              show_default=True, help="One PointInstancer, or one Xform per body.")
@click.option("--frames", default=None, metavar="START:END",
              help="Write only these frames, numbered as the output's time codes (from "
                   "the scene's start frame); the simulation always starts at the first.")
@click.option("--threads", type=click.IntRange(min=1), default=None,
              help="CPU threads (default: the cores other processes leave free, "
                   "followed as they change).")
@click.option("--report", "report_path", type=click.Path(dir_okay=False), default=None,
              help="Write bake figures (time, steps, overlap, ...) as JSON.")
@click.option("--cache-dir", type=click.Path(file_okay=False), default=None,
              help="Sphere-set cache folder (default: $DEMPIPE_CACHE_DIR or the user cache).")
@click.option("--force", is_flag=True,
              help="Bake even a scene that `dempipe check` refuses: deep frame-0 overlaps, "
                   "a dt above the critical step, tunnelling speeds.")
@click.option("--checkpoint-every", "checkpoint_seconds", type=Number(lo=0),
              default=None, metavar="SECONDS",
              help="Longest wall time between two checkpoints: what a SIGKILL or power cut "
                   "can lose [default: 60].")
@click.option("--chunk-frames", type=click.IntRange(min=1, max=1_000_000), default=None,
              hidden=True,
              help="Frames per chunk written to disk (default: 32 MiB of frames).")
@click.option("--resume", is_flag=True,
              help="Go on from the checkpoint an interrupted bake to OUTPUT left (the same "
                   "scene and settings; from frame 0 when there is none).")
@click.option("--resolution", type=click.IntRange(min=1), default=None,
              help="Spheres across the smallest shape (replaces the scene's; for a bare "
                   "USD stage, dempipe's own setting).")
@click.option("--sphere-diameter", type=Number(lo=0, lo_open=True), default=None,
              metavar="M", help="Sphere diameter in metres (instead of --resolution).")
@click.option("--quiet", "-q", is_flag=True,
              help="No progress bar and no closing summary (errors and warnings still "
                   "show; --report keeps the figures).")
def bake(scene, output, device, layout, frames, threads, report_path, cache_dir, force,
         checkpoint_seconds, chunk_frames, resume, resolution, sphere_diameter, quiet):
    """Simulate SCENE (a .toml scene file, or a UsdPhysics stage .usd/.usda/.usdc) and
    write its animation to OUTPUT (for a stage: an overlay layer over it).

    Frames go to disk as they are made, with checkpoints, in a hidden folder beside
    OUTPUT. SIGINT, SIGTERM or SIGHUP stop the bake within about a second: the
    frames done are written to OUTPUT's .partial file and `--resume` goes on from
    the last checkpoint (docs/faults.md)."""
    from dempipe.pipeline.bake import bake as run_bake, write_report
    from dempipe.spheres.cache import SphereCache
    from dempipe.errors import DempipeError

    def warn(msg):
        click.echo(f"warning: {msg}", err=True)

    if resolution is not None and sphere_diameter is not None:
        raise click.UsageError("give --resolution or --sphere-diameter, not both")
    if report_path:
        from pathlib import Path

        from dempipe.pipeline.bake import check_report_path, check_writable

        check_report_path(report_path, output, scene)
        check_writable(Path(report_path).parent, "report folder")
    cache = SphereCache(cache_dir, strict=True) if cache_dir else None
    threads = clamp_threads(threads, warn)
    progress = Progress(quiet)
    try:
        result = run_bake(scene, output, device=device, layout=layout, frames=frames,
                          threads=threads, cache=cache, progress=progress, warn=warn,
                          force=force, resume=resume, chunk_frames=chunk_frames,
                          checkpoint_seconds=checkpoint_seconds, simulation={k: v for k, v in (
                              ("resolution", resolution), ("sphere_diameter", sphere_diameter))
                              if v is not None})
    except DempipeError as exc:
        partial = getattr(exc, "result", None)
        if partial is not None and report_path:
            write_report(report_path, partial.report)
        raise
    finally:
        progress.close()
    r = result.report
    if report_path:
        write_report(report_path, r)
    if not quiet:
        click.echo(
            f"wrote {result.path}: {r['bodies']} bodies, {r['frames']} frames, "
            f"{r['steps']} steps of {r['dt']:.3g} s in {r['simulate_seconds']:.1f} s on "
            f"{_device_text(r)} "
            f"({r['sphere_steps_per_second'] / 1e6:.2f} M sphere-steps/s"
            + (f"; {r['steps_skipped_asleep']} skipped, every body asleep"
               if r.get("steps_skipped_asleep") else "")
            + "), largest overlap "
            f"{r['max_overlap']:.1%} of a diameter" + _bonds_text(r), err=True)


def _bonds_text(r) -> str:
    """The summary's glue part: how many bonds broke (per frame: --report's
    bonds_broken_per_frame)."""
    if not r.get("bonds"):
        return ""
    broken = sum(r.get("bonds_broken_per_frame") or [])
    most = max(r.get("bonds_broken_per_frame") or [0])
    return (f"; {broken} of {r['bonds']} glue bonds broke"
            + (f", at most {most} in one frame" if broken else ""))
