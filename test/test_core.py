"""The numerical core against independent references: numpy's polynomials, finite
differences, hand-computed plant sequences, and its own two code paths."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
from numpy.polynomial import chebyshev, legendre

from lenn_ros.core import jit
from lenn_ros.core.expansions import cross_term_exponents, expand, feature_count, legendre_features
from lenn_ros.core.metrics import RunningNMSE, nmse, nmse_db
from lenn_ros.core.networks import MLP, FunctionalLinkNetwork, LeNN, ModelFileError, OnlineRegressor
from lenn_ros.core.structure import Identifier, ModelStructure
from lenn_ros.paper.complexity import lenn_complexity, mlp_complexity
from lenn_ros.paper.evaluation import run_example, simulate
from lenn_ros.paper.examples import EXAMPLES, get_example
from lenn_ros.paper.expression import ExpressionError, compile_expression
from lenn_ros.paper.plants import Plant, example_plant, plant_from_expressions
from lenn_ros.paper.signals import Excitation, noise_std
from lenn_ros.paper.signals import test_sinusoid as eq11_sinusoid

X = np.linspace(-1.0, 1.0, 201)


# -- expansions ---------------------------------------------------------------------------
def test_legendre_expansion_equals_numpy_legendre() -> None:
    features = legendre_features(X[:, None], 14)
    assert features.shape == (201, 15)
    assert np.all(features[:, 0] == 1.0)
    for degree in range(1, 15):
        reference = legendre.legval(X, [0] * degree + [1])
        assert np.max(np.abs(features[:, degree] - reference)) < 1e-12


def test_chebyshev_expansion_equals_numpy_chebyshev() -> None:
    features = expand(X[:, None], 8, "chebyshev")
    for degree in range(1, 9):
        assert np.max(np.abs(features[:, degree] - chebyshev.chebval(X, [0] * degree + [1]))) < 1e-12


def test_per_input_layout_is_the_papers() -> None:
    """[x1, x2] -> [1, L1(x1), L2(x1), L3(x1), L1(x2), L2(x2), L3(x2)] (Fig. 3)."""
    x = np.array([[0.3, -0.7]])
    row = legendre_features(x, 3)[0]
    expected = [1.0]
    for value in x[0]:
        expected += [legendre.legval(value, [0] * d + [1]) for d in (1, 2, 3)]
    np.testing.assert_allclose(row, expected, atol=1e-15)
    assert feature_count(2, 6) == 12  # Ex. 2: "expanded to 12 terms"
    assert feature_count(5, 2) == 10  # Ex. 4: "expanded to 10 terms"


def test_cross_terms_are_products_of_legendre_polynomials() -> None:
    x = np.array([[0.2, -0.5], [0.9, 0.4]])
    features = expand(x, 2, "legendre", cross_degree=3)
    crosses = cross_term_exponents(2, 3)
    assert (1, 1) in crosses and (2, 1) in crosses and (1, 2) in crosses
    column = 1 + 2 * 2 + crosses.index((2, 1))
    expected = legendre.legval(x[:, 0], [0, 0, 1]) * x[:, 1]
    np.testing.assert_allclose(features[:, column], expected, atol=1e-15)


def test_inputs_outside_the_interval_are_clipped_and_counted_or_refused() -> None:
    model = LeNN(n_inputs=1, order=3)
    model.predict(np.array([[1.5], [0.2]]))
    assert model.n_clipped_ == 1
    strict = LeNN(n_inputs=1, order=3, out_of_range="error")
    with pytest.raises(ValueError, match="outside"):
        strict.predict(np.array([[1.5]]))


# -- learning rules: gradients equal finite differences -----------------------------------
def _squared_error(model: OnlineRegressor, x: np.ndarray, d: float) -> float:
    return 0.5 * float(d - model.predict(x)[0]) ** 2


def _check_gradient(model: OnlineRegressor, parameters: str, x: np.ndarray, d: float) -> None:
    """One update with beta = 0 moves the weights by -alpha dE/dw (eqs. 6-10)."""
    model.predict(x)  # initialise
    before = getattr(model, parameters).copy()
    numeric = np.empty_like(before)
    step = 1e-6
    for i in range(len(before)):
        weights = getattr(model, parameters)
        weights[i] = before[i] + step
        plus = _squared_error(model, x, d)
        weights[i] = before[i] - step
        minus = _squared_error(model, x, d)
        weights[i] = before[i]
        numeric[i] = (plus - minus) / (2 * step)
    model.partial_fit(x, np.array([d]))
    analytic = -(getattr(model, parameters) - before) / model.alpha
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("output", ["tanh", "linear"])
def test_lenn_gradient_equals_finite_differences(output: str) -> None:
    model = LeNN(n_inputs=2, order=4, output=output, output_scale=1.7, alpha=0.1, beta=0.0, init_scale=0.4)
    _check_gradient(model, "weights_", np.array([[0.3, -0.6]]), 0.8)


def test_lenn_with_two_branches_gradient_equals_finite_differences() -> None:
    model = LeNN(n_inputs=2, order=5, branches=[[0], [1]], alpha=0.1, beta=0.0, init_scale=0.3)
    _check_gradient(model, "weights_", np.array([[0.3, -0.6]]), 0.4)


@pytest.mark.parametrize(("hidden", "branches"), [((20, 10), None), ((6, 4), [[0], [1, 2]]), ((5,), None)])
def test_mlp_gradient_equals_finite_differences(hidden: tuple[int, ...], branches) -> None:
    model = MLP(n_inputs=3, hidden=hidden, branches=branches, alpha=0.05, beta=0.0, output_scale=1.3)
    _check_gradient(model, "params_", np.array([[0.3, -0.6, 0.9]]), 0.5)


def test_momentum_follows_eq_10() -> None:
    """dw_k = alpha e (1 - y^2) phi + beta dw_{k-1}, on two samples by hand."""
    model = LeNN(n_inputs=1, order=2, alpha=0.3, beta=0.6, init_scale=0.2, random_state=4)
    x = np.array([[0.5], [-0.25]])
    d = np.array([0.4, -0.1])
    model.predict(x[:1])
    w = model.weights_.copy()
    dw = np.zeros_like(w)
    for k in range(2):
        phi = legendre_features(x[k : k + 1], 2)[0]
        y = math.tanh(w @ phi)
        dw = 0.3 * (d[k] - y) * (1 - y * y) * phi + 0.6 * dw
        w = w + dw
    model.partial_fit(x, d)
    np.testing.assert_allclose(model.weights_, w, rtol=1e-14)


def test_compiled_kernels_equal_their_pure_python_run(tmp_path) -> None:
    """Compiled kernels against the same code with numba switched off, in a fresh process.

    Not ``.py_func``: a kernel split into compiled helpers keeps calling them compiled.
    """
    if not jit.COMPILED:
        pytest.skip("numba is not installed: the kernels are plain Python already, nothing to compare")
    import kernel_reference

    reference = tmp_path / "python.npz"
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1", "PYTHONPATH": os.pathsep.join(sys.path)}
    subprocess.run([sys.executable, kernel_reference.__file__, str(reference)], env=env, check=True, timeout=120)
    python = np.load(reference)
    for solver in kernel_reference.SOLVERS:
        weights, y = kernel_reference.run(solver)
        np.testing.assert_allclose(weights, python[f"{solver}_w"], rtol=0, atol=1e-12, err_msg=solver)
        np.testing.assert_allclose(y, python[f"{solver}_y"], rtol=0, atol=1e-12, err_msg=solver)


# -- persistence ---------------------------------------------------------------------------
@pytest.mark.parametrize("network", ["lenn", "mlp"])
def test_save_load_predict_is_bit_identical(tmp_path, network: str) -> None:
    example = EXAMPLES[3]
    model = example.make_network(network, seed=7)
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (500, 2))
    model.partial_fit(x, rng.uniform(-1, 1, 500))
    model.save(tmp_path / "model.npz")
    loaded = OnlineRegressor.load(tmp_path / "model.npz")
    assert np.array_equal(loaded.predict(x), model.predict(x))
    # and learning continues identically (momentum is part of the saved state)
    more = rng.uniform(-1, 1, (50, 2))
    targets = rng.uniform(-1, 1, 50)
    assert np.array_equal(loaded.update(more, targets), model.update(more, targets))


def test_weights_of_another_network_are_refused(tmp_path) -> None:
    EXAMPLES[1].make_network("lenn").save(tmp_path / "lenn.npz")
    with pytest.raises(ModelFileError, match="different network"):
        EXAMPLES[1].make_network("mlp").load_state(tmp_path / "lenn.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a model")
    with pytest.raises(ModelFileError, match="not a lenn_ros weights file"):
        EXAMPLES[1].make_network("lenn").load_state(tmp_path / "junk.npz")


def test_rls_state_round_trips(tmp_path) -> None:
    model = FunctionalLinkNetwork(n_inputs=2, order=3, output="linear", solver="rls", forgetting=0.99)
    rng = np.random.default_rng(2)
    model.partial_fit(rng.uniform(-1, 1, (200, 2)), rng.normal(size=200))
    model.save(tmp_path / "rls.npz")
    loaded = OnlineRegressor.load(tmp_path / "rls.npz")
    assert np.array_equal(loaded.covariance_, model.covariance_)


# -- plants and signals -------------------------------------------------------------------
def test_example1_plant_matches_its_difference_equation_by_hand() -> None:
    plant = example_plant(1)
    u = [0.5, -0.25, 1.0]
    y = plant.run(np.array(u))
    g = [0.6 * math.sin(math.pi * v) + 0.3 * math.sin(3 * math.pi * v) + 0.1 * math.sin(5 * math.pi * v) for v in u]
    y1 = g[0]  # y(1) = 0.3*0 + 0.6*0 + g(u(0))
    y2 = 0.3 * y1 + g[1]
    y3 = 0.3 * y2 + 0.6 * y1 + g[2]
    np.testing.assert_allclose(y, [0.0, y1, y2, y3], rtol=1e-15)


def test_examples_2_3_4_match_their_difference_equations() -> None:
    y = example_plant(2).run(np.array([0.5, 0.2, -0.3]))
    f = lambda a, b: a * b * (a + 2.5) * (a - 1.0) / (1 + a * a + b * b)  # noqa: E731
    assert y[1] == pytest.approx(0.5) and y[2] == pytest.approx(f(0.5, 0.0) + 0.2)
    assert y[3] == pytest.approx(f(y[2], y[1]) - 0.3)
    y = example_plant(3).run(np.array([0.5, -0.4]))
    assert y[1] == pytest.approx(0.5 * 1.3 * 0.0)  # g(0.5) = 0.5 * 1.3 * 0
    assert y[2] == pytest.approx(y[1] * (y[1] + 0.3) / (1 + y[1] ** 2) + (-0.4) * 0.4 * (-0.9))
    y = example_plant(4).run(np.array([0.7, -0.2, 0.1]))
    f4 = lambda a1, a2, a3, a4, a5: (a1 * a2 * a3 * a5 * (a3 - 1) + a4) / (1 + a2 * a2 + a3 * a3)  # noqa: E731
    assert y[1] == pytest.approx(f4(0, 0, 0, 0.7, 0))
    assert y[2] == pytest.approx(f4(y[1], 0, 0, -0.2, 0.7))
    assert y[3] == pytest.approx(f4(y[2], y[1], 0, 0.1, -0.2))


def test_user_defined_plant_equals_the_builtin_example() -> None:
    user = plant_from_expressions(1, 2, 1, g="0.6*sin(pi*u1) + 0.3*sin(3*pi*u1) + 0.1*sin(5*pi*u1)", a=(0.3, 0.6))
    u = np.random.default_rng(0).uniform(-1, 1, 200)
    np.testing.assert_allclose(user.run(u), example_plant(1).run(u), rtol=1e-13)


@pytest.mark.parametrize(
    "text",
    ["__import__('os').system('true')", "y1.__class__", "open('x')", "[y1 for y1 in ()]", "'a'", "lambda: 1"],
)
def test_expressions_cannot_run_code(text: str) -> None:
    with pytest.raises(ExpressionError):
        compile_expression(text, ("y1",))


def test_inconsistent_plants_are_refused() -> None:
    with pytest.raises(ValueError, match="m <= n"):
        Plant(4, n=1, m=2, f=lambda *a: 0.0)
    with pytest.raises(ValueError, match="coefficients a"):
        Plant(1, n=2, m=1, g=lambda u: u, a=(0.3,))
    with pytest.raises(ValueError, match="unknown example"):
        get_example(5)


def test_test_signal_is_eq_11() -> None:
    u = eq11_sinusoid(600)
    assert u[0] == pytest.approx(math.sin(2 * math.pi / 250))
    assert u[249] == pytest.approx(math.sin(2 * math.pi * 250 / 250), abs=1e-12)
    assert u[250] == pytest.approx(0.8 * math.sin(2 * math.pi * 251 / 250) + 0.2 * math.sin(2 * math.pi * 251 / 25))
    assert noise_std(-10.0) == pytest.approx(math.sqrt(0.1 / 3))


def test_sample_by_sample_excitation_equals_the_whole_series() -> None:
    """The live simulator (one sample at a time) and simulate() see the same data."""
    whole = Excitation(3, "paper", 5000, 600, -10.0)
    u, noise = whole.series()
    stepwise = Excitation(3, "paper", 5000, 600, -10.0)
    pairs = np.array([stepwise.sample(k) for k in range(5600)])
    assert np.array_equal(pairs[:, 0], u) and np.array_equal(pairs[:, 1], noise)
    assert np.all(noise[5000:] == 0.0)  # the test phase is noise-free by default


# -- metrics and complexity ------------------------------------------------------------------
def test_nmse_of_perfect_and_zero_models() -> None:
    y = np.array([1.0, 2.0, 3.0, 6.0])
    assert nmse_db(y, y) == -np.inf
    assert nmse(y, np.zeros(4)) == pytest.approx(np.mean(y**2) / np.var(y))
    running = RunningNMSE()
    y_hat = y + np.array([0.1, -0.2, 0.05, 0.3])
    for a, b in zip(y, y_hat, strict=True):
        running.add(a, b)
    assert running.nmse_db == pytest.approx(nmse_db(y, y_hat), abs=1e-12)


def test_table1_counts() -> None:
    assert mlp_complexity([1, 20, 10, 1]).as_dict() == {
        "weights": 261,
        "additions": 3 * 230 + 3 - 20,  # S2 = 1*20 + 20*10 + 10*1
        "multiplications": 4 * 230 + 3 * 31 - 20 + 2,
        "tanh": 31,
    }
    assert lenn_complexity(14).as_dict() == {"weights": 15, "additions": 31, "multiplications": 59, "tanh": 1}
    assert EXAMPLES[3].complexity("lenn").weights == 30  # N1 and N2, {14-1} each


# -- the identifier: one-sample path equals the batch path -------------------------------------
@pytest.mark.skipif(not jit.JIT, reason="the compiled step exists only where numba compiles")
@pytest.mark.parametrize(
    ("number", "settings"),
    [
        (1, {"solver": "sgd", "alpha": 0.5}),  # known linear part, tanh output
        (2, {"solver": "sgd", "alpha": 1e308}),  # a non-finite step: rollback in the middle of a step
        (3, {"solver": "sgd"}),  # two branches
        (4, {"solver": "nlms", "output": "linear"}),
        (4, {"solver": "rls", "output": "linear", "forgetting": 0.995, "cross_degree": 2}),
        (1, {"solver": "rls", "output": "linear", "basis": "chebyshev"}),
    ],
)
def test_compiled_step_equals_the_python_step(monkeypatch, number: int, settings: dict) -> None:
    """The one-call compiled step gives the Python step's numbers, weights and counters, bit for bit."""
    from lenn_ros.core import structure

    example = EXAMPLES[number]
    series = simulate(example.plant(), example.noise_db, 3, 1500, 200)
    u, y = 1.6 * series.u, series.y  # |u| up to 1.6 > 1: inputs get clipped
    learn = np.arange(1700) < 1500
    runs = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(structure.StepPlan, "for_model", classmethod(lambda cls, model, shape: None))
        identifier = Identifier(example.structure, example.make_network("lenn", 5, **settings), health_interval=300)
        results = [identifier.step(k + 1 + (k >= 900), u[k], y[k], bool(learn[k])) for k in range(1700)]  # a gap
        assert (identifier._plan is not None) == compiled
        runs.append((results, identifier))
    (fast, fast_id), (slow, slow_id) = runs
    fields = ("y_hat", "y_hat_next", "error", "learned", "event")
    for a, b in zip(fast, slow, strict=True):
        assert [getattr(a, name) for name in fields] == [getattr(b, name) for name in fields]
    assert fast_id.counters == slow_id.counters
    # |u| up to 1.6 is clipped wherever u feeds the network (690-1379 inputs here); example 2's u
    # enters only through its known linear part (u_lags 0), so nothing of it is clipped there
    assert (fast_id.counters["clipped"] > 0) == (example.structure.u_lags > 0), fast_id.counters["clipped"]
    assert fast_id.diverged == slow_id.diverged == (number == 2)
    assert np.array_equal(fast_id.model.weights_, slow_id.model.weights_)
    assert fast_id.model.n_samples_seen_ == slow_id.model.n_samples_seen_
    assert fast_id.model.n_clipped_ == slow_id.model.n_clipped_


