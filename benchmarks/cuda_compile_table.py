"""Compile every CUDA kernel a scene can launch for a real GPU, without a GPU.

    python benchmarks/cuda_compile_table.py            # print the table
    python benchmarks/cuda_compile_table.py --write    # and put it into docs/cuda.md

Two steps, each in its own process (numba reads ``NUMBA_ENABLE_CUDASIM`` once, at
its first import of ``numba.cuda``):

1. **Record** (CUDA simulator): small scenes covering every feature switch
   (friction, walls, sleeping, one-sphere bodies, static mesh colliders, glue) are
   stepped, probed and grown by ``CudaBackend`` running its general kernels;
   every kernel launch is recorded with the numba types of its arguments. So
   the signatures are the ones the backend really launches, never a
   hand-written copy.
2. **Compile** (numba-cuda, no simulator): each recorded (kernel, signature) is
   compiled to PTX for compute capability ``--cc`` (9.0: H100/H200) by
   ``numba.cuda.compile_ptx`` with NVVM, then assembled by ``ptxas -arch=sm_XX
   -v``, whose report gives the registers, the stack frame (local memory) and
   the spill stores/loads of each kernel. The kernels specialized to the scene
   (``kernels.cuda.backend.SPECIALIZED``) are compiled for every one of the 16 feature
   sets a scene can need (``kernels.cuda.backend.kernels(flags)``), with the general
   kernel's signature (the same arrays). The jobs are shared among up to
   ``os.cpu_count()`` processes.

Needs: ``numba-cuda`` with NVVM and NVRTC (``pip install -e '.[test]'`` brings
``cuda-toolkit[nvvm,nvrtc]==13.0.*``) and ``ptxas`` (CUDA toolkit; on PATH or in
``/usr/local/cuda*/bin``), of the same CUDA release: NVVM 13.5 writes PTX 9.5,
which ptxas 13.0 refuses.

Results are cached in ``cuda_compile/`` of dempipe's cache folder
(``$DEMPIPE_CACHE_DIR``, else ``~/.cache/dempipe``), keyed by the source of the package and of this
script and by the tools' versions: a second run on unchanged code assembles
nothing. ``--no-cache`` compiles anyway. tests/sim/test_cuda_compile.py runs this.
"""

from __future__ import annotations

import argparse
import glob
import hashlib
import json
import os
import pickle
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DOC = ROOT / "docs" / "cuda.md"
BEGIN = "<!-- cuda_compile_table: begin -->"
END = "<!-- cuda_compile_table: end -->"


# ---------------------------------------------------------------------------
# Step 1: record the launches (runs under the CUDA simulator)
# ---------------------------------------------------------------------------

