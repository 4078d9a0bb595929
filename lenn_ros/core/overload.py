"""Shedding load: which waiting message is still worth processing when they come too fast.

A driver that floods a topic (a burst, a misconfigured rate) sends more messages than
the identifier can process. Its subscription queue then fills and, at its depth, the
middleware overwrites the oldest message without a word; before that, every message
is processed later and later, and a sample paired seconds after it was measured is
of no use to a live identifier. So each message taken from a queue is asked how long
it waited there (its *lag*: now minus its receive time, both on the system clock):
one that waited longer than the lag limit is shed, unprocessed and counted, and the
node reaches the newest messages again at the cost of one take per old one (much less
than a model step and its outputs). The newest win.

The lag limit is ``max_lag``, and at most half the time the queue takes to fill at the
rate messages arrive now (``depth`` / rate / 2, the rate measured on the receive times):
the node sheds before the middleware has to drop anything itself, so what is lost is
what is counted. Once a queue's message is over the limit, that queue is caught up:
everything older than ``CATCH_UP`` of the limit is shed, then the node processes at
full speed again from the newest. (Shedding only what is just over the limit would keep
the node a whole limit behind for as long as the flood lasts, processing a message now
and then: on this 2-core machine 834 of 9 000 per second, against 3 000 with the catch-up.)
Nothing here knows ROS; the identifier node asks :meth:`Shedder.admit` for every
message it takes.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class _Rate:
    """Messages per second of receive time on one queue, over windows of ``Shedder.WINDOW``."""

    start: float = 0.0
    count: int = 0
    per_second: float = 0.0
    catching_up: bool = False  # over the limit: shedding down to CATCH_UP of it


@dataclass
class Shedder:
    """Admit or shed each message taken from a queue; see the module docstring."""

    max_lag: float = 0.5  # s; 0: never shed
    depth: int = 10_000  # the queues' depth (KEEP_LAST); 0: unknown or KEEP_ALL (max_lag alone)
    shed: int = 0
    lag: float = 0.0  # of the last message taken, s
    _rates: dict[object, _Rate] = field(default_factory=dict)

    #: Receive time over which an arrival rate is measured, s.
    WINDOW = 0.25
    #: A queue caught up sheds down to this fraction of the lag limit.
    CATCH_UP = 0.1

    def admit(self, queue: object, received: float, now: float) -> bool:
        """Whether the message that arrived at ``received`` on ``queue`` is processed (False: shed, counted)."""
        self.lag = now - received
        rate = self._rates.get(queue)
        if rate is None:
            rate = self._rates[queue] = _Rate(start=received)
        rate.count += 1
        if received - rate.start >= self.WINDOW:
            rate.per_second = rate.count / (received - rate.start)
            rate.start, rate.count = received, 0
        limit = self.limit(rate.per_second)
        if rate.catching_up:
            rate.catching_up = self.lag > self.CATCH_UP * limit
        elif self.max_lag and self.lag > limit:
            rate.catching_up = True
        if not self.max_lag or not rate.catching_up:
            return True
        self.shed += 1
        return False

    @property
    def behind(self) -> bool:
        """Whether some queue is being caught up now (the node is overloaded)."""
        return any(rate.catching_up for rate in self._rates.values())

    def limit(self, per_second: float) -> float:
        """The lag beyond which a message is shed, at an arrival rate of ``per_second``."""
        if self.depth and per_second > 0:
            return min(self.max_lag, 0.5 * self.depth / per_second)
        return self.max_lag
