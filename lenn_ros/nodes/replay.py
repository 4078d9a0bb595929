"""Publish a recorded run (``u``, ``y_p`` and the latched ``test_start``) back into the graph.

Why a node and not ``ros2 bag play``: rosbag2 is not pip-installable, and the identifier
pairs u(k) with y_p(k) by *publication sequence number*, which only holds if one node
publishes u(k) then y_p(k), once each, for every k. ``ros2 bag play`` (where installed)
keeps them aligned too when it plays both topics from the start, but cannot pace by the
identifier's progress.

What is published (``source``): sample k of the recording as the k-th u and y_p, so a
lost or reordered message in the bag shifts nothing.

* ``auto`` (default): the identifier's recorded ``samples`` topic when the bag has it
  (the pairs it formed live, so the replayed run is the live one whatever the recorder
  lost of u / y_p), else ``raw``;
* ``samples``: that topic, or an error;
* ``raw``: the recording's input topics paired as the identifier pairs them
  (:func:`lenn_ros.service.recording.read_recording`, as evaluate and fit read them): by the
  recorded sequence number, or on the grid or stamps the parameters name; a restart of the
  numbering at 1 is a new stream, published through new publishers as a loop pass is. A bag
  without sequence numbers is paired by order, and only when both counts match.

What is read is said as the identifier is told it, by parameters spelled like its own
(``u_topics``, ``u_field``, ``u_names``, ``y_topics``, ``y_field``, ``y_names``, ``pairing``,
``sample_period``, ``slop``; empty: what the bag's ``identifier_config`` says, else ``u`` and
``y_p``), so a robot's own bag replays as the samples the identifier would form from it.

A sample index the recording does not hold whole (a half lost, or an index neither holds) is
still published, NaN: the identifier screens NaN (counted, the pair skipped, its history
restarted there) instead of pairing later samples off by one. One log line says how many.

Pacing (``rate``):

* ``rate > 0``: the recorded spacing (log times of ``u``; from ``samples``, the sample
  times), divided by ``rate``.
* ``rate == 0``: as fast as possible *without loss*. Replay first waits for subscribers,
  publishes RELIABLE (``topics.data_qos``), and keeps every subscriber's queue of
  ``topics.DATA_DEPTH`` samples from overflowing in one of two ways:

  - once an identifier is seen (a publisher on ``y_hat``; looked up every 128 samples)
    and ``max_in_flight > 0``: back-pressure. At most ``max_in_flight`` (default
    DATA_DEPTH / 2) samples are published ahead of the ``y_hat`` messages received (or
    of its ``samples`` messages, if more: a skipped NaN sample has no y_hat).
    If no ``y_hat`` arrives for ``wait_timeout`` seconds, replay falls back to:
  - a fixed cap of ``max_rate_hz`` samples per second (default 1000, the rate for which
    DATA_DEPTH gives a stalled subscriber 10 s before it loses anything).

Before exiting, replay waits until every subscriber has acknowledged every sample.

Several channels (MIMO): a bag whose u / y_p are Float64MultiArray (a recorded MIMO run,
an ``import-csv`` with several columns), or fields that name several channels, is replayed
the same way, as vector messages whose layout label names the channels.

Looping (``loop``): each pass is a new stream, as if the run were recorded again. Replay
waits until the last pass is acknowledged, then publishes through *new* publishers, so
the DDS publication sequence numbers (the sample index the identifier pairs by) start
at 1 again, re-publishes ``test_start``, and holds sample 2 until every reader has
acknowledged sample 1 (so both of a subscriber's readers know the new writers). Counting on instead would make the
identifier take pass 2 as samples N+1.. of one history: past ``test_start``, so learning
would stay frozen for every later pass.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from typing import Any

import numpy as np
import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rcl_interfaces.srv import SetParameters
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from lenn_ros import topics
from lenn_ros.bag import BagError
from lenn_ros.bag.vectors import read_test_start
from lenn_ros.config import side_channels
from lenn_ros.core.runs import finite_rows
from lenn_ros.nodes import TEST_START_UNMATCHED, latched_readers_matched
from lenn_ros.nodes.channels import Channels
from lenn_ros.service import RecordingError
from lenn_ros.service.recording import numbered_rows, read_recording

SOURCES = ("auto", "samples", "raw")
#: What is read from the bag, spelled like the identifier's parameters ('' / [''] / 0: what the bag says).
READING_PARAMETERS = (
    ("u_topics", [""], "the bag's input topic(s), as the identifier's -r u:=TOPIC / u_topics ([''] = u)"),
    ("y_topics", [""], "the bag's output topic(s) ([''] = y_p)"),
    ("u_field", "", "field of the input message, e.g. data[1] ('' = the identifier's u_field, else data)"),
    ("y_field", "", "field of the output message, e.g. position[elbow]"),
    ("u_names", [""], "the input channels' names (u_names)"),
    ("y_names", [""], "the output channels' names (y_names)"),
    ("pairing", "", "how the topics become samples: sequence, stamp or sample ('' = as recorded, else sequence)"),
    ("sample_period", 0.0, "sample pairing: seconds between samples"),
    ("slop", 0.0, "stamp pairing: largest |t_u - t_y| of a pair, seconds"),
)


class Replay(Node):
    """Publishes one bag's samples; :meth:`run` does the publishing so main() controls the loop."""

    def __init__(self, stop: threading.Event | None = None, **kwargs: Any) -> None:
        super().__init__("replay", **kwargs)
        self._declare("bag", "", "Bag directory (or .mcap) to replay; needs u and y_p topics.")
        self._declare(
            "rate",
            1.0,
            "Speed: 1.0 = recorded timing, 2.0 = twice as fast, 0 = as fast as possible without loss.",
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1000.0)],
        )
        self._declare("loop", False, "Start again from the first sample when done (until SIGINT).")
        self._declare(
            "source",
            "auto",
            "What to publish: 'samples' (the identifier's recorded pairs), 'raw' (u/y_p paired by sequence "
            "number) or 'auto' (samples if the bag has them, else raw).",
        )
        self._declare(
            "wait_for_subscribers",
            1,
            "Subscribers that u and y_p must each have before the first sample is sent.",
            integer_range=[IntegerRange(from_value=0, to_value=100)],
        )
        self._declare(
            "wait_timeout",
            30.0,
            "Seconds to wait for subscribers (and, with rate 0, for y_hat progress); 0 = forever.",
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=3600.0)],
        )
        self._declare(
            "max_rate_hz",
            1000.0,
            "With rate 0 and no y_hat feedback: samples per second cap (0 = no cap).",
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1.0e6)],
        )
        self._declare(
            "max_in_flight",
            topics.DATA_DEPTH // 2,
            "With rate 0: samples published ahead of the y_hat messages received (0 = ignore y_hat).",
            integer_range=[IntegerRange(from_value=0, to_value=topics.DATA_DEPTH)],
        )
        self._declare(
            "apply_changes",
            True,
            "Set the live parameter changes the bag recorded (identifier_config) on the identifier at their samples.",
        )
        self._declare("identifier", "/identifier", "The identifier node whose parameters apply_changes sets.")
        for name, default, text in READING_PARAMETERS:
            self._declare(name, default, text)
        self.stop = stop or threading.Event()
        bag = self.get_parameter("bag").value
        if not bag:
            raise BagError("parameter 'bag' is empty; run with --ros-args -p bag:=PATH")
        self.bag = bag
        self._load(str(self._param("source")))
        self._schedule_changes()
        self.published = 0
        self.y_hat_count = 0
        self.samples_count = 0
        self._feedback_allowed = False
        self._identifier_seen = False
        self._next_slot = 0.0
        self.passes = 0
        self._open_stream()
        self.pub_start = None
        if self.test_start is not None:
            int_msg = topics.message_class(topics.INT64)
            self.pub_start = self.create_publisher(int_msg, topics.TEST_START, topics.latched_qos())
        self.create_subscription(self.channels.message_type, topics.Y_HAT, self._on_y_hat, topics.data_qos())
        array = topics.message_class(topics.FLOAT64_ARRAY)
        self.create_subscription(array, topics.SAMPLES, self._on_sample, topics.data_qos(), raw=True)

    def _reading(self) -> dict[str, Any]:
        """What is read, from the parameters spelled like the identifier's (see the module docstring)."""
        listed = {side: [str(t) for t in self._param(f"{side}_topics") if str(t).strip()] for side in ("u", "y")}
        names = {side: ",".join(str(n) for n in self._param(f"{side}_names") if str(n).strip()) for side in ("u", "y")}
        return {
            "u": listed["u"], "y": listed["y"], "u_field": self._param("u_field"), "y_field": self._param("y_field"),
            "u_names": names["u"], "y_names": names["y"], "pairing": self._param("pairing") or None,
            "sample_period": self._param("sample_period") or None, "slop": self._param("slop") or None,
        }  # fmt: skip

    def _load(self, source: str) -> None:
        """Sample k of each publisher run at its k-th row (NaN where the recording does not hold it whole)."""
        if source not in SOURCES:
            raise ValueError(f"source {source!r} is not one of {', '.join(SOURCES)}")
        try:
            read = read_recording(self.bag, self._reading(), recorded=source != "raw")
        except RecordingError as error:
            raise BagError(str(error)) from None
        samples = read.samples
        if source == "samples" and samples.source != "samples":
            raise BagError(f"{self.bag}: no identifier samples topic in the bag; use source:=raw")
        rows, self.run_of = numbered_rows(samples.index)
        shape = (len(self.run_of), *np.shape(samples.u)[1:])
        self.u, self.y_p = np.full(shape, np.nan), np.full((len(self.run_of), *np.shape(samples.y)[1:]), np.nan)
        self.u[rows], self.y_p[rows] = samples.u, samples.y
        self.index = np.concatenate([np.arange(1, n + 1) for n in np.bincount(self.run_of)]) if rows.size else rows
        times = np.full(len(self.run_of), np.nan)
        times[rows] = samples.time
        self.offsets = _due(times)
        self.stream_starts = {int(k) for k in np.flatnonzero(np.diff(self.run_of)) + 1}
        self.test_start = read_test_start(self.bag)
        names = {side: side_channels(read.values, side)[0] for side in ("u", "y")}
        self.channels = Channels(names, vector=np.ndim(self.u) == 2)  # (the recording's samples are vectors)
        self._say_loaded(read, rows)

    def _say_loaded(self, read: Any, rows: np.ndarray) -> None:
        """One line: what is replayed, in how many streams, and how many sample indices it lacks."""
        samples = read.samples
        what = samples.source if samples.source != "samples" else "the identifier's samples"
        if samples.source == "samples":
            refused = int(np.count_nonzero(~(finite_rows(samples.u) & finite_rows(samples.y))))
            what += f" ({refused} refused live, as NaN)"
        channels = f"{np.size(self.u[:1])} input(s) and {np.size(self.y_p[:1])} output(s)"
        line = f"replaying {what}: {channels}, {len(self.run_of)} samples in {len(self.stream_starts) + 1} stream(s)"
        counters = read.session.all_counters()
        dropped = sum(counters.get(name, 0) for name in ("duplicates", "stale"))
        tail = f"; {dropped} repeated or stale messages dropped" if dropped else ""
        absent = len(self.run_of) - rows.size
        if not absent:
            self.get_logger().info(f"{line}, all complete{tail}")
            return
        self.get_logger().warning(
            f"{line}; {absent} sample indices not whole in the recording (a half or both lost): published in place "
            f"as NaN, so the identifier skips each and restarts its history there; no later sample is shifted{tail}"
        )

    def _schedule_changes(self) -> None:
        """The recorded live changes by the row before which each is set (the first whose index reaches it)."""
        from lenn_ros.service.building import recorded_changes

        self._changes: dict[int, list[Any]] = {}
        changes = recorded_changes(self.bag)
        if not changes:
            return
        if not self._param("apply_changes"):
            self.get_logger().warning(
                f"{len(changes)} live parameter change(s) recorded in the bag are NOT set (apply_changes false): "
                "the identifier learns with its starting values throughout"
            )
            return
        self._set_parameters = self.create_client(SetParameters, f"{self._param('identifier')}/set_parameters")
        first_stream = self.index[self.run_of == 0]  # (the changes were made during the first)
        for change in changes:
            row = int(np.searchsorted(first_stream, change.from_index, side="left"))
            if row >= first_stream.size:
                self.get_logger().warning(f"live change {change.values} from sample {change.from_index}, after the "
                                          "last sample replayed: not set (no sample learns with it)")  # fmt: skip
                continue
            self._changes.setdefault(row, []).append(change)
        self.get_logger().info(
            f"{len(changes)} live parameter change(s) recorded: each set on {self._param('identifier')} before "
            "its sample, once the identifier has handled every earlier one (first pass only)"
        )

    def _apply_changes(self, executor: SingleThreadedExecutor, row: int) -> None:
        """Before row ``row``: wait until the identifier has handled every sample published, then set each
        change through its parameter service (as ``ros2 param set``), so it takes effect from this sample."""
        from rclpy.parameter import Parameter

        end = time.monotonic() + self._settle_timeout()
        while self._progress() < self.published and time.monotonic() < end and not self.stop.is_set():
            executor.spin_once(timeout_sec=0.02)
        for change in self._changes.get(row, []):
            shown = ", ".join(f"{name}={value!r}" for name, value in change.values.items())
            request = SetParameters.Request(
                parameters=[Parameter(name, value=value).to_parameter_msg() for name, value in change.values.items()]
            )
            if not self._set_parameters.wait_for_service(timeout_sec=self._settle_timeout()):
                self.get_logger().error(
                    f"sample {change.from_index}: no service {self._set_parameters.srv_name}: {shown} not set"
                )
                continue
            future = self._set_parameters.call_async(request)
            executor.spin_until_future_complete(future, timeout_sec=self._settle_timeout())
            results = future.result().results if future.result() is not None else []
            refused = [result.reason for result in results if not result.successful]
            if len(results) != len(change.values) or refused:
                self.get_logger().error(f"sample {change.from_index}: {shown} not set: {refused or 'no answer'}")
            else:
                self.get_logger().info(f"sample {change.from_index}: set {shown} (recorded live change)")

    def _open_stream(self) -> None:
        """Publishers for one pass: new ones start their publication sequence numbers at 1."""
        self.pub_u = self.create_publisher(self.channels.message_type, topics.U, topics.data_qos())
        self.pub_y = self.create_publisher(self.channels.message_type, topics.Y_P, topics.data_qos())

    def _restart_stream(self, executor: SingleThreadedExecutor, label: str) -> None:
        acked = self.wait_acked()
        if not acked:
            self.get_logger().warning("previous pass not acknowledged by every subscriber before restarting")
        self._wait_identifier_idle(executor)
        self.destroy_publisher(self.pub_u)
        self.destroy_publisher(self.pub_y)
        self._open_stream()
        self.get_logger().info(f"{label}: new publishers, sample indices restart at 1")

    def _start_stream(self, executor: SingleThreadedExecutor, restart: str | None) -> None:
        """Begin a stream (a pass, or a publisher run recorded in the bag): indices from 1, test_start again."""
        if restart is not None:
            self._restart_stream(executor, restart)
        self._wait_for_subscribers(executor)
        if self.pub_start is not None:
            self._wait_test_start_readers(executor)
            self.pub_start.publish(topics.message_class(topics.INT64)(data=int(self.test_start)))
            if not self.pub_start.wait_for_all_acked(Duration(seconds=self._settle_timeout())):
                self.get_logger().warning("test_start not acknowledged by every reader before sample 1")
        self._next_slot = time.monotonic()

    def _wait_test_start_readers(self, executor: SingleThreadedExecutor) -> None:
        """Every test_start reader the graph shows is matched before sample 1 goes out.

        test_start is latched, so a reader matched late still gets it, but an identifier
        that gets it after its sample ``test_start`` has learnt from test samples. A node's
        readers reach the graph together, while each one matches on its own. Bounded by
        ``wait_timeout``; without subscribers to wait for (``wait_for_subscribers`` 0) no wait.
        """
        wanted = int(self._param("wait_for_subscribers"))
        if not wanted:
            return
        end = time.monotonic() + self._settle_timeout()
        while not self.stop.is_set() and time.monotonic() < end:
            if latched_readers_matched(self, self.pub_start, topics.U, wanted):
                return
            executor.spin_once(timeout_sec=0.02)
        self.get_logger().warning(TEST_START_UNMATCHED)

    def _wait_identifier_idle(self, executor: SingleThreadedExecutor, quiet: float = 1.0) -> None:
        """With an identifier on the graph: wait until its y_hat stops coming (it has caught up).

        Acknowledged is not processed: a lagging identifier still holds the end of the last
        pass in its queues, and taking new u halves before old y_p halves would make them
        look like old indices. Bounded by ``wait_timeout``. ``quiet``: a second without
        progress; 0.3 s was shorter than a busy 2-core machine can hold a process off its core.
        """
        if self.count_publishers(topics.Y_HAT) == 0:
            return
        end = time.monotonic() + self._settle_timeout()
        last, calm_until = self._progress(), time.monotonic() + quiet
        while not self.stop.is_set() and time.monotonic() < min(calm_until, end):
            executor.spin_once(timeout_sec=0.02)
            if self._progress() != last:
                last, calm_until = self._progress(), time.monotonic() + quiet

    def _settle_new_stream(self) -> None:
        """Hold sample 2 until every reader has acknowledged sample 1 of a new pass.

        A publisher counts a subscription as soon as *it* has discovered it, but the reader
        may discover the new writer later; the writer's history then re-sends what it
        missed, yet a subscriber's u and y_p readers catch up in any order. The identifier
        would see, say, y_p 1..2000 before u 1: all but sample 1 look like old indices of
        the previous pass. An acknowledgement comes from a reader that knows the writer.
        """
        if not self.wait_acked(timeout=self._settle_timeout()):
            self.get_logger().warning("sample 1 of the new pass not acknowledged by every subscriber")

    def _declare(self, name: str, default: Any, description: str, **ranges: Any) -> None:
        self.declare_parameter(name, default, ParameterDescriptor(description=description, read_only=True, **ranges))

    def _on_y_hat(self, _msg: Any) -> None:
        self.y_hat_count += 1

    def _on_sample(self, _msg: Any) -> None:
        self.samples_count += 1

    def _progress(self) -> int:
        """Samples the identifier has handled: a NaN-marked (skipped) one has a samples row but no y_hat."""
        return max(self.y_hat_count, self.samples_count)

    def _param(self, name: str) -> Any:
        return self.get_parameter(name).value

    def _settle_timeout(self) -> float:
        """How long a settling step waits (acks, matching, an idle identifier): ``wait_timeout``, 0 meaning 30 s."""
        return float(self._param("wait_timeout")) or 30.0

    def _spin_until(self, executor: SingleThreadedExecutor, deadline: float) -> None:
        while not self.stop.is_set() and (left := deadline - time.monotonic()) > 0:
            executor.spin_once(timeout_sec=min(left, 0.05))

    def _wait_for_subscribers(self, executor: SingleThreadedExecutor) -> None:
        wanted = int(self._param("wait_for_subscribers"))
        timeout = float(self._param("wait_timeout")) or float("inf")
        deadline = time.monotonic() + timeout
        while min(self.pub_u.get_subscription_count(), self.pub_y.get_subscription_count()) < wanted:
            if self.stop.is_set():
                return
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {wanted} subscriber(s) on u and y_p after {timeout:.0f} s; start them first")
            executor.spin_once(timeout_sec=0.05)

    def run(self, executor: SingleThreadedExecutor) -> int:
        """Publish every sample (repeatedly with ``loop``, each pass a new stream); returns how many."""
        rate = float(self._param("rate"))
        # Back-pressure is allowed with rate 0; it starts once a y_hat publisher is seen
        # (looked up every 128 samples, so an identifier started late still counts).
        self._feedback_allowed = rate == 0 and int(self._param("max_in_flight")) > 0
        self._identifier_seen = False
        while not self.stop.is_set():
            self._start_stream(executor, f"pass {self.passes + 1}" if self.passes else None)
            self._play_once(executor, rate)
            self.passes += 1
            if not self._param("loop") or not len(self.u):
                break
        return self.published

    def _paced_by_y_hat(self) -> bool:
        if self._feedback_allowed and not self._identifier_seen and self.published % 128 == 0:
            self._identifier_seen = self.count_publishers(topics.Y_HAT) > 0
            if self._identifier_seen:
                self.get_logger().info("y_hat publisher found: pacing by the identifier's progress")
        return self._feedback_allowed and self._identifier_seen

    def _play_once(self, executor: SingleThreadedExecutor, rate: float) -> None:
        max_rate = float(self._param("max_rate_hz"))
        window = int(self._param("max_in_flight"))
        timeout = float(self._param("wait_timeout")) or float("inf")
        start = time.monotonic()
        for k in range(len(self.u)):
            if self.stop.is_set():
                break
            if k in self.stream_starts:  # the recorded publisher restarted: so does ours
                self._start_stream(executor, f"stream {int(self.run_of[k]) + 1} of the bag")
                start = time.monotonic() - (self.offsets[k] / rate if rate > 0 else 0.0)
            if rate > 0:
                self._spin_until(executor, start + self.offsets[k] / rate)
            elif self._paced_by_y_hat():
                self._feedback_allowed = self._wait_for_progress(executor, window, timeout)
            elif max_rate > 0:
                self._next_slot = max(self._next_slot + 1.0 / max_rate, time.monotonic() - 0.01)
                self._spin_until(executor, self._next_slot)
            if k in self._changes and not self.passes:
                self._apply_changes(executor, k)
            elif k == 0 and self.passes == 1 and self._changes:
                self.get_logger().warning(
                    "loop: the recorded live changes were set in the first pass only; later passes keep their "
                    "last values"
                )
            self.pub_u.publish(self.channels.message(self.u[k], "u"))
            self.pub_y.publish(self.channels.message(self.y_p[k], "y"))
            self.published += 1
            if (k == 0 and self.passes) or k in self.stream_starts:
                self._settle_new_stream()

    def _wait_for_progress(self, executor: SingleThreadedExecutor, window: int, timeout: float) -> bool:
        """Block while ``window`` samples are unanswered; False (give up feedback) after ``timeout``."""
        last_count, last_change = self._progress(), time.monotonic()
        while self.published - self._progress() >= window and not self.stop.is_set():
            executor.spin_once(timeout_sec=0.05)
            if self._progress() != last_count:
                last_count, last_change = self._progress(), time.monotonic()
            elif time.monotonic() - last_change > timeout:
                self.get_logger().warning(f"no y_hat for {timeout:.0f} s: pacing by max_rate_hz instead")
                return False
        return True

    def wait_acked(self, timeout: float = 10.0) -> bool:
        """True when every subscriber has every sample, so exiting now loses nothing."""
        limit = Duration(seconds=timeout)
        return all(pub.wait_for_all_acked(limit) for pub in (self.pub_u, self.pub_y))


def _due(times: np.ndarray) -> np.ndarray:
    """Seconds from the first sample at which each row is due: a row without a time (not in the recording) with
    the row before it (the first rows: with the first known)."""
    known = np.isfinite(times)
    if not known.any():
        return np.zeros(times.size)
    before = np.maximum.accumulate(np.where(known, np.arange(times.size), -1))
    filled = times[np.where(before >= 0, before, int(np.argmax(known)))]
    return filled - filled[0]


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()

    def request_stop(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    node = None
    status = 0
    executor = SingleThreadedExecutor()
    try:
        node = Replay(stop=stop)
        executor.add_node(node)
        count = node.run(executor)
        acked = node.wait_acked()
        note = "" if acked else " (not all acknowledged by subscribers)"
        print(f"replay: published {count} samples of {node.bag}{note}", flush=True)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (BagError, TimeoutError, ValueError, ParameterException) as err:
        print(f"replay: {err}", file=sys.stderr)
        status = 1
    finally:
        if node is not None:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown()
    return status


if __name__ == "__main__":
    sys.exit(main())
