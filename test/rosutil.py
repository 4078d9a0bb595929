"""Helpers for tests that start real nodes: subprocesses and an in-test publisher."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor

from lenn_ros import topics

REPO = Path(__file__).resolve().parents[1]


def start_node(
    module: str, *params: str, params_file: Path | None = None, ros_args: tuple[str, ...] = ()
) -> subprocess.Popen[str]:
    """The node's entry module as a real process; ``ros_args`` e.g. ("-r", "u:=/robot/cmd")."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    env["PYTHONUNBUFFERED"] = "1"
    args = [sys.executable, "-m", f"lenn_ros.nodes.{module}", "--ros-args"]
    if params_file is not None:
        args += ["--params-file", str(params_file)]
    for param in params:
        args += ["-p", param]
    args += list(ros_args)
    return subprocess.Popen(args, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def stop(proc: subprocess.Popen[str], sig: int = signal.SIGINT, timeout: float = 20) -> tuple[str, str]:
    proc.send_signal(sig)
    try:
        return proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


class ParameterClient:
    """Sets a node's parameters through its ``set_parameters`` service, as ``ros2 param set`` does."""

    def __init__(self, domain_id: int, node_name: str = "/identifier") -> None:
        from rcl_interfaces.srv import SetParameters

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("test_parameter_client", context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.request_type = SetParameters.Request
        self.client = self.node.create_client(SetParameters, f"{node_name}/set_parameters")

    def __enter__(self) -> ParameterClient:
        assert self.client.wait_for_service(timeout_sec=20)
        return self

    def __exit__(self, *_: object) -> None:
        self.node.destroy_node()
        self.ctx.try_shutdown()

    def set(self, name: str, value):
        """The service's result for this one parameter (``successful``, ``reason``)."""
        from rclpy.parameter import Parameter

        future = self.client.call_async(self.request_type(parameters=[Parameter(name, value=value).to_parameter_msg()]))
        rclpy.spin_until_future_complete(self.node, future, executor=self.executor, timeout_sec=10)
        assert future.result() is not None, f"no answer from the parameter service setting {name}"
        return future.result().results[0]


class Talker:
    """Publishes u(k) = k and y_p(k) = -k like the plant simulator (one node, u then y_p)."""

    def __init__(self, domain_id: int) -> None:
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("test_talker", context=self.ctx)
        msg = topics.message_class(topics.FLOAT64)
        self.msg = msg
        self.pubs = [self.node.create_publisher(msg, name, topics.data_qos()) for name in (topics.U, topics.Y_P)]
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        self.sent = 0

    def wait_matched(self, timeout: float = 15) -> bool:
        deadline = time.monotonic() + timeout
        tick = threading.Event()
        while min(p.get_subscription_count() for p in self.pubs) < 1:
            if time.monotonic() > deadline:
                return False
            tick.wait(0.05)
        return True

    def publish(self, n: int) -> None:
        for _ in range(n):
            k = self.sent
            self.pubs[0].publish(self.msg(data=float(k)))
            self.pubs[1].publish(self.msg(data=-float(k)))
            self.sent += 1

    def acked(self, timeout: float = 10) -> bool:
        return all(p.wait_for_all_acked(Duration(seconds=timeout)) for p in self.pubs)

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=5)  # the spin thread must be out before the node goes
        self.node.destroy_node()
        self.ctx.try_shutdown()


class Listener:
    """Counts every message of a run's topics and keeps the identifier's last status."""

    def __init__(self, domain_id: int) -> None:
        import json

        from std_msgs.msg import Float64, String

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("test_listener", context=self.ctx)
        self.values: dict[str, list[float]] = {name: [] for name in (topics.U, topics.Y_P, topics.Y_HAT, topics.ERROR)}
        self.status: dict = {}
        self.status_event = threading.Event()
        for name in self.values:
            self.node.create_subscription(Float64, name, lambda m, n=name: self.values[n].append(m.data),
                                          topics.data_qos())  # fmt: skip

        def on_status(message: String) -> None:
            self.status = json.loads(message.data)
            self.status_event.set()

        self.node.create_subscription(String, topics.STATUS, on_status, topics.data_qos())
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def wait_status(self, condition, timeout: float = 30.0) -> dict:
        """The first status (JSON) for which condition(status) holds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.status_event.clear()
            if self.status and condition(self.status):
                return self.status
            self.status_event.wait(0.5)
        raise AssertionError(f"status never satisfied the condition; last: {self.status}")

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=5)  # the spin thread must be out before the node goes
        self.node.destroy_node()
        self.ctx.try_shutdown()


def final_status(stderr: str) -> dict:
    """The JSON status line the identifier prints when it stops."""
    import json

    for line in reversed(stderr.splitlines()):
        if line.startswith("identifier: {"):
            return json.loads(line.split(": ", 1)[1])
    raise AssertionError(f"no final status in the identifier's output:\n{stderr[-2000:]}")
