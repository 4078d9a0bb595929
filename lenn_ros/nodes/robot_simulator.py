"""robot_simulator: a robot's driver around a paper plant, on its own clock.

What an identifier meets on a real robot, in one process (the commands come from
another one, e.g. ``robot_controller``):
- subscribes to ``cmd`` (``std_msgs/msg/Float64MultiArray``, value ``data[command_index]``,
  BEST_EFFORT) and holds the latest command received (zero-order hold, by receive time);
- steps the plant of paper example ``example`` every 1 / ``rate_hz`` s of its own clock,
  starting ``start_delay`` s after it starts; step k at t_k applies the latest command
  received at or before t_k. Step k is computed once a command received after t_k has
  been taken (so none received before t_k can still wait in the executor's queue), or
  ``command_wait`` s after t_k (a silent controller: the last command holds). A late
  timer catches up with the steps it owes, each with the command current at its own
  t_k, so the plant is sampled exactly every period;
- publishes ``joint_states`` (``sensor_msgs/msg/JointState``, name ``[joint_name]``,
  ``position[0]`` = y_p(k), ``header.stamp`` = t_k) ``latency`` + U[0, ``jitter``] s after
  the step, in order; ``loss`` of the measurements are never published; optional
  plant-input noise (``noise_db``) and measurement noise (``measurement_noise``);
- optional timing faults of a real driver: ``stamp_jitter`` (its loop wakes off time:
  step k runs, takes its command and is stamped at t_k + U[-stamp_jitter, stamp_jitter]),
  ``stamp_offset`` (its stamps are on a clock that far ahead of the receive clock:
  another machine's, unsynchronised);
- stops after ``steps`` steps or ``duration`` s (0 and 0: until stopped) and writes the
  plant's own series to ``log`` (.npz: stamp_ns, u applied and when it was received,
  noise, y, y_measured, published; see :class:`~lenn_ros.paper.robot.RobotLog`): the lockstep reference.

QoS of both topics can be set by parameters (``qos_overrides./cmd.subscription.*``,
``qos_overrides./joint_states.publisher.*``). Times are the ROS clock's.
"""

from __future__ import annotations

import sys
from collections import deque

from builtin_interfaces.msg import Time as TimeMsg
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from lenn_ros.nodes import run_node
from lenn_ros.nodes.robot_controller import CMD, describe
from lenn_ros.paper.examples import get_example
from lenn_ros.paper.physical import PLANT_CHANGES, change_plant, physical_plant
from lenn_ros.paper.robot import CommandHold, SimulatedRobot

#: Default topic of the measurements (relative: remap with -r joint_states:=/robot/joint_states).
JOINT_STATES = "joint_states"


