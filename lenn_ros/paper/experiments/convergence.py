"""How fast a rule learns: learning curves and "samples to 1 dB".

**samples to 1 dB**: the frozen model is scored (one-step test NMSE) after 250, 500,
1000, ... (doubling) training samples and after all of them; the figure is the first
checkpoint from which every later checkpoint lies within 1 dB of the final NMSE. "From
which every later" rather than "first within" so a gradient rule's curve that crosses
the final level on its way down and wanders off again is not credited with converging early.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lenn_ros.core.metrics import nmse_db
from lenn_ros.core.networks import DivergenceError, OnlineRegressor
from lenn_ros.core.structure import ModelStructure
from lenn_ros.paper.evaluation import Series

FIRST_CHECKPOINT = 250
WITHIN_DB = 1.0


def checkpoints(train_samples: int, first: int = FIRST_CHECKPOINT) -> list[int]:
    """250, 500, 1000, ... (doubling) below ``train_samples``, then ``train_samples``."""
    points = []
    point = first
    while point < train_samples:
        points.append(point)
        point *= 2
    return [*points, train_samples]


def learning_curve(structure: ModelStructure, model: OnlineRegressor, series: Series, at: Sequence[int]) -> list[float]:
    """One-step test NMSE (dB) of the model frozen after each checkpoint of training.

    Trains on exactly the samples :func:`train_and_test` learns from (the errors at
    k < checkpoint), feeding the compiled rule in runs between checkpoints, so the
    last point, at ``series.test_start``, equals train_and_test's one-step NMSE (a
    test checks it); scoring a frozen model on 600 samples costs one forward pass.
    """
    inputs, targets, known = structure.training_pairs(series.u, series.y)
    first = structure.warm_up - 1
    test_rows = slice(series.test_start - first - 1, None)  # row r predicts y[first + 1 + r]
    y_test = series.y[series.test_start :]
    curve: list[float] = []
    done, failed = 0, False
    for point in at:
        stop = max(0, min(point, series.test_start) - first - 1)
        if not failed and stop > done:
            try:
                model.update(inputs[done:stop], targets[done:stop], learn=True)
            except DivergenceError:
                failed = True
            done = stop
        curve.append(float("nan") if failed else nmse_db(y_test, known[test_rows] + model.predict(inputs[test_rows])))
    return curve


def samples_to_within(at: Sequence[int], curve: Sequence[float], within_db: float = WITHIN_DB) -> int | None:
    """First checkpoint from which every later one is within ``within_db`` of the last."""
    values = np.asarray(curve, dtype=float)
    if not np.all(np.isfinite(values)):
        return None
    close = np.abs(values - values[-1]) <= within_db
    index = len(close)
    while index > 0 and close[index - 1]:
        index -= 1
    return int(at[index])


def samples_to_level(at: Sequence[int], curve: Sequence[float], level_db: float) -> int | None:
    """First checkpoint from which every later one is at or below ``level_db`` (None: never).

    With the paper's reported LeNN NMSE as the level this compares speed across rows
    whose final accuracy differs, which "samples to 1 dB of its own final" cannot.
    """
    values = np.asarray(curve, dtype=float)
    below = np.isfinite(values) & (values <= level_db)
    if not below[-1]:
        return None
    index = len(below)
    while index > 0 and below[index - 1]:
        index -= 1
    return int(at[index])
