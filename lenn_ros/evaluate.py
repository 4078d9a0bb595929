"""``lenn-ros evaluate BAG``: the identifier's own computation over a recording.

No ROS graph, the same :class:`~lenn_ros.core.session.Session` as the node:

- a bag recorded with the identifier running holds its ``samples`` topic (each
  sample's index, time, u, y_p and learn flag, as the node formed them): those
  samples are learnt again in one batched pass, so the figure equals the live one
  by construction, whatever the recorder lost of the raw u / y_p topics;
- otherwise the raw u and y_p messages are paired by the session exactly as the node
  would pair them (its pairing mode, message types and field paths, from the params
  file): by the recorded sequence number, header stamp or sample grid. A bag without
  sequence numbers (an import, an old recorder) is paired by order only when both
  topics have the same count, and says so.

The configuration is the params file given, else the one the identifier recorded in
the bag (``identifier_config``); without either, evaluate stops and says what to pass.
The live parameter changes that config logs (``changes``: alpha halved at sample k...) are
applied at their samples through the node's own :meth:`Session.apply_parameters` code, so the
figure stays the live one across them; one that cannot be applied is said in one line.
The identifier is built as the node builds it: when the configuration names
``weights_in``, learning starts from those weights (a relative path is taken from the
current directory, as the node takes it from its own), so a model written by
``lenn-ros fit -o DIR`` or a bag of a node started from one is scored from the weights
it really started from, not from fresh ones.
Every gap, refused or clipped sample and an unstable free run are reported, and each
thing that makes the figures mean less is a warning (text and ``warnings`` in JSON).

One path for any number of channels: a model of several outputs is learnt by the same
session and scored output by output with the same code (its free run of all outputs
together, restarted after every break), reported as one table; one output keeps the
single figures.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros import bag as bags
from lenn_ros import topics
from lenn_ros.bag.vectors import read_test_start
from lenn_ros.config import (
    NODE_PARAMETERS,
    build_identifier,
    field_extractor,
    input_topics,
    read_params_file,
    resolve,
)
from lenn_ros.core.evaluation import Evaluation, finite_rows, free_run_problems, free_run_segments
from lenn_ros.core.fields import stamp_seconds
from lenn_ros.core.metrics import coverage, nmse_db, rmse
from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.pairing import U, Y
from lenn_ros.core.session import ParameterChange, Session, SessionConfig, describe_gaps, json_safe
from lenn_ros.core.spread import Z95
from lenn_ros.core.structure import Identifier
from lenn_ros.fit.data import REPORT_FILE

_NODE_DEFAULTS = {parameter.name: parameter.default for parameter in NODE_PARAMETERS}
RESOLVED_TOPICS = topics.RESOLVED_TOPICS


class EvaluateError(ValueError):
    """A recording or configuration evaluate cannot use, with the fix in one line."""


@dataclass
class BagEvaluation:
    evaluations: dict[str, Evaluation]  # per output channel, in the model's order
    pairs: int
    unpaired: int
    rejected: int
    test_start: int  # sample index of the first test sample
    source: str = "samples"  # what was paired: "samples", or "u/y_p by <mode>"
    missing: int = 0  # sample indices absent from the recording
    counters: dict[str, int] = field(default_factory=dict)
    notices: list[str] = field(default_factory=list)
    weights_in: str = ""  # the weights file learning started from ("" = fresh weights)
    gaps: list[str] = field(default_factory=list)  # the missing indices in words (session.describe_gaps)
    intervals: dict[str, Any] = field(default_factory=dict)  # the bands and their coverage here, per output

    @property
    def evaluation(self) -> Evaluation:
        """The first (for one output, the only) output's scores."""
        return next(iter(self.evaluations.values()))

    @property
    def single(self) -> bool:
        return len(self.evaluations) == 1

    @property
    def channels(self) -> dict[str, dict[str, float]]:
        """Per output channel: NMSE (dB) and RMSE one-step and in free run on the test part."""
        keys = ("nmse_db", "rmse", "nmse_free_run_db", "rmse_free_run")
        return {name: {key: getattr(e, key) for key in keys} for name, e in self.evaluations.items()}

    @property
    def warnings(self) -> list[str]:
        """What makes the figures mean less, each with its fix; the free run's own problems last."""
        found = []
        clipped = self.counters.get("clipped_inputs", 0)
        if clipped:
            found.append(
                f"{clipped} one-step network inputs (training and test) were outside [-1, 1] and clipped: the "
                "params file's y_scale/u_scale and y_offset/u_offset do not cover these signals (offset = middle "
                "of the range, scale = half the range plus a margin); set them, or let lenn-ros fit take them "
                "from the data"
            )
        if self.counters.get("diverged", 0):
            found.append(
                f"learning diverged ({self.counters['diverged']} time(s), resumed {self.counters.get('resumed', 0)} "
                "time(s)): the weights were rolled back to the last healthy block and learning paused (resuming "
                "after resume_after blocks), so the test scores weights learnt around the divergence; lower alpha "
                "(or nlms_step), set y_scale/u_scale/offsets for the signals, or use lenn-ros fit"
            )
        for name, evaluation in self.evaluations.items():
            found += [text if self.single else f"{name}: {text}" for text in evaluation.free_run_warnings]
        return found

    def as_dict(self) -> dict[str, Any]:
        e = self.evaluation
        common = {
            "pairs": self.pairs,
            "unpaired": self.unpaired,
            "rejected": self.rejected,
            "test_start": self.test_start,
            "skipped": e.skipped + self.unpaired + self.rejected,
            "source": self.source,
            "missing": self.missing,
            "gaps": self.gaps,
            "free_run_unstable": any(
                ev.free_run_warnings and not all("clipped" in w for w in ev.free_run_warnings)
                for ev in self.evaluations.values()
            ),
            "counters": self.counters,
            "notices": self.notices,
            "weights_in": self.weights_in,
            "intervals": self.intervals,
            "warnings": self.warnings,
        }
        if self.single:
            return {**e.as_dict(), **common}
        channels = {name: evaluation.as_dict() for name, evaluation in self.evaluations.items()}
        return json_safe({"channels": channels, "free_run": e.free_run, "samples": e.samples, "trained": e.trained,
                          **common})  # fmt: skip


