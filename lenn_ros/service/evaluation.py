"""A recording evaluated offline: the identifier's own computation over it, no ROS graph.

The same :class:`~lenn_ros.session.Session` as the node:

- a bag recorded with the identifier running holds its ``samples`` topic (each sample's index,
  time, u, y_p and learn flag, as the node formed them): those samples are learnt again in one
  batched pass, so the figure equals the live one by construction, whatever the recorder lost of
  the raw topics;
- otherwise (or when the topics are named, ``--u`` ...) the raw input topics are paired by the
  session exactly as the node would pair them (:func:`lenn_ros.service.recording.pair_raw`): by the
  recorded sequence number, header stamp or sample grid; every message of the recording is read.

The configuration is the params file given, else the one the identifier recorded in the bag
(``identifier_config``); with topics named and neither, the node's defaults. The live parameter
changes that config logs are applied at their samples through the node's own
:meth:`Session.apply_parameters` code, so the figure stays the live one across them; one that cannot
be applied is said in one line. ``weights_in`` is loaded as the node loads it.

The test part, in the node's sample numbering: ``--test-from K`` (samples K.. are scored, the ones
before learnt from; K is honoured exactly or refused in one line), else the recorded one (the
identifier's frozen phase, or ``test_start``), else the last fifth of the samples, said in the
report's first line (:data:`DEFAULT_TEST_SHARE`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros import topics
from lenn_ros.bag.vectors import read_test_start
from lenn_ros.core.evaluation import Evaluation
from lenn_ros.core.runs import describe_gaps, finite_rows, missing, split_row
from lenn_ros.service import RecordingError
from lenn_ros.service.building import recorded_changes, weights_path
from lenn_ros.service.reading import given
from lenn_ros.service.recording import Reading, raw_losses, read_recording
from lenn_ros.service.scoring import fit_band_coverage, one_step_band, score
from lenn_ros.session import ParameterChange, Session, json_safe

#: Without a recorded test phase or ``--test-from``: the last fifth of the samples is the test part.
DEFAULT_TEST_SHARE = 0.2
#: Live changes that act where halves are screened, paired or shed: part of the recorded samples already,
#: but not of a pairing of the raw u / y_p, which uses the starting values throughout.
PAIRING_PARAMETERS = ("u_limit", "y_limit", "out_of_range", "max_lag")
#: Live changes with no bearing on the figures (where files go, how often the node reports).
NODE_ONLY_PARAMETERS = ("weights_out", "autosave_period", "report_every", "warn_period")


@dataclass
class BagEvaluation:
    """What ``evaluate`` found: per output channel the scores, and how the samples came about."""

    evaluations: dict[str, Evaluation]  # per output channel, in the model's order
    pairs: int
    unpaired: int
    rejected: int
    test_start: int  # sample index of the first test sample
    source: str = "samples"  # what was paired: "samples", or "<topics> by <mode>"
    missing: int = 0  # sample indices absent from the recording
    counters: dict[str, int] = field(default_factory=dict)
    notices: list[str] = field(default_factory=list)
    weights_in: str = ""  # the weights file learning started from ("" = fresh weights)
    gaps: list[str] = field(default_factory=list)  # the missing indices in words (session.describe_gaps)
    intervals: dict[str, Any] = field(default_factory=dict)  # the bands and their coverage here, per output
    test_default: str = ""  # why the test part is where it is, when nobody said (the default)

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
            **({"test_default": self.test_default} if self.test_default else {}),
        }
        if self.single:
            return {**e.as_dict(), **common}
        channels = {name: evaluation.as_dict() for name, evaluation in self.evaluations.items()}
        return json_safe({"channels": channels, "free_run": e.free_run, "samples": e.samples, "trained": e.trained,
                          **common})  # fmt: skip


def change_notes(changes: list[ParameterChange], source: str) -> list[str]:
    """One line per live change: applied at its sample, or why it is not (never silently ignored)."""
    notes = []
    for change in changes:
        for name, value in change.values.items():
            what = f"parameter change: {name}={value!r} from sample {change.from_index} (set live)"
            if name in NODE_ONLY_PARAMETERS:
                continue
            if name in PAIRING_PARAMETERS and source != "samples":
                notes.append(f"{what} NOT applied offline: the raw u / y_p are paired with the starting value")
            else:
                notes.append(f"{what}, applied offline at that sample")
    return notes


def evaluate_bag(
    path: str | Path,
    params: str | None = None,
    test_from: int | None = None,
    node: str = "/identifier",
    flags: dict[str, Any] | None = None,
    progress: bool = False,
) -> BagEvaluation:
    """Train on the bag's training part, score the frozen model on its test part (see the module docstring).

    ``node``: whose section of the params file applies (``/robot1/identifier``), by rcl's rules; ``flags``:
    what is read (:mod:`lenn_ros.service.reading`), over what the configuration says.
    """
    path = Path(path)
    named = given(flags)
    read = read_recording(path, flags, params, node, model=True, recorded=True, progress=progress, defaults=named)
    identifier, values, session = read.identifier, read.values, read.session
    changes = recorded_changes(path)
    index, u, y, source = read.samples.index, read.samples.u, read.samples.y, _source(read, named)
    start, default = _test_part(path, index, read.learn, test_from, source)
    # raw inputs carry no learn flag: the learning parameter as it was set live, up to the test part
    learn = (index < start) & (_learning_switch(index, values, changes) if read.learn is None else read.learn)
    y_hat = session.run_samples(index, u, y, learn, changes)
    evaluations = dict(zip(identifier.names, score(identifier, index, u, y, y_hat, start), strict=True))
    return _result(path, session, values, evaluations, (index, u, y, y_hat), start, source, changes, default)


def _result(
    path: Path,
    session: Session,
    values: dict[str, Any],
    evaluations: dict[str, Evaluation],
    series: tuple[np.ndarray, ...],
    start: int,
    source: str,
    changes: list[ParameterChange],
    default: str,
) -> BagEvaluation:
    """The scores with what the session counted and said, the gaps and the bands."""
    index, u, y, y_hat = series
    first = next(iter(evaluations.values()))
    counters = session.all_counters()
    notices = sorted({f"{n.kind}: {n.text}" for n in session.take_notices() if n.kind != "phase"})
    notices += change_notes(changes, source)
    for topic, lost in raw_losses(path).items():
        notices.append(f"recording: {lost} {topic} messages missing (gaps in their sequence numbers)")
    if first.free_run.get("test_record_of_its_own"):
        notices.append(f"free run: {first.free_run['test_record_of_its_own']}")
    if first.free_run.get("segments", 1) > 1:
        notices.append(
            f"free run: restarted from the measured outputs after each of {first.free_run['segments'] - 1} "
            f"break(s) in the test part (lost or invalid samples); {first.free_run['not_simulated']} test "
            "samples not simulated, not scored"
        )
    absent = missing(index)[1] + int(index[0] - 1)
    rejected = int(np.count_nonzero(~(finite_rows(u) & finite_rows(y))))
    unpaired = sum(counters.get(name, 0) for name in ("unpaired", "dropped_u", "dropped_y"))
    weights_in = str(weights_path(values["weights_in"])) if values.get("weights_in") else ""
    gaps = describe_gaps(index, session.config.pairing, session.config.sample_period)
    stds, bands = session.last_y_hat_std, session.last_y_hat_band
    one_step = one_step_band(index >= start, y, y_hat, stds, list(evaluations), bands)
    intervals = {**fit_band_coverage(weights_in, evaluations), **one_step}
    return BagEvaluation(
        evaluations, len(index), unpaired, rejected, int(start), source, absent, counters, notices, weights_in, gaps,
        intervals, default,
    )  # fmt: skip


def _source(read: Reading, named: bool) -> str:
    """What was paired, as the report's first line says it: the identifier's samples, or the topics and how."""
    samples = read.samples
    if samples.source == "samples":
        return "samples"
    plain = [topic.rsplit("/", 1)[-1] for topic in samples.topics] == [topics.U, topics.Y_P]
    return f"u/y_p by {samples.source.rsplit(' by ', 1)[-1]}" if plain else samples.source


def _test_part(
    path: Path, index: np.ndarray, learn: np.ndarray | None, test_from: int | None, source: str
) -> tuple[int, str]:
    """The first test sample (the node's numbering) and, when nobody said where, why it is there.

    Asked for (``--test-from``): honoured exactly, or refused in one line when no sample would be learnt
    from or scored. Else the recording's (the frozen phase, the ``test_start`` topic), else the default.
    """
    if test_from is not None:
        _split(index, test_from, f"--test-from {test_from}", "")
        return int(test_from), ""
    start = _last_phase_start(index, learn) if learn is not None else None
    if start is None:
        start = read_test_start(path)
    if start is not None:
        _split(index, start, f"{path}: its recorded test start {start}", "; pass --test-from K")
        return int(start), ""
    row = min(len(index) - 1, max(1, round(len(index) * (1.0 - DEFAULT_TEST_SHARE))))
    start = int(index[row])
    return start, (
        f"no test phase recorded (no frozen phase, no test_start): the last {DEFAULT_TEST_SHARE:.0%} of the samples "
        f"are the test part, from sample {start} (--test-from K sets another)"
    )


def _split(index: np.ndarray, k: int, asked: str, fix: str) -> None:
    """The split at sample number ``k`` honoured, or refused in one line (the rule of :func:`core.runs.split_row`)."""
    try:
        split_row(index, k)
    except ValueError as reason:
        joined = " " if str(reason).startswith("is ") else ": "
        raise RecordingError(f"{asked}{joined}{reason}{fix}") from None


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
