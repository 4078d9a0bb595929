"""Vector runs (MIMO): ``u`` and ``y_p`` as ``std_msgs/msg/Float64MultiArray``, one message per sample.

The channel names travel in every message, as ``layout.dim[0].label`` (comma-joined,
``size`` = ``stride`` = the channel count): a bag then says which column is which in
``ros2 bag``, Foxglove or PlotJuggler too, without a side file that can get lost. A
SISO run stays ``std_msgs/msg/Float64`` (:mod:`lenn_ros.bag.csv_import`), so every
existing bag and consumer is untouched.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lenn_ros import topics
from lenn_ros.bag.errors import BagError
from lenn_ros.bag.msgtypes import TYPESTORE
from lenn_ros.bag.reader import find_topic, iter_messages, topic_types
from lenn_ros.bag.run import RawPairs, pair_raw, read_samples
from lenn_ros.bag.scalars import Series, topic_series
from lenn_ros.bag.writer import BagWriter

__all__ = [
    "VectorPairs",
    "VectorRun",
    "is_vector_run",
    "pair_vector_run",
    "read_test_start",
    "read_vector_run",
    "vector_message",
    "write_vector_run",
]


@dataclass(frozen=True)
class VectorRun:
    """A vector run's paired samples: ``u`` (N, n_u), ``y`` (N, n_y), channel names, 1-based test start."""

    u: np.ndarray
    y: np.ndarray
    u_names: tuple[str, ...]
    y_names: tuple[str, ...]
    test_start: int | None = None


def vector_message(values: Sequence[float], names: Sequence[str]):
    """One sample as a Float64MultiArray whose single dimension's label names the channels."""
    types = TYPESTORE.types
    dim = types["std_msgs/msg/MultiArrayDimension"](label=",".join(names), size=len(names), stride=len(names))
    layout = types["std_msgs/msg/MultiArrayLayout"](dim=[dim], data_offset=0)
    return types[topics.FLOAT64_ARRAY](layout=layout, data=np.ascontiguousarray(values, dtype=np.float64))


def write_vector_run(
    out_path: str | Path,
    u_rows: np.ndarray,
    y_rows: np.ndarray,
    names: tuple[Sequence[str], Sequence[str]],
    dt: float,
    test_from: int | None = None,
) -> Path:
    """/u and /y_p (rows: samples, columns: channels) stamped at k*dt, the latched /test_start first."""
    u_names, y_names = names
    out_path = Path(out_path)
    with BagWriter(out_path, flush_period=None) as bag:
        bag.add_topic("/" + topics.U, topics.FLOAT64_ARRAY)
        bag.add_topic("/" + topics.Y_P, topics.FLOAT64_ARRAY)
        if test_from is not None:
            bag.add_topic("/" + topics.TEST_START)
            bag.write_value("/" + topics.TEST_START, int(test_from), 0)
        for k, (u, y) in enumerate(zip(u_rows, y_rows, strict=True)):
            stamp = round(k * dt * 1e9)
            bag.write_message("/" + topics.U, vector_message(u, u_names), stamp)
            bag.write_message("/" + topics.Y_P, vector_message(y, y_names), stamp)
    return out_path


def is_vector_run(path: str | Path) -> bool:
    """Whether the bag's ``u`` topic holds Float64MultiArray samples (a MIMO run)."""
    available = topic_types(path)
    topic = find_topic(available, topics.U)
    return topic is not None and available[topic] == topics.FLOAT64_ARRAY


def read_vector_run(path: str | Path) -> VectorRun:
    """u and y_p of a vector run, paired by message order (as import-csv writes them), with their names."""
    path = Path(path)
    (_, u_rows), (_, y_rows), names, test_start = _read_channels(path)
    pairs = min(len(u_rows), len(y_rows))
    return VectorRun(u=u_rows[:pairs], y=y_rows[:pairs], u_names=names[0], y_names=names[1], test_start=test_start)


