"""The identifier node's parameters: declared from the one table, checked when set, and every way a user's
parameter can fail to apply said in one line.

The table is :mod:`lenn_ros.config` (the reference page is generated from it). What rclpy would drop
without a word is said here: a ``-p`` for a name never declared (with the closest known name), a
params file with no section for this node's name, a ``qos_overrides.`` name no subscription has; a
QoS override given under an input's name before remapping is applied to the remapped topic.
"""

from __future__ import annotations

import difflib
import sys
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter as RosParameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSPolicyKind, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions

from lenn_ros.config import NODE_PARAMETERS, Parameter, check_value, identifier_parameters
from lenn_ros.service.params import unmatched_params_files

#: Parameters set by rclpy itself or by the QoS override mechanism: not unknown.
FOREIGN_PARAMETERS = ("use_sim_time", "start_type_description_service", "qos_overrides.")
#: What ``qos_overrides./topic.subscription.*`` may set (rclpy's default set lacks durability).
QOS_OVERRIDES = QoSOverridingOptions(
    policy_kinds=(QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH, QoSPolicyKind.RELIABILITY, QoSPolicyKind.DURABILITY)
)
#: The presets, declared first: they choose the table's defaults.
PRESETS = (
    ("example", 0, "paper example whose structure and parameters are the defaults (0 = none: my plant)"),
    ("network", "lenn", "lenn or mlp"),
    ("parameters", "calibrated", "alpha/beta preset: calibrated or paper"),
)


def descriptor(parameter: Parameter) -> ParameterDescriptor:
    """Description and range; doubles take integers too (``ros2 param set ... alpha 1``)."""
    text = parameter.description + (f" (one of: {', '.join(parameter.choices)})" if parameter.choices else "")
    described = ParameterDescriptor(description=text, read_only=not parameter.live)
    if isinstance(parameter.default, float):
        described.dynamic_typing = True  # the on-set callback checks the number and its range
    if parameter.low is not None and not isinstance(parameter.default, bool):
        if isinstance(parameter.default, int):
            described.integer_range = [
                IntegerRange(from_value=int(parameter.low), to_value=int(parameter.high), step=1)
            ]
        else:
            described.floating_point_range = [
                FloatingPointRange(from_value=float(parameter.low), to_value=float(parameter.high))
            ]
    return described


