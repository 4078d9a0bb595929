"""A training part longer than this machine's memory holds: the model is built on its latest samples.

The selection holds, for each view judged at a time (one per core), the network inputs of its
longest lag span and a dictionary's features over every training row. Measured with two cores
(peak resident memory): a single joint logged at 200 Hz, 14 KB per training row (an hour's log,
480 000 training rows: 6.9 GB); the six-joint industrial robot, 43 KB per row at 40 000 rows (2.0 GB)
and 48 KB at 230 000 (11.1 GB). An hour of that robot at 200 Hz would need about 35 GB, more than
this 24 GB machine has: the kernel would end the process without a word.

So before anything is built, ``fit`` estimates the bytes per training row from the widest view
(every column at the longest lag span) and the cores it will use, and when the training part
needs more than MEMORY_SHARE of the memory available, it keeps the latest training rows that
fit: those that lead into the test part, which a plant that drifted over a day is closest to.
The report says so in one line. The test part is scored as recorded.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from lenn_ros.core.threads import cores
from lenn_ros.fit.data import Data
from lenn_ros.fit.families import LONGEST_LAGS
from lenn_ros.fit.numbering import span

#: share of the memory available when ``fit`` starts that its training rows may take
MEMORY_SHARE = 0.5
#: bytes per training row, per core, per network input of the widest view (its inputs, their features and
#: the copies made while ranking): 1.24 times what the robot measured at 230 000 rows, 1.6 times the joint
BYTES_PER_INPUT = 28
#: ... and per core for the dictionary's features beyond the inputs' own (a degree-3 dictionary of a narrow view)
BYTES_PER_CORE = 8_000
#: fewer training rows than this are never cut: a short record fits anywhere
LEAST_ROWS = 20_000


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux's MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def bytes_per_row(n_columns: int, workers: int) -> int:
    """The estimated peak bytes ``fit`` takes per training row, for a widest view of ``n_columns`` columns."""
    return workers * (BYTES_PER_INPUT * LONGEST_LAGS * n_columns + BYTES_PER_CORE)


def within_memory(
    data: Data, test_from: int, available: int | None = None, workers: int | None = None
) -> tuple[Data, int, dict[str, Any]]:
    """(the record with its earliest training rows left out where the training part would not fit in memory,
    ``test_from`` in it, what was done: {} when nothing). ``available``: bytes (default: the machine's now)."""
    available = available_memory() if available is None else available
    start = test_from - 1
    if available is None:
        return data, test_from, {}
    widest = data.n_y + data.n_u  # a several-output fit's coupled view reads every output and every input
    per_row = bytes_per_row(widest, workers or cores())
    rows = max(LEAST_ROWS, int(MEMORY_SHARE * available // per_row))
    if start <= rows:
        return data, test_from, {}
    keep = np.ones(len(data.y), dtype=bool)
    keep[: start - rows] = False
    gib = 2.0**30
    text = (
        f"the {start} training samples would need about {start * per_row / gib:.1f} GiB to fit, more than "
        f"{MEMORY_SHARE:.0%} of the {available / gib:.1f} GiB available: the model is built on the last {rows} "
        f"(samples {span(data, start - rows, start - 1)}); the {start - rows} before them are left out"
    )
    info = {"train_samples_used": rows, "samples_left_out": start - rows, "bytes_per_row": per_row, "text": text}
    return data.kept(keep), rows + 1, info
