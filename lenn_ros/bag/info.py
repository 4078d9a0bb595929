"""``lenn-ros bag-info``: what a bag holds per topic, including the messages it lost.

Loss shows as gaps in the MCAP ``sequence`` field (the DDS publication sequence number
the recorder stores). Rule, for one publisher per topic as the package's nodes publish:
the sequence numbers in log-time order are split where a publisher (re)starts at 1;
within each run, ``missing`` = numbers between its first and last that never arrived,
``reordered`` = messages that arrived after a higher number. A recorder started late
is not loss (the count starts at the first number seen). Topics recorded without
sequence numbers (0: the RMW gives none, or an imported CSV) report ``missing: null``.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros.bag.qos import dump_qos, parse_qos
from lenn_ros.bag.reader import _types, read_summary
from lenn_ros.bag.scalars import read_series

__all__ = ["bag_info", "sequence_gaps"]


def sequence_gaps(sequence: np.ndarray) -> dict[str, int | None]:
    """``missing``, ``reordered`` and ``restarts`` of sequence numbers in arrival order (see module doc)."""
    known = np.asarray(sequence, dtype=np.int64)
    known = known[known > 0]
    if not known.size:
        return {"missing": None, "reordered": 0, "restarts": 0}
    starts = np.flatnonzero(known == 1)
    bounds = [0, *[int(s) for s in starts if s > 0], len(known)]
    missing = reordered = 0
    for lo, hi in itertools.pairwise(bounds):
        part = known[lo:hi]
        increasing = part.size < 2 or bool(np.all(part[1:] > part[:-1]))  # the usual case: no sort needed
        distinct = part.size if increasing else np.unique(part).size
        missing += int(part.max() - part.min() + 1 - distinct)
        reordered += int(np.sum(part[1:] < np.maximum.accumulate(part)[:-1]))
    return {"missing": missing, "reordered": reordered, "restarts": len(bounds) - 2}


def _topic_entry(path: Path, file: Path, summary: Any, channel: Any, type_name: str) -> dict[str, Any]:
    series = read_series(path, file, summary, channel.topic, with_values=False)
    times = series.log_time_ns
    qos = parse_qos(channel.metadata.get("offered_qos_profiles", "") or [])
    return {
        "type": type_name,
        "count": int(times.size),
        "first_ns": int(times.min()) if times.size else None,
        "last_ns": int(times.max()) if times.size else None,
        **sequence_gaps(series.sequence),
        "offered_qos": dump_qos(qos),
    }


def bag_info(path: str | Path) -> dict[str, Any]:
    """Summary: per topic type, count, first/last log time, missing/reordered sequence numbers, offered QoS."""
    path = Path(path)
    file, summary = read_summary(path)
    types = _types(summary)
    entries = {
        channel.topic: _topic_entry(path, file, summary, channel, types[channel.topic])
        for channel in sorted(summary.channels.values(), key=lambda c: c.topic)
    }
    firsts = [e["first_ns"] for e in entries.values() if e["first_ns"] is not None]
    lasts = [e["last_ns"] for e in entries.values() if e["last_ns"] is not None]
    total = sum(e["count"] for e in entries.values())
    start, end = (min(firsts), max(lasts)) if firsts else (None, None)
    return {
        "path": str(path),
        "storage": "mcap",
        "message_count": total,
        "start_ns": start,
        "end_ns": end,
        "duration_s": (end - start) / 1e9 if firsts else 0.0,
        "missing": sum(e["missing"] or 0 for e in entries.values()),
        "topics": entries,
    }
