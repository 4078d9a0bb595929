"""The identifier node's inputs: u and y_p subscribed, taken, read and offered to the session; the graph they are in.

- **subscriptions**: any message type, raw (read once admitted), with QoS settable by parameters;
  on a DDS participant of their own by default (:class:`~lenn_ros.nodes.InputsNode`), so a flood of
  them cannot delay the parameter services; RELIABLE for sequence pairing (a lockstep simulator
  must lose nothing), BEST_EFFORT otherwise, which matches every publisher;
- **taking**: straight from the subscriptions, every message waiting, bounded per turn
  (``DRAIN_SECONDS``: under a flood the queues never empty, and a drain that ran until they did
  would starve the timers, the parameter services and the stop request); a message that waited
  too long is shed unread (the session decides, :mod:`lenn_ros.core.overload`);
- **the graph**: a publisher of another type stops the node at its start (later: said); who
  publishes goes to the session (pairing by sequence number needs one publisher of both);
  a QoS that cannot match is said with the override that fixes it;
- **the watchdog**: an input whose matched publishers deliver nothing, or far below their rate,
  is said with its publishers, counted and resubscribed (:mod:`lenn_ros.core.watchdog`).
"""

from __future__ import annotations

import time
from typing import Any

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from std_msgs.msg import Int64

from lenn_ros import topics
from lenn_ros.config import field_extractor
from lenn_ros.core.fields import FieldError, has_header, stamp_seconds
from lenn_ros.core.holding import START_GRACE
from lenn_ros.core.pairing import U, Y
from lenn_ros.core.watchdog import InputWatchdog
from lenn_ros.nodes import DRAIN_SECONDS, InputsNode, rclpy_internals, watched_publishers
from lenn_ros.nodes.node_parameters import QOS_OVERRIDES, NodeParameters
from lenn_ros.session import Notice


