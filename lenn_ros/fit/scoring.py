"""The frozen model on the test part: its one-step and free-run figures, where it extrapolates, and its bands.

The test samples only score the model: one-step and free run across the record's gaps
(:func:`score`), the share of the free run's error where a signal leaves the training
range (:func:`beyond_training_range`), whether the test part is a record of its own that
its own first samples must seed (:func:`separate_test_record`), and 95 % bands from
errors on samples the model was not fitted to (:func:`fit_intervals`). Apart from the
procedure: all of it reads the model delivered and the samples, nothing of how the model
was chosen.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lenn_ros.core.evaluation import free_run_problems, free_run_segments, join_verdict
from lenn_ros.core.metrics import band_half_width, coverage, nmse_db, rmse
from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.structure import Identifier
from lenn_ros.core.threads import cores, side_by_side
from lenn_ros.fit.data import Data
from lenn_ros.fit.numbering import number, span
from lenn_ros.fit.record import Record
from lenn_ros.fit.result import OutputFit, OutputReport
from lenn_ros.fit.selection import out_of_fold_residuals
from lenn_ros.fit.termmodel import TermModel


@dataclass
class TestPart:
    """The frozen model on the test part: each output's figures (its bands, model and choices are the
    procedure's to add), the free run of all outputs together, and each output's one-step predictions over
    the training rows (what a model the blocks did not run takes its bands from: :func:`fit_intervals`)."""

    outputs: list[OutputReport]
    free_run: dict[str, Any]
    y_hat_train: list[np.ndarray]


def score(
    identifier: Identifier | MimoIdentifier,
    data: Data,
    start: int,
    models: list[TermModel],
    columns: list[list[int]],
) -> TestPart:
    """Test-part figures of the frozen model, per output: one-step and free run from sample ``start``.

    ``data.breaks`` (samples that start a new run: gaps in a bag) are never crossed: the
    one-step pass and the free run restart from the measured outputs after each
    (:func:`~lenn_ros.core.evaluation.free_run_segments`, as ``evaluate`` does); the samples
    that seed them are not scored. Several outputs run their free run together, each fed the
    model's outputs. ``models``: each output's terms as the identifier runs them, over the
    ``columns`` of [y, u] of its view (clipped inputs and the training range are counted there).
    The samples the free run's description names are numbered as ``data`` numbers them
    (:mod:`~lenn_ros.fit.numbering`), whatever rows were left out before the test part.
    """
    u, y = data.matrices()
    single = isinstance(identifier, Identifier)
    run_u, run_y = (u[:, 0], y[:, 0]) if single else (u, y)
    cuts = sorted(int(b) for b in data.breaks if 0 < b < len(y))
    y_hat = np.full(y.shape, np.nan)
    window = identifier.structure.warm_up
    for a, b in itertools.pairwise([0, *cuts, len(y)]):
        if b - a > window:
            y_hat[a:b] = identifier.run(run_u[a:b], run_y[a:b], learn=False).reshape(b - a, -1)
    values = np.column_stack([y, u])
    seedable = start not in cuts and len(y) - start > 2 * window  # its own seed leaves most of it to score
    views = [values[:, c] for c in columns]
    record_of_its_own = separate_test_record(models, views, start, cuts) if seedable else ""
    if record_of_its_own:  # the test part is seeded by its own first samples, as after a gap
        y_hat[start : start + window] = np.nan
        cuts = sorted([*cuts, start])
    index = np.arange(len(y)) + np.searchsorted(cuts, np.arange(len(y)), side="right")  # one lost per break
    y_free, info = free_run_segments(identifier, index, run_u, run_y, start)
    y_free = y_free.reshape(len(y) - start, -1)
    info = {
        **info,
        "starts_from": f"measured outputs of samples {span(data, start, min(start + window, len(y)) - 1)}, not scored"
        if start in cuts
        else f"measured outputs before sample {number(data, start)}",
        "test_record_of_its_own": record_of_its_own,
    }
    healthy = not info["diverged"]
    outputs = [
        _figures(name, model, values[:, columns[j]], start, (y[start:, j], y_hat[start:, j], y_free[:, j]), info,
                 healthy)
        for j, (name, model) in enumerate(zip(data.y_names, models, strict=True))
    ]  # fmt: skip
    return TestPart(outputs, info, [y_hat[:start, j] for j in range(len(models))])


def _figures(
    name: str,
    model: TermModel,
    view: np.ndarray,
    start: int,
    series: tuple[np.ndarray, np.ndarray, np.ndarray],
    info: dict[str, Any],
    healthy: bool,
) -> OutputReport:
    """One output's test figures. ``view``: its [y, u] columns over the whole record; ``series``: its test
    samples, the model's one-step predictions and its free run over them; ``info``: the free run of all
    outputs, ``healthy`` when it did not diverge."""
    y_test, one_step, free = series
    simulated, predicted = np.isfinite(free), np.isfinite(one_step)
    ok = healthy and bool(simulated.any())
    x_test, _ = model.layout.regressors(view[start - model.warm_up :])
    scaled = (view[start:] - np.asarray(model.layout.offsets)) / np.asarray(model.layout.scales)
    return OutputReport(
        name=name,
        samples=len(y_test),
        rmse=rmse(y_test[predicted], one_step[predicted]),
        nmse_db=nmse_db(y_test[predicted], one_step[predicted]),
        rmse_free_run=rmse(y_test[simulated], free[simulated]) if ok else math.nan,
        nmse_free_run_db=nmse_db(y_test[simulated], free[simulated]) if ok else math.nan,
        free_run=info,
        clipped_inputs_one_step=int(np.count_nonzero(np.abs(x_test) > 1.0)),
        test_samples_outside_training_range={
            "u": int(np.count_nonzero(np.abs(scaled[:, 1:]) > 1.0)),
            "y": int(np.count_nonzero(np.abs(scaled[:, 0]) > 1.0)),
        },
        beyond_training_range=beyond_training_range(view, start, model.layout.names, y_test - free),
        warnings=free_run_problems(y_test[simulated], free[simulated], info),
        y_test=y_test,
        y_hat_test=one_step,
        y_free_test=free,
    )


def beyond_training_range(
    view: np.ndarray, start: int, names: tuple[str, ...], free_error: np.ndarray
) -> dict[str, Any]:
    """The test samples where a signal the model reads lies beyond the range its training samples span, and the
    share of the free run's squared error they carry (``free_error``: the free run's errors, NaN where it did
    not run). There the model extrapolates: a level the record never reached (a tank filled higher than in
    training) is where a polynomial bends away, however well it simulated inside (a tank at -16 dB carried 39 %
    of its error in the quarter of its test that was above its training levels)."""
    low, high = view[:start].min(axis=0), view[:start].max(axis=0)
    test = view[start:]
    outside = (test < low) | (test > high)
    rows = outside.any(axis=1)
    squared = np.where(np.isfinite(free_error), free_error, 0.0) ** 2
    total = float(squared.sum())
    return {
        "samples": int(rows.sum()),
        "by_signal": {name: int(count) for name, count in zip(names, outside.sum(axis=0), strict=True) if count},
        "free_run_error_share": float(squared[rows].sum()) / total if total > 0 else 0.0,
    }


def separate_test_record(models: list[TermModel], views: list[np.ndarray], start: int, cuts: list[int]) -> str:
    """Why the test part is a record of its own, not the build part's continuation ('' if it continues).

    The rule is :func:`~lenn_ros.core.evaluation.join_verdict` (evaluate's too), on each output's
    chosen structure; any output whose verdict says so marks the split. ``views``: each output's
    [y, u] columns over the whole record; rows whose regressors reach across one of the ``cuts``
    (gaps) are neither fitted nor judged.
    """

    def verdict(job: tuple[TermModel, np.ndarray]) -> str:
        model, view = job
        record = Record.of(view, cuts)
        warm = model.warm_up
        features, targets = model.regression(record.values)
        sample = np.arange(warm, record.n)
        valid = record.valid_rows(warm)
        build, join = valid & (sample < start), valid & (sample >= start) & (sample < start + warm)
        return join_verdict(features, targets, build, join, warm)

    jobs = list(zip(models, views, strict=True))
    return next((text for text in side_by_side(verdict, jobs, cores()) if text), "")


def fit_intervals(
    part: OutputReport, y_hat_train: np.ndarray, identifier: Identifier | None, fitted: OutputFit, held_out: bool
) -> dict[str, Any]:
    """Nominal 95 % bands of one output, one step ahead and in free run, and how much of the test part they cover.

    Both from errors on samples the model was not fitted to: the blocks the structure
    was chosen by, each run by the weights fitted without it (``held_out``), one step
    ahead and in free run. An MLP or SGD model, which the blocks did not run, takes its
    own errors over the training record (in-sample: optimistic, and said). A
    half-width is the 95 % quantile of |e|, not 1.96 sigma: free-run errors drift and
    have heavy tails. The one-step std is also the noise the twin node may add. ``part``: the output's
    test figures and series; ``y_hat_train``: its one-step predictions over the training rows.
    """
    record = fitted.record
    y_train = record.y
    if held_out:
        one_step = out_of_fold_residuals(fitted.chosen, record, one_step=True)
        free = out_of_fold_residuals(fitted.chosen, record)
        source = "the selection's blocks, each run by the weights fitted without it"
    else:
        warm = identifier.structure.warm_up
        one_step = y_hat_train[warm:] - y_train[warm:]
        free = identifier.free_run(record.values[:, 1], y_train, warm) - y_train[warm:]
        source = "the delivered model over the training record (in-sample: optimistic)"
    one_step = one_step[np.isfinite(one_step)]
    one_step_width, free_width = band_half_width(one_step), band_half_width(free)
    y_test = part.y_test
    return {
        "level": 0.95,
        "one_step": {
            "half_width": one_step_width,
            "std": float(np.std(one_step)) if len(one_step) else math.nan,
            "from": f"{len(one_step)} one-step errors of {source}",
            "coverage_test": coverage(y_test, part.y_hat_test, one_step_width),
        },
        "free_run": {
            "half_width": free_width,
            "from": f"{int(np.count_nonzero(np.isfinite(free)))} errors of {source}",
            "coverage_test": coverage(y_test, part.y_free_test, free_width),
        },
    }
