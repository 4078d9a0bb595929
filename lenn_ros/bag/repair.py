"""``lenn-ros bag-repair``: rebuild a valid bag from what a killed recorder left.

A killed recorder leaves an MCAP file without summary, footer or metadata.yaml, maybe
with a chunk cut off in the middle. ``mcap.stream_reader.StreamReader`` reads such a
file record by record; it reports a record cut off at the end as a short one (it
returns what is there), so each record's declared length is checked against the bytes
present. Whole chunks are split with ``breakup_chunk`` (CRC checked); the cut-off last
chunk, when uncompressed (as :class:`~lenn_ros.bag.BagWriter` writes them), gives up
its whole messages too. Every complete message keeps its log time, publish time and
sequence number.
"""

from __future__ import annotations

import shutil
import struct
import time
from collections import Counter
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import IO

from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from lenn_ros.bag.errors import MCAP_MAGIC, BagError
from lenn_ros.bag.qos import parse_qos
from lenn_ros.bag.writer import BagWriter

__all__ = ["RecoveryReport", "recover"]


@dataclass
class _Scan:
    """Everything usable in an MCAP file, read record by record (no summary needed)."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    complete: bool = False
    stop_reason: str = ""
    bytes_used: int = 0
    file_size: int = 0

    def take(self, record: object) -> None:
        if isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record
        elif isinstance(record, Message):
            self.messages.append(record)


def _whole_records(stream: IO[bytes], data: bytes, skip_magic: bool, base: int = 0):
    """(record, end offset) for each record of ``data`` that is entirely present; stops at the first cut one."""
    start = stream.tell() + (0 if skip_magic else len(MCAP_MAGIC))
    records = StreamReader(stream, skip_magic=skip_magic, emit_chunks=True).records
    while True:
        try:
            record = next(records)
        except StopIteration:
            return
        except Exception as err:  # mcap raises several types at a cut or damaged record
            if start == len(data):
                raise _Stop(f"no footer: the file ends after its last whole record (byte {base + start})") from None
            raise _Stop(f"record at byte {base + start} is cut off or damaged ({type(err).__name__})") from None
        end = stream.tell()
        (declared,) = struct.unpack_from("<Q", data, start + 1) if start + 9 <= len(data) else (len(data),)
        if start + 9 + declared > len(data):
            present = len(data) - start - 9
            raise _Stop(f"record at byte {base + start} is cut off (needs {declared} bytes, {present} present)")
        yield record, end
        start = end


class _Stop(Exception):
    pass


def _salvage_tail(data: bytes, start: int, scan: _Scan) -> None:
    """Take the whole messages of the uncompressed chunk cut off at ``start`` (being written at the kill).

    StreamReader cannot return a chunk that is cut short, so the missing bytes are made up
    with zeros: the chunk header then parses, and only the records before the cut are used.
    """
    if start + 9 > len(data) or data[start] != 0x06:
        return
    (declared,) = struct.unpack_from("<Q", data, start + 1)
    missing = start + 9 + declared - len(data)
    try:
        chunk = next(StreamReader(BytesIO(data[start:] + bytes(missing)), skip_magic=True, emit_chunks=True).records)
    except Exception:  # the cut is inside the chunk header: nothing to take
        return
    if not isinstance(chunk, Chunk) or chunk.compression != "" or not 0 < missing <= len(chunk.data):
        return
    records = chunk.data[: len(chunk.data) - missing]
    try:
        for record, _end in _whole_records(BytesIO(records), records, skip_magic=True):
            scan.take(record)
    except _Stop:
        pass


def _take_chunk(chunk: Chunk, scan: _Scan, at: int) -> bool:
    try:
        for record in breakup_chunk(chunk, validate_crc=True):
            scan.take(record)
    except Exception as err:  # any decoding failure means the chunk is unusable
        scan.stop_reason = f"chunk at byte {at} is corrupt ({type(err).__name__}: {err})"
        return False
    return True


def _scan_mcap(file: Path) -> _Scan:
    data = file.read_bytes()
    scan = _Scan(file_size=len(data))
    if data[: len(MCAP_MAGIC)] != MCAP_MAGIC:
        raise BagError(f"{file}: empty or not an MCAP file (wrong magic bytes); nothing to recover")
    stream = BytesIO(data)
    scan.bytes_used = len(MCAP_MAGIC)
    try:
        for record, end in _whole_records(stream, data, skip_magic=False):
            if isinstance(record, Chunk) and not _take_chunk(record, scan, scan.bytes_used):
                return scan
            scan.take(record)
            scan.bytes_used = end
            if isinstance(record, Footer):
                scan.complete = True
                scan.bytes_used = len(data)
    except _Stop as stop:
        scan.stop_reason = str(stop)
        _salvage_tail(data, scan.bytes_used, scan)
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


def _locate(path: Path) -> tuple[Path, Path]:
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


def _write(scan: _Scan, staging: Path) -> Counter[str]:
    messages: Counter[str] = Counter()
    try:
        bag = BagWriter(staging, flush_period=None).open()
    except BagError as err:
        raise BagError(f"{staging}: cannot create the repaired bag ({err}); choose another output path") from None
    with bag:
        topics = {}
        for cid, channel in sorted(scan.channels.items()):
            schema = scan.schemas.get(channel.schema_id)
            name = schema.name if schema is not None else ""
            text = schema.data.decode() if schema is not None else ""
            qos = parse_qos(channel.metadata.get("offered_qos_profiles", "") or [])
            rihs01 = channel.metadata.get("topic_type_hash", "RIHS01_" + "0" * 64)
            bag.add_topic(channel.topic, name, qos, definition=(text, rihs01))
            topics[cid] = channel.topic
        for message in scan.messages:
            if message.channel_id in topics:
                topic = topics[message.channel_id]
                times = {"publish_time_ns": message.publish_time, "sequence": message.sequence}
                bag.write_raw(topic, message.data, message.log_time, **times)
                messages[topic] += 1
    return messages


def _swap_in(bag_dir: Path, source: Path, staging: Path) -> Path:
    """Keep the damaged file (and old metadata) under new names; move the repaired bag in."""
    kept = source.with_name(source.name + ".damaged")
    if kept.exists():
        kept = source.with_name(f"{source.name}.damaged-{time.time_ns()}")
    source.rename(kept)
    meta = bag_dir / "metadata.yaml"
    if meta.exists():
        meta.rename(kept.with_name(kept.name.replace(".mcap", ".metadata.yaml")))
    for item in staging.iterdir():
        item.rename(bag_dir / (f"{bag_dir.name}.mcap" if item.suffix == ".mcap" else item.name))
    shutil.rmtree(staging.parent)
    return kept


def recover(path: str | Path, out: str | Path | None = None) -> RecoveryReport:
    """Rebuild a valid bag from every complete message of the MCAP file at ``path``.

    With ``out=None`` the bag directory is repaired in place: the damaged file is kept as
    ``<name>.mcap.damaged`` (nothing is ever deleted) and a new ``<dir>.mcap`` plus
    metadata.yaml take its place. Otherwise a new bag is written at ``out``.
    """
    bag_dir, source = _locate(Path(path))
    scan = _scan_mcap(source)
    if not scan.channels:
        raise BagError(
            f"{source}: no complete chunk in the file (the recorder was killed before its first flush); "
            "nothing to recover — record again, with a shorter flush_period if needed"
        )
    final = Path(out) if out is not None else bag_dir
    staging = final if out is not None else bag_dir.parent / f".{bag_dir.name}.repair" / bag_dir.name
    if out is None and staging.parent.exists():
        shutil.rmtree(staging.parent)
    messages = _write(scan, staging)
    kept = _swap_in(bag_dir, source, staging) if out is None else source
    return RecoveryReport(
        path=final,
        source=kept,
        messages={channel.topic: messages[channel.topic] for _cid, channel in sorted(scan.channels.items())},
        was_complete=scan.complete,
        stop_reason=scan.stop_reason,
        bytes_used=scan.bytes_used,
        file_size=scan.file_size,
    )
