"""Run recordings as rosbag2 bags with MCAP storage, without needing a ROS install.

Why rosbags and not rosbag2: the offline tools (``lenn-ros evaluate``, ``bag-info``,
``import-csv``) must run where only pip is available, and a bag written here must open
in ``ros2 bag info`` / Foxglove on a full ROS 2 install. rosbags writes exactly that
layout (``<dir>/metadata.yaml`` + ``<dir>/<dir>.mcap``) from plain Python.

Crash safety. rosbags' MCAP writer keeps the current chunk in memory and only writes it
when it exceeds 1 MiB; the schemas and channels live in that first chunk too, and the
summary + footer are written by ``close()``. A SIGKILLed recorder would therefore leave a
file holding only the magic and header. :class:`BagWriter` closes the pending chunk
itself and flushes the file to the kernel every ``flush_period`` seconds (checked on each
write and by :meth:`BagWriter.maybe_flush`, which the recorder calls from a timer) and
whenever the chunk reaches ``max_chunk_size`` bytes (values above 1 MiB act as 1 MiB,
rosbags' own limit). **Loss bound on SIGKILL**: only the messages written since the last
flush are lost, i.e. at most ``flush_period`` seconds (plus one timer period of latency)
and at most ``max_chunk_size`` bytes of messages. Flushing hands the bytes to the kernel,
which survives a killed process; ``fsync=True`` also survives a power cut. Such a file
has no footer and usually no metadata.yaml; :func:`recover` rebuilds a valid bag from
every complete record in it.
"""

from __future__ import annotations

import csv
import math
import mmap
import shutil
import struct
import sys
import time
import zlib
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, Writer
from rosbags.rosbag2.enums import StoragePlugin
from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos
from rosbags.typesys import Stores, get_typestore

from lenn_ros import topics

__all__ = [
    "BagError",
    "BagWriter",
    "RecoveryReport",
    "RunData",
    "bag_info",
    "default_qos",
    "import_csv",
    "qos_from_profile",
    "read_run",
    "recover",
]

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: rosbags closes a chunk by itself once it holds more than this many bytes.
ROSBAGS_CHUNK_LIMIT = 2**20
REPAIR_HINT = "run `lenn-ros bag-repair {path}` to rebuild it from its complete chunks"

_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_SPECS = {spec.name: spec for spec in topics.RUN_TOPICS}


class BagError(ValueError):
    """A bag that cannot be used, with a message that names the problem and the fix."""


# --------------------------------------------------------------------------- QoS


def _qos_time(duration: Any) -> QosTime:
    sec, nsec = divmod(int(getattr(duration, "nanoseconds", duration)), 1_000_000_000)
    return QosTime(sec, nsec)


def qos_from_profile(profile: Any) -> Qos:
    """Convert an rclpy ``QoSProfile`` (duck-typed, so rclpy is not imported) to rosbags' ``Qos``.

    Policies are matched by name because that is what both enums promise; an unknown name
    becomes UNKNOWN rather than an error, as rosbag2 does.
    """

    def pick(enum: Any, policy: Any) -> Any:
        name = getattr(policy, "name", str(policy)).upper()
        return enum.__members__.get(name, enum.UNKNOWN)

    return Qos(
        history=pick(QosHistory, profile.history),
        depth=int(profile.depth),
        reliability=pick(QosReliability, profile.reliability),
        durability=pick(QosDurability, profile.durability),
        deadline=_qos_time(profile.deadline),
        lifespan=_qos_time(profile.lifespan),
        liveliness=pick(QosLiveliness, profile.liveliness),
        liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def default_qos(spec: topics.TopicSpec) -> Qos:
    """The QoS our publishers offer on ``spec``, without importing rclpy.

    Mirrors ``topics.data_qos()`` / ``topics.latched_qos()`` (a test checks they agree)
    so that ``import-csv`` on a machine without ROS stores the same offered QoS as a
    live recording; ``ros2 bag play`` then re-offers a latched ``test_start``.
    """
    zero = QosTime(0, 0)
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=1 if spec.latched else topics.DATA_DEPTH,
        reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL if spec.latched else QosDurability.VOLATILE,
        deadline=zero,
        lifespan=zero,
        liveliness=QosLiveliness.SYSTEM_DEFAULT,
        liveliness_lease_duration=zero,
        avoid_ros_namespace_conventions=False,
    )


