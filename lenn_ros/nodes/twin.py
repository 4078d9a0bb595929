"""twin: a fitted model run as the plant, on the robot's own topics.

``ros2 run lenn_ros twin --ros-args -p model:=DIR`` (DIR as ``lenn-ros fit -o DIR``
wrote it) subscribes to ``u`` with the type and field the identifier read the command
with, steps the model's free run, and publishes the output on ``y_p`` as the robot
does: the same type, the value where the identifier's ``y_field`` reads it (a
JointState with the joint's name, a Float64, a Float64MultiArray of the channels).
A controller can then be tried against the learnt model on the same topics, with the
same remaps, before the real machine.

Stepping (``step_on``): ``auto`` (default) steps on a timer at the model's
``sample_period`` when it has one (a plant runs on its own clock, whatever the
controller's rate: a 50 Hz controller meets a 100 Hz plant as it would the real one),
else on each command. ``timer`` steps every ``sample_period`` s (the parameter, else the
model's) with the latest command held, waiting until the first one arrives. ``input``
steps once per command message, as the plant simulator does: on u(k) it publishes y(k)
(the output measured as u(k) is applied, from the inputs up to u(k-1)) with the
command's stamp, then applies u(k); a run driven by a log's inputs publishes exactly
``fit``'s free run.

The command is subscribed BEST_EFFORT, as the identifier subscribes its inputs: it
matches every publisher (a ros2_control controller publishes BEST_EFFORT), and
``qos_overrides.<topic>.subscription.*`` changes it (RELIABLE to lose nothing of a
RELIABLE publisher's burst). The history the run starts from is the operating point at
rest unless ``y_initial`` / ``u_initial`` give the last samples before it.
``noise:=true`` adds to each published value (never to the model's own state) Gaussian
noise of the fit's one-step residual std (``fit.json``), or ``noise_std``.

Everything it cannot do is said in one line naming the topic as remapped, at
most every ``WARN_PERIOD`` s per kind, and counted in ``~/status`` (JSON, every second):
a command it cannot read or that is not finite, a model that left its range, a publisher
whose QoS cannot match (with the override that fixes it), no command at all
``NO_COMMAND_AFTER`` s after the start (with the publishers matched), and matched
publishers that stop delivering (the identifier's input watchdog, ``input_timeout``:
said, counted, resubscribed).
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import numpy as np
from rclpy.event_handler import QoSRequestedIncompatibleQoSInfo, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSPolicyKind, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.subscription import Subscription
from rclpy.time import Time
from std_msgs.msg import String

from lenn_ros import topics
from lenn_ros.config import NODE_PARAMETERS, ConfigError, field_extractor, side_channels
from lenn_ros.core.fields import FieldError, compose, has_header, is_vector
from lenn_ros.core.watchdog import InputWatchdog
from lenn_ros.model import ModelError, load_model
from lenn_ros.nodes import run_node, watched_publishers
from lenn_ros.nodes.node_parameters import QOS_OVERRIDES
from lenn_ros.nodes.robot_controller import describe

#: s between two lines about the same kind of trouble (the counts go on in status)
WARN_PERIOD = 5.0
#: s after the start without a command that make the one line about it (discovery takes a moment)
NO_COMMAND_AFTER = 3.0
#: s the timer's steps may lag the model's clock and be caught up (more: a machine suspended, the clock jumps)
MAX_BEHIND = 1.0
STEP_ON = ("auto", "input", "timer")
#: the identifier's entry: the same meaning, default and range
INPUT_TIMEOUT = next(entry for entry in NODE_PARAMETERS if entry.name == "input_timeout")
#: what a subscription's override can change to meet a publisher it cannot match (other policies: the publisher's)
QOS_FIX = {QoSPolicyKind.RELIABILITY: "reliability:=best_effort", QoSPolicyKind.DURABILITY: "durability:=volatile"}


class Twin(Node):
    """Command in, the model's free run out, on the topics the identifier learnt it from."""

    def __init__(self) -> None:
        super().__init__("twin")
        self._declare()
        p = self.get_parameter
        if not p("model").value:
            raise SystemExit("twin: no model: give -p model:=DIR, a directory lenn-ros fit -o DIR wrote")
        try:
            self.model = load_model(str(p("model").value))
            values = self.model.values
            if any(len(side_channels(values, side)[2]) > 1 for side in ("u", "y")):
                raise ConfigError("a model read from several u or y topics: the twin takes one topic per side")
            self.extract = field_extractor(values, "u")
            self.stepper = self.model.stepper(
                self._history(p("y_initial").value, self.model.n_y), self._history(p("u_initial").value, self.model.n_u)
            )
        except (ModelError, ConfigError, FieldError) as error:
            raise SystemExit(f"twin: {error}") from None
        self.y_names = [name for name in values.get("y_names", [""]) if name]
        self.y_field = str(values["y_field"])
        self.y_class = topics.message_class(str(values["y_type"]))
        self.u_class = topics.message_class(str(values["u_type"]))
        self.y_stamped = has_header(self.y_class)
        self.noise_std = self._noise_std(bool(p("noise").value), float(p("noise_std").value))
        self.rng = np.random.default_rng(int(p("seed").value))
        period, why = self._stepping()
        self.counters = {
            "commands": 0, "published": 0, "unreadable": 0, "refused": 0, "diverged": 0,
            "qos_incompatible": 0, "no_command": 0, "skipped": 0,
        }  # fmt: skip
        self._last_said: dict[str, float] = {}
        self.latest: np.ndarray | None = None
        options = QoSOverridingOptions.with_default_policies()
        self.publisher = self.create_publisher(
            self.y_class, topics.Y_P, topics.data_qos(), qos_overriding_options=options
        )
        # as remapped: what the user knows the topics by
        self.u_name, self.y_name = self.resolve_topic_name(topics.U), self.resolve_topic_name(topics.Y_P)
        self.subscription = self._subscribe()
        timeout = float(p(INPUT_TIMEOUT.name).value)
        self.watchdog = InputWatchdog(timeout=timeout) if timeout else None
        self.status = self.create_publisher(String, "~/status", topics.latched_qos())
        self.started = time.monotonic()
        self.create_timer(1.0, self._publish_status)
        stepping = "each command" if self.step_on == "input" else f"a {period:g} s timer, the latest command held"
        self.get_logger().info(
            f"twin of {self.model.source}: {self.u_name} ({values['u_type']} {values['u_field']}, "
            f"{self.subscription.qos_profile.reliability.name}) -> {self.y_name} ({values['y_type']} {self.y_field}), "
            f"stepping on {stepping} ({why}), history of {self.model.history} samples from "
            f"{'the parameters' if len(p('y_initial').value) > 1 else 'rest at the operating point'}"
            + (f", noise std {self.noise_std:.4g}" if self.noise_std else "")
        )

    # -- set-up -----------------------------------------------------------------------------------
    def _declare(self) -> None:
        """The parameters, read-only (a twin is restarted to change them)."""
        declare = self.declare_parameter
        declare("model", "", describe("model directory written by lenn-ros fit -o DIR (or its params.yaml)"))
        steps = "auto: timer if the model has a sample_period, else input; input: one step per command; timer"
        declare("step_on", "auto", describe(f"{steps}: every sample_period, the latest command held"))
        declare("sample_period", 0.0, describe("timer / auto: s per step (0 = the model's sample_period)", 0.0, 3600.0))
        declare("y_initial", [0.0], describe("outputs before the run, oldest first ([0.0] alone: at rest)"))
        declare("u_initial", [0.0], describe("inputs before the run, oldest first ([0.0] alone: at rest)"))
        declare("noise", False, describe("add Gaussian noise of the fit's one-step residual std to the output"))
        declare("noise_std", 0.0, describe("noise: its std (0 = the fit's one-step residual std)", 0.0, 1e12))
        declare("seed", 0, describe("seed of the noise", 0, 2**31 - 1))
        timeout = INPUT_TIMEOUT
        declare(timeout.name, timeout.default, describe(timeout.description, timeout.low, timeout.high))

    def _stepping(self) -> tuple[float, str]:
        """``step_on`` resolved (auto: timer when there is a period) and its timer made; returns the period and why,
        for the start line. A plant runs on its own clock: stepped per command, a 50 Hz controller would meet a
        model of 0.01 s sampling running at half its speed."""
        given = float(self.get_parameter("sample_period").value)
        period = given or self.model.sample_period
        self.step_on = str(self.get_parameter("step_on").value)
        if self.step_on not in STEP_ON:
            raise SystemExit(f"twin: step_on {self.step_on!r}: use one of {', '.join(STEP_ON)}")
        why = f"step_on {self.step_on}"
        if self.step_on == "auto":
            source = "sample_period" if given else "the model's sample period"
            self.step_on, why = ("timer", source) if period > 0 else ("input", "the model has no sample period")
        if self.step_on == "timer":
            if period <= 0:
                raise SystemExit(
                    "twin: step_on timer needs a sample period: the model has none (fitted without one); "
                    "give -p sample_period:=SECONDS"
                )
            self.period, self.next_step = period, None
            self.create_timer(period, self._tick)
        return period, why

    def _history(self, given: Any, channels: int) -> np.ndarray | None:
        """A history parameter as (samples, channels), or None for the default [0.0] (at rest)."""
        values = [float(v) for v in given]
        if values in ([], [0.0]):
            return None
        if len(values) % channels:
            raise ConfigError(f"a history of {len(values)} values for {channels} channels: give whole samples")
        return np.array(values).reshape(-1, channels)

    def _noise_std(self, noise: bool, given: float) -> float:
        if not noise:
            return 0.0
        if given > 0:
            return given
        std = self.model.intervals().get("one_step", {}).get("std")
        if not std:
            raise SystemExit(
                "twin: noise:=true, but the model directory has no fit report (fit.json) with the residual std: "
                "give -p noise_std:=STD"
            )
        return float(std)

    def _subscribe(self) -> Subscription:
        """The command's subscription: BEST_EFFORT, which matches every publisher (a RELIABLE subscription hears
        nothing from a BEST_EFFORT controller), overridable by parameters, and a QoS mismatch said by us: rclpy's
        own warning names the topic before remapping and no fix."""
        return self.create_subscription(
            self.u_class,
            topics.U,
            self._on_command,
            QoSProfile(depth=topics.DATA_DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT),
            qos_overriding_options=QOS_OVERRIDES,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible_qos),
        )

    # -- stepping --------------------------------------------------------------------------------
    def _on_command(self, message: Any) -> None:
        self.counters["commands"] += 1
        if self.watchdog is not None:
            self.watchdog.arrived(self.u_name, time.monotonic())
        try:
            value = np.atleast_1d(np.asarray(self.extract(message), dtype=np.float64))
        except FieldError as error:
            self.counters["unreadable"] += 1
            self._say(
                "unreadable", f"cannot read the command on {self.u_name}: {error}; the model holds its last input"
            )
            return
        if not np.all(np.isfinite(value)):
            self.counters["refused"] += 1
            self._say(
                "refused",
                f"command {value.tolist()} on {self.u_name} is not finite: refused, the model holds its last input",
            )
            return
        if self.step_on == "timer":
            self.latest = value
            return
        self._step(value, getattr(getattr(message, "header", None), "stamp", None))

    def _tick(self) -> None:
        """The steps due on the model's clock, the latest command held: a tick the busy machine delayed is caught up
        (a plant does not wait; without it a loaded 2-core machine ran the model at 45 % of its speed), each output
        stamped at its sample's time; over ``MAX_BEHIND`` s behind, the clock jumps instead, said and counted."""
        if self.latest is None:  # before the first command: nothing to hold (said once, by _check_commands)
            return
        now = time.monotonic()
        # int() truncates: a tick up to one period early steps (rcl's schedule and this one differ by the first
        # tick's delay), one earlier than that waits; the steps never run ahead of the clock by more than one
        due = 1 if self.next_step is None else int((now - self.next_step) / self.period) + 1
        if due > MAX_BEHIND / self.period:
            self.counters["skipped"] += due - 1
            self._say(
                "skipped", f"{self.y_name} fell {due - 1} steps behind the twin's {self.period:g} s clock: skipped them"
            )
            due, self.next_step = 1, None
        if due < 1:
            return
        self.next_step = (now if self.next_step is None else self.next_step) + due * self.period
        clock = self.get_clock().now().nanoseconds
        for k in range(due, 0, -1):
            self._step(self.latest, Time(nanoseconds=clock - round((k - 1) * self.period * 1e9)).to_msg())

    def _step(self, value: np.ndarray, stamp: Any) -> None:
        """One step of the model, its output published (stamped ``stamp``, else now)."""
        out = self.stepper.step(value)
        if self.stepper.diverged:
            self.counters["diverged"] += 1
            self._say(
                "diverged",
                f"the model's output on {self.y_name} left its range after {self.stepper.steps} steps: restarted from "
                "its history",
            )
            self.stepper.reset()
            return
        if self.noise_std:
            out = out + self.rng.normal(0.0, self.noise_std, size=out.shape)
        message = self.y_class()
        compose(message, self.y_field, out if is_vector(self.y_field) else out[0], self.y_names)
        if self.y_stamped:
            message.header.stamp = stamp if stamp is not None else self.get_clock().now().to_msg()
        self.publisher.publish(message)
        self.counters["published"] += 1

    # -- the command's graph: a QoS that cannot match, no command, a watchdog --------------------
    def _on_incompatible_qos(self, event: QoSRequestedIncompatibleQoSInfo) -> None:
        self.counters["qos_incompatible"] += max(1, event.total_count_change)
        try:
            policy = QoSPolicyKind(event.last_policy_kind)
        except ValueError:
            policy = QoSPolicyKind.INVALID
        fix = QOS_FIX.get(policy)
        self._say(
            "qos_incompatible",
            f"a publisher on {self.u_name} offers a QoS this subscription cannot match ({policy.name}), so nothing "
            "arrives from it: "
            + (f"add -p qos_overrides.{self.u_name}.subscription.{fix}" if fix else "change the publisher's QoS"),
        )

    def _check_commands(self) -> None:
        """Once, NO_COMMAND_AFTER s after the start without a command: whether anything is there to send one."""
        if self.counters["commands"] or self.counters["no_command"]:
            return
        quiet = time.monotonic() - self.started
        if quiet < NO_COMMAND_AFTER:
            return
        self.counters["no_command"] = 1
        matched, present = self.subscription.get_publisher_count(), self.count_publishers(self.u_name)
        if matched:
            why = f"{matched} publisher(s) matched but none sent anything"
        elif present:
            why = f"{present} publisher(s) on it, none matched (their QoS or type cannot match this subscription)"
        else:
            why = "no publisher on it: start the controller, or remap the twin's u to its topic (-r u:=/its/command)"
        self.get_logger().warning(f"no command on {self.u_name} in {quiet:.0f} s: {why}; the twin waits")

    def _watch(self) -> None:
        """The identifier's input watchdog (core.watchdog): matched publishers that deliver nothing are said with
        their names, counted and resubscribed (a reader the middleware no longer serves is mended by a new one)."""
        if self.watchdog is None:
            return
        publishers = watched_publishers(self, [self.subscription], self.watchdog)
        for event in self.watchdog.check(time.monotonic(), publishers):
            if event.kind == "resumed":
                self.get_logger().info(event.text)
            else:
                self.get_logger().warning(event.text)
            if event.resubscribe:
                self.destroy_subscription(self.subscription)
                self.subscription = self._subscribe()

    # -- saying what happens ---------------------------------------------------------------------
    def _say(self, kind: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last_said.get(kind, -WARN_PERIOD) >= WARN_PERIOD:
            self._last_said[kind] = now
            count = self.counters.get(kind)
            self.get_logger().warning(text + (f" ({count} so far)" if count else ""))

    def _publish_status(self) -> None:
        self._check_commands()
        self._watch()
        watchdog = self.watchdog.counters if self.watchdog is not None else {}
        status = {"model": self.model.source, "step_on": self.step_on, "steps": self.stepper.steps,
                  "listeners": self.publisher.get_subscription_count()}  # fmt: skip
        self.status.publish(String(data=json.dumps({**status, **self.counters, **watchdog})))


def main(args: list[str] | None = None) -> int:
    return run_node(Twin, "twin", args)


if __name__ == "__main__":
    sys.exit(main())
