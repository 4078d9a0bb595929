"""Replay republishes sample k as the k-th u and y_p, whatever the recording lost or reordered.

The pairing itself (the one of every offline command, :func:`lenn_ros.service.recording.pair_raw`,
the node's session over a recording) is checked without ROS first; then the replay node as a real
process into an rclpy listener and into the real identifier.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from lenn_ros import topics
from lenn_ros.bag import BagWriter, iter_messages, read_run, read_samples, topic_types
from lenn_ros.service import RecordingError
from lenn_ros.service.recording import numbered_rows, read_recording

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "bags" / "example1"
LOST_U, LOST_Y = 100, 2000  # sequence numbers (= sample indices) dropped from the copy
SWAPPED = (501, 504)  # y_p samples whose arrivals are swapped in the copy


# -- the pairing alone ---------------------------------------------------------------------------


def halves_bag(path: Path, u: list[tuple[int, float]], y_p: list[tuple[int, float]]) -> Path:
    """A bag of u and y_p messages (sequence number, value), each list in its arrival order, interleaved."""
    with BagWriter(path) as bag:
        for name in ("/u", "/y_p"):
            bag.add_topic(name)
        for t, (name, (sequence, value)) in enumerate(
            [pair for both in zip([("/u", m) for m in u], [("/y_p", m) for m in y_p], strict=False) for pair in both]
            + [("/u", m) for m in u[len(y_p) :]]
            + [("/y_p", m) for m in y_p[len(u) :]]
        ):
            bag.write_value(name, value, 1_000_000 * (t + 1), sequence=sequence)
    return path


def test_lost_and_reordered_halves_pair_by_index(tmp_path: Path) -> None:
    u = [(1, 10.0), (2, 20.0), (4, 40.0), (5, 50.0)]  # u(3) lost
    y = [(1, -1.0), (3, -3.0), (2, -2.0), (5, -5.0)]  # y_p(2), y_p(3) swapped, y_p(4) lost
    read = read_recording(halves_bag(tmp_path / "b", u, y))
    samples = read.samples
    assert samples.index.tolist() == [1, 2, 5] and not samples.by_order  # 3 and 4 are not whole
    assert samples.u.tolist() == [10.0, 20.0, 50.0] and samples.y.tolist() == [-1.0, -2.0, -5.0]
    assert read.session.all_counters()["unpaired"] == 2  # y_p(3) and u(4): counted, never paired


def test_numbered_rows_give_every_index_of_each_run() -> None:
    rows, runs = numbered_rows(np.array([3, 5, 1, 2]))  # a publisher run 3, 5; a restart 1, 2
    assert rows.tolist() == [2, 4, 5, 6] and runs.tolist() == [0, 0, 0, 0, 0, 1, 1]


def test_restart_at_one_is_a_new_stream_and_repeats_keep_the_first(tmp_path: Path) -> None:
    u = [(1, 1.0), (2, 2.0), (2, 2.5), (3, 3.0), (1, 11.0), (2, 12.0)]  # a repeated 2, then a restart
    y = [(1, -1.0), (1, -1.5), (2, -2.0), (3, -3.0), (1, -11.0), (2, -12.0)]  # a repeated 1 first: no restart
    read = read_recording(halves_bag(tmp_path / "b", u, y))
    assert read.samples.index.tolist() == [1, 2, 3, 1, 2]
    assert read.samples.u.tolist() == [1.0, 2.0, 3.0, 11.0, 12.0]
    assert read.samples.y.tolist() == [-1.0, -2.0, -3.0, -11.0, -12.0]
    counters = read.session.all_counters()
    assert counters["restarts"] == 1 and counters["duplicates"] + counters["stale"] == 2


def test_without_sequence_numbers_by_order_only_when_counts_match(tmp_path: Path) -> None:
    read = read_recording(halves_bag(tmp_path / "even", [(0, 1.0), (0, 2.0)], [(0, -1.0), (0, -2.0)]))
    assert read.samples.by_order and read.samples.index.tolist() == [1, 2] and read.samples.y.tolist() == [-1.0, -2.0]
    with pytest.raises(RecordingError, match="u has 3 messages, y_p 2: pairing by order would shift"):
        read_recording(halves_bag(tmp_path / "odd", [(0, 1.0), (0, 2.0), (0, 3.0)], [(0, -1.0), (0, -2.0)]))


def copy_damaged(source: Path, target: Path, keep_samples: bool) -> Path:
    """``source`` without u(LOST_U) and y_p(LOST_Y), y_p SWAPPED in arrival; ``samples`` kept or not."""
    messages = [
        m
        for m in iter_messages(source)
        if not (m.topic == "/u" and m.sequence == LOST_U)
        and not (m.topic == "/y_p" and m.sequence == LOST_Y)
        and (keep_samples or m.topic != "/samples")
    ]
    where = [i for i, m in enumerate(messages) if m.topic == "/y_p" and m.sequence in SWAPPED]
    a, b = where
    messages[a], messages[b] = (
        dataclasses.replace(messages[b], log_time_ns=messages[a].log_time_ns),
        dataclasses.replace(messages[a], log_time_ns=messages[b].log_time_ns),
    )
    with BagWriter(target) as writer:
        for topic, type_name in topic_types(source).items():
            if keep_samples or topic != "/samples":
                writer.add_topic(topic, type_name)
        for m in messages:
            writer.write_message(
                m.topic, m.message, m.log_time_ns, publish_time_ns=m.publish_time_ns, sequence=m.sequence
            )
    return target


def test_damaged_shipped_bag_pairs_as_recorded(tmp_path: Path) -> None:
    original = read_run(EXAMPLE)
    assert original.u_sequence.tolist() == list(range(1, original.u.size + 1))  # sample k at position k - 1
    damaged = read_recording(copy_damaged(EXAMPLE, tmp_path / "damaged", keep_samples=False)).samples
    expected = [k for k in range(1, original.u.size + 1) if k not in (LOST_U, LOST_Y)]
    assert damaged.index.tolist() == expected  # the swapped arrivals are put back in order, nothing shifted
    assert np.array_equal(damaged.u, original.u[np.array(expected) - 1])
    assert np.array_equal(damaged.y, original.y_p[np.array(expected) - 1])


# -- the replay node over DDS --------------------------------------------------------------------


def _ros() -> None:
    pytest.importorskip("rclpy")
    pytest.importorskip("domain_coordinator")


class PairListener:
    """Keeps every u and y_p by publication sequence number, one dict per stream (publisher run)."""

    def __init__(self, domain_id: int, extra: dict[str, Callable[[object], None]] | None = None) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("pair_listener", context=self.ctx)
        self.streams: dict[str, list[dict[int, float]]] = {topics.U: [], topics.Y_P: []}
        self.lock = threading.Lock()
        float64 = topics.message_class(topics.FLOAT64)
        for name in (topics.U, topics.Y_P):
            self.node.create_subscription(
                float64, name, lambda m, info, n=name: self._on(n, m, info), topics.data_qos()
            )
        for name, callback in (extra or {}).items():
            self.node.create_subscription(topics.message_class(topics.FLOAT64_ARRAY), name, callback, topics.data_qos())
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _on(self, name: str, message: object, info: dict[str, int]) -> None:
        sequence = info["publication_sequence_number"]
        with self.lock:
            streams = self.streams[name]
            if not streams or (sequence == 1 and streams[-1]):
                streams.append({})
            streams[-1][sequence] = message.data

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=5)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def run_replay(bag: Path, *params: str, timeout: float = 60) -> tuple[int | None, str, str]:
    from rosutil import start_node

    replay = start_node("replay", f"bag:={bag}", "rate:=0.0", "max_rate_hz:=4000.0", *params)
    try:
        stdout, stderr = replay.communicate(timeout=timeout)
    finally:
        if replay.poll() is None:
            replay.kill()
            replay.communicate()
    return replay.returncode, stdout, stderr


def assert_as_recorded(received: dict[int, float], recorded: np.ndarray, nan_at: set[int]) -> None:
    """Message k (1-based) equals recorded sample k; the samples in ``nan_at`` are NaN."""
    assert sorted(received) == list(range(1, recorded.size + 1)), f"{len(received)} of {recorded.size} received"
    got = np.array([received[k] for k in range(1, recorded.size + 1)])
    marked = set((np.flatnonzero(np.isnan(got)) + 1).tolist())
    assert marked == nan_at, f"NaN at {sorted(marked)[:10]}, expected {sorted(nan_at)}"
    same = ~np.isnan(got)
    wrong = np.flatnonzero(got[same] != recorded[same])
    assert not wrong.size, (
        f"{wrong.size} samples differ from the recording, first index {np.flatnonzero(same)[wrong[0]] + 1}"
    )


@pytest.mark.ros
@pytest.mark.timeout(90)
@pytest.mark.parametrize("keep_samples", [False, True], ids=["raw", "samples"])
def test_replay_of_a_damaged_bag_publishes_samples_in_place(tmp_path: Path, domain: int, keep_samples: bool) -> None:
    """Raw: u(k), y_p(k) as recorded at index k, the two incomplete samples NaN-marked, not shifted.

    With the identifier's samples topic in the bag (auto), the recorder's losses do not
    matter: the pairs the identifier formed live are published, all complete.
    """
    _ros()
    original = read_run(EXAMPLE)
    bag = copy_damaged(EXAMPLE, tmp_path / "damaged", keep_samples)
    listener = PairListener(domain)
    try:
        code, stdout, stderr = run_replay(bag)
    finally:
        listener.close()
    assert code == 0, stderr
    n = original.u.size
    assert f"replay: published {n} samples" in stdout and "not all acknowledged" not in stdout, stdout
    assert len(listener.streams[topics.U]) == len(listener.streams[topics.Y_P]) == 1
    u, y_p = listener.streams[topics.U][0], listener.streams[topics.Y_P][0]
    if keep_samples:
        assert "replaying the identifier's samples (0 refused live, as NaN)" in stderr, stderr
        assert f"{n} samples in 1 stream(s), all complete" in stderr
        assert_as_recorded(u, original.u, set())
        assert_as_recorded(y_p, original.y_p, set())
        return
    lines = [line for line in stderr.splitlines() if "not whole in the recording" in line]
    assert len(lines) == 1, stderr
    assert "/u, /y_p by sequence" in lines[0]
    assert "2 sample indices not whole in the recording" in lines[0]
    assert_as_recorded(u, original.u, {LOST_U, LOST_Y})  # a sample either half of which is lost: NaN, in place
    assert_as_recorded(y_p, original.y_p, {LOST_U, LOST_Y})


@pytest.mark.ros
@pytest.mark.timeout(150)
def test_identifier_learns_the_recorded_pairs_from_a_damaged_bag(tmp_path: Path, domain: int) -> None:
    """The real identifier's samples are the recorded (u(k), y_p(k)); the incomplete two are skipped."""
    _ros()
    from rosutil import final_status, start_node, stop

    original = read_run(EXAMPLE)
    live = read_samples(EXAMPLE)
    assert live is not None
    n = original.u.size
    bag = copy_damaged(EXAMPLE, tmp_path / "damaged", keep_samples=False)
    rows: list[list[float]] = []
    done = threading.Event()

    def on_sample(message: object) -> None:
        rows.append(list(message.data))
        if len(rows) >= n:
            done.set()

    listener = PairListener(domain, {topics.SAMPLES: on_sample})
    readers: list[int] = []
    listener.node.create_subscription(
        topics.message_class(topics.STRING),
        topics.STATUS,
        lambda m: readers.append(json.loads(m.data)["readers"]["samples"]),
        topics.data_qos(),
    )
    identifier = start_node("identifier", params_file=REPO / "config" / "example1_lenn.yaml")
    ident_err = ""
    try:
        # samples is VOLATILE: what the identifier publishes before it has matched the listener is lost
        deadline = time.monotonic() + 60
        while not (readers and readers[-1] >= 1) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert readers and readers[-1] >= 1, f"the identifier never matched the listener's samples reader: {readers}"
        code, _stdout, stderr = run_replay(bag, "wait_for_subscribers:=2", timeout=90)  # listener + identifier
        assert code == 0, stderr
        received = done.wait(30)
        _out, ident_err = stop(identifier)
        assert received, f"{len(rows)} of {n} samples from the identifier\n{stderr[-1500:]}\n{ident_err[-1500:]}"
    finally:
        if identifier.poll() is None:
            _out, ident_err = stop(identifier)
        listener.close()
    table = np.array(rows[:n])
    assert table[:, 0].astype(int).tolist() == list(range(1, n + 1))
    u, y_p, learnt = table[:, 2], table[:, 3], table[:, 4]
    assert np.flatnonzero(np.isnan(u) | np.isnan(y_p)).tolist() == [LOST_U - 1, LOST_Y - 1]
    complete = ~(np.isnan(u) | np.isnan(y_p))
    assert np.array_equal(u[complete], original.u[complete]) and np.array_equal(y_p[complete], original.y_p[complete])
    assert not learnt[~complete].any()
    status = final_status(ident_err)
    counters = status["counters"]
    # each of the two samples not whole in the recording arrives NaN on both topics: 4 NaN halves
    assert counters["nan"] == 4 and counters["unpaired"] == 0 and counters["stale"] == 0, counters
    # learnt where the live run learnt, but not from a skipped sample nor while the history refills after it
    assert live.learn is not None
    warm_up = int(np.argmax(live.learn))  # samples the live run needed before its first step
    expected = live.learn.copy()
    for k in (LOST_U, LOST_Y):
        expected[k - 1 : k + warm_up] = False
    assert np.array_equal(learnt != 0, expected), np.flatnonzero((learnt != 0) != expected)[:10]