class RobotSimulator(Node):
    """The driver: command in, plant stepped on schedule, stamped measurements out."""

    def __init__(self) -> None:
        super().__init__("robot_simulator")
        declare = self.declare_parameter
        declare("example", 1, describe("paper example 1-4 whose plant the robot is", 1, 4))
        declare(
            "plant",
            "example",
            describe("the robot's plant: example (the paper's, above), friction_joint (radians) or servo_axis (a belt "
                     "drive under its PD loop: u the position setpoint, rad)"),
        )  # fmt: skip
        example = get_example(self.get_parameter("example").value)
        declare("rate_hz", 100.0, describe("plant steps per second", 0.1, 10_000.0))
        declare("start_delay", 2.0, describe("seconds after start before the first step", 0.0, 3600.0))
        declare("steps", 0, describe("stop after this many steps (0 = no limit)", 0, 10**9))
        declare("duration", 0.0, describe("stop after this many seconds of stepping (0 = no limit)", 0.0, 1e9))
        declare("loss", 0.02, describe("probability that a measurement is never published", 0.0, 0.99))
        declare("latency", 0.005, describe("seconds from a step to its measurement's publication", 0.0, 10.0))
        declare("jitter", 0.004, describe("extra publication delay, uniform in [0, jitter] s", 0.0, 10.0))
        declare(
            "stamp_jitter",
            0.0,
            describe("driver loop jitter: step k runs and is stamped at t_k + U[-j, j] s (< half a period)", 0.0, 10.0),
        )
        declare("stamp_offset", 0.0, describe("stamps on a clock this far ahead of the receive clock, s", -1e6, 1e6))
        declare("noise_db", example.noise_db, describe("plant-input noise vs. U[-1,1] power, dB", -300.0, 40.0))
        declare("measurement_noise", 0.0, describe("standard deviation added to the published y_p", 0.0, 1e6))
        declare("seed", 0, describe("seed of the noise, loss and jitter streams", 0, 2**31 - 1))
        declare("joint_name", "joint1", describe("the joint's name in JointState.name"))
        declare("command_index", 0, describe("element of the command's data that drives the plant", 0, 10_000))
        declare("log", "", describe("write the plant's own series here at exit (.npz; '' = none)"))
        declare("depth", 100, describe("history depth of both topics", 1, 100_000))
        declare(
            "command_wait", 0.05, describe("seconds after t_k to wait for a later command before stepping", 0.0, 10.0)
        )
        p = self.get_parameter
        rate = p("rate_hz").value
        self.period_ns = round(1e9 / rate)
        limits = [n for n in (p("steps").value, round(p("duration").value * rate)) if n > 0]
        self.max_steps = min(limits) if limits else None
        try:
            plant = example.plant() if p("plant").value == "example" else physical_plant(p("plant").value, 1.0 / rate)
        except ValueError as error:
            raise SystemExit(f"robot_simulator: {error}") from None
        self._check_change(p("plant").value)
        self.robot = SimulatedRobot(
            plant,
            self.period_ns,
            input_noise_db=p("noise_db").value,
            measurement_noise=p("measurement_noise").value,
            loss=p("loss").value,
            latency_s=p("latency").value,
            jitter_s=p("jitter").value,
            seed=p("seed").value,
            example=example.number if p("plant").value == "example" else 0,
            stamp_jitter_s=p("stamp_jitter").value,
            stamp_offset_s=p("stamp_offset").value,
        )
        self.hold, self.bad_commands = CommandHold(), 0
        self.command_index, self.joint_name = p("command_index").value, p("joint_name").value
        self.latency_ns, self.command_wait_ns = round(p("latency").value * 1e9), round(p("command_wait").value * 1e9)
        depth, overriding = p("depth").value, QoSOverridingOptions.with_default_policies
        self.create_subscription(
            Float64MultiArray,
            CMD,
            self._on_command,
            QoSProfile(depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT),
            qos_overriding_options=overriding(),
        )
        self.publisher = self.create_publisher(
            JointState,
            JOINT_STATES,
            QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE),
            qos_overriding_options=overriding(),
        )
        self._created_ns = self._now_ns()
        self._first_ns: int | None = None
        self.k = 0
        self._t_k: int | None = None  # when step k runs (drawn once: the loop's jitter)
        self.pending: deque[tuple[int, JointState]] = deque()
        self.create_timer(max(self.period_ns * 0.5e-9, 0.001), self._tick)
        described = example.description if p("plant").value == "example" else plant.name
        self.get_logger().info(
            f"{described}: {rate} Hz from {p('start_delay').value} s, "
            f"{self.max_steps or 'unlimited'} steps, loss {p('loss').value}, "
            f"publication delay {p('latency').value}+U[0,{p('jitter').value}] s, stamp jitter "
            f"±{p('stamp_jitter').value} s, stamp offset {p('stamp_offset').value} s; "
            f"{self.resolve_topic_name(CMD)} -> {self.resolve_topic_name(JOINT_STATES)}"
        )

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _on_command(self, message: Float64MultiArray, info: dict) -> None:
        if len(message.data) <= self.command_index:
            self.bad_commands += 1
            self.get_logger().warning(
                f"a command with {len(message.data)} values has no data[{self.command_index}]: ignored "
                f"({self.bad_commands} so far)",
                throttle_duration_sec=5.0,
            )
            return
        received = info.get("received_timestamp") if not self.get_parameter("use_sim_time").value else None
        if self.hold.received == 0:
            self.get_logger().info("first command received")
        self.hold.add(int(received) if received else self._now_ns(), float(message.data[self.command_index]))
        if self._first_ns is not None:
            self._advance(self._now_ns())

    def _tick(self) -> None:
        now = self._now_ns()
        if self._first_ns is None:
            if now - self._created_ns < self.get_parameter("start_delay").value * 1e9:
                return
            self._first_ns = now
            if self.hold.received == 0:
                self.get_logger().warning(f"no command on {self.resolve_topic_name(CMD)} yet: holding 0")
        self._advance(now)
        if self._finished() and not self.pending:
            log = self.robot.log
            self.get_logger().info(
                f"done: {len(log)} steps, {sum(log.published)} measurements published, "
                f"{len(log) - sum(log.published)} lost on purpose, {self.hold.received} commands received"
            )
            raise SystemExit(0)

    def _advance(self, now: int) -> None:
        """Every step that is due and whose command is settled; every measurement that is due."""
        while not self._finished():
            if self._t_k is None:
                self._t_k = self.robot.step_time_ns(self._first_ns + self.k * self.period_ns)
            t_k = self._t_k
            if now < t_k + self.latency_ns:
                break
            if self.hold.latest_ns <= t_k and now < t_k + self.command_wait_ns:
                break  # a command received before t_k may still be queued: wait for a later one
            self._step(t_k)
            self._t_k = None
        while self.pending and self.pending[0][0] <= now:
            self.publisher.publish(self.pending.popleft()[1])

    def _finished(self) -> bool:
        return self.max_steps is not None and self.k >= self.max_steps

    def _step(self, stamp_ns: int) -> None:
        if self.change_step and self.k == self.change_step:
            self._change_plant()
        y, published, delay = self.robot.step(stamp_ns, *self.hold.at(stamp_ns))
        y += self.offset
        self.k += 1
        if not published:
            return
        message = JointState(name=[self.joint_name], position=[y])
        header_ns = self.robot.header_stamp_ns(stamp_ns)
        message.header.stamp = TimeMsg(sec=header_ns // 10**9, nanosec=header_ns % 10**9)
        self.pending.append((stamp_ns + round(delay * 1e9), message))

    def _declare_change(self) -> None:
        """The plant-change options: a gain, friction, payload or offset change at a step (the alarm's demo)."""
        declare = self.declare_parameter
        declare("change_step", 0, describe("step at which the plant changes (0 = never; physical plants)", 0, 10**9))
        declare("change_kind", "gain", describe("what changes at change_step: gain, friction, payload or offset"))
        size = "relative size of the change (-0.2: 20 % less; offset: added to y, in the output's units)"
        declare("change_size", -0.2, describe(size, -10.0, 10.0))

    def _check_change(self, plant: str) -> None:
        self._declare_change()
        p = self.get_parameter
        self.change_step, self.change_kind = p("change_step").value, p("change_kind").value
        self.change_size, self.offset = p("change_size").value, 0.0
        if self.change_step and (plant == "example" or self.change_kind not in PLANT_CHANGES):
            raise SystemExit(
                f"robot_simulator: cannot change the plant: change_kind {self.change_kind!r} (known: "
                f"{', '.join(PLANT_CHANGES)}) needs a physical plant (plant:=friction_joint or servo_axis)"
            )

    def _change_plant(self) -> None:
        """The plant changes under the model, as a robot's does (a payload picked up, a belt worn): said once."""
        change_plant(self.robot.plant, self.change_kind, self.change_size)
        if self.change_kind == "offset":
            self.offset = self.change_size
        self.get_logger().info(f"step {self.k}: plant changed: {self.change_kind} {self.change_size:+g}")

    def shutdown(self) -> None:
        """Called by run_node on the way out (end, SIGINT or SIGTERM): the lockstep series."""
        path = self.get_parameter("log").value
        if path:
            written = self.robot.log.save(path)
            self.get_logger().info(f"log: {len(self.robot.log)} steps written to {written}")


def main(args: list[str] | None = None) -> int:
    return run_node(RobotSimulator, "robot_simulator", args)


if __name__ == "__main__":
    sys.exit(main())
