"""A test part scored: one-step and free run (restarted from the measured outputs after every break), and the
95 % bands with what they cover. Used by ``evaluate`` (a recording) and by ``fit``'s reading of a bag's fit.

The free run's restarts are :func:`lenn_ros.core.evaluation.free_run_segments` (the gap rule of
:mod:`lenn_ros.core.runs`); a model of several outputs is run with all its outputs together and scored
output by output with the same code as one output.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros.core.evaluation import Evaluation, free_run_problems, free_run_segments, join_verdict
from lenn_ros.core.metrics import coverage, nmse_db, rmse
from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.runs import finite_rows, runs
from lenn_ros.core.spread import Z95
from lenn_ros.core.structure import Identifier
from lenn_ros.fit.bands import HorizonBand, run_steps
from lenn_ros.fit.data import REPORT_FILE


def score(
    identifier: Identifier | MimoIdentifier,
    index: np.ndarray,
    u: np.ndarray,
    y: np.ndarray,
    y_hat: np.ndarray,
    start: int,
) -> list[Evaluation]:
    """Each output's scores over the samples from ``start`` on: one-step (``y_hat``), and the free run of all
    outputs together (restarted from the measured outputs after every break). A test part that is a record of
    its own (:func:`~lenn_ros.core.evaluation.join_verdict`, fit's rule) is seeded by its own first samples,
    which are not scored, as fit scores it."""
    test = index >= start
    first = int(np.argmax(test))
    own = test_record_of_its_own(identifier, index, u, y, first)
    if own:  # a break at the split: as after a gap
        index = index + (np.arange(len(index)) >= first)
        y_hat = np.array(y_hat, dtype=np.float64, copy=True)
        y_hat[first : first + identifier.structure.warm_up] = np.nan
    y_free, free_run = free_run_segments(identifier, index, u, y, first)
    free_run["test_record_of_its_own"] = own
    columns = y.reshape(len(y), -1)
    predicted = y_hat.reshape(len(y), -1)
    simulated_all = y_free.reshape(len(y_free), -1)
    return [_score_output(columns[:, j], predicted[:, j], simulated_all[:, j], free_run, test)
            for j in range(columns.shape[1])]  # fmt: skip


def test_record_of_its_own(identifier: Identifier | MimoIdentifier, index: np.ndarray, u: np.ndarray,
                           y: np.ndarray, first: int) -> str:  # fmt: skip
    """Why the test part from row ``first`` is a record of its own ('' if it continues the build part): fit's
    rule (:func:`~lenn_ros.core.evaluation.join_verdict`) on each output's structure, over the rows whose
    regressors lie within one run of valid samples (:func:`~lenn_ros.core.runs.runs`). A functional-link model's
    features are its terms; an MLP's, its regressors (a linear model of them). Any output may mark the split."""
    starts, stops = runs(index, finite_rows(u) & finite_rows(y))
    if first in set(starts.tolist()) or first <= 0:  # a break there already
        return ""
    u2 = np.asarray(u, dtype=np.float64).reshape(len(index), -1)
    y2 = np.asarray(y, dtype=np.float64).reshape(len(index), -1)
    for j, output in enumerate(identifier.outputs):
        structure, warm = output.structure, output.structure.warm_up
        if not structure.scaled or len(index) - first <= 2 * warm:
            return ""
        others = identifier.structure.other_values(j, u2, y2) if identifier.vector else u2[:, 0]
        features, targets, build, join = [], [], [], []
        for begin, end in zip(starts, stops, strict=True):
            if end - begin <= warm or begin >= first + warm:
                continue
            inputs, target, _ = structure.training_pairs(others[begin:end], y2[begin:end, j])
            if not output.model.is_initialised:
                output.model._initialise()
            phi = output.model.features(inputs) if hasattr(output.model, "features") else inputs
            features.append(np.column_stack([phi, np.ones(len(phi))]) if phi is inputs else phi)
            targets.append(target)
            rows = np.arange(begin + warm, end)
            build.append(rows < first)
            join.append((rows >= first) & (rows < first + warm))
        if not features:
            return ""
        text = join_verdict(np.concatenate(features), np.concatenate(targets), np.concatenate(build),
                            np.concatenate(join), warm)  # fmt: skip
        if text:
            return text
    return ""


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


def one_step_band(
    test: np.ndarray, y: np.ndarray, y_hat: np.ndarray, std: np.ndarray, names: list[str], band: np.ndarray
) -> dict[str, Any]:
    """The node's nominal 95 % one-step band (``y_hat_std``, as published live) and its live band (``y_hat_band``,
    under ``live``), and what each covers of the test part, per output (one output's at the top level, several
    by name, as :func:`fit_band_coverage` has them).

    ``run_samples`` gives every prediction the std and the live half-width the node published with it (RLS
    covariance and innovation variance, the multiplier that keeps the running coverage at 95 %: ``core.spread``),
    so these are the bands live users saw.
    """
    if np.shape(std) != np.shape(y) or np.shape(band) != np.shape(y):
        return {}
    columns = [np.reshape(a, (len(y), -1)) for a in (y, y_hat, std, band)]
    bands = {}
    for j, name in enumerate(names):
        measured, predicted, spread, live = (column[:, j] for column in columns)
        scored = test & np.isfinite(predicted) & np.isfinite(spread) & np.isfinite(live)
        if not scored.any():
            continue
        error = np.abs(measured[scored] - predicted[scored])
        half, live = Z95 * spread[scored], live[scored]
        bands[name] = {
            "median_half_width": float(np.median(half)),
            "from": "the node's y_hat_std (RLS covariance and innovation variance), as published live",
            "coverage_test": float(np.mean(error <= half)),
            "live": {"median_half_width": float(np.median(live)), "coverage_test": float(np.mean(error <= live))},
        }
    if not bands:
        return {}
    return {"level": 0.95, "one_step": bands[names[0]] if len(names) == 1 else bands}


def fit_band_coverage(weights_in: str, evaluations: dict[str, Evaluation]) -> dict[str, Any]:
    """The nominal 95 % free-run band of the fit the weights came from (its ``fit.json``), and what it covers here.

    The band is the fit's estimate (errors on its held-out blocks, by steps since a run's start:
    :func:`fit_free_run_widths`); the model scored here went on learning from the bag's training
    phase, so the coverage says how well the fit's uncertainty carries over to this recording.
    Several outputs: one band each, under ``free_run`` by output name. Empty without a fit report.
    """
    report = Path(weights_in).parent / REPORT_FILE if weights_in else None
    if report is None or not report.is_file():
        return {}
    try:
        fitted = json.loads(report.read_text())
    except (OSError, ValueError):
        return {}
    covered = {}
    for (name, evaluation), band in zip(evaluations.items(), fit_free_run_bands(fitted), strict=False):
        widths = fit_free_run_widths(band, evaluation.y_free_test)
        if widths is None:
            continue
        finite = widths[np.isfinite(widths)]
        covered[name] = {
            "half_width": float(np.median(finite)) if len(finite) else math.nan,
            "from": str(report),
            "coverage_test": coverage(evaluation.y_test, evaluation.y_free_test, widths),
            **({"by_horizon": band["by_horizon"]} if "by_horizon" in band else {}),
        }
    if not covered:
        return {}
    return {"level": 0.95, "free_run": covered["y"] if list(covered) == ["y"] else covered}


def fit_free_run_bands(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Each output's free-run band in a fit report (fit.json: one output's at the top level, several under
    ``per_output``), in the outputs' order; ``{}`` for an output without one."""
    return [part.get("intervals", {}).get("free_run", {}) for part in report.get("per_output") or [report]]


def fit_free_run_widths(band: dict[str, Any], y_free: np.ndarray) -> np.ndarray | None:
    """Per-sample half-widths of a fit's free-run band (fit.json's ``intervals.free_run``) along ``y_free``: by steps
    since each run's start where the fit gave them by horizon (``by_horizon``: fit's test part is scored so, and a
    free run restarted after a gap starts narrow again), else its one number; NaN where nothing was simulated.
    None without a band. ``evaluate``'s coverage and its plot both take them from here."""
    y_free = np.asarray(y_free, dtype=np.float64)
    if band.get("by_horizon"):
        widths = HorizonBand.from_dict(band["by_horizon"]).at(run_steps(y_free))
    elif band.get("half_width"):
        widths = np.full(len(y_free), float(band["half_width"]))
    else:
        return None
    return np.where(np.isfinite(y_free), widths, np.nan)