def identifier_from_params(path: str | None, node: str = "/identifier") -> tuple[Identifier, dict]:
    """The identifier a params file describes for the node ``node`` (fully qualified, rcl's matching rules,
    as the node itself is given its parameters), and every node value (defaults filled in)."""
    values = read_params_file(path, node) if path else {}
    resolved, network = resolve(values)
    values = {**_NODE_DEFAULTS, **values}
    # the fields say how many channels (MIMO): node-level values, which resolve() leaves out
    identifier = build_identifier({**values, **resolved}, network)
    return _as_node_builds_it(identifier, values, f"params file {path}"), values


def weights_path(value: str) -> Path:
    """``weights_in`` as the identifier node opens it: ``~`` expanded, a relative path from the cwd.

    The node cannot know which params file a value came from (ROS merges them), so it
    opens the path from its working directory; evaluate does the same, so one params
    file means the same model in both. ``lenn-ros fit -o DIR`` writes an absolute path.
    """
    return Path(os.path.expanduser(value))


def _as_node_builds_it(identifier: Identifier, values: dict[str, Any], source: str) -> Identifier:
    """What the node's ``_build_model`` adds to the bare identifier: divergence guard and start weights."""
    identifier.health_interval = int(values["health_interval"])
    identifier.divergence_ratio = float(values["divergence_ratio"])
    identifier.resume_after = int(values["resume_after"])
    if values.get("weights_in"):
        path = weights_path(values["weights_in"])
        if not path.is_file():
            raise EvaluateError(
                f"weights_in {path} (from the {source}) does not exist (a relative path is taken from the current "
                f"directory {Path.cwd()}, as the identifier node does): run from there, give an absolute path, "
                "or set weights_in to '' for fresh weights"
            )
        (identifier if isinstance(identifier, MimoIdentifier) else identifier.model).load_state(path)
        identifier.mark_healthy()
    return identifier


