"""Refinement on simulation error: least squares gives the best one-step predictor,
which is not the best simulator when the data are noisy (the regressors carry the
noise: equation-error bias). Levenberg-Marquardt on the free-run error itself
removes that bias; the Jacobian comes from compiled free runs with each weight
nudged (a few dozen weights, each run a few milliseconds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lenn_ros.core.selection import TermModel


@dataclass
class Refinement:
    """What the refinement did (reported by ``fit``)."""

    iterations: int
    best_iteration: int  # the iteration whose weights were kept (0: the starting weights)
    rmse_before: float  # free-run RMSE over the fitted segment
    rmse_after: float
    rmse_validation_before: float | None = None
    rmse_validation_after: float | None = None

    def as_dict(self) -> dict:
        return {k: (round(v, 9) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def _simulation_residual(model: TermModel, u: np.ndarray, y: np.ndarray, weights: np.ndarray) -> np.ndarray | None:
    y_sim, _, diverged_at = model.free_run(u, y, model.warm_up, weights)
    return None if diverged_at >= 0 else y[model.warm_up :] - y_sim


def refine_simulation_error(
    model: TermModel,
    u: np.ndarray,
    y: np.ndarray,
    iterations: int = 20,
    validation: tuple[np.ndarray, np.ndarray, int] | None = None,
) -> tuple[np.ndarray, Refinement]:
    """Weights minimising the free-run error over (u, y), starting from ``model.weights``.

    With ``validation`` = (u, y, start), the weights kept are those of the iteration
    with the lowest free-run RMSE there (early stopping); otherwise the last accepted.
    """
    weights = np.array(model.weights, dtype=np.float64, copy=True)
    residual = _simulation_residual(model, u, y, weights)
    if residual is None:
        raise ValueError("the model to refine diverges in free run")
    cost = float(residual @ residual)
    start_rmse = math.sqrt(cost / len(residual))
    best_val = _held_out_rmse(model, validation, weights) if validation else None
    best_weights, val_before = weights.copy(), best_val
    damping, done, best_iteration = 1e-3, 0, 0
    for _ in range(iterations):
        jacobian = _jacobian(model, u, y, weights, residual)
        if jacobian is None:
            break
        step = _damped_step(model, u, y, weights, jacobian, residual, cost, damping)
        if step is None:
            break
        weights, residual, cost, damping = step
        done += 1
        if validation:
            value = _held_out_rmse(model, validation, weights)
            if value < best_val:
                best_val, best_weights, best_iteration = value, weights.copy(), done
        else:
            best_weights, best_iteration = weights.copy(), done
        if len(residual) and abs(cost) < 1e-300:
            break
    final = _simulation_residual(model, u, y, best_weights)
    after = math.sqrt(float(final @ final) / len(final)) if final is not None else math.inf
    return best_weights, Refinement(done, best_iteration, start_rmse, after, val_before, best_val)


def _held_out_rmse(model: TermModel, validation: tuple[np.ndarray, np.ndarray, int], weights: np.ndarray) -> float:
    """Free-run RMSE on the validation series, inf when it diverges: a diverged run must never look best."""
    vu, vy, vstart = validation
    y_sim, _, diverged_at = model.free_run(vu, vy, vstart, weights)
    return math.inf if diverged_at >= 0 else float(np.sqrt(np.mean((vy[vstart:] - y_sim) ** 2)))


def _jacobian(
    model: TermModel, u: np.ndarray, y: np.ndarray, weights: np.ndarray, residual: np.ndarray
) -> np.ndarray | None:
    """d y_sim / d w by forward differences, one free run per weight; None if a nudged run diverges.

    A model that diverges under a nudge of one part in a million sits on the edge of
    stability, where the linearisation means nothing: the refinement stops there.
    """
    jacobian = np.empty((len(residual), len(weights)))
    for j in range(len(weights)):
        step = 1e-6 * max(abs(weights[j]), 1e-3)
        nudged = weights.copy()
        nudged[j] += step
        r = _simulation_residual(model, u, y, nudged)
        if r is None:
            return None
        jacobian[:, j] = (residual - r) / step  # d y_sim / d w
    return jacobian


def _damped_step(
    model: TermModel,
    u: np.ndarray,
    y: np.ndarray,
    weights: np.ndarray,
    jacobian: np.ndarray,
    residual: np.ndarray,
    cost: float,
    damping: float,
) -> tuple[np.ndarray, np.ndarray, float, float] | None:
    """One Levenberg-Marquardt step: (weights, residual, cost, damping) after it, or None if no damping helps.

    The damping grows tenfold until a step lowers the simulation cost (a step judged
    by the linearisation alone could diverge in free run) and shrinks after success.
    """
    normal = jacobian.T @ jacobian
    gradient = jacobian.T @ residual
    while damping < 1e8:
        try:
            delta = np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-12), gradient)
        except np.linalg.LinAlgError:
            damping *= 10.0
            continue
        r = _simulation_residual(model, u, y, weights + delta)
        if r is not None and float(r @ r) < cost:
            return weights + delta, r, float(r @ r), max(damping / 3.0, 1e-9)
        damping *= 10.0
    return None