def normalise(parameter: Parameter, value: Any) -> Any:
    """An integer given for a double parameter is that double."""
    if isinstance(parameter.default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


class NodeParameters:
    """The table of one identifier node's parameters and the values it started with (``values``)."""

    def __init__(self, node: Node, siblings: frozenset[str], counters: dict[str, int]) -> None:
        """``siblings``: names a ``-p`` gives to another node of the process (a fleet's); ``counters``: the node's,
        where ``unknown_parameters`` is counted."""
        self.node, self.siblings, self.counters = node, siblings, counters
        self.qos_aliases: set[str] = set()
        for name, default, text in PRESETS:
            described = ParameterDescriptor(description=text, read_only=True)
            if name == "example":
                described.integer_range = [IntegerRange(from_value=0, to_value=4, step=1)]
            node.declare_parameter(name, default, described)
        self.example = node.get_parameter("example").value
        self.network = node.get_parameter("network").value
        if self.network not in ("lenn", "mlp"):
            raise SystemExit(f"identifier: network must be 'lenn' or 'mlp', not {self.network!r}")
        preset = node.get_parameter("parameters").value
        parameters = identifier_parameters(self.example, self.network, preset) + NODE_PARAMETERS
        self.table = {p.name: p for p in parameters}
        for parameter in self.table.values():
            node.declare_parameter(parameter.name, parameter.default, descriptor(parameter))
        self.values: dict[str, Any] = {}
        for name, parameter in self.table.items():
            value = normalise(parameter, node.get_parameter(name).value)
            problem = check_value(parameter, value)
            if problem:
                raise SystemExit(f"identifier: {problem}")
            self.values[name] = value

    def warn_unknown(self) -> None:
        """rclpy drops ``-p name:=value`` for a name never declared, and a params file with no section for this
        node's name applies to nothing: say both."""
        node = self.node
        known = set(self.table) | {name for name, _, _ in PRESETS} | self.siblings
        for name in node._parameter_overrides:
            if name in known or name.startswith(FOREIGN_PARAMETERS):
                continue
            self.counters["unknown_parameters"] += 1
            close = difflib.get_close_matches(name, sorted(known), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            node.get_logger().error(f"unknown parameter {name!r} is ignored{hint}")
        name = node.get_fully_qualified_name()
        for path, keys in unmatched_params_files(sys.argv, name):
            self.counters["unknown_parameters"] += 1
            node.get_logger().error(
                f"params file {path} has no section for this node ({name}; its keys: {', '.join(keys)}), so none "
                f"of its parameters apply: name the section '/**:' (any node) or '/**/{node.get_name()}:'"
            )

    def alias_qos_overrides(self, topics: list[str]) -> None:
        """QoS overrides given under an input's name before remapping apply to the remapped topic.

        rclpy declares ``qos_overrides.<topic>.subscription.*`` under the resolved, remapped
        name (``/joint_states``), so the README's ``qos_overrides./u...`` was refused as
        unknown once ``-r u:=/joint_states`` was given. Each such override is copied to the
        remapped name before the subscriptions declare theirs; one given under both names
        keeps the remapped one's value, and the user is told which.
        """
        node = self.node
        overrides = node._parameter_overrides
        for topic in topics:
            plain, remapped = node.resolve_topic_name(topic, only_expand=True), node.resolve_topic_name(topic)
            prefix = f"qos_overrides.{plain}.subscription."
            if plain == remapped:
                continue
            for name, parameter in list(overrides.items()):
                if not name.startswith(prefix):
                    continue
                target = f"qos_overrides.{remapped}.subscription.{name[len(prefix) :]}"
                self.qos_aliases.add(name)
                if target in overrides:
                    node.get_logger().warning(f"{name} and {target} both given: {target} applies (remapped name)")
                    continue
                overrides[target] = RosParameter(target, value=parameter.value)
                node.get_logger().info(f"{name} applies to {remapped} ({plain} is remapped to it)")

    def warn_unknown_qos_overrides(self, u_name: str, y_name: str) -> None:
        """``qos_overrides.`` names that no subscription declared (a typo, a wrong topic) are ignored: say so."""
        node = self.node
        for name in node._parameter_overrides:
            if name.startswith("qos_overrides.") and not node.has_parameter(name) and name not in self.qos_aliases:
                self.counters["unknown_parameters"] += 1
                node.get_logger().error(
                    f"unknown QoS override {name!r} is ignored: this node takes "
                    f"qos_overrides.{u_name}.subscription.* and qos_overrides.{y_name}.subscription.* "
                    "(reliability, history, depth, durability; an input's name before remapping works too)"
                )

    def overridden_qos(self, topic: str, profile: QoSProfile) -> QoSProfile:
        """``profile`` with the user's ``qos_overrides.<topic>.subscription.*``, declared on this node as
        rclpy declares them for a subscription of its own (read-only, the profile's value as default).

        For a subscription that lives on the inputs' node. It used to be created here first and
        destroyed once its QoS was read: a publisher waiting for subscribers could match that
        transient one and send its first messages to it, and they were lost (a lockstep
        simulator's, a two-second run's warm-up). Done through the public parameter API.
        """
        node = self.node
        name = node.resolve_topic_name(topic)
        qos = QoSProfile(
            history=profile.history, depth=profile.depth, reliability=profile.reliability,
            durability=profile.durability,
        )  # fmt: skip
        enums = {"history": HistoryPolicy, "reliability": ReliabilityPolicy, "durability": DurabilityPolicy}
        for kind in QOS_OVERRIDES.policy_kinds:
            policy = kind.name.lower()
            current = getattr(qos, policy)
            key = f"qos_overrides.{name}.subscription.{policy}"
            if node.has_parameter(key):
                value = node.get_parameter(key).value
            else:
                described = ParameterDescriptor(
                    description=f"{policy} for subscription `{name}` with id `None`", read_only=True
                )
                default = current.name.lower() if policy in enums else current
                value = node.declare_parameter(key, default, described).value
            if policy in enums:
                try:
                    value = enums[policy][str(value).upper()]
                except KeyError:
                    raise SystemExit(f"identifier: {key} = {value!r} is no {policy} policy") from None
            setattr(qos, policy, value)
        return qos

    def check(self, parameters: list[RosParameter]) -> SetParametersResult:
        """The on-set callback: a value out of its range or choices is refused with the reason."""
        for parameter in parameters:
            spec = self.table.get(parameter.name)
            if spec is None:
                continue
            problem = check_value(spec, normalise(spec, parameter.value))
            if problem:
                return SetParametersResult(successful=False, reason=problem)
        return SetParametersResult(successful=True)

    def accepted(self, parameters: list[RosParameter]) -> dict[str, Any]:
        """The table's values among ``parameters`` (accepted), normalised, and now the node's."""
        values = {p.name: normalise(self.table[p.name], p.value) for p in parameters if p.name in self.table}
        self.values.update(values)
        return values
