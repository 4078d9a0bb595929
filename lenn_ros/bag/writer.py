"""Write rosbag2 bags (``<dir>/metadata.yaml`` + ``<dir>/<dir>.mcap``) through the public ``mcap`` writer.

Why not rosbag2: it is not pip-installable, and a bag written here must open in
``ros2 bag info`` / Foxglove on a full install as well as in rosbags and ``mcap_ros2``.
The file is what rosbag2's MCAP plugin writes: profile ``ros2``, one ``ros2msg``
schema per type (full definition text), ``cdr`` channels whose metadata holds
``offered_qos_profiles`` (and ``topic_type_hash``), a ``rosbag2`` metadata record, and
per message ``log_time`` = receive time, ``publish_time`` = DDS source timestamp,
``sequence`` = DDS publication sequence number mod 2**32 (0 when unknown).

Crash safety: the choice. ``mcap.writer.Writer`` offers three things: chunked or
unchunked output, the chunk size, and ``Writer.flush()`` (public since mcap 1.6), which
closes the open chunk and flushes the stream. We write **chunked, uncompressed**
chunks and call ``flush()`` every ``flush_period`` seconds (on each write and from
:meth:`BagWriter.maybe_flush`, which the recorder calls from a timer) and whenever the
messages since the last flush reach ``max_chunk_size`` bytes. Why not unchunked: it
would survive a kill equally well but leaves no message index, which readers (and our
fast numpy path, see :mod:`lenn_ros.bag.scalars`) use to find a topic's messages
without walking every record. Why uncompressed: a chunk cut short by a kill can still
be salvaged message by message (``bag-repair``); Float64 records barely compress.

**Loss bound on SIGKILL**: the messages written since the last flush, i.e. at most
``flush_period`` seconds (plus one timer period) and ``max_chunk_size`` bytes of them.
Flushing hands the bytes to the kernel, which survives a killed process; ``fsync=True``
also survives a power cut. Such a file has no summary, footer or metadata.yaml;
:func:`lenn_ros.bag.recover` rebuilds a valid bag from every complete message in it.
What DDS still held and the recorder had not taken is lost as well: see the recorder.
"""

from __future__ import annotations

import os
import time
from collections import Counter
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import mcap
import yaml
from mcap.writer import CompressionType, Writer

from lenn_ros import topics
from lenn_ros.bag import msgtypes
from lenn_ros.bag.errors import BagError
from lenn_ros.bag.qos import as_qos_list, dump_qos, qos_yaml

#: Default chunk size bound (rosbag2's MCAP default is 768 KiB; rosbags used 1 MiB).
DEFAULT_CHUNK_SIZE = 2**20
#: rmw reports this (or 0) when the middleware has no publication sequence numbers.
SEQUENCE_UNSUPPORTED = 2**64 - 1
_SPECS = {spec.name: spec for spec in topics.RUN_TOPICS}
_MESSAGE_OVERHEAD = 9 + 22  # MCAP message record: opcode + length, then channel/sequence/log/publish time


def spec_for(topic: str) -> topics.TopicSpec | None:
    """The package's topic spec for a recorded name (``/ns/u`` -> ``u``), if it is one of ours."""
    return _SPECS.get(topic.rstrip("/").rsplit("/", 1)[-1])


def mcap_sequence(sequence: int) -> int:
    """The MCAP ``sequence`` field for a DDS publication sequence number (0 = unknown)."""
    sequence = int(sequence)
    return 0 if sequence in (0, SEQUENCE_UNSUPPORTED) or sequence < 0 else sequence % 2**32


