"""One sample numbering for ``fit``: ``--test-from K`` is a sample's number, honoured exactly or refused.

A sample's number is the node's: a bag's sample index (``read_recording``), a CSV's data row from 1
(a row missing a cell is a gap and keeps its number). Samples numbered below K build the model, the
others score it, and the report names samples by number. Checked on real files: a CSV and the bag
``lenn-ros import-csv`` makes of it, a robot's own recording in both rosbag2 storages (MCAP and
sqlite3, read through the one pairing of the service), an ``import-csv`` vector bag whose channels are
picked by label, and a CSV with rows missing a cell.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from robot_bag import PERIOD, U_FLAGS, Y_FLAGS, write_robot_bag
from test_fit import cubic_plant

from lenn_ros.bag.vectors import write_vector_run
from lenn_ros.fit.data import Data, FitError
from lenn_ros.fit.load import load_data
from lenn_ros.fit.numbering import first_test_row, split_line, split_numbers
from lenn_ros.fit.procedure import fit
from lenn_ros.service.recording import read_recording

REPO = Path(__file__).resolve().parents[1]
ROBOT_FLAGS = (*U_FLAGS, *Y_FLAGS, "--sample-period", str(PERIOD))


def lenn_ros(*arguments: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "lenn_ros.cli", *arguments]
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, cwd=REPO, check=False)


def write_csv(path: Path, u: np.ndarray, y: np.ndarray, missing: dict[int, str] | None = None) -> Path:
    """u, y with a header, every value exact (%.17g); ``missing``: 0-based rows written with a cell left out."""
    lines = [f"{a:.17g},{b:.17g}" for a, b in zip(u, y, strict=True)]
    for row, text in (missing or {}).items():
        lines[row] = text
    path.write_text("u,y\n" + "\n".join(lines) + "\n")
    return path


# -- the rule ------------------------------------------------------------------------------------


def test_the_first_test_row_is_the_first_sample_numbered_k_or_above_and_k_outside_is_refused() -> None:
    index = np.r_[np.arange(1, 101), np.arange(104, 201)]  # samples 101..103 missing
    data = Data(np.zeros(index.size), np.zeros(index.size), "x", index=index)
    assert first_test_row(data, 50) == 49 and first_test_row(data, 104) == 100
    assert first_test_row(data, 102) == 100  # in the gap: the first scored sample is 104
    assert split_numbers(data, 100, 102) == {"train": [1, 100], "first_test": 104}
    assert split_line(102, 100, 97, split_numbers(data, 100, 102)) == (
        "built on samples 1..100, tested on 97 samples from 102 (the first is sample 104)"
    )
    assert split_line(150, 146, 51, split_numbers(data, 146, 150)) == (
        "built on 146 samples numbered 1..149, tested on 51 samples from 150"
    )
    plain = Data(np.zeros(200), np.zeros(200), "x")  # rows are numbers: the line as it always was
    assert split_numbers(plain, 120, 121) == {} and split_line(121, 120, 80, {}) == (
        "built on samples 1..120, tested on 80 samples from 121"
    )
    for k in (1, 0, -5, 201, 10**6):
        refused = rf"^--test-from {k} is outside the samples, numbered 1\.\.200: K must be in 2\.\.200 \("
        with pytest.raises(FitError, match=refused + r"samples numbered below K are learnt from, K\.\. scored\)$"):
            first_test_row(plain, k)
    with pytest.raises(FitError, match=r"the recorded test start 500 is outside .*; pass --test-from K$"):
        first_test_row(plain, 500, recorded=True)
    restarted = Data(np.zeros(6), np.zeros(6), "x", index=np.array([1, 2, 3, 1, 2, 3]))
    with pytest.raises(FitError, match=r"the numbering starts again after sample 3"):
        first_test_row(restarted, 3)


# -- a CSV and its import-csv bag ----------------------------------------------------------------


@pytest.mark.slow
def test_a_csv_and_its_import_csv_bag_build_and_score_alike(tmp_path: Path) -> None:
    """100 000 samples: ``fit CSV`` and ``fit BAG`` (the bag ``lenn-ros import-csv`` wrote, a real subprocess) with
    the same ``--test-from`` build on the same samples and score alike. The fits run in-process on both
    ``load_data`` records (two CLI fits of 100 000 samples would take minutes more); the bag is read through
    ``read_recording``, numbered 1..N like the CSV's rows."""
    n, k = 100_000, 80_001
    u, y = cubic_plant(n, 7)
    csv, bag = write_csv(tmp_path / "log.csv", u, y), tmp_path / "log_bag"
    done = lenn_ros("import-csv", str(csv), "--u", "u", "--y", "y", "--dt", "0.01", "-o", str(bag))
    assert done.returncode == 0, done.stderr
    from_csv, from_bag = load_data(csv), load_data(bag)
    assert from_bag.index.tolist() == list(range(1, n + 1)) and from_csv.index is None
    assert np.array_equal(from_bag.u, from_csv.u) and np.array_equal(from_bag.y, from_csv.y)
    by_csv, by_bag = fit(from_csv, k, refine=False), fit(from_bag, k, refine=False)
    assert by_csv.train_samples == by_bag.train_samples == k - 1 and by_csv.samples == by_bag.samples == n - k + 1
    assert by_csv.nmse_free_run_db == pytest.approx(by_bag.nmse_free_run_db, abs=1e-6)
    assert by_csv.nmse_db == pytest.approx(by_bag.nmse_db, abs=1e-6)
    assert by_csv.nmse_free_run_db < -30.0  # (measured -45.4 dB)
    assert by_bag.numbers == {} and by_bag.free_run["starts_from"] == f"measured outputs before sample {k}"


