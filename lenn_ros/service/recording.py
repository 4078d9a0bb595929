"""A recording to samples: every message of any rosbag2 bag, paired by the node's own session.

What the identifier node does live (a message's field read, its header stamp or arrival time taken,
the half screened, merged and paired by the session's pairing), :func:`pair_raw` does over a
recording, so a bag yields the samples the node would have formed, numbered as the node numbers
them (a publication sequence number, a grid point of the sample period, a pair of stamps). It is
the one pairing of raw topics: ``evaluate``, ``fit`` (a bag), ``replay`` and ``bag-info`` use it.

Offline is not live in three ways, and only these:

- nothing is held for readers and nothing is shed: there are no readers to wait for and all the
  time that is needed, so every pair the session forms is kept (:class:`PairSink`, numpy blocks,
  memory ~40 bytes a sample and channel);
- a message is read once, from any storage (MCAP through ``mcap``, with the MCAP fast path of
  :mod:`lenn_ros.bag.scalars` for numbers; sqlite3 through rosbags), the topics one after another
  into columns (:class:`Halves`, memory ~50 bytes a message), then offered in the order of
  arrival (log time) to the session, as live; pairing by sequence number, in each publisher run's
  index order (a message the recorder logged late still meets its partner);
- a recording without sequence numbers (an import, a sqlite3 bag) paired by ``sequence`` is paired
  by order, and only when both topics hold as many messages (else the error says why).

Whatever the session drops (a lone half, a grid point without a new measurement, an unreadable
field) it counts and says, as live.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros import topics
from lenn_ros.bag.reader import iter_messages, open_bag, read_summary, topic_counts, topic_types
from lenn_ros.bag.scalars import FLOAT64_ARRAY, SCALAR_TYPES, read_series
from lenn_ros.config import field_extractor, is_mimo, side_channels
from lenn_ros.core.alignment import Pair
from lenn_ros.core.fields import FieldError, parse_path, split_paths, stamp_seconds
from lenn_ros.core.pairing import U, sequence_streams
from lenn_ros.progress import progress as progress_bar
from lenn_ros.service import RecordingError
from lenn_ros.service.reading import input_bag_topics
from lenn_ros.session import Session

#: Messages read before a progress bar is worth drawing.
LONG_READ = 200_000


@dataclass(frozen=True)
class Halves:
    """One input topic's messages as the session is offered them: columns in log-time order.

    ``values`` is (n,) for one channel, (n, channels) for several; a message whose field could not be
    read is NaN with ``readable`` False (counted, never paired). ``stamp`` is the header stamp (s) where
    the message has one and the node would use it, else NaN (then the arrival time times it).
    """

    topic: str
    side: str  # "u" or "y"
    part: int  # which of the side's topics (0 for one)
    values: np.ndarray
    readable: np.ndarray
    stamp: np.ndarray
    received: np.ndarray  # log (receive) time, s
    sequence: np.ndarray  # DDS publication sequence number, 0 where unknown
    source: np.ndarray  # DDS publish time, s, NaN where unknown
    error: str = ""  # why the first unreadable message was

    @property
    def times(self) -> np.ndarray:
        """What times each half in the session: its stamp, else its arrival."""
        return np.where(np.isnan(self.stamp), self.received, self.stamp)


@dataclass(frozen=True)
class Samples:
    """A recording's samples: ``index`` (the node's numbering), ``time`` (s), ``u`` / ``y`` ((N,) or (N, channels)).

    ``source`` says what was paired and how; ``by_order``: paired by position (no sequence numbers).
    """

    index: np.ndarray
    time: np.ndarray
    u: np.ndarray
    y: np.ndarray
    source: str
    by_order: bool = False
    topics: tuple[str, ...] = ()  # the recorded topics read, u's first (empty: the identifier's samples)


class PairSink:
    """Every pair a session forms offline, in numpy blocks (a pair object per sample would take ~10x the memory)."""

    BLOCK = 65_536

    def __init__(self) -> None:
        self._pending: list[Pair] = []
        self._blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def __call__(self, pairs: list[Pair]) -> None:
        self._pending.extend(pairs)
        if len(self._pending) >= self.BLOCK:
            self._flush()

    def _flush(self) -> None:
        pairs, self._pending = self._pending, []
        if pairs:
            self._blocks.append(
                (
                    np.fromiter((p.index for p in pairs), np.int64, len(pairs)),
                    np.fromiter((p.time for p in pairs), np.float64, len(pairs)),
                    np.asarray([p.u for p in pairs], dtype=np.float64),
                    np.asarray([p.y for p in pairs], dtype=np.float64),
                )
            )

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(index, time, u, y) of every pair so far, in the order formed."""
        self._flush()
        if not self._blocks:
            return np.empty(0, np.int64), np.empty(0), np.empty(0), np.empty(0)
        return tuple(np.concatenate(column) for column in zip(*self._blocks, strict=True))  # type: ignore[return-value]


