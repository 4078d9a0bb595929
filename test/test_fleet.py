"""A fleet: several identifiers in one process, each its plant's own (topics, parameters, model, status)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rosutil import start_node, stop  # noqa: E402

from lenn_ros import topics  # noqa: E402
from lenn_ros.paper.evaluation import simulate  # noqa: E402
from lenn_ros.paper.examples import EXAMPLES  # noqa: E402

PLANTS = ("line1/press", "line2/oven", "idle")


def final_statuses(stderr: str) -> dict[str, dict]:
    """Every identifier's final status line, by its u topic's namespace."""
    statuses = {}
    for line in stderr.splitlines():
        if line.startswith("identifier: {"):
            status = json.loads(line.split(": ", 1)[1])
            statuses[status["topics"]["u"].rsplit("/", 1)[0]] = status
    return statuses


def test_fleet_identifies_each_plant_on_its_own(tmp_path: Path, domain: int) -> None:
    """Two plants driven with different data, one idle; a params file sets one plant's network."""
    params = tmp_path / "fleet.yaml"
    params.write_text(
        json.dumps(
            {
                "/**": {"ros__parameters": {"example": 1, "status_period": 0.2}},
                "/line2/oven/identifier": {"ros__parameters": {"network": "mlp"}},
            }
        )
    )
    fleet = start_node("fleet", f"plants:=[{', '.join(PLANTS)}]", params_file=params)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("two_plants", context=context)  # one lockstep publisher per plant's pair
    float64 = topics.message_class(topics.FLOAT64)
    names = (topics.U, topics.Y_P)
    publishers = {
        plant: [node.create_publisher(float64, f"/{plant}/{name}", topics.data_qos()) for name in names]
        for plant in PLANTS[:2]
    }
    counts = {PLANTS[0]: 1500, PLANTS[1]: 900}
    learnt: dict[str, int] = {}  # each driven plant's identifier's learned count, from its status topic
    string = topics.message_class(topics.STRING)
    for plant in counts:
        node.create_subscription(
            string, f"/{plant}/{topics.STATUS}",
            lambda message, plant=plant: learnt.__setitem__(plant, json.loads(message.data)["counters"]["learned"]),
            topics.data_qos(),
        )  # fmt: skip
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while min(p.get_subscription_count() for pair in publishers.values() for p in pair) < 1:
            assert time.monotonic() < deadline, "the fleet's identifiers never subscribed"
            time.sleep(0.05)
        series = simulate(EXAMPLES[1].plant(), EXAMPLES[1].noise_db, 2, 1500, 0)
        for plant, count in counts.items():
            for k in range(count):
                u_pub, y_pub = publishers[plant]
                u_pub.publish(float64(data=float(series.u[k])))
                y_pub.publish(float64(data=float(series.y[k])))
        wait = rclpy.duration.Duration(seconds=10)
        assert all(p.wait_for_all_acked(wait) for pair in publishers.values() for p in pair)
        # poll until every pair is learnt (held first: the graph check's grace), not a sleep tied to that grace
        expected = {plant: count - EXAMPLES[1].structure.warm_up for plant, count in counts.items()}
        deadline = time.monotonic() + 30
        while learnt != expected:
            assert time.monotonic() < deadline, f"learnt {learnt}, expected {expected} within 30 s"
            time.sleep(0.05)
    finally:
        _, err = stop(fleet)
        executor.shutdown()
        thread.join(timeout=5)
        node.destroy_node()
        context.try_shutdown()
    statuses = final_statuses(err)
    assert set(statuses) == {f"/{plant}" for plant in PLANTS}, err[-2000:]
    for plant, count in counts.items():
        counters = statuses[f"/{plant}"]["counters"]
        assert counters["paired"] == counters["samples"] == count and counters["lost"] == 0, (plant, counters)
        # all but the warm-up (no prediction yet): learnt, not merely received
        assert counters["learned"] == count - EXAMPLES[1].structure.warm_up, (plant, counters)
    assert statuses["/line1/press"]["network"] == "lenn" and statuses["/line2/oven"]["network"] == "mlp"
    assert statuses["/idle"]["counters"]["u_messages"] == 0
    assert "unknown parameter" not in err and "Traceback" not in err, err[-2000:]


@pytest.mark.parametrize(
    ("plants", "message"),
    [("[]", "no plants"), ("[a, a]", "plants named twice: /a"), ("['bad name']", "is not a namespace")],
)
def test_a_bad_plant_list_is_one_line(domain: int, plants: str, message: str) -> None:
    fleet = start_node("fleet", f"plants:={plants}")
    _, err = fleet.communicate(timeout=60)
    assert fleet.returncode == 2 and message in err and "Traceback" not in err, err