class BagWriter:
    """Write a rosbag2/MCAP bag message by message, with a bounded loss if the process dies.

    Use as a context manager. Topics are added with :meth:`add_topic` (any time, also
    after messages were written); messages are raw CDR bytes (what an rclpy ``raw=True``
    subscription hands over, :meth:`write_raw`), plain values for the std_msgs scalar
    types (:meth:`write_value`), or message objects (:meth:`write_message`).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        flush_period: float | None = 1.0,
        max_chunk_size: int = DEFAULT_CHUNK_SIZE,
        fsync: bool = False,
    ) -> None:
        if flush_period is not None and flush_period <= 0:
            raise ValueError(f"flush_period must be > 0 seconds or None, got {flush_period}")
        if max_chunk_size <= 0:
            raise ValueError(f"max_chunk_size must be > 0 bytes, got {max_chunk_size}")
        self.path = Path(path)
        self.flush_period = flush_period
        self.max_chunk_size = int(max_chunk_size)
        self.fsync = fsync
        self.counts: Counter[str] = Counter()
        #: Messages per topic that have reached the kernel (survive a SIGKILL).
        self.flushed_counts: Counter[str] = Counter()
        self._file: IO[bytes] | None = None
        self._mcap: Writer | None = None
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, dict[str, Any]] = {}  # topic -> metadata.yaml entry
        self._pending_bytes = 0
        self._pending = 0
        self._last_flush = time.monotonic()
        self._start_ns: int | None = None
        self._end_ns = 0

    # -- lifecycle
    def open(self) -> BagWriter:
        if self.path.exists():
            raise BagError(f"{self.path}: already exists; choose a new output path (bags are never overwritten)")
        if not hasattr(Writer, "flush"):
            raise BagError(f"mcap {mcap.__version__} has no Writer.flush (bounded-loss writing); install mcap>=1.6")
        try:
            self.path.mkdir(parents=True)
            self._file = self.mcap_path.open("wb")
        except OSError as err:
            raise BagError(f"{self.path}: cannot create the bag ({err.strerror}); choose another output path") from None
        self._mcap = Writer(self._file, chunk_size=self.max_chunk_size, compression=CompressionType.NONE)
        self._mcap.start(profile="ros2", library=f"lenn_ros (mcap-python {mcap.__version__})")
        self._last_flush = time.monotonic()
        return self

    def close(self) -> None:
        """Write the last chunk, the summary, the footer and metadata.yaml."""
        if self._mcap is None:
            return
        writer, self._mcap = self._mcap, None
        text = yaml.safe_dump(self._metadata(), default_flow_style=False)
        writer.add_metadata("rosbag2", {"serialized_metadata": text})
        writer.finish()
        assert self._file is not None
        self._file.close()
        tmp = self.path / "metadata.yaml.tmp"
        tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": self._metadata()}, default_flow_style=False))
        tmp.replace(self.path / "metadata.yaml")
        self.flushed_counts = Counter(self.counts)

    def __enter__(self) -> BagWriter:
        return self if self._mcap is not None else self.open()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    @property
    def mcap_path(self) -> Path:
        return self.path / f"{self.path.name}.mcap"

    @property
    def topics(self) -> dict[str, str]:
        """Topic -> type of every topic added so far."""
        return {topic: entry["topic_metadata"]["type"] for topic, entry in self._topics.items()}

    # -- topics and messages
    def add_topic(
        self,
        topic: str,
        type_name: str | None = None,
        qos: Any = None,
        *,
        definition: tuple[str, str] | None = None,
    ) -> None:
        """Register ``topic``; type and QoS default to those of :mod:`lenn_ros.topics`.

        ``type_name`` may be any installed message type, or any type at all when
        ``definition`` gives its (``ros2msg`` text, RIHS01 hash), as copied from another bag.
        ``qos`` may be an rclpy ``QoSProfile``, a rosbags ``Qos`` or a list of them (one
        per publisher, as rosbag2 stores it).
        """
        writer = self._require_open()
        spec = spec_for(topic)
        if type_name is None:
            if spec is None:
                raise BagError(f"topic {topic!r}: type unknown; pass type_name (e.g. {topics.FLOAT64!r})")
            type_name = spec.type_name
        if topic in self._channels:
            raise BagError(f"topic {topic!r} added twice to {self.path}")
        type_name = msgtypes.normalise(type_name)
        text, rihs01 = definition if definition is not None else msgtypes.msgdef(type_name)
        if type_name not in self._schemas:
            self._schemas[type_name] = writer.register_schema(type_name, "ros2msg", text.encode())
        qos_list = as_qos_list(qos, spec)
        metadata = {"offered_qos_profiles": qos_yaml(qos_list), "topic_type_hash": rihs01}
        self._channels[topic] = writer.register_channel(topic, "cdr", self._schemas[type_name], metadata)
        self._topics[topic] = {
            "topic_metadata": {
                "name": topic,
                "type": type_name,
                "serialization_format": "cdr",
                "offered_qos_profiles": dump_qos(qos_list),
                "type_description_hash": rihs01,
            },
            "message_count": 0,
        }

    def write_raw(
        self,
        topic: str,
        data: bytes | memoryview,
        log_time_ns: int,
        *,
        publish_time_ns: int = 0,
        sequence: int = 0,
    ) -> None:
        """Append one CDR-serialised message (log time = receive time, publish time = source stamp)."""
        writer = self._require_open()
        try:
            channel = self._channels[topic]
        except KeyError:
            raise BagError(f"topic {topic!r} was not added to {self.path}; call add_topic first") from None
        data = bytes(data)
        log_time_ns, publish_time_ns = int(log_time_ns), int(publish_time_ns)
        if not (0 <= log_time_ns < 2**64 and 0 <= publish_time_ns < 2**64):
            got = f"log {log_time_ns}, publish {publish_time_ns}"
            raise BagError(f"topic {topic!r}: times must be 0..2**64-1 ns, got {got}")
        writer.add_message(channel, log_time_ns, data, publish_time_ns, mcap_sequence(sequence))
        self._start_ns = log_time_ns if self._start_ns is None else min(self._start_ns, log_time_ns)
        self._end_ns = max(self._end_ns, log_time_ns)
        self.counts[topic] += 1
        self._topics[topic]["message_count"] += 1
        self._pending += 1
        self._pending_bytes += _MESSAGE_OVERHEAD + len(data)
        self.maybe_flush()

    def write_value(self, topic: str, value: float | int | str, log_time_ns: int, **times: int) -> None:
        """Serialise a plain value as the topic's std_msgs scalar type (Float*/Int*/UInt*/Bool/String)."""
        type_name = self.topics.get(topic)
        if type_name is None:
            raise BagError(f"topic {topic!r} was not added to {self.path}; call add_topic first")
        fields = msgtypes.TYPESTORE.fielddefs.get(type_name, ([], []))[1]
        if not type_name.startswith("std_msgs/msg/") or [name for name, _ in fields] != ["data"]:
            raise BagError(f"topic {topic!r}: write_value handles std_msgs scalars, not {type_name}; use write_message")
        cast = str if type_name.endswith("String") else float if "Float" in type_name else int
        self.write_message(topic, msgtypes.TYPESTORE.types[type_name](data=cast(value)), log_time_ns, **times)

    def write_message(self, topic: str, message: Any, log_time_ns: int, **times: int) -> None:
        """Serialise a rosbags typestore message or an rclpy message and append it."""
        if hasattr(message, "__msgtype__"):
            data = msgtypes.TYPESTORE.serialize_cdr(message, message.__msgtype__)
        else:
            from rclpy.serialization import serialize_message

            data = serialize_message(message)
        self.write_raw(topic, data, log_time_ns, **times)

    # -- durability
    def maybe_flush(self, now: float | None = None) -> bool:
        """Flush if the chunk is big enough or the flush period has passed; True if it flushed."""
        if not self._pending:
            return False
        now = time.monotonic() if now is None else now
        due = self.flush_period is not None and now - self._last_flush >= self.flush_period
        if due or self._pending_bytes >= self.max_chunk_size:
            self.flush()
            return True
        return False

    def flush(self) -> None:
        """Close the open chunk and hand the file's bytes to the kernel (see module doc)."""
        writer = self._require_open()
        writer.flush()
        if self.fsync:
            assert self._file is not None
            os.fsync(self._file.fileno())
        self._pending = 0
        self._pending_bytes = 0
        self._last_flush = time.monotonic()
        self.flushed_counts = Counter(self.counts)

    def _metadata(self) -> dict[str, Any]:
        start = self._start_ns or 0
        duration = {"nanoseconds": max(0, self._end_ns - start)}
        count = self.counts.total()
        return {
            "version": 9,
            "storage_identifier": "mcap",
            "relative_file_paths": [self.mcap_path.name],
            "duration": duration,
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": list(self._topics.values()),
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": self.mcap_path.name,
                    "starting_time": {"nanoseconds_since_epoch": start},
                    "duration": duration,
                    "message_count": count,
                }
            ],
            "custom_data": None,
            "ros_distro": "jazzy",
        }

    def _require_open(self) -> Writer:
        if self._mcap is None:
            raise BagError(f"{self.path}: bag is not open; use `with BagWriter(path) as bag:`")
        return self._mcap
