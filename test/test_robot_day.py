"""Issue 18: a robot's whole day, shortened (``bench/robot_day.py --scale 0.2``), with the defaults alone.

Real processes over DDS: a friction joint published as stamped BEST_EFFORT JointState at
1 kHz with the joints in another order, a controller's Float64MultiArray at 50 Hz from
another process, the identifier given only remaps, types, fields, ``pairing:=sample``
and ``sample_period``, and the recorder. The day: the driver alone, moving, standing
still, moving with ``alpha`` changed live, a 5 s burst as fast as the driver can,
moving, then ``learning:=false`` and a frozen test phase; SIGINT; ``evaluate`` of the bag.
The full-length day's figures are the benchmark's (bench/RESULTS.md). Bounds from two
short days on this machine: test phase -62.5 dB (bound -30), exit 1.25 s (bound 2),
RSS +31 kB once the pairing queue is full (bound 1 MB), evaluate equal to the live figure.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(900)]

REPO = Path(__file__).resolve().parents[1]


def _day(tmp_path: Path, *extra: str) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run(
        [sys.executable, str(REPO / "bench" / "robot_day.py"), "--scale", "0.2", "--json",
         "--bag", str(tmp_path / "day"), *extra],
        env=env, capture_output=True, text=True, timeout=800, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout)
    print(json.dumps({k: v for k, v in result.items() if k != "identifier_log"}, indent=1))
    return result


@pytest.mark.parametrize("solver", [None, "rls"], ids=["defaults", "rls"])
def test_a_robot_day_with_the_defaults(tmp_path: Path, domain: int, solver: str | None) -> None:
    result = _day(tmp_path, *(["--solver", solver] if solver else []))
    phases = {row["phase"]: row for row in result["phases"]}
    assert phases["driver alone"]["paired"] == 0  # no command yet: nothing pairs
    # bounded while the command is absent: the mean RSS of the second half within 1 MB of the first
    assert result["rss_kib_second_half_mean"] - result["rss_kib_first_half_mean"] < 1024
    # learning resumes after standing still and after the burst (most samples learnt, not frozen)
    for name in ("moving, alpha changed", "moving after the burst"):
        assert phases[name]["learned"] > 0.5 * phases[name]["paired"] > 0, phases[name]
    assert result["alpha_call"]["accepted"] and result["learning_false_call"]["accepted"]
    # every call answered within the 0.5 s. With the inputs on the identifier's own participant
    # (up to 2.9 s: the flood delayed the service requests in the middleware) that failed; with them apart
    # (the default) measured max 73.1 / 76.8 ms, p50 27.9 / 30.1 ms (defaults / rls, 2026-12-04)
    assert result["burst_calls_unanswered"] == 0 and result["burst_call_p50_ms"] < 100.0
    assert result["burst_call_max_ms"] < 500.0, result["burst_call_max_ms"]
    assert phases["burst"]["shed"] > 0  # overloaded, it shed (counted), and it says so
    assert any("shed" in line for line in result["identifier_log"])
    assert result["live_test_nmse_db"] is not None and result["live_test_nmse_db"] <= -30.0
    # evaluate equals live: the bag holds the whole run once status says the recorder has every output
    # (acknowledged). It once never did under pytest: the recorder logged a line per gap through the burst
    # into a pipe nobody read, and blocked when it filled (now one line per 5 s, and the children log to
    # files). Measured: caught up 1.9 s after the day, equal to 1e-14 dB.
    assert result["recorder_caught_up_s"] is not None, result["recorder"]
    assert result["offline_test_nmse_db"] == pytest.approx(result["live_test_nmse_db"], abs=1e-6)
    assert result["exit_code"] == 0 and result["sigint_exit_s"] < 2.0
    # a healthy day (rest, motion, alpha changed live, a burst, a frozen phase) raises no plant-change alarm
    assert result["live_counters"]["change_alarms"] == 0 and result["change"]["count"] == 0, result["change"]
