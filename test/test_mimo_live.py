"""A two-output plant identified live: the simulator's MIMO plant, two identifier processes over DDS.

One simulator publishes u and y_p as Float64MultiArray; the MIMO identifier (couplings
full) and, in a namespace, one SISO model per output (couplings diagonal) learn from
the same messages (bench/mimo_live.py runs them). Per-channel NMSE over seeds must
show the coupling captured, and equal what the core computes offline from the same seeds.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(300)]

rclpy = pytest.importorskip("rclpy")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from mimo_live import NAMES, run_live, run_offline  # noqa: E402

TRAIN, TEST, NOISE_DB = 3000, 600, -30.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_output_plant_identified_live_beats_one_siso_model_per_output(tmp_path: Path, domain: int, seed: int):
    live = run_live(seed, TRAIN, TEST, NOISE_DB, tmp_path)
    for couplings, status in live.items():
        counters = status["counters"]
        assert counters["paired"] == TRAIN + TEST and counters["lost"] == counters["rejected"] == 0, counters
        assert status["u_channels"] == ["u1", "u2"] and status["y_channels"] == list(NAMES)
        assert status["phase_samples"] == TEST and status["learning"] is False  # frozen at test_start
        offline = run_offline(seed, TRAIN, TEST, NOISE_DB, couplings)
        for name in NAMES:
            assert status["channels"][name]["phase_nmse_db"] == pytest.approx(offline[name], abs=1e-9)
    for name in NAMES:
        mimo = live["full"]["channels"][name]["phase_nmse_db"]
        siso = live["diagonal"]["channels"][name]["phase_nmse_db"]
        assert mimo < siso - 5.0, (name, mimo, siso)
