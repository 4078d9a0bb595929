"""robot_controller: a controller process commanding the simulated robot, as ros2_control does.

Publishes the command u on ``cmd`` as ``std_msgs/msg/Float64MultiArray`` (the value in
``data[0]``, like the forward command controller's ``commands`` topic), BEST_EFFORT,
without a header: a receiver can only time it by its arrival. The values are the
paper's excitation (:class:`~lenn_ros.paper.signals.Excitation`, seeded): uniform on
[-1, 1], then optionally the eq. 11 test sinusoid. One value per tick at
``rate_hz``, its own clock, unrelated to the driver's: a late tick is not caught up
(a controller sends the command that is current, not a backlog).
"""

from __future__ import annotations

import sys
import time

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from std_msgs.msg import Float64MultiArray

from lenn_ros.nodes import run_node
from lenn_ros.paper.signals import SIGNALS, Excitation

#: Default topic of the command (relative: remap with -r cmd:=/robot/commands).
CMD = "cmd"


def describe(text: str, low: float | None = None, high: float | None = None) -> ParameterDescriptor:
    """A read-only parameter's description and range (rclpy refuses an override outside it)."""
    descriptor = ParameterDescriptor(description=text, read_only=True)
    if isinstance(low, int) and isinstance(high, int):
        descriptor.integer_range = [IntegerRange(from_value=low, to_value=high, step=1)]
    elif low is not None and high is not None:
        descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high))]
    return descriptor


class RobotController(Node):
    """Sends one excitation sample per tick until ``duration`` or the signal's end."""

    def __init__(self) -> None:
        super().__init__("robot_controller")
        declare = self.declare_parameter
        declare("rate_hz", 50.0, describe("commands per second", 0.1, 10_000.0))
        declare("seed", 0, describe("seed of the excitation", 0, 2**31 - 1))
        declare("signal", "uniform", describe(f"command signal: {', '.join(SIGNALS)} (paper: uniform, then eq. 11)"))
        declare("train_samples", 50_000, describe("signal paper: commands of uniform random input", 0, 10**9))
        declare("test_samples", 600, describe("signal paper: commands of the eq. 11 sinusoid after them", 0, 10**9))
        declare("duration", 0.0, describe("seconds to run from the first command (0 = to the signal's end)", 0.0, 1e9))
        declare("depth", 10, describe("publisher history depth", 1, 10_000))
        declare("amplitude", 1.0, describe("commands are amplitude x the signal (2.0: torques of +-2 N m)", 0, 1e9))
        p = self.get_parameter
        self.amplitude = float(p("amplitude").value)
        try:
            self.excitation = Excitation(
                p("seed").value, p("signal").value, p("train_samples").value, p("test_samples").value
            )
        except ValueError as error:
            raise SystemExit(f"robot_controller: {error}") from None
        qos = QoSProfile(depth=p("depth").value, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.publisher = self.create_publisher(
            Float64MultiArray, CMD, qos, qos_overriding_options=QoSOverridingOptions.with_default_policies()
        )
        self.duration = p("duration").value
        self.sent = 0
        self.started: float | None = None
        self.create_timer(1.0 / p("rate_hz").value, self._tick)
        self.get_logger().info(
            f"commanding {self.resolve_topic_name(CMD)} at {p('rate_hz').value} Hz: signal {p('signal').value}, "
            f"seed {p('seed').value}, {self.duration or 'no'} s limit"
        )

    def _tick(self) -> None:
        now = time.monotonic()
        if self.started is None:
            self.started = now
        length = self.excitation.length
        if (self.duration and now - self.started >= self.duration) or (length is not None and self.sent >= length):
            self.get_logger().info(f"done: {self.sent} commands sent")
            raise SystemExit(0)
        u, _ = self.excitation.sample(self.sent)
        self.publisher.publish(Float64MultiArray(data=[self.amplitude * u]))
        self.sent += 1


def main(args: list[str] | None = None) -> int:
    return run_node(RobotController, "robot_controller", args)


if __name__ == "__main__":
    sys.exit(main())