def _as_qos_list(qos: Any, spec: topics.TopicSpec | None) -> list[Qos]:
    if qos is None:
        return [default_qos(spec)] if spec is not None else []
    items = list(qos) if isinstance(qos, list | tuple) else [qos]
    return [q if isinstance(q, Qos) else qos_from_profile(q) for q in items]


def _spec_for(topic: str) -> topics.TopicSpec | None:
    return _SPECS.get(topic.rstrip("/").rsplit("/", 1)[-1])


# --------------------------------------------------------------------------- writing


class BagWriter:
    """Write a rosbag2/MCAP bag message by message, with a bounded loss if the process dies.

    Use as a context manager. Topics are added with :meth:`add_topic`; messages are raw
    CDR bytes (what an rclpy ``raw=True`` subscription hands over) or plain Python values
    for the std_msgs types of :mod:`lenn_ros.topics` (:meth:`write_value`).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        flush_period: float | None = 1.0,
        max_chunk_size: int = ROSBAGS_CHUNK_LIMIT,
        fsync: bool = False,
    ) -> None:
        if flush_period is not None and flush_period <= 0:
            raise ValueError(f"flush_period must be > 0 seconds or None, got {flush_period}")
        if max_chunk_size <= 0:
            raise ValueError(f"max_chunk_size must be > 0 bytes, got {max_chunk_size}")
        self.path = Path(path)
        self.flush_period = flush_period
        self.max_chunk_size = min(int(max_chunk_size), ROSBAGS_CHUNK_LIMIT)
        self.fsync = fsync
        self.counts: Counter[str] = Counter()
        #: Messages per topic that have reached the kernel (survive a SIGKILL).
        self.flushed_counts: Counter[str] = Counter()
        self._writer: Writer | None = None
        self._connections: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self._pending = 0
        self._last_flush = time.monotonic()

    # -- lifecycle
    def open(self) -> BagWriter:
        if self.path.exists():
            raise BagError(f"{self.path}: already exists; choose a new output path (bags are never overwritten)")
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        storage = self._writer.storage
        if not all(hasattr(storage, name) for name in ("chunk", "close_chunk", "bio")):
            self._writer.abort()
            raise BagError(
                "this rosbags version's MCAP writer has no chunk/close_chunk/bio, so bounded-loss flushing "
                "cannot work; install rosbags 0.11.x"
            )
        self._last_flush = time.monotonic()
        return self

    def close(self) -> None:
        """Write the last chunk, the summary, the footer and metadata.yaml."""
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        writer.close()
        self.flushed_counts = Counter(self.counts)

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    @property
    def mcap_path(self) -> Path:
        return self.path / f"{self.path.name}.mcap"

    # -- topics and messages
    def add_topic(self, topic: str, type_name: str | None = None, qos: Any = None) -> None:
        """Register ``topic``; type and QoS default to those of :mod:`lenn_ros.topics`.

        ``qos`` may be an rclpy ``QoSProfile``, a rosbags ``Qos`` or a list of them (one per
        publisher, as rosbag2 stores it).
        """
        writer = self._require_open()
        spec = _spec_for(topic)
        if type_name is None:
            if spec is None:
                raise BagError(f"topic {topic!r}: type unknown; pass type_name (e.g. {topics.FLOAT64!r})")
            type_name = spec.type_name
        if topic in self._connections:
            raise BagError(f"topic {topic!r} added twice to {self.path}")
        self._connections[topic] = writer.add_connection(
            topic,
            type_name,
            typestore=_TYPESTORE,
            serialization_format="cdr",
            offered_qos_profiles=_as_qos_list(qos, spec),
        )
        self._types[topic] = type_name

    def write_raw(self, topic: str, data: bytes | memoryview, timestamp_ns: int) -> None:
        """Append one CDR-serialised message with log time ``timestamp_ns``."""
        writer = self._require_open()
        try:
            connection = self._connections[topic]
        except KeyError:
            raise BagError(f"topic {topic!r} was not added to {self.path}; call add_topic first") from None
        writer.write(connection, int(timestamp_ns), data)
        self.counts[topic] += 1
        self._pending += 1
        self.maybe_flush()

    def write_value(self, topic: str, value: float | int | str, timestamp_ns: int) -> None:
        """Serialise a plain value as the topic's std_msgs type (Float64 / Int64 / String)."""
        type_name = self._types.get(topic)
        if type_name is None:
            raise BagError(f"topic {topic!r} was not added to {self.path}; call add_topic first")
        cls = _TYPESTORE.types[type_name]
        cast = {topics.FLOAT64: float, topics.INT64: int, topics.STRING: str}.get(type_name)
        if cast is None:
            raise BagError(f"topic {topic!r}: write_value handles Float64/Int64/String, not {type_name}")
        self.write_raw(topic, _TYPESTORE.serialize_cdr(cls(data=cast(value)), type_name), timestamp_ns)

    # -- durability
    def maybe_flush(self, now: float | None = None) -> bool:
        """Flush if the chunk is big enough or the flush period has passed; True if it flushed."""
        if not self._pending:
            return False
        now = time.monotonic() if now is None else now
        due = self.flush_period is not None and now - self._last_flush >= self.flush_period
        if due or self._chunk_bytes() >= self.max_chunk_size:
            self.flush()
            return True
        return False

    def flush(self) -> None:
        """Close the pending chunk and hand the file's bytes to the kernel (see module doc)."""
        writer = self._require_open()
        storage = writer.storage
        if storage is not None:
            if self._pending and self._chunk_bytes() > 0:
                storage.close_chunk()  # type: ignore[attr-defined]
            storage.bio.flush()  # type: ignore[attr-defined]
            if self.fsync:
                import os

                os.fsync(storage.bio.fileno())  # type: ignore[attr-defined]
        self._pending = 0
        self._last_flush = time.monotonic()
        self.flushed_counts = Counter(self.counts)

    def _chunk_bytes(self) -> int:
        # rosbags' McapWriter keeps the open chunk in ``storage.chunk.bio`` (checked by the tests).
        storage = self._writer.storage if self._writer else None
        chunk = getattr(storage, "chunk", None)
        return chunk.bio.tell() if chunk is not None else 0

    def _require_open(self) -> Writer:
        if self._writer is None:
            raise BagError(f"{self.path}: bag is not open; use `with BagWriter(path) as bag:`")
        return self._writer


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class RunData:
    """One run's series. Optional topics that the bag lacks are ``None``, never empty arrays.

    Values are in log-time order (rosbags' order), times are log timestamps in ns.
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


def _check_mcap_file(file: Path, shown: Path, context: str = "") -> None:
    """Fail early, with the fix, on files rosbags would only report as 'invalid magic'."""
    try:
        with file.open("rb") as f:
            head = f.read(len(MCAP_MAGIC))
            size = f.seek(0, 2)
            f.seek(max(0, size - len(MCAP_MAGIC)))
            tail = f.read()
    except OSError as err:
        raise BagError(f"{file}: cannot read ({err.strerror}); check the path and its permissions") from None
    if head != MCAP_MAGIC:
        raise BagError(f"{file}: not an MCAP file (wrong magic bytes); pass a rosbag2 directory recorded with MCAP")
    if size < len(MCAP_MAGIC) + 37 or tail != MCAP_MAGIC:
        raise BagError(
            f"{file}: {context}truncated MCAP file (no footer; the recorder was probably killed); "
            + REPAIR_HINT.format(path=shown)
        )


def _open_target(path: Path) -> Path:
    """The path to hand to rosbags' Reader: the bag directory, or its .mcap if metadata is gone."""
    if not path.exists():
        raise BagError(f"{path}: no such file or directory; pass a bag directory made by `recorder` or `import-csv`")
    if path.is_file():
        if path.suffix != ".mcap":
            raise BagError(f"{path}: not a rosbag2 bag; pass the bag directory (with metadata.yaml) or its .mcap file")
        _check_mcap_file(path, path)
        return path
    mcaps = sorted(path.glob("*.mcap"))
    if not (path / "metadata.yaml").exists():
        if not mcaps:
            raise BagError(
                f"{path}: not a rosbag2 bag (no metadata.yaml, no .mcap file); pass the bag directory itself"
            )
        if len(mcaps) > 1:
            raise BagError(f"{path}: metadata.yaml missing and several .mcap files; " + REPAIR_HINT.format(path=path))
        _check_mcap_file(mcaps[0], path, context="no metadata.yaml next to it and ")
        return mcaps[0]
    for mcap_file in mcaps:
        _check_mcap_file(mcap_file, path)
    return path


