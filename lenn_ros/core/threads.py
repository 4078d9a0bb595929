"""Independent work on the machine's cores, in threads.

The heavy parts of the package (compiled free runs and steps, the feature expansion,
one-thread BLAS, numpy's array arithmetic) release the GIL, so independent pieces (a
fit's candidates, outputs or refinements; a several-output model's outputs run over a
record) use every core from threads, with no copy of the data into other processes.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator, Sized


def side_by_side(work: Callable, items: Iterable, workers: int) -> Iterator:
    """``work(item)`` for each item on up to ``workers`` threads, yielded in the items' order as each is done.

    With one worker (or one item) everything runs on this thread. ``items`` may be
    a generator: the pool takes each item as this thread makes it, so making the next
    overlaps with the work on those before.
    """
    if workers <= 1 or (isinstance(items, Sized) and len(items) <= 1):
        yield from (work(item) for item in items)
        return
    from concurrent.futures import ThreadPoolExecutor

    count = len(items) if isinstance(items, Sized) else workers
    with ThreadPoolExecutor(max_workers=min(workers, count)) as pool:
        yield from pool.map(work, items)


#: caps :func:`cores` in a process that shares its machine's cores with others of its kind (a fit-fleet
#: worker: workers x threads must fit the cores, or every fit's thread pools contend for them)
THREADS_VARIABLE = "LENN_ROS_THREADS"
#: the thread pools of the libraries below the package, capped alike in such a process before numpy loads
#: (fit already keeps BLAS to one thread; numba compiles nothing parallel today: both set for what may come)
LIBRARY_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


class ThreadsError(ValueError):
    """LENN_ROS_THREADS is not a number of threads (the user's to fix: :mod:`lenn_ros.errors`)."""


def cores() -> int:
    """Threads the work may use: the cores this process may run on, at most LENN_ROS_THREADS when set."""
    available = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    cap = os.environ.get(THREADS_VARIABLE, "").strip()
    if not cap:
        return available
    if not cap.isdigit() or int(cap) < 1:
        raise ThreadsError(f"{THREADS_VARIABLE}={cap!r}: expected a whole number of threads >= 1")
    return min(available, int(cap))


def worker_environment(threads: int) -> dict[str, str]:
    """The environment of a worker process given ``threads`` of the machine's cores: the package's
    cap and the libraries' (to be set before the process starts, as numpy reads them when it loads)."""
    return {name: str(max(1, threads)) for name in (THREADS_VARIABLE, *LIBRARY_THREADS)}
