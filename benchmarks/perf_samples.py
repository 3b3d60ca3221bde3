"""Where the compiled code spends its time, instruction by instruction (Linux perf).

numba's compiled functions have no symbols perf can see, and functions loaded from
numba's disk cache have no code library left to name them. So this script runs the
dense pile of cpu_bench with a fresh, empty cache (everything is compiled in this
process), then writes /tmp/perf-PID.map (perf's map of JIT-compiled code: address,
size, name for every function of the kernels' code libraries) and a copy of the
machine code of the functions asked for. Two steps:

    perf record -e cpu-clock -F 4000 -o perf.data \\
        python benchmarks/perf_samples.py --spheres 30000 --steps 8000 --dump code/
    python benchmarks/perf_samples.py --report perf.data --dump code/

The first prints ms/step; compiling takes a minute or two of the samples, so give it
enough steps. The second prints the share of the samples in each dumped function and
its hottest instructions (objdump), and writes code/<name>_<address>.annot (every instruction
with its sample count). ``-e cpu-clock`` is a timer: it needs no hardware counters
(this machine's VM has none), but a sample lands on the instruction that was waiting,
often one after a slow load or a division: read the hot spots with that in mind, and
measure any change against the code without it (docs/performance.md, "Where a step goes").
Not part of run_all: it needs perf and is a tool, not a benchmark.
"""

from __future__ import annotations

import argparse
import collections
import glob
import os
import subprocess
import sys
import tempfile
import time

#: Functions whose code is copied (by a part of the name). The parallel loops' bodies
#: are "parfor_gufunc"s; LLVM may inline a small callee (sphere_forces) into its own.
DUMP = ("pair_forces", "sphere_forces", "body_update", "parfor_gufunc")


def code_libraries(namespace):
    """Every code library behind the compiled dispatchers in ``namespace``, with the
    libraries they link (the parallel loops' functions live in those)."""
    libs = []
    for name in dir(namespace):
        for cres in getattr(getattr(namespace, name), "overloads", {}).values():
            todo = [cres.library]
            while todo:
                lib = todo.pop()
                if all(lib is not seen for seen in libs):
                    libs.append(lib)
                    todo.extend(getattr(lib, "_linking_libraries", []))
    return libs


def write_perf_map(namespace) -> list:
    """/tmp/perf-PID.map for the functions of ``namespace``'s libraries; returns
    [(address, size, name)]."""
    found = {}
    for lib in code_libraries(namespace):
        try:
            module = lib._final_module
        except Exception:          # loaded from a cache: no module to read names from
            continue
        for fn in module.functions:
            if fn.is_declaration:
                continue
            address = lib._codegen._engine.get_function_address(fn.name)
            if address:
                found[address] = fn.name
    addresses = sorted(found)
    rows = []
    for k, a in enumerate(addresses):
        size = min(addresses[k + 1] - a if k + 1 < len(addresses) else 4096, 1 << 20)
        rows.append((a, size, found[a]))
    with open(f"/tmp/perf-{os.getpid()}.map", "w") as f:
        for a, size, name in rows:
            f.write(f"{a:x} {size:x} {name[:200]}\n")
    return rows


def read_code(address: int, size: int) -> bytes:
    """Up to ``size`` bytes of this process's memory from ``address``, stopping at the
    first unmapped page (a function's size is only known up to the next one mapped,
    which may lie in another allocation)."""
    out = b""
    with open("/proc/self/mem", "rb", buffering=0) as mem:
        while len(out) < size:
            piece = min(4096 - (address + len(out)) % 4096, size - len(out))
            try:
                mem.seek(address + len(out))
                out += mem.read(piece)
            except OSError:
                break
    return out


def run(args):
    os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="dempipe-perf-")
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:0] = [here, os.path.join(here, "..", "tests")]
    import numba
    from cpu_bench import dense_pile

    from dempipe.sim.simulator import Simulator

    model = dense_pile(args.spheres)
    sim = Simulator(model)
    state = model.initial_state()
    sim.backend.step(state, 20)
    numba.set_num_threads(args.threads or numba.config.NUMBA_NUM_THREADS)
    t0 = time.perf_counter()
    sim.backend.step(state, args.steps)
    print(f"{model.n_spheres:,} spheres: {(time.perf_counter() - t0) / args.steps * 1e3:.3f} "
          f"ms/step on {numba.get_num_threads()} thread(s)")
    rows = write_perf_map(sim.backend.k)
    os.makedirs(args.dump, exist_ok=True)
    for a, size, name in rows:
        for want in DUMP:
            if want in name:
                with open(os.path.join(args.dump, f"{want}_{a:x}.bin"), "wb") as f:
                    f.write(read_code(a, size))
                break
    print(f"{len(rows)} functions mapped; code of {', '.join(DUMP)} in {args.dump}")


def report(args):
    out = subprocess.run(["perf", "script", "-i", args.report, "-F", "ip"],
                         capture_output=True, text=True, check=True).stdout
    samples = collections.Counter(int(x, 16) for x in out.split())
    total = sum(samples.values())
    for path in sorted(glob.glob(os.path.join(args.dump, "*.bin"))):
        stem = os.path.basename(path)[:-4]
        name, base = stem.rsplit("_", 1)
        base = int(base, 16)
        size = os.path.getsize(path)
        inside = {a: c for a, c in samples.items() if base <= a < base + size}
        if not inside:
            continue
        asm = subprocess.run(["objdump", "-D", "-b", "binary", "-mi386:x86-64",
                              f"--adjust-vma={base:#x}", path],
                             capture_output=True, text=True, check=True).stdout
        lines = []
        for line in asm.splitlines():
            head = line.split(":", 1)[0].strip()
            try:
                a = int(head, 16)
            except ValueError:
                continue
            lines.append((inside.get(a, 0), line.strip()))
        with open(os.path.join(args.dump, f"{name}_{base:x}.annot"), "w") as f:
            f.write("\n".join(f"{c:7d} {text}" for c, text in lines) + "\n")
        n = sum(inside.values())
        if n < 0.002 * total:
            continue                        # a stage that barely ran
        print(f"\n{name} at {base:#x}: {n} samples, {n / total:.1%} of all")
        for c, text in sorted(lines, reverse=True)[: args.top]:
            print(f"  {c:6d} ({c / n:5.1%})  {text}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spheres", type=int, default=30_000, help="size of the dense pile")
    ap.add_argument("--steps", type=int, default=8000, help="timed steps")
    ap.add_argument("--threads", type=int, default=1, help="numba threads (0: all)")
    ap.add_argument("--dump", default="perf-code", help="folder for the code copies")
    ap.add_argument("--report", metavar="PERF_DATA", help="report on a recorded run")
    ap.add_argument("--top", type=int, default=15, help="hottest instructions shown")
    args = ap.parse_args()
    report(args) if args.report else run(args)


if __name__ == "__main__":
    main()
