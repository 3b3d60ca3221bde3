"""Farming work out to Dask: a LocalCluster on this machine, or a running scheduler.

    with connect(workers=2) as farm:                 # or connect(scheduler="tcp://host:8786")
        futures = [farm.submit(fn, arg, key=f"wedge-{i}") for i, arg in enumerate(args)]
        for future, value, error in farm.finished(futures):
            ...

What `dempipe wedge` and `dempipe report --workers/--scheduler` run on. Dask's
distributed scheduler does the scheduling, the retries of tasks whose worker died
and the dashboard; this module only starts or joins a cluster whose bakes do not
fight over the cores (below) and turns Dask's failures into one-line reasons.

Dask is an optional extra (``pip install "dempipe[farm]"``). This module imports it
inside its functions only, and nothing else in dempipe imports this module unless
work is farmed out, so ``import dempipe`` and every other command never import dask.

Threads. A farm worker runs one task at a time (Dask ``nthreads`` 1) and each task
bakes with the numba thread pool its worker process was given: ``NUMBA_NUM_THREADS``
in the worker's environment (numba reads it once, when it is first imported, so it
must be set when the worker process starts; the local cluster passes it in the
nanny's ``env``). Several workers on one machine also get ``OMP_WAIT_POLICY=PASSIVE``:
numba's OpenMP threads otherwise spin while they wait, and two bakes on 2 cores ran
14x slower than one after the other (docs/performance.md, "Two bakes at once"). For
workers started by hand or by a batch system, docs/farm.md says how to size them;
:func:`host_warnings` says when a running cluster's workers would fight.
"""

from __future__ import annotations

import logging
import os
from contextlib import contextmanager
from dataclasses import dataclass, field

from dempipe.errors import DempipeError

#: What to run when Dask is missing.
INSTALL_HINT = 'pip install "dempipe[farm]"'
#: How long to wait for a running scheduler to answer, and for its first worker [s].
CONNECT_TIMEOUT = 30.0
WORKER_TIMEOUT = 120.0
#: Seconds a --scheduler address has to answer as Dask does (probe_scheduler).
PROBE_TIMEOUT = 5.0
#: The largest length a Dask handshake starts with (it is about 60 bytes).
HANDSHAKE_BYTES_MAX = 1 << 20


class FarmError(DempipeError):
    """Dask is missing, a scheduler cannot be reached, or a cluster's settings are unusable."""