class IdentifierInputs:
    """The node's input subscriptions and what happens to each message taken from them (module docstring)."""

    def __init__(self, node: Any, parameters: NodeParameters, message_types: dict[str, Any], separate: bool) -> None:
        """``node``: the identifier (its session, its publishing, its log); ``separate``: u and y_p on a participant
        of their own (``companion``, which the node's loop must serve too)."""
        self.node, self.parameters, self.message_types = node, parameters, message_types
        values = parameters.values
        self.values = values
        self.extract = {channel: field_extractor(values, channel) for channel in (U, Y)}
        self.stamped = {
            channel: has_header(cls) and values["use_header_stamp"] for channel, cls in message_types.items()
        }
        reliability = ReliabilityPolicy.RELIABLE if values["pairing"] == "sequence" else ReliabilityPolicy.BEST_EFFORT
        self.profile = QoSProfile(depth=topics.DATA_DEPTH, reliability=reliability)
        self.companion = InputsNode(node) if separate else None
        owner = self.companion or node
        # first, and on the inputs' participant: a lockstep publisher that sees our data readers
        # in the graph sees this one too, and waits until it has the latched index before sample 1
        self.test_start = owner.create_subscription(
            Int64, node.resolve_topic_name(topics.TEST_START), self._on_test_start, topics.latched_qos()
        )
        self.subscriptions = {
            (channel, part): self._subscribe(channel, part, name) for channel, part, name in node.inputs
        }
        self.names = {key: subscription.topic_name for key, subscription in self.subscriptions.items()}
        self.node_name = owner.get_fully_qualified_name()  # whom `ros2 topic info -v` names as their subscriber
        self.watchdog = InputWatchdog(timeout=values["input_timeout"]) if values["input_timeout"] else None
        self.sim_time = bool(node.get_parameter("use_sim_time").value)

    def queue_depth(self) -> int:
        """What the queues really hold, after the overrides (0: KEEP_ALL, no depth to overflow)."""
        kept = [s.qos_profile for s in self.subscriptions.values()]
        return min(qos.depth for qos in kept) if all(qos.history != HistoryPolicy.KEEP_ALL for qos in kept) else 0

    def _subscribe(self, channel: str, part: int, name: str) -> Any:
        """One input's subscription, raw, with the QoS-mismatch event said in one line."""
        node = self.node
        events = SubscriptionEventCallbacks(incompatible_qos=lambda event, c=channel: self._on_incompatible_qos(c))
        callback = lambda message, info, c=channel, p=part: self._on_message(c, message, info, p)  # noqa: E731
        message_type = self.message_types[channel]
        if self.companion is None:
            return node.create_subscription(
                message_type, name, callback, self.profile, event_callbacks=events,
                qos_overriding_options=QOS_OVERRIDES, raw=True,
            )  # fmt: skip
        return self.companion.create_subscription(
            message_type, node.resolve_topic_name(name), callback, self.parameters.overridden_qos(name, self.profile),
            event_callbacks=events, raw=True,
        )  # fmt: skip

    def resubscribe(self, topic: str) -> None:
        """The watchdog's remedy for an input that matched publishers no longer deliver: a new subscription (a new
        reader in the middleware), the old one destroyed (the wait-set loop picks the new one up at its next turn)."""
        for (channel, part, name), key in zip(self.node.inputs, self.subscriptions, strict=True):
            old = self.subscriptions[key]
            if old.topic_name != topic:
                continue
            (self.companion or self.node).destroy_subscription(old)
            self.subscriptions[key] = self._subscribe(channel, part, name)

    def destroy(self) -> None:
        """No more input (the node stops): under a flood the middleware would go on queueing for the whole exit."""
        for subscription in self.subscriptions.values():
            (self.companion or self.node).destroy_subscription(subscription)
        self.subscriptions = {}

    # -- messages --------------------------------------------------------------------------------
    def _on_test_start(self, message: Int64) -> None:
        self.node.session.set_test_start(int(message.data))

    def _on_message(self, channel: str, message: Any, info: dict, part: int = 0) -> None:
        """One message from the executor, then every message already waiting on u and y_p.

        The executor rebuilds its wait set in Python for each message it hands over (most of the cost at
        kilohertz rates); taking what is queued straight from the subscriptions handles a burst in one
        wake-up. Pairing does not depend on the order in which u and y_p are taken (index, stamp or time
        decide). Under the wait-set loop, which takes what waits itself, a message the executor hands over
        (with a timer or a service due) is just offered: the service behind it in the executor's list
        comes sooner.
        """
        self.offer(channel, message, info, part)
        if not self.node.loop_takes_messages:
            self.drain()
        self.node.emit_notices()

    def drain(self) -> int:
        """Take test_start, u and y_p messages already waiting, until none is left or the turn's time is up;
        returns how many u / y_p messages it took (see the module docstring)."""
        taken, count = True, 0
        deadline = time.monotonic() + DRAIN_SECONDS
        while taken and time.monotonic() < deadline:
            taken = False
            latched = rclpy_internals.take(self.test_start, raw=False)  # the phase switches first
            if latched is not None:
                self._on_test_start(latched[0])
            for (other, part), subscription in self.subscriptions.items():
                waiting = rclpy_internals.take(subscription)
                if waiting is not None:
                    self.offer(other, waiting[0], waiting[1], part)
                    taken = True
                    count += 1
        return count

    def offer(self, channel: str, serialized: bytes, info: dict, part: int = 0) -> None:
        """One message as it was taken, serialised: shed unread if it waited too long, else read and offered.

        The subscriptions are raw so that shedding costs a take (8 us for a JointState) and
        not a deserialisation as well (30 us more): under a flood the node must shed faster
        than messages arrive to reach the newest again.
        """
        node, session = self.node, self.node.session
        arrived = info.get("received_timestamp")
        if self.watchdog is not None:
            self.watchdog.arrived(self.names[channel, part], time.monotonic())
        if arrived and not session.admit((channel, part), arrived * 1e-9, time.time()):
            return  # shed: the node is behind (counted, said by the session)
        message = deserialize_message(serialized, self.message_types[channel])
        received = arrived * 1e-9 if arrived and not self.sim_time else node.now()
        try:
            value = self.extract[channel](message)
        except FieldError as error:
            key = "u_field" if channel == U else "y_field"
            session.unreadable(channel, received, f"{key} {self.values[key]}", str(error))
            node.log(Notice("field", f"{node.u_name if channel == U else node.y_name}: {error}; message skipped"))
            return
        stamp = stamp_seconds(message) if self.stamped[channel] else None
        source = info.get("source_timestamp")
        if not session.publishers_known:
            self.check_graph()
        samples = session.offer(
            channel,
            value,
            stamp if stamp is not None else received,
            received=received,
            sequence=info.get("publication_sequence_number"),
            source_time=source * 1e-9 if source else None,
            part=part,
        )
        node.publish(samples)

    # -- the graph and the watchdog --------------------------------------------------------------
    def publishers_matched(self) -> dict[str, int]:
        """Publishers each input topic's subscription has matched: nothing arrives from one not counted
        here yet (DDS discovery), so a script that publishes as soon as the node is up can wait for it."""
        return {s.topic_name: s.get_publisher_count() for s in self.subscriptions.values()}

    def check_graph(self, at_start: bool = False) -> None:
        """What the graph offers on u / y_p: a wrong type is said here (or stops the node at its
        start); who publishes goes to the session, which decides about pairing by sequence number."""
        node = self.node
        publishers: dict[str, set] = {U: set(), Y: set()}
        for channel, _, topic in node.inputs:
            key = "u_type" if channel == U else "y_type"
            name = node.resolve_topic_name(topic)
            infos = node.get_publishers_info_by_topic(name)
            publishers[channel] |= {(info.node_namespace, info.node_name) for info in infos}
            wrong = sorted({info.topic_type for info in infos if info.topic_type != self.values[key]})
            if wrong:
                text = (
                    f"{name} is published as {', '.join(wrong)}, not {key} {self.values[key]}: "
                    f"pass -p {key}:={wrong[0]} and a matching -p {key[0]}_field:=..."
                )
                if at_start or time.monotonic() - node.started < START_GRACE:
                    raise SystemExit(f"identifier: {text}")  # discovery takes a moment: still "at start"
                node.node_counters["type_mismatch"] += 1
                node.log(Notice("type", text))
        node.session.graph_publishers(publishers)

    def _on_incompatible_qos(self, channel: str) -> None:
        node = self.node
        name = node.u_name if channel == U else node.y_name
        node.node_counters["qos_incompatible"] += 1
        node.log(
            Notice(
                "qos",
                f"a publisher on {name} offers a QoS this subscription cannot match (e.g. BEST_EFFORT against "
                f"RELIABLE), so nothing arrives: add -p qos_overrides.{name}.subscription.reliability:=best_effort",
            )
        )

    def watch(self) -> None:
        """The input watchdog's turn (core.watchdog): each stall or slow topic said with its matched publishers,
        a stalled one resubscribed."""
        if self.watchdog is None:
            return
        publishers = watched_publishers(self.node, self.subscriptions.values(), self.watchdog)
        for event in self.watchdog.check(time.monotonic(), publishers):
            self.node.log(Notice(f"input_{event.kind}", event.text, event.topic))
            if event.resubscribe:
                self.resubscribe(event.topic)

    def status(self) -> dict[str, Any]:
        """The watchdog's counters and the inputs stalled now (none without a watchdog)."""
        if self.watchdog is None:
            return {"counters": {}, "stalled": []}
        return {"counters": dict(self.watchdog.counters), "stalled": self.watchdog.stalled}
