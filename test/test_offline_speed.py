"""The fast offline paths against the references they replaced (issue 12: reproduce's marginal cost).

The compiled expansion must give the numpy expansion's bits (training and the live
node then cannot drift apart), and the least-squares floor from normal equations or
a row-by-row QR must give ``np.linalg.lstsq``'s NMSE (the README reports it to 0.01 dB).
"""

from __future__ import annotations

import numpy as np
import pytest

from lenn_ros.core import jit
from lenn_ros.core.expansions import (
    dictionary_exponents,
    expand,
    full_exponents,
    term_features,
    term_features_reference,
)
from lenn_ros.core.metrics import nmse_db
from lenn_ros.core.structure import Identifier
from lenn_ros.paper import evaluation
from lenn_ros.paper.evaluation import least_squares_floor, least_squares_weights, least_squares_weights_reference
from lenn_ros.paper.examples import EXAMPLES

pytestmark = pytest.mark.skipif(not jit.JIT, reason="numba does not compile here: the references run anyway")


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint64)


def _inputs(rows: int, n_inputs: int) -> np.ndarray:
    """Uniform inputs with the interval's ends and zero in them (where recursions are exact or signed)."""
    x = np.random.default_rng(rows).uniform(-1.0, 1.0, (rows, n_inputs))
    x.flat[: min(3, x.size)] = [-1.0, 0.0, 1.0][: min(3, x.size)]
    return x


# -- the expansion ------------------------------------------------------------------------------
@pytest.mark.parametrize("basis", ["legendre", "chebyshev"])
@pytest.mark.parametrize("rows", [1, 31, 32, 33, 500])  # one block, exact blocks, a partial last block
def test_compiled_term_features_are_bitwise_the_numpy_reference(basis: str, rows: int) -> None:
    x = _inputs(rows, 3)
    for exponents in (full_exponents(3, 14, 4), dictionary_exponents(3, 4, pure_degree=9)):
        compiled, reference = term_features(x, exponents, basis), term_features_reference(x, exponents, basis)
        assert np.array_equal(_bits(compiled), _bits(reference))


def test_terms_of_factors_only_are_expanded_within_their_table() -> None:
    """``fit``'s input averages: terms with no polynomial, only a factor g(w . x) over 64 lags. Their inputs are
    read at table depth 1, which a table sized by the exponents alone (all 0) did not have: the compiled
    expansion wrote past its end and aborted the process (double free). Now it is the reference's value."""
    x = _inputs(5000, 64)
    rng = np.random.default_rng(3)
    factors = np.column_stack([[1.0, 4.0, 3.0], np.zeros(3), rng.normal(0.0, 0.1, (3, 64))])
    exponents = np.zeros((3, 64), dtype=np.int64)
    compiled = term_features(x, exponents, "legendre", factors)
    reference = term_features_reference(x, exponents, "legendre", factors)
    assert np.allclose(compiled, reference, rtol=0, atol=1e-12)


@pytest.mark.parametrize("number", sorted(EXAMPLES))
@pytest.mark.parametrize(
    "overrides", [{}, {"basis": "chebyshev"}, {"cross_degree": 3, "branches": None}], ids=["paper", "cheb", "cross"]
)
def test_network_features_are_bitwise_the_per_branch_expansion(number: int, overrides: dict) -> None:
    """One compiled pass over all branches (Ex. 3: N1[y] + N2[u]) == expand() per branch, concatenated."""
    network = EXAMPLES[number].make_network("lenn", 0, **overrides)
    x = _inputs(777, network.n_inputs)
    order, basis, cross = network.order, network.basis, network.cross_degree
    parts = [expand(x[:, branch], order, basis, cross) for branch in network.branch_inputs_]
    assert np.array_equal(_bits(network.features(x)), _bits(np.hstack(parts)))


