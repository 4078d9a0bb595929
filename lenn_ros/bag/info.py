"""``lenn-ros bag-info``: what a recording holds per topic, as ``ros2 bag info`` shows it, and what it lost.

Any rosbag2 recording (MCAP, one file or split; sqlite3). Per topic: type, count, first and last
log time, rate (messages over the span), time gaps (a log-time step longer than
:data:`GAP_FACTOR` times the topic's median step and at least :data:`GAP_MIN_S`: the publisher or the
recorder paused), and, where the recording stores DDS sequence numbers (the package's recorder),
the messages it lost: the sequence numbers in log-time order are split where a publisher (re)starts
at 1; within each run, ``missing`` = numbers between its first and last that never arrived,
``reordered`` = messages that arrived after a higher number. A recorder started late is not loss
(the count starts at the first number seen). Topics recorded without sequence numbers (0: the RMW
gives none, an import, any sqlite3 bag) report ``missing: null``.
"""

from __future__ import annotations

import itertools
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros.bag.qos import dump_qos, parse_qos
from lenn_ros.bag.reader import open_bag, read_summary, topic_types
from lenn_ros.bag.scalars import topic_series
from lenn_ros.core.pairing import sequence_streams

__all__ = ["bag_info", "format_info", "sequence_gaps"]

#: A log-time step this many times a topic's median step is a gap ...
GAP_FACTOR = 5.0
#: ... and at least this long (s), so jitter of a fast topic is none.
GAP_MIN_S = 0.05


def sequence_gaps(sequence: np.ndarray) -> dict[str, int | None]:
    """``missing``, ``reordered`` and ``restarts`` of sequence numbers in arrival order (see module doc)."""
    known = np.asarray(sequence, dtype=np.int64)
    known = known[known > 0]
    if not known.size:
        return {"missing": None, "reordered": 0, "restarts": 0}
    runs = sequence_streams(known)
    bounds = [0, *(np.flatnonzero(np.diff(runs)) + 1).tolist(), len(known)]
    missing = reordered = 0
    for lo, hi in itertools.pairwise(bounds):
        part = known[lo:hi]
        increasing = part.size < 2 or bool(np.all(part[1:] > part[:-1]))  # the usual case: no sort needed
        distinct = part.size if increasing else np.unique(part).size
        missing += int(part.max() - part.min() + 1 - distinct)
        reordered += int(np.sum(part[1:] < np.maximum.accumulate(part)[:-1]))
    return {"missing": missing, "reordered": reordered, "restarts": len(bounds) - 2}


def time_gaps(log_time_ns: np.ndarray) -> dict[str, Any]:
    """Pauses in a topic's log times: how many, the longest (s), and the first's start (s since the epoch)."""
    times = np.sort(np.asarray(log_time_ns, dtype=np.int64))
    if times.size < 3:
        return {"count": 0, "longest_s": 0.0, "first_at_s": None}
    steps = np.diff(times) * 1e-9
    limit = max(GAP_FACTOR * float(np.median(steps)), GAP_MIN_S)
    where = np.flatnonzero(steps > limit)
    return {
        "count": int(where.size),
        "longest_s": float(steps[where].max()) if where.size else 0.0,
        "first_at_s": float(times[where[0]] * 1e-9) if where.size else None,
    }


def _qos(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Offered QoS per topic, as the recording stores it (an MCAP channel's metadata; sqlite3: metadata.yaml)."""
    found = open_bag(path)
    if found.single_mcap is not None:
        _, summary = read_summary(path)
        return {
            channel.topic: dump_qos(parse_qos(channel.metadata.get("offered_qos_profiles", "") or []))
            for channel in summary.channels.values()
        }
    from lenn_ros.bag.reader import _sqlite_reader

    if found.storage != "sqlite3":
        return {}
    reader = _sqlite_reader(found)
    try:
        return {c.topic: dump_qos(list(getattr(c.ext, "offered_qos_profiles", []) or [])) for c in reader.connections}
    finally:
        reader.close()


def _topic_entry(path: Path, topic: str, type_name: str, qos: list[dict[str, Any]]) -> dict[str, Any]:
    series = topic_series(path, topic, with_values=False)
    times = series.log_time_ns
    span = (int(times.max()) - int(times.min())) * 1e-9 if times.size > 1 else 0.0
    return {
        "type": type_name,
        "count": int(times.size),
        "first_ns": int(times.min()) if times.size else None,
        "last_ns": int(times.max()) if times.size else None,
        "rate_hz": (times.size - 1) / span if span > 0 else None,
        "time_gaps": time_gaps(times),
        **sequence_gaps(series.sequence),
        "offered_qos": qos,
    }


def bag_info(path: str | Path) -> dict[str, Any]:
    """Summary: storage, files, span; per topic type, count, rate, time gaps, missing/reordered numbers, QoS."""
    path = Path(path)
    found = open_bag(path)
    qos = _qos(path)
    entries = {
        topic: _topic_entry(path, topic, type_name, qos.get(topic, []))
        for topic, type_name in sorted(topic_types(path).items())
    }
    firsts = [e["first_ns"] for e in entries.values() if e["first_ns"] is not None]
    lasts = [e["last_ns"] for e in entries.values() if e["last_ns"] is not None]
    start, end = (min(firsts), max(lasts)) if firsts else (None, None)
    return {
        "path": str(path),
        "storage": found.storage,
        "files": [str(file) for file in found.files],
        "bytes": sum(file.stat().st_size for file in found.files),
        "message_count": sum(e["count"] for e in entries.values()),
        "start_ns": start,
        "end_ns": end,
        "duration_s": (end - start) / 1e9 if firsts else 0.0,
        "missing": sum(e["missing"] or 0 for e in entries.values()),
        "topics": entries,
    }


def _when(ns: int | None) -> str:
    if ns is None:
        return "-"
    return f"{datetime.fromtimestamp(ns * 1e-9, tz=UTC):%Y-%m-%d %H:%M:%S.%f}"[:-3] + f" UTC ({ns * 1e-9:.3f})"


def _size(count: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if count < 1024 or unit == "GiB":
            return f"{count:.1f} {unit}" if unit != "B" else f"{count} B"
        count /= 1024
    return ""


def format_info(info: dict[str, Any]) -> str:
    """The summary a person reads, laid out as ``ros2 bag info`` lays out its own."""
    files = ", ".join(Path(file).name for file in info["files"])
    lines = [
        f"Files:        {files} ({info['storage']}, {_size(info['bytes'])})",
        f"Duration:     {info['duration_s']:.3f} s",
        f"Start:        {_when(info['start_ns'])}",
        f"End:          {_when(info['end_ns'])}",
        f"Messages:     {info['message_count']}",
        "Topics:",
    ]
    width = max((len(topic) for topic in info["topics"]), default=5)
    kinds = max((len(entry["type"]) for entry in info["topics"].values()), default=4)
    for topic, entry in info["topics"].items():
        rate = f"{entry['rate_hz']:9.2f} Hz" if entry["rate_hz"] else " " * 12
        gaps = entry["time_gaps"]
        paused = f"{gaps['count']} pause(s), the longest {gaps['longest_s']:.3f} s" if gaps["count"] else "no pauses"
        lost = "" if entry["missing"] is None else f", {entry['missing']} lost (sequence numbers)"
        if entry.get("reordered"):
            lost += f", {entry['reordered']} reordered"
        if entry.get("restarts"):
            lost += f", {entry['restarts']} publisher restart(s)"
        lines.append(f"  {topic:<{width}}  {entry['type']:<{kinds}}  {entry['count']:>9} msgs {rate}  {paused}{lost}")
    return "\n".join(lines)
