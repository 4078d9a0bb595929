"""What is read from a recording: topics, fields, channel names, pairing and sample period.

One way to say it for every offline command (``fit``, ``evaluate``, ``bag-info``, and ``replay``'s
parameters), spelled like the identifier node's parameters, because it *is* what the node is told:

- ``--u TOPIC`` / ``--y TOPIC``: the input and output topics as recorded (the node's ``-r u:=TOPIC``;
  repeated: one topic per part of the side, the node's ``u_topics`` / ``y_topics``);
- ``--u-field PATH`` / ``--y-field PATH``: ``data[1]``, ``position[elbow]``, ``data[*]`` (``u_field`` ...);
- ``--u-names A,B`` / ``--y-names A,B``: the channels' names (``u_names`` ...);
- ``--pairing MODE``, ``--sample-period T`` (``sample`` pairing on that grid), ``--slop S``.

Where nothing is given, the identifier's configuration recorded in the bag (``identifier_config``,
with the topics its inputs were remapped to) says it, else a params file, else the node's
defaults (``u`` and ``y_p``, ``std_msgs/Float64`` ``data``, sequence pairing). A topic's type is
always the bag's own.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lenn_ros import topics
from lenn_ros.service import RecordingError

#: Node parameters that say how the input topics become samples: what a recording is read with, and what
#: ``fit -o`` writes into the params file so the node started from it reads the same topics the same way.
READING = (
    "u_type",
    "y_type",
    "u_field",
    "y_field",
    "u_topics",
    "y_topics",
    "u_names",
    "y_names",
    "pairing",
    "slop",
    "sample_period",
    "max_delay",
    "y_max_age",
    "max_skew",
    "max_clock_offset",
    "use_header_stamp",
)
#: The flags (argparse destinations) that name what is read.
FLAGS = ("u", "y", "u_field", "y_field", "u_names", "y_names", "sample_period", "pairing", "slop")
#: Node values that decide how many channels a sample has.
CHANNELS = ("u_type", "y_type", "u_field", "y_field", "u_names", "y_names", "u_topics", "y_topics")


def add_flags(parser: argparse.ArgumentParser, csv: bool = False) -> None:
    """The flags of :data:`FLAGS` (``csv``: ``--u`` / ``--y`` also name a data file's columns, as fit's do, and the
    channels of a bag of plain Float64MultiArray ``u`` / ``y_p``, by label)."""
    column = {
        side: f"; for a CSV: the plant {what}'s column (name or 0-based index; default '{side}', or the {which} of two "
        f"columns); repeat for several {what}s (one model per output over every channel). For a bag of plain "
        f"Float64MultiArray u / y_p (import-csv's): a channel's label or 0-based index"
        if csv
        else ""
        for side, what, which in (("u", "input", "first"), ("y", "output", "second"))
    }
    metavar = "TOPIC|COL" if csv else "TOPIC"
    parser.add_argument(
        "--u",
        action="append",
        metavar=metavar,
        help="the input topic as recorded (the node's -r u:=TOPIC; repeated: one topic per part of the side, "
        "u_topics)" + column["u"],
    )
    parser.add_argument(
        "--y", action="append", metavar=metavar, help="the output topic as recorded (-r y_p:=TOPIC)" + column["y"]
    )
    parser.add_argument("--u-field", metavar="PATH", help="field of the input message, e.g. data[1] (u_field)")
    parser.add_argument("--y-field", metavar="PATH", help="field of the output message, e.g. position[elbow] (y_field)")
    parser.add_argument(
        "--u-names",
        metavar="A,B",
        help="the input channels' names, comma-separated (u_names): how many data[*] holds, which joints of a "
        "JointState position[*], in this order",
    )
    parser.add_argument("--y-names", metavar="A,B", help="the output channels' names (y_names), as --u-names")
    parser.add_argument(
        "--sample-period", type=float, metavar="T", help="seconds between samples: pairs on that grid (pairing sample)"
    )
    parser.add_argument(
        "--pairing", choices=["sequence", "stamp", "sample"], help="how the topics become samples (pairing)"
    )
    parser.add_argument("--slop", type=float, metavar="S", help="stamp pairing: largest |t_u - t_y| of a pair (slop)")


def flags_of(args: argparse.Namespace) -> dict[str, Any]:
    """The :data:`FLAGS` an argparse namespace holds (None where not given)."""
    return {key: getattr(args, key, None) for key in FLAGS}


def given(flags: dict[str, Any] | None) -> bool:
    """Whether any flag names what is read."""
    return bool(flags) and any(value not in (None, [], "") for value in flags.values())


def listed(value: str | list[str] | None) -> list[str]:
    """A ``--u`` / ``--y`` flag as a list (the command line repeats them; a caller may pass one)."""
    if not value:
        return []
    return [value] if isinstance(value, str) else [str(item) for item in value if item]


def with_flags(values: dict[str, Any], flags: dict[str, Any] | None, types: dict[str, str], path: Path) -> dict:
    """The node values with what the flags say: a topic's type is the bag's, its field the flag's."""
    values = {**values, topics.RESOLVED_TOPICS: dict(values.get(topics.RESOLVED_TOPICS, {}))}
    flags = flags or {}
    for side, node_name in (("u", topics.U), ("y", topics.Y_P)):
        _side_flags(values, flags, side, node_name, types, path)
    if flags.get("sample_period"):
        values["sample_period"] = float(flags["sample_period"])
        values["pairing"] = flags.get("pairing") or "sample"
    elif flags.get("pairing"):
        values["pairing"] = flags["pairing"]
    if flags.get("slop") is not None:
        values["slop"] = float(flags["slop"])
    return values


