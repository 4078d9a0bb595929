"""The measuring side of the live benchmarks: parameter calls and every status message of an identifier.

One node of the benchmark's own process, spun on a thread, so a call's latency is the
identifier's answer time and not the benchmark's loop. Shared by ``overload.py`` and
``robot_day.py`` (run as scripts, they import it from their own folder).
"""

from __future__ import annotations

import json
import threading
import time
from typing import Any


class Probe:
    """``set``/``get`` on ``/identifier``'s parameter services and the statuses it publishes, timed."""

    def __init__(self, node_name: str, timeout: float = 5.0) -> None:
        import rclpy
        from rcl_interfaces.srv import GetParameters, SetParameters
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import String

        from lenn_ros import topics

        rclpy.init()
        self.rclpy, self.timeout = rclpy, timeout
        self.node = rclpy.create_node(node_name)
        self.setter = self.node.create_client(SetParameters, "/identifier/set_parameters")
        self.getter = self.node.create_client(GetParameters, "/identifier/get_parameters")
        self.statuses: list[tuple[float, dict]] = []  # (received at, status), in arrival order
        self.node.create_subscription(String, topics.STATUS, self._on_status, topics.data_qos())
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _on_status(self, message: Any) -> None:
        self.statuses.append((time.monotonic(), json.loads(message.data)))

    def _call(self, client: Any, request: Any) -> tuple[float | None, Any]:
        """(latency in s, answer), or (None, None) when no answer came within ``timeout``."""
        done = threading.Event()
        sent = time.monotonic()
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.set())
        if not done.wait(self.timeout):
            return None, None
        return time.monotonic() - sent, future.result()

    def set(self, name: str, value: Any) -> tuple[float | None, bool]:
        """(latency in s or None when unanswered, accepted)."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        latency, answer = self._call(self.setter, request)
        return latency, bool(answer is not None and answer.results[0].successful)

    def get(self, name: str) -> Any:
        """The parameter's value, or None when unanswered."""
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python

        _, answer = self._call(self.getter, GetParameters.Request(names=[name]))
        return None if answer is None else parameter_value_to_python(answer.values[0])

    def last(self, before: float) -> dict:
        """The last status received before ``before`` (empty if none)."""
        chosen: dict = {}
        for received, status in self.statuses:
            if received > before:
                break
            chosen = status
        return chosen

    def counter(self, name: str, at: float) -> int:
        """A counter as the last status received before ``at`` said it."""
        return int(self.last(at).get("counters", {}).get(name, 0))

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=5)
        self.node.destroy_node()
        self.rclpy.try_shutdown()
