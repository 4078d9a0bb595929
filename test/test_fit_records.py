"""Several records, one model: ``lenn-ros fit run1.csv run2.csv --test run3.csv``.

Each file is a run of its own: nothing is fitted, simulated or scored across a join (the model of two
records is exactly that of one file with a gap between the runs, and not that of the runs written one
after the other), the scales and blocks come from every build record, a ``--test`` record is scored
whole from its own first samples, and the combinations that name no one split are refused in one line.
Checked on real CSV files of a simulated joint driven by three different excitations, a real bag written
by ``import-csv`` (the package's writer), and the command line in subprocesses.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lenn_ros.bag.csv_import import import_csv
from lenn_ros.fit.data import FitError
from lenn_ros.fit.procedure import fit
from lenn_ros.fit.records import load_records, split_of
from lenn_ros.fit.report import format_report

REPO = Path(__file__).resolve().parents[1]
RUN = 1500


def joint(u: np.ndarray) -> np.ndarray:
    """A joint's response to its command: a damped second-order response through a saturating drive, a
    load term that grows with the state."""
    y = np.zeros(len(u))
    for k in range(1, len(u)):
        before = y[k - 2] if k > 1 else 0.0
        y[k] = 0.6 * y[k - 1] - 0.15 * before + 0.8 * np.tanh(1.5 * u[k - 1]) + 0.1 * u[k - 1] * y[k - 1]
    return y


def excitations(seed: int = 1) -> dict[str, np.ndarray]:
    """Three runs of one joint: held random steps, a modulated sine, smoothed noise."""
    rng = np.random.default_rng(seed)
    k = np.arange(RUN)
    return {
        "steps": np.repeat(rng.uniform(-1.0, 1.0, RUN // 25 + 1), 25)[:RUN],
        "sine": 0.9 * np.sin(2 * np.pi * k / 97) * np.sin(2 * np.pi * k / 433),
        "noise": np.convolve(rng.normal(0.0, 0.6, RUN), np.ones(5) / 5, "same"),
    }


def write_runs(folder: Path, seed: int = 1) -> dict[str, Path]:
    """Each excitation's run as a CSV file (u, y with measurement noise, values exact)."""
    rng = np.random.default_rng(seed + 100)
    paths = {}
    for name, u in excitations(seed).items():
        y = joint(u) + rng.normal(0.0, 0.01, len(u))
        paths[name] = folder / f"{name}.csv"
        write_rows(paths[name], [np.column_stack([u, y])])
    return paths


def write_rows(path: Path, runs: list[np.ndarray], gap: bool = False) -> Path:
    """The runs' rows one after the other, ``gap``: a row missing its cells between them (a gap in one file)."""
    blocks = ["\n".join(f"{a:.17g},{b:.17g}" for a, b in run) for run in runs]
    path.write_text("u,y\n" + ("\n,\n" if gap else "\n").join(blocks) + "\n")
    return path


def rows(path: Path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", skiprows=1)


def fitted(paths: list[Path], tests: list[Path], test_from: int | None = None, refine: bool = True):
    data = load_records(paths, tests)
    start, recorded = split_of(data, test_from)
    return data, fit(data, start, refine=refine, recorded=recorded)


def lenn_ros(*arguments: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "lenn_ros.cli", *arguments]
    return subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=REPO, check=False)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return write_runs(tmp_path_factory.mktemp("runs"))


def test_a_model_of_two_runs_simulates_a_third_as_well_as_the_better_single_run_model(
    runs: dict[str, Path], tmp_path: Path
) -> None:
    """The command line (a subprocess) fits the steps' and the sine's runs, scores the noise run given with
    ``--test`` and writes one model; the report names both build runs and their samples. Its free run of the third
    run is within 0.5 dB of the better model of one run (measured: -29.96 dB against -29.47 and -13.22 dB)."""
    out = tmp_path / "model"
    done = lenn_ros("fit", str(runs["steps"]), str(runs["sine"]), "--test", str(runs["noise"]), "-o", str(out))
    assert done.returncode == 0, done.stderr
    assert f"build {runs['steps']}: {RUN} samples, numbered 1..{RUN}" in done.stdout
    assert f"build {runs['sine']}: {RUN} samples, numbered {RUN + 1}..{2 * RUN} (its own 1..{RUN})" in done.stdout
    assert f"test  {runs['noise']}: {RUN} samples" in done.stdout
    report = json.loads((out / "fit.json").read_text())
    assert [(r["role"], r["samples"]) for r in report["records"]] == [("build", RUN), ("build", RUN), ("test", RUN)]
    assert report["train_samples"] == 2 * RUN and report["samples"] == RUN
    assert (out / "params.yaml").is_file() and (out / "weights.npz").is_file()
    singles = [fitted([runs[name]], [runs["noise"]])[1].nmse_free_run_db for name in ("steps", "sine")]
    assert report["nmse_free_run_db"] <= min(singles) + 0.5, (report["nmse_free_run_db"], singles)
    # scored on the third run as a record of its own: its free run seeded by its own first samples
    assert report["free_run"]["starts_from"].startswith(f"measured outputs of samples {2 * RUN + 1}..")


