"""`dempipe spheres`: build (and cache) sphere sets of meshes or built-in shapes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from dempipe_cli.params import Number

from dempipe.errors import ShapeError
from dempipe.spheres.options import DEFAULT_MODE, DEFAULT_SPACING, SPACING_RANGE


def _resolve_input(arg: str, scale: float):
    """(name, mesh) of a mesh file path or a built-in shape name."""
    from dempipe.mesh import shapes

    path = Path(arg)
    if path.is_file():
        return path.stem, shapes.load_mesh(path, scale=scale)
    if arg in shapes.SHAPES:
        mesh = shapes.build_shape(arg)
        if scale != 1.0:
            mesh.apply_scale(scale)
        return arg, mesh
    known = ", ".join(sorted(shapes.SHAPES))
    if path.exists():
        raise ShapeError(f"{arg}: not a mesh file (it is a folder or special file)")
    raise ShapeError(f"{arg}: no such mesh file and no built-in shape of that name "
                     f"(shapes: {known}){shapes.did_you_mean(arg, shapes.SHAPES)}")


def _make_parent(out: str) -> None:
    from dempipe.errors import ExportError

    parent = Path(out).parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ExportError(f"{parent}: cannot create the output folder "
                          f"({exc.strerror or exc})") from None


def _output_path(out: str, name: str) -> str:
    return out.replace("{name}", name)


def _list_shapes() -> None:
    from dempipe.mesh import shapes

    for spec in shapes.list_shapes():
        params = ", ".join(f"{k}={p.default}" for k, p in spec.params.items())
        click.echo(f"{spec.name:10s} {spec.doc}" + (f"  [{params}]" if params else ""))


@click.command("spheres")
@click.argument("inputs", metavar="MESH_OR_SHAPE...", nargs=-1)
@click.option("--diameter", "-d", type=Number(), default=None,
              help="Sphere diameter in metres (after --scale).")
@click.option("--resolution", "-r", type=Number(), default=None,
              help="Spheres across the longest bounding-box extent (sets the diameter per input).")
@click.option("--scale", type=Number(), default=1.0, show_default=True,
              help="Scale applied to the mesh (e.g. 0.01 for a mesh in centimetres).")
@click.option("-o", "--output", "output", type=str, default=None,
              help="Write the sphere set: .npz (arrays) or .usda/.usdc/.usd (mesh and spheres). "
                   "With several inputs the path must contain {name}.")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
@click.option("--cache-dir", type=click.Path(file_okay=False), default=None,
              help="Cache folder (default: $DEMPIPE_CACHE_DIR or the user cache folder).")
@click.option("--no-cache", is_flag=True, help="Neither read nor write the cache.")
@click.option("--list-shapes", is_flag=True, help="List the built-in shapes and exit.")
@click.option("--mode", "modes", type=click.Choice(["lattice", "surface", "both"]),
              default=None, help="Sphere-set mode: lattice (solid voxelization), surface "
                                 "(centres on the surface's inward offset, round bodies roll) "
                                 "or both, one line each. Default: the library's default mode.")
@click.option("--spacing", type=click.FloatRange(*SPACING_RANGE), default=DEFAULT_SPACING,
              show_default=True,
              help="Surface mode: the shell's spacing as a fraction of the diameter (the "
                   "scene key surface_spacing).")
@click.option("--fracture", type=click.IntRange(2, None), default=None, metavar="N",
              help="Cut each input into N Voronoi pieces and show them: per piece its "
                   "volume, sphere count and whether it is watertight (-o: the pieces "
                   "as USD, slightly exploded, broken faces in their own material).")
@click.option("--seed", type=click.IntRange(0, None), default=0, show_default=True,
              help="--fracture: the seed of the pieces' seed points.")
@click.option("--errors/--no-errors", default=True, show_default=True,
              help="Measure the Hausdorff distance and bump height of the spheres' envelope.")
def spheres(inputs, diameter, resolution, scale, output, as_json, cache_dir, no_cache, list_shapes,
            modes, spacing, fracture, seed, errors):
    """Approximate meshes or built-in shapes by spheres of one diameter.

    MESH_OR_SHAPE is a mesh file (OBJ, STL, PLY, OFF, GLB/GLTF) or the name of a
    built-in shape (see --list-shapes; an existing file of that name wins), with
    its default parameters. Prints per input the sphere count (and how many of
    them are surface spheres, within one lattice layer of the surface: the ones a
    scene's default contact_layers = 1 keeps for contacts), a lattice's volume
    error (N d^3 against the mesh volume) and inertia error (relative Frobenius; a
    surface set is a shell and its body's mass comes from the mesh),
    the build time and whether the cache had it, and (unless --no-errors) the Hausdorff
    distance between the mesh and the spheres' envelope and the bump height (the
    dips between neighbouring spheres beyond the rounding any sphere of that
    diameter has), both in metres and in diameters.
    """
    if list_shapes:
        _list_shapes()
        return
    if not inputs:
        raise click.UsageError("give at least one mesh file or shape name (or --list-shapes)")
    if (diameter is None) == (resolution is None):
        raise click.UsageError("give exactly one of --diameter and --resolution")
    if no_cache and cache_dir is not None:
        raise click.UsageError("--cache-dir and --no-cache exclude each other")
    given = click.get_current_context().get_parameter_source("spacing")
    if given == click.core.ParameterSource.COMMANDLINE and (modes or DEFAULT_MODE) == "lattice":
        raise click.UsageError("--spacing is the surface mode's: add --mode surface (or "
                               "--mode both)")
    if not (math.isfinite(scale) and scale > 0):
        raise click.BadParameter(f"must be a positive number, got {scale}", param_hint="--scale")
    if output is not None:
        suffix = Path(output).suffix.lower()
        if suffix not in (".npz", ".usda", ".usdc", ".usd"):
            raise click.BadParameter(f"{output}: use a .npz, .usda, .usdc or .usd file",
                                     param_hint="-o")
        if len(inputs) > 1 and "{name}" not in output:
            raise click.UsageError("with several inputs, -o must contain {name} "
                                   "(e.g. -o spheres_{name}.npz)")
        if fracture is not None and suffix == ".npz":
            raise click.BadParameter(f"{output}: pieces are written as USD (.usda, .usdc, .usd)",
                                     param_hint="-o")
        if modes == "both" and "{mode}" not in output:
            raise click.UsageError("with --mode both, -o must contain {mode} "
                                   "(e.g. -o {name}_{mode}.npz)")

    from dempipe.spheres.cache import SphereCache
    from dempipe.spheres.options import BuildOptions
    from dempipe.spheres.sphere_set import (
        build_sphere_set_with_info, diameter_for_resolution, mesh_for_errors, surface_mask)
    from dempipe.usd.sphere_set import save_sphere_set
    from dempipe.spheres.surface import envelope_errors
    from dempipe.spheres.fidelity import off_axis_share

    cache = None
    if not no_cache:
        # A folder the user named must work (CacheError); the default one may be
        # unwritable, in which case the cache warns once and is skipped.
        cache = SphereCache(cache_dir, strict=cache_dir is not None)
    mode_list = ["lattice", "surface"] if modes == "both" else [modes or DEFAULT_MODE]

    results = []
    for arg in inputs:
        name, mesh = _resolve_input(arg, scale)
        d = diameter if diameter is not None else diameter_for_resolution(mesh, resolution)
        from dempipe.check.sizes import check_lattice

        check_lattice(mesh, d, "--diameter" if diameter is not None else "--resolution",
                      "Fix: " + ("raise --diameter" if diameter is not None
                                 else "lower --resolution"), f"shape {name}")
        if fracture is not None:
            results.append(_fracture_rows(name, arg, mesh, d, fracture, seed, cache, output,
                                          as_json))
            continue
        for mode in mode_list:
            sphere_set, info = build_sphere_set_with_info(mesh, d, name=name, cache=cache,
                                                          options=BuildOptions(
                                                              mode=mode, spacing=spacing))
            row = {
                "name": name,
                "input": arg,
                "mode": mode,
                "spacing": spacing if mode == "surface" else None,
                "count": sphere_set.count,
                "surface_count": int(surface_mask(sphere_set.centers, sphere_set.diameter, 1).sum()),
                "diameter": sphere_set.diameter,
                "volume": sphere_set.volume,
                # an open mesh encloses no volume: its mass properties are the spheres',
                # so there is nothing to compare them with (None, "n/a"); a surface set
                # is a shell of overlapping spheres, whose cells say nothing of the
                # body's mass (taken from the mesh)
                "volume_error_percent": (None if "not_watertight" in sphere_set.notes
                                         or mode == "surface"
                                         else 100.0 * sphere_set.sphere_volume_error),
                "inertia_error_percent": (None if "not_watertight" in sphere_set.notes
                                          or mode == "surface"
                                          else 100.0 * sphere_set.inertia_error),
                # the area off the lattice's axes (check's round-lattice warning)
                "off_axis_share": off_axis_share(mesh.vertices, mesh.faces),
                "hausdorff": None,
                "bump": None,
                # the spheres that meet walls through an inscribed ball or ring of the
                # mesh (spheres.inscribed: how round bodies roll), as a bake builds them
                # and of those, the ones holding a rim (a sharp circular edge's ring)
                **_inscribed_count(sphere_set, mesh, mode),
                "build_seconds": info.seconds,
                "cache": info.cache,
                "mesh_sha256": sphere_set.mesh_sha256,
                "output": None,
            }
            if errors:
                e = envelope_errors(mesh_for_errors(mesh), sphere_set.centers + sphere_set.com,
                                    sphere_set.diameter)
                row["hausdorff"], row["bump"] = e.hausdorff, e.bump
            if output is not None:
                out = _output_path(output, name).replace("{mode}", mode)
                _make_parent(out)       # as bake does for its output
                save_sphere_set(out, sphere_set, mesh=mesh, name=name)
                row["output"] = out
            results.append(row)
            if not as_json:
                click.echo(_line(row))
    if as_json:
        click.echo(json.dumps(results, indent=2))


def _fracture_rows(name, arg, mesh, d, n, seed, cache, output, as_json) -> dict:
    """Cut one input into ``n`` pieces; print (unless JSON) and return its rows."""
    from dempipe.mesh.fracture import FractureSpec
    from dempipe.spheres.pieces import build_pieces
    from dempipe.usd.sphere_set import save_fractured

    fractured, info = build_pieces(mesh, d, FractureSpec(pieces=n, seed=seed), name=name,
                                   cache=cache)
    rows = []
    for k, (piece, ss) in enumerate(zip(fractured.pieces, fractured.sphere_sets)):
        rows.append({"piece": k, "volume": ss.volume, "count": ss.count,
                     "watertight": bool(piece.trimesh().is_watertight),
                     "inside_faces": int(piece.inside.sum())})
    out = None
    if output is not None:
        out = _output_path(output, name)
        _make_parent(out)
        save_fractured(out, fractured, name=name)
    result = {"name": name, "input": arg, "diameter": d, "pieces": rows,
              "volume": float(sum(r["volume"] for r in rows)),
              "count": int(sum(r["count"] for r in rows)), "build_seconds": info.seconds,
              "cache": info.cache, "output": out}
    if not as_json:
        click.echo(f"{name}: {len(rows)} pieces of {result['count']} spheres of d={d:.6g} m, "
                   f"volume {result['volume']:.6g} m^3, {info.seconds:.2f} s, cache {info.cache}"
                   + (f" -> {out}" if out else ""))
        for r in rows:
            click.echo(f"  piece {r['piece']:02d}: volume {r['volume']:.6g} m^3, "
                       f"{r['count']} spheres, watertight {'yes' if r['watertight'] else 'NO'}")
    return result


def _inscribed_count(sphere_set, mesh, mode) -> dict:
    import numpy as np

    from dempipe.spheres.inscribed import inscribed_tori, lattice_tori

    tori = inscribed_tori if mode == "surface" else lattice_tori
    rows = tori(sphere_set.centers, sphere_set.diameter, mesh.vertices - sphere_set.com,
                mesh.faces)
    grown = np.any(rows[:, 0:3] != 0.0, axis=1)
    # a rim's ring has a tube of 0 (spheres/inscribed.py rims)
    return {"inscribed": int(np.count_nonzero(grown)),
            "rims": int(np.count_nonzero(grown & (rows[:, 9] > 0.0) & (rows[:, 10] == 0.0)))}


def _line(row) -> str:
    d = row["diameter"]
    line = f"{row['name']}: {row['count']} spheres ({row['mode']}) of d={d:.6g} m, "
    if row["mode"] == "lattice":
        line = line[:-2] + f" ({row['surface_count']} on the surface), "
    if row["hausdorff"] is not None:
        line += (f"Hausdorff {row['hausdorff']:.3g} m ({row['hausdorff'] / d:.2f} d), "
                 f"bump {row['bump']:.3g} m ({row['bump'] / d:.3f} d), ")
    if row["inscribed"] is not None:
        line += f"{row['inscribed']} meet walls through inscribed balls or rings"
        line += f" ({row['rims']} on rims), " if row["rims"] else ", "
    if row["volume_error_percent"] is None and row["mode"] == "surface":
        line += "mass and inertia from the mesh (the spheres are its contact shell), "
    elif row["volume_error_percent"] is None:
        line += "volume and inertia errors n/a (an open mesh: mass from the spheres), "
    else:
        line += (f"volume error {row['volume_error_percent']:+.2f}%, "
                 f"inertia error {row['inertia_error_percent']:.2f}%, ")
    from dempipe.spheres.fidelity import ROUND_SHARE

    if row["mode"] == "lattice" and row["off_axis_share"] > ROUND_SHARE:
        line += f"{row['off_axis_share']:.0%} of the surface off the lattice's axes (round: "
        if row["inscribed"]:
            # as `dempipe check`'s round-lattice, which names only shapes without tori
            line += ("it rolls on walls through its mesh's balls and rings, and is "
                     "terraced against other bodies; --mode surface rolls on them), ")
        else:
            line += ("terraced, it rolls badly; a finer resolution or --mode surface "
                     "rolls), ")
    line += f"{row['build_seconds']:.2f} s, cache {row['cache']}"
    if row["output"]:
        line += f" -> {row['output']}"
    return line