@pytest.mark.parametrize(("number", "network"), [(1, "lenn"), (3, "lenn"), (3, "mlp"), (4, "lenn")])
def test_step_by_step_equals_batch_run(number: int, network: str) -> None:
    example = EXAMPLES[number]
    series = simulate(example.plant(), example.noise_db, 5, 2500, 300)
    learn = np.arange(2800) < 2500
    batch = Identifier(example.structure, example.make_network(network, 5), health_interval=700)
    y_batch = batch.run(series.u, series.y, learn)
    online = Identifier(example.structure, example.make_network(network, 5), health_interval=700)
    y_online = np.full(2800, np.nan)
    for k in range(2800):
        result = online.step(k + 1, series.u[k], series.y[k], bool(learn[k]))
        if result.y_hat is not None:
            y_online[k] = result.y_hat
    assert np.array_equal(y_batch, y_online, equal_nan=True)
    assert batch.counters["learned"] == online.counters["learned"]


def test_gaps_duplicates_and_bad_samples_are_never_learnt_from() -> None:
    example = EXAMPLES[2]
    identifier = Identifier(example.structure, example.make_network("lenn", 0))
    u = np.random.default_rng(0).uniform(-1, 1, 50)
    y = example.plant().run(u)
    for k in range(20):
        identifier.step(k + 1, u[k], y[k])
    weights = identifier.model.weights_.copy()
    assert identifier.step(20, u[19], y[19]).event == "duplicate"
    assert identifier.step(5, u[4], y[4]).event == "duplicate"
    result = identifier.step(23, u[22], y[22])  # 21 and 22 lost
    assert result.event == "gap" and result.error is None and not result.learned
    assert identifier.step(24, u[23], y[23]).error is None  # history not yet complete again (two y lags)
    assert np.array_equal(identifier.model.weights_, weights)
    assert identifier.counters["lost"] == 2 and identifier.counters["duplicates"] == 2


