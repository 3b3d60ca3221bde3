"""The `dempipe` command: a thin click layer over the library.

Each subcommand lives in its own module and only parses options, calls the
library, and shows progress. Errors derived from :class:`dempipe.DempipeError`
become one line on stderr and a non-zero exit; tracebacks only with ``--debug``.
"""

from __future__ import annotations

# First of all, before click and the library load: the stop handlers
# (dempipe.interrupt), so that a signal during start-up stops cleanly too.
from dempipe import interrupt as _interrupt  # noqa: I001  (cheap: no numpy, no pxr)

_interrupt.install()
_interrupt.hold()       # until main() can catch the stop: recorded, raised there

import sys
import warnings

import click

import dempipe
from dempipe.errors import DempipeError

# subcommand name -> (module, attribute); imported only when that command runs,
# so `dempipe --help` stays fast and never imports pxr or numba.cuda.
COMMANDS = {
    "spheres": ("dempipe_cli.spheres_cmd", "spheres"),
    "cache": ("dempipe_cli.cache_cmd", "cache"),
    "bake": ("dempipe_cli.bake_cmd", "bake"),
    "check": ("dempipe_cli.check_cmd", "check"),
    "report": ("dempipe_cli.report_cmd", "report"),
    "preview": ("dempipe_cli.preview_cmd", "preview"),
    "wedge": ("dempipe_cli.wedge_cmd", "wedge"),
    "scene": ("dempipe_cli.scene_cmd", "scene"),
    "blender-extension": ("dempipe_cli.blender_cmd", "blender_extension"),
}

HELP = {
    "spheres": "Build (and cache) sphere sets of meshes or built-in shapes.",
    "cache": "Inspect or clear the sphere-set cache.",
    "bake": "Simulate a scene and write the animation to USD.",
    "check": "Predict stability problems of a scene without simulating.",
    "report": "Measure error against run time for a scene's settings.",
    "preview": "Render a still or a movie of a bake (needs dempipe[preview]).",
    "wedge": "Bake variants of a scene (seeds, any key) as tasks on Dask.",
    "scene": "Convert a TOML scene to a UsdPhysics stage (scene export).",
    "blender-extension": "Write the Blender extension (Bake from Blender) as a zip.",
}


class LazyGroup(click.Group):
    def list_commands(self, ctx):
        return [name for name, (mod, _) in COMMANDS.items() if _module_exists(mod)]

    def get_command(self, ctx, name):
        if name not in COMMANDS or not _module_exists(COMMANDS[name][0]):
            return None
        from importlib import import_module

        module, attr = COMMANDS[name]
        return getattr(import_module(module), attr)

    def format_commands(self, ctx, formatter):
        # Short help without importing every subcommand module.
        rows = [(name, HELP[name]) for name in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


def _module_exists(module: str) -> bool:
    from importlib.util import find_spec

    return find_spec(module) is not None



def _show_warning(message, category, filename, lineno, file=None, line=None):
    click.echo(f"warning: {message}", err=True)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(dempipe.__version__, prog_name="dempipe")
@click.option("--debug", is_flag=True, help="Show full tracebacks on errors.")
@click.pass_context
def app(ctx, debug):
    """dempipe: rigid bodies as sphere sets (Harada et al. 2007), baked to USD."""
    ctx.ensure_object(dict)
    ctx.obj["debug"] = debug
    warnings.showwarning = _show_warning


def _exit_if_stopped(exc: BaseException, debug: bool) -> None:
    """A failure while a stop is pending is the stop's doing (interrupt.stop_behind):
    report the stop and exit 128 + its number, the traceback only with --debug."""
    from dempipe import interrupt

    stop = interrupt.stop_behind(exc)
    if stop is None:
        return
    if debug:
        import traceback
        traceback.print_exception(exc)
    click.echo(f"error: stopped by {interrupt.signal_name(stop.signum)}", err=True)
    sys.exit(stop.exit_code)


def main(argv=None):
    """Console entry point: run the app, turn DempipeError into one line + exit code.

    The stop handlers (dempipe.interrupt) go in first, so that SIGINT, SIGTERM and
    SIGHUP stop even the start-up cleanly (exit 128 + the signal's number) and a
    bake keeps its frames and checkpoint."""
    from dempipe import interrupt

    interrupt.install()
    args = list(argv if argv is not None else sys.argv[1:])
    debug = "--debug" in args
    if debug:                       # the group's flag, wherever it was given
        args = ["--debug"] + [a for a in args if a != "--debug"]
    try:
        interrupt.release()
        interrupt.check()           # a stop during the imports above
        app.main(args=args, prog_name="dempipe", standalone_mode=False)
        interrupt.check()           # a stop swallowed by a library: still a stop
    except interrupt.StopRequested as exc:
        click.echo(f"error: stopped by {interrupt.signal_name(exc.signum)}", err=True)
        sys.exit(exc.exit_code)
    except click.exceptions.Abort:
        stop = interrupt.requested()
        click.echo("Aborted." if stop is None
                   else f"error: stopped by {interrupt.signal_name(stop)}", err=True)
        sys.exit(130 if stop is None else 128 + stop)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except DempipeError as exc:
        if debug:                   # the traceback, and the same exit code as without
            import traceback
            traceback.print_exception(exc)
        click.echo(f"error: {exc}", err=True)
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        click.echo("Interrupted.", err=True)
        sys.exit(130)
    except Exception as exc:  # a bug: still one line unless --debug
        _exit_if_stopped(exc, debug)
        if debug:
            raise
        click.echo(
            f"internal error: {type(exc).__name__}: {exc} (rerun with --debug for the traceback)",
            err=True,
        )
        sys.exit(1)


if __name__ == "__main__":
    main()
