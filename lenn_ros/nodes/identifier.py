"""identifier: online series-parallel identification of the plant behind u and y_p.

A thin adapter: parameters in (declared from :mod:`lenn_ros.config`), u / y_p in,
paired by publication sequence number (:class:`~lenn_ros.core.pairing.Pairer`), one
:meth:`Identifier.step <lenn_ros.core.structure.Identifier.step>` per pair, and out:

- ``y_hat``: the prediction of y_p(k+1), published as soon as y_p(k) and u(k) are in;
- ``error``: e(k) = y_p(k) - y^(k), once y_p(k) arrives for a predicted step;
- ``nmse``: running NMSE (dB) of the current phase, every ``report_every`` errors;
- ``status``: JSON with counters, phase, NMSE, divergence flag (every ``status_period`` s).

Bad samples (NaN, inf, |value| above ``u_limit`` / ``y_limit``) never reach the
learning rule: rejected (default) or clipped, counted, logged at most once a second.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter as RosParameter
from std_msgs.msg import Float64, Int64, String

from lenn_ros import topics
from lenn_ros.config import NODE_PARAMETERS, Parameter, build_identifier, check_value, identifier_parameters
from lenn_ros.core.metrics import RunningNMSE
from lenn_ros.core.networks import ModelFileError
from lenn_ros.core.pairing import Pairer, U, Y, screen
from lenn_ros.nodes import run_node


def _descriptor(parameter: Parameter) -> ParameterDescriptor:
    text = parameter.description + (f" (one of: {', '.join(parameter.choices)})" if parameter.choices else "")
    descriptor = ParameterDescriptor(description=text, read_only=not parameter.live)
    if parameter.low is not None and not isinstance(parameter.default, bool):
        if isinstance(parameter.default, int):
            descriptor.integer_range = [
                IntegerRange(from_value=int(parameter.low), to_value=int(parameter.high), step=1)
            ]
        else:
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(parameter.low), to_value=float(parameter.high))
            ]
    return descriptor


class IdentifierNode(Node):
    """Learns a LeNN or MLP model of the plant online, sample by sample."""

    def __init__(self) -> None:
        super().__init__("identifier")
        self.declare_parameter(
            "example",
            1,
            ParameterDescriptor(
                description="paper example whose structure and parameters are the defaults (0 = none)",
                read_only=True,
                integer_range=[IntegerRange(from_value=0, to_value=4, step=1)],
            ),
        )
        self.declare_parameter("network", "lenn", ParameterDescriptor(description="lenn or mlp", read_only=True))
        self.declare_parameter(
            "parameters",
            "calibrated",
            ParameterDescriptor(description="alpha/beta preset: calibrated or paper", read_only=True),
        )
        example = self.get_parameter("example").value
        network = self.get_parameter("network").value
        preset = self.get_parameter("parameters").value
        if network not in ("lenn", "mlp"):
            raise SystemExit(f"identifier: network must be 'lenn' or 'mlp', not {network!r}")
        self.table = {p.name: p for p in identifier_parameters(example, network, preset) + NODE_PARAMETERS}
        for parameter in self.table.values():
            self.declare_parameter(parameter.name, parameter.default, _descriptor(parameter))
        values = {name: self.get_parameter(name).value for name in self.table}
        self.values = values
        for name, value in values.items():
            problem = check_value(self.table[name], value)
            if problem:
                raise SystemExit(f"identifier: {problem}")
        try:
            self.identifier = build_identifier(values, network)
        except ValueError as error:
            raise SystemExit(f"identifier: {error}") from None
        self.identifier.health_interval = values["health_interval"]
        self.identifier.divergence_ratio = values["divergence_ratio"]
        if values["weights_in"]:
            try:
                self.identifier.model.load_state(values["weights_in"])
            except ModelFileError as error:
                raise SystemExit(f"identifier: {error}") from None
            self.identifier.mark_healthy()
        self.network = network
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self.pairer = Pairer(window=topics.DATA_DEPTH)
        waits = values["wait_for_y_hat_subscribers"] or values["wait_for_error_subscribers"]
        self._held: list[tuple[int, float, float]] | None = [] if waits else None
        self.test_start: int | None = None
        self.phase_learning: bool | None = None
        self.phase_nmse = RunningNMSE()
        self.errors_since_report = 0
        self.bad_samples = {"nan": 0, "out_of_range": 0, "clipped": 0}
        self._last_warning = 0.0
        self._last_save = time.monotonic()
        qos = topics.data_qos()
        self.y_hat_publisher = self.create_publisher(Float64, topics.Y_HAT, qos)
        self.error_publisher = self.create_publisher(Float64, topics.ERROR, qos)
        self.nmse_publisher = self.create_publisher(Float64, topics.NMSE, qos)
        self.status_publisher = self.create_publisher(String, topics.STATUS, qos)
        self.create_subscription(Float64, topics.U, lambda m, i: self._on_half(U, m, i), qos)
        self.create_subscription(Float64, topics.Y_P, lambda m, i: self._on_half(Y, m, i), qos)
        self.create_subscription(Int64, topics.TEST_START, self._on_test_start, topics.latched_qos())
        self.create_timer(values["status_period"], self._on_timer)
        model = self.identifier.model
        self.get_logger().info(
            f"{network} with {model.n_weights} weights, example preset {example or 'none'}, "
            f"learning {'on' if values['learning'] else 'off'}"
        )

    # -- parameters --------------------------------------------------------------------
    def _check_parameters(self, parameters: list[RosParameter]) -> SetParametersResult:
        for parameter in parameters:
            spec = self.table.get(parameter.name)
            if spec is None:
                continue
            problem = check_value(spec, parameter.value)
            if problem:
                return SetParametersResult(successful=False, reason=problem)
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[RosParameter]) -> None:
        model = self.identifier.model
        for parameter in parameters:
            name, value = parameter.name, parameter.value
            self.values[name] = value
            if name in ("alpha", "beta", "forgetting", "nlms_step") and name in model.get_params():
                model.set_params(**{name: value})
            elif name == "divergence_ratio":
                self.identifier.divergence_ratio = value
            elif name == "learning" and value and self.identifier.diverged:
                self.identifier.mark_healthy()  # the user re-enables learning after a divergence
                self.get_logger().info("learning re-enabled after divergence")
            elif name == "weights_out" and value:
                self._save(value)

    def _value(self, name: str) -> Any:
        """Current value of a parameter, from a cache the post-set callback refreshes.

        rclpy's get_parameter costs microseconds; the per-sample path reads several.
        """
        return self.values[name]

    # -- data --------------------------------------------------------------------------
    def _on_test_start(self, message: Int64) -> None:
        self.test_start = int(message.data)

    def _on_half(self, topic: str, message: Float64, info: dict) -> None:
        index = int(info["publication_sequence_number"])
        limit = self._value("u_limit" if topic == U else "y_limit")
        value, verdict = screen(float(message.data), limit, self._value("out_of_range"))
        if verdict != "ok":
            self.bad_samples[verdict] += 1
            consequence = "clipped to the limit" if verdict == "clipped" else "the pair is skipped, never learnt from"
            self._warn(f"{topic}[{index}] = {message.data!r}: {verdict}; {consequence}")
        restarts = self.pairer.counters["restarts"]
        pairs = self.pairer.add(topic, index, value)
        if self.pairer.counters["restarts"] != restarts:
            self.identifier.restart_stream()
            self._warn("sample indices started over (publisher restart): history reset")
        if self._held is not None:
            self._held.extend(pairs)
            pairs = self._release_held()
        for pair_index, u, y in pairs:
            self._on_pair(pair_index, u, y)

    def _release_held(self) -> list[tuple[int, float, float]]:
        """The pairs held back so far, once the output subscribers have matched."""
        if self._held is None or not self._outputs_matched():
            return []
        pairs, self._held = self._held, None
        return pairs

    def _outputs_matched(self) -> bool:
        """Our outputs are VOLATILE: what is published before a reader matched is lost to it."""
        return self.y_hat_publisher.get_subscription_count() >= self._value(
            "wait_for_y_hat_subscribers"
        ) and self.error_publisher.get_subscription_count() >= self._value("wait_for_error_subscribers")

    def _on_pair(self, index: int, u: float, y: float) -> None:
        if math.isnan(u) or math.isnan(y):
            self.identifier.skip(index)
            return
        learn = self._value("learning") and not (
            self._value("follow_test_start") and self.test_start is not None and index >= self.test_start
        )
        if learn != self.phase_learning:
            self.phase_learning = learn
            self.phase_nmse.reset()
            self.get_logger().info(f"sample {index}: {'training' if learn else 'frozen (test)'} phase")
        result = self.identifier.step(index, u, y, learn)
        if result.event in ("gap", "diverged"):
            self._warn(f"sample {index}: {result.event}; counters {self.identifier.counters}")
        if result.error is not None:
            self.error_publisher.publish(Float64(data=result.error))
            self.phase_nmse.add(y, result.y_hat)
            self.errors_since_report += 1
            if self.errors_since_report >= self._value("report_every"):
                self.errors_since_report = 0
                self.nmse_publisher.publish(Float64(data=self.phase_nmse.nmse_db))
        if result.y_hat_next is not None:
            self.y_hat_publisher.publish(Float64(data=result.y_hat_next))

    def _warn(self, text: str) -> None:
        now = time.monotonic()
        if now - self._last_warning >= 1.0:
            self._last_warning = now
            self.get_logger().warning(text)

    # -- reporting and persistence --------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """Everything a user or a test needs to know about the run so far."""
        return {
            "network": self.network,
            "learning": bool(self.phase_learning) if self.phase_learning is not None else self._value("learning"),
            "diverged": self.identifier.diverged,
            "test_start": self.test_start,
            "phase_samples": self.phase_nmse.count,
            "phase_nmse_db": self.phase_nmse.nmse_db,
            "phase_rmse": self.phase_nmse.rmse,
            "counters": {**self.identifier.counters, **self.pairer.counters, **self.bad_samples},
            "samples_seen": int(getattr(self.identifier.model, "n_samples_seen_", 0)),
        }

    def _on_timer(self) -> None:
        for pair_index, u, y in self._release_held():
            self._on_pair(pair_index, u, y)
        self.status_publisher.publish(String(data=json.dumps(self.status())))
        period = self._value("autosave_period")
        if period > 0 and self._value("weights_out") and time.monotonic() - self._last_save >= period:
            self._save(self._value("weights_out"))

    def _save(self, path: str) -> None:
        try:
            self.identifier.model.save(os.path.expanduser(path))
            self._last_save = time.monotonic()
        except OSError as error:
            self.get_logger().error(f"could not save weights to {path}: {error}")

    def shutdown(self) -> None:
        """Final status line and weights on the way out (SIGINT, SIGTERM or end)."""
        if self._value("weights_out"):
            self._save(self._value("weights_out"))
        print(f"identifier: {json.dumps(self.status())}", file=sys.stderr, flush=True)


def main(args: list[str] | None = None) -> int:
    return run_node(IdentifierNode, "identifier", args)


if __name__ == "__main__":
    sys.exit(main())
