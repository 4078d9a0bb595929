"""Over DDS: the simulator's actuator loses 20 % at a step the identifier is not told; the identifier, started
from fit's model of the plant (as a user runs it: the alarm's reference is the model it serves), raises
/diagnostics WARN "plant changed" within 200 samples (2 s at 100 Hz), logs it once, and publishes y_hat_std
beside y_hat."""

from __future__ import annotations

import math
import re
import threading

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(180)]

rclpy = pytest.importorskip("rclpy")

from pathlib import Path  # noqa: E402

from rosutil import Listener, final_status, start_node, stop  # noqa: E402

from lenn_ros import topics  # noqa: E402
from lenn_ros.fit.data import Data  # noqa: E402
from lenn_ros.fit.export import write_outputs  # noqa: E402
from lenn_ros.fit.procedure import fit  # noqa: E402
from lenn_ros.paper.experiments.tracking import simulate_change  # noqa: E402

CHANGE_STEP = 12_000
TOTAL = 15_000
RATE = 1000.0  # Hz of wall time: the alarm's hold (500 samples) spans several status periods of 0.1 s


def fitted_example_3(folder: Path) -> Path:
    """fit's model of Ex. 3's plant from another run of it (noise-free, as the simulator below runs it)."""
    u, y = simulate_change(9, 20_000, 20_000, 1.0, 3, noise_db=-300.0)
    data = Data(u=u, y=y, source="Ex. 3, the day before")
    return Path(write_outputs(folder, fit(data, test_from=16_000), data)["params"])


def test_a_plant_change_raises_the_warn_within_2_s_at_100_hz_and_y_hat_std_is_published(
    domain: int, tmp_path: Path
) -> None:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from std_msgs.msg import Float64

    listener = Listener(domain)
    warnings: list[str] = []
    stds: list[float] = []
    lock = threading.Lock()

    def on_diagnostics(message: DiagnosticArray) -> None:
        with lock:
            warnings.extend(s.message for s in message.status if s.level == DiagnosticStatus.WARN)

    listener.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diagnostics, 10)
    listener.node.create_subscription(Float64, topics.Y_HAT_STD, lambda m: stds.append(m.data), topics.data_qos())
    params = fitted_example_3(tmp_path)
    identifier = start_node("identifier", "status_period:=0.1", "wait_for_y_hat_subscribers:=2", params_file=params)
    simulator = start_node(
        "plant_simulator",
        "example:=3",
        "seed:=5",
        f"train_samples:={TOTAL}",
        "test_samples:=0",
        f"rate_hz:={RATE}",
        f"change_step:={CHANGE_STEP}",
        "noise_db:=-300.0",
        "change_input_gain:=0.8",
        "wait_for_subscribers:=2",
        "exit_when_done:=true",
    )
    try:
        _, sim_err = simulator.communicate(timeout=120)
        assert simulator.returncode == 0, sim_err
        listener.wait_status(lambda s: s["counters"]["paired"] == TOTAL, timeout=30)
    finally:
        _, id_err = stop(identifier)
        listener.close()
    assert f"step {CHANGE_STEP}: plant changed (actuator gain x0.8" in sim_err
    status = final_status(id_err)
    assert status["change"]["count"] >= 1 and status["counters"]["change_alarms"] == status["change"]["count"]
    raised = [int(n) for n in re.findall(r"plant changed at sample (\d+)", id_err)]
    assert raised, id_err[-3000:]
    # sample k of the identifier is the simulator's step k - 1: the first new output is sample CHANGE_STEP + 2
    delay = raised[0] - (CHANGE_STEP + 2)
    said_lines = "\n".join(line for line in id_err.splitlines() if "change" in line or "plant" in line)
    assert 0 <= delay <= 200, f"alarm at sample {raised[0]}, change at {CHANGE_STEP + 2}:\n{said_lines[:3000]}"
    with lock:
        said = [w for w in warnings if w.startswith("plant changed at sample")]
    assert said and f"plant changed at sample {raised[0]} (t=" in said[0] and "times its learnt level" in said[0]
    assert "change alarm armed" in id_err  # (said once it knew its reference simulates)
    # one std per y_hat, in step; NaN until the first error has been seen (nothing known yet), then > 0
    assert len(stds) == len(listener.values[topics.Y_HAT]) > 0
    assert math.isnan(stds[0]) and all(s > 0 for s in stds[1:])
