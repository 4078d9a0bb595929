"""bench/speed.py: compiled kernels equal their pure-Python versions; the quick offline run works."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import speed as bench
import speed_offline as offline

from lenn_ros.core import jit

#: The kernels the package ships, each with the network configuration that drives it.
REQUIRED = ("lenn_sgd", "lenn_nlms", "lenn_rls", "mlp")
BRANCHED = ("lenn_sgd_two_branches", "mlp_two_branches")


@pytest.fixture(scope="module")
def equality() -> dict[str, dict[str, float]]:
    if not jit.COMPILED:
        pytest.skip("numba is not installed: the kernels run as Python, nothing to compare")
    return offline.kernel_equality(2000)


@pytest.mark.parametrize("name", REQUIRED + BRANCHED)
def test_compiled_kernel_equals_py_func(equality: dict[str, dict[str, float]], name: str) -> None:
    """2000 learning updates from the same state: weights, optimiser state and outputs agree to 1e-12."""
    result = equality[name]
    assert result["samples"] == 2000
    assert result["max_abs_state_difference"] <= 1e-12
    assert result["max_abs_output_difference"] <= 1e-12


def test_equality_check_would_see_a_difference() -> None:
    """The comparison is not vacuous: a different start state shows up in the difference."""
    name, network, x, d = offline.equality_cases(200)[0]
    twin = network.__class__(**network.get_params())
    twin._initialise()
    twin.weights_ = twin.weights_ + 1e-6
    inputs = offline.kernel_inputs(network, x)
    y_a = offline.run_kernel(network, inputs, d)
    y_b = offline.run_kernel(twin, inputs, d, python=True)
    assert name == "lenn_sgd"
    assert np.max(np.abs(y_a - y_b)) > 1e-12


def test_numpy_reference_loop_is_the_kernels_rule() -> None:
    """The plain-numpy baseline of the benchmark learns exactly what the compiled kernel learns."""
    example = offline.EXAMPLES[1]
    x, d = offline.training_pairs(example, 500)
    network = offline.fresh_network(example, "lenn", x, d)
    start = network.weights_.copy()
    w_numpy, y_numpy = offline.numpy_reference_loop(network.features(x), d, start, network.alpha, network.beta)
    y_kernel = network.update(x, d)
    assert np.max(np.abs(network.weights_ - w_numpy)) < 1e-12
    assert np.max(np.abs(y_kernel - y_numpy)) < 1e-12


def test_quick_offline_bench_runs_and_reports_every_figure() -> None:
    """`python bench/speed.py --quick --skip-online` end to end (smaller sizes still, to stay fast)."""
    sizes = dataclasses.replace(
        offline.QUICK,
        repeats=3,  # medians of 3 interleaved runs: one timing hit by a load spike does not decide a ratio
        fit_samples=1000,
        single_calls=20,
        train_samples=5000,
        numpy_samples=300,
        run_samples=5000,
        bag_samples=1000,
        equality_samples=50,
    )
    report = bench.run(quick=True, skip_online=True, sizes=sizes)
    assert {
        "cost_per_update",
        "offline_throughput",
        "kernel_equality",
        "online",
        "targets",
        "machine_at_start",
        "offline_clock",
    } <= set(report)
    assert [row["example"] for row in report["cost_per_update"]] == [1, 2, 3, 4]
    # Timings are the benchmark's figures (its table in bench/RESULTS.md), not asserted here: ratios of
    # timings taken beside other work on a 2-core machine failed twice (the MLP's batch gain 3.2x against a 4x
    # bound, measured 7.9-8.2x when quiet). What must hold is that every figure was measured.
    timings = ("partial_fit_us", "single_call_us", "kernel_us", "predict_us")
    for row in report["cost_per_update"]:
        for kind in ("lenn", "mlp"):
            costs = row[kind]
            assert costs["multiplications"] == offline.EXAMPLES[row["example"]].complexity(kind).multiplications
            assert all(math.isfinite(costs[name]) and costs[name] > 0 for name in timings), (kind, costs)
        assert math.isfinite(row["lenn"]["live_step_us"]) and row["lenn"]["live_step_us"] > 0, row["lenn"]
        assert row["table1_mult_ratio"] > 1 and row["explanation"]
    throughput = report["offline_throughput"]
    assert set(throughput) == {"lenn_ex1", "mlp_ex1", "identifier_run_ex4", "evaluate_bag"}
    assert math.isfinite(throughput["lenn_ex1"]["speedup_vs_numpy"])  # 16.7-20.6 at these sizes, 22.5 at full
    assert throughput["identifier_run_ex4"]["samples"] == 5000
    assert throughput["evaluate_bag"].get("samples") == 1000 or "skipped" in throughput["evaluate_bag"]
    assert set(report["kernel_equality"]) == set(REQUIRED + BRANCHED)
    assert report["online"] == {"skipped": "--skip-online"}
    assert len(report["targets"]) == 5 and report["targets"][-1]["met"] is None
    # both outputs render; the JSON is strict (no NaN)
    assert "### Targets" in bench.markdown(report)
    json.loads(json.dumps(bench._finite_only(report), allow_nan=False))


def test_fleet_bench_judges_loss_and_backlog() -> None:
    """A trial passes only with every plant's samples paired and learnt from, none lost, and no plant behind."""
    import fleet

    plants = ["p0", "p1"]

    def statuses(paired: int, lost: int = 0, unlearnt: int = 0) -> dict[str, dict]:
        learned = paired - fleet.EXAMPLES[1].structure.warm_up - unlearnt
        counters = {"paired": paired, "learned": learned, "lost": lost, "stale": 0, "samples": paired}
        return {plant: {"counters": dict(counters)} for plant in plants}

    cases = {
        "clean": (statuses(500), 0, True),
        "lost": (statuses(498, lost=2), 0, False),
        "paired, not learnt from": (statuses(500, unlearnt=3), 0, False),
        "behind": (statuses(500), 7, False),
        "silent plant": ({"p0": statuses(500)["p0"]}, 0, False),
    }
    for name, (given, lag, passed) in cases.items():
        trial = fleet.Trial("fleet", len(plants), sent=500, worst_lag_samples=lag, rate_hz=fleet.RATE_HZ)
        fleet.judge(trial, given, plants)
        assert trial.passed == passed and (passed or trial.reason), name
    slow = fleet.Trial("fleet", len(plants), sent=500, rate_hz=0.9 * fleet.RATE_HZ)
    fleet.judge(slow, statuses(500), plants)
    assert not slow.passed and "the driver reached 90 Hz" in slow.reason


