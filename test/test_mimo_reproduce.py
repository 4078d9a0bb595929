"""``lenn-ros reproduce-mimo``: the MIMO LeNN against one SISO LeNN per output, over seeds."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lenn_ros.core.scaling import DEFAULT_MARGIN
from lenn_ros.paper.evaluation import simulate_mimo
from lenn_ros.paper.experiments import mimo
from lenn_ros.paper.plants import narendra_mimo_plant

REPO = Path(__file__).resolve().parents[1]


def lenn_ros(*arguments: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", *arguments], capture_output=True, text=True, timeout=timeout, cwd=REPO
    )


@pytest.fixture(scope="module")
def small() -> mimo.Result:
    """Three seeds, few samples: the LeNNs (RLS) have settled, the comparison is already clear."""
    return mimo.run(3, train_samples=3000, test_samples=600, models=mimo.MODELS[:2])


def _means(result: mimo.Result) -> dict[tuple[str, str], tuple[float, float]]:
    cells = {}
    for row in result.rows:
        d = row.as_dict()
        cells[(row.channel, row.model.key)] = (d["nmse_db_mean"], d["nmse_free_run_db_mean"])
    return cells


def test_mimo_lenn_beats_one_siso_lenn_per_output_on_both_outputs(small: mimo.Result) -> None:
    means = _means(small)
    for channel in ("y0", "y1"):
        mimo_one, mimo_free = means[(channel, "mimo_lenn")]
        siso_one, siso_free = means[(channel, "siso_lenn")]
        assert mimo_one < siso_one - 8.0, channel  # measured: 13.1 dB (y0), 11.4 dB (y1)
        assert mimo_free < siso_free - 6.0, channel  # measured: 10.6 dB (y0), 9.9 dB (y1)
        assert mimo_one < -20.0 and mimo_free < -18.0, channel
    assert not any(any(row.free_run_diverged) for row in small.rows)
    assert all(row.seeds == [0, 1, 2] for row in small.rows)


def test_rows_come_per_output_in_model_order_with_the_right_network_sizes(small: mimo.Result) -> None:
    assert [(row.channel, row.model.key) for row in small.rows] == [
        ("y0", "mimo_lenn"),
        ("y0", "siso_lenn"),
        ("y1", "mimo_lenn"),
        ("y1", "siso_lenn"),
    ]
    # bias + 4 per input + the cross terms of total degree <= 3: 2 inputs (own y, own u) give 1 + 8 + 3,
    # 4 inputs (every output and input) 1 + 16 + 6 + 16: the MIMO model is bigger, not only better coupled
    weights = {row.model.key: row.weights for row in small.rows}
    assert weights == {"siso_lenn": 12, "mimo_lenn": 39}


def test_scaling_comes_from_the_training_part_only() -> None:
    series = simulate_mimo(narendra_mimo_plant(), -20.0, seed=0, train_samples=2000, test_samples=600)
    scales = mimo.channel_scaling(series)
    changed = simulate_mimo(narendra_mimo_plant(), -20.0, seed=0, train_samples=2000, test_samples=600)
    changed.y[series.test_start :] *= 10.0  # a test part far outside the training range
    assert mimo.channel_scaling(changed) == scales
    for j in range(2):
        scaled = (series.y[: series.test_start, j] - scales["y_offset"][j]) / scales["y_scale"][j]
        assert np.abs(scaled).max() == pytest.approx(1.0 / (1.0 + DEFAULT_MARGIN))
        scaled_u = (series.u[: series.test_start, j] - scales["u_offset"][j]) / scales["u_scale"][j]
        assert np.abs(scaled_u).max() == pytest.approx(1.0 / (1.0 + DEFAULT_MARGIN))


def test_a_diverged_seed_makes_the_cell_diverged_not_an_average() -> None:
    row = mimo.Row("y0", mimo.MODELS[2], 321, [0, 1], [-12.0, -13.0], [float("nan"), -11.0], [True, False])
    table = mimo.format_table([row])
    assert "diverged" in table and "-12.50 ± 0.71" in table
    assert row.as_dict()["nmse_free_run_db_mean"] is None


def test_figure_has_one_panel_per_output_and_leaves_pyplot_alone(small: mimo.Result) -> None:
    import matplotlib

    backend = matplotlib.get_backend()
    figure = mimo.figure(small.last, small.last_seed)
    axes = figure.get_axes()
    assert len(axes) == 2
    for axis in axes:
        assert len(axis.get_lines()) == 4  # plant, MIMO one-step, MIMO free run, SISO free run
        assert len(axis.get_lines()[0].get_ydata()) == 600
    assert matplotlib.get_backend() == backend
    assert "matplotlib.pyplot" not in sys.modules or not sys.modules["matplotlib.pyplot"].get_fignums()


def test_cli_prints_a_table_and_writes_the_figure(tmp_path: Path) -> None:
    result = lenn_ros("reproduce-mimo", "--seeds", "2", "--train-samples", "2000", "--plot", str(tmp_path))
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stdout.splitlines() if line.startswith("| y")]
    assert len(lines) == 6  # 2 outputs x (MIMO LeNN, SISO LeNN, MLP)
    assert all(line.rstrip().endswith("| 0–1 |") and " ± " in line for line in lines)
    png = tmp_path / "mimo_narendra2x2.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_json_has_the_per_channel_fields() -> None:
    result = lenn_ros("reproduce-mimo", "--seeds", "2", "--train-samples", "1500", "--noise-db", "-30", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["seeds"] == [0, 1] and report["train_samples"] == 1500 and report["noise_db"] == -30.0
    rows = report["rows"]
    assert {(row["channel"], row["model"]) for row in rows} == {
        (channel, model) for channel in ("y0", "y1") for model in ("mimo_lenn", "siso_lenn", "mimo_mlp")
    }
    for row in rows:
        assert {
            "nmse_db",
            "nmse_db_mean",
            "nmse_db_std",
            "nmse_free_run_db",
            "nmse_free_run_db_mean",
            "nmse_free_run_db_std",
            "couplings",
            "weights",
        } <= set(row)
        assert len(row["nmse_db"]) == 2 and row["nmse_db_mean"] < 0
