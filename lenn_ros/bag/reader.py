"""Read any message of any rosbag2 recording, with its log time, publish time and sequence number.

A recording is a rosbag2 directory (``metadata.yaml`` and its files) or one file:

- MCAP, one file or a split bag's several (the recorder, ``import-csv``, ``ros2 bag record``
  from Jazzy on): read with ``mcap.reader``, which keeps the DDS publish time and sequence
  number the recorder stored;
- sqlite3 (``.db3``: ``ros2 bag record`` on Humble and Iron, and Jazzy with ``-s sqlite3``):
  read with rosbags' public ``rosbag2.Reader``; such a bag stores no publish time or sequence
  number (both 0, as for an import).

Messages are deserialised with rosbags' typestore into objects with attribute access like
an rclpy message (``msg.header.stamp.sec``, ``msg.position[0]``, ``msg.name``). Types the
typestore does not know are registered from the bag's own schema text, so a bag of any
message type reads without its package installed. Every way a file can be unusable is a
one-line :class:`BagError` that names the fix (usually ``lenn-ros bag-repair``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from mcap.reader import make_reader
from mcap.summary import Summary

from lenn_ros.bag import msgtypes
from lenn_ros.bag.errors import MCAP_MAGIC, REPAIR_HINT, BagError

__all__ = [
    "BagFiles",
    "BagMessage",
    "find_topic",
    "iter_messages",
    "locate_mcap",
    "open_bag",
    "read_summary",
    "topic_counts",
    "topic_types",
]


@dataclass(frozen=True)
class BagMessage:
    """One recorded message, as the recorder received it."""

    topic: str  # as recorded, e.g. "/u" or "/robot/joint_states"
    type_name: str  # "sensor_msgs/msg/JointState"
    log_time_ns: int  # receive time at the recorder
    publish_time_ns: int  # DDS source timestamp (0 if unknown)
    sequence: int  # DDS publication sequence number (0 if unknown)
    message: Any  # deserialised; attribute access like an rclpy message


def _check_mcap_file(file: Path, shown: Path, context: str = "") -> None:
    """Fail early, with the fix, on files a reader would only report as 'invalid magic'."""
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


@dataclass(frozen=True)
class BagFiles:
    """Where a recording's messages are: its storage and its files, in recording order."""

    path: Path  # as the user gave it
    storage: str  # "mcap" or "sqlite3"
    files: tuple[Path, ...]
    directory: Path | None  # the rosbag2 directory holding metadata.yaml (None: a lone .mcap file)

    @property
    def single_mcap(self) -> Path | None:
        """The one MCAP file, where there is one: the fast paths (summary, chunk indexes) read only that."""
        return self.files[0] if self.storage == "mcap" and len(self.files) == 1 else None


def _metadata(directory: Path) -> dict[str, Any] | None:
    """The rosbag2 ``metadata.yaml`` of a directory, or None where there is none."""
    file = directory / "metadata.yaml"
    if not file.is_file():
        return None
    try:
        info = yaml.safe_load(file.read_text())["rosbag2_bagfile_information"]
    except (OSError, yaml.YAMLError, KeyError, TypeError) as err:
        raise BagError(f"{file}: not a rosbag2 metadata file ({type(err).__name__}: {err})") from None
    return info if isinstance(info, dict) else None


