"""Pairing u(k) with y_p(k) by sample index, never by luck of arrival order.

u and y_p travel on two topics; an executor may deliver several u before the
matching y_p, and a fault may lose, repeat or reorder messages. Each message comes
with an index (the DDS publication sequence number: the plant simulator publishes
u(k) and y_p(k) once per step from one node, so both are k + 1). A pair is released
only when both halves with the same index are there, in increasing index order; a
half that can no longer be paired (its partner's index was passed) is dropped and
counted, as are repeats and stale indices. Memory is bounded by ``window``.

Sequence numbers start again at 1 when the publisher restarts. Both halves of a new
sample 1 arriving after later samples are taken as such a restart (a new stream);
a lone repeated index 1, like any other old index, is counted as stale, and one that comes
before any later sample as a repeat (the first kept): the rule of :func:`sequence_streams`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

U, Y = "u", "y"


@dataclass
class Pairer:
    """Matches halves by index; see the module docstring for the rules."""

    window: int = 10_000
    counters: dict[str, int] = field(
        default_factory=lambda: {"paired": 0, "duplicates": 0, "stale": 0, "unpaired": 0, "restarts": 0}
    )

    def __post_init__(self) -> None:
        self._pending: dict[str, dict[int, float]] = {U: {}, Y: {}}
        self._restart_halves: dict[str, Any] = {}
        self._restart_waiting: dict[str, dict[int, Any]] = {U: {}, Y: {}}
        self._last_released = 0

    @property
    def queued(self) -> int:
        """Halves waiting for their partner (and, after a restart of one topic, for the other's)."""
        waiting = sum(len(halves) for halves in self._restart_waiting.values())
        return sum(len(pending) for pending in self._pending.values()) + waiting + len(self._restart_halves)

    def add(self, topic: str, index: int, value: float) -> list[tuple[int, float, float]]:
        """Offer one half; returns the pairs (index, u, y) completed by it."""
        if index <= self._last_released:
            return self._old_index(topic, index, value)
        pending, other = self._pending[topic], self._pending[U if topic == Y else Y]
        if index in pending:
            self.counters["duplicates"] += 1
            return []
        if index not in other:
            pending[index] = value
            if len(pending) > self.window:
                del pending[min(pending)]
                self.counters["unpaired"] += 1
            return []
        partner = other.pop(index)
        return [self._release(index, (value, partner) if topic == U else (partner, value))]

    def _old_index(self, topic: str, index: int, value: Any) -> list[tuple[int, Any, Any]]:
        """An index already passed: stale, or part of a restarted stream.

        Index 1 again means a restarted publisher, or a second one. Only when *both*
        halves of sample 1 come back is it taken as a restart (a new stream). Halves of
        a stream whose sample 1 came back are kept meanwhile (up to ``window``) and
        replayed into the new stream, so a topic that restarts ahead of the other
        loses nothing.
        """
        if index == 1 and self._last_released <= 1:  # nothing higher came yet: a repeat, not a restart
            self.counters["duplicates"] += 1
            return []
        self.counters["stale"] += 1  # unless a restart claims it
        if index == 1:
            self._restart_halves.setdefault(topic, value)  # (a repeat of it keeps the first, as any repeat)
        elif topic in self._restart_halves and len(self._restart_waiting[topic]) < self.window:
            self._restart_waiting[topic][index] = value
        if len(self._restart_halves) < 2:
            return []
        waiting = self._restart_waiting
        self.counters["stale"] -= 2 + sum(len(halves) for halves in waiting.values())
        halves = (self._restart_halves[U], self._restart_halves[Y])
        self._restart()
        released = [self._release(1, halves)]
        for channel in (U, Y):
            for later, later_value in sorted(waiting[channel].items()):
                released += self.add(channel, later, later_value)
        return released

    def _release(self, index: int, halves: tuple[float, float]) -> tuple[int, float, float]:
        self._last_released = index
        for pending in self._pending.values():
            for old in [i for i in pending if i < index]:
                del pending[old]
                self.counters["unpaired"] += 1
        self.counters["paired"] += 1
        return (index, halves[0], halves[1])

    def _restart(self) -> None:
        """The publisher restarted (its sequence numbers began again at 1)."""
        self.counters["restarts"] += 1
        self._restart_halves = {}
        self._restart_waiting = {U: {}, Y: {}}
        self._pending = {U: {}, Y: {}}
        self._last_released = 0


def sequence_streams(sequence: np.ndarray) -> np.ndarray:
    """Publisher run per message of one topic (arrival order): index 1 after a higher one is a restart.

    The :class:`Pairer`'s restart rule over a whole recording: a repeated 1 with nothing higher
    before it is a duplicate, not a restart. Only the (few) 1s are visited, so a long recording
    stays numpy-fast. Used offline to put a recording's halves in each run's index order
    (:func:`lenn_ros.service.recording.pair_raw`) and to count a topic's restarts (``bag-info``).
    """
    ones = np.flatnonzero(sequence == 1)
    restarts = np.zeros(sequence.size, dtype=np.int64)
    if not ones.size:
        return restarts
    # before[j]: the highest index between the previous 1 (or the start) and ones[j]
    # (reduceat of an empty span gives the element itself: a 1 at position 0 compares as 1).
    before = np.maximum.reduceat(sequence, np.r_[0, ones])[: ones.size]
    running = 0
    for position, highest in zip(ones, before, strict=True):
        running = max(running, int(highest))
        if running > 1:
            restarts[position] = 1
            running = 0
    return np.cumsum(restarts)


def screen(value: float, limit: float, policy: str = "reject") -> tuple[float, str]:
    """Vet one sample before it can reach a model: (value to use, verdict).

    Verdicts: ``"ok"``; ``"nan"`` (NaN or inf: always rejected, value becomes NaN);
    ``"out_of_range"`` (|value| > limit under policy "reject": value becomes NaN);
    ``"clipped"`` (policy "clip": value clamped to +-limit). A NaN value marks the
    whole pair for skipping, so a bad half never meets the learning rule.
    """
    if value != value or value in (float("inf"), float("-inf")):
        return float("nan"), "nan"
    if abs(value) > limit:
        if policy == "clip":
            return (limit if value > 0 else -limit), "clipped"
        return float("nan"), "out_of_range"
    return value, "ok"


def screen_values(values: np.ndarray, limit: float, policy: str = "reject") -> tuple[np.ndarray, str]:
    """:func:`screen` for a vector half (several channels of one message): one verdict for the message.

    A NaN/inf in any channel or (policy "reject") any channel beyond the limit marks
    the whole vector NaN: a sample is learnt from every channel or from none.
    """
    values = np.array(values, dtype=np.float64)
    if not np.isfinite(values).all():
        return np.full_like(values, np.nan), "nan"
    beyond = np.abs(values) > limit
    if beyond.any():
        if policy == "clip":
            return np.clip(values, -limit, limit), "clipped"
        return np.full_like(values, np.nan), "out_of_range"
    return values, "ok"
