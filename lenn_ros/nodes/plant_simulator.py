"""plant_simulator: publishes u(k) and the noisy plant output y_p(k), step by step.

A thin adapter over :mod:`lenn_ros.core` (plants, excitation). At step k it publishes
u(k) on ``u`` and y_p(k) on ``y_p`` (one message each, so their publication sequence
numbers both equal k + 1: the identifier pairs them by it), then applies u(k) plus
noise to the plant. ``test_start`` (latched) tells listeners where training ends.

Stepping: ``rate_hz`` > 0 steps on a wall-clock schedule (catching up in bursts if a
tick is late); ``rate_hz`` = 0 steps as fast as the identifier keeps up: it counts
the identifier's ``y_hat`` messages (as replay does) and never runs more than ``window`` steps ahead,
so the RELIABLE queues (depth topics.DATA_DEPTH) can never overflow.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from std_msgs.msg import Float64, Float64MultiArray, Int64

from lenn_ros import topics
from lenn_ros.core.holding import START_GRACE
from lenn_ros.nodes import TEST_START_UNMATCHED, latched_readers_matched, run_node
from lenn_ros.nodes.channels import Channels
from lenn_ros.paper.examples import get_example
from lenn_ros.paper.expression import ExpressionError
from lenn_ros.paper.plants import MIMO_PLANTS, MimoPlant, Plant, plant_from_expressions
from lenn_ros.paper.signals import SIGNALS, Excitation


def _describe(text: str, low: float | None = None, high: float | None = None, read_only: bool = True):
    descriptor = ParameterDescriptor(description=text, read_only=read_only)
    if isinstance(low, int) and isinstance(high, int):
        descriptor.integer_range = [IntegerRange(from_value=low, to_value=high, step=1)]
    elif low is not None:
        descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high))]
    return descriptor


#: Seconds lockstep waits for an identifier's first y_hat (see PlantSimulator._stall_limit): its
#: hold's grace for the publishers' names, and as long again for its outputs' readers.
FIRST_ANSWER_WAIT = 3 * START_GRACE


class PlantSimulator(Node):
    """Simulates one of the paper's examples (or a user-defined plant) in real time."""

    #: s to wait on the way out until every reader has our samples: a recorder can lag the
    #: lockstep run by many seconds (it writes every topic), and what a writer leaves
    #: unacknowledged when it goes away is lost to the bag
    ack_timeout = 60.0

    def __init__(self) -> None:
        super().__init__("plant_simulator")
        declare = self.declare_parameter
        declare("example", 1, _describe("paper example 1-4; 0 = user-defined plant (model, f, g, a, b)", 0, 4))
        declare("model", 4, _describe("user-defined plant: model class 1-4", 1, 4))
        declare("n", 1, _describe("user-defined plant: past outputs n", 1, 10))
        declare("m", 1, _describe("user-defined plant: past inputs m (m <= n)", 1, 10))
        declare("f", "", _describe("user-defined f over y1..yn (Model 4: then u1..um); arithmetic only"))
        declare("g", "", _describe("user-defined g over u1..um; arithmetic only"))
        declare("a", [0.0], _describe("user-defined Model 1 coefficients a_0..a_{n-1}"))
        declare("b", [0.0], _describe("user-defined Model 2 coefficients b_0..b_{m-1}"))
        declare(
            "mimo_plant",
            "",
            _describe(f"several inputs and outputs: {', '.join(MIMO_PLANTS)} (u, y_p as Float64MultiArray); '' = SISO"),
        )
        declare("signal", "paper", _describe(f"input signal: {', '.join(SIGNALS)} (paper: uniform, then eq. 11)"))
        declare("train_samples", 50_000, _describe("samples of uniform random input before the test", 0, 10**9))
        declare("test_samples", 600, _describe("samples of the eq. 11 test sinusoid", 0, 10**9))
        example = self.get_parameter("example").value
        default_noise = get_example(example).noise_db if example else -20.0
        declare("noise_db", default_noise, _describe("plant-input noise power vs. U[-1,1] input power, dB", -300, 40))
        declare("test_noise", False, _describe("also add the noise during the test phase"))
        declare("seed", 0, _describe("seed of the input and noise streams", 0, 2**31 - 1))
        declare(
            "rate_hz",
            100.0,
            _describe("plant steps per second; 0 = as fast as the identifier keeps up", 0.0, 1.0e6, read_only=False),
        )
        declare(
            "window", 1000, _describe("rate 0: max steps ahead of the identifier's y_hat", 1, topics.DATA_DEPTH // 2)
        )
        declare(
            "stall_timeout",
            2.0,
            _describe(
                "rate 0: seconds without y_hat before the window is re-based (identifier restarted)",
                0.1,
                3600.0,
            ),
        )
        declare("wait_for_subscribers", 1, _describe("subscribers to u and y_p needed before stepping", 0, 100))
        declare("change_step", 0, _describe("tracking scenario: step at which the plant changes (0 = never)", 0, 10**9))
        declare("change_gain", 1.0, _describe("gain of the unknown nonlinear part after change_step", -10.0, 10.0))
        declare(
            "change_input_gain",
            1.0,
            _describe(
                "actuator gain after change_step: the plant receives this x u(k) + noise (0.8: -20 %; any SISO plant)",
                -10.0,
                10.0,
            ),
        )
        declare("exit_when_done", False, _describe("exit after the last test sample"))
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self.plant = self._make_plant()
        p = self.get_parameter
        self.channels = Channels.numbered(self.plant.n_u, self.plant.n_y, isinstance(self.plant, MimoPlant))
        self._make_excitations()
        self.k = 0
        self.input_gain = 1.0  # change_input_gain from change_step on
        self.acknowledged = 0
        self._last_acknowledged = 0
        self._stalled_since = time.monotonic()
        value_type = self.channels.message_type
        self.u_publisher = self.create_publisher(value_type, topics.U, topics.data_qos())
        self.y_publisher = self.create_publisher(value_type, topics.Y_P, topics.data_qos())
        self.test_start_publisher = self.create_publisher(Int64, topics.TEST_START, topics.latched_qos())
        self.y_hat_subscription = self.create_subscription(value_type, topics.Y_HAT, self._on_y_hat, topics.data_qos())
        if self.excitation.test_start is not None:
            self.test_start_publisher.publish(Int64(data=self.excitation.test_start + 1))
        self.started: float | None = None
        self._inputs_ready_at: float | None = None  # when u and y_p had their readers (test_start may lag)
        self.done = False
        self.timer = self.create_timer(self._period(), self._tick)
        self.get_logger().info(
            f"{self.plant.name}: signal {p('signal').value}, {self.excitation.length or 'endless'} samples, "
            f"noise {p('noise_db').value} dB, rate {p('rate_hz').value or 'lockstep'}"
        )

    def _make_excitations(self) -> None:
        """One input stream per plant input (a MIMO plant's own per channel), and the vector layouts."""
        p = self.get_parameter
        self.excitations = [
            Excitation(
                p("seed").value,
                p("signal").value,
                p("train_samples").value,
                p("test_samples").value,
                p("noise_db").value,
                p("test_noise").value,
                channel=channel,
            )
            for channel in range(self.plant.n_u)
        ]
        self.excitation = self.excitations[0]

    def _make_plant(self) -> Plant | MimoPlant:
        p = self.get_parameter
        example = p("example").value
        mimo = p("mimo_plant").value
        if mimo:
            if mimo not in MIMO_PLANTS:
                raise SystemExit(f"plant_simulator: mimo_plant {mimo!r}: choose one of {', '.join(MIMO_PLANTS)}")
            return MIMO_PLANTS[mimo]()
        if example:
            return get_example(example).plant()
        try:
            return plant_from_expressions(
                p("model").value,
                p("n").value,
                p("m").value,
                p("f").value or None,
                p("g").value or None,
                [a for a in p("a").value],
                [b for b in p("b").value],
            )
        except (ExpressionError, ValueError) as error:
            raise SystemExit(f"plant_simulator: user-defined plant: {error}") from None

    def _check_parameters(self, parameters) -> SetParametersResult:
        for parameter in parameters:
            if parameter.name == "rate_hz" and parameter.value < 0:
                return SetParametersResult(successful=False, reason="rate_hz must be >= 0")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters) -> None:
        """A new rate takes effect at once: restart the schedule from the current step."""
        if any(parameter.name == "rate_hz" for parameter in parameters) and hasattr(self, "timer"):
            self.timer.cancel()
            self.destroy_timer(self.timer)
            if self.started is not None:
                rate = self.get_parameter("rate_hz").value
                self.started = time.monotonic() - (self.k / rate if rate > 0 else 0.0)
            self.timer = self.create_timer(self._period(), self._tick)

    def _period(self) -> float:
        rate = self.get_parameter("rate_hz").value
        return 0.001 if rate <= 0 else max(1.0 / rate, 0.001)

    def _on_y_hat(self, _message: Float64 | Float64MultiArray) -> None:
        self.acknowledged += 1

    def _stall_limit(self) -> float:
        """Seconds without a y_hat before lockstep takes the samples in flight as lost (or, when done, exits).

        Until an identifier's first y_hat, at least :data:`FIRST_ANSWER_WAIT`: it holds its first
        pairs, unlearnt, until its outputs' readers match and the graph names who publishes u and
        y_p, which under load takes longer than ``stall_timeout`` (a 500-sample launch in CI ended
        with every pair held). Only while some node publishes y_hat: with none, nothing will answer.
        """
        limit = self.get_parameter("stall_timeout").value
        if self.acknowledged == 0 and self.y_hat_subscription.get_publisher_count() > 0:
            return max(limit, FIRST_ANSWER_WAIT)
        return limit

    def _ready(self) -> bool:
        """The data topics are VOLATILE: a reader that has not matched yet would miss sample 1.

        With a test phase, every test_start reader has its index too: one that gets it after
        that sample has learnt from test samples. That wait is bounded (``stall_timeout``)
        and said when it runs out, for a reader that never matches.
        """
        needed = self.get_parameter("wait_for_subscribers").value
        if min(self.u_publisher.get_subscription_count(), self.y_publisher.get_subscription_count()) < needed:
            return False
        if self.excitation.test_start is None or not needed:
            return True
        if latched_readers_matched(self, self.test_start_publisher, topics.U, needed):
            return True
        now = time.monotonic()
        self._inputs_ready_at = self._inputs_ready_at or now
        if now - self._inputs_ready_at < self.get_parameter("stall_timeout").value:
            return False
        self.get_logger().warning(TEST_START_UNMATCHED)
        return True

    def _tick(self) -> None:
        if self.done:
            return
        if self.started is None:
            if not self._ready():
                return
            self.started = time.monotonic()
        rate = self.get_parameter("rate_hz").value
        if rate > 0:
            due = int((time.monotonic() - self.started) * rate) + 1 - self.k
            due = min(due, self.get_parameter("window").value)
        else:
            due = self.get_parameter("window").value - (self.k - self.acknowledged)
            if due > 0 or self.acknowledged != self._last_acknowledged:
                self._last_acknowledged, self._stalled_since = self.acknowledged, time.monotonic()
            elif time.monotonic() - self._stalled_since > (limit := self._stall_limit()):
                self.get_logger().warning(
                    f"no y_hat for {limit:g} s at step {self.k}: "
                    "the samples in flight are taken as lost and stepping resumes"
                )
                self.acknowledged = self.k
                self._stalled_since = time.monotonic()
        for _ in range(max(due, 0)):
            if not self._step():
                self._finish()
                return

    def _step(self) -> bool:
        length = self.excitation.length
        if length is not None and self.k >= length:
            return False
        if self.k and self.k == self.get_parameter("change_step").value:
            self._change_plant()
        drawn = [excitation.sample(self.k) for excitation in self.excitations]
        u = np.array([value for value, _ in drawn])
        noise = np.array([value for _, value in drawn])
        self.u_publisher.publish(self.channels.message(u, "u"))
        self.y_publisher.publish(self.channels.message(np.ravel(self.plant.output), "y"))
        try:
            self.plant.step(self.channels.value(self.input_gain * u + noise))
        except ExpressionError as error:
            # A formula can pass every check and still fail at some state (u1/y1 at rest). Raised
            # from this timer callback it would be a traceback; run_node prints this one line, exit 2.
            raise SystemExit(f"plant_simulator: {self.plant.name} plant failed at step {self.k}: {error}") from None
        self.k += 1
        return True

    def _change_plant(self) -> None:
        """Tracking scenario: the unknown part's gain jumps, or the actuator's; the plant's state carries over."""
        input_gain = self.get_parameter("change_input_gain").value
        if input_gain != 1.0:
            self.input_gain = input_gain
            self.get_logger().info(
                f"step {self.k}: plant changed (actuator gain x{input_gain:g}: it now receives {input_gain:g} u "
                "+ noise)"
            )
        if self.get_parameter("change_gain").value == 1.0:
            return
        example = self.get_parameter("example").value
        if not example or self.get_parameter("mimo_plant").value:
            self.get_logger().warning("change_gain applies to the paper's examples only; ignored")
            return
        changed = get_example(example).plant(gain=self.get_parameter("change_gain").value)
        changed.y_past, changed.u_past = self.plant.y_past, self.plant.u_past
        self.plant = changed
        self.get_logger().info(f"step {self.k}: plant changed (gain {self.get_parameter('change_gain').value})")

    def _finish(self) -> None:
        self.done = True
        self.get_logger().info(f"done: published {self.k} samples of u and y_p")
        if self.get_parameter("exit_when_done").value:
            # Lockstep: leave once every step has its y_hat (the run's data is consumed), so that whoever
            # waits for this process may stop the identifier at once; else after stall_timeout s without
            # one (an identifier's first steps, until its regressor is complete, have none). Not after
            # a moment's quiet: a loaded identifier can pause longer than that with a window's backlog
            # still queued, and stopped then it leaves what its exit budget cannot take unlearnt (3-10
            # of the last y_p in full test runs). At a rate: once y_hat has been quiet for 0.5 s.
            self._quiet_since = (time.monotonic(), self.acknowledged)
            self.create_timer(0.05, self._exit_when_quiet)

    def _exit_when_quiet(self) -> None:
        since, count = self._quiet_since
        now = time.monotonic()
        lockstep = self.get_parameter("rate_hz").value <= 0  # (at a rate, y_hat need not answer every step)
        if lockstep and self.acknowledged >= self.k:
            raise SystemExit(0)
        if self.acknowledged != count:
            self._quiet_since = (now, self.acknowledged)
        elif now - since >= (self._stall_limit() if lockstep else 0.5):
            if lockstep and self.acknowledged:
                self.get_logger().info(
                    f"exiting: {self.k - self.acknowledged} of {self.k} steps had no y_hat after {now - since:.1f} s "
                    "without one (an identifier's first steps have none, until its regressor is complete; "
                    "more means it lost some)"
                )
            elif lockstep and self.y_hat_subscription.get_publisher_count() > 0:
                self.get_logger().warning(
                    f"exiting: none of {self.k} steps had a y_hat within {now - since:.1f} s: the identifier "
                    "still holds them (its 'pairs held' line says what for)"
                )
            raise SystemExit(0)


def main(args: list[str] | None = None) -> int:
    return run_node(PlantSimulator, "plant_simulator", args)


if __name__ == "__main__":
    sys.exit(main())