def write_bag(path: Path, u: list[tuple[int, float]], y_p: list[tuple[int, float]], test_start: int | None) -> Path:
    """A bag from (sequence number, value) messages in arrival order."""
    with BagWriter(path) as bag:
        for name in ("/u", "/y_p", "/test_start"):
            bag.add_topic(name)
        if test_start is not None:
            bag.write_value("/test_start", test_start, 0)
        for t, ((su, vu), (sy, vy)) in enumerate(zip(u, y_p, strict=True)):
            bag.write_value("/u", vu, 1_000_000 * (t + 1), sequence=su)
            bag.write_value("/y_p", vy, 1_000_000 * (t + 1) + 1, sequence=sy)
    return path


@pytest.mark.ros
@pytest.mark.timeout(60)
def test_restarted_publisher_in_the_bag_is_a_new_stream(tmp_path: Path, domain: int) -> None:
    """A recording where the plant restarted (indices 1..4, then 1..3) replays as two streams, as recorded."""
    _ros()
    first, second = [(k, float(k)) for k in range(1, 5)], [(k, 10.0 + k) for k in range(1, 4)]
    u = first + second
    y_p = [(k, -v) for k, v in u]
    bag = write_bag(tmp_path / "restarted", u, y_p, test_start=3)
    starts: list[int] = []
    listener = PairListener(domain)
    listener.node.create_subscription(
        topics.message_class(topics.INT64), topics.TEST_START, lambda m: starts.append(m.data), topics.latched_qos()
    )
    try:
        code, _stdout, stderr = run_replay(bag)
    finally:
        listener.close()
    assert code == 0, stderr
    assert "7 samples in 2 stream(s), all complete" in stderr, stderr
    assert "stream 2 of the bag: new publishers, sample indices restart at 1" in stderr
    assert listener.streams[topics.U] == [dict(first), dict(second)]
    assert listener.streams[topics.Y_P] == [{k: -v for k, v in first}, {k: -v for k, v in second}]
    assert starts[:2] == [3, 3]


@pytest.mark.ros
@pytest.mark.timeout(60)
def test_unequal_counts_without_sequence_numbers_are_refused(tmp_path: Path, domain: int) -> None:
    """No indices and a message fewer on y_p: no telling where it was lost, so replay says so and stops."""
    _ros()
    path = tmp_path / "imported"
    with BagWriter(path) as bag:
        bag.add_topic("/u")
        bag.add_topic("/y_p")
        for k in range(5):
            bag.write_value("/u", float(k), k)
            if k != 2:
                bag.write_value("/y_p", -float(k), k)
    code, _stdout, stderr = run_replay(path, timeout=30)
    assert code == 1
    assert "u has 5 messages, y_p 4: pairing by order would shift every later pair" in stderr, stderr
