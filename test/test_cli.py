"""The command line as a user runs it: real subprocesses, shipped configs and bags."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from lenn_ros.config import resolve
from lenn_ros.paper.examples import EXAMPLES
from lenn_ros.service.params import read_params_file

REPO = Path(__file__).resolve().parents[1]


def lenn_ros(*arguments: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", *arguments], capture_output=True, text=True, timeout=timeout, cwd=REPO
    )


@pytest.mark.parametrize("path", sorted((REPO / "config").glob("example*_*.yaml")), ids=lambda p: p.stem)
def test_shipped_params_files_match_the_examples(path: Path) -> None:
    values = read_params_file(path)
    resolved, network = resolve(values)
    example = EXAMPLES[values["example"]]
    preset = example.network_params(network)
    assert resolved["alpha"] == preset["alpha"] and resolved["beta"] == preset["beta"]
    assert resolved["y_scale"] == example.structure.y_scale
    assert read_params_file(path, "plant_simulator")["noise_db"] == example.noise_db


@pytest.mark.parametrize("number", [1, 2, 3, 4])
def test_shipped_bags_evaluate_with_their_params(number: int) -> None:
    result = lenn_ros("evaluate", f"bags/example{number}", "--params", f"config/example{number}_lenn.yaml", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["samples"] == 600 and report["pairs"] == 3600
    assert report["nmse_db"] < -5.0 and report["rmse"] > 0.0
    assert set(report) >= {"nmse_db", "nmse_free_run_db", "rmse", "rmse_free_run", "samples"}


def test_reproduce_json_has_the_promised_keys() -> None:
    result = lenn_ros("reproduce", "--example", "4", "--seeds", "2", "--iterations", "3000", "--json")
    assert result.returncode == 0, result.stderr
    rows = json.loads(result.stdout)
    assert [(r["example"], r["network"]) for r in rows] == [(4, "lenn"), (4, "mlp")]
    for row in rows:
        assert {
            "example",
            "network",
            "seeds",
            "nmse_db_mean",
            "nmse_db_std",
            "nmse_free_run_db_mean",
            "paper_nmse_db",
        } <= set(row)
        assert row["seeds"] == [0, 1] and row["nmse_db_mean"] < 0


def test_reproduce_plots(tmp_path: Path) -> None:
    result = lenn_ros(
        "reproduce",
        "--example",
        "1",
        "--network",
        "lenn",
        "--seeds",
        "1",
        "--iterations",
        "2000",
        "--plots",
        str(tmp_path),
    )
    assert result.returncode == 0, result.stderr
    png = tmp_path / "example1_lenn.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["evaluate", "/nonexistent/bag"], "no such file or directory"),
        (["evaluate", "bags/example1", "--params", "/nonexistent.yaml"], "does not exist"),
        (["evaluate", "bags/example1", "--test-from", "999999"], "K must be in 2..3600"),
        (["import-csv", "/nonexistent.csv", "--u", "u", "--y", "y", "--dt", "0.01", "-o", "/tmp/x"], "nonexistent"),
    ],
)
def test_user_errors_are_one_line(arguments: list[str], message: str) -> None:
    result = lenn_ros(*arguments)
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_import_csv_then_evaluate(tmp_path: Path) -> None:
    from lenn_ros.paper.evaluation import simulate

    series = simulate(EXAMPLES[4].plant(), -20.0, seed=2, train_samples=3000, test_samples=600)
    csv = tmp_path / "log.csv"
    csv.write_text(
        "time,command,position\n"
        + "".join(
            f"{k * 0.01:.2f},{float(u)!r},{float(y)!r}\n"
            for k, (u, y) in enumerate(zip(series.u, series.y, strict=True))
        )
    )
    bag = tmp_path / "bag"
    result = lenn_ros(
        "import-csv",
        str(csv),
        "--u",
        "command",
        "--y",
        "position",
        "--dt",
        "0.01",
        "-o",
        str(bag),
        "--test-from",
        "3001",
    )
    assert result.returncode == 0, result.stderr
    params = REPO / "config" / "example4_lenn.yaml"
    result = lenn_ros("evaluate", str(bag), "--params", str(params), "--json")
    assert result.returncode == 0, result.stderr
    from lenn_ros.paper.evaluation import train_and_test
    from lenn_ros.service.building import identifier_from_params

    expected = train_and_test(identifier_from_params(str(params))[0], series)
    assert json.loads(result.stdout)["nmse_db"] == pytest.approx(expected.nmse_db, abs=1e-9)


def test_a_bug_shows_a_traceback_not_a_user_error() -> None:
    """A ValueError / RuntimeError from a defect is not the user's: it must not become a one-line error."""
    for bug in ("ValueError('a defect')", "RuntimeError('a defect')"):
        code = (
            "import sys\n"
            "from lenn_ros import cli, evaluate\n"
            "def broken(args):\n"
            f"    raise {bug}\n"
            "evaluate.main = broken\n"
            "sys.exit(cli.main(['evaluate', 'bags/example1']))\n"
        )
        result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
        assert result.returncode == 1, result.stderr
        assert "Traceback" in result.stderr and "in broken" in result.stderr


