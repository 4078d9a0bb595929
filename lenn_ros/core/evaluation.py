"""Series-parallel training then frozen testing over a recorded or simulated series.

One function, :func:`train_and_test`, is the whole protocol of the paper's Section IV
applied to paired series (u(k), y_p(k)): learn while k < test_start, freeze, then
score one-step (series-parallel) and free-run (parallel) over the test samples.
``lenn-ros reproduce`` feeds it simulated data, ``lenn-ros evaluate`` a bag's data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lenn_ros.core.examples import TEST_SAMPLES, TRAIN_SAMPLES, PaperExample
from lenn_ros.core.metrics import nmse_db, rmse
from lenn_ros.core.plants import Plant
from lenn_ros.core.signals import Excitation
from lenn_ros.core.structure import Identifier


@dataclass
class Series:
    """Paired samples: y[k] is the plant output shown when u[k] was applied."""

    u: np.ndarray
    y: np.ndarray
    test_start: int  # first index of the test phase (learning frozen from here)


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


def simulate(
    plant: Plant,
    noise_db: float | None,
    seed: int,
    train_samples: int = TRAIN_SAMPLES,
    test_samples: int = TEST_SAMPLES,
    test_noise: bool = False,
) -> Series:
    """The paper's data: uniform random training input, then the eq. 11 sinusoid.

    White Gaussian noise (see :func:`signals.noise_std`) is added to the input the
    plant receives, not to the u the model sees, during training; the test is
    noise-free unless ``test_noise`` (the paper's Ex. 1 figure of -25 dB is out of
    reach with noise in the test: the README shows the bound). Separate random
    streams for the input and the noise keep one from shifting the other.
    """
    excitation = Excitation(seed, "paper", train_samples, test_samples, noise_db, test_noise)
    u, noise = excitation.series()
    applied = u + noise
    plant.reset()
    y = plant.run(applied)[:-1]
    return Series(u=u, y=y, test_start=train_samples)


def train_and_test(identifier: Identifier, series: Series) -> Evaluation:
    """Learn on k < test_start, then score the frozen model on k >= test_start."""
    k = np.arange(len(series.y))
    y_hat = identifier.run(series.u, series.y, learn=k < series.test_start)
    test = slice(series.test_start, None)
    y_test, y_hat_test = series.y[test], y_hat[test]
    y_free = identifier.free_run(series.u, series.y, series.test_start)
    train_mask = (k < series.test_start) & np.isfinite(y_hat)
    return Evaluation(
        nmse_db=nmse_db(y_test, y_hat_test),
        nmse_free_run_db=nmse_db(y_test, y_free),
        rmse=rmse(y_test, y_hat_test),
        rmse_free_run=rmse(y_test, y_free),
        samples=len(y_test),
        trained=int(train_mask.sum()),
        skipped=int((~np.isfinite(y_hat[: series.test_start])).sum()),
        y_test=y_test,
        y_hat_test=y_hat_test,
        y_free_test=y_free,
        train_errors=(series.y - y_hat)[train_mask],
        free_run=dict(identifier.last_free_run),
        free_run_warnings=free_run_problems(y_test, y_free, identifier.last_free_run),
    )


def run_example(
    example: PaperExample,
    network: str,
    seed: int,
    train_samples: int = TRAIN_SAMPLES,
    test_samples: int = TEST_SAMPLES,
    parameters: str = "calibrated",
    **overrides,
) -> Evaluation:
    """One seed of one example with one network, the paper's protocol end to end."""
    series = simulate(example.plant(), example.noise_db, seed, train_samples, test_samples)
    model = example.make_network(network, seed, parameters, **overrides)
    return train_and_test(Identifier(example.structure, model), series)


def least_squares_floor(example: PaperExample, series: Series, **feature_overrides) -> float:
    """One-step test NMSE (dB) of the best linear fit of the LeNN's features.

    The features are the example's LeNN expansion (or ``feature_overrides``, e.g. a
    cross-term expansion), fitted by batch least squares to all training targets,
    then frozen and tested like the online models. No online rule with the same
    features and a linear output can do better on the same data in the mean-square
    sense, so it is the bound against which a gap to the paper's figure is judged.
    """
    model = example.make_network("lenn", 0, output="linear", output_scale=1.0, **feature_overrides)
    structure = example.structure
    train = slice(0, series.test_start)
    x, targets, _ = structure.training_pairs(series.u[train], series.y[train])
    features = model.features(x)
    model.update(x[:1], targets[:1], learn=False)  # initialise the state arrays
    model.weights_ = np.linalg.lstsq(features, targets, rcond=None)[0]
    identifier = Identifier(structure, model, learning=False)
    y_hat = identifier.run(series.u, series.y, learn=False)
    test = slice(series.test_start, None)
    return nmse_db(series.y[test], y_hat[test])


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