@pytest.mark.parametrize("number", [1, 3, 4])
def test_identifier_run_is_bitwise_the_numpy_path(number: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Training, the divergence guard's blocks and the free run give the same bits with numba's expansion off."""
    example = EXAMPLES[number]
    series = evaluation.simulate(example.plant(), example.noise_db, 2, 4500, 300)

    def run() -> tuple[np.ndarray, ...]:
        identifier = Identifier(example.structure, example.make_network("lenn", 2))
        evaluated = evaluation.train_and_test(identifier, series)
        return evaluated.y_hat_test, evaluated.y_free_test, evaluated.train_errors, identifier.model.weights_

    compiled = run()
    monkeypatch.setattr(jit, "JIT", False)
    reference = run()
    for a, b in zip(compiled, reference, strict=True):
        assert np.array_equal(_bits(a), _bits(b))


@pytest.mark.parametrize("number", sorted(EXAMPLES))
def test_regressors_are_the_lagged_samples(number: int) -> None:
    """Slices instead of gathered indices: the same regressors as the definition y(k - i), u(k - i)."""
    structure = EXAMPLES[number].structure
    rng = np.random.default_rng(number)
    u, y = rng.normal(size=60), rng.normal(size=60)
    x, linear = structure.regressors(u, y)
    k = np.arange(structure.warm_up - 1, 60)
    columns = [(y[k - i] - structure.y_offset) / structure.y_scale for i in range(structure.y_lags)]
    columns += [(u[k - i] - structure.u_offset) / structure.u_scale for i in range(structure.u_lags)]
    expected = np.full(len(k), float(structure.output_offset))
    for i, a in enumerate(structure.known_a):
        expected = expected + a * y[k - i]
    for i, b in enumerate(structure.known_b):
        expected = expected + b * u[k - i]
    assert np.array_equal(x, np.stack(columns, axis=1)) and np.array_equal(linear, expected)
    short, _ = structure.regressors(u[: structure.warm_up - 1], y[: structure.warm_up - 1])
    assert short.shape == (0, structure.n_inputs)


# -- the least-squares floor ----------------------------------------------------------------------
@pytest.mark.parametrize("number", sorted(EXAMPLES))
def test_least_squares_floor_equals_lstsq_within_0_01_db(number: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Normal equations for Ex. 1, 2, 4; Ex. 3's ill-conditioned order-14 expansion of y takes the QR."""
    example = EXAMPLES[number]
    series = evaluation.simulate(example.plant(), example.noise_db, 0, 20_000, 600)
    calls: list[int] = []
    qr = evaluation._qr_least_squares
    monkeypatch.setattr(evaluation, "_qr_least_squares", lambda *args: calls.append(1) or qr(*args))
    fast = least_squares_floor(example, series)
    assert bool(calls) == (number == 3)
    monkeypatch.setattr(jit, "JIT", False)  # features matrix + np.linalg.lstsq
    assert abs(fast - least_squares_floor(example, series)) < 0.01


@pytest.mark.parametrize(("number", "overrides"), [(1, {}), (2, {"cross_degree": 3, "branches": None}), (3, {})])
def test_least_squares_weights_predict_as_lstsq(number: int, overrides: dict) -> None:
    """Same fitted outputs as lstsq; Ex. 3's two branch biases (a repeated column) take the minimum-norm fit."""
    example = EXAMPLES[number]
    series = evaluation.simulate(example.plant(), example.noise_db, 1, 8000, 0)
    x, targets, _ = example.structure.training_pairs(series.u, series.y)
    model = example.make_network("lenn", 0, output="linear", output_scale=1.0, **overrides)
    phi = model.features(x)
    fitted = phi @ least_squares_weights(model, x, targets)
    reference = phi @ least_squares_weights_reference(model, x, targets)
    assert np.max(np.abs(fitted - reference)) < 1e-6 * np.max(np.abs(reference))


def test_floor_scored_on_the_test_window_equals_scoring_the_whole_series() -> None:
    """Frozen weights: the warm-up before the test gives its predictions bit for bit."""
    example = EXAMPLES[2]
    series = evaluation.simulate(example.plant(), example.noise_db, 0, 5000, 600)
    model = example.make_network("lenn", 0, output="linear", output_scale=1.0)
    model._initialise()
    whole = Identifier(example.structure, model, learning=False).run(series.u, series.y, learn=False)[5000:]
    start = 5000 - example.structure.warm_up
    window = Identifier(example.structure, model, learning=False).run(series.u[start:], series.y[start:], learn=False)
    assert np.array_equal(_bits(window[-600:]), _bits(whole))
    assert nmse_db(series.y[5000:], window[-600:]) == nmse_db(series.y[5000:], whole)


# -- the benchmark ----------------------------------------------------------------------------
def test_marginal_benchmark_runs_and_reports_the_rate() -> None:
    """bench/reproduce_marginal.py at tiny sizes, one run each (two short processes)."""
    import reproduce_marginal

    result = reproduce_marginal.measure(1000, 3000, repeats=1, numpy_samples=200, warmup=False)
    assert result["small"] > 0 and result["large"] > 0 and result["numpy_samples_per_s"] > 0
    table = reproduce_marginal.format_table(1000, 3000, 1, result)
    assert "| 1 000 |" in table and "| 3 000 |" in table and "marginal" in table and "numpy" in table