def configuration(
    path: str, params: str | None, node: str = "/identifier", weights: bool = True
) -> tuple[Identifier, dict[str, Any]]:
    """The identifier and node values a recording is read with: the params file given (``node``'s sections of
    it, by rcl's rules), else its identifier_config. ``weights=False``: the recorded configuration without the
    weights learning started from (``weights_in``), which pairing a record does not need (fit builds its own
    model; the file may have stayed on the robot)."""
    if params:
        return identifier_from_params(params, node)
    recorded = [message for message in bags.iter_messages(path, [topics.IDENTIFIER_CONFIG])]
    if not recorded:
        raise EvaluateError(
            f"{path}: the bag holds no identifier configuration (identifier_config); pass --params FILE, the "
            "params file the identifier ran with (e.g. config/example1_lenn.yaml)"
        )
    values = json.loads(recorded[-1].message.data)
    values.pop(topics.PARAMETER_CHANGES, None)  # (recorded_changes reads them: the values are the starting ones)
    values.setdefault("resume_after", 0)  # recorded before learning resumed by itself: it never did live
    if not weights:
        values["weights_in"] = ""
    network = values.pop("network", "lenn")
    resolved_topics = values.pop(RESOLVED_TOPICS, {})
    model_values, _ = resolve({**{k: v for k, v in values.items() if k not in _NODE_DEFAULTS}, "network": network})
    values = {**_NODE_DEFAULTS, **values, RESOLVED_TOPICS: resolved_topics}
    identifier = build_identifier({**values, **model_values}, network)
    return _as_node_builds_it(identifier, values, f"identifier configuration recorded in {path}"), values


def recorded_changes(path: str) -> list[ParameterChange]:
    """The live parameter changes the identifier recorded (``identifier_config``'s change log), in order.

    Each republished config carries the whole log: the last one read has them all (a
    recorder that joined late still got it, the topic being latched).
    """
    logs = [
        json.loads(m.message.data).get(topics.PARAMETER_CHANGES)
        for m in bags.iter_messages(path, [topics.IDENTIFIER_CONFIG])
    ]
    logs = [log for log in logs if log]
    return [ParameterChange.from_dict(entry) for entry in logs[-1]] if logs else []


#: Live changes that act where halves are screened, paired or shed: part of the recorded samples already,
#: but not of a pairing of the raw u / y_p, which uses the starting values throughout.
PAIRING_PARAMETERS = ("u_limit", "y_limit", "out_of_range", "max_lag")
#: Live changes with no bearing on the figures (where files go, how often the node reports).
NODE_ONLY_PARAMETERS = ("weights_out", "autosave_period", "report_every", "warn_period")


def change_notes(changes: list[ParameterChange], source: str, mimo: bool) -> list[str]:
    """One line per live change: applied at its sample, or why it is not (never silently ignored)."""
    notes = []
    for change in changes:
        for name, value in change.values.items():
            what = f"parameter change: {name}={value!r} from sample {change.from_index} (set live)"
            if name in NODE_ONLY_PARAMETERS:
                continue
            if mimo:
                notes.append(f"{what} NOT applied offline: a MIMO model is evaluated with the starting values")
            elif name in PAIRING_PARAMETERS and source != "samples":
                notes.append(f"{what} NOT applied offline: the raw u / y_p are paired with the starting value")
            else:
                notes.append(f"{what}, applied offline at that sample")
    return notes


def make_session(identifier: Identifier, values: dict[str, Any]) -> Session:
    """The node's session over a recording: its pairing, learning on (the phases are the recording's)."""
    return Session(identifier, SessionConfig.from_values(values, follow_test_start=False, learning=True))


def _recorded_samples(path: str, identifier: Identifier | MimoIdentifier) -> tuple[np.ndarray, ...] | None:
    """The identifier's own samples, sorted by index (a repeated index: the first, as live)."""
    shape = (identifier.structure.n_u, identifier.structure.n_y) if isinstance(identifier, MimoIdentifier) else (1, 1)
    samples = bags.read_samples(path, None, *shape)
    if samples is None or samples.index.size == 0:
        return None
    index, _time, u, y, learn = samples.ordered()
    return index, u, y, learn


def _raw_losses(path: str) -> dict[str, int]:
    """Messages of u / y_p missing from the recording, from gaps in their sequence numbers."""
    info = bags.bag_info(path)["topics"]
    losses = {}
    for topic, entry in info.items():
        name = topic.rstrip("/").rsplit("/", 1)[-1]
        if name in (topics.U, topics.Y_P) and entry.get("missing"):
            losses[topic] = int(entry["missing"])
    return losses


