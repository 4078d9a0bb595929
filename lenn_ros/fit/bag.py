"""The samples of a recording, as the identifier node pairs them, for ``lenn-ros fit BAG``.

A robot's bag holds its own topics (a driver's ``sensor_msgs/JointState``, a
controller's ``std_msgs/Float64MultiArray``), not ``u`` and ``y_p``. What they mean is
what the identifier was told: types, fields, pairing and sample period. The recorder
keeps that in ``identifier_config`` (with the topics the node's inputs resolved to
after remapping); without it, flags say the same (``--u TOPIC --u-field PATH --y TOPIC
--y-field PATH --sample-period T``). The raw messages are then paired by the node's
own :class:`~lenn_ros.core.session.Session` (:func:`lenn_ros.service.recording.pair_raw`: every
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
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lenn_ros import topics
from lenn_ros.bag.reader import topic_types
from lenn_ros.bag.vectors import read_test_start
from lenn_ros.config import side_channels
from lenn_ros.core.fields import FieldError
from lenn_ros.core.runs import breaks, finite_rows
from lenn_ros.fit.data import Data, FitError
from lenn_ros.service import RecordingError
from lenn_ros.service.reading import READING, listed
from lenn_ros.service.recording import read_recording

#: node parameters that say how the input topics become samples: copied into the fitted params file
INTERPRETATION = READING


def load_bag(path: Path, flags: dict[str, Any], progress: bool = False) -> Data:
    """u, y (and the gaps between them) of a bag, paired as the node pairs them; see the module docstring.

    ``flags``: what is read (:mod:`lenn_ros.service.reading`: ``u`` / ``y`` a topic, or a list: one topic per
    part of the side, ``u_field``, ``y_field``, ``u_names``, ``y_names``, ``sample_period``, ``pairing``).
    Several channels on a side give (N, channels) arrays, each channel named as the node names it.
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
    names: dict[str, tuple[str, ...]] = {}
    if u.ndim > 1 or y.ndim > 1:
        names = _channel_names(path, values)
        u, y = u.reshape(len(index), -1), y.reshape(len(index), -1)
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


def _channel_names(path: Path, values: dict[str, Any]) -> dict[str, tuple[str, ...]]:
    """``u_names`` / ``y_names`` of a bag read as several channels, as the node names them."""
    try:
        return {"u_names": tuple(side_channels(values, "u")[0]), "y_names": tuple(side_channels(values, "y")[0])}
    except FieldError as error:
        raise FitError(f"{path}: {error}") from None


def _side_source(values: dict[str, Any], resolved: dict[str, str], side: str, name: str) -> str:
    """What the report says a side was read from: its topic(s) and field."""
    topics_listed = [str(t) for t in values.get(f"{side}_topics", [""]) if str(t).strip()]
    shown = ", ".join(topics_listed) if len(topics_listed) > 1 else resolved.get(name, name)
    return f"{shown} {values[f'{side}_field']}"


def has_identifier_config(path: Path) -> bool:
    """Whether the identifier recorded its configuration in the bag (what its topics mean)."""
    return topics.IDENTIFIER_CONFIG in _short_names(topic_types(path))


def _short_names(types: dict[str, str]) -> set[str]:
    return {topic.rstrip("/").rsplit("/", 1)[-1] for topic in types}