def _scenes():
    """(name, model, features) of the scenes the recording steps: between them,
    every feature switch on and off (``Features``: friction, walls, sleeping,
    rotation)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from dataclasses import replace

    import numpy as np
    from bodies import ball_set, box_set
    from dempipe.sim.materials import Material
    from dempipe.sim.builder import ModelBuilder

    d = 0.01

    def build(friction, walls, sleeping, shape="box"):
        b = ModelBuilder(d)
        ss, mesh = box_set(2, 1, 1, d) if shape == "box" else ball_set(d)
        s = b.add_shape("s", mesh, ss)
        m = b.add_material(Material("m", density=1000, restitution=0.5, friction=friction))
        pos = [[0, 0, 0.0049], [0.0205, 0, 0.0049], [0.01, 0.0, 0.0145]]
        b.add_bodies("g", s, m, pos, velocities=[[0.1, 0, -0.2]] * 3,
                     angular_velocities=[[0, 0, 1.0]] * 3)
        if walls:
            b.add_box([-0.02, -0.02, 0], [0.04, 0.02, 0.1], material=m)
        else:
            # no walls: a static collider of spheres (a pseudo-body) to land on
            sf, mf = box_set(6, 2, 1, d)
            sf.centers = sf.centers + np.array([0.01, 0.0, -0.0051])
            b.add_static_mesh("floor", mf, sf, m)
        model = b.finalize(fps=60, n_frames=1,
                           sleep=(1.0, 100.0, 1e-9) if sleeping else None)
        return replace(model, sleep_steps=2) if sleeping else model

    out = []
    for friction in (0.0, 0.4):
        for walls in (False, True):
            model = build(friction, walls, False)
            out.append((f"friction={friction > 0} walls={walls}", model, None))
    sleepy = build(0.4, True, True)
    out.append(("sleeping", sleepy, None))
    ball = build(0.4, True, False, shape="ball")
    out.append(("one-sphere bodies (no rotation)", ball, None))
    # prescribed motion: a belt, a moving box, a kinematic body, an emitter
    from dempipe.sim.motion import Motion

    b = ModelBuilder(d)
    ss, mesh = box_set(2, 1, 1, d)
    s = b.add_shape("s", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.4))
    b.add_bodies("g", s, m, [[0, 0, 0.0049], [0.0205, 0, 0.0049]])
    b.add_bodies("k", s, m, [[-0.02, 0, 0.006]], kinematic=True,
                 motion=Motion(velocity=(0.1, 0, 0), angular_velocity=(0, 0, 5.0)))
    b.add_bodies("e", s, m, [[0.04, 0, 0.006]], start_time=1e-9)
    b.add_plane([0, 0, 0], [0, 0, 1], m, motion=Motion(velocity=(0.05, 0, 0)))
    b.add_box([-0.05, -0.02, -0.01], [0.08, 0.02, 0.1], material=m,
              motion=Motion(velocity=(0.02, 0, 0)))
    moving = b.finalize(fps=60, n_frames=1, sleep=(1.0, 100.0, 1e-9))
    out.append(("prescribed motion", replace(moving, sleep_steps=2), None))
    # glue: three pieces of one lattice, glued where their spheres touch (the glue passes)
    b = ModelBuilder(d)
    ss, mesh = box_set(2, 1, 1, d)
    s = b.add_shape("s", mesh, ss)
    m = b.add_material(Material("m", density=1000, restitution=0.5, friction=0.4,
                                glue_strength=1e3))
    b.add_bodies("g", s, m, [[0, 0, 0.0051], [0.02, 0, 0.0051], [0.04, 0, 0.0051]],
                 angular_velocities=[[0, 0, 1.0]] * 3, glue=[0, 0, 0])
    b.add_plane([0, 0, 0], [0, 0, 1], m)
    glued = b.finalize(fps=60, n_frames=1, sleep=(1.0, 100.0, 1e-9))
    out.append(("glue", replace(glued, sleep_steps=2), None))
    return out


def _host(a):
    """The host array behind a simulator device array, recursively in tuples."""
    if hasattr(a, "_ary"):
        return a._ary
    if isinstance(a, tuple):
        vals = [_host(x) for x in a]
        return type(a)(*vals) if hasattr(a, "_fields") else tuple(vals)
    return a


def record(steps: int = 3) -> dict:
    """{kernel name: [argument types, ...]} of every launch of the scenes' steps,
    probes and overlap reads (call with the CUDA simulator on)."""
    import numba
    from dempipe.sim.kernels.cuda import backend as kc

    seen: dict[str, dict[str, tuple]] = {}

    class Recorder:
        def __init__(self, name, kernel):
            self.name, self.kernel = name, kernel

        def __getitem__(self, config):
            launch = self.kernel[config]

            def run(*args):
                types = tuple(numba.typeof(_host(a)) for a in args)
                seen.setdefault(self.name, {})[str(types)] = types
                return launch(*args)
            return run

    names = [n for n in dir(kc) if n.startswith("k_")]
    originals = {n: getattr(kc, n) for n in names}
    for n in names:
        setattr(kc, n, Recorder(n, originals[n]))
    try:
        for _, model, features in _scenes():
            # the general kernels (the module's, which this records); their
            # signatures are the variants' too (compile_jobs)
            backend = kc.CudaBackend(model, features=features, specialize=False)
            state = model.initial_state()
            backend.probe(state)
            backend.take_max_overlap()
            backend.step(state, steps)
            backend.velocities(state)
            backend.grow_neighbours(2 * int(backend.d["nbr"].shape[1]))
            backend.step(state, 1)
    finally:
        for n in names:
            setattr(kc, n, originals[n])
    return {name: list(sigs.values()) for name, sigs in sorted(seen.items())}


# ---------------------------------------------------------------------------
# Step 2: compile and assemble (runs with numba-cuda, no simulator, no GPU needed)
# ---------------------------------------------------------------------------

class _Device:
    """What numba-cuda asks the driver for while compiling (see _compiling_for)."""

    def __init__(self, cc):
        self.compute_capability = cc


class _compiling_for:
    """numba-cuda asks the driver for the current device's compute capability
    while it compiles a kernel's device functions, even under
    ``compile_ptx(cc=...)`` (``numba.cuda.dispatcher.get_current_device``), which
    fails on a machine without a GPU. This answers that one question with the
    capability being compiled for, for the duration of the compile; nothing else
    of the driver is touched (PTX is produced by NVVM, assembled by ptxas)."""

    def __init__(self, cc):
        self.cc = cc

    def __enter__(self):
        from numba.cuda import dispatcher
        self.module, self.saved = dispatcher, dispatcher.get_current_device
        dispatcher.get_current_device = lambda: _Device(self.cc)

    def __exit__(self, *exc):
        self.module.get_current_device = self.saved


def ptxas_path() -> str | None:
    """ptxas on PATH, else in the newest /usr/local/cuda*/bin."""
    found = shutil.which("ptxas")
    if found:
        return found
    for c in sorted(glob.glob("/usr/local/cuda*/bin/ptxas"), reverse=True):
        return c
    return None


_PROPS = re.compile(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads")
_REGS = re.compile(r"Used (\d+) registers")


def parse_ptxas(report: str) -> dict:
    """Registers, stack frame [bytes] (local memory) and spill stores/loads [bytes]
    of the single entry function in a ``ptxas -v`` report."""
    regs = _REGS.search(report)
    props = _PROPS.search(report)
    if regs is None or props is None:
        raise RuntimeError(f"unexpected ptxas report:\n{report}")
    stack, stores, loads = (int(x) for x in props.groups())
    return dict(registers=int(regs.group(1)), stack=stack, spill_stores=stores,
                spill_loads=loads)


def compile_kernel(pyfunc, types, cc, ptxas: str, workdir: str) -> dict:
    """PTX of ``pyfunc`` for ``types`` and compute capability ``cc``, assembled."""
    from numba import cuda
    t0 = time.perf_counter()
    with _compiling_for(cc):
        ptx, _ = cuda.compile_ptx(pyfunc, types, cc=cc)
    t1 = time.perf_counter()
    path = os.path.join(workdir, f"{pyfunc.__name__}.ptx")
    with open(path, "w") as f:
        f.write(ptx)
    arch = f"sm_{cc[0]}{cc[1]}"
    r = subprocess.run([ptxas, f"-arch={arch}", "-v", "-o", os.devnull, path],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"ptxas -arch={arch} failed on {pyfunc.__name__}:\n{r.stderr}")
    row = parse_ptxas(r.stderr + r.stdout)
    row.update(nvvm_s=round(t1 - t0, 2), ptx_lines=ptx.count("\n"))
    return row


def jobs(records: dict) -> list[tuple]:
    """(kernel, flags or None, signature index, contact law, glue) of every kernel
    variant to compile: each recorded kernel as launched, each SPECIALIZED one for
    every feature set, the contact pass (the one kernel a law changes) for every
    other law with every feature on (its most demanding variant: the others are
    subsets), and k_bodies with the bonds' sums (glue, every feature on; the glue
    passes themselves are recorded as launched, their general kernels)."""
    import itertools

    from dempipe.sim import laws
    from dempipe.sim.kernels.cuda import backend as kc
    out = []
    for name, sigs in records.items():
        for i in range(len(sigs)):
            if name in kc.SPECIALIZED:
                out += [(name, flags, i, laws.DEFAULT, False)
                        for flags in itertools.product((False, True), repeat=4)]
            else:
                out.append((name, None, i, laws.DEFAULT, False))
            if name == "k_pair_forces":
                out += [(name, (True,) * 4, i, law, False) for law in laws.LAWS
                        if law != laws.DEFAULT]
            if name == "k_bodies":
                out.append((name, (True,) * 4, i, laws.DEFAULT, True))
    return out


def compile_jobs(records: dict, todo: list, cc=(9, 0)) -> list[dict]:
    """One row per job (see ``jobs``): its ptxas resources."""
    from dempipe.sim.kernels.cuda import backend as kc
    ptxas = ptxas_path()
    if ptxas is None:
        raise RuntimeError("ptxas not found (install the CUDA toolkit, or put it on PATH)")
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for name, flags, i, law, glue in todo:
            kernel = getattr(kc, name) if flags is None else \
                getattr(kc.kernels(flags, law, glue), name)
            row = compile_kernel(kernel.py_func, tuple(records[name][i]), cc, ptxas, work)
            tag = kc.variant_tag(flags) if flags else ""
            row.update(kernel=name, variant=tag + ("" if law == "linear" else f"_{law}")
                       + ("_glue" if glue else ""),
                       signature=", ".join(str(t) for t in records[name][i]))
            rows.append(row)
    return rows


# ---------------------------------------------------------------------------
# Driver: the two processes, the cache, the table
# ---------------------------------------------------------------------------

def _versions(ptxas: str | None) -> str:
    from importlib import metadata
    parts = []
    for pkg in ("numba", "numba-cuda", "nvidia-nvvm", "cuda-toolkit"):
        try:
            parts.append(f"{pkg}={metadata.version(pkg)}")
        except metadata.PackageNotFoundError:
            parts.append(f"{pkg}=none")
    if ptxas:
        r = subprocess.run([ptxas, "--version"], capture_output=True, text=True)
        parts.append(r.stdout.strip().splitlines()[-1] if r.stdout.strip() else "ptxas=?")
    return "; ".join(parts)


def _cache_key(cc, ptxas) -> str:
    h = hashlib.sha256()
    for p in sorted((ROOT / "dempipe").rglob("*.py")) + [Path(__file__).resolve(),
                                                         ROOT / "tests" / "bodies.py"]:
        h.update(str(p.relative_to(ROOT)).encode())
        h.update(p.read_bytes())
    h.update(repr(cc).encode())
    h.update(_versions(ptxas).encode())
    return h.hexdigest()[:24]


def _cache_dir() -> Path:
    from dempipe.spheres.cache import default_cache_dir
    return default_cache_dir() / "cuda_compile"


def _child(mode: str, arg: str, cc, wait: bool = True):
    """Run this script's ``mode`` step in a fresh process (started; waited for and
    checked unless ``wait`` is False: then the Popen, see _check)."""
    env = dict(os.environ)
    env.pop("NUMBA_ENABLE_CUDASIM", None)
    if mode == "record":
        env["NUMBA_ENABLE_CUDASIM"] = "1"
        env.setdefault("NUMBA_NUM_THREADS", "1")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    cmd = [sys.executable, str(Path(__file__).resolve()), f"--{mode}", arg,
           "--cc", f"{cc[0]}.{cc[1]}"]
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return _check(mode, p) if wait else p


def _check(mode, p) -> None:
    out, err = p.communicate()
    if p.returncode != 0:
        raise RuntimeError(f"{mode} step failed:\n{out[-3000:]}\n{err[-6000:]}")


def run(cc=(9, 0), use_cache: bool = True) -> dict:
    """The compile table for ``cc``: {"rows": [...], "versions", "cc", "seconds",
    "cached"}. Raises RuntimeError when a step fails (a kernel that does not
    compile or assemble)."""
    ptxas = ptxas_path()
    key = _cache_key(cc, ptxas)
    cached = _cache_dir() / f"{key}.json"
    if use_cache and cached.is_file():
        result = json.loads(cached.read_text())
        result["cached"] = True
        return result
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        rec, out = os.path.join(work, "records.pkl"), os.path.join(work, "rows.json")
        _child("record", rec, cc)
        t1 = time.perf_counter()
        n = max(1, min(os.cpu_count() or 1, 8))
        procs = [_child("compile", os.pathsep.join([rec, f"{out}.{i}", str(i), str(n)]), cc,
                        wait=False) for i in range(n)]
        for p in procs:
            _check("compile", p)
        rows = [r for i in range(n) for r in json.loads(Path(f"{out}.{i}").read_text())]
    t2 = time.perf_counter()
    result = dict(rows=rows, versions=_versions(ptxas), cc=list(cc),
                  record_s=round(t1 - t0, 1), compile_s=round(t2 - t1, 1), cached=False)
    cached.parent.mkdir(parents=True, exist_ok=True)
    tmp = cached.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    os.replace(tmp, cached)
    return result


def table(result: dict) -> str:
    """The markdown table of a ``run``."""
    cc = result["cc"]
    lines = [f"Compiled for sm_{cc[0]}{cc[1]} by `python benchmarks/cuda_compile_table.py` "
             f"({result['versions']}).", "",
             "| kernel | variants | registers | stack frame (local memory) [B] "
             "| spill stores [B] | spill loads [B] |",
             "|---|---:|---:|---:|---:|---:|"]
    by_kernel: dict[str, list] = {}
    for r in result["rows"]:
        by_kernel.setdefault(r["kernel"], []).append(r)

    def span(vals):
        lo, hi = min(vals), max(vals)
        return f"{lo}" if lo == hi else f"{lo}-{hi}"
    for name, rs in sorted(by_kernel.items()):
        lines.append(f"| `{name}` | {len(rs)} | {span([r['registers'] for r in rs])} | "
                     f"{span([r['stack'] for r in rs])} | "
                     f"{span([r['spill_stores'] for r in rs])} | "
                     f"{span([r['spill_loads'] for r in rs])} |")
    tags = sorted({r["variant"] for r in result["rows"] if r["variant"]})
    special = sorted({r["kernel"] for r in result["rows"] if r["variant"]})
    if tags:
        lines += ["", "The kernels specialized to the scene, per feature set (F friction, "
                  "R rotation, S sleeping, W walls; 1 compiled in; _hertz: the contact pass "
                  "of that law, the others' kernels do not depend on it; _glue: the body "
                  "stage adding the glue bonds' sums): registers / stack frame [B].",
                  "", "| variant | " + " | ".join(f"`{k}`" for k in special) + " |",
                  "|---|" + "---:|" * len(special)]
        cell = {(r["kernel"], r["variant"]): r for r in result["rows"]}
        for t in tags:
            lines.append(f"| {t} | " + " | ".join(
                f"{cell[k, t]['registers']} / {cell[k, t]['stack']}" if (k, t) in cell else "–"
                for k in special) + " |")
    return "\n".join(lines)


def write_doc(text: str, doc: Path = DOC) -> None:
    """Replace the table between the markers in docs/cuda.md (atomically)."""
    src = doc.read_text()
    i, j = src.index(BEGIN), src.index(END)
    new = src[:i + len(BEGIN)] + "\n" + text + "\n" + src[j:]
    tmp = doc.with_suffix(".md.tmp")
    tmp.write_text(new)
    os.replace(tmp, doc)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cc", default="9.0", help="compute capability (default 9.0)")
    ap.add_argument("--write", action="store_true", help="put the table into docs/cuda.md")
    ap.add_argument("--no-cache", action="store_true", help="compile even if cached")
    ap.add_argument("--record", help=argparse.SUPPRESS)
    ap.add_argument("--compile", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    cc = tuple(int(x) for x in args.cc.split("."))
    if args.record:
        with open(args.record, "wb") as f:
            pickle.dump(record(), f)
        return 0
    if args.compile:
        rec, out, i, n = args.compile.split(os.pathsep)
        with open(rec, "rb") as f:
            records = pickle.load(f)
        rows = compile_jobs(records, jobs(records)[int(i)::int(n)], cc)
        Path(out).write_text(json.dumps(rows))
        return 0
    result = run(cc, use_cache=not args.no_cache)
    text = table(result)
    print(text)
    spills = [r for r in result["rows"] if r["spill_stores"] or r["spill_loads"]]
    print(f"\n{len(result['rows'])} kernel variants; spills: {len(spills)}; "
          + ("cached" if result["cached"] else
             f"record {result['record_s']} s, compile {result['compile_s']} s"))
    if args.write:
        write_doc(text)
    return 1 if spills else 0


if __name__ == "__main__":
    sys.exit(main())
