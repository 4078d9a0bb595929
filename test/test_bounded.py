"""Issue 18, item 2: every queue has a cap, and what a full one drops is counted and said.

One input silent for a long time (a driver at 1 kHz, the controller not yet started; or
the driver stalled under a live controller): the items each queue holds are counted,
not the process's memory (``bench/silent_topic.py`` measures that, over DDS).
"""

from __future__ import annotations

import pytest

from lenn_ros.core.alignment import MAX_QUEUE
from lenn_ros.core.merging import TopicMerger
from lenn_ros.core.pairing import U, Y
from lenn_ros.core.structure import Identifier
from lenn_ros.paper.examples import EXAMPLES
from lenn_ros.session import MAX_HELD, Session, SessionConfig

RATE = 1000.0


def session(pairing: str) -> Session:
    example = EXAMPLES[1]
    identifier = Identifier(example.structure, example.make_network("lenn", 0))
    config = SessionConfig(pairing=pairing, sample_period=1 / RATE, slop=0.2 / RATE, u_name="/cmd", y_name="/joints")
    return Session(identifier, config)


def feed_alone(live: Session, channel: str, first: int, last: int, said: list | None = None) -> None:
    """One input alone; the notices of kind ``overflow`` into ``said``, taken as the node takes them."""
    for k in range(first, last):
        t = 1000.0 + k / RATE
        live.offer(channel, 0.1, t, received=t + 0.002)
        if k % 50 == 0:
            live.poll(t + 0.002)  # the node's poll timer, every 50 ms
            notices = live.take_notices()
            if said is not None:
                said += [notice.text for notice in notices if notice.kind == "overflow"]


@pytest.mark.parametrize("pairing", ["sample", "stamp"])
@pytest.mark.parametrize("silent", [U, Y])
def test_one_silent_input_holds_a_bounded_queue(pairing: str, silent: str) -> None:
    """100 s of one input at 1 kHz, the other silent: the queue stops growing at MAX_QUEUE, the rest is counted."""
    live = session(pairing)
    talking = Y if silent == U else U
    said: list[str] = []
    feed_alone(live, talking, 0, 20_000, said)
    after_20s = live.queued()
    feed_alone(live, talking, 20_000, 100_000, said)
    after_100s = live.queued()
    assert after_20s == after_100s == {"pairing": MAX_QUEUE, "merging": 0, "held": 0, "warm_up": 0}
    status = live.status()
    assert status["queued"] == after_100s
    assert status["counters"]["overflow"] == 100_000 - MAX_QUEUE  # every message beyond the cap, once
    assert 1 <= len(said) <= 20  # the first drop, then each time the count doubled: a handful, not 90 000
    assert said[0].startswith("1 messages dropped unpaired so far")
    silent_name, talking_name = ("/cmd", "/joints") if silent == U else ("/joints", "/cmd")
    assert f"{silent_name} is silent, so {talking_name}'s queue is full" in said[-1]


@pytest.mark.parametrize("pairing", ["sample", "stamp"])
def test_pairing_goes_on_after_the_silent_input_starts(pairing: str) -> None:
    """The controller starts after 30 s of driver alone: pairs form at once, from the newest measurements."""
    live = session(pairing)
    feed_alone(live, Y, 0, 30_000)
    samples = []
    for k in range(30_000, 31_000):
        t = 1000.0 + k / RATE
        samples += live.offer(U, 0.2, t, received=t + 0.001)
        samples += live.offer(Y, 0.1, t, received=t + 0.002)
    samples += live.poll(1000.0 + 31.1)
    assert len(samples) >= 990
    assert min(sample.time for sample in samples) >= 1000.0 + 29.9  # nothing from the stale queue is paired
    assert live.queued()["pairing"] < 100


def test_held_pairs_are_capped_while_the_outputs_have_no_readers() -> None:
    live = session("sample")
    live.hold.holding = True
    for k in range(3 * MAX_HELD):
        t = 1000.0 + k / RATE
        live.offer(U, 0.2, t, received=t + 0.001)
        live.offer(Y, 0.1, t, received=t + 0.002)
    assert live.held == MAX_HELD
    dropped = live.counters["held_overflow"]
    assert dropped >= 2 * MAX_HELD - 5  # (the last few wait in the grid for a later measurement)
    said = [notice.text for notice in live.take_notices() if notice.kind == "held_overflow"]
    assert 1 <= len(said) <= 16 and f"{MAX_HELD} wait for the outputs' readers" in said[0]
    samples = live.release()
    assert len(samples) == MAX_HELD and samples[0].index > dropped  # the newest were kept


@pytest.mark.parametrize("mode", ["stamp", "sequence"])
def test_a_merger_keeps_at_most_window_groups(mode: str) -> None:
    """Two topics on one side, one of them silent, a max_delay that never expires anything: the window caps it."""
    merger = TopicMerger((1, 1), mode, slop=0.0, max_delay=1e9, window=500)
    for k in range(5000):
        merger.add(0, [1.0], 1000.0 + k / RATE, 1000.0 + k / RATE, sequence=k + 1)
    assert merger.queued <= 501
    assert merger.counters["overflow"] + merger.counters["merge_dropped"] + merger.queued == 5000


# -- overload: the newest win (issue 18, item 3; the node over DDS: test_overload.py) -----------
def test_a_backlog_is_shed_down_to_the_newest_and_counted() -> None:
    """A queue 0.6 s behind: shed until a message is fresh (10 % of the limit), then all processed again."""
    live = session("sample")
    live.config.queue_depth = 10_000
    now, admitted = 2000.0, []
    for k in range(7000):  # 1 kHz of arrivals, the node reaching them 0.6 s late and catching up 10x faster
        received = now - 0.6 + k * 1e-3
        taken_at = now + k * 1e-4
        admitted.append(live.admit(("y", 0), received, taken_at))
    first_kept = admitted.index(True, admitted.index(False))
    lag_then = (now + first_kept * 1e-4) - (now - 0.6 + first_kept * 1e-3)
    assert admitted[0] is False and lag_then <= 0.05 + 1e-9  # shed down to 10 % of the 0.5 s limit
    assert all(admitted[first_kept:])  # caught up: from there on everything is processed
    assert live.counters["shed"] == admitted.count(False) == first_kept
    said = [n.text for n in live.take_notices() if n.kind == "shed"]
    assert 1 <= len(said) <= 12 and said[0].startswith("overloaded: 1 messages shed unprocessed so far")


def test_the_lag_limit_shrinks_with_the_rate_so_the_middleware_never_drops_first() -> None:
    from lenn_ros.core.overload import Shedder

    shedder = Shedder(max_lag=0.5, depth=10_000)
    assert shedder.limit(1000.0) == 0.5  # 10 s to fill the queue: max_lag decides
    assert shedder.limit(40_000.0) == 0.125  # a 40 kHz burst fills it in 0.25 s: shed at half that
    assert Shedder(max_lag=0.5, depth=0).limit(40_000.0) == 0.5  # KEEP_ALL or unknown depth


def test_sequence_mode_never_sheds() -> None:
    live = session("sequence")
    assert all(live.admit(("y", 0), 100.0, 100.0 + lag) for lag in (0.1, 5.0, 60.0))
    assert live.counters["shed"] == 0