def recorded_topic(path: str, types: dict[str, str], name: str, values: dict[str, Any]) -> str:
    """The bag's topic the node read as ``name``: the name it resolved (remapped) to, else one ending in ``name``.

    The identifier records its resolved input topics in ``identifier_config``
    (``resolved_topics``: ``u`` -> ``/arm/joint_cmd``), which is what the recorder saw.
    """
    resolved = values.get(RESOLVED_TOPICS, {}).get(name)
    if resolved in types:
        return resolved
    short = name.rstrip("/").rsplit("/", 1)[-1]
    found = [topic for topic in types if topic == name or topic.rstrip("/").rsplit("/", 1)[-1] == short]
    if not found:
        shown = f"{name} (remapped to {resolved})" if resolved else name
        raise EvaluateError(f"{path}: no {shown} topic in the bag (topics: {', '.join(sorted(types)) or 'none'})")
    return found[0]


def pair_raw(path: str, session: Session, values: dict[str, Any]) -> tuple[np.ndarray, ...]:
    """Pair the recorded u / y_p messages the way the node would have: (index, u, y, paired by order)."""
    types = bags.topic_types(path)
    names, parts = {}, {}
    for channel, part, name in input_topics(values):
        topic = recorded_topic(path, types, name, values)
        names[topic], parts[topic] = channel, part
    extract = {side: field_extractor(values, side) for side in (U, Y)}
    messages = list(bags.iter_messages(path, list(names)))
    by_order = values["pairing"] == "sequence" and not any(message.sequence for message in messages)
    if by_order:
        counts = [sum(1 for m in messages if names[m.topic] == channel) for channel in (U, Y)]
        if counts[0] != counts[1]:
            raise EvaluateError(
                f"{path}: no sequence numbers recorded and u has {counts[0]} messages, y_p {counts[1]}: pairing "
                "by order would shift every later pair; record with lenn_ros's recorder (it stores indices)"
            )
    if values["pairing"] == "sequence" and not by_order:
        messages = _in_index_order(messages, names)
    session.holding = True  # collect the pairs; they are learnt in one batch below
    seen = {U: 0, Y: 0}
    for message in messages:
        channel = names[message.topic]
        seen[channel] += 1
        stamp = stamp_seconds(message.message) if values["use_header_stamp"] else None
        received = message.log_time_ns * 1e-9
        session.offer(
            channel,
            extract[channel](message.message),
            stamp if stamp is not None else received,
            received=received,
            sequence=seen[channel] if by_order else message.sequence,
            source_time=None if by_order else (message.publish_time_ns * 1e-9 or None),
            part=parts[message.topic],
        )
    session.flush()
    pairs = session.release_pairs()
    index = np.array([pair.index for pair in pairs], dtype=np.int64)
    return index, np.array([p.u for p in pairs]), np.array([p.y for p in pairs]), by_order


def _in_index_order(messages: list, names: dict[str, str]) -> list:
    """Undo reordering in the recording: by publisher run (a restart begins at 1), then index.

    Live, the node can only wait a while for a late half; offline the whole recording is
    known, so a message that arrived late still meets its partner.
    """
    epochs: dict[str, int] = {}
    highest: dict[str, int] = {}
    keyed = []
    for position, message in enumerate(messages):
        channel = names[message.topic]
        if message.sequence == 1 and highest.get(channel, 0) > 1:
            epochs[channel] = epochs.get(channel, 0) + 1
            highest[channel] = 0
        highest[channel] = max(highest.get(channel, 0), message.sequence)
        keyed.append((epochs.get(channel, 0), message.sequence, position, message))
    return [item[-1] for item in sorted(keyed, key=lambda item: item[:3])]


