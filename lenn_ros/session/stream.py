"""The stream stages of a session: halves in, pairs out.

A half (a value of u or y_p with its time, sequence number and source timestamp) goes through:

- **overload** (:meth:`Stream.admit`, live only): shed unread when the node is behind
  (:mod:`lenn_ros.core.overload`), never in ``sequence`` pairing;
- **presence**: counted, lone or silent inputs said (:mod:`lenn_ros.session.presence`);
- **merging**: a side's several topics into one vector half per sample (:mod:`lenn_ros.core.merging`);
- **screen**: NaN and absurd values refused or clipped (:mod:`lenn_ros.session.values`);
- **pairing**: by sequence number (one lockstep publisher, :mod:`lenn_ros.core.pairing`: refused
  with the fix named when the middleware gives no numbers, or the halves of a pair were published
  more than ``max_skew`` apart and not in turn after the pair before), by header stamps within
  ``slop``, or on a sample grid (:mod:`lenn_ros.core.alignment`).

Times are stamps where a message has one, else receive times. Live and offline run the same
stages; offline nothing is shed (no queue) and nothing is held (no reader to wait for).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from lenn_ros.core.alignment import GridSampler, Pair, StampAligner
from lenn_ros.core.merging import TopicMerger, default_max_age
from lenn_ros.core.overload import Shedder
from lenn_ros.core.pairing import Pairer, U
from lenn_ros.session.config import SessionConfig
from lenn_ros.session.notices import Notices
from lenn_ros.session.presence import ClockWatch, Presence
from lenn_ros.session.values import Values

#: What rmw reports when it has no publication sequence numbers (rmw_cyclonedds: 2**64-1).
SEQUENCE_UNSUPPORTED = (0, 2**64 - 1)


class Stream:
    """Screen, merge, pair or align, shed; see the module docstring. ``on_restart``: the sample indices
    started over (a publisher restart, a clock jump): the model's history must restart too."""

    def __init__(
        self, config: SessionConfig, notices: Notices, values: type[Values], on_restart: Callable[[], None]
    ) -> None:
        self.config, self.notices, self.values, self.on_restart = config, notices, values, on_restart
        delay = config.max_delay_s
        self.pairer = Pairer(window=10_000) if config.pairing == "sequence" else None
        self.aligner: StampAligner | GridSampler | None = None
        if config.pairing == "stamp":
            self.aligner = StampAligner(slop=config.slop, max_delay=delay)
        elif config.pairing == "sample":
            self.aligner = GridSampler(config.sample_period, max_delay=delay, y_max_age=config.y_max_age)
        self.mergers = {
            channel: TopicMerger(
                tuple(parts),
                config.pairing,
                slop=config.slop,
                max_delay=delay,
                max_age=default_max_age(config.sample_period),
            )
            for channel, parts in ((U, config.u_parts), ("y", config.y_parts))
            if len(parts) > 1
        }
        self.presence = Presence(config, notices)
        self.clocks = ClockWatch(config, notices)
        self.shedder = Shedder(config.max_lag, config.queue_depth)
        self.refusal: str | None = None  # set when pairing cannot work (two publishers in sequence pairing)
        self._seen_merge: dict[str, dict[str, int]] = {}
        self._seen_dropped = 0
        self._seen_faults = 0  # sequence mode: stale + duplicate halves already said
        self._last_sources: tuple[float, float] | None = None  # sequence mode: the last pair's (u, y) publish times
        self._first: tuple[Pair, tuple[float, float]] | None = None  # a first pair published apart: the next judges it

    # -- overload ------------------------------------------------------------------------------
    def admit(self, queue: object, received: float, now: float) -> bool:
        """Whether a message taken from ``queue`` (received at ``received``, taken at ``now``, system clock, s)
        is processed, or shed because the node is behind (:mod:`~lenn_ros.core.overload`); shed ones are
        counted and said at the first and each time their count doubles.

        Never in ``sequence`` mode: its one lockstep publisher waits for the identifier (it
        cannot flood it), and a sample shed there would be a gap where offline has none.
        """
        if self.pairer is not None:
            self.shedder.lag = now - received  # (still shown in status)
            return True
        shedder = self.shedder
        shedder.max_lag, shedder.depth = self.config.max_lag, self.config.queue_depth
        if shedder.admit(queue, received, now):
            return True
        self.notices.counters["shed"] = shedder.shed
        self.notices.doubling(
            "shed",
            shedder.shed,
            f"overloaded: {shedder.shed} messages shed unprocessed so far (this one waited {shedder.lag:.3f} s in its "
            f"queue, more than max_lag {self.config.max_lag:g} s or half the time its queue of "
            f"{self.config.queue_depth or 'unknown depth'} takes to fill at this rate): messages arrive faster than "
            "the node can learn from them, so it keeps up with the newest",
        )
        return False

    # -- halves --------------------------------------------------------------------------------
    def offer(
        self,
        channel: str,
        value: Any,
        time: float,
        received: float,
        sequence: int | None,
        source_time: float | None,
        part: int,
    ) -> list[Pair]:
        """One half of ``channel`` (U or Y): the pairs it completes."""
        self.presence.arrived(channel, received)
        if self.pairer is None:
            self.clocks.observe(channel, time, received)
        merger = self.mergers.get(channel)
        if merger is None:
            return self._offer_half(channel, value, time, received, sequence, source_time)
        pairs = []
        for half in merger.add(part, value, time, received, sequence, source_time):
            pairs += self._offer_half(channel, half.value, half.time, half.received, half.sequence, half.source_time)
        self._after_merge(channel, merger)
        return pairs

    def _offer_half(
        self, channel: str, value: Any, time: float, received: float, sequence: int | None, source_time: float | None
    ) -> list[Pair]:
        """A whole half (one topic's message, or the side's topics merged): screened, then paired."""
        config, counters = self.config, self.notices.counters
        name = config.u_name if channel == U else config.y_name
        limit = config.u_limit if channel == U else config.y_limit
        raw = value
        value, verdict = self.values.screen(value, limit, config.out_of_range)
        if verdict != "ok":
            counters[verdict] += 1
            consequence = "clipped to the limit" if verdict == "clipped" else "its sample is skipped, never learnt"
            shown = self.values.shown(raw, value)
            self.notices.say(verdict, f"{name} = {shown!r} at t={time:.6f}: {verdict.replace('_', ' ')}; {consequence}")
        if self.refusal is not None:
            counters["refused"] += 1
            self.notices.say("refused", self.refusal)
            return []
        if self.pairer is not None:
            return self._pair_by_sequence(channel, value, time, sequence, source_time)
        assert self.aligner is not None
        pairs = self.aligner.add(channel, value, time, received)
        self._after_alignment()
        return pairs

    def unreadable(self, channel: str, received: float, field: str, error: str) -> None:
        """A message of ``channel`` arrived (receive time ``received``) but its ``field`` could not be read.

        Counted (``field_errors``) and kept for the lone-input notice of the other channel:
        its messages did arrive, so "nothing on" it would send the user to check the topic
        name and QoS, when the fix is the field path (a joint name, an index).
        """
        self.presence.unreadable_message(channel, received, f"{field} ({error})")

    def poll(self, now: float) -> list[Pair]:
        """Time passes (receive clock, s): settle waiting samples, watch for a lone input or none at all."""
        self.presence.check(now)
        if self.aligner is None:
            return []
        pairs = self.aligner.poll(now)
        self._after_alignment()
        return pairs

    def flush(self) -> list[Pair]:
        """End of a recording: settle what can still be settled (a side's incomplete parts are dropped;
        a first pair published apart with no second to vouch for it is refused)."""
        for channel, merger in self.mergers.items():
            merger.flush()
            self._after_merge(channel, merger)
        if self._first is not None:  # (sequence pairing: no aligner)
            first, self._first = self._first, None
            return [self._refused(*first)]
        if isinstance(self.aligner, GridSampler):
            return self.aligner.flush()
        if isinstance(self.aligner, StampAligner):
            return self.aligner.poll(math.inf)
        return []

    # -- pairing -------------------------------------------------------------------------------
    def _pair_by_sequence(
        self, channel: str, value: Any, time: float, sequence: int | None, source_time: float | None
    ) -> list[Pair]:
        assert self.pairer is not None
        if sequence is None or sequence in SEQUENCE_UNSUPPORTED:
            self.notices.counters["no_sequence"] += 1
            self.notices.say(
                "no_sequence",
                "pairing 'sequence' needs DDS publication sequence numbers and this middleware gives none "
                "(e.g. rmw_cyclonedds): nothing is paired; use pairing:=sample sample_period:=T (or pairing:=stamp)",
            )
            return []
        restarts = self.pairer.counters["restarts"]
        released = self.pairer.add(channel, int(sequence), (value, time, source_time))
        if self.pairer.counters["restarts"] != restarts:
            self.on_restart()
            self._last_sources = None
            if self._first is not None:  # the old run's first pair never had a second to vouch for it: said, dropped
                self._refused(*self._first)
                self._first = None
            self.notices.say("restart", "sample indices started over (publisher restart): history reset")
        self._say_pairing_faults(bool(released))
        pairs = []
        for index, u, y in released:
            pairs += self._checked(index, u, y)
        return pairs

    def _checked(self, index: int, u: tuple, y: tuple) -> list[Pair]:
        """A pair of released halves, refused (NaN) when they were published apart and out of turn.

        A pair with none before it (the first, or the first after a restart) has no turn to be in: if its
        halves are further apart than ``max_skew`` it waits for the next pair, which vouches for it when both
        its halves come after both of the first's (a lockstep publisher descheduled between its first u and
        y_p), and refuses it otherwise. The next pair then goes with it.
        """
        (u_value, _u_time, u_source), (y_value, y_time, y_source) = u, y
        pair = Pair(index, y_time, u_value, y_value)
        if u_source is None or y_source is None:
            return [pair]
        sources = (u_source, y_source)
        previous, self._last_sources = self._last_sources, sources
        judged = []
        if self._first is not None:
            first, self._first = self._first, None
            judged.append(first[0] if min(sources) >= max(first[1]) else self._refused(*first))
        if abs(u_source - y_source) <= self.config.max_skew or (previous is not None and min(sources) >= max(previous)):
            judged.append(pair)
        elif previous is None:
            self._first = (pair, sources)
        else:
            judged.append(self._refused(pair, sources))
        return judged

    def _refused(self, pair: Pair, sources: tuple[float, float]) -> Pair:
        """``pair`` refused as two streams' halves that share an index (counted and said): NaN, never learnt."""
        config = self.config
        self.notices.counters["misaligned"] += 1
        self.notices.say(
            "misaligned",
            f"{config.u_name}[{pair.index}] and {config.y_name}[{pair.index}] were published "
            f"{abs(sources[0] - sources[1]):.3f} s apart and not both after the pair before: not one lockstep "
            "publisher, so equal indices are not one sample; refused, never learnt. "
            "Use pairing:=sample sample_period:=T (or pairing:=stamp)",
        )
        return Pair(pair.index, pair.time, math.nan, math.nan)

    def _say_pairing_faults(self, released: bool) -> None:
        """Stale, repeated and unpaired halves of sequence pairing, each said as its count grows.

        Stale ones only when a pair is released: the first halves of a restarted publisher count
        as stale until both halves of its sample 1 are in, and then the Pairer takes them back.
        """
        assert self.pairer is not None
        counters = self.pairer.counters
        faults = counters["stale"] + counters["duplicates"]
        if released and faults > self._seen_faults:
            self.notices.say(
                "stale",
                f"{faults - self._seen_faults} {self.config.u_name}/{self.config.y_name} half(s) ignored, never "
                f"learnt (so far {counters['stale']} stale: index already paired or passed; {counters['duplicates']} "
                "duplicate: index repeated): a second publisher on one topic, one publisher restarted alone, or "
                "messages reordered on the way (a RELIABLE QoS with KEEP_ALL history keeps them in order)",
            )
            self._seen_faults = faults
        self._seen_faults = min(self._seen_faults, faults)  # a restart reclaimed halves counted stale
        if counters["unpaired"] > self._seen_dropped:
            dropped = counters["unpaired"] - self._seen_dropped
            self._seen_dropped = counters["unpaired"]
            self.notices.say("dropped", f"{dropped} half(s) found no partner with the same index and were dropped")

    def _after_merge(self, channel: str, merger: TopicMerger) -> None:
        """A side's topics that do not come together: say which, and what became of the parts."""
        names = self.config.u_parts_names if channel == U else self.config.y_parts_names
        side = "u" if channel == U else "y_p"
        if merger.counters["overflow"]:
            self.notices.doubling(
                f"{channel}_overflow",
                merger.counters["overflow"],
                f"{merger.counters['overflow']} incomplete {side} groups dropped so far: "
                f"more than {merger.window} wait for the side's other topics ({', '.join(names)})",
            )
        seen = self._seen_merge.setdefault(channel, {"merge_dropped": 0, "merge_stale": 0})
        for kind in ("merge_dropped", "merge_stale"):
            count = merger.counters[kind]
            if count <= seen[kind]:
                continue
            topic = ""
            if kind == "merge_stale" and merger.stale_part is not None:
                topic = names[merger.stale_part] if merger.stale_part < len(names) else f"part {merger.stale_part}"
                text = (f"{topic} is older than {merger.max_age:.3f} s when the other topics of its side arrive: "
                        f"no sample formed ({count} so far); is it still published?")  # fmt: skip
            else:
                text = (f"{count - seen[kind]} {side} message(s) found no partner on the "
                        f"side's other topics ({', '.join(names)}) and were dropped ({count} so far)")  # fmt: skip
            self.notices.say(kind, text, topic)
            seen[kind] = count

    def _after_alignment(self) -> None:
        aligner = self.aligner
        assert aligner is not None
        if aligner.restarted:
            aligner.restarted = False
            self.on_restart()
            text = "time went backwards (clock reset, bag looped): history reset"
            if self.clocks.offset is not None:
                text += f"; the inputs' clocks also differ by {abs(self.clocks.offset):.3f} s (see clock_offset)"
            self.notices.say("clock_jump", text)
        overflow = aligner.counters["overflow"]
        if overflow and aligner.overflowed is not None:
            config = self.config
            name, other = (config.u_name, config.y_name)[:: 1 if aligner.overflowed == U else -1]
            self.notices.doubling(
                "overflow",
                overflow,
                f"{overflow} messages dropped unpaired so far: {other} is silent, so {name}'s queue is full "
                f"({aligner.max_queue} waiting for a partner; the newest are kept). Is {other} published?",
            )
        dropped = sum(v for k, v in aligner.counters.items() if k.startswith("dropped") or k == "grid_gaps")
        if dropped > self._seen_dropped:
            what = "grid points without a new y_p (gaps)" if isinstance(aligner, GridSampler) else "unpaired halves"
            self.notices.say("dropped", f"{dropped - self._seen_dropped} {what}: {dict(aligner.counters)}")
            self._seen_dropped = dropped

    # -- reporting -----------------------------------------------------------------------------
    def counters(self) -> dict[str, int]:
        """The pairing's and the mergers' counters, named as ``status`` shows them."""
        source = self.pairer.counters if self.pairer is not None else self.aligner.counters  # type: ignore[union-attr]
        counters = dict(source)
        for channel, merger in self.mergers.items():
            for name, value in merger.counters.items():
                counters[f"{channel}_{name}"] = value
        return counters

    def queued(self) -> dict[str, int]:
        """Halves waiting to be paired and parts waiting to be merged (all bounded)."""
        source = self.pairer if self.pairer is not None else self.aligner
        return {
            "pairing": source.queued if source is not None else 0,
            "merging": sum(merger.queued for merger in self.mergers.values()),
        }
