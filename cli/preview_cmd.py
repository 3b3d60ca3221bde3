"""`dempipe preview BAKE -o OUT.png|mp4|gif`: pictures of a bake without a DCC.

Parses options and calls dempipe.preview (docs/preview.md). Needs the extra
``dempipe[preview]``; without it, one line saying how to install it and exit 2.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click

from dempipe_cli.params import Number


class MovieProgress:
    """Frames done, frames per second and ETA on stderr: a bar on a terminal, a line
    every 5 s in a log (as `dempipe bake` does)."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self.t0 = time.perf_counter()
        self.last = -1.0

    def __call__(self, done: int, total: int):
        if self.quiet:
            return
        now = time.perf_counter()
        if not self.tty and done < total and now - self.last < 5.0:
            return
        self.last = now
        elapsed = now - self.t0
        rate = done / elapsed if elapsed > 0 else 0.0
        eta = (total - done) / rate if rate else 0.0
        width = 24
        bar = "#" * int(width * done / total)
        line = f"[{bar:<{width}}] frame {done}/{total}  {rate:.1f} frames/s  ETA {eta:4.0f} s"
        click.echo(line + ("\r" if self.tty and done < total else "\n"), err=True, nl=False)


@click.command("preview")
@click.argument("bake", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="A still (.png) or a movie (.mp4, .gif).")
@click.option("--frame", type=int, default=None, metavar="N",
              help="The frame of a still [default: the last frame].")
@click.option("--frames", default=None, metavar="START:END",
              help="The frames of a movie, inclusive [default: all].")
@click.option("--camera", type=click.Choice(["three-quarter", "top", "front"]),
              default="three-quarter", show_default=True,
              help="Framing the bodies at the bake's first and last frames.")
@click.option("--size", default="1280x720", show_default=True, metavar="WxH",
              help="Picture size in pixels.")
@click.option("--fps", type=Number(lo=0, lo_open=True, hi=1000), default=None,
              help="Movie frame rate [default: the stage's framesPerSecond].")
@click.option("--msaa", type=click.Choice(["0", "2", "4", "8"]), default=None,
              help="Multisamples a pixel (antialiasing) [default: 4 for a still, 0 for a "
                   "movie, 2.7x faster a frame].")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def preview(bake, output, frame, frames, camera, size, fps, msaa, quiet):
    """Render a still or a movie of BAKE (a USD stage: any dempipe bake, either layout).

    Shaded meshes in the colours the USD carries (bound UsdPreviewSurface or
    displayColor), the colliders or a ground grid, sun shadows. Needs the extra:
    pip install 'dempipe[preview]'.
    """
    from dempipe.preview import (
        MOVIE_EXTENSIONS, STILL_EXTENSIONS, parse_size, render_frame, render_movie, require)
    from dempipe.preview.reader import PreviewError

    out = Path(output)
    ext = out.suffix.lower()
    if ext not in STILL_EXTENSIONS + MOVIE_EXTENSIONS:
        raise PreviewError(f"{out}: unknown extension {out.suffix!r} (use .png for a still, "
                           f".mp4 or .gif for a movie)")
    require("moderngl", "PIL", "av") if ext == ".mp4" else require()
    wh = parse_size(size)
    if fps is not None and not fps > 0:
        raise PreviewError(f"--fps: {fps:g} must be greater than 0")
    t0 = time.perf_counter()
    if ext in STILL_EXTENSIONS:
        if frames is not None:
            raise PreviewError("--frames is for movies (.mp4, .gif); use --frame N for a still")
        path = render_frame(bake, out, frame=frame, camera=camera, size=wh,
                            **({"samples": int(msaa)} if msaa else {}))
        what = "frame " + (str(frame) if frame is not None else "(last)")
    else:
        if frame is not None:
            raise PreviewError("--frame is for stills (.png); use --frames START:END for a movie")
        path = render_movie(bake, out, frames=frames, camera=camera, size=wh, fps=fps,
                            progress=MovieProgress(quiet),
                            **({"samples": int(msaa)} if msaa else {}))
        what = "frames " + (frames or "(all)")
    if not quiet:
        click.echo(f"wrote {path}: {what}, {wh[0]}x{wh[1]}, {camera} camera, "
                   f"{time.perf_counter() - t0:.1f} s", err=True)
