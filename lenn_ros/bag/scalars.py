"""Fast path: numeric series of std_msgs scalar / Float64MultiArray topics, decoded with numpy.

Why: deserialising message by message costs microseconds each, so a 10^6-sample bag
took seconds to evaluate. Here the summary's chunk indexes point at each chunk and its
per-channel message indexes (``(log_time, offset)`` pairs, read with one
``np.frombuffer``); the record fields (sequence, log and publish time) and the CDR
payload are then gathered for all of a channel's messages in a chunk at once. The CDR
layouts used are fixed: a 4-byte encapsulation header (little endian required, else
the slow path), then the value; a Float64MultiArray is accepted when every message has
the same size and layout bytes (the data array then sits at the same offset in all).
Anything else (no message index, big-endian CDR, varying layouts, unchunked files)
goes through the general reader, message by message: slower, same result.
``bench/bag_read.py`` measures both.
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.records import ChunkIndex
from mcap.summary import Summary

from lenn_ros.bag.errors import BagError

__all__ = ["SCALAR_TYPES", "Series", "read_series", "topic_series"]

#: std_msgs type -> numpy dtype of its one ``data`` field.
SCALAR_TYPES = {
    f"std_msgs/msg/{name}": np.dtype(code).newbyteorder("<")
    for name, code in (
        ("Float64", "f8"), ("Float32", "f4"), ("Int64", "i8"), ("UInt64", "u8"), ("Int32", "i4"),
        ("UInt32", "u4"), ("Int16", "i2"), ("UInt16", "u2"), ("Int8", "i1"), ("UInt8", "u1"),
        ("Bool", "u1"), ("Byte", "u1"), ("Char", "u1"),
    )
}  # fmt: skip
FLOAT64_ARRAY = "std_msgs/msg/Float64MultiArray"
_HEADER = 4  # CDR encapsulation header


@dataclass(frozen=True)
class Series:
    """One topic's messages in log-time order: values (n,) or (n, width) for arrays, and record fields."""

    values: np.ndarray | None  # None when only the record fields were asked for
    log_time_ns: np.ndarray
    publish_time_ns: np.ndarray
    sequence: np.ndarray


class _SlowPath(Exception):
    """This chunk/channel cannot be decoded in bulk; use the general reader."""


def _gather(buf: np.ndarray, offsets: np.ndarray, width: int, dtype: str) -> np.ndarray:
    """The ``dtype`` value of ``width`` bytes at each offset (unaligned reads, vectorised)."""
    rows = buf[offsets[:, None] + np.arange(width)]
    return rows.view(np.dtype(dtype)).reshape(len(offsets), -1)


def _chunk_records(mm: mmap.mmap, index: ChunkIndex) -> np.ndarray:
    """The uncompressed records of one chunk as a uint8 array (no copy when uncompressed)."""
    pos = index.chunk_start_offset + 9 + 8 + 8 + 8 + 4
    (name_len,) = struct.unpack_from("<I", mm, pos)
    compression = bytes(mm[pos + 4 : pos + 4 + name_len]).decode()
    (size,) = struct.unpack_from("<Q", mm, pos + 4 + name_len)
    start = pos + 12 + name_len
    if compression == "":
        return np.frombuffer(mm, np.uint8, count=size, offset=start)
    data = bytes(mm[start : start + size])
    if compression == "zstd":
        import zstandard

        return np.frombuffer(zstandard.decompress(data, max_output_size=index.uncompressed_size), np.uint8)
    if compression == "lz4":
        import lz4.frame

        return np.frombuffer(lz4.frame.decompress(data), np.uint8)
    raise _SlowPath(compression)


