"""A run's numeric series (``u``, ``y_p``, ``y_hat``, ``error``, ``test_start``, ``samples``) as numpy arrays.

Both functions use the fast path of :mod:`lenn_ros.bag.scalars`. Topic lookup works under
a namespace: ``u`` finds ``/u`` or ``/id3/u`` (``namespace=`` picks one of several).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lenn_ros import topics
from lenn_ros.bag.errors import BagError
from lenn_ros.bag.reader import _types, find_topic, read_summary
from lenn_ros.bag.scalars import Series, read_series

__all__ = ["RunData", "SampleSeries", "read_run", "read_samples"]

_SPECS = {spec.name: spec for spec in topics.RUN_TOPICS}
_RUN_SERIES = (topics.U, topics.Y_P, topics.Y_HAT, topics.ERROR, topics.TEST_START)


@dataclass(frozen=True)
class RunData:
    """One run's series. Optional topics that the bag lacks are ``None``, never empty arrays.

    Values are in log-time order; ``*_t`` are log (receive) times in ns,
    ``*_publish_t`` DDS source timestamps in ns (0 if unknown), ``*_sequence`` DDS
    publication sequence numbers (0 if unknown; gaps are lost messages).
    """

    path: Path
    u: np.ndarray
    u_t: np.ndarray
    y_p: np.ndarray
    y_p_t: np.ndarray
    y_hat: np.ndarray | None = None
    y_hat_t: np.ndarray | None = None
    error: np.ndarray | None = None
    error_t: np.ndarray | None = None
    test_start: int | None = None
    topics: dict[str, str] = field(default_factory=dict)
    u_sequence: np.ndarray | None = None
    y_p_sequence: np.ndarray | None = None
    u_publish_t: np.ndarray | None = None
    y_p_publish_t: np.ndarray | None = None


def _check_type(path: Path, topic: str, name: str, available: dict[str, str]) -> None:
    expected = _SPECS[name].type_name if name in _SPECS else None
    if expected is not None and available[topic] != expected:
        raise BagError(
            f"{path}: topic {topic!r} has type {available[topic]}, expected {expected}; "
            "record it with lenn_ros's message types"
        )


def _read(path: Path, require: Sequence[str], namespace: str | None) -> tuple[dict[str, Series], dict[str, str]]:
    file, summary = read_summary(path)
    available = _types(summary)
    series: dict[str, Series] = {}
    found: dict[str, str] = {}
    for name in dict.fromkeys((*_RUN_SERIES, *require)):
        topic = find_topic(available, name, namespace)
        if topic is None:
            if name in require:
                listed = ", ".join(sorted(available)) or "none"
                raise BagError(f"{path}: required topic {name!r} is missing (topics in bag: {listed})")
            continue
        _check_type(path, topic, name, available)
        found[name] = topic
        series[name] = read_series(path, file, summary, topic)
        if name in require and not len(series[name].log_time_ns):
            raise BagError(f"{path}: topic {topic!r} has no messages; record a run that publishes it")
    return series, found


def read_run(
    path: str | Path,
    *,
    require: Sequence[str] = (topics.U, topics.Y_P),
    namespace: str | None = None,
) -> RunData:
    """Read a run's series; every way a bag can be unusable gives a one-line :class:`BagError`."""
    path = Path(path)
    series, found = _read(path, require, namespace)

    def get(name: str, attr: str, empty: bool = False) -> np.ndarray | None:
        if name in series:
            return getattr(series[name], attr)
        return (np.empty(0) if attr == "values" else np.empty(0, np.int64)) if empty else None

    starts = get(topics.TEST_START, "values")
    return RunData(
        path=path,
        u=get(topics.U, "values", True),
        u_t=get(topics.U, "log_time_ns", True),
        y_p=get(topics.Y_P, "values", True),
        y_p_t=get(topics.Y_P, "log_time_ns", True),
        y_hat=get(topics.Y_HAT, "values"),
        y_hat_t=get(topics.Y_HAT, "log_time_ns"),
        error=get(topics.ERROR, "values"),
        error_t=get(topics.ERROR, "log_time_ns"),
        test_start=int(starts[-1]) if starts is not None and len(starts) else None,
        topics=found,
        u_sequence=get(topics.U, "sequence"),
        y_p_sequence=get(topics.Y_P, "sequence"),
        u_publish_t=get(topics.U, "publish_time_ns"),
        y_p_publish_t=get(topics.Y_P, "publish_time_ns"),
    )


@dataclass(frozen=True)
class SampleSeries:
    """The identifier's ``samples`` topic: the pairs it formed, one row per sample (see topics.SAMPLES)."""

    index: np.ndarray  # int64, 1-based sample index
    time: np.ndarray  # seconds, the sample's time
    u: np.ndarray  # NaN for a refused sample
    y_p: np.ndarray
    learn: np.ndarray | None  # bool: learnt from (None in bags from before the flag existed)
    log_time_ns: np.ndarray
    topic: str


def read_samples(path: str | Path, namespace: str | None = None) -> SampleSeries | None:
    """The ``samples`` topic as arrays (columns ``topics.SAMPLE_LABELS``); None if the bag has none."""
    path = Path(path)
    file, summary = read_summary(path)
    available = _types(summary)
    topic = find_topic(available, topics.SAMPLES, namespace)
    if topic is None:
        return None
    _check_type(path, topic, topics.SAMPLES, available)
    series = read_series(path, file, summary, topic)
    values = series.values if series.values is not None and series.values.size else np.empty((0, 5))
    if values.ndim != 2 or values.shape[1] < 4:
        raise BagError(
            f"{path}: {topic!r} rows have {values.shape[-1]} values, expected {', '.join(topics.SAMPLE_LABELS)}"
        )
    return SampleSeries(
        index=values[:, 0].astype(np.int64),
        time=values[:, 1].copy(),
        u=values[:, 2].copy(),
        y_p=values[:, 3].copy(),
        learn=values[:, 4] != 0 if values.shape[1] > 4 else None,
        log_time_ns=series.log_time_ns,
        topic=topic,
    )
