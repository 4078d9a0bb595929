"""The samples of a recording, as the identifier node pairs them, for ``lenn-ros fit BAG``.

A robot's bag holds its own topics (a driver's ``sensor_msgs/JointState``, a
controller's ``std_msgs/Float64MultiArray``), not ``u`` and ``y_p``. What they mean is
what the identifier was told: types, fields, pairing and sample period. The recorder
keeps that in ``identifier_config`` (with the topics the node's inputs resolved to
after remapping); without it, flags say the same (``--u TOPIC --u-field PATH --y TOPIC
--y-field PATH --sample-period T``). The raw messages are then paired by the node's
own :class:`~lenn_ros.session.Session` (:func:`lenn_ros.service.recording.pair_raw`: every
message of the recording, any storage), so ``fit`` learns from exactly the samples the node would
have formed, numbered as the node numbers them (``--test-from K`` is one of those numbers). A
sample index missing from the pairs (a lost message, a stalled driver, a refused value) is a gap
(:mod:`lenn_ros.core.runs`): the fit never joins the samples on either side of it.

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

A bag of plain ``u`` / ``y_p`` (a simulator's, ``import-csv``'s) is read the same way, by
the node's defaults: Float64MultiArray samples whole, their channels named by the messages'
labels; ``--u NAME`` / ``--y NAME`` pick channels of such a bag by label, as a CSV's columns
(:func:`channel_picks`). Any storage and path ``open_bag`` takes: a directory (MCAP or
sqlite3, one file or split), its ``.mcap`` file, or a ``.db3`` file beside its metadata.yaml.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lenn_ros import topics
from lenn_ros.bag.reader import find_topic, topic_types
from lenn_ros.bag.vectors import read_test_start
from lenn_ros.config import side_channels
from lenn_ros.core.fields import FieldError, is_vector
from lenn_ros.core.runs import breaks, finite_rows
from lenn_ros.fit.data import Data, FitError
from lenn_ros.service import RecordingError
from lenn_ros.service.reading import READING, listed
from lenn_ros.service.recording import array_width, labelled_names, read_recording

#: node parameters that say how the input topics become samples: copied into the fitted params file
INTERPRETATION = READING


def load_bag(path: Path, flags: dict[str, Any], progress: bool = False) -> Data:
    """u, y (and the gaps between them) of a bag, paired as the node pairs them; see the module docstring.

    ``flags``: what is read (:mod:`lenn_ros.service.reading`: ``u`` / ``y`` a topic, or a list: one topic per
    part of the side, ``u_field``, ``y_field``, ``u_names``, ``y_names``, ``sample_period``, ``pairing``); for
    a bag of plain Float64MultiArray ``u`` / ``y_p`` (``import-csv``'s), ``u`` / ``y`` may name its channels
    instead (:func:`channel_picks`). Several channels on a side give (N, channels) arrays, each channel named as
    the node names it. ``progress``: a bar on stderr while a long recording is read.
    """
    types = topic_types(path)
    short = _short_names(types)
    configured = topics.IDENTIFIER_CONFIG in short
    plain = {topics.U, topics.Y_P} <= short  # a simulator's or import-csv's u / y_p: the defaults read them
    if not (configured or plain) and not (listed(flags.get("u")) and listed(flags.get("y"))):
        shown = ", ".join(f"{topic} ({kind})" for topic, kind in sorted(types.items())) or "none"
        raise FitError(
            f"{path}: no identifier_config in the bag to say what its topics mean: pass --u TOPIC --u-field PATH "
            f"--y TOPIC --y-field PATH (and --sample-period T for topics from separate nodes); topics: {shown}"
        )
    try:
        flags = flags if configured else channel_picks(path, types, flags)
        read = read_recording(path, flags, progress=progress)
    except (RecordingError, ValueError) as error:
        raise FitError(str(error).splitlines()[0]) from None
    samples, values = read.samples, read.values
    # a refused value (NaN) is a gap, like a lost message: the fit never joins across it
    good = finite_rows(samples.u) & finite_rows(samples.y)
    index, u, y = samples.index[good], samples.u[good], samples.y[good]
    if len(index) < 2:
        raise FitError(f"{path}: only {len(index)} samples could be paired; check the fields and the pairing")
    resolved = values[topics.RESOLVED_TOPICS]
    source = (
        f"bag {path}: {_side_source(values, resolved, 'u', topics.U)}, "
        f"{_side_source(values, resolved, 'y', topics.Y_P)}, paired by "
        f"{'order' if samples.by_order else values['pairing']}"
    )
    interpretation = {key: values[key] for key in INTERPRETATION if key in values}
    if u.ndim > 1 or y.ndim > 1:
        names = _channel_names(path, values)
        u, y = u.reshape(len(index), -1), y.reshape(len(index), -1)
    else:  # one channel each: named where the flags picked it by name
        names = {f"{side}_names": tuple(values[f"{side}_names"]) for side in ("u", "y")
                 if len(values.get(f"{side}_names") or ()) == 1}  # fmt: skip
    return Data(
        u,
        y,
        source,
        test_start=read_test_start(path),  # a sample number, as --test-from is
        breaks=[int(b) for b in breaks(index)],
        index=index,
        interpretation=interpretation,
        **names,
    )


def channel_picks(path: Path, types: dict[str, str], flags: dict[str, Any]) -> dict[str, Any]:
    """The flags with ``--u`` / ``--y`` that name channels of a plain Float64MultiArray ``u`` / ``y_p`` (by label,
    as ``import-csv`` writes them, or 0-based index) said as the node's field and names: ``--u b --u a`` reads
    ``data[1], data[0]`` named ``b, a``. So the session reads just those channels, and the params file ``-o``
    writes makes the node read the same. A flag that names a topic of the bag stays a topic."""
    flags = dict(flags)
    for side, name in (("u", topics.U), ("y", topics.Y_P)):
        wanted, topic = listed(flags.get(side)), find_topic(types, name)
        if not wanted or topic is None or types[topic] != topics.FLOAT64_ARRAY or flags.get(f"{side}_field"):
            continue
        if any(_is_topic(item, types) for item in wanted):
            continue
        labels = labelled_names(path, topic) or [f"{side}{i}" for i in range(array_width(path, topic))]
        columns = [_channel(labels, item, path, name) for item in wanted]
        flags[side] = None
        flags[f"{side}_field"] = ", ".join(f"data[{column}]" for column in columns)
        flags[f"{side}_names"] = ",".join(labels[column] for column in columns)
    return flags


def _is_topic(name: str, types: dict[str, str]) -> bool:
    return any(topic == name or topic == f"/{name.lstrip('/')}" for topic in types)


def _channel(names: list[str], column: str, path: Path, topic: str) -> int:
    """A channel by its label or 0-based index, as a CSV column is found."""
    if column in names:
        return names.index(column)
    if column.isdigit() and int(column) < len(names):
        return int(column)
    raise FitError(f"{path}: no {topic} channel or topic {column!r}; its channels are {', '.join(names)}")


def _channel_names(path: Path, values: dict[str, Any]) -> dict[str, tuple[str, ...]]:
    """``u_names`` / ``y_names`` of a bag read as several channels, as the node names them."""
    try:
        return {"u_names": tuple(side_channels(values, "u")[0]), "y_names": tuple(side_channels(values, "y")[0])}
    except FieldError as error:
        raise FitError(f"{path}: {error}") from None


def _side_source(values: dict[str, Any], resolved: dict[str, str], side: str, name: str) -> str:
    """What the report says a side was read from: its topic(s) and field, and the channels' names where the field
    reads several or the flags named one."""
    topics_listed = [str(t) for t in values.get(f"{side}_topics", [""]) if str(t).strip()]
    shown = ", ".join(topics_listed) if len(topics_listed) > 1 else resolved.get(name, name)
    field, names = str(values[f"{side}_field"]), [str(n) for n in values.get(f"{side}_names") or () if str(n)]
    return f"{shown} {field}" + (f" ({', '.join(names)})" if names and (is_vector(field) or len(names) == 1) else "")


def has_identifier_config(path: Path) -> bool:
    """Whether the identifier recorded its configuration in the bag (what its topics mean)."""
    return topics.IDENTIFIER_CONFIG in _short_names(topic_types(path))


def _short_names(types: dict[str, str]) -> set[str]:
    return {topic.rstrip("/").rsplit("/", 1)[-1] for topic in types}
