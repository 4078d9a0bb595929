"""The input watchdog alone (no ROS): a stall, a slow topic, a resume, and what is not watched."""

from __future__ import annotations

from lenn_ros.core.watchdog import MIN_MESSAGES, InputWatchdog

PUBLISHER = {"/joint_states": ["/driver"]}


def feed(watchdog: InputWatchdog, topic: str, start: float, stop: float, rate: float) -> float:
    """Arrivals at ``rate`` Hz from ``start`` to ``stop`` (s); returns the last arrival's time."""
    t = start
    while t < stop:
        watchdog.arrived(topic, t)
        t += 1.0 / rate
    return t - 1.0 / rate


def test_a_stall_is_said_once_with_the_publisher_then_retried_later_and_a_resume_is_said() -> None:
    watchdog = InputWatchdog(timeout=5.0)
    last = feed(watchdog, "/joint_states", 0.0, 60.0, 1000.0)
    assert watchdog.check(last + 4.9, PUBLISHER) == []  # within the timeout: nothing yet
    events = watchdog.check(last + 5.01, PUBLISHER)
    assert [e.kind for e in events] == ["stalled"] and events[0].resubscribe
    assert "/joint_states" in events[0].text and "/driver" in events[0].text and "resubscribed" in events[0].text
    assert watchdog.check(last + 7.0, PUBLISHER) == []  # one line per retry: the next after the backoff
    assert [e.kind for e in watchdog.check(last + 10.02, PUBLISHER)] == ["stalled"]  # 5 s later
    assert watchdog.check(last + 14.0, PUBLISHER) == []  # then 10 s later, not before
    assert watchdog.counters == {"input_stalls": 1, "resubscribed": 2, "input_slow": 0}
    assert watchdog.stalled == ["/joint_states"]
    watchdog.arrived("/joint_states", last + 16.0)
    assert [e.kind for e in watchdog.check(last + 16.1, PUBLISHER)] == ["resumed"]
    assert watchdog.stalled == []


def test_no_stall_without_a_matched_publisher_and_none_for_a_topic_whose_rate_is_unknown() -> None:
    watchdog = InputWatchdog(timeout=5.0)
    last = feed(watchdog, "/joint_states", 0.0, 60.0, 1000.0)
    assert watchdog.check(last + 30.0, {}) == []  # the publisher left the graph: the silence notice's business
    sparse = InputWatchdog(timeout=5.0)
    for k in range(MIN_MESSAGES - 1):  # too few to trust a rate
        sparse.arrived("/cmd", k * 0.01)
    assert sparse.check(100.0, {"/cmd": ["/controller"]}) == []
    slow = InputWatchdog(timeout=5.0)
    feed(slow, "/cmd", 0.0, 200.0, 1.0)  # 1 Hz: too slow to tell a pause from a stop
    assert slow.check(300.0, {"/cmd": ["/controller"]}) == []


def test_a_slow_topic_is_said_once_and_a_rate_back_resumes_it() -> None:
    watchdog = InputWatchdog(timeout=5.0)
    last = feed(watchdog, "/joint_states", 0.0, 60.0, 1000.0)
    last = feed(watchdog, "/joint_states", last + 0.2, last + 4.0, 20.0)  # 2 % of its rate, never 5 s silent
    events = watchdog.check(last, PUBLISHER)
    assert [e.kind for e in events] == ["slow"] and not events[0].resubscribe
    assert "under 10%" in events[0].text
    assert watchdog.check(last + 0.1, PUBLISHER) == []  # once per episode
    last = feed(watchdog, "/joint_states", last + 0.001, last + 3.0, 1000.0)
    assert [e.kind for e in watchdog.check(last, PUBLISHER)] == ["resumed"]
    assert watchdog.counters["input_slow"] == 1 and watchdog.counters["input_stalls"] == 0


def test_a_steady_topic_at_its_rate_is_never_said() -> None:
    watchdog = InputWatchdog(timeout=5.0)
    t = 0.0
    for second in range(120):
        t = feed(watchdog, "/joint_states", float(second), second + 1.0, 500.0)
        assert watchdog.check(t, PUBLISHER) == []
    assert watchdog.counters == {"input_stalls": 0, "resubscribed": 0, "input_slow": 0}


def test_a_topic_that_stops_is_a_stall_never_first_a_slow_topic_whatever_its_window() -> None:
    """A stop is one event: a window that began just before it must not read as "slow" before the stall."""
    for stop in (60.0, 60.1, 60.15, 60.2, 60.5, 61.0, 61.95):  # the stop at phases of the 2 s rate window (60.06)
        watchdog = InputWatchdog(timeout=2.0)
        last = feed(watchdog, "/joint_states", 0.0, stop, 200.0)
        kinds = [e.kind for k in range(1, 400) for e in watchdog.check(last + 0.01 * k, PUBLISHER)]
        assert kinds == ["stalled"], (stop, kinds)
        assert watchdog.counters["input_slow"] == 0


def test_the_window_after_a_stall_is_not_read_as_slow() -> None:
    """The first window after a stall must not span it: the topic back at its rate is resumed, never slow."""
    for stop in (60.07, 60.2, 60.5, 61.0, 61.9):  # the stop at phases of the 2 s rate window (60.06)
        watchdog = InputWatchdog(timeout=2.0)
        last = feed(watchdog, "/joint_states", 0.0, stop, 200.0)
        kinds = [e.kind for k in range(1, 400) for e in watchdog.check(last + 0.01 * k, PUBLISHER)]
        back = last + 4.0
        for k in range(1, 1200):  # back at its rate for 6 s, checked every 10 ms
            watchdog.arrived("/joint_states", back + k / 200.0)
            if k % 2 == 0:
                kinds += [e.kind for e in watchdog.check(back + k / 200.0, PUBLISHER)]
        assert kinds == ["stalled", "resumed"], (stop, kinds)
        assert watchdog.counters["input_slow"] == 0