def _bulk_columns(field: str, type_name: str, vector: bool) -> list[int] | None:
    """The Float64MultiArray columns (or [0] for a number's ``data``) a field reads, where the MCAP fast path
    reads them exactly as the field path would; None where only the general reader can. ``vector``: the halves
    are vectors (a model of several channels reads each field as a list of paths)."""
    if type_name in SCALAR_TYPES:
        return [0] if field == "data" and not vector else None
    if type_name != FLOAT64_ARRAY or "[*]" in field:
        return None
    columns = []
    for path in split_paths(field):
        steps = parse_path(path)
        if len(steps) != 1 or steps[0].attribute != "data" or not isinstance(steps[0].index, int):
            return None
        columns.append(steps[0].index)
    return columns


def _fast_halves(path: Path, topic: str, side: str, part: int, columns: list[int], vector: bool) -> Halves | None:
    """A number topic's halves straight from the MCAP chunks (no message is deserialised); None: not possible."""
    found = open_bag(path)
    if found.single_mcap is None:
        return None
    file, summary = read_summary(path)
    series = read_series(path, file, summary, topic)
    values = series.values
    if values is None:
        return None
    if values.ndim == 2:
        if values.shape[1] <= max(columns):
            return None  # (the general reader says which messages lack the element)
        values = values[:, columns] if vector else values[:, columns[0]]
    n = len(series.log_time_ns)
    source = series.publish_time_ns * 1e-9
    return Halves(
        topic, side, part, np.asarray(values, dtype=np.float64), np.ones(n, bool), np.full(n, np.nan),
        series.log_time_ns * 1e-9, series.sequence, np.where(series.publish_time_ns > 0, source, np.nan),
    )  # fmt: skip


class _Columns:
    """One topic's halves as the general reader delivers its messages, read as the node reads them.

    Kept in typed arrays (8 bytes a number), not lists of Python objects: an hour of a 1 kHz driver is
    3.6 million messages, which as lists took a gigabyte.
    """

    def __init__(self, extract: Callable[[Any], Any], stamped: bool, width: int, vector: bool) -> None:
        self.extract, self.stamped, self.width, self.vector = extract, stamped, width, vector
        self.values = array("d")
        self.readable = array("b")
        self.stamp = array("d")
        self.received = array("q")
        self.sequence = array("q")
        self.source = array("q")
        self.error = ""
        self._nan = [math.nan] * width

    def add(self, message: Any) -> None:
        try:
            value = self.extract(message.message)
            readable = True
        except FieldError as error:
            value, readable = self._nan, False
            self.error = self.error or str(error)
        stamp = stamp_seconds(message.message) if self.stamped else None
        if self.vector:
            self.values.extend(value)
        else:
            self.values.append(value if readable else math.nan)
        self.readable.append(readable)
        self.stamp.append(math.nan if stamp is None else stamp)
        self.received.append(message.log_time_ns)
        self.sequence.append(message.sequence)
        self.source.append(message.publish_time_ns)

    def halves(self, topic: str, side: str, part: int) -> Halves:
        values = np.frombuffer(self.values, dtype=np.float64)
        values = values.reshape(len(self.received), self.width) if self.vector else values
        received = np.frombuffer(self.received, dtype=np.int64)
        order = np.argsort(received, kind="stable")  # (in log-time order within each file: keep ties as they came)
        source = np.frombuffer(self.source, dtype=np.int64)
        return Halves(
            topic, side, part, values[order], np.frombuffer(self.readable, dtype=np.int8)[order].astype(bool),
            np.frombuffer(self.stamp, dtype=np.float64)[order], received[order] * 1e-9,
            np.frombuffer(self.sequence, dtype=np.int64)[order], np.where(source > 0, source * 1e-9, np.nan)[order],
            self.error,
        )  # fmt: skip


