"""Read any message of a bag, with its MCAP log time, publish time and sequence number.

Built on ``mcap.reader`` (the summary, message order) and rosbags' typestore (CDR to
objects with attribute access like an rclpy message: ``msg.header.stamp.sec``,
``msg.position[0]``, ``msg.name``). Types the typestore does not know are registered
from the bag's own schema text, so a bag of any message type reads without its
package installed. Every way a file can be unusable is a one-line :class:`BagError`
that names the fix (usually ``lenn-ros bag-repair``).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from mcap.summary import Summary

from lenn_ros.bag import msgtypes
from lenn_ros.bag.errors import MCAP_MAGIC, REPAIR_HINT, BagError

__all__ = ["BagMessage", "find_topic", "iter_messages", "locate_mcap", "read_summary", "topic_types"]


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


def locate_mcap(path: str | Path) -> Path:
    """The one .mcap file of a bag directory (metadata.yaml optional) or the .mcap given, checked."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such file or directory; pass a bag directory made by `recorder` or `import-csv`")
    if path.is_file():
        if path.suffix != ".mcap":
            raise BagError(f"{path}: not a rosbag2 bag; pass the bag directory (with metadata.yaml) or its .mcap file")
        _check_mcap_file(path, path)
        return path
    mcaps = sorted(path.glob("*.mcap"))
    has_metadata = (path / "metadata.yaml").exists()
    if not mcaps:
        if has_metadata and any(path.glob("*.db3")):
            raise BagError(f"{path}: sqlite3 storage; lenn_ros reads MCAP bags (`ros2 bag convert` makes one)")
        raise BagError(f"{path}: not a rosbag2 bag (no metadata.yaml, no .mcap file); pass the bag directory itself")
    if len(mcaps) > 1:
        hint = REPAIR_HINT.format(path=path)
        raise BagError(f"{path}: several .mcap files (a split bag); pass one of them, or {hint}")
    _check_mcap_file(mcaps[0], path, context="" if has_metadata else "no metadata.yaml next to it and ")
    return mcaps[0]


def _corrupt(path: Path, err: Exception) -> BagError:
    hint = REPAIR_HINT.format(path=path)
    return BagError(f"{path}: corrupt or unreadable bag ({type(err).__name__}: {err}); {hint}")


def read_summary(path: str | Path) -> tuple[Path, Summary]:
    """(.mcap file, its summary: schemas, channels, statistics, chunk indexes)."""
    file = locate_mcap(path)
    try:
        with file.open("rb") as f:
            summary = make_reader(f).get_summary()
    except Exception as err:  # mcap raises several unrelated types for damaged files
        raise _corrupt(Path(path), err) from None
    if summary is None:
        raise BagError(f"{path}: the MCAP file has no summary section; " + REPAIR_HINT.format(path=path))
    return file, summary


def _types(summary: Summary) -> dict[str, str]:
    out = {}
    for channel in summary.channels.values():
        schema = summary.schemas.get(channel.schema_id)
        out[channel.topic] = schema.name if schema is not None else ""
    return out


def topic_types(path: str | Path) -> dict[str, str]:
    """Topic (as recorded) -> message type, e.g. ``{"/u": "std_msgs/msg/Float64"}``."""
    return _types(read_summary(path)[1])


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


def iter_messages(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Every message (of ``topics``, names as recorded or short names), in log-time order.

    A name the bag does not hold yields nothing (check :func:`topic_types` to tell the user).
    """
    path = Path(path)
    file, summary = read_summary(path)
    available = _types(summary)
    wanted = _resolve(available, topics)
    if wanted == []:
        return
    for schema in summary.schemas.values():
        if schema.encoding == "ros2msg":
            try:
                msgtypes.register_msgdef(schema.name, schema.data.decode())
            except Exception as err:
                raise BagError(f"{path}: schema {schema.name!r} cannot be parsed ({err})") from None
    with file.open("rb") as f:
        reader = make_reader(f)
        try:
            for schema, channel, message in reader.iter_messages(topics=wanted, log_time_order=True):
                type_name = schema.name if schema is not None else ""
                yield BagMessage(
                    topic=channel.topic,
                    type_name=type_name,
                    log_time_ns=message.log_time,
                    publish_time_ns=message.publish_time,
                    sequence=message.sequence,
                    message=msgtypes.TYPESTORE.deserialize_cdr(message.data, type_name),
                )
        except BagError:
            raise
        except Exception as err:
            raise _corrupt(path, err) from None