def evaluate_bag(
    path: str, params: str | None = None, test_from: int | None = None, node: str = "/identifier"
) -> BagEvaluation:
    """Train on the bag's training phase, score the frozen model on its test phase.

    ``node``: whose section of the params file applies (``/robot1/identifier``), by rcl's rules.
    """
    identifier, values = configuration(path, params, node)
    session = make_session(identifier, values)
    changes = recorded_changes(path)
    index, u, y, learn, start, source = _samples(path, session, values, test_from, changes)
    mimo = isinstance(identifier, MimoIdentifier)
    notes = change_notes(changes, source, mimo)
    names = list(identifier.names) if mimo else ["y"]
    y_hat = session.run_samples(index, u, y, learn, () if mimo else changes)
    evaluations = dict(zip(names, _score(identifier, index, u, y, y_hat, start), strict=True))
    first = next(iter(evaluations.values()))
    counters = session.all_counters()
    notices = sorted({f"{n.kind}: {n.text}" for n in session.take_notices() if n.kind != "phase"}) + notes
    for topic, lost in _raw_losses(path).items():
        notices.append(f"recording: {lost} {topic} messages missing (gaps in their sequence numbers)")
    if first.free_run.get("segments", 1) > 1:
        notices.append(
            f"free run: restarted from the measured outputs after each of {first.free_run['segments'] - 1} "
            f"break(s) in the test part (lost or invalid samples); {first.free_run['not_simulated']} test "
            "samples not simulated, not scored"
        )
    missing = int(np.sum(np.clip(np.diff(index) - 1, 0, None))) + int(index[0] - 1)
    rejected = int(np.count_nonzero(~(finite_rows(u) & finite_rows(y))))
    unpaired = sum(counters.get(name, 0) for name in ("unpaired", "dropped_u", "dropped_y"))
    weights_in = str(weights_path(values["weights_in"])) if values.get("weights_in") else ""
    gaps = describe_gaps(index, session.config.pairing, session.config.sample_period)
    bands = fit_band_coverage(weights_in, evaluations)
    intervals = {**bands, **one_step_band(index >= start, y, y_hat, session)} if not mimo else bands
    return BagEvaluation(
        evaluations, len(index), unpaired, rejected, int(start), source, missing, counters, notices, weights_in, gaps,
        intervals,
    )  # fmt: skip


def one_step_band(test: np.ndarray, y: np.ndarray, y_hat: np.ndarray, session: Session) -> dict[str, Any]:
    """The node's nominal 95 % one-step band (``y_hat_std``, as published live) and what it covers of the test part.

    ``run_samples`` gives every prediction the std the node published with it (RLS
    covariance and innovation variance, ``core.spread``), so this is the band live users saw.
    """
    std = session.last_y_hat_std
    if len(std) != len(y):
        return {}
    scored = test & np.isfinite(y_hat) & np.isfinite(std)
    if not scored.any():
        return {}
    half = Z95 * std[scored]
    return {
        "level": 0.95,
        "one_step": {
            "median_half_width": float(np.median(half)),
            "from": "the node's y_hat_std (RLS covariance and innovation variance), as published live",
            "coverage_test": float(np.mean(np.abs(y[scored] - y_hat[scored]) <= half)),
        },
    }


def fit_band_coverage(weights_in: str, evaluations: dict[str, Evaluation]) -> dict[str, Any]:
    """The nominal 95 % free-run band of the fit the weights came from (its ``fit.json``), and what it covers here.

    The band is the fit's estimate (errors on its held-out blocks); the model scored here
    went on learning from the bag's training phase, so the coverage says how well the
    fit's uncertainty carries over to this recording. Several outputs: one band each,
    under ``free_run`` by output name. Empty without a fit report.
    """
    report = Path(weights_in).parent / REPORT_FILE if weights_in else None
    if report is None or not report.is_file():
        return {}
    try:
        fitted = json.loads(report.read_text())
    except (OSError, ValueError):
        return {}
    parts = fitted.get("per_output") or [fitted]
    covered = {}
    for (name, evaluation), part in zip(evaluations.items(), parts, strict=False):
        width = part.get("intervals", {}).get("free_run", {}).get("half_width")
        if not width:
            continue
        simulated = np.isfinite(evaluation.y_free_test)
        share = coverage(evaluation.y_test[simulated], evaluation.y_free_test[simulated], float(width))
        covered[name] = {"half_width": float(width), "from": str(report), "coverage_test": share}
    if not covered:
        return {}
    return {"level": 0.95, "free_run": covered["y"] if list(covered) == ["y"] else covered}


