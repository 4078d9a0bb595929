"""Offline training by epochs for the gradient-trained models (SGD LeNN, MLP).

The paper's models learn in one pass over 50 000 samples; a real log may hold a few
hundred, where one pass leaves SGD far from its optimum (repeating the rows by hand
took one-step RMSE from 1.20 to 0.16 on one data set). So the estimation samples
are passed again and again, each epoch one call of the compiled kernel, and the
weights kept are those of the epoch with the lowest free-run error on the held-out
tail (early stopping): more epochs past that point fit the noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lenn_ros.core.networks import DivergenceError
from lenn_ros.core.structure import Identifier


@dataclass
class EpochTraining:
    """What :func:`train_epochs` did."""

    epochs: int  # run
    best_epoch: int  # whose weights were kept (0: none improved on the start)
    stopped: str  # why it stopped
    validation_rmse: list[float] = field(default_factory=list)  # free-run RMSE after each epoch

    def as_dict(self) -> dict:
        return {
            "epochs": self.epochs,
            "best_epoch": self.best_epoch,
            "stopped": self.stopped,
            "rmse_free_run_validation": [round(v, 9) if math.isfinite(v) else None for v in self.validation_rmse],
        }


def held_out_rmse(identifier: Identifier, u: np.ndarray, y: np.ndarray, start: int) -> float:
    """Free-run RMSE over samples ``start``.. (inf if it diverged)."""
    y_free = identifier.free_run(u, y, start)
    if identifier.last_free_run.get("diverged") or not np.all(np.isfinite(y_free)):
        return math.inf
    return float(np.sqrt(np.mean((y_free - y[start:]) ** 2)))


def train_epochs(
    identifier: Identifier,
    u: np.ndarray,
    y: np.ndarray,
    validation_start: int,
    max_epochs: int = 50,
    patience: int = 5,
) -> EpochTraining:
    """Several epochs over samples before ``validation_start``, early-stopped on the rest.

    Each epoch is one compiled pass (``model.update`` over all estimation rows, one
    update per sample, in order). The model ends with the best epoch's weights.
    """
    u = np.asarray(u, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    structure, model = identifier.structure, identifier.model
    x, targets, _ = structure.training_pairs(u[:validation_start], y[:validation_start])
    inputs = np.clip(x, -1.0, 1.0)
    best_state, best = model.state(), held_out_rmse(identifier, u, y, validation_start)
    report = EpochTraining(0, 0, f"no improvement in {patience} epochs")
    for epoch in range(1, max_epochs + 1):
        try:
            model.update(inputs, targets, learn=True)
        except DivergenceError:
            report.stopped = f"weights diverged in epoch {epoch}"
            break
        score = held_out_rmse(identifier, u, y, validation_start)
        report.epochs, report.validation_rmse = epoch, [*report.validation_rmse, score]
        if score < best:
            best, best_state, report.best_epoch = score, model.state(), epoch
        elif epoch - report.best_epoch >= patience:
            break
    else:
        report.stopped = f"max_epochs {max_epochs}"
    model.set_state(best_state)
    identifier.mark_healthy()
    return report