def test_divergence_guard_restores_the_healthy_weights() -> None:
    example = EXAMPLES[1]
    series = simulate(example.plant(), example.noise_db, 0, 4000, 600)
    model = example.make_network("lenn", 0, output="linear")  # a tanh output saturates instead of exploding
    identifier = Identifier(example.structure, model, health_interval=500)
    identifier.run(series.u[:3001], series.y[:3001], True)
    frozen = Identifier(example.structure, model, learning=False)
    before = nmse_db(series.y[4000:], frozen.run(series.u, series.y, False)[4000:])
    assert not identifier.diverged
    identifier.model.set_params(alpha=50.0, beta=0.9)  # a user sets an absurd learning rate live
    identifier.run(series.u[3000:4000], series.y[3000:4000], True)
    assert identifier.diverged and identifier.counters["diverged"] == 1
    assert np.all(np.isfinite(identifier.model.weights_))
    after = nmse_db(series.y[4000:], frozen.run(series.u, series.y, False)[4000:])
    assert after < before + 1.0  # predictions go on from a model as good as before the fault


def test_reproduction_of_example_1_reaches_the_papers_figure() -> None:
    """A short, real run: the calibrated LeNN beats -23 dB after 20 000 samples."""
    result = run_example(EXAMPLES[1], "lenn", seed=11, train_samples=20_000)
    assert result.nmse_db < -23.0


