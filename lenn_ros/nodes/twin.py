"""twin: a fitted model run as the plant, on the robot's own topics.

``ros2 run lenn_ros twin --ros-args -p model:=DIR`` (DIR as ``lenn-ros fit -o DIR``
wrote it) subscribes to ``u`` with the type and field the identifier read the command
with, steps the model's free run, and publishes the output on ``y_p`` as the robot
does: the same type, the value where the identifier's ``y_field`` reads it (a
JointState with the joint's name, a Float64, a Float64MultiArray of the channels).
A controller can then be tried against the learnt model on the same topics, with the
same remaps, before the real machine.

Stepping (``step_on``): ``input`` (default) steps once per command message, as the
plant simulator does: on u(k) it publishes y(k) (the output measured as u(k) is
applied, from the inputs up to u(k-1)) with the command's stamp, then applies u(k); a
run driven by a log's inputs publishes exactly ``fit``'s free run. ``timer`` steps every
``sample_period`` s of the model on its own clock with the latest command held (a
driver's loop), waiting, and saying so, until the first one arrives.

The history the run starts from is the operating point at rest unless ``y_initial`` /
``u_initial`` give the last samples before it. ``noise:=true`` adds to each published
value (never to the model's own state) Gaussian noise of the fit's one-step residual
std (``fit.json``), or ``noise_std``. Everything it cannot do (a command it cannot
read, a non-finite one, a model that left its range) is said in one line, at most
every ``WARN_PERIOD`` s per kind, and counted in ``~/status`` (JSON, every second).
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.qos_overriding_options import QoSOverridingOptions
from std_msgs.msg import String

from lenn_ros import topics
from lenn_ros.config import ConfigError, field_extractor, side_channels
from lenn_ros.core.fields import FieldError, compose, has_header, is_vector
from lenn_ros.model import ModelError, load_model
from lenn_ros.nodes import run_node
from lenn_ros.nodes.robot_controller import describe

#: s between two lines about the same kind of trouble (the counts go on in status)
WARN_PERIOD = 5.0
STEP_ON = ("input", "timer")


class Twin(Node):
    """Command in, the model's free run out, on the topics the identifier learnt it from."""

    def __init__(self) -> None:
        super().__init__("twin")
        declare = self.declare_parameter
        declare("model", "", describe("model directory written by lenn-ros fit -o DIR (or its params.yaml)"))
        declare("step_on", "input", describe("input: one step per command message; timer: every sample_period"))
        declare(
            "sample_period", 0.0, describe("step_on timer: s per step (0 = the model's sample_period)", 0.0, 3600.0)
        )
        declare("y_initial", [0.0], describe("outputs before the run, oldest first ([0.0] alone: at rest)"))
        declare("u_initial", [0.0], describe("inputs before the run, oldest first ([0.0] alone: at rest)"))
        declare("noise", False, describe("add Gaussian noise of the fit's one-step residual std to the output"))
        declare("noise_std", 0.0, describe("noise: its std (0 = the fit's one-step residual std)", 0.0, 1e12))
        declare("seed", 0, describe("seed of the noise", 0, 2**31 - 1))
        p = self.get_parameter
        self.step_on = str(p("step_on").value)
        if self.step_on not in STEP_ON:
            raise SystemExit(f"twin: step_on {self.step_on!r}: use one of {', '.join(STEP_ON)}")
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
        self.y_stamped = has_header(self.y_class)
        self.noise_std = self._noise_std(bool(p("noise").value), float(p("noise_std").value))
        self.rng = np.random.default_rng(int(p("seed").value))
        self.counters = {"commands": 0, "published": 0, "unreadable": 0, "refused": 0, "diverged": 0}
        self._last_said: dict[str, float] = {}
        self.latest: np.ndarray | None = None
        options = QoSOverridingOptions.with_default_policies()
        self.publisher = self.create_publisher(
            self.y_class, topics.Y_P, topics.data_qos(), qos_overriding_options=options
        )
        self.create_subscription(
            topics.message_class(str(values["u_type"])),
            topics.U,
            self._on_command,
            topics.data_qos(),
            qos_overriding_options=options,
        )
        self.status = self.create_publisher(String, "~/status", topics.latched_qos())
        self.create_timer(1.0, self._publish_status)
        period = float(p("sample_period").value) or self.model.sample_period
        if self.step_on == "timer":
            if period <= 0:
                raise SystemExit(
                    "twin: step_on timer needs a sample period: the model has none (fitted without one); "
                    "give -p sample_period:=SECONDS"
                )
            self.create_timer(period, self._tick)
        self.get_logger().info(
            f"twin of {self.model.source}: {self.resolve_topic_name(topics.U)} ({values['u_type']} "
            f"{values['u_field']}) -> {self.resolve_topic_name(topics.Y_P)} ({values['y_type']} {self.y_field}), "
            f"stepping on {'each command' if self.step_on == 'input' else f'a {period:g} s timer'}, "
            f"history of {self.model.history} samples from "
            f"{'the parameters' if len(p('y_initial').value) > 1 else 'rest at the operating point'}"
            + (f", noise std {self.noise_std:.4g}" if self.noise_std else "")
        )

    # -- set-up -----------------------------------------------------------------------------------
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

    # -- stepping --------------------------------------------------------------------------------
    def _on_command(self, message: Any) -> None:
        self.counters["commands"] += 1
        try:
            value = np.atleast_1d(np.asarray(self.extract(message), dtype=np.float64))
        except FieldError as error:
            self.counters["unreadable"] += 1
            self._say("unreadable", f"cannot read the command: {error}; the model holds its last input")
            return
        if not np.all(np.isfinite(value)):
            self.counters["refused"] += 1
            self._say("refused", f"command {value.tolist()} is not finite: refused, the model holds its last input")
            return
        if self.step_on == "timer":
            self.latest = value
            return
        self._step(value, getattr(message, "header", None))

    def _tick(self) -> None:
        if self.latest is None:
            self._say("waiting", f"no command yet on {self.resolve_topic_name(topics.U)}: the twin waits for one")
            return
        self._step(self.latest, None)

    def _step(self, value: np.ndarray, header: Any) -> None:
        out = self.stepper.step(value)
        if self.stepper.diverged:
            self.counters["diverged"] += 1
            self._say(
                "diverged",
                f"the model's output left its range after {self.stepper.steps} steps: restarted from its history",
            )
            self.stepper.reset()
            return
        if self.noise_std:
            out = out + self.rng.normal(0.0, self.noise_std, size=out.shape)
        message = self.y_class()
        compose(message, self.y_field, out if is_vector(self.y_field) else out[0], self.y_names)
        if self.y_stamped:
            stamp = getattr(header, "stamp", None)
            message.header.stamp = stamp if stamp is not None else self.get_clock().now().to_msg()
        self.publisher.publish(message)
        self.counters["published"] += 1

    # -- saying what happens ---------------------------------------------------------------------
    def _say(self, kind: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last_said.get(kind, -WARN_PERIOD) >= WARN_PERIOD:
            self._last_said[kind] = now
            count = self.counters.get(kind)
            self.get_logger().warning(text + (f" ({count} so far)" if count else ""))

    def _publish_status(self) -> None:
        self.status.publish(
            String(data=json.dumps({"model": self.model.source, "steps": self.stepper.steps, **self.counters}))
        )


def main(args: list[str] | None = None) -> int:
    return run_node(Twin, "twin", args)


if __name__ == "__main__":
    sys.exit(main())