def _read_channels(path: Path) -> tuple[tuple[Series, np.ndarray], tuple[Series, np.ndarray], list, int | None]:
    """u and y_p as recorded ((series, rows) each), their channel names and the last test_start (None: none)."""
    available = topic_types(path)
    series, names = [], []
    for name, kind in ((topics.U, "u"), (topics.Y_P, "y")):
        topic = find_topic(available, name)
        if topic is None or available[topic] != topics.FLOAT64_ARRAY:
            found = f"type {available[topic]}" if topic else "missing"
            raise BagError(f"{path}: topic {name!r} is {found}; a vector run needs {topics.FLOAT64_ARRAY} on u and y_p")
        read = topic_series(path, topic)
        if read.values is None or not len(read.values):
            raise BagError(f"{path}: topic {topic!r} has no messages; record a run that publishes it")
        values = np.asarray(read.values, dtype=np.float64).reshape(len(read.values), -1)
        series.append((read, values))
        names.append(_labels(path, topic, values.shape[1], kind))
    return series[0], series[1], names, _test_start(path, available)


def read_test_start(path: str | Path) -> int | None:
    """The last ``test_start`` in a bag, whatever its u / y_p are (None: none recorded)."""
    path = Path(path)
    return _test_start(path, topic_types(path))


def _test_start(path: Path, available: dict[str, str]) -> int | None:
    start = find_topic(available, topics.TEST_START)
    starts = topic_series(path, start).values if start else None
    return int(starts[-1]) if starts is not None and len(starts) else None


def _labels(path: Path, topic: str, width: int, kind: str) -> tuple[str, ...]:
    """The channel names of the topic's first message; u0, u1... when its label does not name each channel."""
    first = next(iter_messages(path, [topic])).message
    dims = list(first.layout.dim)
    names = tuple(part.strip() for part in dims[0].label.split(",")) if dims else ()
    if len(names) != width or not all(names):
        return tuple(f"{kind}{i}" for i in range(width))
    return names


@dataclass(frozen=True)
class VectorPairs:
    """Sample k of a vector recording at row k, for replay: ``pairs`` (indices, streams, which halves the
    recording holds, times, as :func:`~lenn_ros.bag.run.pair_raw` gives them) and the vectors, NaN rows
    for a missing half."""

    pairs: RawPairs
    u: np.ndarray
    y_p: np.ndarray
    u_names: tuple[str, ...]
    y_names: tuple[str, ...]
    test_start: int | None
    source: str


def pair_vector_run(path: str | Path, use_samples: bool = True) -> VectorPairs:
    """The identifier's recorded samples (``use_samples`` and present), else u / y_p paired by sequence number.

    Pairing is :func:`~lenn_ros.bag.run.pair_raw`'s, done on row numbers and then
    gathered, so vectors are paired exactly as scalars are.
    """
    path = Path(path)
    (u_read, u_rows), (y_read, y_rows), names, test_start = _read_channels(path)
    recorded = read_samples(path, None, u_rows.shape[1], y_rows.shape[1]) if use_samples else None
    if recorded is not None and recorded.index.size:
        index, time, u_samples, y_samples, _learn = recorded.ordered()
        times = np.round(time * 1e9).astype(np.int64)
        rows = np.arange(len(index), dtype=np.float64)
        pairs = pair_raw(rows, rows, index, index, u_t=times, y_p_t=times, fill=True)
        u_rows, y_rows, source = (
            u_samples.reshape(len(index), -1),
            y_samples.reshape(len(index), -1),
            "the identifier's samples",
        )
    else:
        pairs = pair_raw(
            np.arange(len(u_rows), dtype=np.float64),
            np.arange(len(y_rows), dtype=np.float64),
            u_read.sequence,
            y_read.sequence,
            u_t=u_read.log_time_ns,
            y_p_t=y_read.log_time_ns,
            fill=True,
        )
        source = "u and y_p paired by " + ("order (no sequence numbers recorded)" if pairs.by_order else "sequence")
    return VectorPairs(
        pairs, _gather(u_rows, pairs.u), _gather(y_rows, pairs.y_p), names[0], names[1], test_start, source
    )


def _gather(rows: np.ndarray, picks: np.ndarray) -> np.ndarray:
    """Row ``picks[k]`` of ``rows`` for each k; a NaN pick (a half the recording lacks) is a NaN row."""
    out = np.full((len(picks), rows.shape[1]), np.nan)
    present = np.isfinite(picks)
    out[present] = rows[picks[present].astype(np.int64)]
    return out
