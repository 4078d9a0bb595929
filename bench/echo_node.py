"""bench_echo: the ceiling for the identifier, an rclpy node that does no work.

It subscribes to ``u`` and ``y_p`` with the identifier's QoS (so the transport
carries exactly what it carries to the identifier) and publishes every ``y_p``
message back on ``y_hat``, unchanged.

    python bench/echo_node.py            # rclpy.spin, like the identifier
    python bench/echo_node.py --waitset  # no executor: own wait set, raw take/publish
    python bench/echo_node.py --events   # rclpy.experimental.EventsExecutor

The first is the ceiling of an rclpy node spun the usual way (the
SingleThreadedExecutor rebuilds its wait set in Python for every message). The
second shows what the executor itself costs: it waits on a wait set built once and
takes / publishes serialised bytes, which is the least Python work per message
rclpy allows. The third is the C++ events executor (rmw "new message" callbacks,
no wait set), the supported route to the second's speed, and the ceiling for an
identifier run with ``executor="events"``.
"""

from __future__ import annotations

import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from std_msgs.msg import Float64

from lenn_ros import topics


class EchoNode(Node):
    def __init__(self, raw: bool = False) -> None:
        super().__init__("bench_echo")
        qos = topics.data_qos()
        self.publisher = self.create_publisher(Float64, topics.Y_HAT, qos)
        self.u_subscription = self.create_subscription(Float64, topics.U, lambda message: None, qos, raw=raw)
        self.y_subscription = self.create_subscription(Float64, topics.Y_P, self.publisher.publish, qos, raw=raw)

    def spin_waitset(self) -> None:
        """Echo without an executor until the context shuts down (SIGINT)."""
        from lenn_ros.nodes import rclpy_internals

        if not rclpy_internals.available():
            raise SystemExit(f"echo_node --waitset: {rclpy_internals.unavailable()}")
        u, y, take = self.u_subscription, self.y_subscription, rclpy_internals.take
        publish = self.publisher.publish  # bytes: published raw
        with rclpy_internals.WaitSet(self.context, [u, y]) as wait_set:
            while self.context.ok():
                wait_set.wait(100_000_000)
                while take(u) is not None:
                    pass
                while (taken := take(y)) is not None:
                    publish(taken[0])

    def spin_events(self) -> None:
        """Echo under the events executor until the context shuts down (SIGINT).

        Not ``rclpy.spin(node, executor=...)``: in rclpy 7.1.6 the events executor's
        ``spin_once()`` without a timeout busy-loops and never delivers a message;
        with a timeout it runs one event (one message) per call.
        """
        from rclpy.experimental import EventsExecutor

        executor = EventsExecutor(context=self.context)
        executor.add_node(self)
        try:
            while self.context.ok():
                executor.spin_once(timeout_sec=0.1)
        finally:
            executor.shutdown()


def main(args: list[str] | None = None) -> int:
    args = list(sys.argv if args is None else args)
    waitset, events = "--waitset" in args, "--events" in args
    rclpy.init(args=[a for a in args if a not in ("--waitset", "--events")])
    node = None
    try:
        node = EchoNode(raw=waitset)
        if waitset:
            node.spin_waitset()
        elif events:
            node.spin_events()
        else:
            rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