def open_bag(path: str | Path) -> BagFiles:
    """The storage and files of a recording: a rosbag2 directory, its one .mcap, or a .db3 beside its metadata."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such file or directory; pass a rosbag2 bag directory (or its .mcap file)")
    if path.is_file():
        if path.suffix == ".db3":
            if _metadata(path.parent) is None:
                raise BagError(f"{path}: a sqlite3 bag is read with its metadata.yaml: pass its directory "
                               "(`ros2 bag reindex DIR` rebuilds a lost metadata.yaml)")  # fmt: skip
            return open_bag(path.parent)
        if path.suffix != ".mcap":
            raise BagError(f"{path}: not a rosbag2 bag; pass the bag directory (with metadata.yaml) or its .mcap file")
        _check_mcap_file(path, path)
        return BagFiles(path, "mcap", (path,), None)
    info = _metadata(path)
    if info is not None:
        return _listed_files(path, info)
    mcaps = sorted(path.glob("*.mcap"))
    if not mcaps:
        if any(path.glob("*.db3")):
            raise BagError(f"{path}: sqlite3 files without metadata.yaml; `ros2 bag reindex {path}` rebuilds it")
        raise BagError(f"{path}: not a rosbag2 bag (no metadata.yaml, no .mcap file); pass the bag directory itself")
    if len(mcaps) > 1:
        hint = REPAIR_HINT.format(path=path)
        raise BagError(f"{path}: several .mcap files and no metadata.yaml to order them; pass one of them, or {hint}")
    _check_mcap_file(mcaps[0], path, context="no metadata.yaml next to it and ")
    return BagFiles(path, "mcap", (mcaps[0],), path)


def _listed_files(path: Path, info: dict[str, Any]) -> BagFiles:
    """The files ``metadata.yaml`` lists, checked: storage known, each file there, no file compression."""
    storage = str(info.get("storage_identifier") or "")
    if storage not in ("mcap", "sqlite3"):
        raise BagError(f"{path}: storage {storage!r}; lenn_ros reads rosbag2 bags in mcap or sqlite3 storage")
    if str(info.get("compression_mode") or "").lower() == "file":
        raise BagError(f"{path}: file-compressed bag; `ros2 bag decompress` (or convert) it first")
    names = [str(name) for name in info.get("relative_file_paths") or []]
    files = tuple(path / name for name in names)
    if not files:
        files = tuple(sorted(path.glob("*.mcap" if storage == "mcap" else "*.db3")))
    missing = [str(file) for file in files if not file.is_file()]
    if missing or not files:
        raise BagError(f"{path}: metadata.yaml lists files that are not there ({', '.join(missing) or 'none'})")
    if storage == "mcap":
        for file in files:
            _check_mcap_file(file, path)
    return BagFiles(path, storage, files, path)


def locate_mcap(path: str | Path) -> Path:
    """The one .mcap file of a bag (directory or file), checked: what the MCAP-only tools (repair) read."""
    found = open_bag(path)
    if found.single_mcap is None:
        what = "sqlite3 storage" if found.storage == "sqlite3" else f"a split bag of {len(found.files)} files"
        raise BagError(f"{path}: {what}; this needs one MCAP file (`ros2 bag convert` makes one)")
    return found.single_mcap


def _corrupt(path: Path, err: Exception) -> BagError:
    hint = REPAIR_HINT.format(path=path)
    return BagError(f"{path}: corrupt or unreadable bag ({type(err).__name__}: {err}); {hint}")


def read_summary(path: str | Path) -> tuple[Path, Summary]:
    """(.mcap file, its summary: schemas, channels, statistics, chunk indexes) of a one-file MCAP bag."""
    file = locate_mcap(path)
    return file, _summary(file, Path(path))


def _summary(file: Path, shown: Path) -> Summary:
    try:
        with file.open("rb") as f:
            summary = make_reader(f).get_summary()
    except Exception as err:  # mcap raises several unrelated types for damaged files
        raise _corrupt(shown, err) from None
    if summary is None:
        raise BagError(f"{shown}: the MCAP file has no summary section; " + REPAIR_HINT.format(path=shown))
    return summary


def _types(summary: Summary) -> dict[str, str]:
    out = {}
    for channel in summary.channels.values():
        schema = summary.schemas.get(channel.schema_id)
        out[channel.topic] = schema.name if schema is not None else ""
    return out


def _sqlite_reader(found: BagFiles) -> Any:
    """rosbags' public rosbag2 reader over a sqlite3 bag, opened (close it), its errors as one line."""
    from rosbags.rosbag2 import Reader, ReaderError

    try:
        reader = Reader(found.directory)
        reader.open()
    except ReaderError as err:
        raise BagError(f"{found.path}: unreadable sqlite3 bag ({err})") from None
    return reader


def topic_types(path: str | Path) -> dict[str, str]:
    """Topic (as recorded) -> message type, e.g. ``{"/u": "std_msgs/msg/Float64"}``."""
    return {topic: type_name for topic, (type_name, _) in _topics(open_bag(path)).items()}


def topic_counts(path: str | Path) -> dict[str, int]:
    """Topic (as recorded) -> how many messages the recording holds (its index: nothing is read)."""
    return {topic: count for topic, (_, count) in _topics(open_bag(path)).items()}


def _topics(found: BagFiles) -> dict[str, tuple[str, int]]:
    """Topic -> (type, message count), over every file of the recording."""
    out: dict[str, tuple[str, int]] = {}
    if found.storage == "sqlite3":
        reader = _sqlite_reader(found)
        try:
            for connection in reader.connections:
                count = out.get(connection.topic, ("", 0))[1] + int(connection.msgcount)
                out[connection.topic] = (connection.msgtype, count)
        finally:
            reader.close()
        return out
    for file in found.files:
        summary = _summary(file, found.path)
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            count = out.get(channel.topic, ("", 0))[1] + int(counts.get(channel.id, 0))
            out[channel.topic] = (schema.name if schema is not None else "", count)
    return out


