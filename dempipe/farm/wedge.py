"""Wedges: variants of one scene's bake, each a task on a Dask cluster.

    result = wedge("shot.toml", "wedge/", seeds=4,
                   vary=["materials.wood.restitution=0.2,0.5"], workers=2)

What `dempipe wedge` runs. A wedge is the grid of ``--seeds`` (the scene's
``simulation.seed`` and the ones after it) and every ``--vary KEY=V1,V2,...`` (any
scene key by its dotted path; ``bodies[0].count`` picks an array entry). Each
variant is written as its own scene file, ``DIR/v000.toml`` (relative mesh paths
made absolute, so ``dempipe bake DIR/v000.toml -o x.usdc`` bakes it again), and
baked by one task into ``DIR/v000.usdc``. ``DIR/wedge.csv`` has a row per
variant: its values, status (``ok``, ``failed: <reason>``, or ``pending`` until it
finishes), output, wall time, the worker that baked it and how many times it was
started (a worker that dies mid-bake has its task started again by the scheduler).
It is rewritten atomically as each variant finishes.

A variant that fails (a bad value, an unstable setting) fails its row only; the
others bake. Run again, a wedge skips every variant whose row says ok, whose
output exists and whose scene file is unchanged. A variant an earlier run left
part-way (a worker killed, a stop signal: its checkpoint folder ``.v000.usdc.bake``
is there) resumes from its last checkpoint through ``bake(..., resume=True)``.

Dask is optional (``pip install "dempipe[farm]"``): see dempipe/farm/cluster.py for the
cluster and how its workers' threads are sized, docs/farm.md for farms.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from dempipe.errors import DempipeError, SceneError
from dempipe.farm import cluster as farming
from dempipe.farm.cluster import failure_reason, host_warnings
from dempipe.pipeline.bake import bake
from dempipe.pipeline.checkpoint import CheckpointError, atomic_write
from dempipe.pipeline.lock import work_dir
from dempipe.preview import contact_sheet as sheet
from dempipe.scene.keys import suggestion
from dempipe.scene.load import load_scene
from dempipe.spheres.cache import SphereCache

#: The wedge's table, in DIR.
CSV_NAME = "wedge.csv"
#: Columns after the variant's name and values.
CSV_TAIL = ("status", "output", "scene", "wall_s", "worker", "threads", "tries", "frames",
            "steps")
SEED_KEY = "simulation.seed"


class WedgeError(DempipeError):
    """A wedge's options are unusable, or some of its variants failed."""


class WedgeFailed(WedgeError):
    """Some variants failed; the others were written (exit status 1)."""

    exit_code = 1


# --------------------------------------------------------------------------- keys and values

_PART = re.compile(r"^([A-Za-z0-9_-]+)((?:\[\d+\])*)$")


def parse_key(key: str) -> tuple:
    """'materials.wood.restitution' -> ('materials', 'wood', 'restitution');
    'bodies[0].count' (or 'bodies.0.count') -> ('bodies', 0, 'count')."""
    parts = []
    for token in key.strip().split("."):
        if token.isdigit() and parts:
            parts.append(int(token))
            continue
        m = _PART.match(token)
        if not m:
            raise WedgeError(f"--vary {key}: {token!r} is not a key (write the scene key's "
                             f"dotted path, e.g. materials.wood.restitution or bodies[0].count)")
        parts.append(m.group(1))
        parts += [int(i) for i in re.findall(r"\[(\d+)\]", m.group(2))]
    return tuple(parts)


def format_key(path: tuple) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else p)
    return out


def _split_values(text: str) -> list[str]:
    """Split on the commas outside brackets and quotes: '[1,2],[3,4]' -> two values."""
    out, depth, quote, cur = [], 0, None, ""
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(cur)
            cur = ""
            continue
        cur += ch
    out.append(cur)
    return [v.strip() for v in out]


def toml_loads(text: str) -> dict:
    """A TOML document's tables (tomllib, or tomli on Python 3.10)."""
    try:
        import tomllib
    except ModuleNotFoundError:          # Python 3.10
        import tomli as tomllib
    return tomllib.loads(text)


