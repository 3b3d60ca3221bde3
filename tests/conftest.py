"""Shared set-up of the suite.

The tests mirror the package (tests/sim/ for dempipe/sim/, ...); the helpers they
share sit here, at the top of tests/, importable by name since pytest puts this folder
on sys.path: ``bodies`` (exact sphere lattices for physics without meshes),
``reference`` (the all-pairs NumPy oracle for one step), ``processes`` (real
`dempipe` processes and sample-by-sample USD comparison), ``cudasim`` (a CUDA test
file run under Numba's simulator), ``moved`` (frames of known motion).

Tiers: ``python -m pytest -m "not slow"`` is the inner loop; the whole suite is what
CI runs. Both run their files on all cores with pytest-xdist (``-n auto --dist
loadfile`` in pyproject.toml: a file's module fixtures are built once), each worker
one process sharing numba's on-disk kernel cache.
"""

import os

# One general kernel for every scene of the suite (sim.kernels.layout.run_flags): a
# kernel variant takes about a minute to compile, and a scene's own variant gives the
# same frames bit for bit. tests/sim/test_specialize.py (which shows that sameness) and
# a CUDA parity case ask for the specialized kernels, as a bake runs them.
os.environ.setdefault("DEMPIPE_KERNELS", "general")

if os.environ.get("PYTEST_XDIST_WORKER"):
    # The workers are the suite's parallelism: one numba thread each. Two workers'
    # parallel loops on shared cores would either spin against each other (libgomp's
    # default) or pay a wake-up per loop (OMP_WAIT_POLICY=PASSIVE, several-fold on the
    # thousands of small steps of a bounce test). Results do not depend on the thread count;
    # the tests that show it start their own two-thread process (processes.run_python).
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")