@pytest.mark.ros
@pytest.mark.timeout(120)
@pytest.mark.parametrize(("setup", "processes"), [("fleet", 1), ("workers", 4)])
def test_fleet_bench_runs_a_real_trial(domain: int, setup: str, processes: int) -> None:
    """Two plants in one fleet process (or over two workers) for 2 s at 100 Hz, through DDS: all of it paired;
    the workers' CPU and memory counted with the launcher's (and multiprocessing's resource tracker)."""
    pytest.importorskip("rclpy")
    import os

    import fleet

    if setup == "workers" and len(os.sched_getaffinity(0)) < 2:
        pytest.skip("workers:=auto is one worker on one core")
    trial = fleet.run_trial(setup, 2, 2.0, domain)
    assert trial.passed, trial
    assert trial.sent == int((fleet.WARM_UP + 2.0) * fleet.RATE_HZ) and trial.counters["paired"] == 2 * trial.sent
    assert trial.cpu_us_per_sample > 0 and trial.rss_mb > 50 * processes and trial.processes == processes
    assert trial.driver_cpu_percent > 0


def test_bag_read_bench_reads_the_same_messages_with_every_reader(tmp_path) -> None:
    """bench/bag_read.py, small and in this process: every reader counts every message of each bag it can read
    (mcap's readers none of sqlite3's), read_recording pairs them, and the table and JSON render."""
    import bag_read

    report = bag_read.run(samples=300, seconds=2.0, isolate=False, directory=tmp_path)
    rows = report["rows"]
    assert len(rows) == 3 * len(bag_read.READERS)
    expected = {"scalar": 600, "robot mcap": 1200, "robot sqlite3": 1200}  # 2 s: 1000 JointState + 200 commands
    for row in rows:
        if row["bag"] == "robot sqlite3" and row["reader"].startswith("mcap"):
            assert row["messages"] is None
            continue
        assert row["messages"] == expected[row["bag"]], row
        assert row["seconds"] >= 0 and row["messages_per_s"] > 0
    paired = {row["bag"]: row["pairs"] for row in rows if row["reader"].startswith("lenn_ros read_recording")}
    assert paired["scalar"] == 300 and paired["robot mcap"] == paired["robot sqlite3"] > 990
    table = bag_read.markdown(report)
    assert table.count("\n") == len(rows) + 1 and "| robot sqlite3 | mcap make_reader (raw) | - |" in table
    json.loads(json.dumps(report, default=str))


def test_long_bag_bench_times_each_command_in_its_own_process(tmp_path) -> None:
    """bench/long_bag.py: the rusage is the command's own (a child that holds 300 MB more than pytest shows it, the
    next one does not inherit it), and bag-info and evaluate of a short robot bag report its samples."""
    import resource
    import sys

    import long_bag
    import robot_bag

    # a child's peak starts from its parent's at the fork (pytest's, here): hold 300 MB above that
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    size = int((own + 300) * 2**20 / 8)
    hold = f"import numpy as np; a = np.ones({size}); print(int(a.sum()))"
    code, _wall, cpu, rss, out, _err = long_bag.timed([sys.executable, "-c", hold], tmp_path)
    assert code == 0 and int(out) == size and rss > own + 280 and cpu > 0
    code, _wall, _cpu, small, _out, _err = long_bag.timed([sys.executable, "-c", "pass"], tmp_path)
    assert code == 0 and small < own + 100  # not its sibling's 300 MB
    # 12 s: past the default model's scale warm-up (5000 samples; a shorter bag fails evaluate's free run)
    written = long_bag.write(tmp_path / "robot", 12.0, "sqlite3", 3, robot_bag.STATE_RATE, print)
    assert written["messages"] == 7200 and written["bytes"] > 0
    bag = tmp_path / "robot"
    results = long_bag.run_bag("12 s", bag, robot_bag.flags(), 4801, ("bag-info", "evaluate"), tmp_path, print)
    assert [r.command for r in results] == ["bag-info", "evaluate --test-from 4801 (default model)"]
    assert all(r.returncode == 0 and r.within_limit and r.peak_rss_mb > 50 for r in results), results
    assert results[0].samples == results[1].samples > 5990
    assert results[1].nmse_free_run_db is not None
    report = {"results": [dataclasses.asdict(r) | {"within_limit": r.within_limit} for r in results]}
    assert long_bag.markdown(report).count("\n") == 3