def _find_topic(available: dict[str, str], name: str, namespace: str | None) -> str | None:
    if namespace is not None:
        wanted = namespace.rstrip("/") + "/" + name
        return wanted if wanted in available else None
    matches = [t for t in available if t.rstrip("/").rsplit("/", 1)[-1] == name]
    if len(matches) > 1:
        if "/" + name in matches:
            return "/" + name
        raise BagError(f"several topics end in {name!r}: {', '.join(sorted(matches))}; pass namespace= to choose one")
    return matches[0] if matches else None


def read_run(
    path: str | Path,
    *,
    require: Sequence[str] = (topics.U, topics.Y_P),
    namespace: str | None = None,
) -> RunData:
    """Read a run's series; every way a bag can be unusable gives a one-line :class:`BagError`."""
    path = Path(path)
    target = _open_target(path)
    series: dict[str, tuple[list[Any], list[int]]] = {}
    try:
        with Reader(target) as reader:
            available = {c.topic: c.msgtype for c in reader.connections}
            wanted = {topics.U, topics.Y_P, topics.Y_HAT, topics.ERROR, topics.TEST_START} | set(require)
            found: dict[str, str] = {}
            for name in wanted:
                topic = _find_topic(available, name, namespace)
                if topic is None:
                    if name in require:
                        listed = ", ".join(sorted(available)) or "none"
                        raise BagError(f"{path}: required topic {name!r} is missing (topics in bag: {listed})")
                    continue
                expected = _SPECS[name].type_name if name in _SPECS else None
                if expected is not None and available[topic] != expected:
                    raise BagError(
                        f"{path}: topic {topic!r} has type {available[topic]}, expected {expected}; "
                        "record it with lenn_ros's message types"
                    )
                found[name] = topic
            by_topic = {topic: name for name, topic in found.items()}
            conns = [c for c in reader.connections if c.topic in by_topic]
            for name in found:
                series[name] = ([], [])
            for conn, timestamp, raw in reader.messages(connections=conns):
                name = by_topic[conn.topic]
                series[name][0].append(_TYPESTORE.deserialize_cdr(raw, conn.msgtype).data)
                series[name][1].append(timestamp)
    except BagError:
        raise
    except Exception as err:  # rosbags raises several unrelated types for damaged files
        raise BagError(f"{path}: corrupt or unreadable bag ({err}); " + REPAIR_HINT.format(path=path)) from None
    for name in require:
        if not series[name][0]:
            raise BagError(f"{path}: topic {found[name]!r} has no messages; record a run that publishes it")

    def arrays(name: str) -> tuple[np.ndarray | None, np.ndarray | None]:
        if name not in series:
            return None, None
        values, times = series[name]
        return np.asarray(values, dtype=np.float64), np.asarray(times, dtype=np.int64)

    u, u_t = arrays(topics.U)
    y_p, y_p_t = arrays(topics.Y_P)
    y_hat, y_hat_t = arrays(topics.Y_HAT)
    error, error_t = arrays(topics.ERROR)
    starts = series.get(topics.TEST_START, ([], []))[0]
    return RunData(
        path=path,
        u=u if u is not None else np.empty(0),
        u_t=u_t if u_t is not None else np.empty(0, np.int64),
        y_p=y_p if y_p is not None else np.empty(0),
        y_p_t=y_p_t if y_p_t is not None else np.empty(0, np.int64),
        y_hat=y_hat,
        y_hat_t=y_hat_t,
        error=error,
        error_t=error_t,
        test_start=int(starts[-1]) if starts else None,
        topics=found,
    )


