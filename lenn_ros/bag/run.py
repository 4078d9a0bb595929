"""A run's numeric series (``u``, ``y_p``, ``y_hat``, ``error``, ``test_start``, ``samples``) as numpy arrays.

Both functions use the fast path of :mod:`lenn_ros.bag.scalars`. Topic lookup works under
a namespace: ``u`` finds ``/u`` or ``/id3/u`` (``namespace=`` picks one of several).

Pairing a recording's raw topics into samples is not done here: the one pairing, the node's
own session over any recording, is :func:`lenn_ros.service.recording.pair_raw`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lenn_ros import topics
from lenn_ros.bag.errors import BagError
from lenn_ros.bag.reader import find_topic, topic_types
from lenn_ros.bag.scalars import Series, topic_series

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
    available = topic_types(path)
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
        series[name] = topic_series(path, topic)
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
    """The identifier's ``samples`` topic: the pairs it formed, one row per sample (see topics.SAMPLES).

    One row layout for any number of channels: ``[index, time, u.., y_p.., learn]``; ``u`` and
    ``y_p`` are (N,) for one channel, (N, channels) for several.
    """

    index: np.ndarray  # int64, 1-based sample index
    time: np.ndarray  # seconds, the sample's time
    u: np.ndarray  # NaN for a refused sample
    y_p: np.ndarray
    learn: np.ndarray | None  # bool: learnt from (None in bags from before the flag existed)
    log_time_ns: np.ndarray
    topic: str

    def ordered(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(index, time, u, y_p, learn) sorted by index, a repeated index keeping its first row (as live)."""
        learn = self.learn if self.learn is not None else np.ones(self.index.size, dtype=bool)
        order = np.argsort(self.index, kind="stable")
        pick = order[np.r_[True, np.diff(self.index[order]) > 0]] if order.size else order
        return self.index[pick], self.time[pick], self.u[pick], self.y_p[pick], learn[pick]


def read_samples(path: str | Path, namespace: str | None = None, n_u: int = 1, n_y: int = 1) -> SampleSeries | None:
    """The ``samples`` topic as arrays, rows ``[index, time, u.., y_p.., learn]`` of a model of ``n_u`` inputs and
    ``n_y`` outputs; None if the bag has none. A width that does not fit is a BagError (another configuration
    recorded it); one channel each also reads rows without the learn flag (older bags)."""
    path = Path(path)
    available = topic_types(path)
    topic = find_topic(available, topics.SAMPLES, namespace)
    if topic is None:
        return None
    _check_type(path, topic, topics.SAMPLES, available)
    series = topic_series(path, topic)
    width = 3 + n_u + n_y
    values = series.values if series.values is not None and series.values.size else np.empty((0, width))
    values = np.asarray(values, dtype=np.float64)
    single = n_u == 1 and n_y == 1
    if values.ndim != 2 or not (values.shape[1] == width or (single and values.shape[1] == width - 1)):
        expected = ", ".join(topics.SAMPLE_LABELS) if single else f"{width} (index, time, u.., y_p.., learn)"
        raise BagError(
            f"{path}: {topic!r} rows have {values.shape[-1]} values, expected {expected} for a model of {n_u} "
            f"input(s) and {n_y} output(s): pass the --params it ran with"
        )
    u, y_p = values[:, 2 : 2 + n_u], values[:, 2 + n_u : 2 + n_u + n_y]
    return SampleSeries(
        index=values[:, 0].astype(np.int64),
        time=values[:, 1].copy(),
        u=u[:, 0].copy() if n_u == 1 else u.copy(),
        y_p=y_p[:, 0].copy() if n_y == 1 else y_p.copy(),
        learn=values[:, width - 1] != 0 if values.shape[1] == width else None,
        log_time_ns=series.log_time_ns,
        topic=topic,
    )
