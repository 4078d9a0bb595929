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
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros import bag as bags
from lenn_ros import topics
from lenn_ros.fit_data import Data, FitError

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
    """u, y (and the gaps between them) of a bag, paired as the node pairs them; see the module docstring."""
    from lenn_ros.bag.vectors import read_test_start
    from lenn_ros.evaluate import EvaluateError, configuration, make_session, pair_raw

    types = bags.topic_types(path)
    short = {topic.rstrip("/").rsplit("/", 1)[-1] for topic in types}
    configured = topics.IDENTIFIER_CONFIG in short
    plain = {topics.U, topics.Y_P} <= short  # a simulator's or import-csv's u / y_p: the defaults read them
    if not (configured or plain) and not (flags.get("u") and flags.get("y")):
        listed = ", ".join(sorted(types)) or "none"
        raise FitError(
            f"{path}: no identifier_config in the bag to say what its topics mean: pass --u TOPIC --u-field PATH "
            f"--y TOPIC --y-field PATH (and --sample-period T for topics from separate nodes); topics: {listed}"
        )
    try:
        identifier, values = configuration(str(path), None) if configured else (_default_identifier(), _defaults())
        values = _with_flags(values, flags, types, path)
        index, u, y, by_order = pair_raw(str(path), make_session(identifier, values), values)
    except (EvaluateError, ValueError) as error:
        raise FitError(str(error).splitlines()[0]) from None
    if np.ndim(u) > 1 or np.ndim(y) > 1:
        raise FitError(f"{path}: the identifier read several channels (MIMO); fit them from a CSV (import-csv)")
    u, y = np.asarray(u, dtype=np.float64), np.asarray(y, dtype=np.float64)
    good = np.isfinite(u) & np.isfinite(y)
    index, u, y = index[good], u[good], y[good]
    if len(index) < 2:
        raise FitError(f"{path}: only {len(index)} samples could be paired; check the fields and the pairing")
    resolved = values[topics.RESOLVED_TOPICS]
    source = (
        f"bag {path}: {resolved.get(topics.U, topics.U)} {values['u_field']}, "
        f"{resolved.get(topics.Y_P, topics.Y_P)} {values['y_field']}, paired by "
        f"{'order' if by_order else values['pairing']}"
    )
    recorded_start = read_test_start(path)
    return Data(
        u,
        y,
        source,
        test_start=_row(index, recorded_start) if recorded_start else None,
        breaks=[int(b) for b in np.flatnonzero(np.diff(index) != 1) + 1],
        index=index,
        interpretation={key: values[key] for key in INTERPRETATION if key in values},
    )


def _row(index: np.ndarray, sample: int) -> int:
    """1-based row of the first sample whose index is ``sample`` or later (a recorded test start is an index)."""
    return int(np.searchsorted(index, sample)) + 1


def _defaults() -> dict[str, Any]:
    from lenn_ros.evaluate import _NODE_DEFAULTS

    return {**_NODE_DEFAULTS, topics.RESOLVED_TOPICS: {}}


def _default_identifier():
    """An identifier for the session to pair with: the model does not change how samples are formed."""
    from lenn_ros.config import build_identifier, resolve

    resolved, network = resolve({"example": 0})
    return build_identifier({**_defaults(), **resolved}, network)


def _with_flags(values: dict[str, Any], flags: dict[str, Any], types: dict[str, str], path: Path) -> dict[str, Any]:
    """The node values with what the flags say: a topic's type is the bag's, its field the flag's."""
    values = {**values, topics.RESOLVED_TOPICS: dict(values.get(topics.RESOLVED_TOPICS, {}))}
    for side, node_name in (("u", topics.U), ("y", topics.Y_P)):
        topic = flags.get(side)
        if topic:
            found = next((t for t in types if t == topic or t == f"/{topic.lstrip('/')}"), None)
            if found is None:
                raise FitError(f"{path}: no topic {topic} in the bag (topics: {', '.join(sorted(types)) or 'none'})")
            values[topics.RESOLVED_TOPICS][node_name] = found
            values[f"{side}_type"] = types[found]
        if flags.get(f"{side}_field"):
            values[f"{side}_field"] = flags[f"{side}_field"]
    if flags.get("sample_period"):
        values["sample_period"] = float(flags["sample_period"])
        values["pairing"] = flags.get("pairing") or "sample"
    elif flags.get("pairing"):
        values["pairing"] = flags["pairing"]
    return values
