"""identifier: online series-parallel identification of the plant behind u and y_p.

A thin adapter around :class:`lenn_ros.session.Session`: parameters in (declared
from :mod:`lenn_ros.config`), u / y_p in (any message type, one scalar each through a
field path), samples formed by the chosen pairing mode, one model step per sample,
and out:

- ``y_hat``: the prediction of y_p(k+1), as soon as sample k is complete (Float64);
- ``error``: e(k) = y_p(k) - y^(k) (Float64);
- ``y_hat_stamped`` / ``error_stamped``: y^(k) and e(k) as JointState stamped with the
  time of sample k, to overlay on y_p in Foxglove / PlotJuggler without a shift;
- ``samples``: each sample as learnt ([index, time, u, y_p, learn]), so a recording
  evaluates offline to exactly the live figure;
- ``nmse`` every ``report_every`` errors; ``status`` (JSON) and ``/diagnostics``
  (DiagnosticArray) every ``status_period`` s; ``identifier_config`` (latched JSON: the starting
  values, republished with each accepted live change and the sample it takes effect from).

Whatever keeps the node from doing what it was asked (no pairs, a wrong type, a QoS
that cannot match, refused pairs, clipped inputs, an unknown parameter, divergence)
is said in one line, throttled per kind, and counted in ``status``.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import json
import math
import os
import sys
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter as RosParameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSPolicyKind, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.serialization import deserialize_message
from std_msgs.msg import Int64, String

from lenn_ros import topics
from lenn_ros.config import (
    NODE_PARAMETERS,
    SCALING_KEYS,
    Parameter,
    build_identifier,
    check_value,
    field_extractor,
    identifier_parameters,
    input_topics,
    is_mimo,
    rls_forgetting,
    side_channels,
    unmatched_params_files,
)
from lenn_ros.core.fields import (
    FieldError,
    check_path,
    check_vector,
    has_header,
    stamp_seconds,
)
from lenn_ros.core.holding import START_GRACE
from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.networks import ModelFileError
from lenn_ros.core.pairing import U, Y
from lenn_ros.core.watchdog import InputWatchdog
from lenn_ros.nodes import DRAIN_SECONDS, InputsNode, console, executor_choice, rclpy_internals, run_node
from lenn_ros.nodes.identifier_outputs import OUTPUTS, IdentifierOutputs
from lenn_ros.session import Notice, Sample, Session, SessionConfig, json_safe

#: Parameters set by rclpy itself or by the QoS override mechanism: not unknown.
_FOREIGN_PARAMETERS = ("use_sim_time", "start_type_description_service", "qos_overrides.")
#: What ``qos_overrides./topic.subscription.*`` may set (rclpy's default set lacks durability).
_QOS_OVERRIDES = QoSOverridingOptions(
    policy_kinds=(QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH, QoSPolicyKind.RELIABILITY, QoSPolicyKind.DURABILITY)
)
#: Notice kinds that are news, not trouble.
_INFO_KINDS = ("phase", "resumed", "scales", "parameters", "change_cleared", "inputs_resumed", "sign", "input_resumed")


def _descriptor(parameter: Parameter) -> ParameterDescriptor:
    """Description and range; doubles take integers too (``ros2 param set ... alpha 1``)."""
    text = parameter.description + (f" (one of: {', '.join(parameter.choices)})" if parameter.choices else "")
    descriptor = ParameterDescriptor(description=text, read_only=not parameter.live)
    is_float = isinstance(parameter.default, float)
    if is_float:
        descriptor.dynamic_typing = True  # the on-set callback checks the number and its range
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


def _normalise(parameter: Parameter, value: Any) -> Any:
    """An integer given for a double parameter is that double."""
    if isinstance(parameter.default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


class IdentifierNode(Node):
    """Learns a LeNN or MLP model of the plant online, sample by sample."""

    #: At exit: seconds the node goes on learning from what is still queued (:meth:`drain`) and,
    #: what is left of it (at least ``_ACK_FLOOR``), waits for readers to acknowledge its last
    #: messages (run_node). A reader that keeps up has them already (acknowledgements wait for
    #: the middleware's next heartbeat, up to 3 s with Fast DDS); the exit must come within 2 s
    #: of SIGINT, and the interpreter's own teardown takes 0.3-0.6 s of them.
    loop_takes_messages = False  # set by run_node's wait-set loop (see _on_message)
    companions: tuple[Node, ...] = ()  # nodes the loop must serve with this one (the InputsNode)
    _EXIT_BUDGET = 1.2
    _console_dropped = 0
    _ACK_FLOOR = 0.4
    _drained_for = 0.0

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
        self._sibling_parameters, self._separate_inputs = frozenset(sibling_parameters), separate_inputs
        super().__init__(node_name, automatically_declare_parameters_from_overrides=False, **node_options)
        self._started = time.monotonic()
        self.values = self._declare_all()
        self.inputs = input_topics(self.values)  # (channel, part, topic): the pairing module's U / Y are 'u' / 'y'
        self.u_name = "+".join(self.resolve_topic_name(name) for channel, _, name in self.inputs if channel == U)
        self.y_name = "+".join(self.resolve_topic_name(name) for channel, _, name in self.inputs if channel == Y)
        self._loggers: dict[str, Any] = {}
        self._logged_at: dict[tuple[str, str], float] = {}  # monotonic time each (kind, subject) was last said
        self.node_counters = {"type_mismatch": 0, "qos_incompatible": 0, "unknown_parameters": 0}
        self._warn_unknown_parameters()
        self._warn_unmatched_params_files()
        self.mimo = is_mimo(self.values)
        message_types = {channel: self._message_class(channel) for channel in (U, Y)}
        self.identifier = self._build_model()
        self._compile_ahead()
        self.session = Session(self.identifier, self._session_config())
        self._extract = {channel: field_extractor(self.values, channel) for channel in (U, Y)}  # U, Y: 'u', 'y'
        self._stamped = {
            channel: has_header(cls) and self.values["use_header_stamp"] for channel, cls in message_types.items()
        }
        if self.values["pairing"] == "stamp" and not all(self._stamped.values()):
            raise SystemExit(
                "identifier: pairing 'stamp' needs header stamps on both inputs, and "
                + " and ".join(
                    f"{name} ({self.values[key]})"
                    for channel, name, key in ((U, self.u_name, "u_type"), (Y, self.y_name, "y_type"))
                    if not self._stamped[channel]
                )
                + " has none: use pairing:=sample sample_period:=T"
            )
        # Held until our outputs have readers and, in sequence mode, until the graph shows one
        # lockstep publisher of both inputs (equal indices from two nodes are not one sample).
        self.session.hold_for({output: self.values[f"wait_for_{output}_subscribers"] for output in OUTPUTS})
        self._check_graph(at_start=True)
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self._create_outputs()
        self.status_publisher = self.create_publisher(String, topics.STATUS, topics.data_qos())
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self._config_publisher = self.create_publisher(String, topics.IDENTIFIER_CONFIG, topics.latched_qos())
        resolved = {name: self.resolve_topic_name(name) for _, _, name in self.inputs}
        self._config = {**self.values, "network": self.network, topics.RESOLVED_TOPICS: resolved}
        self._publish_config()
        self._sim_time = bool(self.get_parameter("use_sim_time").value)
        self._message_types = message_types
        self._alias_qos_overrides()
        self._subscribe(message_types)
        self.watchdog = InputWatchdog(timeout=self.values["input_timeout"]) if self.values["input_timeout"] else None
        self._input_names = {key: s.topic_name for key, s in self._data_subscriptions.items()}
        self._warn_unknown_qos_overrides()
        self.create_timer(self.values["status_period"], self._on_status_timer)
        if self.values["pairing"] != "sequence":
            self.create_timer(min(0.05, self.values["sample_period"] or 0.05), self._on_poll_timer)
        self._autosave_timer = None
        self._schedule_autosave()
        self._warned_kinds: set[str] = set()
        weights = sum(model.n_weights for model in self._models())
        shape = f"{len(self.identifier.names)} outputs ({self.values['couplings']} couplings), " if self.mimo else ""
        self.get_logger().info(
            f"{self.network} with {shape}{weights} weights, example preset {self.example or 'none'}, "
            f"{self.u_name} ({self.values['u_type']} {self.values['u_field']}) and {self.y_name} "
            f"({self.values['y_type']} {self.values['y_field']}) paired by {self.values['pairing']}, "
            f"learning {'on' if self.values['learning'] else 'off'}"
        )

    # -- set-up ----------------------------------------------------------------------------
    def _create_outputs(self) -> None:
        """y_hat, error (plain and stamped), samples and nmse: scalars, or one element per output channel."""
        if self.mimo:
            outputs, labels = list(self.identifier.names), topics.sample_labels(*self._channel_names())
        else:
            outputs, labels = [self.y_name], topics.SAMPLE_LABELS
        self.outputs = IdentifierOutputs(
            self, outputs, labels, self.mimo, self.values, lambda: self.session.phase_nmse.nmse_db
        )

    def _declare_all(self) -> dict[str, Any]:
        presets = (
            ("example", 0, "paper example whose structure and parameters are the defaults (0 = none: my plant)"),
            ("network", "lenn", "lenn or mlp"),
            ("parameters", "calibrated", "alpha/beta preset: calibrated or paper"),
        )
        for name, default, text in presets:
            descriptor = ParameterDescriptor(description=text, read_only=True)
            if name == "example":
                descriptor.integer_range = [IntegerRange(from_value=0, to_value=4, step=1)]
            self.declare_parameter(name, default, descriptor)
        self.example = self.get_parameter("example").value
        self.network = self.get_parameter("network").value
        if self.network not in ("lenn", "mlp"):
            raise SystemExit(f"identifier: network must be 'lenn' or 'mlp', not {self.network!r}")
        preset = self.get_parameter("parameters").value
        self.table = {p.name: p for p in identifier_parameters(self.example, self.network, preset) + NODE_PARAMETERS}
        for parameter in self.table.values():
            self.declare_parameter(parameter.name, parameter.default, _descriptor(parameter))
        values = {}
        for name, parameter in self.table.items():
            value = _normalise(parameter, self.get_parameter(name).value)
            problem = check_value(parameter, value)
            if problem:
                raise SystemExit(f"identifier: {problem}")
            values[name] = value
        return values

    def _warn_unknown_parameters(self) -> None:
        """rclpy drops ``-p name:=value`` for a name never declared: say so."""
        known = set(self.table) | {"example", "network", "parameters"} | self._sibling_parameters
        for name in self._parameter_overrides:
            if name in known or name.startswith(_FOREIGN_PARAMETERS):
                continue
            self.node_counters["unknown_parameters"] += 1
            close = difflib.get_close_matches(name, sorted(known), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            self.get_logger().error(f"unknown parameter {name!r} is ignored{hint}")

    def _warn_unmatched_params_files(self) -> None:
        """A params file with no section for this node's name is applied to nothing: say so."""
        name = self.get_fully_qualified_name()
        for path, keys in unmatched_params_files(sys.argv, name):
            self.node_counters["unknown_parameters"] += 1
            self.get_logger().error(
                f"params file {path} has no section for this node ({name}; its keys: {', '.join(keys)}), so none "
                f"of its parameters apply: name the section '/**:' (any node) or '/**/{self.get_name()}:'"
            )

    def _alias_qos_overrides(self) -> None:
        """QoS overrides given under an input's name before remapping apply to the remapped topic.

        rclpy declares ``qos_overrides.<topic>.subscription.*`` under the resolved, remapped
        name (``/joint_states``), so the README's ``qos_overrides./u...`` was refused as
        unknown once ``-r u:=/joint_states`` was given. Each such override is copied to the
        remapped name before the subscriptions declare theirs; one given under both names
        keeps the remapped one's value, and the user is told which.
        """
        self._qos_aliases: set[str] = set()
        for _, _, topic in self.inputs:
            plain, remapped = self.resolve_topic_name(topic, only_expand=True), self.resolve_topic_name(topic)
            prefix = f"qos_overrides.{plain}.subscription."
            if plain == remapped:
                continue
            for name, parameter in list(self._parameter_overrides.items()):
                if not name.startswith(prefix):
                    continue
                target = f"qos_overrides.{remapped}.subscription.{name[len(prefix) :]}"
                self._qos_aliases.add(name)
                if target in self._parameter_overrides:
                    self.get_logger().warning(f"{name} and {target} both given: {target} applies (remapped name)")
                    continue
                self._parameter_overrides[target] = RosParameter(target, value=parameter.value)
                self.get_logger().info(f"{name} applies to {remapped} ({plain} is remapped to it)")

    def _warn_unknown_qos_overrides(self) -> None:
        """``qos_overrides.`` names that no subscription declared (a typo, a wrong topic) are ignored: say so."""
        for name in self._parameter_overrides:
            if name.startswith("qos_overrides.") and not self.has_parameter(name) and name not in self._qos_aliases:
                self.node_counters["unknown_parameters"] += 1
                self.get_logger().error(
                    f"unknown QoS override {name!r} is ignored: this node takes "
                    f"qos_overrides.{self.u_name}.subscription.* and qos_overrides.{self.y_name}.subscription.* "
                    "(reliability, history, depth, durability; an input's name before remapping works too)"
                )

    def _message_class(self, channel: str) -> Any:
        type_key, field_key = ("u_type", "u_field") if channel == U else ("y_type", "y_field")
        try:
            cls = topics.message_class(self.values[type_key])
            check = check_vector if self.mimo else check_path
            check(cls, self.values[field_key], self.values[type_key], type_key)
        except (ValueError, FieldError) as error:
            raise SystemExit(f"identifier: {type_key}/{field_key}: {error}") from None
        return cls

    def _channel_names(self) -> tuple[list[str], list[str]]:
        """Input and output channel names of a MIMO model (checked when the model was built)."""
        return side_channels(self.values, "u")[0], side_channels(self.values, "y")[0]

    def _models(self) -> list[Any]:
        """Every network the node learns: one, or one per output channel."""
        return self.identifier.models if self.mimo else [self.identifier.model]

    def _build_model(self) -> Any:
        try:
            identifier = build_identifier(self.values, self.network)
        except ValueError as error:
            raise SystemExit(f"identifier: {error}") from None
        identifier.health_interval = self.values["health_interval"]
        identifier.divergence_ratio = self.values["divergence_ratio"]
        identifier.resume_after = self.values["resume_after"]
        if self.values["weights_in"]:
            path = os.path.abspath(os.path.expanduser(self.values["weights_in"]))
            try:
                loader = identifier if isinstance(identifier, MimoIdentifier) else identifier.model
                loader.load_state(path)
            except ModelFileError as error:
                raise SystemExit(f"identifier: {error}") from None
            identifier.mark_healthy()
            self.get_logger().info(self._loaded_text(identifier, path))
        return identifier

    def _loaded_text(self, identifier: Any, path: str) -> str:
        """One line at start for ``weights_in``: learning resumes from a file, not from fresh weights, and
        the user must be able to see which file and which network (a stale path is otherwise silent)."""
        models = identifier.models if isinstance(identifier, MimoIdentifier) else [identifier.model]
        model = models[0]
        structural = {k: v for k, v in model.get_params().items() if k in model._structural_params and v is not None}
        structure = identifier.structure
        lags = f"y_lags {structure.y_lags}, u_lags {structure.u_lags}, " if hasattr(structure, "y_lags") else ""
        outputs = f" for {len(models)} outputs" if len(models) > 1 else ""
        seen = sum(int(getattr(each, "n_samples_seen_", 0)) for each in models)
        from_file = not isinstance(identifier, MimoIdentifier) and not (
            float(self.values["y_scale"]) and float(self.values["u_scale"])
        )
        scales = (
            "; scales from the file (the run that saved it learnt them): "
            + ", ".join(f"{key} {getattr(structure, key):.6g}" for key in SCALING_KEYS)
            if from_file
            else ""
        )
        return (
            f"weights_in: loaded {sum(each.n_weights for each in models)} weights{outputs} from {path} "
            f"(learnt from {seen} samples): {self.network}, {lags}"
            + ", ".join(f"{key} {value}" for key, value in structural.items())
            + scales
        )

    def _compile_ahead(self) -> None:
        """Step a throwaway copy of the model through its warm-up now, before any subscription exists.

        On a machine whose numba cache is cold the first live sample would otherwise wait
        seconds for the compiled step (4 s for a MIMO output's), while a BEST_EFFORT queue
        overflows; with the cache warm this takes milliseconds.
        """
        scratch = copy.deepcopy(self.identifier)
        if isinstance(scratch, MimoIdentifier):
            u, y = np.zeros(scratch.structure.n_u), np.zeros(scratch.structure.n_y)
            window = max(output.structure.warm_up for output in scratch.outputs)
        else:
            u, y, window = 0.0, 0.0, scratch.structure.warm_up
            if not scratch.structure.scaled:  # (scales to be learnt by the warm-up: any will do to compile)
                scratch.set_structure(dataclasses.replace(scratch.structure, y_scale=1.0, u_scale=1.0))
        for k in range(window + 2):
            scratch.step(k + 1, u, y, True)

    def _session_config(self) -> SessionConfig:
        try:
            parts = {}
            if self.mimo:
                for side in ("u", "y"):
                    _, sizes, names = side_channels(self.values, side)
                    parts[f"{side}_parts"] = sizes
                    parts[f"{side}_parts_names"] = tuple(self.resolve_topic_name(name) for name in names)
            return SessionConfig.from_values(self.values, u_name=self.u_name, y_name=self.y_name, **parts)
        except ValueError as error:
            raise SystemExit(f"identifier: {error}") from None

    def _subscribe(self, message_types: dict[str, Any]) -> None:
        """u and y_p with QoS settable by parameters (``qos_overrides./u.subscription.*``).

        Default: RELIABLE for sequence pairing (a lockstep simulator must lose
        nothing), BEST_EFFORT otherwise, which matches every publisher, RELIABLE or not.
        """
        reliability = (
            ReliabilityPolicy.RELIABLE if self.values["pairing"] == "sequence" else ReliabilityPolicy.BEST_EFFORT
        )
        profile = QoSProfile(depth=topics.DATA_DEPTH, reliability=reliability)
        self._data_subscriptions: dict[tuple[str, int], Any] = {}
        inputs = InputsNode(self) if self._separate_inputs else None
        # first, and on the inputs' participant: a lockstep publisher that sees our data readers
        # in the graph sees this one too, and waits until it has the latched index before sample 1
        self._test_start_subscription = (inputs or self).create_subscription(
            Int64, self.resolve_topic_name(topics.TEST_START), self._on_test_start, topics.latched_qos()
        )
        self._profile, self._inputs_node = profile, inputs
        for channel, part, name in self.inputs:
            self._data_subscriptions[channel, part] = self._subscribe_input(channel, part, name)
        if inputs is not None:
            self.companions = (inputs,)
        self._inputs_node_name = (inputs or self).get_fully_qualified_name()
        # (after the overrides: what the queues really hold; KEEP_ALL has no depth to overflow)
        kept = [s.qos_profile for s in self._data_subscriptions.values()]
        keep_last = all(qos.history != HistoryPolicy.KEEP_ALL for qos in kept)
        self.session.config.queue_depth = min(qos.depth for qos in kept) if keep_last else 0

    def _subscribe_input(self, channel: str, part: int, name: str) -> Any:
        """One input's subscription (raw: read once admitted, :meth:`_offer`), on the inputs' node when it has one
        (its QoS overrides are this node's parameters), with the QoS-mismatch event said in one line."""
        events = SubscriptionEventCallbacks(incompatible_qos=lambda event, c=channel: self._on_incompatible_qos(c))
        callback = lambda message, info, c=channel, p=part: self._on_message(c, message, info, p)  # noqa: E731
        message_type = self._message_types[channel]
        if self._inputs_node is None:
            return self.create_subscription(
                message_type, name, callback, self._profile, event_callbacks=events,
                qos_overriding_options=_QOS_OVERRIDES, raw=True,
            )  # fmt: skip
        return self._inputs_node.create_subscription(
            message_type, self.resolve_topic_name(name), callback, self._overridden_qos(name, self._profile),
            event_callbacks=events, raw=True,
        )  # fmt: skip

    def _resubscribe(self, topic: str) -> None:
        """The watchdog's remedy for an input that matched publishers no longer deliver: a new subscription (a new
        reader in the middleware), the old one destroyed (the wait-set loop picks the new one up at its next turn)."""
        for (channel, part, name), key in zip(self.inputs, self._data_subscriptions, strict=True):
            old = self._data_subscriptions[key]
            if old.topic_name != topic:
                continue
            (self._inputs_node or self).destroy_subscription(old)
            self._data_subscriptions[key] = self._subscribe_input(channel, part, name)

    def _overridden_qos(self, topic: str, profile: QoSProfile) -> QoSProfile:
        """``profile`` with the user's ``qos_overrides.<topic>.subscription.*``, declared on this node as
        rclpy declares them for a subscription of its own (read-only, the profile's value as default).

        For a subscription that lives on the inputs' node. It used to be created here first and
        destroyed once its QoS was read: a publisher waiting for subscribers could match that
        transient one and send its first messages to it, and they were lost (a lockstep
        simulator's, a two-second run's warm-up). Done through the public parameter API.
        """
        name = self.resolve_topic_name(topic)
        qos = QoSProfile(
            history=profile.history, depth=profile.depth, reliability=profile.reliability,
            durability=profile.durability,
        )  # fmt: skip
        enums = {"history": HistoryPolicy, "reliability": ReliabilityPolicy, "durability": DurabilityPolicy}
        for kind in _QOS_OVERRIDES.policy_kinds:
            policy = kind.name.lower()
            current = getattr(qos, policy)
            key = f"qos_overrides.{name}.subscription.{policy}"
            if self.has_parameter(key):
                value = self.get_parameter(key).value
            else:
                descriptor = ParameterDescriptor(
                    description=f"{policy} for subscription `{name}` with id `None`", read_only=True
                )
                default = current.name.lower() if policy in enums else current
                value = self.declare_parameter(key, default, descriptor).value
            if policy in enums:
                try:
                    value = enums[policy][str(value).upper()]
                except KeyError:
                    raise SystemExit(f"identifier: {key} = {value!r} is no {policy} policy") from None
            setattr(qos, policy, value)
        return qos

    # -- parameters ----------------------------------------------------------------------------
    def _check_parameters(self, parameters: list[RosParameter]) -> SetParametersResult:
        for parameter in parameters:
            spec = self.table.get(parameter.name)
            if spec is None:
                continue
            problem = check_value(spec, _normalise(spec, parameter.value))
            if problem:
                return SetParametersResult(successful=False, reason=problem)
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[RosParameter]) -> None:
        """Accepted values: the session applies (and records) what concerns the model and the pairing
        (:meth:`Session.apply_parameters`, the code evaluate replays a recording's changes through);
        the node the rest. The change log goes out on ``identifier_config`` at once, so a recorder
        has each change with the sample it takes effect from."""
        values = {}
        for parameter in parameters:
            if parameter.name in self.table:
                values[parameter.name] = _normalise(self.table[parameter.name], parameter.value)
        if not values:
            return
        self.values.update(values)
        effective = dict(values)
        if "forgetting" in values:  # 0 asks for a memory in seconds: the lambda it means is applied and recorded
            effective["forgetting"] = rls_forgetting(self.values)
        change = self.session.apply_parameters(effective)
        self._emit_notices()
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

    # -- data ----------------------------------------------------------------------------------
    def _on_test_start(self, message: Int64) -> None:
        self.session.set_test_start(int(message.data))

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_message(self, channel: str, message: Any, info: dict, part: int = 0) -> None:
        """One message from the executor, then every message already waiting on u and y_p.

        The executor rebuilds its wait set in Python for each message it hands over
        (most of the cost at kilohertz rates); taking what is queued straight from the
        subscriptions handles a burst in one wake-up. Pairing does not depend on the
        order in which u and y_p are taken (index, stamp or time decide). Under the wait-set
        loop, which takes what waits itself, a message the executor hands over (with a timer
        or a service due) is just offered: the service behind it in the executor's list
        comes sooner.
        """
        self._offer(channel, message, info, part)
        if not self.loop_takes_messages:
            self._drain()
        self._emit_notices()

    def drain(self, executor: Any = None) -> None:
        """On the way out (run_node): learn from the messages still queued, such as a replay's last
        window, within the exit budget; not when overloaded (the newest are gone already). Without
        rclpy's internals nothing can be taken directly: the executor hands them over instead."""
        if self.session.shedder.behind:
            return
        start = time.monotonic()
        take = (
            self._drain
            if rclpy_internals.available() or executor is None
            else lambda: rclpy_internals.run_ready(executor)
        )
        while time.monotonic() - start < self._EXIT_BUDGET - self._ACK_FLOOR and take():
            pass
        self._publish(self.session.poll(self._paired_until()))
        self._drained_for = time.monotonic() - start

    def _drain(self) -> int:
        """Take test_start, u and y_p messages already waiting, until none is left or the turn's time is up.

        Bounded (``DRAIN_SECONDS``): under a flood the queues never empty, and a drain that
        ran until they did would starve the timers (status, the grid's poll), the parameter
        services and the stop request. What is left waits for the next turn; what waits too
        long is shed (``Session.admit``). Returns how many u / y_p messages it took.
        """
        taken, count = True, 0
        deadline = time.monotonic() + DRAIN_SECONDS
        while taken and time.monotonic() < deadline:
            taken = False
            latched = rclpy_internals.take(self._test_start_subscription, raw=False)  # the phase switches first
            if latched is not None:
                self._on_test_start(latched[0])
            for (other, part), subscription in self._data_subscriptions.items():
                waiting = rclpy_internals.take(subscription)
                if waiting is not None:
                    self._offer(other, waiting[0], waiting[1], part)
                    taken = True
                    count += 1
        return count

    def _offer(self, channel: str, serialized: bytes, info: dict, part: int = 0) -> None:
        """One message as it was taken, serialised: shed unread if it waited too long, else read and offered.

        The subscriptions are raw so that shedding costs a take (8 us for a JointState) and
        not a deserialisation as well (30 us more): under a flood the node must shed faster
        than messages arrive to reach the newest again.
        """
        arrived = info.get("received_timestamp")
        if self.watchdog is not None:
            self.watchdog.arrived(self._input_names[channel, part], time.monotonic())
        if arrived and not self.session.admit((channel, part), arrived * 1e-9, time.time()):
            return  # shed: the node is behind (counted, said by the session)
        message = deserialize_message(serialized, self._message_types[channel])
        received = arrived * 1e-9 if arrived and not self._sim_time else self._now()
        try:
            value = self._extract[channel](message)
        except FieldError as error:
            key = "u_field" if channel == U else "y_field"
            self.session.unreadable(channel, received, f"{key} {self.values[key]}", str(error))
            self._log(Notice("field", f"{self.u_name if channel == U else self.y_name}: {error}; message skipped"))
            return
        stamp = stamp_seconds(message) if self._stamped[channel] else None
        source = info.get("source_timestamp")
        if not self.session.publishers_known:
            self._check_graph()
        samples = self.session.offer(
            channel,
            value,
            stamp if stamp is not None else received,
            received=received,
            sequence=info.get("publication_sequence_number"),
            source_time=source * 1e-9 if source else None,
            part=part,
        )
        self._publish(samples)

    def _on_poll_timer(self) -> None:
        self._drain()  # what is queued is older than now: settle it before the clock closes grid points
        self._publish(self.session.poll(self._paired_until()))
        self._emit_notices()

    def _paired_until(self) -> float:
        """The clock the pairing closes grid points and gives up on partners by: now, less how far behind
        the node is (the lag of the last message taken), so a backlog is not taken for silence."""
        return self._now() - self.session.shedder.lag

    def _publish(self, samples: list[Sample]) -> None:
        """Every output of each sample (:mod:`~lenn_ros.nodes.identifier_outputs`), after the held pairs
        the session lets go (it decides, :mod:`~lenn_ros.core.holding`; the node only counts the readers)."""
        if self.session.held:
            samples = self.session.release_ready(self._readers(), time.monotonic()) + samples
        self.outputs.publish(samples)

    def _publishers_matched(self) -> dict[str, int]:
        """Publishers each input topic's subscription has matched: nothing arrives from one not counted
        here yet (DDS discovery), so a script that publishes as soon as the node is up can wait for it."""
        return {
            subscription.topic_name: subscription.get_publisher_count()
            for subscription in self._data_subscriptions.values()
        }

    def _readers(self) -> dict[str, int]:
        """Matched readers of each output that can hold the first pairs back."""
        return self.outputs.readers()

    # -- the graph: types, publishers, QoS --------------------------------------------------------
    def _check_graph(self, at_start: bool = False) -> None:
        """What the graph offers on u / y_p: a wrong type is said here (or stops the node at its
        start); who publishes goes to the session, which decides about pairing by sequence number."""
        publishers: dict[str, set] = {U: set(), Y: set()}
        for channel, _, topic in self.inputs:
            key = "u_type" if channel == U else "y_type"
            name = self.resolve_topic_name(topic)
            infos = self.get_publishers_info_by_topic(name)
            publishers[channel] |= {(info.node_namespace, info.node_name) for info in infos}
            wrong = sorted({info.topic_type for info in infos if info.topic_type != self.values[key]})
            if wrong:
                text = (
                    f"{name} is published as {', '.join(wrong)}, not {key} {self.values[key]}: "
                    f"pass -p {key}:={wrong[0]} and a matching -p {key[0]}_field:=..."
                )
                if at_start or time.monotonic() - self._started < START_GRACE:
                    raise SystemExit(f"identifier: {text}")  # discovery takes a moment: still "at start"
                self.node_counters["type_mismatch"] += 1
                self._log(Notice("type", text))
        self.session.graph_publishers(publishers)

    def _on_incompatible_qos(self, channel: str) -> None:
        name = self.u_name if channel == U else self.y_name
        self.node_counters["qos_incompatible"] += 1
        self._log(
            Notice(
                "qos",
                f"a publisher on {name} offers a QoS this subscription cannot match (e.g. BEST_EFFORT against "
                f"RELIABLE), so nothing arrives: add -p qos_overrides.{name}.subscription.reliability:=best_effort",
            )
        )

    # -- reporting and persistence ---------------------------------------------------------------
    def _emit_notices(self) -> None:
        for notice in self.session.take_notices():
            self._log(notice)

    def _log(self, notice: Notice) -> None:
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
        status["network"] = self.network
        status["counters"].update(self.node_counters)
        if self.watchdog is not None:
            status["counters"].update(self.watchdog.counters)
            status["inputs_stalled"] = self.watchdog.stalled
        status["counters"]["console_lines_lost"] = console.dropped_lines()
        status["topics"] = {"u": self.u_name, "y_p": self.y_name}
        status["inputs_node"] = self._inputs_node_name  # whom `ros2 topic info -v` names as u's and y_p's subscriber
        status["readers"] = self._readers()
        status["publishers"] = self._publishers_matched()
        status["held"] = self.session.held
        status["acknowledged"] = self._outputs_acknowledged()
        if self.mimo:
            status["u_channels"], status["y_channels"] = self._channel_names()
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

    def _watch_inputs(self) -> None:
        """The input watchdog's turn (core.watchdog): each stall or slow topic said with its matched publishers,
        a stalled one resubscribed."""
        if self.watchdog is None:
            return
        publishers = {}
        for subscription in self._data_subscriptions.values():
            topic = subscription.topic_name
            if subscription.get_publisher_count() and self.watchdog.watched(topic):
                infos = self.get_publishers_info_by_topic(topic)
                publishers[topic] = sorted({f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in infos}) or ["?"]
        for event in self.watchdog.check(time.monotonic(), publishers):
            self._log(Notice(f"input_{event.kind}", event.text, event.topic))
            if event.resubscribe:
                self._resubscribe(event.topic)

    def _on_status_timer(self) -> None:
        self._watch_inputs()
        dropped = console.dropped_lines()
        if dropped > self._console_dropped:  # (said on the console itself once it takes lines again)
            self._console_dropped = dropped
            self._warned_kinds.add("console: log lines dropped, stderr not read")
        self._check_graph()
        self._publish(self.session.poll(self._paired_until()))
        self._emit_notices()
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
            level, text = DiagnosticStatus.WARN, self.session.change_text(change["since_sample"], change["since_time"])
        elif status.get("inputs_stalled"):  # for as long as it lasts
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
        for name, channel in status.get("channels", {}).items():
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
            if self.mimo:
                self.identifier.save_state(os.path.expanduser(path))
            else:
                structure = self.identifier.structure
                scaling = {key: getattr(structure, key) for key in SCALING_KEYS} if structure.scaled else None
                self.identifier.model.save(os.path.expanduser(path), scaling=scaling)
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
        for subscription in self._data_subscriptions.values():
            (self.companions[0] if self.companions else self).destroy_subscription(subscription)
        self._data_subscriptions = {}


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