def _toml_error():
    try:
        import tomllib
    except ModuleNotFoundError:
        import tomli as tomllib
    return tomllib.TOMLDecodeError


def parse_value(text: str):
    """A TOML value ('0.5', '8', 'true', '[0, 0, 1]', '"cpu"'); a bare word is a string."""
    try:
        return toml_loads(f"v = {text}")["v"]
    except _toml_error():
        return text


def parse_vary(spec: str) -> tuple[tuple, list]:
    """'KEY=V1,V2,...' -> (key path, [values]); a WedgeError naming the option otherwise."""
    if "=" not in spec:
        raise WedgeError(f"--vary {spec}: expected KEY=V1,V2,... "
                         f"(e.g. materials.wood.restitution=0.2,0.5)")
    key, _, values = spec.partition("=")
    path = parse_key(key)
    texts = _split_values(values)
    if not values.strip() or any(not t for t in texts):
        raise WedgeError(f"--vary {spec}: expected comma-separated values after '=' "
                         f"(e.g. {key.strip()}=0.2,0.5)")
    vals = [parse_value(t) for t in texts]
    if len({json.dumps(v, sort_keys=True, default=str) for v in vals}) < len(vals):
        raise WedgeError(f"--vary {spec}: a value is given twice")
    return path, vals


def set_key(data: dict, path: tuple, value) -> None:
    """Set ``path`` in the TOML data, creating a missing top-level table (``simulation``,
    ``output``); WedgeError for a path that runs through a value, past the end of an
    array, or through a table the scene does not have below the top level (a misspelt
    material or shape would otherwise become a new, unused one)."""
    node = data
    for i, p in enumerate(path):
        last = i == len(path) - 1
        where = format_key(path[:i + 1])
        if isinstance(p, int):
            if not isinstance(node, list):
                raise WedgeError(f"--vary {format_key(path)}: {format_key(path[:i])} is not "
                                 f"an array of tables")
            if p >= len(node):
                raise WedgeError(f"--vary {format_key(path)}: the scene has {len(node)} "
                                 f"{format_key(path[:i])} entries (indices from 0)")
        elif not isinstance(node, dict):
            raise WedgeError(f"--vary {format_key(path)}: {format_key(path[:i])} is a value, "
                             f"not a table")
        if last:
            node[p] = value
        else:
            if isinstance(p, str) and p not in node:
                if i > 0:
                    names = [k for k, v in node.items() if isinstance(v, (dict, list))]
                    raise WedgeError(f"--vary {format_key(path)}: the scene has no {where} "
                                     f"({suggestion(p, names)})")
                node[p] = [] if isinstance(path[i + 1], int) else {}
            node = node[p]
            if isinstance(path[i + 1], str) and isinstance(node, list):
                raise WedgeError(f"--vary {format_key(path)}: {where} is an array; pick an "
                                 f"entry, e.g. {where}[0].{path[i + 1]}")


# --------------------------------------------------------------------------- TOML out

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _tkey(k: str) -> str:
    return k if _BARE.match(k) else json.dumps(k, ensure_ascii=False)


def _tvalue(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list):
        return "[" + ", ".join(_tvalue(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_tkey(k)} = {_tvalue(x)}" for k, x in v.items()) + "}"
    if hasattr(v, "isoformat"):
        return v.isoformat()
    raise WedgeError(f"cannot write {v!r} in TOML")


