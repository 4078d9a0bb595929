"""What scoring a frozen model over a recorded test part needs, for ``evaluate`` and ``fit``.

:class:`Evaluation` holds the scores and series behind them; :func:`free_run_segments` runs
the free run across breaks, :func:`free_run_problems` says what is wrong with one, and
:func:`~lenn_ros.core.runs.finite_rows` which samples are numbers (the gap rule:
:mod:`lenn_ros.core.runs`). The paper's protocol over
simulated data (``lenn-ros reproduce``) is :mod:`lenn_ros.paper.evaluation`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lenn_ros.core.metrics import nmse_db
from lenn_ros.core.runs import finite_rows, runs


@dataclass
class Evaluation:
    """Scores over the test phase and the series behind them (for plots)."""

    nmse_db: float
    nmse_free_run_db: float
    rmse: float
    rmse_free_run: float
    samples: int  # test samples scored
    trained: int  # samples learnt from
    skipped: int  # samples that produced no prediction (warm-up)
    y_test: np.ndarray
    y_hat_test: np.ndarray
    y_free_test: np.ndarray
    train_errors: np.ndarray  # a-priori error e(k) during training (learning curve)
    free_run: dict = field(default_factory=dict)  # Identifier.last_free_run: clipped inputs, diverged
    free_run_warnings: list[str] = field(default_factory=list)  # free_run_problems(): [] when healthy

    def as_dict(self) -> dict[str, float | int]:
        return {
            "nmse_db": self.nmse_db,
            "nmse_free_run_db": self.nmse_free_run_db,
            "rmse": self.rmse,
            "rmse_free_run": self.rmse_free_run,
            "samples": self.samples,
            "trained": self.trained,
            "skipped": self.skipped,
            "free_run_clipped_inputs": int(self.free_run.get("clipped_inputs", 0)),
            "free_run_diverged": bool(self.free_run.get("diverged", False)),
            "free_run_warnings": list(self.free_run_warnings),
        }


def free_run_problems(y_test: np.ndarray, y_free: np.ndarray, info: dict | None = None) -> list[str]:
    """One line per thing wrong with a free run, for the text report and the JSON (``[]``: none).

    A free run is unstable when it diverged (``info`` from ``Identifier.last_free_run``)
    or came out non-finite, and useless when its NMSE is above 0 dB (worse than
    predicting the mean of y). Clipped network inputs are reported too: the model was
    driven outside the range it was built for, so its figure means less.
    """
    info = info or {}
    problems = []
    y_free = np.asarray(y_free, dtype=np.float64)
    if info.get("unscaled"):
        return [
            "no free run: the model's scales were never learnt (the warm-up, scale_warm_up, needs more samples in "
            "which the signals move than the training part held): give y_scale/u_scale, or a longer training part"
        ]
    if info.get("diverged") or not np.all(np.isfinite(y_free)):
        where = f" at sample {info['diverged_at'] + 1}" if info.get("diverged_at") is not None else ""
        problems.append(
            f"free run diverged{where}: the model is unstable in simulation; "
            "fit a structure that simulates (lenn-ros fit) or lower the lags/order"
        )
    elif len(y_test) and nmse_db(y_test, y_free) > 0.0:
        problems.append(
            f"free run NMSE {nmse_db(y_test, y_free):.2f} dB is worse than predicting the mean: "
            "the model does not simulate this plant (unstable or wrong structure)"
        )
    if info.get("clipped_inputs"):
        problems.append(
            f"{info['clipped_inputs']} free-run network inputs were outside [-1, 1] and clipped: "
            "scale/offset too small for these signals (lenn-ros fit takes them from the data)"
        )
    return problems


def free_run_segments(
    identifier: Any, index: np.ndarray, u: np.ndarray, y: np.ndarray, first: int
) -> tuple[np.ndarray, dict[str, Any]]:
    """The free run over the test part, restarted from the measured outputs after every break.

    A simulation cannot cross a lost sample or a NaN input: it would feed the model a
    value that does not exist (the whole rest came out NaN and was reported as
    divergence). After a break the next ``warm_up`` measured samples seed the model's
    history again, as at the start of the test part; they are not simulated (NaN) and
    not scored. Without breaks this is one ``free_run`` from ``first``, as before.
    A MIMO model's rows (u (N, n_u), y (N, n_y)) break where any channel is invalid
    (``lenn-ros fit``'s MIMO selection and test scores run through here too).
    """
    window = identifier.structure.warm_up
    valid = finite_rows(u) & finite_rows(y)
    starts, stops = runs(index, valid)
    y_free = np.full((len(y) - first, *np.shape(y)[1:]), np.nan)
    info: dict[str, Any] = {"samples": 0, "clipped_inputs": 0, "diverged": False, "diverged_at": None}
    info["segments"] = 0
    if not identifier.structure.scaled:  # the warm-up never learnt the scales: there is no model to run
        info.update(unscaled=True, not_simulated=len(y_free))
        return y_free, info
    for begin, end in zip(starts, stops, strict=True):
        simulate_from = max(first, begin + window)
        if end <= first or simulate_from >= end or not valid[begin]:
            continue
        y_free[simulate_from - first : end - first] = identifier.free_run(
            u[begin:end], y[begin:end], simulate_from - begin
        )
        part = identifier.last_free_run
        info["segments"] += 1
        info["samples"] += int(part["samples"])
        info["clipped_inputs"] += int(part["clipped_inputs"])
        if part["diverged"] and not info["diverged"]:
            info["diverged"], info["diverged_at"] = True, int(begin + part["diverged_at"])
    info["not_simulated"] = int(len(y_free) - info["samples"])
    return y_free, info


#: how many times the largest one-step error on the build part the error across the split must exceed
#: (:func:`join_verdict`): that largest is itself the extreme of thousands of errors
JOIN_FACTOR = 2.0


def join_verdict(features: np.ndarray, targets: np.ndarray, build: np.ndarray, join: np.ndarray, warm: int) -> str:
    """Why the test part is a record of its own, not the build part's continuation ('' if it continues).

    The one rule, for ``fit`` and ``evaluate`` alike. Benchmark files put a test experiment after
    the build experiments, and users join two recordings the same way. Simulated from the build
    part's last samples, such a test part starts from another experiment's state. A lightly damped
    plant (Bouc-Wen) then carries that transient for a thousand samples, and an integrating one keeps
    the offset for ever: the score measures the join, not the model. The join shows one step ahead:
    the model's structure (``features`` of each complete regressor row, ``targets`` what they
    predict), its weights fitted by least squares to the ``build`` rows (the best one-step predictor
    of that structure: refined or live-learnt weights trade one-step error for simulation), errs on
    the ``join`` rows (those whose regressors still hold build samples) more than JOIN_FACTOR times
    the largest error it makes anywhere on the build part. Then the free run starts from the test
    part's own first ``warm`` samples, which are not scored.
    """
    if np.count_nonzero(build) <= 2 * features.shape[1] or not join.any():
        return ""
    weights = np.linalg.lstsq(features[build], targets[build], rcond=None)[0]
    error = np.abs(targets - features @ weights)
    largest, across = float(error[build].max()), float(error[join].max())
    if across <= JOIN_FACTOR * largest:
        return ""
    return (
        f"the test part is a record of its own: one step ahead across the split the model's structure, "
        f"fitted by least squares, errs {across / largest:.1f} times its largest error on the build part, "
        f"so the free run starts from the test part's own first {warm} samples, which are not scored"
    )