def read_halves(path: str | Path, values: dict[str, Any], progress: bool = False) -> list[Halves]:
    """Every message of the inputs ``values`` name (topics, fields, stamps as the node uses them), as columns.

    Number topics of a one-file MCAP bag are read in bulk; the others are read message by message in
    one pass over the recording (a bar on stderr when ``progress`` and the read is long).
    """
    path = Path(path)
    types = topic_types(path)
    vector = is_mimo(values)  # (the one place: the halves are vectors for a model of several channels)
    inputs = input_bag_topics(path, types, values)
    width = {side: len(side_channels(values, side)[0]) for side in (U, "y")}
    found: dict[str, Halves] = {}
    slow: dict[str, tuple[str, int, _Columns]] = {}
    for side, part, topic in inputs:
        field = str(values[f"{side}_field"])
        columns = _bulk_columns(field, types[topic], vector)
        halves = _fast_halves(path, topic, side, part, columns, vector) if columns is not None else None
        if halves is not None:
            found[topic] = halves
            continue
        stamped = bool(values.get("use_header_stamp", True))
        channels = width[side] // max(1, _parts(values, side))
        slow[topic] = (side, part, _Columns(field_extractor(values, side), stamped, channels, vector))
    if slow:
        counts = topic_counts(path)
        total = sum(counts.get(topic, 0) for topic in slow)
        bar = progress_bar(total, progress and total >= LONG_READ, f"reading {path.name}", unit="msg")
        try:
            # in log-time order: mcap's file order decodes the whole file before its first message (memory
            # growing with the file); log-time order holds a chunk or two
            for message in iter_messages(path, list(slow), progress=bar.update):
                slow[message.topic][2].add(message)
        finally:
            bar.close()
        for topic, (side, part, columns) in slow.items():
            found[topic] = columns.halves(topic, side, part)
    return [found[topic] for _, _, topic in inputs]


def _parts(values: dict[str, Any], side: str) -> int:
    return max(1, len([t for t in values.get(f"{side}_topics", [""]) if str(t).strip()]))


def pair_raw(path: str | Path, session: Session, values: dict[str, Any], progress: bool = False) -> Samples:
    """The recording's inputs paired by ``session`` as the node would pair them; see the module docstring."""
    path = Path(path)
    halves = read_halves(path, values, progress)
    sequence = values["pairing"] == "sequence"
    by_order = sequence and not any(h.sequence.any() for h in halves)
    if by_order:
        counts = {side: sum(len(h.received) for h in halves if h.side == side) for side in (U, "y")}
        if counts[U] != counts["y"]:
            raise RecordingError(
                f"{path}: no sequence numbers recorded and u has {counts[U]} messages, y_p {counts['y']}: pairing "
                "by order would shift every later pair; record with lenn_ros's recorder (it stores indices), or "
                "pair by time: --pairing sample --sample-period T (or --pairing stamp)"
            )
    for h in halves:
        for received in h.received[~h.readable].tolist():
            session.unreadable(h.side, received, f"{h.side}_field {values[f'{h.side}_field']}", h.error)
    sink = PairSink()
    session.collect = sink
    _offer_all(session, halves, by_order, sequence and not by_order)
    session.flush()
    session.collect = None
    index, time, u, y = sink.arrays()
    how = "order (no sequence numbers recorded)" if by_order else values["pairing"]
    names = ", ".join(h.topic for h in halves)
    return Samples(index, time, u, y, f"{names} by {how}", by_order, tuple(h.topic for h in halves))


