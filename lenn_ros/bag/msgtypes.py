"""Message types without a ROS install: one rosbags typestore, extended on demand.

Why: a bag's schema record must carry the full ``ros2msg`` definition text (rosbag2,
Foxglove and ``mcap_ros2`` decode from it), and reading must deserialise any type a
bag holds. rosbags' Jazzy store knows the common interfaces; anything else is taken
from the ``.msg`` files an installed message package ships (``<prefix>/share/<pkg>/msg``,
found through ``AMENT_PREFIX_PATH`` and the running interpreter's prefix) or, when
reading, from the bag's own schema text.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from lenn_ros.bag.errors import BagError

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

_PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string", "wstring",
}  # fmt: skip


def _share_dirs() -> list[Path]:
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    return [Path(p) / "share" for p in prefixes]


def _msg_file(type_name: str) -> Path | None:
    package, _, name = type_name.split("/")
    for share in _share_dirs():
        candidate = share / package / "msg" / f"{name}.msg"
        if candidate.is_file():
            return candidate
    return None


def _dependencies(text: str, package: str) -> set[str]:
    """Full names of the non-primitive field types a .msg text uses (constants are primitive)."""
    found = set()
    for raw in text.splitlines():
        tokens = raw.split("#", 1)[0].split()
        if len(tokens) < 2:
            continue
        base = re.split(r"[\[<]", tokens[0])[0]
        if base in _PRIMITIVES:
            continue
        if "/" not in base:
            base = "std_msgs/Header" if base == "Header" else f"{package}/{base}"
        found.add(f"{base.split('/')[0]}/msg/{base.split('/')[-1]}")
    return found


def normalise(type_name: str) -> str:
    """``pkg/Name`` or ``pkg/msg/Name`` to ``pkg/msg/Name``; a one-line BagError otherwise."""
    parts = type_name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise BagError(f"{type_name!r} is not a message type name like 'std_msgs/msg/Float64'")
    return "/".join(parts)


def ensure_type(type_name: str) -> str:
    """Make ``type_name`` (and the types it uses) known to :data:`TYPESTORE`; returns its full name."""
    type_name = normalise(type_name)
    pending, seen = [type_name], set()
    found: dict[str, Any] = {}
    while pending:
        name = pending.pop()
        if name in TYPESTORE.types or name in seen:
            continue
        seen.add(name)
        path = _msg_file(name)
        if path is None:
            raise BagError(
                f"message type {name!r} is unknown: not in rosbags' Jazzy types and no {name.split('/')[-1]}.msg "
                "under <prefix>/share; install its message package (or source its workspace)"
            )
        text = path.read_text(encoding="utf-8")
        found.update(get_types_from_msg(text, name))
        pending.extend(_dependencies(text, name.split("/")[0]))
    if found:
        TYPESTORE.register(found)
    return type_name


def register_msgdef(type_name: str, text: str) -> None:
    """Register a type from a bag's ``ros2msg`` schema text (the type plus its ``MSG:`` sections)."""
    if type_name in TYPESTORE.types or not text:
        return
    sections = re.split(r"^=+\s*$", text, flags=re.MULTILINE)
    found: dict[str, Any] = {}
    for index, section in enumerate(sections):
        name = type_name
        if index:
            header, _, section = section.strip("\n").partition("\n")
            if not header.startswith("MSG: "):
                continue
            name = normalise(header[5:].strip())
        if name not in TYPESTORE.types:
            found.update(get_types_from_msg(section, name))
    TYPESTORE.register(found)


def msgdef(type_name: str) -> tuple[str, str]:
    """(``ros2msg`` definition text with its dependencies, RIHS01 hash) of an installed type."""
    type_name = ensure_type(type_name)
    text, _md5 = TYPESTORE.generate_msgdef(type_name, ros_version=2)
    return text, TYPESTORE.hash_rihs01(type_name)
