"""A watchdog for every input topic: matched publishers that deliver nothing, or far below their rate.

The identifier counts on its inputs arriving; when one stops while the graph still shows its
publisher matched, the cause may be the publisher (stopped, stalled) or the path (a reader the
middleware no longer serves, a subscription gone deaf). From here the two look alike, so the
watchdog says what it sees in one line (the topic, its matched publishers, when its last message
came), counts it, and asks the node to resubscribe, which mends the second and costs nothing in
the first. Only a topic whose rate is known is watched (:data:`MIN_MESSAGES` at least
:data:`MIN_RATE` Hz): a topic that never arrived is the lone-input notice's business, and one that
publishes only on change has no rate to fall below.

- **stalled**: nothing for ``timeout`` s (at least :data:`PERIODS` of its measured period); said,
  counted, resubscribed; again after twice as long, and so on (each episode: one line per retry);
- **slow**: over the last full window of :data:`WINDOW` s or more (closed by an arrival), under
  :data:`SLOW_SHARE` of its measured rate; said and counted once per episode (no action: messages
  do come). A window still open is not judged: a topic that stops would read as slow in it before
  its stall, and a stop is one event, said as a stall;
- **resumed**: a stalled or slow topic at half its rate again; said once.

Nothing here knows ROS: the node reports arrivals (:meth:`InputWatchdog.arrived`) and the matched
publishers it sees (:meth:`InputWatchdog.check`), and acts on the events returned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: Messages a topic must have delivered before its rate is trusted.
MIN_MESSAGES = 100
#: Rates below this (Hz) are not watched: too slow to tell a pause from a stop within seconds.
MIN_RATE = 5.0
#: A stall lasts at least this many of the topic's periods, and ``timeout`` s.
PERIODS = 20
#: Seconds over which the recent rate is measured (the slow check).
WINDOW = 2.0
#: Recent rate under this share of the measured one is "far below".
SLOW_SHARE = 0.1
#: Time constant (s) of the measured rate: minutes of steady arrivals, not the last burst.
RATE_TIME = 30.0


@dataclass
class _Topic:
    first: float
    last: float
    count: int = 0
    rate: float = 0.0  # measured, Hz (exponentially weighted over RATE_TIME)
    window_start: float = 0.0
    window_count: int = 0
    recent: float = math.inf  # the last full window's rate, Hz
    state: str = "ok"  # ok, stalled, slow
    next_action: float = math.inf  # when a stalled topic is resubscribed again
    backoff: float = 0.0


@dataclass(frozen=True)
class InputEvent:
    """What the watchdog saw: ``kind`` stalled, slow or resumed, on ``topic``, with the line to say."""

    kind: str
    topic: str
    text: str
    resubscribe: bool = False


@dataclass
class InputWatchdog:
    """Per input topic: see the module docstring. ``timeout``: seconds without a message that make a stall."""

    timeout: float = 5.0
    counters: dict[str, int] = field(default_factory=lambda: {"input_stalls": 0, "input_slow": 0, "resubscribed": 0})
    topics: dict[str, _Topic] = field(default_factory=dict)

    def arrived(self, topic: str, now: float) -> None:
        """One message of ``topic`` at ``now`` (monotonic or receive clock, s: one clock throughout)."""
        entry = self.topics.get(topic)
        if entry is None:
            self.topics[topic] = _Topic(first=now, last=now, count=1, window_start=now, window_count=1)
            return
        entry.count += 1
        entry.last = now
        if entry.state == "stalled":  # the first message after a stall opens a window: the stall is not a rate
            entry.window_start, entry.window_count = now, 1
            return
        entry.window_count += 1
        span = now - entry.window_start
        if span >= WINDOW:
            entry.recent = entry.window_count / span
            weight = 1.0 - math.exp(-span / RATE_TIME) if entry.rate else 1.0
            entry.rate += weight * (entry.recent - entry.rate)
            entry.window_start, entry.window_count = now, 0

    def watched(self, topic: str) -> bool:
        """Whether the topic's rate is known well enough to tell a stall from a pause."""
        entry = self.topics.get(topic)
        return entry is not None and entry.count >= MIN_MESSAGES and entry.rate >= MIN_RATE

    def check(self, now: float, publishers: dict[str, list[str]]) -> list[InputEvent]:
        """The events since the last check; ``publishers``: per topic, the matched publishers' names."""
        events: list[InputEvent] = []
        for topic, entry in self.topics.items():
            if not self.watched(topic):
                continue
            names = publishers.get(topic, [])
            quiet = now - entry.last
            if quiet >= max(self.timeout, PERIODS / entry.rate) and names:
                events += self._stalled(topic, entry, now, quiet, names)
            elif self._back(entry, quiet):
                events.append(self._resumed(topic, entry))
            elif entry.state == "ok" and names:
                events += self._slow(topic, entry, entry.recent, names, now)
        return events

    def _back(self, entry: _Topic, quiet: float) -> bool:
        """Whether a stalled topic delivers again, or a slow one at half its rate."""
        if entry.state == "stalled":
            return quiet < max(self.timeout, PERIODS / entry.rate)
        return entry.state == "slow" and entry.recent >= 0.5 * entry.rate

    def _slow(self, topic: str, entry: _Topic, recent: float, names: list[str], now: float) -> list[InputEvent]:
        if recent >= SLOW_SHARE * entry.rate:
            return []
        entry.state = "slow"
        self.counters["input_slow"] += 1
        return [InputEvent("slow", topic, (
            f"{topic} delivers {recent:.1f} messages/s over the last {WINDOW:g} s or more, under "
            f"{SLOW_SHARE:.0%} of its {entry.rate:.1f}/s, though {_listed(names)} matched: the publisher slowed, or "
            "its messages are lost on the way"))]  # fmt: skip

    def _stalled(self, topic: str, entry: _Topic, now: float, quiet: float, names: list[str]) -> list[InputEvent]:
        """A stall: said and resubscribed at once, then again after twice as long each time."""
        if entry.state != "stalled":
            entry.state, entry.backoff, entry.next_action = "stalled", self.timeout, now
            self.counters["input_stalls"] += 1
        if now < entry.next_action:
            return []
        entry.next_action = now + entry.backoff
        entry.backoff *= 2
        self.counters["resubscribed"] += 1
        return [InputEvent("stalled", topic, (
            f"nothing on {topic} for {quiet:.1f} s though {_listed(names)} matched (its last message "
            f"{quiet:.1f} s ago, after {entry.rate:.1f} messages/s): a stopped publisher, or a subscription the "
            "middleware no longer serves; resubscribed"), resubscribe=True)]  # fmt: skip

    def _resumed(self, topic: str, entry: _Topic) -> InputEvent:
        was, entry.state, entry.next_action = entry.state, "ok", math.inf
        return InputEvent(
            "resumed", topic, f"{topic} delivers again ({'after a stall' if was == 'stalled' else 'at its rate'})"
        )

    @property
    def stalled(self) -> list[str]:
        """The topics stalled or slow now (for /diagnostics: WARN while any is)."""
        return [topic for topic, entry in self.topics.items() if entry.state != "ok"]


def _listed(names: list[str]) -> str:
    if len(names) == 1:
        return f"its publisher {names[0]} is"
    return f"{len(names)} publishers ({', '.join(names)}) are"