def _message_offsets(mm: mmap.mmap, offset: int) -> np.ndarray:
    """Offsets (into the chunk's records) of one channel's messages, from its MessageIndex record."""
    (length,) = struct.unpack_from("<I", mm, offset + 9 + 2)
    pairs = np.frombuffer(mm, "<u8", count=length // 8, offset=offset + 9 + 2 + 4)
    return pairs[1::2].astype(np.int64)


def _array_layout(payload: bytes) -> tuple[int, int, np.ndarray]:
    """Where a Float64MultiArray's float64 data starts, its element count, and which prefix bytes count.

    The third value marks the prefix bytes that carry the layout; CDR alignment padding
    is left as the serialiser found the memory (rclpy's is not zeroed), so it differs
    between otherwise identical messages and must not be compared.
    """
    meaningful = []

    def skip_padding(pos: int, alignment: int) -> int:
        pad = -(pos - _HEADER) % alignment
        meaningful.extend([False] * pad)
        return pos + pad

    pos = _HEADER
    meaningful.extend([True] * _HEADER)
    (dims,) = struct.unpack_from("<I", payload, pos)
    pos += 4
    meaningful.extend([True] * 4)
    for _ in range(dims):
        (label,) = struct.unpack_from("<I", payload, pos)
        pos += 4 + label
        meaningful.extend([True] * (4 + label))
        pos = skip_padding(pos, 4)
        pos += 8  # size, stride
        meaningful.extend([True] * 8)
    pos += 8  # data_offset, element count
    meaningful.extend([True] * 8)
    (count,) = struct.unpack_from("<I", payload, pos - 4)
    pos = skip_padding(pos, 8)
    return pos, count, np.asarray(meaningful, dtype=bool)


def _decode(buf: np.ndarray, data_at: np.ndarray, sizes: np.ndarray, type_name: str) -> np.ndarray:
    if not np.all(buf[data_at + 1] == 1):  # encapsulation: CDR little endian
        raise _SlowPath("big-endian CDR")
    if type_name in SCALAR_TYPES:
        dtype = SCALAR_TYPES[type_name]
        if not np.all(sizes >= _HEADER + dtype.itemsize):
            raise _SlowPath("short payload")
        return _gather(buf, data_at + _HEADER, dtype.itemsize, dtype.str)[:, 0]
    size = int(sizes[0])
    if not np.all(sizes == size):
        raise _SlowPath("array sizes vary")
    first = bytes(buf[data_at[0] : data_at[0] + size])
    at, count, meaningful = _array_layout(first)
    prefixes = _gather(buf, data_at, at, "u1")[:, meaningful]
    if at + 8 * count > size or not np.all(prefixes == prefixes[0]):
        raise _SlowPath("array layouts vary")
    return _gather(buf, data_at + at, 8 * count, "<f8")


def _chunk_part(mm: mmap.mmap, index: ChunkIndex, channel_id: int, type_name: str | None) -> tuple[np.ndarray, ...]:
    if channel_id not in index.message_index_offsets:
        if index.message_index_length == 0:
            raise _SlowPath("no message index")
        empty = np.empty(0, np.int64)
        return (np.empty(0), empty, empty, empty)
    buf = _chunk_records(mm, index)
    offsets = _message_offsets(mm, index.message_index_offsets[channel_id])
    fields = _gather(buf, offsets + 1, 30, "u1")  # record length .. publish time
    length = fields[:, :8].copy().view("<u8")[:, 0].astype(np.int64)
    sequence = fields[:, 10:14].copy().view("<u4")[:, 0].astype(np.int64)
    log_time = fields[:, 14:22].copy().view("<u8")[:, 0].astype(np.int64)
    publish = fields[:, 22:30].copy().view("<u8")[:, 0].astype(np.int64)
    values = np.empty(0) if type_name is None else _decode(buf, offsets + 31, length - 22, type_name)
    return values, log_time, publish, sequence


def _bulk(file: Path, summary: Summary, channel_id: int, type_name: str | None) -> Series:
    parts = []
    indexes = sorted(summary.chunk_indexes, key=lambda i: i.chunk_start_offset)
    failure = "no chunks" if not indexes else ""
    with file.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        for index in indexes:
            try:
                parts.append(_chunk_part(mm, index, channel_id, type_name))
            except (_SlowPath, struct.error, IndexError, ValueError) as err:
                # Only the text leaves this block: a live traceback would keep views of the map open.
                failure = f"{type(err).__name__}: {err}"
                break
    if failure:
        raise _SlowPath(failure)
    log_time = np.concatenate([p[1] for p in parts])
    order = np.argsort(log_time, kind="stable") if np.any(np.diff(log_time) < 0) else slice(None)
    values = None
    if type_name is not None:
        shaped = [p[0] for p in parts if len(p[1])]
        values = np.concatenate(shaped)[order] if shaped else np.empty(0)
        if type_name in SCALAR_TYPES:
            values = values.astype(np.float64)
    return Series(
        values,
        log_time[order],
        np.concatenate([p[2] for p in parts])[order],
        np.concatenate([p[3] for p in parts])[order],
    )


def _slow(path: Path, topic: str, with_values: bool) -> Series:
    from lenn_ros.bag.reader import iter_messages

    values, log_time, publish, sequence = [], [], [], []
    for item in iter_messages(path, [topic], raw=not with_values):
        log_time.append(item.log_time_ns)
        publish.append(item.publish_time_ns)
        sequence.append(item.sequence)
        if with_values:
            values.append(np.asarray(item.message.data, dtype=np.float64))
    as_int = [np.asarray(a, dtype=np.int64) for a in (log_time, publish, sequence)]
    stacked = (np.stack(values) if values else np.empty(0)) if with_values else None
    return Series(stacked, *as_int)


def topic_series(path: str | Path, topic: str, with_values: bool = True) -> Series:
    """One topic's series from any recording: the MCAP fast path where it applies (one MCAP file), else the
    general reader message by message (a split or sqlite3 bag: same result, slower)."""
    from lenn_ros.bag.reader import open_bag, read_summary

    path = Path(path)
    if open_bag(path).single_mcap is not None:
        file, summary = read_summary(path)
        return read_series(path, file, summary, topic, with_values)
    return _slow(path, topic, with_values)


def read_series(path: Path, file: Path, summary: Summary, topic: str, with_values: bool = True) -> Series:
    """One topic's values (std_msgs scalar or Float64MultiArray) and record fields, fast when possible.

    ``with_values=False`` reads only the record fields, for a topic of any type.
    """
    channel = next((c for c in summary.channels.values() if c.topic == topic), None)
    if channel is None:
        raise BagError(f"{path}: no topic {topic!r}")
    schema = summary.schemas.get(channel.schema_id)
    type_name = schema.name if schema is not None else ""
    if with_values and type_name not in SCALAR_TYPES and type_name != FLOAT64_ARRAY:
        raise BagError(f"{path}: topic {topic!r} has type {type_name}, not a std_msgs number or Float64MultiArray")
    try:
        return _bulk(file, summary, channel.id, type_name if with_values else None)
    except (_SlowPath, struct.error, IndexError, ValueError):
        return _slow(path, topic, with_values)