def bag_info(path: str | Path) -> dict[str, Any]:
    """Summary for ``lenn-ros bag-info``: topics with type, count and offered QoS, duration, storage."""
    path = Path(path)
    target = _open_target(path)
    try:
        with Reader(target) as reader:
            counts: Counter[str] = Counter()
            types: dict[str, str] = {}
            qos: dict[str, list[Any]] = {}
            for conn in reader.connections:
                counts[conn.topic] += conn.msgcount
                types[conn.topic] = conn.msgtype
                qos.setdefault(conn.topic, []).extend(dump_qos_v9(list(getattr(conn.ext, "offered_qos_profiles", []))))
            total = reader.message_count
            start = reader.start_time if total else None
            end = reader.end_time if total else None
    except Exception as err:
        raise BagError(f"{path}: corrupt or unreadable bag ({err}); " + REPAIR_HINT.format(path=path)) from None
    return {
        "path": str(path),
        "storage": "mcap" if target.suffix == ".mcap" or any(path.glob("*.mcap")) else "sqlite3",
        "message_count": total,
        "start_ns": start,
        "end_ns": end,
        "duration_s": (end - start) / 1e9 if total else 0.0,
        "topics": {t: {"type": types[t], "count": counts[t], "offered_qos": qos[t]} for t in sorted(types)},
    }


