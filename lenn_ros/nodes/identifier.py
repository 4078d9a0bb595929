"""identifier: online series-parallel identification of the plant behind u and y_p.

A thin adapter around :class:`lenn_ros.session.Session`: parameters in (declared from
:mod:`lenn_ros.config`, :mod:`~lenn_ros.nodes.node_parameters`), u / y_p in (any message type, one
value or several channels each through a field path, :mod:`~lenn_ros.nodes.identifier_inputs`),
samples formed by the chosen pairing mode, one model step per sample, and out
(:mod:`~lenn_ros.nodes.identifier_outputs`):

- ``y_hat``: the prediction of y_p(k+1), as soon as sample k is complete (Float64, or one
  Float64MultiArray element per output channel);
- ``error``: e(k) = y_p(k) - y^(k);
- ``y_hat_stamped`` / ``error_stamped``: y^(k) and e(k) as JointState stamped with the
  time of sample k, to overlay on y_p in Foxglove / PlotJuggler without a shift;
- ``y_hat_std`` / ``y_hat_std_stamped``: the one-step std of each prediction (the band);
- ``y_hat_band`` / ``y_hat_band_stamped``: the live 95 % band's half-width (y_hat +- y_hat_band);
- ``samples``: each sample as learnt ([index, time, u.., y_p.., learn]), so a recording
  evaluates offline to exactly the live figure;
- ``nmse`` every ``report_every`` errors; ``status`` (JSON) and ``/diagnostics``
  (DiagnosticArray) every ``status_period`` s; ``identifier_config`` (latched JSON: the starting
  values, republished with each accepted live change and the sample it takes effect from).

Whatever keeps the node from doing what it was asked (no pairs, a wrong type, a QoS
that cannot match, refused pairs, clipped inputs, an unknown parameter, divergence, an input
that stops while its publisher is matched, a console nobody reads) is said in one line,
throttled per kind, and counted in ``status``.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.parameter import Parameter as RosParameter
from std_msgs.msg import String

from lenn_ros import topics
from lenn_ros.config import input_topics, rls_forgetting, side_channels
from lenn_ros.core.fields import FieldError, check_vector
from lenn_ros.core.networks import ModelFileError
from lenn_ros.core.pairing import U, Y
from lenn_ros.nodes import console, executor_choice, rclpy_internals, run_node
from lenn_ros.nodes.identifier_inputs import IdentifierInputs
from lenn_ros.nodes.identifier_outputs import OUTPUTS, IdentifierOutputs
from lenn_ros.nodes.node_parameters import NodeParameters
from lenn_ros.service import RecordingError
from lenn_ros.service.building import as_node_builds_it, build_identifier, compile_ahead, loaded_text, weights_path
from lenn_ros.session import Notice, Sample, Session, SessionConfig, json_safe

#: Notice kinds that are news, not trouble.
_INFO_KINDS = ("phase", "resumed", "scales", "parameters", "change_cleared", "inputs_resumed", "sign", "input_resumed")


class IdentifierNode(Node):
    """Learns a LeNN or MLP model of the plant online, sample by sample."""

    #: At exit: seconds the node goes on learning from what is still queued (:meth:`drain`) and,
    #: what is left of it (at least ``_ACK_FLOOR``), waits for readers to acknowledge its last
    #: messages (run_node). A reader that keeps up has them already (acknowledgements wait for
    #: the middleware's next heartbeat, up to 3 s with Fast DDS); the exit must come within 2 s
    #: of SIGINT, and the interpreter's own teardown takes 0.3-0.6 s of them.
    loop_takes_messages = False  # set by run_node's wait-set loop (see IdentifierInputs)
    companions: tuple[Node, ...] = ()  # nodes the loop must serve with this one (the InputsNode)
    _EXIT_BUDGET = 1.2
    _ACK_FLOOR = 0.4
    _drained_for = 0.0
    _console_dropped = 0

    @property
    def ack_timeout(self) -> float:
        return max(self._ACK_FLOOR, self._EXIT_BUDGET - self._drained_for)

    def __init__(
        self,
        node_name: str = "identifier",
        sibling_parameters: tuple[str, ...] = (),
        separate_inputs: bool = False,
        **node_options: Any,
    ) -> None:
        """``node_options`` go to rclpy's Node (namespace, parameter_overrides, context...),
        so several identifiers can share one process (a fleet); ``sibling_parameters`` are
        names a ``-p`` gives to another node of that process (not reported as unknown here).
        ``separate_inputs``: u and y_p on a DDS participant of their own (:class:`InputsNode`,
        ``companions``), so a flood of them cannot delay the parameter services; a fleet
        of identifiers, which would otherwise make one participant per plant, shares one."""
        super().__init__(node_name, automatically_declare_parameters_from_overrides=False, **node_options)
        self.started = time.monotonic()
        self.node_counters = {"type_mismatch": 0, "qos_incompatible": 0, "unknown_parameters": 0}
        self.parameters = NodeParameters(self, frozenset(sibling_parameters), self.node_counters)
        self.values, self.network, self.example = (
            self.parameters.values,
            self.parameters.network,
            self.parameters.example,
        )
        self.inputs = input_topics(self.values)  # (channel, part, topic): the pairing module's U / Y are 'u' / 'y'
        self.u_name = "+".join(self.resolve_topic_name(name) for channel, _, name in self.inputs if channel == U)
        self.y_name = "+".join(self.resolve_topic_name(name) for channel, _, name in self.inputs if channel == Y)
        self._loggers: dict[str, Any] = {}
        self._logged_at: dict[tuple[str, str], float] = {}  # monotonic time each (kind, subject) was last said
        self._warned_kinds: set[str] = set()
        self.parameters.warn_unknown()
        message_types = {channel: self._message_class(channel) for channel in (U, Y)}
        self.identifier = self._build_model()
        compile_ahead(self.identifier)
        self.session = Session(self.identifier, self._session_config())
        self.parameters.alias_qos_overrides([name for _, _, name in self.inputs])
        self.input = IdentifierInputs(self, self.parameters, message_types, separate_inputs)
        self.companions = (self.input.companion,) if self.input.companion is not None else ()
        self.session.config.queue_depth = self.input.queue_depth()
        self._refuse_stampless()
        # Held until our outputs have readers and, in sequence mode, until the graph shows one
        # lockstep publisher of both inputs (equal indices from two nodes are not one sample).
        self.session.hold_for({output: self.values[f"wait_for_{output}_subscribers"] for output in OUTPUTS})
        self.input.check_graph(at_start=True)
        self.add_on_set_parameters_callback(self.parameters.check)
        self.add_post_set_parameters_callback(self._apply_parameters)
        names = list(self.identifier.names) if self.session.values.vector else [self.y_name]
        self.outputs = IdentifierOutputs(
            self, names, self._sample_labels(), self.session.values.vector, self.values,
            lambda: self.session.phase_nmse.nmse_db,
        )  # fmt: skip
        self.status_publisher = self.create_publisher(String, topics.STATUS, topics.data_qos())
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self._config_publisher = self.create_publisher(String, topics.IDENTIFIER_CONFIG, topics.latched_qos())
        resolved = {name: self.resolve_topic_name(name) for _, _, name in self.inputs}
        self._config = {**self.values, "network": self.network, topics.RESOLVED_TOPICS: resolved}
        self._publish_config()
        self.parameters.warn_unknown_qos_overrides(self.u_name, self.y_name)
        self.create_timer(self.values["status_period"], self._on_status_timer)
        if self.values["pairing"] != "sequence":
            self.create_timer(min(0.05, self.values["sample_period"] or 0.05), self._on_poll_timer)
        self._autosave_timer = None
        self._schedule_autosave()
        self.get_logger().info(self._started_text())

    # -- set-up ----------------------------------------------------------------------------
    def _message_class(self, channel: str) -> Any:
        type_key, field_key = ("u_type", "u_field") if channel == U else ("y_type", "y_field")
        try:
            cls = topics.message_class(self.values[type_key])
            check_vector(cls, self.values[field_key], self.values[type_key], type_key)  # (one path: one channel)
        except (ValueError, FieldError) as error:
            raise SystemExit(f"identifier: {type_key}/{field_key}: {error}") from None
        return cls

    def _build_model(self) -> Any:
        """The identifier the parameters describe, built as every front-end builds it (service.building)."""
        try:
            identifier = build_identifier(self.values, self.network)
            identifier = as_node_builds_it(identifier, self.values, "identifier's parameters")
        except (ValueError, ModelFileError, RecordingError) as error:
            raise SystemExit(f"identifier: {error}") from None
        if self.values["weights_in"]:
            path = os.path.abspath(weights_path(self.values["weights_in"]))
            self.get_logger().info(loaded_text(identifier, path, self.network, self.values))
        return identifier

    def _session_config(self) -> SessionConfig:
        """The session's configuration: the parameters, the topics' names, a side's topics (several channels)."""
        try:
            parts = {}
            for side in ("u", "y"):
                _, sizes, names = side_channels(self.values, side)  # (one topic: no parts)
                parts[f"{side}_parts"] = sizes
                parts[f"{side}_parts_names"] = tuple(self.resolve_topic_name(name) for name in names)
            return SessionConfig.from_values(self.values, u_name=self.u_name, y_name=self.y_name, **parts)
        except ValueError as error:
            raise SystemExit(f"identifier: {error}") from None

    def _sample_labels(self) -> tuple[str, ...]:
        """The ``samples`` rows' labels: index, time, each input channel, each output channel, learn."""
        if not self.session.values.vector:  # (one channel of each: the plain labels)
            return topics.SAMPLE_LABELS
        return topics.sample_labels(*(side_channels(self.values, side)[0] for side in ("u", "y")))

    def _refuse_stampless(self) -> None:
        """Pairing by stamp needs a header on both inputs: said at the start, with the mode that works."""
        stamped = self.input.stamped
        if self.values["pairing"] != "stamp" or all(stamped.values()):
            return
        missing = [
            f"{name} ({self.values[key]})"
            for channel, name, key in ((U, self.u_name, "u_type"), (Y, self.y_name, "y_type"))
            if not stamped[channel]
        ]
        raise SystemExit(
            f"identifier: pairing 'stamp' needs header stamps on both inputs, and {' and '.join(missing)} has none: "
            "use pairing:=sample sample_period:=T"
        )

    def _started_text(self) -> str:
        weights = sum(model.n_weights for model in self.identifier.models)
        names = self.identifier.names
        shape = f"{len(names)} outputs ({self.values['couplings']} couplings), " if len(names) > 1 else ""
        return (
            f"{self.network} with {shape}{weights} weights, example preset {self.example or 'none'}, "
            f"{self.u_name} ({self.values['u_type']} {self.values['u_field']}) and {self.y_name} "
            f"({self.values['y_type']} {self.values['y_field']}) paired by {self.values['pairing']}, "
            f"learning {'on' if self.values['learning'] else 'off'}"
        )

    # -- parameters ----------------------------------------------------------------------------
    def _apply_parameters(self, parameters: list[RosParameter]) -> None:
        """Accepted values: the session applies (and records) what concerns the model and the pairing
        (:meth:`Session.apply_parameters`, the code evaluate replays a recording's changes through);
        the node the rest. The change log goes out on ``identifier_config`` at once, so a recorder
        has each change with the sample it takes effect from."""
        values = self.parameters.accepted(parameters)
        if not values:
            return
        effective = dict(values)
        if "forgetting" in values:  # 0 asks for a memory in seconds: the lambda it means is applied and recorded
            effective["forgetting"] = rls_forgetting(self.values)
        change = self.session.apply_parameters(effective)
        self.emit_notices()
        self._publish_config()
        shown = ", ".join(f"{name}={value!r}" for name, value in values.items())
        self.get_logger().info(f"parameters {shown} in effect from sample {change.from_index} (recorded)")
        if values.get("weights_out"):
            self._save(values["weights_out"])
        if "autosave_period" in values:
            self._schedule_autosave()

    def _publish_config(self) -> None:
        """``identifier_config`` (latched): the values the node started with and every live change since,
        each with the sample it takes effect from (``changes``), so the last message alone is the whole run's."""
        changes = [change.as_dict() for change in self.session.changes]
        message = {**self._config, topics.PARAMETER_CHANGES: changes}
        self._config_publisher.publish(String(data=json.dumps(json_safe(message))))

    # -- samples ---------------------------------------------------------------------------------
    def now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def drain(self, executor: Any = None) -> None:
        """On the way out (run_node): learn from the messages still queued, such as a replay's last
        window, within the exit budget; not when overloaded (the newest are gone already). Without
        rclpy's internals nothing can be taken directly: the executor hands them over instead."""
        if self.session.shedder.behind:
            return
        start = time.monotonic()
        internal = rclpy_internals.available() or executor is None
        take = self.input.drain if internal else lambda: rclpy_internals.run_ready(executor)
        while time.monotonic() - start < self._EXIT_BUDGET - self._ACK_FLOOR and take():
            pass
        self.publish(self.session.poll(self._paired_until()))
        self._drained_for = time.monotonic() - start

    def _on_poll_timer(self) -> None:
        self.input.drain()  # what is queued is older than now: settle it before the clock closes grid points
        self.publish(self.session.poll(self._paired_until()))
        self.emit_notices()

    def _paired_until(self) -> float:
        """The clock the pairing closes grid points and gives up on partners by: now, less how far behind
        the node is (the lag of the last message taken), so a backlog is not taken for silence."""
        return self.now() - self.session.shedder.lag

    def publish(self, samples: list[Sample]) -> None:
        """Every output of each sample (:mod:`~lenn_ros.nodes.identifier_outputs`), after the held pairs
        the session lets go (it decides, :mod:`~lenn_ros.core.holding`; the node only counts the readers)."""
        if self.session.held:
            samples = self.session.release_ready(self.outputs.readers(), time.monotonic()) + samples
        self.outputs.publish(samples)

    # -- reporting and persistence ---------------------------------------------------------------
    def emit_notices(self) -> None:
        for notice in self.session.take_notices():
            self.log(notice)

    def log(self, notice: Notice) -> None:
        """One line per notice, throttled per kind so one warning never hides another.

        Throttled here, not by rclpy's ``throttle_duration_sec``: rclpy refuses a call whose
        throttle differs from that logger's earlier calls (a ValueError that stopped the node
        at the first warning after ``warn_period`` was set live).
        """
        if notice.kind in _INFO_KINDS:
            self.get_logger().info(notice.text)
            return
        logger = self._loggers.get(notice.kind)
        if logger is None:
            logger = self._loggers[notice.kind] = self.get_logger().get_child(notice.kind)
        self._warned_kinds.add(notice.kind)
        now, key = time.monotonic(), (notice.kind, notice.subject)
        if now - self._logged_at.get(key, -math.inf) >= self.values["warn_period"]:
            self._logged_at[key] = now
            logger.warning(notice.text)

    def status(self) -> dict[str, Any]:
        """Everything a user or a test needs to know about the run so far (JSON-safe)."""
        status = self.session.status()
        inputs = self.input.status()
        status["network"] = self.network
        status["counters"].update({**self.node_counters, **inputs["counters"]})
        status["counters"]["console_lines_lost"] = console.dropped_lines()
        status["inputs_stalled"] = inputs["stalled"]
        status["topics"] = {"u": self.u_name, "y_p": self.y_name}
        status["inputs_node"] = self.input.node_name  # whom `ros2 topic info -v` names as u's and y_p's subscriber
        status["readers"] = self.outputs.readers()
        status["publishers"] = self.input.publishers_matched()
        status["held"] = self.session.held
        status["acknowledged"] = self._outputs_acknowledged()
        status["u_channels"], status["y_channels"] = (side_channels(self.values, side)[0] for side in ("u", "y"))
        return status

    def _outputs_acknowledged(self) -> bool:
        """Whether every RELIABLE reader (a recorder) has had every output message so far, asked without waiting.

        A recorder that falls behind (a burst it also records) holds its backlog in our
        writers' histories; a run stopped before it caught up leaves the bag short of
        its last samples. ``status["acknowledged"]`` lets whoever stops the run wait for it.
        """
        from rclpy.duration import Duration

        quiet = {topics.STATUS, topics.DIAGNOSTICS.lstrip("/"), "parameter_events", "rosout"}
        zero = Duration()
        return all(
            publisher.wait_for_all_acked(zero)
            for publisher in self.publishers
            if publisher.topic_name.rsplit("/", 1)[-1] not in quiet
        )

    def _on_status_timer(self) -> None:
        self.input.watch()
        dropped = console.dropped_lines()
        if dropped > self._console_dropped:  # (said on the console itself once it takes lines again)
            self._console_dropped = dropped
            self._warned_kinds.add("console: log lines dropped, stderr not read")
        self.input.check_graph()
        self.publish(self.session.poll(self._paired_until()))
        self.emit_notices()
        status = self.status()
        self.status_publisher.publish(String(data=json.dumps(status)))
        self.diagnostics_publisher.publish(self._diagnostics(status))
        self._warned_kinds.clear()

    def _diagnostics(self, status: dict[str, Any]) -> DiagnosticArray:
        """OK / WARN / ERROR with every counter, for rqt_robot_monitor and friends."""
        counters = status["counters"]
        if status["diverged"] or status["refused"] or counters["type_mismatch"] or counters["qos_incompatible"]:
            level, text = DiagnosticStatus.ERROR, status["refused"] or "diverged, type or QoS mismatch"
        elif status["change"]["alarm"]:  # while it is on, whatever else was said
            change = status["change"]
            level, text = DiagnosticStatus.WARN, self.session.change_text(change["raised_at"], change["since_time"])
        elif status["inputs_stalled"]:  # for as long as it lasts
            level, text = DiagnosticStatus.WARN, f"input stalled or slow: {', '.join(status['inputs_stalled'])}"
        elif self.session.silent:  # for as long as it lasts, not only in the period it was said
            level, text = DiagnosticStatus.WARN, f"no {self.u_name} or {self.y_name} for silence_timeout or longer"
        elif self._warned_kinds:
            level, text = DiagnosticStatus.WARN, "warnings: " + ", ".join(sorted(self._warned_kinds))
        else:
            level, text = DiagnosticStatus.OK, "identifying" if counters.get("learned") else "waiting for data"
        values = [KeyValue(key=key, value=str(value)) for key, value in counters.items()]
        for key in ("pairing", "learning", "phase_samples", "phase_nmse_db", "phase_rmse", "samples_seen"):
            values.append(KeyValue(key=key, value=str(status[key])))
        change = status["change"]
        for key in ("alarm", "count", "since_sample", "magnitude", "ratio"):
            values.append(KeyValue(key=f"change.{key}", value=str(change.get(key))))
        for name, channel in status["channels"].items():
            values.append(KeyValue(key=f"phase_nmse_db.{name}", value=str(channel["phase_nmse_db"])))
        entry = DiagnosticStatus(
            level=level, name=f"lenn_ros identifier: {self.get_fully_qualified_name()}", message=text, values=values
        )
        entry.hardware_id = self.get_fully_qualified_name()
        array = DiagnosticArray(status=[entry])
        array.header.stamp = self.get_clock().now().to_msg()
        return array

    def _schedule_autosave(self) -> None:
        """Autosave on its own timer, so it runs as often as autosave_period says."""
        if self._autosave_timer is not None:
            self.destroy_timer(self._autosave_timer)
            self._autosave_timer = None
        period = self.values["autosave_period"]
        if period > 0:
            self._autosave_timer = self.create_timer(period, self._autosave)

    def _autosave(self) -> None:
        if self.values["weights_out"]:
            self._save(self.values["weights_out"])

    def _save(self, path: str) -> None:
        try:
            self.identifier.save_state(weights_path(path))
        except OSError as error:
            self.get_logger().error(f"could not save weights to {path}: {error}")

    def shutdown(self) -> None:
        """Final status line and weights on the way out (SIGINT, SIGTERM or end), then no more input.

        The input subscriptions go at once: under a flood the middleware would otherwise
        go on receiving (and queueing) messages for the rest of the exit, and the
        teardown waited for it (2 s of a 3.4 s exit on 2 cores).
        """
        if self.values["weights_out"]:
            self._save(self.values["weights_out"])
        unlearnt = self.session.held_at_stop()
        if unlearnt is not None:
            self.get_logger().warning(unlearnt)
        print(f"identifier: {json.dumps(self.status())}", file=sys.stderr, flush=True)
        self.input.destroy()


#: The loop the identifier runs under unless ``LENN_ROS_EXECUTOR`` says otherwise (see ``run_node``).
#: The wait-set loop: half the CPU per sample of the single-threaded executor at 500-1000 Hz
#: (messages one by one), rclpy's own executor still for timers and services, and none of
#: the experimental events executor's defects to work around (bench/RESULTS.md, "Loops").
EXECUTOR = "waitset"


def main(args: list[str] | None = None, exit_process: bool = True) -> int:
    """The node's program; ``exit_process=False`` returns instead of ending the process (see run_node)."""

    def nodes() -> list[Node]:
        # the inputs on a participant of their own unless LENN_ROS_INPUTS_PARTICIPANT=0: under a flood
        # of them, parameter calls then take tens of ms instead of seconds (docs/nodes.md)
        node = IdentifierNode(separate_inputs=os.environ.get("LENN_ROS_INPUTS_PARTICIPANT") != "0")
        return [node, *node.companions]

    return run_node(nodes, "identifier", args, executor=executor_choice(EXECUTOR), exit_process=exit_process)


if __name__ == "__main__":
    sys.exit(main())
