"""The frozen model on the test part: its one-step and free-run figures, where it extrapolates, and its bands.

The test samples only score the model: one-step and free run across the record's gaps
(:func:`score`), the share of the free run's error where a signal leaves the training
range (:func:`beyond_training_range`), whether the test part is a record of its own that
its own first samples must seed (:func:`separate_test_record`), and 95 % bands from
errors on samples the model was not fitted to, wider where a test regressor lies far from the
build data and growing along a free run (:func:`fit_intervals`, :mod:`~lenn_ros.fit.bands`). Apart from the
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
from lenn_ros.fit.bands import (
    LEVEL,
    UNLIKE_SHARE,
    HeldOut,
    HorizonBand,
    OneStepBand,
    held_out_free_runs,
    held_out_one_step,
    horizon_band,
    one_step_band,
    raw_features,
    run_steps,
)
from lenn_ros.fit.data import Data
from lenn_ros.fit.numbering import number, span
from lenn_ros.fit.record import Record
from lenn_ros.fit.result import OutputFit, OutputReport
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
        view_test=view[start - model.warm_up :],
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

    Both from errors on samples the model was not fitted to: the blocks the structure was chosen by, each run
    by the weights fitted without it (``held_out``), one step ahead and in free run. The one-step band widens
    with the regressor's distance from the build data, the free-run band grows with the steps since the run's
    start (:mod:`~lenn_ros.fit.bands`: one number each covered 76-80 % of some test parts). An MLP or SGD
    model, which the blocks did not run, takes its own errors over the training record (in-sample:
    optimistic, and said), and a band of one number each (one run tells little of how errors grow along
    runs). The one-step std is also the noise the twin node may add. ``part``: the output's test figures and
    series (its per-sample half-widths are set here, for the plot); ``y_hat_train``: its one-step predictions
    over the training rows.
    """
    record = fitted.record
    if held_out:
        held = held_out_one_step(fitted.chosen, record)
        free, steps, blocks = held_out_free_runs(fitted.chosen, record)
        source = "the selection's blocks, each run by the weights fitted without it (refined as the model's)"
    else:
        warm = identifier.structure.warm_up
        errors = y_hat_train[warm:] - record.y[warm:]
        held = HeldOut(errors[np.isfinite(errors)], np.empty((0, 0)), np.empty(0, dtype=np.int64))
        free = identifier.free_run(record.values[:, 1], record.y, warm) - record.y[warm:]
        steps = np.zeros(len(free), dtype=np.int64)  # one run, not runs by horizon: its band is one number
        blocks = None
        source = "the delivered model over the training record (in-sample: optimistic)"
    one_step, notes = _one_step(part, fitted, held, source)
    free_run = _free_run(part, free, steps, blocks, source)
    return {"level": LEVEL, "one_step": one_step, "free_run": free_run, **notes}


def _one_step(part: OutputReport, fitted: OutputFit, held: HeldOut, source: str) -> tuple[dict[str, Any], dict]:
    """The one-step band's figures (and the note when the test part is unlike the build part); sets the part's
    per-sample half-widths. One number where the regressors' distance cannot be read (no held-out features, an
    output read as |y|)."""
    band = one_step_band(held) if len(held.features) else None
    features = _test_features(part, fitted) if band is not None else None
    predicted = np.isfinite(part.y_hat_test)
    constant = band_half_width(held.errors)
    figures: dict[str, Any] = {"held_out_half_width": constant}
    notes = {}
    if band is None or features is None:
        widths = np.full(part.samples, constant)
        figures["rule"] = "one number: the 95 % quantile of |e|"
    else:
        widths = band.half_width(*features)
        far = float(np.mean(band.distance(features[0])[predicted] > band.typical_r)) if predicted.any() else 0.0
        figures.update(rule=ONE_STEP_RULE, quantile=band.quantile, far_from_build_test=far, **_covered(band))
        if far > UNLIKE_SHARE:
            notes["unlike_build"] = (
                f"the test part is not drawn like the build part: {far:.0%} of its regressors lie farther from the "
                "build data than 99 % of the build rows do (leverage); the one-step band widens with that distance, "
                "but the held-out blocks vouch for its 95 % only where the test part is like them"
            )
    widths = np.where(predicted, widths, np.nan)
    part.one_step_half_width_test = widths
    return {
        "half_width": _typical(widths),
        "std": float(np.std(held.errors)) if len(held.errors) else math.nan,
        "from": f"{len(held.errors)} one-step errors of {source}",
        "coverage_test": coverage(part.y_test, part.y_hat_test, widths),
        **_extent(widths),
        **figures,
    }, notes


#: how the one-step band is made, as fit.json says it (lenn_ros.fit.bands)
ONE_STEP_RULE = (
    "q l(x) sqrt(1 + r(x)): r the leverage of the regressor's features over its mean among the build rows, l the "
    "local error level; q the 95 % quantile of the held-out errors normalised alike"
)


def _test_features(part: OutputReport, fitted: OutputFit) -> tuple[np.ndarray, np.ndarray] | None:
    """The chosen model's features of every test regressor (:func:`~lenn_ros.fit.bands.raw_features`), None where
    the view scored is not the one the model was fitted on (an output read as |y|, fitted signed)."""
    model, view = fitted.chosen.model, part.view_test
    lead = len(view) - part.samples
    if model is None or (fitted.sign or {}).get("used") or lead < model.warm_up:
        return None
    raw, clipped = raw_features(model, view[lead - model.warm_up :])
    return (raw, clipped) if len(raw) == part.samples else None


def _free_run(
    part: OutputReport, errors: np.ndarray, steps: np.ndarray, blocks: np.ndarray | None, source: str
) -> dict[str, Any]:
    """The free-run band's figures by steps since the run's start; sets the part's per-sample half-widths."""
    band = horizon_band(errors, steps, blocks)
    simulated = np.isfinite(part.y_free_test)
    widths = band.at(run_steps(part.y_free_test)) if band is not None else np.full(part.samples, math.nan)
    widths = np.where(simulated, widths, np.nan)
    part.free_run_half_width_test = widths
    return {
        "half_width": _typical(widths),
        "from": f"{int(np.count_nonzero(np.isfinite(errors)))} errors of {source}"
        + (", by steps since the run's start" if band is not None and len(band.starts) > 1 else ""),
        "coverage_test": coverage(part.y_test, part.y_free_test, widths),
        **_extent(widths),
        "held_out_half_width": band_half_width(errors),
        **({"by_horizon": band.as_dict()} if band is not None else {}),
        **_covered(band),
    }


def _covered(band: OneStepBand | HorizonBand | None) -> dict[str, list[float]]:
    """``held_out_blocks_covered``: [lowest, highest] share of a held-out block the band calibrated on the other
    blocks covered (:func:`~lenn_ros.fit.bands.blocks_covered`); nothing where it was not measured."""
    covered = band.blocks_covered if band is not None else None
    return {"held_out_blocks_covered": list(covered)} if covered is not None else {}


def _typical(widths: np.ndarray) -> float:
    """A band's typical half-width over the test part: the median of its finite ones (NaN: none)."""
    finite = widths[np.isfinite(widths)]
    return float(np.median(finite)) if len(finite) else math.nan


def _extent(widths: np.ndarray) -> dict[str, float]:
    """The smallest and largest half-width over the test part."""
    finite = widths[np.isfinite(widths)]
    low, high = (float(finite.min()), float(finite.max())) if len(finite) else (math.nan, math.nan)
    return {"half_width_min_test": low, "half_width_max_test": high}
