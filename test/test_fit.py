"""``lenn-ros fit``: structure selection, compiled free run, params/weights round trip, user mistakes.

Synthetic data come from a known NARX plant with a cubic stiffness (a small
Silverbox), so the test can check that the selection finds what matters; one test
runs on a slice of the real Silverbox recording.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from lenn_ros.config import ConfigError, build_identifier, read_params_file, resolve
from lenn_ros.core.evaluation import free_run_problems
from lenn_ros.core.examples import get_example
from lenn_ros.core.expansions import format_terms, parse_terms
from lenn_ros.core.scaling import Scaling
from lenn_ros.core.selection import (
    PARSIMONY,
    Candidate,
    TermModel,
    _simplest_first,
    evaluate_prefixes,
    forward_regression,
    in_sample_problem,
)
from lenn_ros.core.structure import Identifier
from lenn_ros.fit import Data, fit

SILVERBOX = Path(__file__).resolve().parents[2] / "shared" / "data" / "silverbox_multisine.csv"
BALL_AND_BEAM = SILVERBOX.parent / "daisy_ball-and-beam.csv"


def cubic_plant(n: int, seed: int, noise: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """y(k) = 1.5 y(k-1) - 0.7 y(k-2) + 0.35 u(k-1) - 0.4 y(k-1)^3, plus output noise."""
    rng = np.random.default_rng(seed)
    u = np.convolve(rng.uniform(-1, 1, n), np.ones(3) / 3, mode="same") + 0.3
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 1.5 * y[k - 1] - 0.7 * y[k - 2] + 0.35 * u[k - 1] - 0.4 * y[k - 1] ** 3
    return u, y + noise * rng.standard_normal(n)


def linear_arx_free_run(u: np.ndarray, y: np.ndarray, start: int) -> float:
    """Free-run RMSE of a least-squares ARX(2, 2) on the same split: the bar to clear."""
    k = np.arange(2, start)
    regressors = np.c_[y[k - 1], y[k - 2], u[k - 1], u[k - 2], np.ones(len(k))]
    theta = np.linalg.lstsq(regressors, y[k], rcond=None)[0]
    sim = y.copy()
    for j in range(start, len(y)):
        sim[j] = theta @ [sim[j - 1], sim[j - 2], u[j - 1], u[j - 2], 1.0]
    return float(np.sqrt(np.mean((sim[start:] - y[start:]) ** 2)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fit_finds_the_cubic_term_and_beats_linear_arx(seed: int) -> None:
    u, y = cubic_plant(3000, seed)
    result = fit(Data(u, y, "synthetic"), 2001)
    report = result["report"]
    assert report["samples"] == 1000
    assert "y1^3" in report["model"]["expansion"]["terms"] or "y1^2" in report["model"]["expansion"]["terms"]
    assert report["rmse_free_run"] < 0.5 * linear_arx_free_run(u, y, 2000)
    assert report["rmse_free_run"] < 0.01  # noise is 0.002; the output spans about +-1
    assert report["warnings"] == []
    assert report["free_run"]["diverged"] is False
    chosen = report["choices"]["candidates"][report["choices"]["chosen"]]
    scored = [c for c in report["choices"]["candidates"] if c["rmse_free_run_validation"]]
    lowest = min(c["rmse_free_run_validation"] for c in scored)
    close = [c for c in scored if c["rmse_free_run_validation"] <= lowest * 1.01]
    assert chosen["rmse_free_run_validation"] <= lowest * 1.01  # parsimony: the fewest terms of those within 1 %
    assert chosen["terms"] == min(c["terms"] for c in close)


def test_cli_json_params_and_weights_rebuild_the_same_model(tmp_path: Path) -> None:
    u, y = cubic_plant(2500, 3)
    data = tmp_path / "log.csv"
    np.savetxt(data, np.c_[np.arange(len(u)), u, y], delimiter=",", header="t,input,output", comments="")
    out = tmp_path / "model"
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(data), "--u", "input", "--y", "2", "--test-from", "2001",
         "--json", "-o", str(out), "--plot", str(tmp_path / "fit.png")],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    for key in ("rmse", "rmse_free_run", "nmse_db", "nmse_free_run_db", "samples", "model", "choices"):
        assert key in report
    assert report["samples"] == 500
    assert {"structure", "expansion", "n_terms", "solver"} <= set(report["model"])
    assert (tmp_path / "fit.png").stat().st_size > 0
    document = yaml.safe_load((out / "params.yaml").read_text())
    assert list(document) == ["/**"]
    values = read_params_file(out / "params.yaml")
    resolved, network = resolve(values)
    identifier = build_identifier(resolved, network)
    identifier.model.load_state(out / "weights.npz")
    y_free = identifier.free_run(u, y, 2000)
    rmse = float(np.sqrt(np.mean((y_free - y[2000:]) ** 2)))
    assert rmse == pytest.approx(report["rmse_free_run"], rel=1e-9)
    # live: RLS keeps adapting from the fitted weights without losing the model
    identifier.learning = True
    before = identifier.model.weights_.copy()
    errors = [identifier.step(k, float(u[k]), float(y[k])).error for k in range(2000, 2500)]
    errors = np.array([e for e in errors if e is not None])
    assert not np.array_equal(before, identifier.model.weights_)
    assert np.sqrt(np.mean(errors**2)) < 0.01


def test_compiled_free_run_equals_the_python_loop_and_counts_clipping() -> None:
    example = get_example(1)
    rng = np.random.default_rng(5)
    u = rng.uniform(-1.5, 1.5, 600)  # beyond the scale: inputs get clipped
    y = np.sin(np.arange(600) / 7.0)
    identifier = Identifier(example.structure, example.make_network("lenn", 0))
    compiled = identifier.free_run(u, y, 100)
    window, y_model, clipped = example.structure.warm_up, y.copy(), 0
    for k in range(99, 599):
        x, linear = example.structure.regressors(u[k - window + 1 : k + 1], y_model[k - window + 1 : k + 1])
        clipped += int(np.count_nonzero(np.abs(x[-1]) > 1.0))
        y_model[k + 1] = linear[-1] + identifier.model.predict(np.clip(x[-1:], -1.0, 1.0))[0]
    assert np.allclose(compiled, y_model[100:], rtol=0, atol=1e-12)
    assert clipped > 0
    assert identifier.last_free_run["clipped_inputs"] == clipped
    assert identifier.counters["clipped_free_run"] == clipped


def test_unstable_free_run_is_flagged_not_printed_as_a_number() -> None:
    scaling = Scaling(0.0, 1.0, 0.0, 1.0)
    u, y = np.ones(200), np.zeros(200)
    exploding = TermModel(1, 1, scaling, parse_terms(["y1", "u1"], 1, 1), weights=np.array([30.0, 1.0]))
    y_sim, clipped, diverged_at = exploding.free_run(u, y, 10)
    assert diverged_at > 10 and np.isnan(y_sim[-1])
    problems = free_run_problems(y[10:] + np.sin(np.arange(190)), y_sim, {"diverged": True, "diverged_at": 11})
    assert "free run diverged at sample 12" in problems[0]
    # an unstable model that only saturates (inputs clipped at +-1) is reported by its clipping
    saturating = TermModel(1, 1, scaling, parse_terms(["y1", "u1"], 1, 1), weights=np.array([1.5, 1.0]))
    y_sim, clipped, diverged_at = saturating.free_run(u, y, 10)
    assert diverged_at == -1 and clipped > 150
    problems = free_run_problems(np.sin(np.arange(190)), y_sim, {"clipped_inputs": clipped})
    assert any("worse than predicting the mean" in p for p in problems)
    assert any(f"{clipped} free-run network inputs" in p for p in problems)


def test_forward_regression_ranks_the_true_terms_first() -> None:
    rng = np.random.default_rng(0)
    features = rng.uniform(-1, 1, (2000, 8))
    targets = 2.0 * features[:, 3] - 1.0 * features[:, 6] + 0.01 * rng.standard_normal(2000)
    order, ratios = forward_regression(features, targets, 4)
    assert order[:2] == [3, 6]
    assert ratios[0] > ratios[1] > ratios[2]


def test_term_names_round_trip() -> None:
    rows = np.array([[0, 0, 0, 0], [3, 0, 0, 0], [1, 0, 0, 2], [0, 1, 1, 0]])
    names = format_terms(rows, 2)
    assert names == ["1", "y1^3", "y1*u2^2", "y2*u1"]
    assert np.array_equal(parse_terms(names, 2, 2), rows)
    with pytest.raises(ValueError, match="y_lags=2"):
        parse_terms(["y3"], 2, 2)


def test_params_file_keys_and_typos(tmp_path: Path) -> None:
    for key in ("/**", "/**/identifier", "identifier", "/robot/identifier"):
        path = tmp_path / "p.yaml"
        path.write_text(yaml.safe_dump({key: {"ros__parameters": {"y_lags": 2}}}))
        assert read_params_file(path, "/robot/identifier" if key.startswith("/robot") else "/identifier")["y_lags"] == 2
    with pytest.raises(ConfigError, match="no section for the node /identifier"):
        read_params_file(path)  # /robot/identifier is not /identifier (rcl's rules, issue 18)
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"y_lag": 2, "u_type": "std_msgs/msg/Float64"}}}))
    with pytest.raises(ConfigError, match=r"'y_lag'.*did you mean 'y_lags'"):
        resolve(read_params_file(path))
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"uscale": 2.0}}}))
    with pytest.raises(ConfigError, match=r"'uscale'.*'u_scale'"):
        resolve(read_params_file(path))


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--test-from", "5"], "at least 100"),
        (["--test-from", "9999"], "outside the data's samples"),
        (["--u", "speed", "--test-from", "500"], "no column 'speed'; columns are u, y, z"),
        (["--y", "z", "--test-from", "500"], "constant"),
    ],
)
def test_new_user_mistakes_get_one_line_naming_the_fix(tmp_path: Path, arguments: list[str], message: str) -> None:
    u, y = cubic_plant(1000, 0)
    data = tmp_path / "log.csv"
    np.savetxt(data, np.c_[u, y, np.ones(1000)], delimiter=",", header="u,y,z", comments="")
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(data), *arguments],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 2
    assert message in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert "Traceback" not in done.stderr


def test_three_columns_without_names_ask_for_them(tmp_path: Path) -> None:
    data = tmp_path / "log.csv"
    np.savetxt(data, np.random.default_rng(0).normal(size=(300, 3)), delimiter=",")
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(data), "--test-from", "200"],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 2 and "pass --u COL --y COL" in done.stderr


@pytest.mark.skipif(not SILVERBOX.exists(), reason="shared Silverbox data not present")
def test_silverbox_slice_beats_linear_and_polynomial_narx_level() -> None:
    """Real data (a slice, to stay fast): the cubic spring must be found and simulated."""
    table = np.loadtxt(SILVERBOX, delimiter=",", skiprows=1, max_rows=30_000)
    u, y = table[:, 1], table[:, 2]
    report = fit(Data(u, y, "silverbox slice"), 24_001)["report"]
    assert report["rmse_free_run"] < 0.5 * linear_arx_free_run(u, y, 24_000)
    assert report["rmse_free_run"] < 0.002  # FROLS reaches ~0.0043 on the full split
    assert any("^3" in term or "^2" in term for term in report["model"]["expansion"]["terms"])


def test_epochs_with_early_stopping_beat_one_pass_on_small_data() -> None:
    """SGD on 1 500 samples: more passes help, and the kept weights are the held-out best."""
    from lenn_ros.core.networks import FunctionalLinkNetwork
    from lenn_ros.core.training import held_out_rmse, train_epochs

    u, y = cubic_plant(1500, 4)
    scaling = Scaling.from_training(u, y)
    structure = TermModel(2, 2, scaling, parse_terms(["1"], 2, 2)).structure
    network = FunctionalLinkNetwork(n_inputs=4, order=3, output="linear", alpha=0.05, beta=0.5, random_state=0)
    identifier = Identifier(structure, network, learning=False)
    report = train_epochs(identifier, u, y, 1200, max_epochs=40, patience=5)
    assert report.epochs > 1
    assert min(report.validation_rmse) < 0.8 * report.validation_rmse[0]
    assert held_out_rmse(identifier, u, y, 1200) == pytest.approx(min(report.validation_rmse))


def test_in_sample_check_rejects_a_model_that_runs_away_on_its_own_data() -> None:
    u, y = cubic_plant(1500, 5)
    scaling = Scaling.from_training(u, y)
    terms = parse_terms(["1", "y1", "y2", "u1", "y1^3"], 2, 2)
    features, targets = TermModel(2, 2, scaling, terms).regression(u, y)
    good = TermModel(2, 2, scaling, terms, weights=np.linalg.lstsq(features, targets, rcond=None)[0])
    assert in_sample_problem(good, u, y) == ""
    runaway = TermModel(2, 2, scaling, terms, weights=good.weights * np.array([1.0, 1.0, 1.0, 1.0, 3.0]))
    assert in_sample_problem(runaway, u, y) == "in-sample free run left the training range"
    flat = TermModel(2, 2, scaling, parse_terms(["1"], 2, 2), weights=np.array([float(y.max())]))
    assert in_sample_problem(flat, u, y) == "in-sample free run worse than its mean"


def test_a_prefix_worse_than_the_held_out_mean_or_failing_the_check_is_not_chosen() -> None:
    u, y = cubic_plant(1500, 6)
    scaling = Scaling.from_training(u, y)
    dictionary = parse_terms(["y1", "y2", "u1", "u2", "y1^3"], 2, 2)
    model = TermModel(2, 2, scaling, dictionary)
    features, targets = model.regression(u[:1200], y[:1200])
    folds = [(features.T @ features, features.T @ targets, u, y, 1200)]
    ranked = [0, 1, 2, 3, 4]
    terms, error, _, why = evaluate_prefixes(model, ranked, folds, dictionary)
    assert terms and not why
    refused, _, _, why = evaluate_prefixes(model, ranked, folds, dictionary, reference=error * 0.5)
    assert refused == 0 and "worse than its mean" in why
    asked: list[int] = []

    def refuse_the_preferred(exponents: np.ndarray, weights: np.ndarray) -> str:
        asked.append(len(exponents))
        return "in-sample free run left the training range" if len(asked) == 1 else ""

    second, _, _, why = evaluate_prefixes(model, ranked, folds, dictionary, check=refuse_the_preferred)
    assert asked[0] == terms and second != terms and not why


def test_of_candidates_within_parsimony_the_fewest_terms_come_first() -> None:
    scaling = Scaling(0.0, 1.0, 0.0, 1.0)
    stub = TermModel(1, 1, scaling, parse_terms(["y1"], 1, 1), weights=np.ones(1))
    big = Candidate(4, 4, 3, "legendre", 86, terms=23, rmse_validation=1.0, model=stub)
    small = Candidate(3, 3, 3, "legendre", 84, terms=10, rmse_validation=1.0 + PARSIMONY / 2, model=stub)
    far = Candidate(2, 2, 1, "legendre", 5, terms=5, rmse_validation=1.0 + 2 * PARSIMONY, model=stub)
    candidates = [big, small, far]
    _simplest_first(candidates)
    assert candidates[0] is small and "fewest terms" in small.note and not big.note


def test_when_no_candidate_passes_the_strict_checks_fit_says_so() -> None:
    """A random walk unrelated to u: nothing simulates it better than the mean."""
    rng = np.random.default_rng(0)
    u, y = rng.uniform(-1, 1, 1500), np.cumsum(rng.standard_normal(1500))
    report = fit(Data(u, y, "random walk"), 1201)["report"]
    assert "no candidate structure passed the strict checks" in report["warnings"][0]
    assert "held-out free run worse than its mean" in report["warnings"][0]


@pytest.mark.skipif(not BALL_AND_BEAM.exists(), reason="shared ball-and-beam data not present")
def test_ball_and_beam_chosen_structure_simulates_its_own_training_data() -> None:
    """Real data, 666 training samples: the old choice ran away on its own estimation samples (1300 clipped)."""
    table = np.genfromtxt(BALL_AND_BEAM, delimiter=",", names=True)
    u, y = np.asarray(table["u"], float), np.asarray(table["y"], float)
    result = fit(Data(u, y, "ball and beam"), 667, refine=False)
    report = result["report"]
    estimation = report["choices"]["estimation_samples"]
    assert in_sample_problem(result["model"], u[:estimation], y[:estimation]) == ""
    assert report["free_run"]["clipped_inputs"] == 0


def test_peer_table_shows_the_test_mean_predictor_and_marks_rows_worse_than_it() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import peer_narx

    split = peer_narx.Split("s", np.zeros(10), np.array([0.0] * 5 + [1.0, -1.0, 1.0, -1.0, 1.0]), 6, "")
    mean = peer_narx.test_mean_rmse(split)
    assert mean == pytest.approx(np.std([1.0, -1.0, 1.0, -1.0, 1.0]))
    model = {"seconds": 1.0, "model": "m"}
    rows = [
        {"data": "good", "test_samples": 5, "test_mean_rmse": mean,
         "lenn": {**model, "rmse_free_run": 0.1}, "frols": {**model, "rmse_free_run": 2.0}},
        {"data": "bad", "test_samples": 5, "test_mean_rmse": mean,
         "lenn": {**model, "rmse_free_run": 1.5}, "frols": {**model, "rmse_free_run": float("nan")}},
    ]  # fmt: skip
    lines = peer_narx.table(rows).splitlines()
    assert "test-mean predictor" in lines[0] and lines[0].count("|") == lines[1].count("|")
    good, bad = lines[2].split(" | "), lines[3].split(" | ")
    assert good[1] == "0.1" and good[2] == "2 (worse than the mean)" and good[3] == f"{mean:.4g}"
    assert bad[1] == "1.5 (worse than the mean)" and bad[2] == "diverged (worse than the mean)"


def test_fit_solver_sgd_trains_the_selected_terms_by_epochs_and_round_trips(tmp_path: Path) -> None:
    from lenn_ros.fit import write_outputs

    u, y = cubic_plant(2500, 8)
    result = fit(Data(u, y, "synthetic"), 2001, solver="sgd")
    report = result["report"]
    assert report["model"]["live"]["solver"] == "sgd" and report["model"]["epochs"]["best_epoch"] > 1
    assert report["choices"]["refinement"] == {"done": False}
    assert report["rmse_free_run"] < 0.5 * float(np.std(y[2000:]))  # well better than the mean
    files = write_outputs(tmp_path / "model", result, u[:2000], y)
    values = read_params_file(files["params"])
    assert values["solver"] == "sgd" and values["alpha"] == pytest.approx(result["identifier"].model.alpha)
    resolved, network = resolve(values)
    identifier = build_identifier(resolved, network)
    identifier.model.load_state(values["weights_in"])
    y_free = identifier.free_run(u, y, 2000)
    assert float(np.sqrt(np.mean((y_free - y[2000:]) ** 2))) == pytest.approx(report["rmse_free_run"], rel=1e-9)
