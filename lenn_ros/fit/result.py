"""What ``fit`` returns: :class:`FitResult`, the report's figures as attributes and the model made, and what it
made of each output (:class:`OutputFit`, :class:`OutputReport`).

The report ``--json`` prints and ``fit -o`` writes as fit.json is :meth:`FitResult.as_dict`
serialised (:meth:`FitResult.to_json`); the text report (:mod:`lenn_ros.fit.report`) reads
the same attributes. A module of its own so that the procedure that makes a result, the
scoring of its test part, its export and its report read it without importing each other.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.structure import Identifier
from lenn_ros.fit.record import Record
from lenn_ros.fit.selection import Candidate
from lenn_ros.fit.termmodel import Layout, TermModel

#: how the names of the series end (the test part's samples, the model's predictions): kept, never serialised
SERIES = "_test"


@dataclass
class OutputFit:
    """What the selection made of one output: its view of the training samples, candidates and choice."""

    name: str
    record: Record
    layout: Layout
    candidates: list[Candidate]
    chosen: Candidate
    refinement: dict[str, Any]
    warnings: list[str] = field(default_factory=list)
    columns: list[int] = field(default_factory=list)  # the view's columns in [y_0.., u_0..]
    #: an output read as its absolute value: what fitting its signed record found and did
    sign: dict[str, Any] | None = None
    delays: tuple[int, ...] = ()  # dead time of each column after the output, in samples (() or 0: none)

    @property
    def model(self) -> TermModel:
        return self.chosen.model


@dataclass
class OutputReport:
    """One output's part of the report: its test figures, its 95 % bands, its model and how that was chosen.

    The fields are the report's, in its order (:meth:`entry`). ``free_run`` is the test
    part's free run, of all outputs together (the same for each). The series (``y_test``,
    the model's one-step ``y_hat_test`` and free-run ``y_free_test`` over the test part, the view the bands read
    and the bands' half-widths per sample) are for the plot and for callers; the report leaves them out.
    """

    name: str
    samples: int
    rmse: float
    nmse_db: float
    rmse_free_run: float
    nmse_free_run_db: float
    free_run: dict[str, Any]
    clipped_inputs_one_step: int
    test_samples_outside_training_range: dict[str, int]
    beyond_training_range: dict[str, Any]
    warnings: list[str]
    y_test: np.ndarray = field(repr=False)
    y_hat_test: np.ndarray = field(repr=False)
    y_free_test: np.ndarray = field(repr=False)
    #: the output's view (its [y, u] columns) over the test part and the samples before it its regressors read
    view_test: np.ndarray = field(default_factory=lambda: np.empty((0, 0)), repr=False)
    #: the 95 % bands' half-width at each test sample, one step ahead and in free run (NaN: no prediction there)
    one_step_half_width_test: np.ndarray = field(default_factory=lambda: np.empty(0), repr=False)
    free_run_half_width_test: np.ndarray = field(default_factory=lambda: np.empty(0), repr=False)
    intervals: dict[str, Any] = field(default_factory=dict)
    model: dict[str, Any] = field(default_factory=dict)
    choices: dict[str, Any] = field(default_factory=dict)

    def entry(self, *, alone: bool) -> dict[str, Any]:
        """This output's figures as the report holds them, series left out: ``alone`` (one input, one output:
        the report's top level) without its name; one of several without its warnings, which the report's own
        list gives with the output's name."""
        left = {"name"} if alone else {"warnings"}
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in left and not _series(f.name)}


def _the_output(name: str) -> property:
    """A figure of the one output's report, read on the result (a model of several outputs: per_output)."""
    return property(lambda self: getattr(self.only, name), doc=f"The one output's ``{name}`` (:attr:`only`).")


