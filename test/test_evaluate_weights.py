"""``lenn-ros evaluate`` starts from the weights the node started from (``weights_in``).

A params file written by ``lenn-ros fit -o DIR``, or the configuration an identifier
started with such a file records in its bag, must be scored from the fitted weights,
exactly as the node would learn from them: the reference here is the same model built
by hand, its weights loaded, trained and tested by :func:`train_and_test`.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_fit import cubic_plant

from lenn_ros import topics
from lenn_ros.bag.writer import BagWriter
from lenn_ros.config import NODE_PARAMETERS, resolve
from lenn_ros.fit.data import Data
from lenn_ros.fit.export import write_outputs
from lenn_ros.fit.procedure import fit
from lenn_ros.paper.evaluation import Series, train_and_test
from lenn_ros.service import RecordingError
from lenn_ros.service.building import build_identifier
from lenn_ros.service.evaluation import evaluate_bag
from lenn_ros.service.params import read_params_file
from lenn_ros.service.scoring import fit_free_run_widths

REPO = Path(__file__).resolve().parents[1]
TRAIN = 2000


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> tuple[np.ndarray, np.ndarray, dict, dict[str, str]]:
    u, y = cubic_plant(2500, 3)
    result = fit(Data(u, y, "synthetic"), TRAIN + 1)
    files = write_outputs(tmp_path_factory.mktemp("fit") / "model", result, Data(u, y, "fitted"))
    return u, y, result, files


def write_bag(path: Path, u: np.ndarray, y: np.ndarray, config: dict | None = None) -> Path:
    """A run bag as import-csv writes it, plus the identifier_config a node records."""
    with BagWriter(path, flush_period=None) as bag:
        for name in (topics.U, topics.Y_P, topics.TEST_START):
            bag.add_topic("/" + name)
        bag.write_value("/" + topics.TEST_START, TRAIN + 1, 0)
        if config is not None:
            bag.add_topic("/" + topics.IDENTIFIER_CONFIG)
            bag.write_value("/" + topics.IDENTIFIER_CONFIG, json.dumps(config), 0)
        for k, (a, b) in enumerate(zip(u, y, strict=True)):
            bag.write_value("/" + topics.U, float(a), k * 10_000_000)
            bag.write_value("/" + topics.Y_P, float(b), k * 10_000_000)
    return path


def reference_nmse(params: str, weights: str, u: np.ndarray, y: np.ndarray) -> float:
    """One-step test NMSE of the params file's model, learning from the fitted weights (the node's start)."""
    resolved, network = resolve(read_params_file(params))
    identifier = build_identifier(resolved, network)
    identifier.free_run_guard = read_params_file(params)["free_run_guard"]  # (fit writes it on: the kept model)
    identifier.model.load_state(weights)
    identifier.mark_healthy()
    return train_and_test(identifier, Series(u, y, TRAIN)).nmse_db


def test_fit_writes_an_absolute_weights_in(fitted) -> None:
    _, _, _, files = fitted
    values = read_params_file(files["params"])
    assert Path(values["weights_in"]).is_absolute()
    assert Path(values["weights_in"]) == Path(files["weights"]).resolve()


def test_evaluate_with_fit_params_starts_from_the_fitted_weights(fitted, tmp_path: Path) -> None:
    u, y, result, files = fitted
    bag = write_bag(tmp_path / "bag", u, y)
    evaluation = evaluate_bag(str(bag), files["params"])
    expected = reference_nmse(files["params"], files["weights"], u, y)
    assert evaluation.evaluation.nmse_db == pytest.approx(expected, abs=1e-9)
    assert evaluation.weights_in == str(Path(files["weights"]).resolve())
    # the figure is fit's model (adapted by RLS over the training part), not a fresh one's
    assert evaluation.evaluation.nmse_db < result.nmse_db + 3.0
    # the fit's free-run band (fit.json beside the weights), and its coverage of this recording's free run
    # by steps since the free run's start, as fit scored its own test part (one run from the test's first sample)
    band = evaluation.intervals["free_run"]
    assert band["by_horizon"] == result.intervals["free_run"]["by_horizon"]
    assert len(band["by_horizon"]["from_step"]) > 1  # (more than one number: the horizon bins are used)
    e = evaluation.evaluation
    widths = fit_free_run_widths(band, e.y_free_test)
    np.testing.assert_array_equal(widths, result.only.free_run_half_width_test)
    assert band["half_width"] == result.intervals["free_run"]["half_width"] == np.median(widths)
    inside = np.abs(e.y_test - e.y_free_test) <= widths
    assert band["coverage_test"] == pytest.approx(inside.mean(), abs=1e-12)
    assert 0.0 < band["coverage_test"] <= 1.0
    # the node's one-step band (y_hat_std as published live) over the test part
    one = evaluation.intervals["one_step"]
    assert 0.93 <= one["coverage_test"] <= 0.97, one
    assert 0.93 <= one["live"]["coverage_test"] <= 0.97, one  # the live band (y_hat_band)


def test_the_fits_free_run_band_widens_along_each_run_and_starts_narrow_again_after_a_gap() -> None:
    """fit.json's band by horizon, read by evaluate: steps since each run's start (a gap restarts the free run from
    measured outputs), and beyond the longest held-out run the growth fit measured between its last two bins."""
    band = {"half_width": 0.2, "by_horizon": {"from_step": [0, 4, 16], "half_width": [0.1, 0.2, 0.4],
                                              "longest_held_out_run": 32, "growth_beyond": 0.5}}  # fmt: skip
    y_free = np.r_[np.zeros(20), np.nan, np.nan, np.zeros(70)]
    widths = fit_free_run_widths(band, y_free)
    np.testing.assert_array_equal(widths[:20], np.repeat([0.1, 0.2, 0.4], [4, 12, 4]))
    assert np.isnan(widths[20:22]).all()
    np.testing.assert_array_equal(widths[22:54], np.repeat([0.1, 0.2, 0.4], [4, 12, 16]))
    np.testing.assert_allclose(widths[-1], 0.4 * (70 / 32) ** 0.5)  # step 69 of the second run
    assert fit_free_run_widths({"half_width": 0.3}, y_free)[0] == 0.3  # a fit of one number (an MLP's, in-sample)
    assert fit_free_run_widths({}, y_free) is None


def test_evaluate_of_a_bag_recorded_with_weights_in_uses_them(fitted, tmp_path: Path) -> None:
    u, y, _, files = fitted
    defaults = {p.name: p.default for p in NODE_PARAMETERS}
    config = {**defaults, **read_params_file(files["params"]), "network": "lenn"}
    config["weights_in"] = str(Path(files["weights"]).resolve())  # as the node records it
    bag = write_bag(tmp_path / "bag", u, y, config)
    evaluation = evaluate_bag(str(bag))  # no --params: the recorded configuration
    expected = reference_nmse(files["params"], files["weights"], u, y)
    assert evaluation.evaluation.nmse_db == pytest.approx(expected, abs=1e-9)
    assert evaluation.weights_in == config["weights_in"]


def test_a_missing_weights_file_stops_naming_the_path(fitted, tmp_path: Path) -> None:
    u, y, _, files = fitted
    document = yaml.safe_load(Path(files["params"]).read_text())
    document["/**"]["ros__parameters"]["weights_in"] = str(tmp_path / "gone.npz")
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(document))
    bag = write_bag(tmp_path / "bag", u, y)
    with pytest.raises(RecordingError, match=r"gone\.npz.*does not exist"):
        evaluate_bag(str(bag), str(params))


def test_a_relative_weights_in_is_taken_from_the_current_directory_as_the_node_does(fitted, tmp_path: Path) -> None:
    u, y, _, files = fitted
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "weights.npz").write_bytes(Path(files["weights"]).read_bytes())
    document = yaml.safe_load(Path(files["params"]).read_text())
    document["/**"]["ros__parameters"]["weights_in"] = "model/weights.npz"
    params = tmp_path / "model" / "params.yaml"
    params.write_text(yaml.safe_dump(document))
    bag = write_bag(tmp_path / "bag", u, y)

    def evaluate(cwd: Path) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "lenn_ros.cli", "evaluate", str(bag), "--params", str(params)],
            capture_output=True, text=True, timeout=300, cwd=cwd, check=False,
            env={**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])},
        )  # fmt: skip

    done = evaluate(tmp_path)
    assert done.returncode == 0, done.stderr
    assert "learning started from the weights in model/weights.npz" in done.stdout
    done = evaluate(params.parent)  # model/model/weights.npz does not exist
    assert done.returncode == 2
    assert "weights_in model/weights.npz" in done.stderr and "current directory" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