def test_params_file_errors_are_still_one_line(tmp_path: Path) -> None:
    """Config problems are ConfigError (the user's): unknown name, bad term list."""
    for body, message in [
        ("identifier:\n  ros__parameters:\n    alhpa: 0.1\n", "unknown parameter 'alhpa'"),
        ("identifier:\n  ros__parameters:\n    terms: ['y(k-9)^2']\n", "y(k-9)"),
    ]:
        params = tmp_path / "bad.yaml"
        params.write_text(body)
        result = lenn_ros("evaluate", "bags/example1", "--params", str(params))
        assert result.returncode == 2, result.stderr
        assert message in result.stderr and "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1


def test_evaluate_warns_in_text_and_json_about_clipping_and_divergence(tmp_path: Path) -> None:
    """A plant around 50 units under the paper's Example-2 scaling (y_scale 3): clipped inputs, diverged learning."""
    import numpy as np

    rng = np.random.default_rng(0)
    u = rng.uniform(0.0, 1.0, 3000)
    y = 50.0 + 5.0 * np.sin(np.arange(3000) / 20.0) + np.convolve(u, [0.0, 1.0, 0.5])[:3000]
    csv = tmp_path / "log.csv"
    csv.write_text("u,y\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(u, y, strict=True)))
    bag = tmp_path / "bag"
    done = lenn_ros("import-csv", str(csv), "--u", "u", "--y", "y", "--dt", "1", "-o", str(bag), "--test-from", "2001")
    assert done.returncode == 0, done.stderr
    text = lenn_ros("evaluate", str(bag), "--params", "config/example2_lenn.yaml")
    assert text.returncode == 0, text.stderr
    warnings = [line.strip() for line in text.stdout.splitlines() if line.strip().startswith("WARNING:")]
    one_step = [w for w in warnings if "one-step network inputs" in w and "clipped" in w]
    assert one_step and "y_scale/u_scale" in one_step[0] and "lenn-ros fit" in one_step[0]
    assert any(w.startswith("WARNING: learning diverged (") and "lenn-ros fit" in w for w in warnings)
    assert any("free-run network inputs" in w or "free run" in w for w in warnings)
    report = json.loads(lenn_ros("evaluate", str(bag), "--params", "config/example2_lenn.yaml", "--json").stdout)
    assert [f"WARNING: {w}" for w in report["warnings"]] == warnings
    assert str(report["counters"]["clipped_inputs"]) in one_step[0]


def test_evaluate_help_says_what_test_from_and_weights_in_mean() -> None:
    text = " ".join(lenn_ros("evaluate", "-h").stdout.split())
    assert "1-based index of the first test sample" in text
    assert "weights_in" in text and "current directory" in text


def test_bench_runs_the_source_tree_benchmarks() -> None:
    """`lenn-ros bench NAME ARGS` is the script of bench/ with ARGS; every listed script exists."""
    from lenn_ros.cli import BENCHMARKS

    assert all((REPO / "bench" / script).is_file() for script, _ in BENCHMARKS.values())
    result = lenn_ros("bench", "reproduce", "-h")
    assert result.returncode == 0 and "usage: reproduce_marginal.py" in result.stdout, result.stderr
    unknown = lenn_ros("bench", "nonsense")
    assert unknown.returncode == 2 and "invalid choice: 'nonsense'" in unknown.stderr


def test_evaluate_says_a_stalled_driver_is_a_stall_with_its_length(tmp_path: Path) -> None:
    """u and y_p at 100 Hz from two nodes, paired on a grid; the driver publishes nothing for 0.5 s.

    Before: "50 sample indices are missing from the recording (lost before recording or
    dropped)"; nothing was lost and nothing is missing from the recording: no y_p was published.
    """
    import numpy as np

    from lenn_ros import topics
    from lenn_ros.bag.writer import BagWriter

    bag_path = tmp_path / "stall"
    with BagWriter(bag_path, flush_period=None) as bag:
        for name in (topics.U, topics.Y_P, topics.TEST_START, topics.IDENTIFIER_CONFIG):
            bag.add_topic("/" + name)
        bag.write_value("/" + topics.TEST_START, 2001, 0)
        config = {"pairing": "sample", "sample_period": 0.01, "use_header_stamp": False}
        bag.write_value("/" + topics.IDENTIFIER_CONFIG, json.dumps(config), 0)
        u = np.sin(0.05 * np.arange(3000))
        for k in range(3000):
            time_ns = 5_000_000_000 + k * 10_000_000
            bag.write_value("/" + topics.U, float(u[k]), time_ns + 1_000_000, sequence=k + 1)
            if not 1000 <= k < 1050:  # the stall: the driver publishes nothing, no sequence number is skipped
                bag.write_value("/" + topics.Y_P, 0.5 * float(u[k - 1]), time_ns + 3_000_000, sequence=k + 1)
    result = lenn_ros("evaluate", str(bag_path))
    assert result.returncode == 0, result.stderr
    assert "missing from the recording" not in result.stdout and "lost before recording" not in result.stdout
    line = next((line for line in result.stdout.splitlines() if "sample indices missing" in line), "")
    assert "50 sample indices missing in 1 gap, the longest 50 samples, 0.510 s without a sample" in line, result.stdout
    assert "a stall, not a loss" in line
