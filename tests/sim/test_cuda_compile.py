"""The CUDA kernels compiled for a real GPU (compute capability 9.0: H100/H200)
and assembled by ptxas, on a machine without a GPU.

The simulator tests (tests/sim/test_cuda.py) run the kernels as Python and type-check
nothing; this compiles each kernel, with the argument types the backend really
launches it with (recorded from small scenes covering every feature switch), to
PTX with NVVM, and assembles it with ``ptxas -arch=sm_90 -v``
(benchmarks/cuda_compile_table.py, which also writes docs/cuda.md's table). It
fails on a kernel that does not compile or assemble and on any register spill:
a spill sends a kernel's values through local memory at every use, which on the
hot kernels (k_pair_forces, k_bodies) would cost more than any of the data-layout
gains docs/cuda.md lists. Needs numba-cuda with NVVM and NVRTC (the ``test``
extra) and ptxas (the CUDA toolkit); it fails, never skips, without them.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import cuda_compile_table as cct  # noqa: E402

sys.path.remove(str(ROOT / "benchmarks"))

# compiling every kernel variant for sm_90 takes minutes: not in the fast tier
pytestmark = pytest.mark.slow

#: Registers a thread may use on sm_90 (ptxas never exceeds it; it spills instead).
MAX_REGISTERS = 255


@pytest.fixture(scope="module")
def compiled():
    assert cct.ptxas_path(), "ptxas not found: install the CUDA toolkit (nvcc, ptxas)"
    return cct.run((9, 0))


def _kernels_defined() -> set[str]:
    """The CUDA target's kernels (dempipe/sim/kernels/cuda/*.py; the general ones: the
    variants are compiled from them)."""
    folder = ROOT / "dempipe" / "sim" / "kernels" / "cuda"
    src = "".join(p.read_text() for p in folder.glob("*.py"))
    return set(re.findall(r"^def (k_\w+)\(", src, flags=re.M))


def test_every_kernel_compiles_and_assembles(compiled):
    names = {r["kernel"] for r in compiled["rows"]}
    defined = _kernels_defined()
    assert defined, "no kernels found in dempipe/sim/kernels/cuda/"
    assert defined <= names, f"kernels never launched by the recorded scenes: {defined - names}"
    for r in compiled["rows"]:
        assert 0 < r["registers"] <= MAX_REGISTERS, r


def test_every_feature_set_is_compiled(compiled):
    # the kernels specialized to the scene: one variant per feature set (2^4)
    variants: dict[str, set] = {}
    for r in compiled["rows"]:
        if r["variant"]:
            variants.setdefault(r["kernel"], set()).add(r["variant"])
    assert set(variants) == {"k_body_patches", "k_pair_forces", "k_sphere_forces", "k_bodies"}
    linear = {k: {t for t in v if "_" not in t} for k, v in variants.items()}
    assert all(len(v) == 16 for v in linear.values()), variants
    # the contact pass of every other law (laws.LAWS), with every feature on
    assert variants["k_pair_forces"] - linear["k_pair_forces"] == {"F1R1S1W1_hertz"}, variants


def test_no_kernel_spills(compiled):
    spills = [(r["kernel"], r["spill_stores"], r["spill_loads"]) for r in compiled["rows"]
              if r["spill_stores"] or r["spill_loads"]]
    assert not spills, f"register spills (kernel, store bytes, load bytes): {spills}"


def test_docs_table_lists_every_kernel(compiled):
    doc = (ROOT / "docs" / "cuda.md").read_text()
    i, j = doc.index(cct.BEGIN), doc.index(cct.END)
    listed = set(re.findall(r"`(k_\w+)`", doc[i:j]))
    names = {r["kernel"] for r in compiled["rows"]}
    assert listed == names, ("docs/cuda.md's compile table is stale: run "
                             "python benchmarks/cuda_compile_table.py --write")


def test_ptxas_report_is_parsed():
    report = ("ptxas info    : Compiling entry function 'k' for 'sm_90'\n"
              "ptxas info    : Function properties for k\n"
              "    40 bytes stack frame, 8 bytes spill stores, 12 bytes spill loads\n"
              "ptxas info    : Used 90 registers, used 1 barriers, 380 bytes cmem[0]\n")
    assert cct.parse_ptxas(report) == dict(registers=90, stack=40, spill_stores=8,
                                           spill_loads=12)
    with pytest.raises(RuntimeError):
        cct.parse_ptxas("ptxas info    : 0 bytes gmem\n")