def test_an_import_csv_vector_bag_is_read_whole_and_its_channels_picked_by_label(tmp_path: Path) -> None:
    """A bag of labelled Float64MultiArray u / y_p (``import-csv``'s with several columns) is read by
    ``read_recording`` like any other: every channel, named by its label, paired in order and numbered 1..N.
    ``--u NAME`` / ``--y NAME`` pick channels by label (or index), in the order given, and the params file
    ``fit -o`` writes makes the node read those channels of those messages."""
    rng = np.random.default_rng(0)
    u_rows, y_rows = rng.normal(size=(50, 3)), rng.normal(size=(50, 2))
    bag = write_vector_run(tmp_path / "vectors", u_rows, y_rows, (("a", "b", "c"), ("p", "q")), 0.01, test_from=41)
    read = read_recording(bag)
    assert read.samples.index.tolist() == list(range(1, 51)) and read.samples.by_order
    assert np.array_equal(read.samples.u, u_rows) and np.array_equal(read.samples.y, y_rows)
    assert read.values["u_names"] == ["a", "b", "c"] and read.values["y_names"] == ["p", "q"]
    data = load_data(bag)
    assert data.u_names == ("a", "b", "c") and data.test_start == 41 and data.index.tolist() == list(range(1, 51))
    picked = load_data(bag, ["c", "a"], ["q"])
    assert picked.u_names == ("c", "a") and picked.y_names == ("q",)
    assert np.array_equal(picked.u, u_rows[:, [2, 0]]) and np.array_equal(picked.y, y_rows[:, [1]])
    assert picked.interpretation["u_field"] == "data[2], data[0]" and picked.interpretation["u_names"] == ["c", "a"]
    assert ": u data[2], data[0] (c, a), y_p data[1] (q), paired by order" in picked.source
    assert np.array_equal(load_data(bag, ["1"], ["0"]).u, u_rows[:, 1])  # by 0-based index, as a CSV's columns
    with pytest.raises(FitError, match=r"no u channel or topic 'd'; its channels are a, b, c"):
        load_data(bag, ["d"], ["p"])


@pytest.mark.slow
def test_fit_of_an_import_csv_vector_bag_picks_the_csvs_columns(tmp_path: Path) -> None:
    """``fit BAG --u u2 --y y1`` on the vector bag ``import-csv`` made: the same fit as ``fit CSV`` of those
    columns (real subprocesses), and the bag's recorded test start is the CSV's ``--test-from``."""
    rng = np.random.default_rng(5)
    u, y = cubic_plant(3000, 5)
    other = rng.uniform(-1, 1, u.size)
    csv = tmp_path / "log.csv"
    np.savetxt(csv, np.c_[other, u, y, -y], delimiter=",", header="u1,u2,y1,y2", comments="", fmt="%.17g")
    bag = tmp_path / "bag"
    done = lenn_ros("import-csv", str(csv), "--u", "u1", "--u", "u2", "--y", "y1", "--y", "y2", "--dt", "0.01",
                    "--test-from", "2401", "-o", str(bag))  # fmt: skip
    assert done.returncode == 0, done.stderr
    by_bag = lenn_ros("fit", str(bag), "--u", "u2", "--y", "y1", "--json", "--no-refine")
    by_csv = lenn_ros("fit", str(csv), "--u", "u2", "--y", "y1", "--test-from", "2401", "--json", "--no-refine")
    assert by_bag.returncode == 0 and by_csv.returncode == 0, by_bag.stderr + by_csv.stderr
    bag_report, csv_report = json.loads(by_bag.stdout), json.loads(by_csv.stdout)
    assert bag_report["test_from"] == csv_report["test_from"] == 2401
    assert bag_report["train_samples"] == csv_report["train_samples"] == 2400
    assert bag_report["nmse_free_run_db"] == pytest.approx(csv_report["nmse_free_run_db"], abs=1e-6)
    assert ": u data[1] (u2), y_p data[0] (y1), paired by order" in bag_report["data"]


# -- a robot's own recording, any storage ---------------------------------------------------------