def test_structure_validation() -> None:
    with pytest.raises(ValueError):
        ModelStructure(y_lags=0, u_lags=0)
    with pytest.raises(ValueError):
        ModelStructure(y_lags=0, u_lags=1, separate=True)


@pytest.mark.parametrize(("basis", "cross"), [("legendre", 0), ("legendre", 3), ("chebyshev", 2)])
def test_one_sample_expansion_is_bitwise_the_batch_expansion(
    basis: str, cross: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The live node expands one sample at a time through a faster scalar path.

    The batch functions are wrapped to refuse single rows, so a one-sample call that
    quietly took the batch path (and so compared the batch path with itself) fails here.
    Trigonometric terms have no scalar path: nothing to compare for them.
    """
    from lenn_ros.core import expansions

    assert set(expansions._SCALAR_RECURSIONS) == {"legendre", "chebyshev"}
    x = np.random.default_rng(0).uniform(-1, 1, (200, 3))
    batch = expand(x, 5, basis, cross)
    original = expansions._UNIVARIATE[basis]

    def batch_only(values: np.ndarray, order: int) -> np.ndarray:
        assert values.shape[0] != 1, "one sample took the batch path"
        return original(values, order)

    monkeypatch.setitem(expansions._UNIVARIATE, basis, batch_only)
    one_by_one = np.vstack([expand(x[i : i + 1], 5, basis, cross) for i in range(200)])
    assert np.array_equal(one_by_one, batch)


@pytest.mark.skipif(not jit.JIT, reason="the compiled step exists only where numba compiles")
def test_terms_with_factors_step_compiled_as_in_python_and_in_batch(monkeypatch) -> None:
    """Every factor kind in a selected-terms model: compiled step = Python step = batch run, bit for bit."""
    from lenn_ros.core import structure
    from lenn_ros.core.expansions import parse_terms, siso_channels
    from lenn_ros.core.networks import FunctionalLinkNetwork
    from lenn_ros.core.structure import ModelStructure

    names = ["1", "y1", "lin(y1-y2)", "tanh(8*y1-8*y2)", "u1*abs(3*y1-3*y2)", "relu(u1-0.2)", "cos(1.5*y1+0.7*u2-0.3)",
             "sqabs(2*y1-2*y2)", "y1^2*u2"]  # fmt: skip
    exponents, factors = parse_terms(names, siso_channels(2, 2))
    shape = ModelStructure(y_lags=2, u_lags=2, y_scale=2.0, u_scale=1.5)
    series = simulate(EXAMPLES[1].plant(), -20.0, 4, 1200, 100)
    u, y = 1.6 * series.u, series.y  # inputs beyond the scale: clipped
    learn = np.arange(1300) < 1200

    def network() -> FunctionalLinkNetwork:
        return FunctionalLinkNetwork(n_inputs=4, exponents=exponents.tolist(), factors=factors.tolist(),
                                     output="linear", solver="rls", forgetting=0.999, init_scale=0.0)  # fmt: skip

    runs = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(structure.StepPlan, "for_model", classmethod(lambda cls, model, shape: None))
        identifier = Identifier(shape, network(), health_interval=300)
        runs.append(([identifier.step(k + 1, u[k], y[k], bool(learn[k])) for k in range(1300)], identifier))
    (fast, fast_id), (slow, slow_id) = runs
    assert fast_id._plan is not None and slow_id._plan is None
    assert [r.y_hat for r in fast] == [r.y_hat for r in slow]
    assert np.array_equal(fast_id.model.weights_, slow_id.model.weights_)
    batch = Identifier(shape, network(), health_interval=300)
    y_batch = batch.run(u, y, learn)
    stepped = np.array([np.nan if r.y_hat is None else r.y_hat for r in fast])
    assert np.array_equal(np.isnan(y_batch), np.isnan(stepped))
    assert np.allclose(y_batch[~np.isnan(y_batch)], stepped[~np.isnan(stepped)], rtol=0, atol=1e-12)
    assert fast_id.counters["clipped"] > 0
    # the compiled free run of the same model: the Python loop of one prediction per sample
    frozen = slow_id
    compiled = frozen.free_run(u, y, 1000)
    y_model, window = y.copy(), shape.warm_up
    for k in range(999, 1299):
        x, linear = shape.regressors(u[k - window + 1 : k + 1], y_model[k - window + 1 : k + 1])
        y_model[k + 1] = linear[-1] + frozen.model.predict(np.clip(x[-1:], -1.0, 1.0))[0]
    assert np.allclose(compiled, y_model[1000:], rtol=0, atol=1e-12)


@pytest.mark.parametrize("example", [1, 2, 3, 4])
def test_one_output_free_run_is_the_several_output_path_compiled_or_not(example: int, monkeypatch) -> None:
    """A single-output identifier runs the one free-run path (core.free_run) with its known linear part
    (Ex. 1, 2, 4) and its two branches (Ex. 3): compiled and in Python, the same outputs, clipping and
    divergence. The Python path is the MLP's; here it runs the same LeNN so the two can be compared."""
    from free_run_check import assert_same_divergence, assert_same_free_run

    from lenn_ros import config
    from lenn_ros.service.building import build_identifier

    if not jit.JIT:
        pytest.skip("numba is not installed: there is no compiled free run")
    spec = get_example(example)
    series = simulate(spec.plant(), spec.noise_db, 3, 1500, 300)
    values, network = config.resolve({"example": example})
    identifier = build_identifier(values, network)
    identifier.run(series.u, series.y, np.arange(len(series.y)) < 1500)
    fast, _info = assert_same_free_run(identifier, series.u, series.y, 1500, monkeypatch)
    assert np.isfinite(fast).all()
    identifier.model.weights_ *= 1e4  # far beyond the output range: both stop at the same sample
    identifier.model.output_scale *= 1e4  # (a tanh output is bounded by its scale)
    assert_same_divergence(identifier, series.u, series.y, 1500, monkeypatch)
