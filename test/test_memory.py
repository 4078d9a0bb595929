"""A training part longer than the machine's memory holds: ``fit`` builds on its latest rows and says so."""

from __future__ import annotations

import numpy as np
import pytest
from test_rest import cubic

from lenn_ros.fit import memory
from lenn_ros.fit.data import Data
from lenn_ros.fit.memory import LEAST_ROWS, MEMORY_SHARE, bytes_per_row, within_memory
from lenn_ros.fit.procedure import fit
from lenn_ros.fit.report import format_report


def record(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The cubic plant of test_fit driven by smoothed noise, with sensor noise."""
    rng = np.random.default_rng(seed)
    u = np.convolve(rng.uniform(-1, 1, n), np.ones(3) / 3, "same")
    return u, cubic(u) + 0.002 * rng.standard_normal(n)


def room_for(rows: int, n_columns: int = 2) -> int:
    """The bytes available at which ``rows`` training rows of a view of ``n_columns`` fit on this machine's cores."""
    return int(rows * bytes_per_row(n_columns, memory.cores()) / MEMORY_SHARE) + 1


def test_the_latest_training_rows_that_fit_are_kept_and_the_test_part_is_left_whole() -> None:
    u, y = record(60_000)
    data = Data(u, y, "long log")
    same, test_from, info = within_memory(data, 50_001, available=room_for(50_000))
    assert same is data and test_from == 50_001 and info == {}  # it fits: nothing is done
    kept, test_from, info = within_memory(data, 50_001, available=room_for(30_000))
    assert (test_from, info["train_samples_used"], info["samples_left_out"]) == (30_001, 30_000, 20_000)
    assert np.array_equal(kept.y, y[20_000:]) and np.array_equal(kept.index, np.arange(20_001, 60_001))
    assert "built on the last 30000 (samples 20001..50000); the 20000 before them are left out" in info["text"]
    # however little memory there is, LEAST_ROWS are kept: a short record is never cut below them
    assert within_memory(data, 50_001, available=1)[1] == LEAST_ROWS + 1
    # rows already left out (a rest cut, a gap) are named by the user's sample numbers
    later = data.kept(np.arange(len(y)) >= 5_000)
    info = within_memory(later, 45_001, available=room_for(30_000))[2]
    assert "(samples 20001..50000); the 15000 before them are left out" in info["text"]


def test_fit_on_a_log_longer_than_memory_builds_on_its_latest_part_and_says_so(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The machine's memory is set low: fit keeps the last training rows that fit, names them, and counts the test
    part as the user does; the model is as good as one fitted to those rows alone."""
    u, y = record(36_000)
    monkeypatch.setattr(memory, "available_memory", lambda: room_for(LEAST_ROWS))
    report = fit(Data(u, y, "long log"), 30_001, refine=False)
    assert (report.test_from, report.train_samples) == (30_001, 30_000)
    memory_note = report.left_out["memory"]
    assert memory_note["train_samples_used"] == LEAST_ROWS and memory_note["samples_left_out"] == 10_000
    assert f"note: {memory_note['text']}" in format_report(report)
    assert report.free_run["starts_from"] == "measured outputs before sample 30001"
    monkeypatch.undo()
    alone = fit(Data(u[10_000:], y[10_000:], "the latest part alone"), 20_001, refine=False)
    assert report.rmse_free_run == pytest.approx(alone.rmse_free_run, rel=1e-9)
    assert report.nmse_free_run_db < -40.0
