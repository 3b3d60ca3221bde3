"""How many threads the CPU target steps with: the cores other processes leave free.

numba's parallel loops run on OpenMP (libgomp) where it is installed, whose idle
threads spin for milliseconds between a step's parallel regions before they sleep.
Alone on a machine that spin is what keeps a small scene's step fast (the regions
follow each other within microseconds, and a sleeping thread takes longer than that
to wake). Beside a second bake, Blender or a CI job it is ruinous: the spinning
threads hold the cores the neighbour's threads wait for, and both crawl.

So a bake watches the machine between its stepping calls (``CoreShare.adjust``, at
most every ``INTERVAL`` seconds): from /proc/stat, the busy time of all cores less
this process's own CPU time is what the others use, and the bake steps with the cores
they leave, at least one thread. Alone it keeps every thread and libgomp's own spin;
beside a neighbour it steps with fewer threads, none of them left spinning on a core
somebody else needs. Two bakes that both do this settle at one core each. The thread
count never changes the frames (the CPU target is bit-identical whatever the count),
only the speed. benchmarks/two_bakes.py measures it; docs/performance.md, "Two bakes
at once".

A thread count the user chose (``--threads``, ``Simulator(threads=...)``, or
NUMBA_NUM_THREADS in the environment) is kept as it is; where /proc/stat cannot be
read (not Linux) nothing changes.
"""

from __future__ import annotations

import numbers
import os
import time

from dempipe.errors import DeviceError

#: Seconds between two looks at the machine: a jiffy is 10 ms, so over half a second
#: the others' share is known to a few percent of a core.
INTERVAL = 0.5
#: The others' load [cores] is rounded up from this fraction: a neighbour that takes
#: a third of a core already makes one of ours wait behind it.
ROUND_UP_FROM = 0.3


def busy_seconds() -> float | None:
    """Busy CPU time of the whole machine since boot [s] (user, nice, system, irq,
    softirq and steal, every core), or None where /proc/stat cannot be read."""
    try:
        with open("/proc/stat", "rb") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != b"cpu" or len(fields) < 9:
        return None
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(x) for x in fields[1:9])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def own_seconds() -> float:
    """This process's CPU time, all its threads, user and system [s]."""
    t = os.times()
    return t.user + t.system


def threads_for(others: float, cores: int, most: int) -> int:
    """Threads to step with when other processes keep ``others`` cores busy [cores]:
    the cores they leave, at most ``most``, at least one."""
    taken = int(others) + (1 if others - int(others) >= ROUND_UP_FROM else 0)
    return max(1, min(most, cores - taken))


class CoreShare:
    """Follows the machine's load with numba's thread count (see the module).

    fixed : the user chose the thread count; ``adjust`` then does nothing.
    """

    def __init__(self, fixed: bool = False):
        import numba

        self._numba = numba
        self.most = int(numba.config.NUMBA_NUM_THREADS)
        try:
            self.cores = len(os.sched_getaffinity(0))
        except AttributeError:
            self.cores = os.cpu_count() or 1
        self.enabled = (not fixed and "NUMBA_NUM_THREADS" not in os.environ
                        and self.most > 1 and busy_seconds() is not None)
        self.threads = int(numba.get_num_threads())
        #: how many times the thread count changed (the bake's report)
        self.changes = 0
        self._last = None

    def adjust(self) -> int:
        """Look at the machine if INTERVAL has passed, set numba's thread count to what
        the other processes leave, and return it."""
        if not self.enabled:
            return self.threads
        now = time.perf_counter()
        sample = (now, busy_seconds(), own_seconds())
        last, self._last = self._last, sample
        if last is None or sample[1] is None:
            return self.threads
        if now - last[0] < INTERVAL:
            self._last = last                   # keep the older sample: a longer window
            return self.threads
        wall = now - last[0]
        others = max(0.0, (sample[1] - last[1]) - (sample[2] - last[2])) / wall
        n = threads_for(others, self.cores, self.most)
        if n != self.threads:
            self._numba.set_num_threads(n)
            self.threads = n
            self.changes += 1
        return n


def check_threads(threads) -> None:
    """A DeviceError unless ``threads`` is None (the CPU threads follow the cores other
    processes leave: CoreShare) or a whole number of at least 1."""
    if threads is not None and (isinstance(threads, bool)
                                or not isinstance(threads, numbers.Integral) or threads < 1):
        raise DeviceError(f"threads: {threads!r} must be a whole number of at least 1 "
                          f"(or None: follow the cores other processes leave)")
