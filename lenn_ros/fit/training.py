"""Offline training by epochs for the gradient-trained models (SGD LeNN, MLP).

The paper's models learn in one pass over 50 000 samples; a real log may hold a few
hundred, where one pass leaves SGD far from its optimum (repeating the rows by hand
took one-step RMSE from 1.20 to 0.16 on one data set). So the estimation samples
are passed again and again, each epoch one call of the compiled kernel, and the
weights kept are those of the epoch with the lowest free-run error on the held-out
tail (early stopping): more epochs past that point fit the noise. ``fit --network mlp``
trains an MLP on the selected lags this way (:func:`fit_mlp`), ``fit --solver sgd`` the
selected terms as an SGD LeNN (:func:`fit_lenn_sgd`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lenn_ros.core.networks import MLP, DivergenceError, FunctionalLinkNetwork
from lenn_ros.core.structure import Identifier
from lenn_ros.fit.families.base import pass_through_weights
from lenn_ros.fit.termmodel import TermModel, siso_view


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


#: share of the training samples the epochs of an MLP / SGD fit are early-stopped on
VALIDATION_FRACTION = 0.2
MIN_VALIDATION = 50


#: MLP learning rate on the normalised target (y - offset) / scale; divided by scale^2 for y itself
MLP_ALPHA = 0.03
MLP_HIDDEN = [20, 10]


def fit_mlp(selected: TermModel, u: np.ndarray, y: np.ndarray, validation_start: int):
    """An MLP on the selected lags, trained by epochs with early stopping (SGD with momentum).

    The target is centred by ``output_offset`` and the tanh output spans the y scale, so
    one learning rate (on the normalised target) suits any units.
    """
    s = selected.layout
    structure = dataclasses.replace(selected.structure, output_offset=s.y_offset)
    network = MLP(
        n_inputs=structure.n_inputs,
        hidden=MLP_HIDDEN,
        output="tanh",
        output_scale=s.y_scale,
        alpha=MLP_ALPHA / s.y_scale**2,
        beta=0.5,
    )
    identifier = Identifier(structure, network, learning=False)
    epochs = train_epochs(identifier, u, y, validation_start, max_epochs=100, patience=10)
    return identifier, epochs


#: SGD momentum for the LeNN by epochs, and the share of the stability bound its step takes
SGD_BETA = 0.5
SGD_STEP = 0.5


def fit_lenn_sgd(selected: TermModel, u: np.ndarray, y: np.ndarray, validation_start: int, increment: bool):
    """The selected terms as an SGD LeNN (what the node runs with ``solver: sgd``), trained by epochs.

    One pass over a few hundred samples leaves SGD far from its optimum, so the estimation
    samples are passed repeatedly, early-stopped on the held-out free run
    (:func:`~lenn_ros.fit.training.train_epochs`). The step is unit-free: with momentum
    beta, alpha = SGD_STEP (1 - beta) / max ||phi||^2 over the training features keeps the
    update below its stability bound 2 (1 - beta) / ||phi||^2 for any data (Legendre terms
    of inputs in [-1, 1] have |phi| <= 1, but a factor of a velocity may reach several).
    The network learns y - y_offset (``output_offset``), so no weight has to climb to the
    signal's level; an increment-form model starts from its pass-through y(k) (weight
    y_scale on ``y1``), the part of the structure that is not learnt but given.
    """
    s = selected.layout
    structure = dataclasses.replace(selected.structure, output_offset=s.y_offset)
    features, _ = selected.regression(siso_view(u[:validation_start], y[:validation_start]))
    largest = float(np.max(np.einsum("ij,ij->i", features, features), initial=1.0))
    network = FunctionalLinkNetwork(
        n_inputs=structure.n_inputs,
        exponents=selected.exponents.tolist(),
        factors=selected.factors.tolist() if len(selected.factors) else None,
        order=max(1, int(selected.exponents.max(initial=1))),
        basis=selected.basis,
        output="linear",
        solver="sgd",
        alpha=SGD_STEP * (1.0 - SGD_BETA) / largest,
        beta=SGD_BETA,
        init_scale=0.0,
    )
    network._initialise()
    if increment:
        network.weights_ = pass_through_weights(selected.exponents, selected.factors, s, with_offset=False)
    identifier = Identifier(structure, network, learning=False)
    epochs = train_epochs(identifier, u, y, validation_start, max_epochs=200, patience=20)
    return identifier, epochs


def describe_sgd(identifier: Identifier, epochs: Any) -> dict[str, Any]:
    m = identifier.model
    return {
        "weights": [float(w) for w in m.weights_],
        "solver": f"sgd with momentum, alpha {m.alpha:.6g}, by epochs (terms from the LeNN selection)",
        "epochs": epochs.as_dict(),
        "live": {"solver": "sgd", "alpha": m.alpha, "beta": m.beta},
    }


def describe_mlp(identifier: Identifier, epochs: Any) -> dict[str, Any]:
    m = identifier.model
    return {
        "network": "mlp",
        "structure": {"y_lags": identifier.structure.y_lags, "u_lags": identifier.structure.u_lags},
        "expansion": {"hidden": list(m.hidden), "output": f"tanh x {m.output_scale:.6g} + output_offset"},
        "n_terms": m.n_weights,
        "solver": f"sgd with momentum, alpha {m.alpha:.6g}, by epochs (lags from the LeNN selection)",
        "epochs": epochs.as_dict(),
        "live": {"solver": "sgd", "alpha": m.alpha, "beta": m.beta},
    }