def _offer_all(session: Session, halves: list[Halves], by_order: bool, in_index_order: bool) -> None:
    """Every readable half to the session: in arrival order, or (sequence pairing) each publisher run's index order."""
    keep = [h.readable for h in halves]
    received = np.concatenate([h.received[k] for h, k in zip(halves, keep, strict=True)])
    which = np.concatenate([np.full(int(k.sum()), i) for i, k in enumerate(keep)])
    row = np.concatenate([np.flatnonzero(k) for k in keep])
    order = np.argsort(received, kind="stable")
    if by_order:
        sequence = np.zeros(received.size, np.int64)
        for side in (U, "y"):  # position among the side's messages in arrival order
            mine = order[np.isin(which[order], [i for i, h in enumerate(halves) if h.side == side])]
            sequence[mine] = np.arange(1, mine.size + 1)
    else:
        sequence = np.concatenate([h.sequence[k] for h, k in zip(halves, keep, strict=True)])
    if in_index_order:
        epoch = np.zeros(received.size, np.int64)
        for i in range(len(halves)):  # a publisher's restart (its numbers again from 1) begins a new run
            mine = order[which[order] == i]
            epoch[mine] = sequence_streams(sequence[mine])
        position = np.empty(received.size, np.int64)
        position[order] = np.arange(received.size)
        order = np.lexsort((position, sequence, epoch))
    offer = session.offer
    unknown = np.full(1, np.nan)  # by order: the publish times say nothing of pairs either
    columns = [(h.side, h.part, h.values, h.times, h.received, h.source) for h in halves]
    for i, r, s in zip(which[order].tolist(), row[order].tolist(), sequence[order].tolist(), strict=True):
        side, part, values, times, arrived, source = columns[i]
        published = source[r] if not by_order else unknown[0]
        offer(
            side,
            values[r],
            float(times[r]),
            received=float(arrived[r]),
            sequence=s or None,
            source_time=None if published != published else float(published),
            part=part,
        )


def recorded_samples(path: str | Path, n_u: int = 1, n_y: int = 1) -> tuple[np.ndarray, ...] | None:
    """The identifier's own ``samples`` (the pairs it formed live), sorted by index, a repeated index the first
    (as live): (index, time, u, y, learn); None where the bag holds none."""
    from lenn_ros.bag.run import read_samples

    samples = read_samples(path, None, n_u, n_y)
    if samples is None or samples.index.size == 0:
        return None
    return samples.ordered()


def raw_losses(path: str | Path) -> dict[str, int]:
    """Messages of u / y_p missing from the recording, from gaps in their sequence numbers."""
    from lenn_ros.bag.info import bag_info

    losses = {}
    for topic, entry in bag_info(path)["topics"].items():
        name = topic.rstrip("/").rsplit("/", 1)[-1]
        if name in (topics.U, topics.Y_P) and entry.get("missing"):
            losses[topic] = int(entry["missing"])
    return losses


def samples_summary(path: str | Path, flags: dict[str, Any], progress: bool = False) -> dict[str, Any]:
    """The samples the identifier would form from the topics ``flags`` name (``bag-info`` with topics named)."""
    from lenn_ros.core.runs import describe_gaps, missing

    read = read_recording(path, flags, progress=progress)
    index, values = read.samples.index, read.values
    counted = {key: value for key, value in read.session.all_counters().items() if value and key != "paired"}
    return {
        "source": read.samples.source,
        "count": int(index.size),
        "first": int(index[0]),
        "last": int(index[-1]),
        "missing": missing(index)[1],
        "gaps": describe_gaps(index, values["pairing"], float(values.get("sample_period") or 0.0)),
        "counters": counted,
    }


def format_samples(summary: dict[str, Any]) -> str:
    """``samples_summary`` as lines under the topics."""
    lines = [f"Samples:      {summary['count']} from {summary['source']}"]
    if summary["count"]:
        lines.append(f"  numbered {summary['first']}..{summary['last']} (the node's numbering: --test-from K is one)")
    lines += [f"  {line}" for line in summary["gaps"]]
    counted = ", ".join(f"{key} {value}" for key, value in summary["counters"].items())
    if counted:
        lines.append(f"  counted: {counted}")
    return "\n".join(lines)


@dataclass
class Reading:
    """A recording read: its samples, the node values they were formed by, and the session that formed them."""

    identifier: Any
    values: dict[str, Any]
    session: Session
    samples: Samples
    learn: np.ndarray | None = None  # the identifier's recorded learn flags (recorded samples only)


def labelled_names(path: str | Path, topic: str) -> list[str]:
    """The channel names a Float64MultiArray topic's first message labels (``import-csv``, the recorder), or []."""
    first = next(iter_messages(path, [topic]), None)
    dims = list(getattr(getattr(first.message, "layout", None), "dim", [])) if first is not None else []
    names = [part.strip() for part in dims[0].label.split(",")] if dims else []
    return names if names and all(names) and len(names) == int(dims[0].size) else []


