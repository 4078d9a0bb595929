"""Over DDS: the identifier publishes the live band's half-width (y_hat_band) with each y_hat, the recorder records it
with y_hat_std, and ``evaluate`` of the recording gives the band the node published."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(180)]

rclpy = pytest.importorskip("rclpy")

from rosutil import Listener, final_status, start_node, stop  # noqa: E402

from lenn_ros import topics  # noqa: E402
from lenn_ros.bag import iter_messages  # noqa: E402
from lenn_ros.service.evaluation import evaluate_bag  # noqa: E402

TRAIN, TEST = 3000, 1000


def test_the_live_band_is_published_with_y_hat_recorded_and_evaluated_as_published(tmp_path: Path, domain: int):
    from std_msgs.msg import Float64

    listener = Listener(domain)
    bands: list[float] = []
    listener.node.create_subscription(Float64, topics.Y_HAT_BAND, lambda m: bands.append(m.data), topics.data_qos())
    bag = tmp_path / "bag"
    recorder = start_node("recorder", f"output:={bag}")
    # y_hat: the simulator, the recorder, the listener; y_hat_band's two readers match with the same participants
    identifier = start_node("identifier", "example:=0", "wait_for_y_hat_subscribers:=3")
    simulator = start_node(
        "plant_simulator",
        "example:=3",
        "seed:=2",
        f"train_samples:={TRAIN}",
        f"test_samples:={TEST}",
        "rate_hz:=0.0",
        "wait_for_subscribers:=3",
        "exit_when_done:=true",
    )
    total = TRAIN + TEST
    try:
        _, sim_err = simulator.communicate(timeout=120)
        assert simulator.returncode == 0, sim_err
        listener.wait_status(lambda s: s["counters"]["paired"] == total, timeout=30)
    finally:
        _, id_err = stop(identifier)
        _, rec_err = stop(recorder)
        listener.close()
    counters = final_status(id_err)["counters"]
    assert counters["paired"] == total and counters["lost"] == 0
    # one half-width per y_hat, in step; NaN until the first error has been seen, then > 0
    assert len(bands) == len(listener.values[topics.Y_HAT]) > TEST
    assert math.isnan(bands[0]) and all(b > 0 for b in bands[1:])
    recorded: dict[str, list[float]] = {"/" + topics.Y_HAT_BAND: [], "/" + topics.Y_HAT_STD: [], "/error": []}
    for message in iter_messages(bag, topics=list(recorded)):
        recorded[message.topic].append(message.message.data)
    band, std, error = (np.array(values) for values in recorded.values())
    assert np.array_equal(band, bands, equal_nan=True) and len(std) == len(band)
    assert len({round(b / s, 9) for b, s in zip(band[1:], std[1:], strict=True)}) > 100  # not 1.96 std
    # the j-th error scores the j-th y_hat: the live band's coverage of the test part, from the recording
    live = float(np.mean(np.abs(error[-TEST:]) <= band[: len(error)][-TEST:]))
    offline = evaluate_bag(str(bag)).intervals["one_step"]["live"]
    assert offline["coverage_test"] == pytest.approx(live, abs=1e-12)
    assert "Traceback" not in rec_err and "[ERROR]" not in rec_err