# --------------------------------------------------------------------------- recovery


@dataclass
class _Channel:
    topic: str
    schema_id: int
    encoding: str
    metadata: dict[str, str]


@dataclass
class _Scan:
    """Everything usable in an MCAP file, read record by record (no summary needed)."""

    schemas: dict[int, tuple[str, str, str]] = field(default_factory=dict)  # id -> (name, encoding, text)
    channels: dict[int, _Channel] = field(default_factory=dict)
    messages: list[tuple[int, int, bytes]] = field(default_factory=list)  # (channel id, log time, data)
    complete: bool = False
    stop_reason: str = ""
    bytes_used: int = 0
    file_size: int = 0


def _string(buf: memoryview, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    return bytes(buf[pos + 4 : pos + 4 + n]).decode(), pos + 4 + n


def _decompress(data: bytes, compression: str, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        if sys.version_info >= (3, 14):
            from compression import zstd
        else:
            from backports import zstd
        return zstd.decompress(data)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise BagError(f"unsupported MCAP chunk compression {compression!r}")


def _scan_records(buf: memoryview, pos: int, end: int, scan: _Scan, inside_chunk: bool) -> int:
    """Parse records from ``pos``; returns where parsing stopped (end, or a record that does not fit)."""
    while pos + 9 <= end:
        op = buf[pos]
        (length,) = struct.unpack_from("<Q", buf, pos + 1)
        body, nxt = pos + 9, pos + 9 + length
        if nxt > end:
            if op == 0x06 and not inside_chunk:
                _salvage_chunk(buf, body, end, scan)
            scan.stop_reason = f"record at byte {pos} is cut off (needs {length} bytes, {end - body} present)"
            return pos
        if op == 0x03:  # Schema
            (sid,) = struct.unpack_from("<H", buf, body)
            name, p = _string(buf, body + 2)
            enc, p = _string(buf, p)
            (n,) = struct.unpack_from("<I", buf, p)
            scan.schemas[sid] = (name, enc, bytes(buf[p + 4 : p + 4 + n]).decode())
        elif op == 0x04:  # Channel
            cid, sid = struct.unpack_from("<HH", buf, body)
            topic, p = _string(buf, body + 4)
            enc, p = _string(buf, p)
            (n,) = struct.unpack_from("<I", buf, p)
            meta, p, stop = {}, p + 4, p + 4 + n
            while p < stop:
                key, p = _string(buf, p)
                meta[key], p = _string(buf, p)
            scan.channels[cid] = _Channel(topic, sid, enc, meta)
        elif op == 0x05:  # Message
            cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", buf, body)
            scan.messages.append((cid, log_time, bytes(buf[body + 22 : nxt])))
        elif op == 0x06 and not inside_chunk:  # Chunk
            if not _read_chunk(buf, body, nxt, scan):
                return pos
        elif op == 0x02 and not inside_chunk:  # Footer
            scan.complete = buf[nxt : nxt + len(MCAP_MAGIC)] == MCAP_MAGIC
            return nxt + len(MCAP_MAGIC)
        pos = nxt
    if pos < end:
        scan.stop_reason = f"{end - pos} trailing bytes at byte {pos} are not a whole record"
    return pos


def _chunk_header(buf: memoryview, body: int) -> tuple[int, int, str, int, int]:
    usize, crc = struct.unpack_from("<QI", buf, body + 16)
    compression, p = _string(buf, body + 28)
    (clen,) = struct.unpack_from("<Q", buf, p)
    return usize, crc, compression, p + 8, clen


def _read_chunk(buf: memoryview, body: int, end: int, scan: _Scan) -> bool:
    try:
        usize, crc, compression, start, clen = _chunk_header(buf, body)
        data = _decompress(bytes(buf[start : min(start + clen, end)]), compression, usize)
    except Exception as err:  # any decoding failure means the chunk is unusable
        scan.stop_reason = f"chunk at byte {body - 9} is corrupt ({err})"
        return False
    if len(data) != usize or (crc and zlib.crc32(data) != crc):
        scan.stop_reason = f"chunk at byte {body - 9} fails its size/CRC check"
        return False
    inner = memoryview(data)
    _scan_records(inner, 0, len(inner), scan, inside_chunk=True)
    return True


def _salvage_chunk(buf: memoryview, body: int, end: int, scan: _Scan) -> None:
    """Take the whole records of a cut-off, uncompressed chunk (the one being written at the kill)."""
    try:
        _usize, _crc, compression, start, _clen = _chunk_header(buf, body)
    except (struct.error, UnicodeDecodeError):
        return
    if compression == "" and start < end:
        _scan_records(buf, start, end, scan, inside_chunk=True)


def _scan_mcap(file: Path) -> _Scan:
    scan = _Scan()
    with file.open("rb") as f:
        size = f.seek(0, 2)
        scan.file_size = size
        if size < len(MCAP_MAGIC):
            raise BagError(f"{file}: empty or not an MCAP file; nothing to recover")
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            buf = memoryview(mm)
            try:
                if bytes(buf[: len(MCAP_MAGIC)]) != MCAP_MAGIC:
                    raise BagError(f"{file}: not an MCAP file (wrong magic bytes); nothing to recover")
                try:
                    scan.bytes_used = _scan_records(buf, len(MCAP_MAGIC), size, scan, inside_chunk=False)
                except (struct.error, UnicodeDecodeError) as err:
                    scan.stop_reason = f"malformed record ({err})"
            finally:
                buf.release()
    return scan


@dataclass(frozen=True)
class RecoveryReport:
    """What :func:`recover` found and wrote."""

    path: Path  # the valid bag directory now holding the recovered messages
    source: Path  # the damaged .mcap (kept, renamed to *.damaged when repaired in place)
    messages: dict[str, int]
    was_complete: bool
    stop_reason: str
    bytes_used: int
    file_size: int

    @property
    def total(self) -> int:
        return sum(self.messages.values())

    def __str__(self) -> str:
        counts = ", ".join(f"{t}: {n}" for t, n in self.messages.items()) or "no messages"
        status = "file was complete" if self.was_complete else f"stopped: {self.stop_reason or 'end of file'}"
        return f"recovered {self.total} messages ({counts}) into {self.path}; {status}; source kept at {self.source}"


def _locate_mcap(path: Path) -> tuple[Path, Path]:
    if not path.exists():
        raise BagError(f"{path}: no such file or directory; pass the bag directory or its .mcap file")
    if path.is_file():
        if path.suffix != ".mcap":
            raise BagError(f"{path}: not an .mcap file; bag-repair handles MCAP storage only")
        return path.parent, path
    mcaps = sorted(path.glob("*.mcap"))
    if len(mcaps) != 1:
        found = "no" if not mcaps else f"{len(mcaps)}"
        raise BagError(f"{path}: {found} .mcap files in the directory; pass the .mcap file to repair")
    return path, mcaps[0]


def recover(path: str | Path, out: str | Path | None = None) -> RecoveryReport:
    """Rebuild a valid bag from what a killed recorder left: every whole record of the MCAP file.

    With ``out=None`` the bag directory is repaired in place: the damaged file is kept as
    ``<name>.mcap.damaged`` (nothing is ever deleted) and a new ``<dir>.mcap`` plus
    metadata.yaml take its place. Otherwise a new bag is written at ``out``.
    """
    bag_dir, source = _locate_mcap(Path(path))
    scan = _scan_mcap(source)
    usable = [m for m in scan.messages if m[0] in scan.channels]
    if not scan.channels:
        raise BagError(
            f"{source}: no complete chunk in the file (the recorder was killed before its first flush); "
            "nothing to recover — record again, with a shorter flush_period if needed"
        )
    final = Path(out) if out is not None else bag_dir
    staging = final if out is not None else bag_dir.parent / f".{bag_dir.name}.repair" / bag_dir.name
    if out is None and staging.parent.exists():
        shutil.rmtree(staging.parent)
    messages: Counter[str] = Counter()
    try:
        writer = Writer(staging, version=9, storage_plugin=StoragePlugin.MCAP)
    except Exception as err:
        raise BagError(f"{staging}: cannot create the repaired bag ({err}); choose another output path") from None
    writer.open()
    try:
        conns = {}
        for cid, chan in sorted(scan.channels.items()):
            name, _enc, text = scan.schemas.get(chan.schema_id, ("", "", ""))
            qos = parse_qos(chan.metadata.get("offered_qos_profiles", ""))
            kwargs: dict[str, Any] = {"typestore": _TYPESTORE}
            if name not in _TYPESTORE.types:
                kwargs = {"msgdef": text, "rihs01": "RIHS01_" + "0" * 64}
            conns[cid] = writer.add_connection(chan.topic, name, offered_qos_profiles=qos, **kwargs)
        for cid, log_time, data in usable:
            writer.write(conns[cid], log_time, data)
            messages[scan.channels[cid].topic] += 1
    except BaseException:
        writer.abort()
        raise
    writer.close()
    kept = source
    if out is None:
        kept = source.with_name(source.name + ".damaged")
        if kept.exists():
            kept = source.with_name(f"{source.name}.damaged-{time.time_ns()}")
        source.rename(kept)
        meta = bag_dir / "metadata.yaml"
        if meta.exists():
            meta.rename(kept.with_name(kept.name.replace(".mcap", ".metadata.yaml")))
        for item in staging.iterdir():
            item.rename(bag_dir / item.name)
        shutil.rmtree(staging.parent)
    return RecoveryReport(
        path=final,
        source=kept,
        messages={chan.topic: messages[chan.topic] for _cid, chan in sorted(scan.channels.items())},
        was_complete=scan.complete,
        stop_reason=scan.stop_reason,
        bytes_used=scan.bytes_used,
        file_size=scan.file_size,
    )


# --------------------------------------------------------------------------- CSV import


def _column_index(header: list[str] | None, column: str | int, csv_path: Path) -> int:
    if isinstance(column, int) or (header is None and str(column).isdigit()):
        index = int(column)
    elif header is not None and column in header:
        return header.index(column)
    elif header is not None and str(column).isdigit():
        index = int(column)
    else:
        shown = ", ".join(header) if header else "no header row"
        raise BagError(f"{csv_path}: no column {column!r} (columns: {shown}); pass a column name or 0-based index")
    width = len(header) if header is not None else None
    if index < 0 or (width is not None and index >= width):
        raise BagError(f"{csv_path}: column index {index} out of range (0..{(width or 1) - 1})")
    return index


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def import_csv(
    csv_path: str | Path,
    u_column: str | int,
    y_column: str | int,
    dt: float,
    out_path: str | Path,
    test_from: int | None = None,
) -> Path:
    """Make a run bag (``/u``, ``/y_p`` at log time k*dt, optional latched ``/test_start``) from logged data.

    ``test_from`` is 1-based, like ``test_start`` on the live graph (the publication
    sequence number of the first test sample, i.e. row k of the data is sample k + 1).
    Columns are names or 0-based indices (a digit string counts as an index unless the
    header has a column of that name). The first row is a header when its cells are not
    all numbers. Errors name the file line, so a user can fix the CSV instead of guessing.
    """
    csv_path, out_path = Path(csv_path), Path(out_path)
    if not (dt > 0 and math.isfinite(dt)):
        raise BagError(f"dt must be a positive number of seconds, got {dt}")
    if not csv_path.is_file():
        raise BagError(f"{csv_path}: no such file; pass the CSV with the logged input and output")
    text = csv_path.read_text(encoding="utf-8-sig")
    try:
        dialect: Any = csv.Sniffer().sniff(text[:4096], delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    rows = [(n, row) for n, row in enumerate(csv.reader(text.splitlines(), dialect), start=1) if any(row)]
    if not rows:
        raise BagError(f"{csv_path}: the file has no rows")
    first = [cell.strip() for cell in rows[0][1]]
    named = any(isinstance(c, str) and not c.isdigit() for c in (u_column, y_column))
    has_header = named or not all(_is_number(c) for c in first if c)
    header = first if has_header else None
    iu = _column_index(header, u_column, csv_path)
    iy = _column_index(header, y_column, csv_path)
    data = rows[1:] if has_header else rows
    u_vals: list[float] = []
    y_vals: list[float] = []
    for line, row in data:
        for index, column, values in ((iu, u_column, u_vals), (iy, y_column, y_vals)):
            if index >= len(row):
                raise BagError(f"{csv_path}: line {line} has {len(row)} cells, no column {column!r}; fix that row")
            cell = row[index].strip()
            try:
                value = float(cell)
            except ValueError:
                raise BagError(f"{csv_path}: line {line}, column {column!r}: {cell!r} is not a number") from None
            if not math.isfinite(value):
                raise BagError(f"{csv_path}: line {line}, column {column!r}: {cell!r} is not finite")
            values.append(value)
    if not u_vals:
        raise BagError(f"{csv_path}: no data rows after the header")
    if test_from is not None and not 1 <= test_from <= len(u_vals):
        raise BagError(
            f"test_from={test_from} is outside samples 1..{len(u_vals)} of {csv_path} (1-based, like test_start)"
        )
    with BagWriter(out_path, flush_period=None) as bag:
        bag.add_topic("/" + topics.U)
        bag.add_topic("/" + topics.Y_P)
        if test_from is not None:
            bag.add_topic("/" + topics.TEST_START)
            bag.write_value("/" + topics.TEST_START, int(test_from), 0)
        for k, (u, y) in enumerate(zip(u_vals, y_vals, strict=True)):
            stamp = round(k * dt * 1e9)
            bag.write_value("/" + topics.U, u, stamp)
            bag.write_value("/" + topics.Y_P, y, stamp)
    return out_path