def _is_table_array(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def dumps_toml(data: dict) -> str:
    """TOML text of ``data`` (what tomllib reads back as the same dict)."""
    lines: list[str] = []

    def table(d: dict, path: tuple, header: str | None) -> None:
        plain = [(k, v) for k, v in d.items()
                 if not isinstance(v, dict) and not _is_table_array(v)]
        if header is not None and (plain or header.startswith("[[") or not d):
            if lines:
                lines.append("")
            lines.append(header)
        for k, v in plain:
            lines.append(f"{_tkey(k)} = {_tvalue(v)}")
        for k, v in d.items():
            sub = path + (k,)
            name = ".".join(_tkey(p) for p in sub)
            if isinstance(v, dict):
                table(v, sub, f"[{name}]")
            elif _is_table_array(v):
                for item in v:
                    table(item, sub, f"[[{name}]]")

    table(data, (), None)
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- the plan


@dataclass
class Variant:
    """One bake of the wedge: its name, the values it sets, its scene text and files."""

    name: str
    values: dict                   # dotted key -> value, in the wedge's key order
    text: str                      # the variant's scene TOML
    scene: Path                    # DIR/<name>.toml
    output: Path                   # DIR/<name>.usdc


@dataclass
class VariantResult:
    """A variant's row of wedge.csv."""

    name: str
    values: dict
    status: str = "pending"
    output: str = ""
    scene: str = ""
    wall_s: float = math.nan
    worker: str = ""
    threads: int | None = None
    tries: int = 0
    frames: int | None = None
    steps: int | None = None
    skipped: bool = False          # done by an earlier run

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def failed(self) -> bool:
        return self.status.startswith("failed")


@dataclass
class WedgeResult:
    """What a wedge did: a result per variant (plan order), the CSV, the dashboard."""

    variants: list
    csv: Path
    keys: list
    wall_s: float = 0.0
    dashboard: str | None = None
    scheduler: str | None = None

    @property
    def ok(self) -> list:
        return [v for v in self.variants if v.ok]

    @property
    def failed(self) -> list:
        return [v for v in self.variants if v.failed]

    @property
    def skipped(self) -> list:
        return [v for v in self.variants if v.skipped]


def contact_sheet(result: WedgeResult, out_png=None, **kw) -> Path:
    """A PNG grid of every finished variant's last frame, labelled with its name and
    values (``dempipe.preview.contact_sheet``; needs ``dempipe[preview]``).

    out_png : default ``wedge.csv``'s folder / contact_sheet.png.
    """
    done = [v for v in result.variants if v.ok and v.output]
    if not done:
        raise WedgeError("contact sheet: no variant finished")
    out = Path(out_png) if out_png is not None else result.csv.parent / "contact_sheet.png"
    labels = [" ".join([v.name] + [f"{k.rsplit('.', 1)[-1]}={val}" for k, val in v.values.items()])
              for v in done]
    return sheet([v.output for v in done], out, labels=labels, **kw)


def absolute_meshes(data: dict, base: Path) -> None:
    """Relative mesh paths in a scene's tables ``data`` made absolute against ``base``, in
    place (a variant's file lives elsewhere)."""
    def fix(d):
        if isinstance(d, dict) and isinstance(d.get("mesh"), str):
            p = Path(d["mesh"]).expanduser()
            if not p.is_absolute():
                d["mesh"] = str((base / p).resolve())

    for spec in (data.get("shapes") or {}).values():
        fix(spec)
    for c in data.get("colliders") or []:
        fix(c)


def plan(scene_path, out_dir, *, seeds: int | None = None, vary=(),
         suffix: str = ".usdc") -> tuple[list, list]:
    """The wedge's variants, in grid order: (keys, [Variant]).

    seeds : N variants of ``simulation.seed``: the scene's seed and the N-1 after it
    vary : 'KEY=V1,V2,...' strings (or (key path, values) pairs); several make a grid,
        the first varying slowest (seeds come first)
    """
    scene_path = Path(scene_path)
    load_scene(scene_path)                   # the base scene must be sound: one line if not
    data = toml_loads(scene_path.read_text(encoding="utf-8"))
    if suffix not in (".usd", ".usdc", ".usda"):
        raise WedgeError(f"--format: unknown {suffix!r} (use usdc, usda or usd)")
    axes = []
    if seeds is not None:
        if int(seeds) < 1:
            raise WedgeError(f"--seeds: {seeds} must be at least 1")
        base = data.get("simulation", {}).get("seed", 0)
        if isinstance(base, bool) or not isinstance(base, int):
            base = 0
        axes.append(((("simulation", "seed")), [base + i for i in range(int(seeds))]))
    for spec in vary:
        axes.append(parse_vary(spec) if isinstance(spec, str) else (tuple(spec[0]), spec[1]))
    if not axes:
        raise WedgeError("nothing to wedge: give --seeds N and/or --vary KEY=V1,V2,...")
    keys = [format_key(p) for p, _ in axes]
    dup = {k for k in keys if keys.count(k) > 1}
    if dup:
        k = sorted(dup)[0]
        what = "--seeds and --vary simulation.seed" if k == SEED_KEY and seeds else f"--vary {k}"
        raise WedgeError(f"{what}: the key is wedged twice; give its values once")
    out = Path(out_dir)
    combos = list(itertools.product(*[vals for _, vals in axes]))
    width = max(3, len(str(len(combos) - 1)))
    variants = []
    for i, combo in enumerate(combos):
        name = f"v{i:0{width}d}"
        d = toml_loads(scene_path.read_text(encoding="utf-8"))
        for (path, _), value in zip(axes, combo):
            set_key(d, path, value)
        absolute_meshes(d, scene_path.resolve().parent)
        values = dict(zip(keys, combo))
        head = [f"# dempipe wedge: variant {name} of {scene_path.resolve()}"]
        head += [f"#   {k} = {_tvalue(v)}" for k, v in values.items()]
        head += [f"# bake it again: dempipe bake {name}.toml -o {name}{suffix}", ""]
        variants.append(Variant(name, values, "\n".join(head) + dumps_toml(d),
                                out / f"{name}.toml", out / f"{name}{suffix}"))
    return keys, variants


# --------------------------------------------------------------------------- the table


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    if isinstance(v, (list, dict, bool)):
        return _tvalue(v)
    return str(v)


def _value_cell(v) -> str:
    return "" if v is None else v if isinstance(v, str) else _tvalue(v)


def format_csv(keys, rows) -> str:
    """wedge.csv's text: variant, the wedged keys, then CSV_TAIL."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["variant", *keys, *CSV_TAIL])
    for r in rows:
        # the wedged values exactly as the scene files hold them; figures to 6 digits
        w.writerow([r.name, *(_value_cell(r.values.get(k)) for k in keys),
                    *(_cell(getattr(r, c)) for c in CSV_TAIL)])
    return buf.getvalue()


def read_csv(path) -> dict:
    """variant name -> row dict of an existing wedge.csv ({} when there is none)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (FileNotFoundError, NotADirectoryError):
        return {}
    except (OSError, UnicodeDecodeError) as exc:
        raise WedgeError(f"{path}: cannot read the wedge table ({exc})") from None
    return {row["variant"]: row for row in csv.DictReader(io.StringIO(text))
            if row.get("variant")}


def _write_text(path: Path, text: str) -> None:
    """``text`` into ``path`` whole or not at all (checkpoint.atomic_write: fsync, the
    temporary file removed on an interrupt); a WedgeError naming the path."""
    try:
        atomic_write(path, lambda fh: fh.write(text.encode("utf-8")))
    except OSError as exc:
        raise WedgeError(f"{path}: cannot write ({exc.strerror or exc})") from None


def _tries_file(v: Variant) -> Path:
    return v.scene.with_name(f".{v.name}.tries")


# --------------------------------------------------------------------------- the task


def _bake_variant(scene: str, output: str, tries: str, *, device=None, layout="instancer",
                  force=False, cache_dir=None) -> dict:
    """The task: bake one variant's scene file on this worker; a dict, never an exception
    for the variant's own faults (a worker that dies is the scheduler's to retry)."""
    import socket

    try:
        from distributed import get_worker

        worker = get_worker().address
    except (ImportError, ValueError):
        worker = f"local:{socket.gethostname()}:{os.getpid()}"
    with open(tries, "a", encoding="utf-8") as fh:           # one line per start
        fh.write(worker + "\n")
    t0 = time.perf_counter()
    warnings: list[str] = []
    out = dict(worker=worker, threads=None, frames=None, steps=None, warnings=warnings)
    try:
        import numba


        # The pool this worker process was given (NUMBA_NUM_THREADS when it started).
        threads = int(numba.config.NUMBA_NUM_THREADS)
        out["threads"] = threads
        kwargs = dict(device=device, layout=layout, threads=threads, force=force,
                      cache=SphereCache(cache_dir) if cache_dir else None,
                      warn=warnings.append, progress=None)
        if not Path(scene).is_file():
            raise WedgeError(f"{scene}: not found on worker {worker}; the wedge's folder "
                             f"must be on a filesystem every worker sees (docs/farm.md)")

        if work_dir(output).exists():
            # carry on from the checkpoint a stopped or killed bake left (an earlier run,
            # or this task's try on a worker that died); one of another scene text (the
            # wedge's base scene changed) is stale: bake from frame 0
            try:
                result = bake(scene, output, resume=True, **kwargs)
            except CheckpointError:
                shutil.rmtree(work_dir(output), ignore_errors=True)
                result = bake(scene, output, **kwargs)
        else:
            result = bake(scene, output, **kwargs)
        out.update(status="ok", frames=result.report.get("frames"),
                   steps=result.report.get("steps"))
        partial = Path(output)
        partial.with_name(f"{partial.stem}.partial{partial.suffix}").unlink(missing_ok=True)
    except DempipeError as exc:
        out["status"] = "failed: " + " ".join(str(exc).split())
    except Exception as exc:                # a bug: still this row only
        out["status"] = f"failed: internal error: {type(exc).__name__}: " + \
            " ".join(str(exc).split())
    out["wall_s"] = time.perf_counter() - t0
    return out


# --------------------------------------------------------------------------- the wedge


def wedge(scene_path, out_dir, *, seeds: int | None = None, vary=(),
          workers: int | None = None, scheduler: str | None = None,
          threads: int | None = None, farm=None, device: str | None = None,
          layout: str = "instancer", suffix: str = ".usdc", force: bool = False,
          cache_dir=None, progress=None, warn=None, after=None) -> WedgeResult:
    """Bake every variant of the wedge as a Dask task; write DIR's files; a WedgeResult.

    workers, threads : a LocalCluster of ``workers`` processes with ``threads`` numba
        threads each (the default: see dempipe.farm.cluster.local_sizes)
    scheduler : the address of a running Dask scheduler (its workers bake)
    farm : an open dempipe.farm.cluster.Farm to use instead (left open)
    device, layout, force, cache_dir : passed to each bake (see dempipe.pipeline.bake.bake)
    progress : callable(str), a line per finished variant and the total
    warn : callable(str) for warnings (workers that would fight over cores, ...)
    after : callable(WedgeResult), called once every variant has finished (the hook
        for a contact sheet of the wedge's outputs)

    A failed variant is a row, not an exception: check ``result.failed``. Raises
    WedgeError / SceneError / FarmError for unusable options, a base scene that does
    not load or a cluster that cannot be reached.
    """
    say = progress or (lambda line: None)
    warn = warn or (lambda line: None)
    t0 = time.perf_counter()
    keys, variants = plan(scene_path, out_dir, seeds=seeds, vary=vary, suffix=suffix)
    if farm is None:
        farming.require_dask("dempipe wedge")
    out = Path(out_dir).resolve()
    if out.exists() and not out.is_dir():
        raise WedgeError(f"{out_dir}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise WedgeError(f"{out_dir}: cannot create the folder ({exc.strerror})") from None
    for v in variants:
        v.scene, v.output = out / v.scene.name, out / v.output.name
    csv_path = out / CSV_NAME
    earlier = read_csv(csv_path)
    rows, todo = {}, []
    for v in variants:
        row = VariantResult(v.name, v.values, output=str(v.output), scene=str(v.scene))
        rows[v.name] = row
        old = earlier.get(v.name, {})
        same = v.scene.is_file() and v.scene.read_text(encoding="utf-8") == v.text
        if same and old.get("status") == "ok" and v.output.is_file():
            row.status, row.skipped, row.worker = "ok", True, old.get("worker", "")
            for name, kind in (("wall_s", float), ("threads", int), ("tries", int),
                               ("frames", int), ("steps", int)):
                try:
                    setattr(row, name, kind(old[name]))
                except (KeyError, TypeError, ValueError):
                    pass
            continue
        if not same:
            _write_text(v.scene, v.text)
        _tries_file(v).unlink(missing_ok=True)
        todo.append(v)
    table = [rows[v.name] for v in variants]
    _write_text(csv_path, format_csv(keys, table))
    result = WedgeResult(table, csv_path, keys)
    if len(todo) < len(variants):
        say(f"{len(variants) - len(todo)} of {len(variants)} variants done by an earlier run: "
            f"skipped")

    # Variants invalid on their own (a value out of range, an unknown key) fail here,
    # before a worker is asked; the rest go to the cluster.

    valid = []
    for v in todo:
        try:
            load_scene(v.scene)
            valid.append(v)
        except SceneError as exc:
            _finish(rows[v.name], dict(status="failed: " + " ".join(str(exc).split())),
                    v, result, say, csv_path, keys)

    for v in valid:
        if work_dir(v.output).exists():
            say(f"{v.name}: an earlier bake stopped part-way; resuming it from its checkpoint")
    if valid:
        if farm is not None:
            _run(farm, valid, rows, result, say, warn, csv_path, keys, device, layout, force,
                 cache_dir)
        else:
            with farming.connect(workers=workers, scheduler=scheduler, threads=threads,
                                 tasks=len(valid)) as f:
                _run(f, valid, rows, result, say, warn, csv_path, keys, device, layout, force,
                     cache_dir)
    result.wall_s = time.perf_counter() - t0
    n_ok, n_failed = len(result.ok), len(result.failed)
    say(f"wedge: {n_ok} of {len(variants)} ok, {n_failed} failed"
        + (f", {len(result.skipped)} done earlier" if result.skipped else "")
        + f" in {result.wall_s:.1f} s; table {csv_path}")
    if after is not None:
        after(result)
    return result


def _run(farm, valid, rows, result, say, warn, csv_path, keys, device, layout, force,
         cache_dir) -> None:
    result.dashboard, result.scheduler = farm.dashboard, farm.scheduler
    if farm.dashboard:
        say(f"Dask dashboard: {farm.dashboard}")

    try:
        for line in host_warnings(farm.survey()):
            warn(line)
    except Exception as exc:          # a survey is advice: never stop the wedge for it
        warn(f"could not ask the workers what they were given ({type(exc).__name__})")
    futures = {}
    for v in valid:
        fut = farm.submit(_bake_variant, str(v.scene), str(v.output), str(_tries_file(v)),
                          device=device, layout=layout, force=force,
                          cache_dir=str(cache_dir) if cache_dir else None, key=f"dempipe-wedge-{v.name}-{os.getpid()}"
                                                       f"-{time.time_ns()}")
        futures[fut] = v
    warned = set()
    for fut, value, error in farm.finished(list(futures)):
        v = futures[fut]
        if error is not None:
            value = dict(status="failed: " + failure_reason(error))
        for msg in value.get("warnings") or ():
            if msg not in warned:          # a warning every variant shares: once
                warned.add(msg)
                warn(f"{v.name}: {msg}")
        _finish(rows[v.name], value, v, result, say, csv_path, keys)


def _finish(row: VariantResult, value: dict, v: Variant, result: WedgeResult, say, csv_path,
            keys) -> None:
    """Record a finished variant: its row, the table on disk, its progress line."""
    for name in ("status", "wall_s", "worker", "threads", "frames", "steps"):
        if value.get(name) is not None:
            setattr(row, name, value[name])
    try:
        row.tries = len(_tries_file(v).read_text(encoding="utf-8").split())
    except OSError:
        row.tries = 0
    if not row.ok:       # what a failed bake kept, if anything
        partial = v.output.with_name(f"{v.output.stem}.partial{v.output.suffix}")
        row.output = str(partial) if partial.exists() else ""
    _write_text(csv_path, format_csv(keys, result.variants))
    done = sum(1 for r in result.variants if r.status != "pending")
    values = " ".join(f"{k.rsplit('.', 1)[-1]}={_value_cell(row.values[k])}" for k in keys)
    tail = (f"ok in {row.wall_s:.1f} s on {row.worker}" if row.ok else row.status)
    again = f" (started {row.tries} times: a worker died)" if row.tries > 1 else ""
    say(f"[{done}/{len(result.variants)}] {row.name} {values}: {tail}{again}")
