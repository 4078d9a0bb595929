"""The identifier under each loop run_node offers (``LENN_ROS_EXECUTOR``): same behaviour, real nodes over DDS.

The loops differ only in how messages reach the node (rclpy's single-threaded
executor, the experimental events executor, or run_node's own wait set), so each
must keep every guarantee: every pair answered, nothing lost, the optional outputs
(samples, error, stamped) complete for a reader, parameter services, status and
autosave timers (also an autosave timer replaced at run time), and a graceful
SIGINT with the final status line and the weights saved.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rosutil import ParameterClient, final_status, start_node, stop

from lenn_ros import topics
from lenn_ros.nodes import EXECUTOR_VARIABLE, EXECUTORS, rclpy_internals
from lenn_ros.nodes.identifier_outputs import OUTPUTS
from lenn_ros.paper.examples import EXAMPLES

PAIRS = 400
AFTER = 20  # pairs sent after learning is switched off


class Outputs:
    """Every output of the identifier a reader can take, and its last status."""

    def __init__(self, domain_id: int) -> None:
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64, Float64MultiArray, String

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("test_outputs", context=self.ctx)
        qos = topics.data_qos()
        self.y_hat: list[float] = []
        self.error: list[float] = []
        self.samples: list[list[float]] = []
        self.stamped: dict[str, list[tuple[int, float]]] = {topics.Y_HAT_STAMPED: [], topics.ERROR_STAMPED: []}
        self.status: dict = {}
        self.node.create_subscription(Float64, topics.Y_HAT, lambda m: self.y_hat.append(m.data), qos)
        self.node.create_subscription(Float64, topics.ERROR, lambda m: self.error.append(m.data), qos)
        self.node.create_subscription(
            Float64MultiArray, topics.SAMPLES, lambda m: self.samples.append(list(m.data)), qos
        )
        for name, values in self.stamped.items():
            self.node.create_subscription(
                JointState,
                name,
                lambda m, v=values: v.append((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m.position[0])),
                qos,
            )
        self.node.create_subscription(String, topics.STATUS, lambda m: setattr(self, "status", json.loads(m.data)), qos)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=5)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def _wait(condition, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _set_parameter(domain: int, name: str, value) -> bool:
    """Through the node's parameter service, as ``ros2 param set`` does."""
    with ParameterClient(domain) as client:
        return bool(client.set(name, value).successful)


def _check_outputs(outputs: Outputs) -> None:
    """The optional outputs, built from reused messages now, say the same as y_hat and samples."""
    total = PAIRS + AFTER
    assert len(outputs.y_hat) == total - (EXAMPLES[1].structure.warm_up - 1)
    assert [row[0] for row in outputs.samples] == [float(k) for k in range(1, total + 1)]
    assert [row[4] for row in outputs.samples[-AFTER:]] == [0.0] * AFTER
    errors = outputs.stamped[topics.ERROR_STAMPED]
    assert len(outputs.error) == len(errors) == len(outputs.stamped[topics.Y_HAT_STAMPED]) > total // 2
    assert [value for _, value in errors] == outputs.error
    # y^(k) stamped at sample k is the prediction published as y_hat at sample k - 1
    predicted = [value for _, value in outputs.stamped[topics.Y_HAT_STAMPED]]
    assert predicted == outputs.y_hat[len(outputs.y_hat) - len(predicted) - 1 : -1]
    sample_times = {round(row[1] * 1e9) for row in outputs.samples}
    assert {stamp for stamp, _ in errors} <= sample_times