def _samples(
    path: str, session: Session, values: dict[str, Any], test_from: int | None, changes: list[ParameterChange]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, str]:
    """(index, u, y, learn, test start, source): the identifier's recorded samples, else the raw u / y_p paired
    as the node pairs them; u and y have a column per channel for a MIMO model."""
    recorded_start = read_test_start  # (the test_start topic alone: u / y_p may be remapped, or vectors)
    recorded = _recorded_samples(path, session.identifier)
    if recorded is not None:
        index, u, y, learn = recorded
        source = "samples"
        start = test_from if test_from is not None else _last_phase_start(index, learn)
        if start is None:  # the identifier learnt throughout: score from the recorded test_start
            start = recorded_start(path)
        if test_from is not None:
            learn = learn & (index < test_from)
    else:
        index, u, y, by_order = pair_raw(path, session, values)
        source = f"u/y_p by {'order (no sequence numbers recorded)' if by_order else values['pairing']}"
        start = test_from if test_from is not None else recorded_start(path)
        if start is None:
            raise EvaluateError(f"{path}: no test_start topic in the bag; pass --test-from K (1-based sample index)")
        learn = (index < start) & _learning_switch(index, values, changes)
    if len(index) == 0:
        raise EvaluateError(f"{path}: no samples could be paired ({source}); see the notices above")
    if start is None or start < index[0] + 1 or start > index[-1]:
        raise EvaluateError(f"test start {start} outside the bag's samples {index[0] + 1}..{index[-1]}")
    return index, u, y, learn, int(start), source


def _learning_switch(index: np.ndarray, values: dict[str, Any], changes: list[ParameterChange]) -> np.ndarray:
    """Per sample, the ``learning`` parameter in effect (its starting value, then each live change from its
    sample): the raw u / y_p carry no learn flag, the recorded samples do."""
    switch = np.full(index.shape, bool(values.get("learning", True)))
    for change in sorted(changes, key=lambda change: change.from_index):
        if "learning" in change.values:
            switch[index >= change.from_index] = bool(change.values["learning"])
    return switch


def _last_phase_start(index: np.ndarray, learn: np.ndarray) -> int | None:
    """First index of the final frozen phase (None if the run never froze)."""
    if learn[-1]:
        return None
    changes = np.flatnonzero(learn[:-1] & ~learn[1:])
    return int(index[changes[-1] + 1]) if changes.size else int(index[0])


def _score(
    identifier: Identifier | MimoIdentifier,
    index: np.ndarray,
    u: np.ndarray,
    y: np.ndarray,
    y_hat: np.ndarray,
    start: int,
) -> list[Evaluation]:
    """Each output's scores over the test part: one-step, and the free run of all outputs together (restarted
    from the measured outputs after every break)."""
    test = index >= start
    first = int(np.argmax(test))
    y_free, free_run = free_run_segments(identifier, index, u, y, first)
    columns = y.reshape(len(y), -1)
    predicted = y_hat.reshape(len(y), -1)
    simulated_all = y_free.reshape(len(y_free), -1)
    return [_score_output(columns[:, j], predicted[:, j], simulated_all[:, j], free_run, test)
            for j in range(columns.shape[1])]  # fmt: skip


def _score_output(
    y: np.ndarray, y_hat: np.ndarray, y_free: np.ndarray, free_run: dict[str, Any], test: np.ndarray
) -> Evaluation:
    scored = test & np.isfinite(y_hat)
    y_test = y[test]
    simulated = np.isfinite(y_test) & (np.isfinite(y_free) | free_run["diverged"])
    if not simulated.any():
        simulated[:] = True  # nothing could be simulated: the figures are NaN, and said so
    train = ~test & np.isfinite(y_hat)
    free_ok = not free_run["diverged"] and simulated.any() and np.all(np.isfinite(y_free[simulated]))
    return Evaluation(
        free_run=free_run,
        free_run_warnings=free_run_problems(y_test[simulated], y_free[simulated], free_run),
        nmse_db=nmse_db(y[scored], y_hat[scored]) if scored.any() else math.nan,
        nmse_free_run_db=nmse_db(y_test[simulated], y_free[simulated]) if free_ok else math.nan,
        rmse=rmse(y[scored], y_hat[scored]) if scored.any() else math.nan,
        rmse_free_run=rmse(y_test[simulated], y_free[simulated]) if free_ok else math.nan,
        samples=int(scored.sum()),
        trained=int(train.sum()),
        skipped=int((~np.isfinite(y_hat[~test])).sum()),
        y_test=y_test,
        y_hat_test=y_hat[test],
        y_free_test=y_free,
        train_errors=(y - y_hat)[train],
    )


