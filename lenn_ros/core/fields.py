"""One scalar out of any message: field paths as ``ros2 topic echo --field`` writes them.

A robot's command and measurement rarely come as ``std_msgs/Float64``: a driver
publishes ``sensor_msgs/JointState``, ros2_control's forward command controller a
``Float64MultiArray``, a force sensor a ``WrenchStamped``. The identifier takes one
scalar from each through a path such as ``data``, ``data[0]``, ``position[2]``,
``twist.linear.x`` or, for JointState-like messages, a joint *name* in the brackets
(``position[elbow]``: the index of ``elbow`` in the message's ``name`` list, looked up
on every message because drivers may reorder joints).

This module knows nothing of ROS: it walks attributes, so it serves rclpy messages
live and the messages rosbags deserialises from a recording alike. :func:`check_path`
validates a path against a message class before any data arrives, so a typo is a
one-line error at start rather than silence later.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

_STEP = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[[^\[\]]+\])*)")
_INDEX = re.compile(r"\[([^\[\]]+)\]")


class FieldError(ValueError):
    """A field path that does not fit the message, with the reason in one line."""


@dataclass(frozen=True)
class _Step:
    attribute: str
    index: int | str | None = None  # int: position; str: a name looked up in the sibling ``name`` list


def parse_path(path: str) -> tuple[_Step, ...]:
    """``twist.linear.x`` -> steps; ``position[elbow]`` -> (position, 'elbow')."""
    text = path.strip()
    if not text:
        raise FieldError("empty field path (e.g. 'data', 'data[0]', 'position[elbow]', 'twist.linear.x')")
    steps: list[_Step] = []
    for part in text.split("."):
        match = _STEP.fullmatch(part)
        if match is None:
            raise FieldError(f"field path {path!r}: cannot read {part!r} (expected name or name[index])")
        indices = _INDEX.findall(match.group(2))
        if len(indices) > 1:
            raise FieldError(f"field path {path!r}: one index per field at most")
        index: int | str | None = None
        if indices:
            token = indices[0].strip()
            index = int(token) if re.fullmatch(r"-?\d+", token) else token
        steps.append(_Step(match.group(1), index))
    return tuple(steps)


def _fields_of(message_class: Any) -> dict[str, str] | None:
    getter = getattr(message_class, "get_fields_and_field_types", None)
    return dict(getter()) if getter is not None else None


def _element_type(type_text: str) -> str | None:
    """'sequence<double>' / 'double[3]' / 'sequence<geometry_msgs/Point, 5>' -> element type."""
    match = re.fullmatch(r"sequence<([^,>]+)(?:,\s*\d+)?>", type_text)
    if match:
        return match.group(1)
    match = re.fullmatch(r"(.+)\[\d*\]", type_text)
    return match.group(1) if match else None


_NUMERIC = {
    "double", "float", "int8", "uint8", "int16", "uint16", "int32", "uint32",
    "int64", "uint64", "octet", "boolean", "byte", "char",
}  # fmt: skip


def _nested_class(message_class: Any, type_text: str) -> Any:
    """The class of a nested message field ('geometry_msgs/Vector3')."""
    import importlib

    package, _, name = type_text.partition("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


#: Message types whose field of this name is an array, to name in a hint (``data[1]`` on a Float64).
ARRAY_TYPES = {
    "data": "std_msgs/msg/Float64MultiArray",
    "position": "sensor_msgs/msg/JointState",
    "velocity": "sensor_msgs/msg/JointState",
    "effort": "sensor_msgs/msg/JointState",
}


def _not_an_array(shown: str, attribute: str, type_text: str, path: str, type_key: str) -> str:
    """An [index] on a scalar field. The index is usually what the user meant (``data[1]``: the
    topic carries an array) and the type is the default one left unset: name the type to set first."""
    example = ARRAY_TYPES.get(attribute, "std_msgs/msg/Float64MultiArray")
    return (
        f"{shown}: {attribute} is {type_text}, not an array, so {path!r} has no element to index: if the topic "
        f"carries an array, set {type_key} to its type (one with {attribute}[], e.g. {type_key}:={example}); "
        f"if it is one {type_text}, drop the [index]"
    )


def check_path(message_class: Any, path: str, type_name: str = "", type_key: str = "the type") -> None:
    """Raise :class:`FieldError` unless ``path`` leads to a number in ``message_class``.

    Uses the rosidl field table of rclpy message classes; what only the data can tell
    (an index past the end, a joint name absent) is reported per message instead.
    ``type_key`` names the setting that chose the class (``u_type``), for the hints.
    """
    shown = type_name or getattr(message_class, "__name__", "message")
    current: Any = message_class
    type_text = ""
    for depth, step in enumerate(parse_path(path)):
        fields = _fields_of(current)
        if fields is None:
            return  # not a rosidl class: the data will tell
        if step.attribute not in fields:
            options = ", ".join(sorted(fields)) or "none"
            raise FieldError(f"{shown} has no field {step.attribute!r} in {path!r} (fields: {options})")
        type_text = fields[step.attribute]
        if step.index is not None:
            element = _element_type(type_text)
            if element is None:
                raise FieldError(_not_an_array(shown, step.attribute, type_text, path, type_key))
            if isinstance(step.index, str) and "name" not in fields:
                raise FieldError(f"{shown} has no 'name' list to look {step.index!r} up in; use a number in {path!r}")
            type_text = element
        if "/" in type_text:
            current = _nested_class(current, type_text)
        elif depth < len(path.split(".")) - 1:
            raise FieldError(f"{shown}: {step.attribute} is a {type_text}, it has no fields ({path!r})")
    if type_text not in _NUMERIC:
        hint = " (give an [index])" if _element_type(type_text) else ""
        raise FieldError(f"{shown}: {path!r} is a {type_text or 'message'}, not a number{hint}")


def compile_path(path: str) -> Callable[[Any], float]:
    """A function message -> float for ``path``; raises FieldError on a message that lacks it."""
    steps = parse_path(path)

    def extract(message: Any) -> float:
        current = message
        for step in steps:
            current = _step_into(current, step, path)
        if isinstance(current, bool | int | float):
            return float(current)
        try:
            return float(current)  # numpy scalars
        except (TypeError, ValueError):
            raise FieldError(f"{path!r} is not a number: {type(current).__name__}") from None

    return extract


def _step_into(parent: Any, step: _Step, path: str) -> Any:
    """One step of a field path: the attribute, then its element (a joint name looked up in ``parent.name``)."""
    try:
        current = getattr(parent, step.attribute)
    except AttributeError:
        raise FieldError(f"message has no field {step.attribute!r} ({path!r})") from None
    if step.index is None:
        return current
    index = step.index
    if isinstance(index, str):
        names = list(getattr(parent, "name", ()))
        if index not in names:
            raise FieldError(f"no joint {index!r} in name {names} ({path!r})")
        index = names.index(index)
    try:
        return current[index]
    except IndexError:
        raise FieldError(f"{step.attribute} has {len(current)} elements, no [{index}] ({path!r})") from None


def stamp_seconds(message: Any) -> float | None:
    """``header.stamp`` in seconds, or None for a message without a header."""
    header = getattr(message, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def has_header(message_class: Any) -> bool:
    """Whether messages of this class carry a ``std_msgs/Header`` (so a stamp)."""
    fields = _fields_of(message_class)
    if fields is None:
        return hasattr(message_class, "header")
    return fields.get("header") == "std_msgs/Header"


# -- several channels from one message (MIMO) -----------------------------------------------------
ALL = "[*]"


def is_vector(text: str) -> bool:
    """A field setting that names several channels: a comma-separated list, or ``name[*]``."""
    return "," in text or ALL in text


def split_paths(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def channel_names(text: str, names: list[str] | tuple[str, ...] = ()) -> list[str]:
    """The channels a field setting names, as they are shown in outputs and status.

    ``names`` (the ``u_names``/``y_names`` parameter; empty: none given) wins; a list
    of paths names each channel by its joint name (``position[elbow]`` -> ``elbow``) or
    its path; ``name[*]`` takes all elements and needs ``names`` for how many.
    """
    names = [name for name in names if name]
    if ALL in text:
        if len(split_paths(text)) != 1 or not text.strip().endswith(ALL) or text.count(ALL) != 1:
            raise FieldError(f"{text!r}: [*] takes all elements of one array, as in 'effort[*]'; no list around it")
        if not names:
            raise FieldError(
                f"{text!r} takes all elements, so give the channels' names (and so their number): "
                "u_names / y_names, e.g. [shoulder, elbow]; or list the fields: 'effort[0], effort[1]'"
            )
        return names
    paths = split_paths(text)
    if names and len(names) != len(paths):
        raise FieldError(f"{len(names)} names for {len(paths)} fields in {text!r}")
    if names:
        return names
    shown = []
    for path in paths:
        last = parse_path(path)[-1]
        shown.append(last.index if isinstance(last.index, str) else path)
    if len(set(shown)) != len(shown):
        raise FieldError(f"{text!r} names one channel twice")
    return shown


def check_vector(message_class: Any, text: str, type_name: str = "", type_key: str = "the type") -> None:
    """:func:`check_path` for each channel of a vector setting (``[*]`` checked as element 0)."""
    for path in split_paths(text):
        check_path(message_class, path.replace(ALL, "[0]"), type_name, type_key)


def compile_vector(text: str, names: list[str] | tuple[str, ...] = ()) -> Callable[[Any], np.ndarray]:
    """A function message -> vector of the channels ``text`` names (see :func:`channel_names`).

    ``name[*]`` on a message with a ``name`` list (JointState) picks the named joints in
    the order of ``names``, by name only (drivers reorder joints): a name the message
    lacks is an error, never a guess by position, even when the counts agree (a driver
    that renamed one joint would otherwise feed its value to another channel). An array
    without a ``name`` list beside it (``data[*]``) is taken as it is and must hold
    exactly one value per channel.
    """
    wanted = channel_names(text, names)
    if ALL not in text:
        extractors = [compile_path(path) for path in split_paths(text)]
        return lambda message: np.array([extract(message) for extract in extractors], dtype=np.float64)
    array_path = text.strip()[: -len(ALL)]
    steps = parse_path(array_path)

    def extract(message: Any) -> np.ndarray:
        parent = message
        for step in steps[:-1]:
            parent = _step_into(parent, step, array_path)
        values = getattr(parent, steps[-1].attribute, None)
        if values is None:
            raise FieldError(f"message has no field {steps[-1].attribute!r} ({text!r})")
        listed = getattr(parent, "name", None)
        if listed is not None:
            return _by_name(list(listed), values, wanted, text)
        if len(values) != len(wanted):
            raise FieldError(f"{text!r} has {len(values)} elements, the model has {len(wanted)} channels {wanted}")
        return np.asarray(values, dtype=np.float64).copy()

    return extract


def _by_name(listed: list[str], values: Any, wanted: list[str], text: str) -> np.ndarray:
    """The values of the ``wanted`` joints from a message's ``name`` list and its array, by name only."""
    missing = [name for name in wanted if name not in listed]
    if missing:
        raise FieldError(
            f"no joint {', '.join(map(repr, missing))} in name {listed} ({text!r}): joints are picked by name, "
            "never by position (u_names / y_names must be the message's names)"
        )
    positions = [listed.index(name) for name in wanted]
    if max(positions) >= len(values):
        raise FieldError(f"{text!r}: {len(values)} values for the {len(listed)} names {listed}")
    return np.array([values[position] for position in positions], dtype=np.float64)


