"""Record a run's topics into a rosbag2/MCAP bag (``ros2 bag record`` is not pip-installable).

The node is a thin adapter around :class:`lenn_ros.bag.BagWriter`: raw (CDR)
subscriptions, so nothing is deserialised and any message type records; per message
the receive time (log time), the DDS source timestamp (publish time) and the DDS
publication sequence number (MCAP ``sequence``), so that ``evaluate`` and ``bag-info``
can pair and count exactly as the live identifier did.

Topics. The package's own topics (``topics.RUN_TOPICS``) with their types and QoS, plus
the identifier's inputs ``u`` and ``y_p`` *whatever their type*: ``u_type`` / ``y_type``
name it (default ``std_msgs/msg/Float64``, subscribed at once so nothing of a run is
missed); empty (or ``auto``) takes it from the graph when a publisher appears. Names
are remappable: ``-r u:=/robot/cmd -r y_p:=/robot/joint_states``. A publisher of
another type than the one given is said in one error line per type (DDS would never
deliver its messages, so without the line the topic would just stay silent).

QoS of u and y_p (parameter ``reliability``): ``auto`` (default) subscribes RELIABLE
while every publisher seen offers RELIABLE (our simulator; nothing may be lost) and
re-subscribes BEST_EFFORT, with one log line, as soon as a BEST_EFFORT publisher
appears (sensor drivers; a RELIABLE reader would never match it). Why not
``QoSOverridingOptions``: an override is fixed at start, while a robot's publishers
appear later; the graph tells what they offer. ``reliable``/``best_effort`` force one.
The depth is ``topics.DATA_DEPTH`` (10 s at 1 kHz) either way.

Stopping. SIGINT and SIGTERM only set a flag (rclpy's own handlers are not installed):
rclpy's handlers shut the context down at once, after which the samples already sitting
in the DDS reader queues can no longer be taken. Here the main loop sees the flag,
drains the executor until the queues stay empty, then closes the bag (complete, with
metadata.yaml).

SIGKILL cannot be caught. What it loses: the messages written since the last flush
(at most ``flush_period`` plus a quarter of it, see :mod:`lenn_ros.bag.writer`) **plus**
what DDS had received but the recorder had not yet taken, which is small when the
recorder keeps up. Measured at the publisher (``bench/recorder_kill.py``: u + y_p at 1 kHz
from another process, SIGKILL at a random moment while sending, counted after repair, on
a shared 2-core machine): ``flush_period`` 0.5 s: 288 ± 124 samples lost, max 489, over 16
runs (one run of an earlier 8 under heavy load: 1146, i.e. ~0.5 s of recorder lag on top
of the tail); ``flush_period`` 0.1 s: 44 ± 38, max 94, over 8 runs. The test asserts
loss <= rate x (1.25 x flush_period + 1 s).
``lenn-ros bag-repair`` rebuilds such a bag.
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from lenn_ros import topics
from lenn_ros.bag import DEFAULT_CHUNK_SIZE, BagError, BagWriter
from lenn_ros.bag.writer import SEQUENCE_UNSUPPORTED
from lenn_ros.nodes import rclpy_internals, run_node

#: The identifier's inputs: any type, QoS chosen from the graph, sequence gaps counted.
_INPUTS = {topics.U: "u_type", topics.Y_P: "y_type"}
_AUTO = ("", "auto")
_GRAPH_PERIOD = 0.25
#: Longest time one executor wake-up spends taking queued messages (then timers run).
_DRAIN_SECONDS = 0.05
#: Shortest time between two lines about samples lost on one topic (see ``_say_lost``).
LOST_REPORT_PERIOD = 5.0


class _Input:
    """State of one input topic (u or y_p): its type, subscription and what was said about it."""

    def __init__(self, name: str, resolved: str, type_name: str | None) -> None:
        self.name = name
        self.resolved = resolved
        self.type_name = type_name
        self.subscription: Any = None
        self.reliability: ReliabilityPolicy | None = None
        self.said: set[str] = set()


class Recorder(Node):
    """Subscribe to the run topics and write every message, as received, to one bag."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("recorder", **kwargs)
        self._declare_parameters()
        output = self.get_parameter("output").value or datetime.now().strftime("run_%Y%m%d_%H%M%S")
        flush_period = float(self.get_parameter("flush_period").value)
        names = list(self.get_parameter("topics").value)
        self.reliability = str(self.get_parameter("reliability").value).lower()
        specs = {spec.name: spec for spec in topics.run_topics(bool(self.get_parameter("mimo").value))}
        unknown = [name for name in names if name not in specs]
        if unknown:
            raise SystemExit(f"recorder: topics {unknown} are not lenn_ros topics; choose from {sorted(specs)}")
        if self.reliability not in ("auto", "reliable", "best_effort"):
            raise SystemExit(f"recorder: reliability {self.reliability!r}: use auto, reliable or best_effort")
        try:
            self.bag = BagWriter(
                Path(output), flush_period=flush_period, max_chunk_size=int(self.get_parameter("max_chunk_size").value)
            ).open()
        except BagError as err:
            raise SystemExit(f"recorder: {err}") from None
        self.counts: Counter[str] = Counter()
        self.gaps: Counter[str] = Counter()
        self.problems: Counter[str] = Counter()
        self._last_seq: dict[str, int] = {}
        self._lost_pending: dict[str, list[float]] = {}  # per topic: samples, gaps since the last line, its time
        self._subs: list[Any] = []  # (not ``_subscriptions``: rclpy's Node uses that name)
        self._name_of: dict[int, str] = {}  # id(subscription) -> the run topic it records
        self._bag_topic: dict[str, str] = {}  # short name -> resolved name stored in the bag
        self._registered: set[str] = set()  # bag topics of u / y_p added to the bag (see _register_input)
        self._inputs: dict[str, _Input] = {}
        self._names = names
        for name in names:
            if name in _INPUTS:
                self._add_input(name)
            else:
                self._subscribe_own(specs[name])
        # Flushes a quiet bag too: pending data is on disk within 1.25 * flush_period.
        self.create_timer(flush_period / 4, self.bag.maybe_flush)
        if self._inputs:
            self.create_timer(_GRAPH_PERIOD, self._check_graph)
            self._check_graph()
        shown = [self._bag_topic.get(n) or f"{self._inputs[n].resolved} (type from the graph)" for n in names]
        self.get_logger().info(f"recording {', '.join(shown)} into {self.bag.path}")

    def _declare_parameters(self) -> None:
        def declare(name: str, value: Any, description: str, **ranges: Any) -> None:
            self.declare_parameter(name, value, ParameterDescriptor(description=description, read_only=True, **ranges))

        declare("output", "", "Bag directory to create (must not exist). Empty: run_<date>_<time> in the working dir.")
        declare("topics", [spec.name for spec in topics.RUN_TOPICS], "lenn_ros topics to record (remappable).")
        declare("u_type", topics.FLOAT64, "Message type of u; empty or 'auto': from the graph once published.")
        declare("y_type", topics.FLOAT64, "Message type of y_p; empty or 'auto': from the graph.")
        declare("mimo", False, "A run with several channels: y_hat and error are Float64MultiArray (README: MIMO).")
        declare("reliability", "auto", "u/y_p subscriptions: auto (follow the publishers), reliable or best_effort.")
        declare(
            "flush_period",
            0.5,
            "Seconds between forced chunk writes: a SIGKILL loses at most about this much data.",
            floating_point_range=[FloatingPointRange(from_value=0.01, to_value=60.0)],
        )
        declare(
            "max_chunk_size",
            DEFAULT_CHUNK_SIZE,
            "Bytes after which a chunk is written even before flush_period.",
            integer_range=[IntegerRange(from_value=1024, to_value=64 * DEFAULT_CHUNK_SIZE)],
        )

    # -- subscriptions
    def _subscribe_own(self, spec: topics.TopicSpec) -> None:
        qos = topics.qos_for(spec)
        sub = self.create_subscription(
            topics.message_class(spec.type_name), spec.name, self._callback_for(spec.name), qos, raw=True
        )
        self._subs.append(sub)
        self._name_of[id(sub)] = spec.name
        self._bag_topic[spec.name] = sub.topic_name
        self.bag.add_topic(sub.topic_name, spec.type_name, qos)

    def _add_input(self, name: str) -> None:
        given = str(self.get_parameter(_INPUTS[name]).value).strip()
        resolved = self.resolve_topic_name(name)
        entry = _Input(name, resolved, None if given.lower() in _AUTO else given)
        self._inputs[name] = entry
        if entry.type_name is not None:
            try:
                topics.message_class(entry.type_name)
            except ValueError as err:
                raise SystemExit(f"recorder: {_INPUTS[name]}: {err}") from None
            self._subscribe_input(entry, self._wanted_reliability([]), offered=None)

    def _wanted_reliability(self, infos: list[Any]) -> ReliabilityPolicy:
        if self.reliability != "auto":
            return ReliabilityPolicy.RELIABLE if self.reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT
        offered = {info.qos_profile.reliability for info in infos}
        return ReliabilityPolicy.BEST_EFFORT if ReliabilityPolicy.BEST_EFFORT in offered else ReliabilityPolicy.RELIABLE

    def _subscribe_input(self, entry: _Input, reliability: ReliabilityPolicy, offered: list[Any] | None) -> None:
        """(Re)create the raw subscription of u or y_p; the bag topic is added the first time."""
        assert entry.type_name is not None
        if entry.subscription is not None:
            self.destroy_subscription(entry.subscription)
            self._subs.remove(entry.subscription)
            self._name_of.pop(id(entry.subscription), None)
        qos = QoSProfile(depth=topics.DATA_DEPTH, reliability=reliability)
        # No QoS event handlers: destroying a subscription whose event handler is in the executor's
        # wait set crashes rclpy 7.1 (SystemError); the graph check below sees incompatible publishers.
        events = SubscriptionEventCallbacks(use_default_callbacks=False)
        entry.subscription = self.create_subscription(
            topics.message_class(entry.type_name),
            entry.name,
            self._callback_for(entry.name),
            qos,
            raw=True,
            event_callbacks=events,
        )
        entry.reliability = reliability
        self._subs.append(entry.subscription)
        self._name_of[id(entry.subscription)] = entry.name
        self._bag_topic.setdefault(entry.name, entry.subscription.topic_name)
        if offered:
            self._register_input(entry, offered)

    def _register_input(self, entry: _Input, offered: list[Any] | None = None) -> None:
        """Add u or y_p to the bag, once, with the QoS its publishers offer (``offered_qos_profiles``), as
        rosbag2 stores it: not our subscription's (RELIABLE, depth 10 000), which is what a typed input
        subscribed at start would otherwise record for a BEST_EFFORT depth-10 driver. Deferred until the
        graph shows a publisher or the first message comes; at the end, a topic that had none."""
        topic = self._bag_topic[entry.name]
        if topic in self._registered or entry.type_name is None:
            return
        if not offered:
            infos = self.get_publishers_info_by_topic(entry.resolved)
            offered = [info.qos_profile for info in infos if info.topic_type == entry.type_name]
        if not offered and entry.subscription is not None:
            offered = [entry.subscription.qos_profile]
            self.get_logger().info(
                f"{entry.resolved}: no publisher in the graph, so the bag stores the subscription's QoS as offered"
            )
        self._registered.add(topic)
        self.bag.add_topic(topic, entry.type_name, offered)

    # -- the graph
    def _check_graph(self) -> None:
        for entry in self._inputs.values():
            infos = self.get_publishers_info_by_topic(entry.resolved)
            if entry.type_name is None and infos:
                self._adopt_type(entry, infos)
            if entry.type_name is None:
                continue
            self._say_wrong_types(entry, infos)
            matching = [info for info in infos if info.topic_type == entry.type_name]
            wanted = self._wanted_reliability(matching)
            best_effort = any(info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for info in matching)
            if best_effort and entry.reliability == ReliabilityPolicy.RELIABLE and self.reliability == "reliable":
                self._problem(entry, "qos", f"{entry.resolved}: a BEST_EFFORT publisher never reaches this RELIABLE "
                              "subscription (nothing arrives from it); run with -p reliability:=auto")  # fmt: skip
            elif wanted == ReliabilityPolicy.BEST_EFFORT and entry.reliability == ReliabilityPolicy.RELIABLE:
                self.get_logger().info(
                    f"{entry.resolved}: a BEST_EFFORT publisher appeared; subscribing BEST_EFFORT "
                    "(a RELIABLE reader never matches it); losses show as sequence gaps"
                )
                self._subscribe_input(entry, wanted, [info.qos_profile for info in matching])
            if matching and entry.name in self._bag_topic:
                self._register_input(entry, [info.qos_profile for info in matching])

    def _adopt_type(self, entry: _Input, infos: list[Any]) -> None:
        offered = sorted({info.topic_type for info in infos})
        entry.type_name = offered[0]
        if len(offered) > 1:
            self._problem(entry, "several", f"{entry.resolved} is published as {', '.join(offered)}: recording "
                          f"{offered[0]}; pass -p {_INPUTS[entry.name]}:=TYPE to choose")  # fmt: skip
        try:
            topics.message_class(entry.type_name)
        except ValueError as err:
            self._problem(entry, "missing", f"{entry.resolved}: cannot record: {err}")
            entry.type_name = None
            return
        self.get_logger().info(f"{entry.resolved}: recording as {entry.type_name} (type taken from the graph)")
        matching = [info for info in infos if info.topic_type == entry.type_name]
        self._subscribe_input(entry, self._wanted_reliability(matching), [info.qos_profile for info in matching])

    def _say_wrong_types(self, entry: _Input, infos: list[Any]) -> None:
        for info in infos:
            if info.topic_type != entry.type_name:
                node = f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                key = _INPUTS[entry.name]
                self._problem(
                    entry,
                    f"type {info.topic_type}",
                    f"{entry.resolved} is published as {info.topic_type} (by {node}), not {key} {entry.type_name}: "
                    f"its messages are NOT recorded; pass -p {key}:={info.topic_type}",
                )

    def _problem(self, entry: _Input, key: str, text: str) -> None:
        """One error line per problem and topic, counted (shown again in the exit summary)."""
        if key not in entry.said:
            entry.said.add(key)
            self.problems[entry.name] += 1
            self.get_logger().error(text)

    # -- messages
    def _callback_for(self, name: str) -> Callable[[bytes, dict[str, int]], None]:
        # Two parameters: rclpy then passes the message info (sequence number, timestamps).
        def on_message(msg: bytes, msg_info: dict[str, int]) -> None:
            self._on_message(name, msg, msg_info)
            self._take_waiting()

        return on_message

    def _take_waiting(self) -> None:
        """Take what is already queued on every subscription, for at most ``_DRAIN_SECONDS``.

        The executor hands over one message per wake-up and rebuilds its wait set in
        Python each time: about 4 000 messages/s here, less than a lockstep run with its
        eleven topics produces, so the DDS queues overflowed and the bag lost messages.
        Taking the waiting messages straight from the subscriptions handles a burst in
        one wake-up; the time bound leaves the flush timer its turn (the SIGKILL bound).
        """
        deadline = time.monotonic() + _DRAIN_SECONDS
        taken = True
        while taken and time.monotonic() < deadline:
            taken = False
            for subscription in list(self._subs):
                name = self._name_of.get(id(subscription))
                if name is None:
                    continue
                waiting = rclpy_internals.take(subscription)
                if waiting is not None:
                    self._on_message(name, waiting[0], waiting[1])
                    taken = True

    #: earliest receive time (system clock, as the middleware's) of the messages taken since :meth:`drain` reset it
    _oldest_taken_ns = 0

    def _on_message(self, name: str, data: bytes, info: dict[str, int]) -> None:
        if name in self._inputs and self._bag_topic[name] not in self._registered:
            self._register_input(self._inputs[name])
        stamp = info.get("received_timestamp") or self.get_clock().now().nanoseconds
        self._oldest_taken_ns = min(self._oldest_taken_ns, stamp)
        sequence = int(info.get("publication_sequence_number", 0))
        self.bag.write_raw(
            self._bag_topic[name], data, stamp, publish_time_ns=info.get("source_timestamp", 0), sequence=sequence
        )
        self.counts[name] += 1
        if name in _INPUTS:
            self._check_sequence(name, sequence)

    def _check_sequence(self, name: str, seq: int) -> None:
        """Count samples the middleware lost; assumes one publisher per topic, as the package does."""
        if seq in (0, SEQUENCE_UNSUPPORTED):
            return
        last = self._last_seq.get(name)
        self._last_seq[name] = seq
        if last is None:
            return
        if seq > last + 1:
            self.gaps[name] += seq - last - 1
            self._say_lost(name, seq - last - 1, seq)
        elif seq <= last:
            self.get_logger().info(f"{name}: sequence restarted at {seq} (new publisher?)")

    def _say_lost(self, name: str, lost: int, seq: int) -> None:
        """One line per topic at most every ``LOST_REPORT_PERIOD`` s: the first gap at once, then a summary.

        A flooded topic loses samples in thousands of small gaps; a line for each filled the
        log, and a recorder whose stderr is a pipe nobody reads blocked on it (bench/robot_day.py:
        the recorder never caught up after a burst). The totals are in the final summary line.
        """
        now = time.monotonic()
        pending = self._lost_pending.setdefault(name, [0, 0, -math.inf])  # samples, gaps, last said at
        pending[0] += lost
        pending[1] += 1
        if now - pending[2] < LOST_REPORT_PERIOD:
            return
        samples, gaps, said = pending
        since = "" if said == -math.inf else f" in the last {now - said:.0f} s"
        self.get_logger().warning(
            f"{name}: {samples} samples lost in {gaps} gap(s){since} (last before sequence number {seq}); "
            f"{self.gaps[name]} in all so far"
        )
        self._lost_pending[name] = [0, 0, now]

    # -- stopping
    def drain(self, executor: SingleThreadedExecutor, quiet: float = 0.2, limit: float = 30.0) -> None:
        """Take what the DDS queues held when the stop came: until nothing arrives for ``quiet`` s.

        A recorder lags a fast lockstep run by seconds (it writes every topic), and what
        its readers hold when it stops is already acknowledged to the publishers, which
        may be gone: it exists nowhere else. With publishers still running it never goes
        quiet: it ends after a wake-up in which every message taken was received after the
        stop (one wake-up takes from every subscription in turn, each queue oldest first,
        so then no queue holds backlog), and ``limit`` ends it in any case, saying so.
        """
        start = time.monotonic()
        stop_ns = time.time_ns()
        end = start + limit
        calm_until = start + quiet
        backlog_in = False
        while not backlog_in and time.monotonic() < min(calm_until, end):
            before = self.counts.total()
            self._oldest_taken_ns = sys.maxsize
            executor.spin_once(timeout_sec=0.02)
            if self.counts.total() != before:
                calm_until = time.monotonic() + quiet
                backlog_in = self._oldest_taken_ns > stop_ns
        if not backlog_in and time.monotonic() >= end:
            self.get_logger().warning(
                f"messages were still arriving {limit:.0f} s after the stop: the bag ends there, "
                "what came later is not in it"
            )

    def shutdown(self) -> None:
        """On the way out (after :meth:`drain`): close the bag, say what is in it."""
        print(self.close(), flush=True)

    def close(self) -> str:
        """Close the bag and return the one-line summary printed at exit."""
        for entry in self._inputs.values():
            if entry.name in self._bag_topic:
                self._register_input(entry)  # (a topic that never had a publisher is still listed)
        self.bag.close()
        counts = ", ".join(f"{name}: {self.counts[name]}" for name in self._names)
        lost = sum(self.gaps.values())
        gaps = f"; {lost} samples lost ({dict(self.gaps)})" if lost else ""
        problems = f"; problems (see the error lines above): {dict(self.problems)}" if self.problems else ""
        return f"recorder: wrote {self.bag.path} ({counts}){gaps}{problems}"


def main(args: list[str] | None = None) -> int:
    return run_node(Recorder, "recorder", args)


if __name__ == "__main__":
    sys.exit(main())