def band_lines(intervals: dict[str, Any]) -> list[str]:
    """The one-step and free-run 95 % bands and their coverage of the test part, one line each."""
    lines = []
    one, run = intervals.get("one_step"), intervals.get("free_run")
    if one:
        width, covered = one["median_half_width"], one["coverage_test"]
        lines.append(f"  one-step 95 % band (y_hat_std, median +-{width:.4g}): covers {covered:.1%}")
    if run:
        lines.append(
            f"  free-run 95 % band of the fit (+-{run['half_width']:.4g}): covers {run['coverage_test']:.1%} here"
        )
    return lines


def main(args) -> int:
    result = evaluate_bag(args.bag, args.params, args.test_from, getattr(args, "node", "/identifier"))
    if args.plot:
        _plot(args, result)
    d = result.as_dict()
    if args.json:
        print(json.dumps(d, indent=1, default=lambda value: None))
        return 0
    print(f"bag {args.bag}: {d['pairs']} samples from {d['source']}, test from sample {d['test_start']}")
    if d["weights_in"]:
        print(f"  learning started from the weights in {d['weights_in']} (weights_in)")
    for line in d["gaps"]:
        print(f"  {line}")
    print(f"  trained on {d['trained']} samples, scored {d['samples']} test samples, skipped {d['skipped']}")
    for line in _figure_lines(result, d):
        print(line)
    for warning in d["warnings"]:
        print(f"  WARNING: {warning}")
    for notice in d["notices"]:
        print(f"  note: {notice}")
    return 0


def _figure_lines(result: BagEvaluation, d: dict[str, Any]) -> list[str]:
    """The scores: one output's two lines and bands, or several outputs' table and bands."""
    lines = []
    if result.single:
        for label, key, rmse_key in (
            ("one-step", "nmse_db", "rmse"),
            ("free-run", "nmse_free_run_db", "rmse_free_run"),
        ):
            value = d[key]
            shown = f"{value:8.3f} dB" if value is not None and math.isfinite(value) else str(value)
            lines.append(f"  NMSE {label}: {shown}   RMSE {d[rmse_key]}")
        return lines + band_lines(d["intervals"])
    lines.append("  channel        NMSE one-step   NMSE free run   RMSE one-step   RMSE free run")
    for name, scores in result.channels.items():
        cells = [scores[key] for key in ("nmse_db", "nmse_free_run_db", "rmse", "rmse_free_run")]
        shown = [f"{value:13.3f}" if math.isfinite(value) else f"{'nan':>13s}" for value in cells]
        lines.append(f"  {name:12s} " + "   ".join(shown))
    for name, band in d["intervals"].get("free_run", {}).items():
        width, covered = band["half_width"], band["coverage_test"]
        lines.append(f"  {name}: free-run 95 % band of the fit (+-{width:.4g}): covers {covered:.1%} here")
    return lines


def _plot(args: Any, result: BagEvaluation) -> None:
    """``--plot``: plant against the model on the test part (one panel per output), the fit's band if known."""
    from lenn_ros.plotting import plot_channels, plot_identification

    if result.single:
        e = result.evaluation
        title = f"{args.bag}: NMSE {e.nmse_db:.2f} dB one-step, {e.nmse_free_run_db:.2f} dB free run"
        band = result.intervals.get("free_run", {}).get("half_width")
        plot_identification(args.plot, e.y_test, e.y_hat_test, title, e.y_free_test, free_run_band=band)
        return
    names = list(result.evaluations)
    stacked = [np.column_stack([getattr(e, key) for e in result.evaluations.values()])
               for key in ("y_test", "y_hat_test", "y_free_test")]  # fmt: skip
    shown = ", ".join(f"{name} {e.nmse_db:.2f}" for name, e in result.evaluations.items())
    path = plot_channels(args.plot, names, stacked[0], stacked[1], f"{args.bag}: one-step NMSE {shown} dB", stacked[2])
    print(f"  wrote {path}")
