"""`dempipe cache`: inspect or clear the sphere-set cache."""

from __future__ import annotations

import json

import click

_cache_dir_option = click.option(
    "--cache-dir", type=click.Path(file_okay=False), default=None,
    help="Cache folder (default: $DEMPIPE_CACHE_DIR or the user cache folder).")


def _human(n: int) -> str:
    size = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return f"{n} B"  # pragma: no cover


@click.group("cache")
def cache():
    """Inspect or clear the sphere-set cache."""


@cache.command("info")
@_cache_dir_option
@click.option("--json", "as_json", is_flag=True, help="Print as JSON.")
def info(cache_dir, as_json):
    """Show the cache folder, its number of entries and their size."""
    from dempipe.spheres.cache import SphereCache

    data = SphereCache(cache_dir).info()
    if as_json:
        click.echo(json.dumps(data))
        return
    click.echo(f"location: {data['location']}")
    click.echo(f"entries:  {data['entries']}")
    click.echo(f"size:     {_human(data['bytes'])} ({data['bytes']} bytes)")


@cache.command("clear")
@_cache_dir_option
def clear(cache_dir):
    """Remove every cached sphere set."""
    from dempipe.spheres.cache import SphereCache

    c = SphereCache(cache_dir)
    n = c.clear()
    click.echo(f"removed {n} entr{'y' if n == 1 else 'ies'} from {c.root}")
