"""Series-parallel training then frozen testing over a recorded or simulated series.

One function, :func:`train_and_test`, is the whole protocol of the paper's Section IV
applied to paired series (u(k), y_p(k)): learn while k < test_start, freeze, then
score one-step (series-parallel) and free-run (parallel) over the test samples.
``lenn-ros reproduce`` and ``reproduce --beyond`` feed it simulated data (``lenn-ros
evaluate`` scores a bag through the node's session instead: :mod:`lenn_ros.service.evaluation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lenn_ros.core import batch_kernels, jit, term_kernels
from lenn_ros.core.evaluation import Evaluation, free_run_problems
from lenn_ros.core.metrics import nmse_db, rmse
from lenn_ros.core.networks import FunctionalLinkNetwork
from lenn_ros.core.structure import Identifier
from lenn_ros.paper.examples import PaperExample
from lenn_ros.paper.plants import MimoPlant, Plant
from lenn_ros.paper.signals import Excitation
from lenn_ros.presets import TEST_SAMPLES, TRAIN_SAMPLES


@dataclass
class Series:
    """Paired samples: y[k] is the plant output shown when u[k] was applied."""

    u: np.ndarray
    y: np.ndarray
    test_start: int  # first index of the test phase (learning frozen from here)


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


def simulate_mimo(
    plant: MimoPlant,
    noise_db: float | None,
    seed: int,
    train_samples: int = TRAIN_SAMPLES,
    test_samples: int = TEST_SAMPLES,
    test_noise: bool = False,
) -> Series:
    """:func:`simulate` for a plant with several inputs: ``u`` and ``y`` have one column per channel.

    Input i is :class:`Excitation` channel i (own streams, its test sinusoid shifted), so
    the plant simulator node stepping channel by channel publishes the same numbers.
    """
    columns = [
        Excitation(seed, "paper", train_samples, test_samples, noise_db, test_noise, channel=i).series()
        for i in range(plant.n_u)
    ]
    u = np.stack([column[0] for column in columns], axis=1)
    applied = u + np.stack([column[1] for column in columns], axis=1)
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
    model.update(x[:1], targets[:1], learn=False)  # initialise the state arrays
    model.weights_ = least_squares_weights(model, x, targets)
    # Frozen weights make every prediction depend on its own regressor only, so the test
    # samples and the warm-up before them give the test's predictions bit for bit; the
    # training part (all but 600 samples) was predicted and thrown away before.
    identifier = Identifier(structure, model, learning=False)
    window = slice(max(series.test_start - structure.warm_up, 0), None)
    y_hat = identifier.run(series.u[window], series.y[window], learn=False)
    y_test = series.y[series.test_start :]
    return nmse_db(y_test, y_hat[len(y_hat) - len(y_test) :])


#: Normal equations are solved when their Jacobi-scaled matrix has a condition number
#: below this: the solution is then good to about eps * 1e8 = 2e-8 relative, far below
#: what moves an NMSE in its second decimal. Above it (Ex. 3's order-14 expansion of
#: y/2, which only spans [-0.33, 0.98]; its two branch biases, an exactly repeated
#: column) squaring the condition number of the features loses the fit, and a QR of
#: the features themselves is used instead.
NORMAL_EQUATIONS_CONDITION = 1.0e8


def least_squares_weights(model: FunctionalLinkNetwork, x: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Batch least-squares weights of ``model``'s features of ``x`` for ``targets``.

    :func:`least_squares_weights_reference` (``np.linalg.lstsq`` on the N x p feature
    matrix) up to rounding, without the matrix: one compiled pass accumulates the
    p x p normal equations, expanding each sample on the fly: 0.06 s against 1.2 s
    for the matrix and its SVD at 550 000 samples of Ex. 1 (cProfile). Ill-conditioned
    features fall back to a QR built row by row (:func:`_qr_least_squares`).
    """
    if not jit.JIT:
        return least_squares_weights_reference(model, x, targets)
    x = np.ascontiguousarray(model._check_inputs(x))
    targets = np.ascontiguousarray(targets, dtype=np.float64)
    exponents = np.ascontiguousarray(model.term_exponents()[0])
    factors = model.term_factors()
    basis = term_kernels.BASIS_CODES[model.basis]
    gram = np.zeros((len(exponents) + 1, len(exponents) + 1))  # [Phi | d]' [Phi | d]
    batch_kernels.normal_equations(x, targets, exponents, factors, basis, gram)
    weights = _solve_normal_equations(gram[:-1, :-1], gram[:-1, -1])
    return _qr_least_squares(x, targets, exponents, factors, basis) if weights is None else weights


def least_squares_weights_reference(model: FunctionalLinkNetwork, x: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """The least-squares weights by SVD of the whole feature matrix (the reference; also the path without numba)."""
    return np.linalg.lstsq(model.features(x), targets, rcond=None)[0]


def _solve_normal_equations(gram: np.ndarray, moment: np.ndarray) -> np.ndarray | None:
    """Solution of gram w = moment by eigendecomposition, or None when the system is too ill-conditioned.

    Scaling to a unit diagonal first makes the condition number measure collinearity
    of the features, not their different sizes (a bias of 1 next to a small L14).
    """
    scale = np.sqrt(np.diag(gram))
    if not np.all(scale > 0.0):  # a feature that is zero on every sample: rank deficient
        return None
    values, vectors = np.linalg.eigh(gram / np.outer(scale, scale))
    if not values[0] > values[-1] / NORMAL_EQUATIONS_CONDITION:
        return None
    return vectors @ ((vectors.T @ (moment / scale)) / values) / scale


def _qr_least_squares(
    x: np.ndarray, targets: np.ndarray, exponents: np.ndarray, factors: np.ndarray, basis: int
) -> np.ndarray:
    """Least squares from the triangular R of [Phi | d], built row by row (:func:`batch_kernels.qr_rows`).

    The conditioning is that of the features, not its square, and the cut-off for
    small singular values is ``np.linalg.lstsq``'s for the whole matrix
    (eps * max(N, p)), so rank-deficient features (repeated biases) get the same
    minimum-norm solution.
    """
    n_terms = len(exponents)
    r = np.zeros((n_terms + 1, n_terms + 1))
    batch_kernels.qr_rows(x, targets, exponents, factors, basis, r)
    cutoff = np.finfo(np.float64).eps * max(len(x), n_terms)
    return np.linalg.lstsq(r[:n_terms, :n_terms], r[:n_terms, n_terms], rcond=cutoff)[0]
