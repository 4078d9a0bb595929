"""The live hold at start: formed pairs wait, unlearnt, until the outputs have their readers and the publishers
are known (:mod:`lenn_ros.core.holding` decides; this stage keeps the pairs, bounded, and says what they wait for).

Offline there is no graph and no reader to wait for: a recording's session never holds, it collects
(:attr:`lenn_ros.session.Session.collect`), every pair kept.
"""

from __future__ import annotations

from lenn_ros.core.alignment import Pair
from lenn_ros.core.holding import START_GRACE, HoldGate
from lenn_ros.session.config import SessionConfig
from lenn_ros.session.notices import Notices

#: Pairs held (not yet learnt) while the outputs wait for readers: beyond this the oldest are dropped.
MAX_HELD = 10_000


class Hold:
    """Pairs held until :class:`~lenn_ros.core.holding.HoldGate` lets them go (live only)."""

    def __init__(self, config: SessionConfig, notices: Notices) -> None:
        self.config, self.notices = config, notices
        self.holding = False  # hold formed samples (unprocessed) until released
        self.gate: HoldGate | None = None  # what the hold waits for (hold_for)
        self.pairs: list[Pair] = []

    def hold_for(self, wanted: dict[str, int], grace: float = START_GRACE) -> None:
        """Hold formed pairs until each output in ``wanted`` has that many readers and, in ``sequence`` pairing,
        the graph has shown who publishes u and y_p."""
        self.gate = HoldGate(self.config.pairing, dict(wanted), self.config.u_name, self.config.y_name, grace)
        self.holding = self.gate.needed

    def keep(self, pairs: list[Pair]) -> None:
        """Hold these pairs; beyond :data:`MAX_HELD` the oldest go (the readers never came: keep the newest)."""
        self.pairs.extend(pairs)
        excess = len(self.pairs) - MAX_HELD
        if excess <= 0:
            return
        del self.pairs[:excess]
        counters = self.notices.counters
        counters["held_overflow"] += excess
        self.notices.doubling(
            "held_overflow",
            counters["held_overflow"],
            f"{counters['held_overflow']} held pairs dropped, never learnt: {MAX_HELD} wait for the "
            "outputs' readers (wait_for_*_subscribers) and no more are kept (the newest are)",
        )

    def release(self) -> list[Pair]:
        """Stop holding: the pairs held so far, to be learnt now."""
        self.holding = False
        held, self.pairs = self.pairs, []
        return held

    def ready(self, readers: dict[str, int], now: float) -> bool:
        """Whether the held pairs may go now (monotonic ``now``, s); what they wait for is said after the grace."""
        gate = self.gate
        if gate is None or not (self.holding and self.pairs):
            return False
        if not gate.readers_missing(readers):
            vouched, unverified = gate.vouched(now)
            if unverified is not None:
                self.notices.say("unverified", unverified)
            if vouched:
                return True
        waiting = gate.waiting_text(len(self.pairs), readers, now)
        if waiting is not None:
            self.notices.say("holding", waiting)
        return False

    def at_stop(self) -> str | None:
        """The line to say when the node stops while it holds pairs (None: it holds none). They are not
        learnt: what they waited for (readers, or who publishes u and y_p) was never confirmed, and a stop
        within the grace would otherwise lose them without a word."""
        if not self.pairs:
            return None
        return (
            f"stopping with {len(self.pairs)} pairs held, not learnt: the outputs' readers or the publishers "
            "of u and y_p were not confirmed yet"
        )

    def discard(self) -> int:
        """Drop the pairs held so far as refused (they are not samples)."""
        dropped = len(self.pairs)
        self.notices.counters["refused"] += dropped
        self.pairs = []
        return dropped

    @property
    def publishers_known(self) -> bool:
        """Whether the graph has shown both inputs' publishers (or the grace for them ran out)."""
        return self.gate is None or self.gate.publishers_known

    def publishers(self, seen: dict[str, set[tuple[str, str]]]) -> tuple[bool, str | None]:
        """The gate's verdict on who publishes u and y_p: (decided, refusal or None)."""
        if self.gate is None:
            return False, None
        return self.gate.publishers(seen)