@pytest.fixture(scope="module")
def robot_reports(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, str]]:
    """``fit`` of the same 40 s robot recording written as MCAP and as sqlite3 (its .db3 file given): (bag, report)."""
    found = {}
    for storage in ("mcap", "sqlite3"):
        bag = write_robot_bag(tmp_path_factory.mktemp(storage) / "arm", 40.0, storage, seed=2)
        target = bag if storage == "mcap" else next(bag.glob("*.db3"))
        done = lenn_ros("fit", str(target), *ROBOT_FLAGS, "--test-from", str(ROBOT_K), timeout=600)
        assert done.returncode == 0, done.stderr
        found[storage] = (target, done.stdout)
    return found


ROBOT_K = 15_001


@pytest.mark.slow
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_robot_bag_is_fitted_on_every_sample_numbered_below_k_and_scored_from_k(
    robot_reports: dict[str, tuple[Path, str]], storage: str
) -> None:
    path, text = robot_reports[storage]
    flags = {"u": U_FLAGS[1], "u_field": U_FLAGS[3], "y": Y_FLAGS[1], "y_field": Y_FLAGS[3], "sample_period": PERIOD}
    index = read_recording(path, flags).samples.index  # the same reading, in-process
    below, scored = int(np.count_nonzero(index < ROBOT_K)), int(np.count_nonzero(index >= ROBOT_K))
    first = text.splitlines()[0]
    built = f"samples 1..{ROBOT_K - 1}" if below == ROBOT_K - 1 else f"{below} samples numbered 1..{index[below - 1]}"
    assert first.endswith(f": built on {built}, tested on {scored} samples from {ROBOT_K}"), first
    assert f"free run (from the measured outputs before sample {ROBOT_K}):" in text
    nmse = float(re.search(r"free run \(from .*?\): RMSE \S+, NMSE (-?[\d.]+) dB", text).group(1))
    assert nmse <= -25.0, text


@pytest.mark.slow
def test_both_storages_give_the_same_report(robot_reports: dict[str, tuple[Path, str]]) -> None:
    def plain(entry: tuple[Path, str]) -> str:
        path, text = entry
        return re.sub(r"\n  [\d.]+ s\n", "\n", text.replace(str(path), "BAG"))  # the path and the time taken

    assert plain(robot_reports["mcap"]) == plain(robot_reports["sqlite3"])


# -- refusals and a CSV's own numbers -------------------------------------------------------------


@pytest.mark.parametrize("k", ["1", "0", "1201", "99999"])
def test_a_test_start_outside_the_numbers_is_refused_in_one_line(tmp_path: Path, k: str) -> None:
    csv = write_csv(tmp_path / "log.csv", *cubic_plant(1200, 1))
    done = lenn_ros("fit", str(csv), "--test-from", k)
    assert done.returncode == 2 and done.stdout == "", done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert f"--test-from {k} is outside the samples, numbered 1..1200: K must be in 2..1200" in done.stderr


def test_a_bags_test_start_outside_its_numbers_is_refused_in_one_line(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    u, y = cubic_plant(500, 2)
    assert lenn_ros("import-csv", str(write_csv(tmp_path / "log.csv", u, y)), "--u", "u", "--y", "y", "--dt", "0.01",
                    "-o", str(bag)).returncode == 0  # fmt: skip
    done = lenn_ros("fit", str(bag), "--test-from", "501")
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert "--test-from 501 is outside the samples, numbered 1..500: K must be in 2..500" in done.stderr


def test_a_csv_with_rows_missing_a_cell_is_reported_by_its_row_numbers(tmp_path: Path) -> None:
    """Rows 301 and 1001 (file lines 302, 1002) miss a cell: gaps that keep their numbers. ``--test-from 301``
    falls on the missing row: samples 1..300 build, the first scored is 302, which the report says, and the
    free run is seeded by samples 302.. (after a gap); ``--test-from 801`` names the training count."""
    u, y = cubic_plant(1200, 3)
    csv = write_csv(tmp_path / "log.csv", u, y, {300: f"{u[300]:.17g},", 1000: f"nan,{y[1000]:.17g}"})
    done = lenn_ros("fit", str(csv), "--test-from", "301", "--no-refine")
    assert done.returncode == 0, done.stderr
    first = done.stdout.splitlines()[0]
    assert first.endswith(": built on samples 1..300, tested on 898 samples from 301 (the first is sample 302)")
    window = int(re.search(r"measured outputs of samples 302\.\.(\d+), not scored", done.stdout).group(1)) - 301
    assert window >= 2
    done = lenn_ros("fit", str(csv), "--test-from", "801", "--no-refine", "--json")
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert (report["test_from"], report["train_samples"], report["samples"]) == (801, 799, 399)
    assert report["sample_numbers"] == {"train": [1, 800], "first_test": 801}
    assert report["free_run"]["starts_from"] == "measured outputs before sample 801"