#: "public": the wait-set loop asked for where rclpy's internals cannot be used (forced off):
#: the single-threaded executor runs instead, the drains take nothing directly, and it is said
@pytest.mark.parametrize("loop", [*EXECUTORS, "public"])
def test_identifier_under_each_loop(tmp_path: Path, domain: int, talker, monkeypatch, loop: str) -> None:
    monkeypatch.setenv(EXECUTOR_VARIABLE, "waitset" if loop == "public" else loop)
    if loop == "public":
        monkeypatch.setenv(rclpy_internals.VARIABLE, "0")
    weights = tmp_path / "weights.npz"
    identifier = start_node(
        "identifier", "example:=1", "status_period:=0.2", f"weights_out:={weights}", "autosave_period:=30.0"
    )
    outputs = Outputs(domain)
    try:
        assert talker.wait_matched(timeout=30), "the identifier's subscriptions never matched"
        _wait(lambda: outputs.node.count_publishers(topics.SAMPLES) > 0 and outputs.status, 30, "status")
        # the identifier's publishers must see our readers too (a y_hat sent before that is lost: CI under load
        # once took 46 of 419): its status counts the matched readers of each output
        _wait(lambda: all(outputs.status.get("readers", {}).get(name, 0) > 0 for name in OUTPUTS), 30, "readers")
        for _ in range(PAIRS // 100):
            talker.publish(100)  # bursts: the loops take what is queued
            time.sleep(0.05)
        _wait(lambda: outputs.status.get("counters", {}).get("paired") == PAIRS, 30, f"{PAIRS} pairs")
        assert _set_parameter(domain, "learning", False)
        talker.publish(AFTER)  # the status says the learning of the last sample
        _wait(lambda: outputs.status.get("counters", {}).get("paired") == PAIRS + AFTER, 30, "the pairs after")
        assert outputs.status["learning"] is False
        assert _set_parameter(domain, "autosave_period", 0.2)  # the autosave timer destroyed and made anew
        _wait(weights.exists, 10, "an autosave from the new timer")
        time.sleep(0.5)  # more timer ticks on the replaced timer
    finally:
        outputs.close()
        _, err = stop(identifier, signal.SIGINT)
    assert identifier.returncode == 0, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    fallback = "the wait-set loop needs rclpy internals (LENN_ROS_RCLPY_INTERNALS=0): running rclpy's single-threaded"
    assert (fallback in err) == (loop == "public"), err[:2000]
    final = final_status(err)
    assert final["counters"]["paired"] == PAIRS + AFTER
    assert final["counters"]["lost"] == 0 and final["counters"]["duplicates"] == 0
    assert weights.exists()
    _check_outputs(outputs)


def test_unknown_loop_is_one_line(domain: int, monkeypatch) -> None:
    monkeypatch.setenv(EXECUTOR_VARIABLE, "fastest")
    identifier = start_node("identifier")
    _, err = identifier.communicate(timeout=60)
    assert identifier.returncode == 2
    assert "unknown executor 'fastest'" in err and "Traceback" not in err


def test_message_info_callback_takes_both_calling_forms() -> None:
    """rclpy 7.1.6's events executor passes one (message, info) tuple; rclpy's own executors two arguments."""
    import inspect

    calls = []
    wrapped = rclpy_internals.MessageInfoCallback(lambda message, info: calls.append((message, info)))
    assert len(inspect.signature(wrapped).parameters) == 2  # so rclpy hands it the message info
    wrapped(("m", {"publication_sequence_number": 1}))
    wrapped("m", {"publication_sequence_number": 2})
    assert calls == [("m", {"publication_sequence_number": 1}), ("m", {"publication_sequence_number": 2})]


def test_public_fallback_reads_the_callback_as_rclpy_does(domain: int, monkeypatch) -> None:
    """Without the internals: the same (message, info) decision as rclpy's own, and nothing taken."""
    from std_msgs.msg import Float64

    context = Context()
    rclpy.init(context=context, domain_id=domain)
    try:
        node = rclpy.create_node("test_fallback", context=context)
        qos = topics.data_qos()
        callbacks = [lambda m: None, lambda m, info: None, rclpy_internals.MessageInfoCallback(lambda m, i: None)]
        subscriptions = [node.create_subscription(Float64, "/x", callback, qos) for callback in callbacks]
        rclpy_internals.unavailable.cache_clear()
        assert rclpy_internals.available(), rclpy_internals.unavailable()
        with_internals = [rclpy_internals.takes_info(s) for s in subscriptions]
        monkeypatch.setenv(rclpy_internals.VARIABLE, "0")
        rclpy_internals.unavailable.cache_clear()
        assert rclpy_internals.unavailable() == "LENN_ROS_RCLPY_INTERNALS=0"
        assert [rclpy_internals.takes_info(s) for s in subscriptions] == with_internals == [False, True, True]
        assert rclpy_internals.take(subscriptions[0]) is None
        node.destroy_node()
    finally:
        monkeypatch.delenv(rclpy_internals.VARIABLE)
        rclpy_internals.unavailable.cache_clear()
        context.try_shutdown()