def require_dask(what: str = "dempipe wedge") -> None:
    """Raise FarmError (one line, with the install command) when dask.distributed is missing."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise FarmError(f"{what} runs its bakes on Dask, which is not installed; "
                        f"install it with: {INSTALL_HINT}") from None


def cores() -> int:
    """CPU cores this process may run on (its affinity, as numba counts them)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def local_sizes(workers: int | None, threads: int | None, tasks: int | None) -> tuple[int, int]:
    """(workers, numba threads per worker) of a local cluster.

    Default: one worker per core, but no more workers than tasks, and the cores
    shared out among the workers (a wedge of 4 on 2 cores: 2 workers of 1 thread;
    a single bake: 1 worker with every core).
    """
    n_cores = cores()
    if workers is None:
        workers = max(1, min(n_cores, tasks or n_cores))
    if threads is None:
        threads = max(1, n_cores // workers)
    return int(workers), int(threads)


def local_worker_env(workers: int, threads: int) -> dict:
    """The environment of a local cluster's worker processes (set before numba starts)."""
    env = {"NUMBA_NUM_THREADS": str(threads)}
    # Several bakes share this machine: threads that spin while they wait steal the
    # others' cores. A wait policy the user set explicitly is kept.
    if workers > 1 and "OMP_WAIT_POLICY" not in os.environ:
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    return env


def worker_facts(dask_worker=None) -> dict:
    """What a worker process was given (run on each worker by :meth:`Farm.survey`).

    Read from the environment, so numba is not imported for it: numba's pool is
    ``NUMBA_NUM_THREADS`` or, unset, every core the process may use.
    """
    import socket

    env_threads = os.environ.get("NUMBA_NUM_THREADS")
    try:
        numba_threads = int(env_threads) if env_threads else cores()
    except ValueError:
        numba_threads = cores()
    return dict(host=socket.gethostname(), cores=cores(), numba_threads=numba_threads,
                wait_policy=os.environ.get("OMP_WAIT_POLICY", ""),
                nthreads=int(getattr(dask_worker, "nthreads", 1) or 1), pid=os.getpid())


def host_warnings(facts: dict) -> list[str]:
    """One-line warnings for workers that would fight over a machine's cores.

    ``facts``: worker address -> :func:`worker_facts`. Warns when a worker runs
    several tasks at once, when the workers on a host have more numba threads in
    all than the host has cores, and when several workers share a host without
    ``OMP_WAIT_POLICY=PASSIVE``. Pure: tested on made-up clusters.
    """
    out = []
    for addr, f in sorted(facts.items()):
        if f["nthreads"] > 1:
            out.append(f"worker {addr} runs {f['nthreads']} tasks at once, each a bake with "
                       f"{f['numba_threads']} threads: start it with `dask worker --nthreads 1` "
                       f"(docs/farm.md)")
    hosts: dict = {}
    for addr, f in facts.items():
        hosts.setdefault(f["host"], []).append(f)
    for host, fs in sorted(hosts.items()):
        threads = sum(f["numba_threads"] * f["nthreads"] for f in fs)
        n_cores = max(f["cores"] for f in fs)
        if threads > n_cores:
            out.append(f"host {host}: {len(fs)} workers with {threads} bake threads in all on "
                       f"{n_cores} cores; set NUMBA_NUM_THREADS={max(1, n_cores // len(fs))} "
                       f"in their environment (docs/farm.md)")
        spinning = [f for f in fs if f["wait_policy"].upper() != "PASSIVE"]
        if len(fs) > 1 and spinning:
            out.append(f"host {host}: {len(fs)} workers share it without "
                       f"OMP_WAIT_POLICY=PASSIVE; their threads spin against each other "
                       f"(docs/farm.md)")
    return out


def failure_reason(exc: BaseException) -> str:
    """One line for a task that raised or whose workers kept dying."""
    name = type(exc).__name__
    if name == "KilledWorker":
        return ("the workers running it died each time it was tried (out of memory? "
                "see the workers' logs)")
    if name == "CancelledError":
        return "cancelled (the scheduler or its workers went away)"
    text = " ".join(str(exc).split())
    return f"{name}: {text}" if text else name


@dataclass
class Farm:
    """A connected Dask client, with what this module knows of its cluster.

    client : distributed.Client
    dashboard : the dashboard's address, or None when there is none (no bokeh)
    local : True for a LocalCluster started here (closed with the Farm)
    threads : numba threads of each local worker (None on a remote cluster)
    """

    client: object
    dashboard: str | None = None
    local: bool = False
    threads: int | None = None
    cluster: object = None
    facts: dict = field(default_factory=dict)

    @property
    def scheduler(self) -> str:
        return self.client.scheduler.address

    def survey(self) -> dict:
        """worker address -> :func:`worker_facts`, for the workers connected now."""
        self.facts = self.client.run(worker_facts)
        return self.facts

    def submit(self, fn, *args, key: str, **kwargs):
        """Run ``fn(*args, **kwargs)`` as a task named ``key`` (never cached: pure=False)."""
        return self.client.submit(fn, *args, key=key, pure=False, **kwargs)

    def finished(self, futures):
        """Yield (future, value, None) or (future, None, exception) as tasks finish."""
        from distributed import as_completed

        for fut in as_completed(futures):
            try:
                yield fut, fut.result(), None
            except Exception as exc:            # the task's, or KilledWorker/CancelledError
                yield fut, None, exc

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()


def _has_bokeh() -> bool:
    from importlib.util import find_spec

    return find_spec("bokeh") is not None


def _dashboard(client) -> str | None:
    """The dashboard's address when the scheduler serves one (it needs bokeh there)."""
    try:
        services = client.scheduler_info().get("services", {})
        if "dashboard" not in services or not client.run_on_scheduler(_has_bokeh):
            return None
        return client.dashboard_link
    except Exception:          # the address is a courtesy: never stop a wedge for it
        return None


def probe_scheduler(address: str, timeout: float = PROBE_TIMEOUT) -> None:
    """Refuse (FarmError) an address where no Dask scheduler listens, before Dask tries.

    A Dask scheduler speaks first: on a new TCP connection it sends its handshake, a
    message whose first 8 bytes are a small little-endian length. Something else
    listening either says nothing (Dask's client then waits out its timeouts, ten
    minutes in all) or says something else (which Dask reads as a length of exabytes
    and fails with a MemoryError). Only tcp:// (or a bare host:port) is probed."""
    import socket
    import struct

    scheme, _, rest = address.rpartition("://")
    if scheme not in ("", "tcp"):
        return
    host, _, port = rest.rpartition(":")
    host = host.strip("[]") or "127.0.0.1"
    try:
        port_n = int(port)
    except ValueError:
        raise FarmError(f"--scheduler {address}: expected tcp://HOST:PORT (e.g. "
                        f"tcp://10.0.0.5:8786)") from None
    try:
        with socket.create_connection((host, port_n), timeout=timeout) as conn:
            conn.settimeout(timeout)
            head = b""
            while len(head) < 8:
                got = conn.recv(8 - len(head))
                if not got:
                    break
                head += got
    except socket.timeout:
        raise FarmError(f"--scheduler {address}: something listens there but does not "
                        f"answer as a Dask scheduler within {timeout:.0f} s; give the "
                        f"address `dask scheduler` prints (docs/farm.md)") from None
    except OSError as exc:
        raise FarmError(f"--scheduler {address}: cannot connect ({exc.strerror or exc}); "
                        f"start one with `dask scheduler` (docs/farm.md)") from None
    if len(head) < 8 or struct.unpack("<Q", head)[0] > HANDSHAKE_BYTES_MAX:
        raise FarmError(f"--scheduler {address}: what listens there is not a Dask "
                        f"scheduler (it answered {head[:16]!r}); give the address "
                        f"`dask scheduler` prints (docs/farm.md)")


@contextmanager
def connect(workers: int | None = None, scheduler: str | None = None,
            threads: int | None = None, tasks: int | None = None, *,
            host: str = "127.0.0.1", dashboard_address: str | None = "127.0.0.1:0",
            what: str = "dempipe wedge"):
    """Start a LocalCluster (``workers``, ``threads``) or join ``scheduler``; yield a Farm.

    workers : local worker processes (default: see :func:`local_sizes`)
    threads : numba threads per local worker (default: the cores shared out)
    tasks : how many tasks will run (caps the default number of local workers)
    scheduler : address of a running ``dask scheduler`` (tcp://host:8786); its
        workers' threads are theirs (docs/farm.md), so ``workers``/``threads`` must
        not be given with it
    host : the interface the local cluster listens on (loopback by default)
    dashboard_address : where a local cluster serves its dashboard (None: none)
    """
    require_dask(what)
    if scheduler and (workers is not None or threads is not None):
        raise FarmError("--scheduler runs on that scheduler's own workers, which bring their "
                        "own threads (docs/farm.md); --workers and --threads size a local "
                        "cluster: give one or the other")
    if workers is not None and workers < 1:
        raise FarmError(f"--workers: {workers} must be at least 1")
    if threads is not None and threads < 1:
        raise FarmError(f"--threads: {threads} must be at least 1")
    from distributed import Client

    if scheduler:
        probe_scheduler(scheduler)
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError, ValueError) as exc:
            raise FarmError(f"--scheduler {scheduler}: cannot connect "
                            f"({' '.join(str(exc).split())}); start one with "
                            f"`dask scheduler` (docs/farm.md)") from None
        farm = Farm(client, dashboard=_dashboard(client))
        try:
            client.wait_for_workers(1, timeout=WORKER_TIMEOUT)
        except (TimeoutError, OSError):
            farm.close()
            raise FarmError(f"--scheduler {scheduler}: no worker joined in "
                            f"{WORKER_TIMEOUT:.0f} s; start some with `dask worker "
                            f"{scheduler} --nthreads 1` (docs/farm.md)") from None
        except BaseException:
            farm.close()
            raise
    else:
        from distributed import LocalCluster

        n, t = local_sizes(workers, threads, tasks)
        kw = dict(dashboard_address=dashboard_address) if dashboard_address else \
            dict(dashboard_address=None)
        try:
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                   host=host, env=local_worker_env(n, t),
                                   silence_logs=logging.ERROR, **kw)
        except (RuntimeError, OSError, TimeoutError) as exc:
            raise FarmError(f"could not start a local Dask cluster of {n} workers "
                            f"({' '.join(str(exc).split())})") from None
        try:
            client = Client(cluster)
        except BaseException:
            cluster.close()
            raise
        farm = Farm(client, dashboard=_dashboard(client), local=True, threads=t,
                    cluster=cluster)
    try:
        yield farm
    finally:
        farm.close()
