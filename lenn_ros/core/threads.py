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


def cores() -> int:
    """Threads the work may use: the cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