def find_topic(available: Iterable[str], name: str, namespace: str | None = None) -> str | None:
    """The recorded topic for a short name: ``u`` finds ``/u`` or, if it is the only one, ``/id3/u``.

    An exact recorded name (``/robot/joint_states``) is taken as is; ``namespace``
    picks ``<namespace>/<name>`` when several namespaces hold the same name.
    """
    available = list(available)
    if name.startswith("/") and name in available:
        return name
    if namespace is not None:
        wanted = namespace.rstrip("/") + "/" + name.lstrip("/")
        return wanted if wanted in available else None
    short = name.strip("/")
    matches = [t for t in available if t.rstrip("/").rsplit("/", 1)[-1] == short]
    if len(matches) > 1:
        if "/" + short in matches:
            return "/" + short
        raise BagError(f"several topics end in {short!r}: {', '.join(sorted(matches))}; pass namespace= to choose one")
    return matches[0] if matches else None


def _resolve(available: dict[str, str], wanted: Iterable[str] | None) -> list[str] | None:
    if wanted is None:
        return None
    found = (find_topic(available, name) for name in wanted)
    return [topic for topic in found if topic is not None]


def iter_messages(
    path: str | Path,
    topics: Iterable[str] | None = None,
    ordered: bool = True,
    progress: Callable[[int], None] | None = None,
    raw: bool = False,
) -> Iterator[BagMessage]:
    """Every message (of ``topics``, names as recorded or short names), file by file.

    ``ordered``: in log-time order within each file (MCAP's heap merge, a few microseconds a
    message); False: in the order the file holds them (the order of arrival for every
    recorder here and for ``ros2 bag record``), for readers that sort what they keep
    themselves. A sqlite3 bag always comes in log-time order. ``progress(n)`` is told every
    10 000 messages; ``raw``: the CDR bytes, not deserialised (for readers of the record fields
    alone). A name the bag does not hold yields nothing (check :func:`topic_types`).
    """
    found = open_bag(path)
    wanted = _resolve({topic: "" for topic in _topics(found)}, topics)
    if wanted == []:
        return
    if found.storage == "sqlite3":
        read = _sqlite_messages(found, wanted, raw)
    else:
        read = _mcap_messages(found, wanted, ordered, raw)
    if progress is None:
        yield from read
        return
    count = 0
    for message in read:
        count += 1
        if count % 10_000 == 0:
            progress(10_000)
        yield message
    progress(count % 10_000)


def _register(found: BagFiles, type_name: str, text: str) -> None:
    try:
        msgtypes.register_msgdef(type_name, text)
    except Exception as err:
        raise BagError(f"{found.path}: schema {type_name!r} cannot be parsed ({err})") from None


def _mcap_messages(found: BagFiles, wanted: list[str] | None, ordered: bool, raw: bool) -> Iterator[BagMessage]:
    deserialize = _as_bytes if raw else msgtypes.TYPESTORE.deserialize_cdr
    for file in found.files:
        for schema in _summary(file, found.path).schemas.values():
            if schema.encoding == "ros2msg":
                _register(found, schema.name, schema.data.decode())
        with file.open("rb") as f:
            reader = make_reader(f)
            try:
                for schema, channel, message in reader.iter_messages(topics=wanted, log_time_order=ordered):
                    type_name = schema.name if schema is not None else ""
                    yield BagMessage(
                        topic=channel.topic,
                        type_name=type_name,
                        log_time_ns=message.log_time,
                        publish_time_ns=message.publish_time,
                        sequence=message.sequence,
                        message=deserialize(message.data, type_name),
                    )
            except BagError:
                raise
            except Exception as err:
                raise _corrupt(found.path, err) from None


def _as_bytes(data: Any, _type_name: str) -> bytes:
    return bytes(data)


def _sqlite_messages(found: BagFiles, wanted: list[str] | None, raw: bool) -> Iterator[BagMessage]:
    """A sqlite3 bag's messages through rosbags: no publish time or sequence number is stored (0)."""
    deserialize = _as_bytes if raw else msgtypes.TYPESTORE.deserialize_cdr
    reader = _sqlite_reader(found)
    try:
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        for connection in connections:
            definition = getattr(connection.msgdef, "data", "") or ""
            if connection.msgtype not in msgtypes.TYPESTORE.types and not raw:
                if not definition:
                    msgtypes.ensure_type(connection.msgtype)
                _register(found, connection.msgtype, definition)
        try:
            for connection, timestamp, data in reader.messages(connections=connections):
                yield BagMessage(connection.topic, connection.msgtype, timestamp, 0, 0, deserialize(data,
                                 connection.msgtype))  # fmt: skip
        except BagError:
            raise
        except Exception as err:
            raise _corrupt(found.path, err) from None
    finally:
        reader.close()
