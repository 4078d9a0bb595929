"""Pairing by index: exact under interleaving, loss, repeats, reordering, restarts."""

from __future__ import annotations

import math

from lenn_ros.core.pairing import Pairer, U, Y, screen


def feed(pairer: Pairer, halves: list[tuple[str, int]]) -> list[tuple[int, float, float]]:
    """u(k) = k, y(k) = -k, so a wrong pair shows as u != -y."""
    out = []
    for topic, k in halves:
        out += pairer.add(topic, k, float(k) if topic == U else -float(k))
    return out


def test_interleaved_arrival_pairs_by_index() -> None:
    pairs = feed(Pairer(), [(U, 1), (U, 2), (U, 3), (Y, 1), (Y, 2), (U, 4), (Y, 3), (Y, 4)])
    assert [p[0] for p in pairs] == [1, 2, 3, 4]
    assert all(u == -y == k for k, u, y in pairs)


def test_lost_half_is_dropped_not_mispaired() -> None:
    pairer = Pairer()
    pairs = feed(pairer, [(U, 1), (Y, 1), (U, 2), (U, 3), (Y, 3), (Y, 2)])  # y(2) arrives after y(3): too late
    assert [p[0] for p in pairs] == [1, 3]
    assert pairer.counters["unpaired"] == 1 and pairer.counters["stale"] == 1


def test_duplicates_are_counted_and_ignored() -> None:
    pairer = Pairer()
    pairs = feed(pairer, [(U, 1), (U, 1), (Y, 1), (Y, 1), (U, 2), (Y, 2)])
    assert [p[0] for p in pairs] == [1, 2]
    # the second y_p(1): already paired, but nothing higher came yet, so a repeat (sequence_streams' rule)
    assert pairer.counters["duplicates"] == 2 and pairer.counters["stale"] == 0


def test_a_restarted_publisher_starts_a_new_stream_but_a_lone_index_1_does_not() -> None:
    pairer = Pairer()
    feed(pairer, [(U, k) for k in range(1, 6)] + [(Y, k) for k in range(1, 6)])
    assert feed(pairer, [(U, 1), (U, 2)]) == []  # a second publisher of u only: stale
    assert pairer.counters["restarts"] == 0 and pairer.counters["stale"] == 2
    pairs = feed(pairer, [(Y, 1), (Y, 2)])  # now both halves of sample 1: a restart
    assert pairer.counters["restarts"] == 1
    # u's new stream ran ahead of y_p's: its sample 2 was kept, not lost as stale
    assert [p[0] for p in pairs] == [1, 2] and pairer.counters["stale"] == 0
    assert all(u == -y for _, u, y in pairs)


def test_memory_stays_bounded_when_one_topic_is_silent() -> None:
    pairer = Pairer(window=100)
    feed(pairer, [(U, k) for k in range(1, 1001)])
    assert pairer.counters["unpaired"] == 900


def test_screen_rejects_nan_inf_and_absurd_values() -> None:
    assert screen(0.5, 10.0) == (0.5, "ok")
    assert math.isnan(screen(float("nan"), 10.0)[0]) and screen(float("inf"), 10.0)[1] == "nan"
    assert screen(1e9, 10.0)[1] == "out_of_range" and math.isnan(screen(1e9, 10.0)[0])
    assert screen(-1e9, 10.0, "clip") == (-10.0, "clipped")