def _side_flags(
    values: dict[str, Any], flags: dict[str, Any], side: str, node_name: str, types: dict[str, str], path: Path
) -> None:
    """One side's topics (one remapped, or the side's parts), type, field and channel names, into ``values``."""
    found = [bag_topic(topic, types, path) for topic in listed(flags.get(side))]
    if len({types[topic] for topic in found}) > 1:
        shown = ", ".join(f"{topic} ({types[topic]})" for topic in found)
        raise RecordingError(f"{path}: the --{side} topics must share one type (the node's {side}_type): {shown}")
    if len(found) == 1:
        values[topics.RESOLVED_TOPICS][node_name] = found[0]
        values[f"{side}_topics"] = [""]
    elif found:  # one topic per part of the side: the node's u_topics / y_topics
        values[f"{side}_topics"] = found
    if found:
        values[f"{side}_type"] = types[found[0]]
    if flags.get(f"{side}_field"):
        values[f"{side}_field"] = flags[f"{side}_field"]
    if flags.get(f"{side}_names"):
        values[f"{side}_names"] = [name.strip() for name in str(flags[f"{side}_names"]).split(",") if name.strip()]


def bag_topic(topic: str, types: dict[str, str], path: Path) -> str:
    """The bag's topic a flag names (with or without the leading /)."""
    found = next((t for t in types if t == topic or t == f"/{topic.lstrip('/')}"), None)
    if found is None:
        raise RecordingError(f"{path}: no topic {topic} in the bag (topics: {', '.join(sorted(types)) or 'none'})")
    return found


def recorded_topic(path: str | Path, types: dict[str, str], name: str, values: dict[str, Any]) -> str:
    """The bag's topic the node read as ``name``: the name it resolved (remapped) to, else one ending in ``name``.

    The identifier records its resolved input topics in ``identifier_config``
    (``resolved_topics``: ``u`` -> ``/arm/joint_cmd``), which is what the recorder saw.
    """
    resolved = values.get(topics.RESOLVED_TOPICS, {}).get(name)
    if resolved in types:
        return resolved
    short = name.rstrip("/").rsplit("/", 1)[-1]
    found = [topic for topic in types if topic == name or topic.rstrip("/").rsplit("/", 1)[-1] == short]
    if not found:
        shown = f"{name} (remapped to {resolved})" if resolved else name
        raise RecordingError(
            f"{path}: no {shown} topic in the bag (topics: {', '.join(sorted(types)) or 'none'}); name the topics "
            "with --u TOPIC --u-field PATH --y TOPIC --y-field PATH"
        )
    return found[0]


def input_bag_topics(path: str | Path, types: dict[str, str], values: dict[str, Any]) -> list[tuple[str, int, str]]:
    """(side ``u``/``y``, part, the bag's topic) of every input the node would subscribe with these values."""
    from lenn_ros.config import input_topics  # (here: the command line imports this module for its flags)

    return [(side, part, recorded_topic(path, types, name, values)) for side, part, name in input_topics(values)]
