"""The samples of a recording, as the identifier node pairs them, for ``lenn-ros fit BAG``.

A robot's bag holds its own topics (a driver's ``sensor_msgs/JointState``, a
controller's ``std_msgs/Float64MultiArray``), not ``u`` and ``y_p``. What they mean is
what the identifier was told: types, fields, pairing and sample period. The recorder
keeps that in ``identifier_config`` (with the topics the node's inputs resolved to
after remapping); without it, flags say the same (``--u TOPIC --u-field PATH --y TOPIC
--y-field PATH --sample-period T``). The raw messages are then paired by the node's
own :class:`~lenn_ros.core.session.Session` (``evaluate.pair_raw``), so ``fit`` learns
from exactly the samples the node would have formed. A sample index missing from the
pairs (a lost message, a stalled driver, a refused value) is a gap: the fit never joins
the samples on either side of it.

The node values that say how the topics become samples are written into the fitted
params file (:data:`INTERPRETATION`), so the identifier started from it reads the same
topics the same way; the topic names stay the node's relative ``u`` / ``y_p``, so the
same ``--ros-args -r u:=... -r y_p:=...`` remaps apply.

A bag of a robot with several channels (``u_field: data[*]`` with ``u_names``, a
JointState's ``position[*]`` with ``y_names``, or a side's several topics) is read the
same way, by the same session: its vectors come back as one column per channel (named as
the node names them), and ``fit`` builds one model per output over them. Without
``identifier_config`` the flags say it: ``--u-field 'data[*]' --u-names u1,u2``, and
``--u`` repeated for one topic per channel.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros import bag as bags
from lenn_ros import topics
from lenn_ros.fit.data import Data, FitError

#: node parameters that say how the input topics become samples: copied into the fitted params file
INTERPRETATION = (
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


def load_bag(path: Path, flags: dict[str, Any]) -> Data:
    """u, y (and the gaps between them) of a bag, paired as the node pairs them; see the module docstring.

    ``flags``: ``u`` / ``y`` (a topic, or a list: one topic per part of the side), ``u_field``,
    ``y_field``, ``u_names``, ``y_names`` (comma-separated), ``sample_period``, ``pairing``.
    Several channels on a side give (N, channels) arrays, each channel named as the node names it.
    """
    from lenn_ros.bag.vectors import read_test_start
    from lenn_ros.evaluate import EvaluateError, configuration, make_session, pair_raw

    types = bags.topic_types(path)
    short = _short_names(types)
    configured = topics.IDENTIFIER_CONFIG in short
    plain = {topics.U, topics.Y_P} <= short  # a simulator's or import-csv's u / y_p: the defaults read them
    if not (configured or plain) and not (_listed(flags.get("u")) and _listed(flags.get("y"))):
        listed = ", ".join(sorted(types)) or "none"
        raise FitError(
            f"{path}: no identifier_config in the bag to say what its topics mean: pass --u TOPIC --u-field PATH "
            f"--y TOPIC --y-field PATH (and --sample-period T for topics from separate nodes); topics: {listed}"
        )
    try:
        identifier, values = configuration(str(path), None, weights=False) if configured else (None, _defaults())
        given = _with_flags(values, flags, types, path)
        if identifier is None or any(given.get(key) != values.get(key) for key in _CHANNELS):
            identifier = _default_identifier(given)  # as many channels as the flags name
        values = given
        index, u, y, by_order = pair_raw(str(path), make_session(identifier, values), values)
    except (EvaluateError, ValueError) as error:
        raise FitError(str(error).splitlines()[0]) from None
    if len(index) < 2:
        raise FitError(f"{path}: only {len(index)} samples could be paired; check the fields and the pairing")
    u, y = np.asarray(u, dtype=np.float64), np.asarray(y, dtype=np.float64)
    # a refused value (NaN) is a gap, like a lost message: the fit never joins across it
    good = np.isfinite(u.reshape(len(u), -1)).all(axis=1) & np.isfinite(y.reshape(len(y), -1)).all(axis=1)
    index, u, y = index[good], u[good], y[good]
    if len(index) < 2:
        raise FitError(f"{path}: only {len(index)} samples could be paired; check the fields and the pairing")
    resolved = values[topics.RESOLVED_TOPICS]
    source = (
        f"bag {path}: {_side_source(values, resolved, 'u', topics.U)}, "
        f"{_side_source(values, resolved, 'y', topics.Y_P)}, paired by "
        f"{'order' if by_order else values['pairing']}"
    )
    recorded_start = read_test_start(path)
    interpretation = {key: values[key] for key in INTERPRETATION if key in values}
    names: dict[str, tuple[str, ...]] = {}
    if u.ndim > 1 or y.ndim > 1:
        names = _channel_names(path, values)
        u, y = u.reshape(len(index), -1), y.reshape(len(index), -1)
    return Data(
        u,
        y,
        source,
        test_start=_row(index, recorded_start) if recorded_start else None,
        breaks=[int(b) for b in np.flatnonzero(np.diff(index) != 1) + 1],
        index=index,
        interpretation=interpretation,
        **names,
    )


def _channel_names(path: Path, values: dict[str, Any]) -> dict[str, tuple[str, ...]]:
    """``u_names`` / ``y_names`` of a bag read as several channels, as the node names them."""
    from lenn_ros.config import side_channels
    from lenn_ros.core.fields import FieldError

    try:
        return {"u_names": tuple(side_channels(values, "u")[0]), "y_names": tuple(side_channels(values, "y")[0])}
    except FieldError as error:
        raise FitError(f"{path}: {error}") from None


def _side_source(values: dict[str, Any], resolved: dict[str, str], side: str, name: str) -> str:
    """What the report says a side was read from: its topic(s) and field."""
    listed = [str(t) for t in values.get(f"{side}_topics", [""]) if str(t).strip()]
    shown = ", ".join(listed) if len(listed) > 1 else resolved.get(name, name)
    return f"{shown} {values[f'{side}_field']}"


def _listed(given: str | list[str] | None) -> list[str]:
    """A ``--u`` / ``--y`` flag as a list (the command line repeats them; a caller may pass one)."""
    if not given:
        return []
    return [given] if isinstance(given, str) else [str(g) for g in given if g]


def has_identifier_config(path: Path) -> bool:
    """Whether the identifier recorded its configuration in the bag (what its topics mean)."""
    return topics.IDENTIFIER_CONFIG in _short_names(bags.topic_types(path))


def _short_names(types: dict[str, str]) -> set[str]:
    return {topic.rstrip("/").rsplit("/", 1)[-1] for topic in types}


def _row(index: np.ndarray, sample: int) -> int:
    """1-based row of the first sample whose index is ``sample`` or later (a recorded test start is an index)."""
    return int(np.searchsorted(index, sample)) + 1


def _defaults() -> dict[str, Any]:
    from lenn_ros.evaluate import _NODE_DEFAULTS

    return {**_NODE_DEFAULTS, topics.RESOLVED_TOPICS: {}}


#: node values that decide how many channels a sample has (and so which identifier the session pairs for)
_CHANNELS = ("u_type", "y_type", "u_field", "y_field", "u_names", "y_names", "u_topics", "y_topics")


def _default_identifier(values: dict[str, Any]):
    """An identifier for the session to pair with, of the channels ``values`` name (one each, or vectors).

    The model does not change how samples are formed, only how many channels they have.
    """
    from lenn_ros.config import build_identifier, resolve

    resolved, network = resolve({"example": 0})
    names = {key: values[key] for key in ("u_names", "y_names") if key in values}  # (resolve gives defaults)
    return build_identifier({**values, **resolved, **names}, network)


def _with_flags(values: dict[str, Any], flags: dict[str, Any], types: dict[str, str], path: Path) -> dict[str, Any]:
    """The node values with what the flags say: a topic's type is the bag's, its field the flag's."""
    values = {**values, topics.RESOLVED_TOPICS: dict(values.get(topics.RESOLVED_TOPICS, {}))}
    for side, node_name in (("u", topics.U), ("y", topics.Y_P)):
        given = _listed(flags.get(side))
        found = [_bag_topic(topic, types, path) for topic in given]
        if len({types[topic] for topic in found}) > 1:
            shown = ", ".join(f"{topic} ({types[topic]})" for topic in found)
            raise FitError(f"{path}: the --{side} topics must share one type (the node's {side}_type): {shown}")
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
    if flags.get("sample_period"):
        values["sample_period"] = float(flags["sample_period"])
        values["pairing"] = flags.get("pairing") or "sample"
    elif flags.get("pairing"):
        values["pairing"] = flags["pairing"]
    return values


def _bag_topic(topic: str, types: dict[str, str], path: Path) -> str:
    """The bag's topic a flag names (with or without the leading /)."""
    found = next((t for t in types if t == topic or t == f"/{topic.lstrip('/')}"), None)
    if found is None:
        raise FitError(f"{path}: no topic {topic} in the bag (topics: {', '.join(sorted(types)) or 'none'})")
    return found