# -- the other way: values into a message (the twin publishes as the robot does) -------------------
def compose(message: Any, text: str, values: Any, names: list[str] | tuple[str, ...] = ()) -> Any:
    """Write ``values`` into ``message`` where the field setting ``text`` reads them; returns ``message``.

    The inverse of :func:`compile_path` / :func:`compile_vector`, so a message composed
    here reads back as ``values`` through the same setting: ``data`` sets the field,
    ``data[2]`` grows the array to three elements, ``position[elbow]`` names the joint
    in the sibling ``name`` list (JointState), ``name[*]`` sets the whole array (with
    ``names`` as the joints' names where the message has a ``name`` list). Nested
    messages on the way (``twist.linear.x``) are the message's own.
    """
    flat = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if ALL in text:
        wanted = channel_names(text, names)
        if len(flat) != len(wanted):
            raise FieldError(f"{len(flat)} values for the {len(wanted)} channels of {text!r}")
        steps = parse_path(text.strip()[: -len(ALL)])
        parent = _parent_of(message, steps, text)
        if hasattr(parent, "name"):
            parent.name = list(wanted)
        setattr(parent, steps[-1].attribute, [float(v) for v in flat])
        return message
    paths = split_paths(text)
    if len(paths) != len(flat):
        raise FieldError(f"{len(flat)} values for the {len(paths)} fields of {text!r}")
    for path, value in zip(paths, flat, strict=True):
        steps = parse_path(path)
        parent, last = _parent_of(message, steps, path), steps[-1]
        if last.index is None:
            setattr(parent, last.attribute, float(value))
            continue
        array = list(getattr(parent, last.attribute))
        index = last.index
        if isinstance(index, str):  # a joint by name: its place in the name list, added at the end if new
            listed = list(getattr(parent, "name", []))
            if index not in listed:
                listed.append(index)
                parent.name = listed
            index = listed.index(index)
        if index < 0:
            raise FieldError(f"{path!r}: a negative index cannot be written")
        array += [0.0] * (index + 1 - len(array))
        array[index] = float(value)
        setattr(parent, last.attribute, array)
    return message


def _parent_of(message: Any, steps: tuple[_Step, ...], path: str) -> Any:
    """The object holding the last step's field: the nested messages of the steps before it."""
    parent = message
    for step in steps[:-1]:
        if step.index is not None:
            raise FieldError(f"{path!r}: only the last field of a path written may be indexed")
        try:
            parent = getattr(parent, step.attribute)
        except AttributeError:
            raise FieldError(f"message has no field {step.attribute!r} ({path!r})") from None
    if not hasattr(parent, steps[-1].attribute):
        raise FieldError(f"message has no field {steps[-1].attribute!r} ({path!r})")
    return parent