@dataclass
class FitResult:
    """What ``fit`` returns: the report's figures as attributes, and the model it made.

    ``data``: what was read. ``test_from``: the number of the first test sample as asked (the
    node's numbering: :mod:`~lenn_ros.fit.numbering`); ``train_samples``: how many samples are numbered
    below it (rows a rule left out included); ``numbers``: the training samples' numbers and the first
    test sample's, where they are not 1..train_samples and ``test_from`` (else {}). ``per_output``: each output's
    figures, bands, model and choices. ``free_run``: the test part's free run, of all outputs
    together. ``model``: the model as the report describes it (one output's; of several, the
    whole, each output's own in its ``per_output`` entry). ``inputs``, ``outputs``: the
    channels' names. ``seconds``: the fit's time. ``left_out``: what each rule that leaves
    training rows out did, by its key (:data:`~lenn_ros.fit.procedure.LEFT_OUT`). ``files``:
    what ``fit -o`` wrote (set by the command). ``records``: the files joined into the data, each a run of its own
    (:mod:`~lenn_ros.fit.records`; empty for one file). Not in the report: the ``identifier`` the
    node runs, each output's terms as the identifier runs them (``models``) and what the
    selection made of each output (``fits``).
    """

    data: str
    test_from: int
    train_samples: int
    per_output: list[OutputReport]
    free_run: dict[str, Any]
    model: dict[str, Any]
    inputs: list[str]
    outputs: list[str]
    seconds: float
    identifier: Identifier | MimoIdentifier = field(repr=False)
    models: list[TermModel] = field(repr=False)
    fits: list[OutputFit] = field(repr=False)
    left_out: dict[str, dict[str, Any]] = field(default_factory=dict)
    files: dict[str, str] | None = None
    numbers: dict[str, Any] = field(default_factory=dict)
    records: list[dict[str, Any]] = field(default_factory=list)

    rmse = _the_output("rmse")
    nmse_db = _the_output("nmse_db")
    rmse_free_run = _the_output("rmse_free_run")
    nmse_free_run_db = _the_output("nmse_free_run_db")
    clipped_inputs_one_step = _the_output("clipped_inputs_one_step")
    test_samples_outside_training_range = _the_output("test_samples_outside_training_range")
    beyond_training_range = _the_output("beyond_training_range")
    intervals = _the_output("intervals")
    choices = _the_output("choices")

    @property
    def alone(self) -> bool:
        """One input and one output: the report gives the output's figures at its top level."""
        return len(self.inputs) == 1 and len(self.per_output) == 1

    @property
    def only(self) -> OutputReport:
        """The one output's report (a model of several outputs has none: read ``per_output``)."""
        if len(self.per_output) != 1:
            raise AttributeError(f"a model of {len(self.per_output)} outputs: read each in per_output")
        return self.per_output[0]

    @property
    def samples(self) -> int:
        """Test samples (every output's)."""
        return self.per_output[0].samples

    @property
    def warnings(self) -> list[str]:
        """The report's warnings: the one output's, or every output's named by it."""
        if self.alone:
            return self.only.warnings
        return [f"{part.name}: {text}" for part in self.per_output for text in part.warnings]

    @property
    def y_test(self) -> np.ndarray:
        """The test part's measured outputs (several outputs, or inputs: one column each)."""
        return self._series("y_test")

    @property
    def y_hat_test(self) -> np.ndarray:
        """The model's one-step predictions over the test part (NaN where it was seeded)."""
        return self._series("y_hat_test")

    @property
    def y_free_test(self) -> np.ndarray:
        """The model's free run over the test part, all outputs together (NaN where it did not run)."""
        return self._series("y_free_test")

    def _series(self, name: str) -> np.ndarray:
        if self.alone:
            return getattr(self.only, name)
        return np.column_stack([getattr(part, name) for part in self.per_output])

    def as_dict(self) -> dict[str, Any]:
        """The report as ``--json`` prints it: plain JSON values (NaN and inf as None), the series left out.

        One input and one output: the output's figures at the top level; several: the model
        as a whole, each output's figures in ``per_output`` and the warnings named by output.
        Then the time taken, what the rules that leave rows out did, and the files written.
        """
        head = {"data": self.data, "test_from": self.test_from, "train_samples": self.train_samples}
        if self.numbers:  # (a record whose rows are its numbers reads as it always did)
            head["sample_numbers"] = self.numbers
        if self.records:
            head["records"] = self.records
        figures = self.only.entry(alone=True) if self.alone else self._several()
        files = {} if self.files is None else {"files": self.files}
        return _plain({**head, **figures, "seconds": self.seconds, **self.left_out, **files})

    def _several(self) -> dict[str, Any]:
        return {
            "samples": self.samples,
            "inputs": self.inputs,
            "outputs": self.outputs,
            "model": self.model,
            "per_output": [part.entry(alone=False) for part in self.per_output],
            "free_run": self.free_run,
            "warnings": self.warnings,
        }

    def to_json(self) -> str:
        """The report as ``--json`` prints it and fit.json holds it (strict JSON)."""
        return json.dumps(self.as_dict(), indent=1, allow_nan=False)


def _series(name: str) -> bool:
    return name.endswith(SERIES)


def _plain(value: Any) -> Any:
    """Strict JSON values: numpy scalars as numbers, tuples as lists, NaN/inf as None (a diverged run)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