def plain_values(path: str | Path, types: dict[str, str], values: dict[str, Any]) -> dict[str, Any]:
    """The node values for a bag of plain ``u`` / ``y_p`` (a simulator's, ``import-csv``'s) that nobody described:
    each side's type is the bag's; a Float64MultiArray side is read whole (``data[*]``), its channels named by the
    messages' layout labels."""
    from lenn_ros.bag.reader import find_topic

    values = dict(values)
    for side, name in ((U, topics.U), ("y", topics.Y_P)):
        topic = find_topic(types, name)
        if topic is None:
            continue
        values[f"{side}_type"] = types[topic]
        if types[topic] == topics.FLOAT64_ARRAY and values.get(f"{side}_field", "data") == "data":
            names = labelled_names(path, topic)
            values[f"{side}_field"] = "data[*]"
            values[f"{side}_names"] = names or [f"{side}{i}" for i in range(array_width(path, topic))]
    return values


def array_width(path: str | Path, topic: str) -> int:
    """Elements of a Float64MultiArray topic's first message (its channels, where no label names them)."""
    first = next(iter_messages(path, [topic]), None)
    return len(first.message.data) if first is not None else 1


def read_recording(
    path: str | Path,
    flags: dict[str, Any] | None = None,
    params: str | None = None,
    node: str = "/identifier",
    model: bool = False,
    recorded: bool = False,
    progress: bool = False,
    defaults: bool | None = None,
) -> Reading:
    """A recording's samples as the node forms them, and what formed them: the one way in for every command.

    What is read: ``flags`` (:mod:`~lenn_ros.service.reading`) over the params file (``node``'s sections), else
    over the identifier's recorded configuration, else over the node's defaults for a bag of plain ``u`` / ``y_p``
    or named topics. ``model``: the model of the params file or the recording (evaluate), else only how topics
    become samples (fit, replay, bag-info). ``recorded``: the identifier's own ``samples`` where the bag holds them
    and no topic is named (the pairs it formed live), else the raw topics paired by :func:`pair_raw`.
    ``defaults``: whether the node's defaults may stand in for a configuration nobody gave (default: where topics
    are named or the bag holds plain ``u`` / ``y_p``).
    """
    from lenn_ros.bag.reader import find_topic
    from lenn_ros.service.building import configuration, make_session
    from lenn_ros.service.reading import given, with_flags

    path = Path(path)
    types = topic_types(path)
    named = given(flags)
    plain = all(find_topic(types, name) is not None for name in (topics.U, topics.Y_P))

    def adjust(values: dict[str, Any]) -> dict[str, Any]:
        if plain and not params and find_topic(types, topics.IDENTIFIER_CONFIG) is None:
            values = plain_values(path, types, values)
        return with_flags(values, flags, types, path) if named else values

    allowed = named or plain if defaults is None else defaults
    identifier, values = configuration(path, params, node, model=model, adjust=adjust, defaults=allowed)
    session = make_session(identifier, values)
    if recorded and not named:
        found = recorded_samples(path, identifier.n_u, identifier.n_y)
        if found is not None:
            index, time, u, y, learn = found
            return Reading(identifier, values, session, Samples(index, time, u, y, "samples"), learn)
    samples = pair_raw(path, session, values, progress)
    if len(samples.index) == 0:
        raise RecordingError(f"{path}: no samples could be paired ({samples.source}); see the notices")
    return Reading(identifier, values, session, samples)


def numbered_rows(index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For a publisher of sample indices (replay): each sample at the row its index says, within its publisher run.

    Returns (row of each sample, run of each row): a restart of the numbering (an index not above the one before)
    begins a new run, and within a run the missing indices from 1 up get rows of their own (NaN when published),
    so the k-th message of a run is its sample k.
    """
    index = np.asarray(index, dtype=np.int64)
    restart = np.r_[True, np.diff(index) <= 0]
    run = np.cumsum(restart) - 1
    starts = np.flatnonzero(restart)
    highest = np.maximum.reduceat(index, starts) if index.size else np.empty(0, np.int64)
    offset = np.r_[0, np.cumsum(highest)[:-1]] if index.size else np.empty(0, np.int64)
    rows = offset[run] + index - 1
    total = int(highest.sum()) if index.size else 0
    runs = np.repeat(np.arange(len(starts)), highest) if index.size else np.empty(0, np.int64)
    assert runs.size == total
    return rows, runs
