"""Record a run's topics into a rosbag2/MCAP bag (``ros2 bag record`` is not pip-installable).

The node is a thin adapter around :class:`lenn_ros.bag.BagWriter`: raw (CDR) subscriptions
so nothing is deserialised, the QoS of :mod:`lenn_ros.topics` so the RELIABLE queues
match the publishers, and the receive time as log time, as rosbag2 does.

Stopping. SIGINT and SIGTERM only set a flag (rclpy's own handlers are not installed):
rclpy's handlers shut the context down at once, after which the samples already sitting
in the DDS reader queues can no longer be taken. Here the main loop sees the flag,
drains the executor until the queues stay empty, then closes the bag. SIGKILL cannot be
caught; the bound on what it loses is the writer's ``flush_period`` / ``max_chunk_size``
(see :mod:`lenn_ros.bag`), and ``lenn-ros bag-repair`` rebuilds such a bag.
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from lenn_ros import topics
from lenn_ros.bag import DEFAULT_CHUNK_SIZE, BagWriter
from lenn_ros.nodes import run_node

#: rmw reports this (or 0) when the middleware has no publication sequence numbers.
_SEQ_UNSUPPORTED = 2**64 - 1
#: Topics whose publication sequence numbers are the sample index (see lenn_ros.topics).
_SEQUENCED = (topics.U, topics.Y_P)


class Recorder(Node):
    """Subscribe to the run topics and write every message, as received, to one bag."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("recorder", **kwargs)
        self.declare_parameter(
            "output",
            "",
            ParameterDescriptor(
                description="Bag directory to create (must not exist). Empty: run_<date>_<time> in the working dir.",
                read_only=True,
            ),
        )
        self.declare_parameter(
            "topics",
            [spec.name for spec in topics.RUN_TOPICS],
            ParameterDescriptor(
                description="Names of the lenn_ros topics to record (relative, remappable).", read_only=True
            ),
        )
        self.declare_parameter(
            "flush_period",
            0.5,
            ParameterDescriptor(
                description="Seconds between forced chunk writes: a SIGKILL loses at most about this much data.",
                floating_point_range=[FloatingPointRange(from_value=0.01, to_value=60.0)],
                read_only=True,
            ),
        )
        self.declare_parameter(
            "max_chunk_size",
            DEFAULT_CHUNK_SIZE,
            ParameterDescriptor(
                description="Bytes after which a chunk is written even before flush_period (default 1 MiB).",
                integer_range=[IntegerRange(from_value=1024, to_value=DEFAULT_CHUNK_SIZE)],
                read_only=True,
            ),
        )
        output = self.get_parameter("output").value or datetime.now().strftime("run_%Y%m%d_%H%M%S")
        flush_period = float(self.get_parameter("flush_period").value)
        names = list(self.get_parameter("topics").value)
        specs = {spec.name: spec for spec in topics.RUN_TOPICS}
        unknown = [name for name in names if name not in specs]
        if unknown:
            raise ValueError(f"topics {unknown} are not lenn_ros topics; choose from {sorted(specs)}")

        self.bag = BagWriter(
            Path(output),
            flush_period=flush_period,
            max_chunk_size=int(self.get_parameter("max_chunk_size").value),
        ).open()
        self.counts: Counter[str] = Counter()
        self.gaps: Counter[str] = Counter()
        self._last_seq: dict[str, int] = {}
        self._subs = []  # (not ``_subscriptions``: rclpy's Node uses that name)
        self._bag_topic: dict[str, str] = {}  # short name -> resolved name stored in the bag
        for name in names:
            spec = specs[name]
            qos = topics.qos_for(spec)
            sub = self.create_subscription(
                topics.message_class(spec.type_name), name, self._callback_for(name), qos, raw=True
            )
            self._subs.append(sub)
            self._bag_topic[name] = sub.topic_name
            self.bag.add_topic(sub.topic_name, spec.type_name, qos)
        # Flushes a quiet bag too: pending data is on disk within 1.25 * flush_period.
        self.create_timer(flush_period / 4, self.bag.maybe_flush)
        self.get_logger().info(f"recording {', '.join(self._bag_topic.values())} into {self.bag.path}")

    def _callback_for(self, name: str) -> Callable[[bytes, dict[str, int]], None]:
        # Two parameters: rclpy then passes the message info (sequence number, timestamps).
        def on_message(msg: bytes, msg_info: dict[str, int]) -> None:
            self._on_message(name, msg, msg_info)

        return on_message

    def _on_message(self, name: str, data: bytes, info: dict[str, int]) -> None:
        stamp = info.get("received_timestamp") or self.get_clock().now().nanoseconds
        self.bag.write_raw(self._bag_topic[name], data, stamp)
        self.counts[name] += 1
        if name in _SEQUENCED:
            self._check_sequence(name, int(info.get("publication_sequence_number", 0)))

    def _check_sequence(self, name: str, seq: int) -> None:
        """Count samples the middleware lost; assumes one publisher per topic, as the package does."""
        if seq in (0, _SEQ_UNSUPPORTED):
            return
        last = self._last_seq.get(name)
        self._last_seq[name] = seq
        if last is None:
            return
        if seq > last + 1:
            self.gaps[name] += seq - last - 1
            self.get_logger().warning(f"{name}: {seq - last - 1} samples lost before sequence number {seq}")
        elif seq <= last:
            self.get_logger().info(f"{name}: sequence restarted at {seq} (new publisher?)")

    def drain(self, executor: SingleThreadedExecutor, quiet: float = 0.2, limit: float = 5.0) -> None:
        """Take what the DDS queues still hold: spin until nothing arrives for ``quiet`` seconds."""
        end = time.monotonic() + limit
        calm_until = time.monotonic() + quiet
        while time.monotonic() < min(calm_until, end):
            before = self.counts.total()
            executor.spin_once(timeout_sec=0.02)
            if self.counts.total() != before:
                calm_until = time.monotonic() + quiet

    def shutdown(self) -> None:
        """On the way out (after :meth:`drain`): close the bag, say what is in it."""
        print(self.close(), flush=True)

    def close(self) -> str:
        """Close the bag and return the one-line summary printed at exit."""
        self.bag.close()
        counts = ", ".join(f"{name}: {self.counts[name]}" for name in self._bag_topic)
        lost = sum(self.gaps.values())
        gaps = f"; {lost} samples lost ({dict(self.gaps)})" if lost else ""
        return f"recorder: wrote {self.bag.path} ({counts}){gaps}"


def main(args: list[str] | None = None) -> int:
    return run_node(Recorder, "recorder", args)


if __name__ == "__main__":
    sys.exit(main())