def test_nothing_is_fitted_across_the_join(runs: dict[str, Path], tmp_path: Path) -> None:
    """Two records give the model and figures of one file holding the runs with a gap between them (the gap rule,
    not a second one), and not those of the runs written one after the other, where rows read across the join."""
    steps, sine, noise = (rows(runs[name]) for name in ("steps", "sine", "noise"))
    _, records = fitted([runs["steps"], runs["sine"]], [runs["noise"]], refine=False)
    gapped = write_rows(tmp_path / "gapped.csv", [steps, sine, noise], gap=True)
    _, one_file = fitted([gapped], [], test_from=2 * RUN + 3, refine=False)
    joined = write_rows(tmp_path / "joined.csv", [steps, sine])
    _, across = fitted([joined], [runs["noise"]], refine=False)
    weights = [result.fits[0].chosen.model.weights for result in (records, one_file, across)]
    assert records.model["expansion"]["terms"] == one_file.model["expansion"]["terms"]
    assert np.array_equal(weights[0], weights[1])
    assert records.nmse_free_run_db == one_file.nmse_free_run_db and records.nmse_db == one_file.nmse_db
    assert len(weights[2]) != len(weights[0]) or not np.allclose(weights[2], weights[0], rtol=1e-6, atol=0)
    assert records.choices["gaps"] == 1 and across.choices["gaps"] == 0


def test_a_bag_joins_csv_records_as_the_same_samples(runs: dict[str, Path], tmp_path: Path) -> None:
    """A bag written by ``import-csv`` (the package's writer) as one of the build records builds the model the CSV
    file does; several test records are each scored from their own start, and overall."""
    bag = import_csv(runs["steps"], "u", "y", 0.01, tmp_path / "steps_bag")
    _, by_bag = fitted([bag, runs["sine"]], [runs["noise"], runs["steps"]], refine=False)
    _, by_csv = fitted([runs["steps"], runs["sine"]], [runs["noise"], runs["steps"]], refine=False)
    assert np.array_equal(by_bag.fits[0].chosen.model.weights, by_csv.fits[0].chosen.model.weights)
    assert by_bag.nmse_free_run_db == pytest.approx(by_csv.nmse_free_run_db, abs=1e-9)
    tested = [r for r in by_bag.records if r["role"] == "test"]
    assert [r["samples"] for r in tested] == [RUN, RUN] and by_bag.samples == 2 * RUN
    scores = [r["scores"]["y"]["nmse_free_run_db"] for r in tested]
    _, alone = fitted([bag, runs["sine"]], [runs["noise"]], refine=False)
    assert scores[0] == pytest.approx(alone.nmse_free_run_db, abs=1e-9)  # each record scored as if alone
    assert scores[1] < scores[0]  # a build run scores better than an unseen one
    assert "one-step NMSE" in format_report(by_bag).split("scaling")[0]


@pytest.mark.parametrize(
    ("extra", "said"),
    [
        ([], "2 records to build on and none to score: pass --test FILE"),
        (["--test-from", "200"], "--test-from 200 with 2 records to build on: each numbers its samples"),
        (["--test-from", "200", "--test", "NOISE"], "--test-from 200 and --test: the test part is the records"),
    ],
)
def test_a_split_that_names_no_one_sample_is_refused_in_one_line(
    runs: dict[str, Path], extra: list[str], said: str
) -> None:
    extra = [str(runs["noise"]) if arg == "NOISE" else arg for arg in extra]
    done = lenn_ros("fit", str(runs["steps"]), str(runs["sine"]), *extra)
    assert done.returncode != 0 and done.stdout == ""
    assert len(done.stderr.strip().splitlines()) == 1 and said in done.stderr, done.stderr


def test_records_of_other_channels_are_refused(runs: dict[str, Path], tmp_path: Path) -> None:
    other = tmp_path / "other.csv"
    other.write_text("u,z\n" + "\n".join(f"{k},{k}" for k in range(300)) + "\n")
    with pytest.raises(FitError, match="every record must hold the same channels"):
        load_records([runs["steps"]], [other], "u", None)


def test_evaluate_scores_several_bags_each_as_a_record_of_its_own(runs: dict[str, Path], tmp_path: Path) -> None:
    """``evaluate A B`` (a subprocess; bags written by ``import-csv``) learns one model through both build parts
    (the last fifth of each is its test part) and scores each bag's test part and both together; the same bag
    twice scores the same twice, whatever came before it in the joined pass (nothing carried across a join)."""
    bags = [str(import_csv(runs[name], "u", "y", 0.01, tmp_path / name)) for name in ("steps", "sine")]
    made = lenn_ros("fit", str(runs["steps"]), "--test", str(runs["noise"]), "--no-refine", "-o", str(tmp_path / "m"))
    assert made.returncode == 0, made.stderr
    params = ("--params", str(tmp_path / "m" / "params.yaml"))
    done = lenn_ros("evaluate", *bags, *params, "--json")
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert [r["test_start"] for r in report["records"]] == [int(0.8 * RUN) + 1] * 2
    assert [r["trained"] for r in report["records"]] == [int(0.8 * RUN)] * 2
    tested = [r["channels"]["y"]["samples"] for r in report["records"]]
    assert all(np.isfinite(r["channels"]["y"]["nmse_free_run_db"]) for r in report["records"])
    assert sum(tested) > 0.19 * 2 * RUN
    twice = json.loads(lenn_ros("evaluate", bags[0], bags[0], *params, "--json").stdout)["records"]
    assert twice[0]["channels"] == twice[1]["channels"]
    refused = lenn_ros("evaluate", *bags, *params, "--test-from", "200")
    assert refused.returncode != 0 and len(refused.stderr.strip().splitlines()) == 1
    assert "--test-from 200 with 2 bags" in refused.stderr
