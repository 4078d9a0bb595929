"""Whether the inputs arrive: one arriving alone, neither arriving, and whether their stamps share a clock.

Two small watches of the halves offered to a session, each saying what it sees in one line:

- :class:`Presence`: an input arriving alone for ``lone_timeout`` (nothing on the other: its
  topic, type or QoS, or a field that cannot be read), and neither arriving for
  ``silence_timeout`` after data flowed (a stopped driver, or one that publishes only on
  change while the robot stands still), said once and shown in ``status`` until data comes.
- :class:`ClockWatch`: the inputs' least (receive - time) over their last messages; two that
  differ by more than ``max_clock_offset`` (default max(T/2, 50 ms)) are two clocks, and every
  pair is shifted by that offset, which nothing in the pairing can tell.
"""

from __future__ import annotations

import math
from collections import deque

from lenn_ros.core.pairing import U, Y
from lenn_ros.session.config import SessionConfig
from lenn_ros.session.notices import Notices

#: Halves per input whose (receive - time) make the clock-offset estimate: their least, since an offset
#: shifts every message and a delay (load, a stall's burst) only some; at 200 Hz 1.3 s, at 50 Hz 5 s.
CLOCK_WINDOW = 256


class Presence:
    """When each input last arrived, and what its absence means (see the module docstring)."""

    def __init__(self, config: SessionConfig, notices: Notices) -> None:
        self.config, self.notices = config, notices
        self.last_seen: dict[str, float] = {}
        self.first_seen: dict[str, float] = {}
        self.unreadable: dict[str, tuple[int, float, str]] = {}  # channel: (count, last receive time, why)
        self.silent_since: float | None = None  # receive time of the last message, while the silence is said

    def arrived(self, channel: str, received: float) -> None:
        """A message of ``channel`` at receive time ``received``: counted, and alone or not."""
        counters = self.notices.counters
        counters["u_messages" if channel == U else "y_messages"] += 1
        self.first_seen.setdefault(channel, received)
        self.last_seen[channel] = received
        if self.silent_since is not None:
            name = self.config.u_name if channel == U else self.config.y_name
            self.notices.say("inputs_resumed", f"{name} arrived again after {received - self.silent_since:.1f} s "
                             "without data: learning goes on")  # fmt: skip
            self.silent_since = None
        if self.alone_for(channel, received) > 0.0:
            counters[f"lone_{channel}"] += 1

    def unreadable_message(self, channel: str, received: float, why: str) -> None:
        """A message that arrived whose field could not be read: counted, and kept for the lone notice."""
        self.notices.counters["field_errors"] += 1
        count = self.unreadable.get(channel, (0, 0.0, ""))[0] + 1
        self.unreadable[channel] = (count, received, why)

    def alone_for(self, channel: str, now: float) -> float:
        """How long ``channel`` has been arriving while the other input is silent (0: not alone)."""
        seen = self.last_seen.get(channel)
        if seen is None or now - seen > self.config.lone_timeout:
            return 0.0
        other_seen = self.last_seen.get(Y if channel == U else U)
        if other_seen is not None and now - other_seen <= self.config.lone_timeout:
            return 0.0
        return now - max(self.first_seen[channel], other_seen if other_seen is not None else -math.inf)

    def check(self, now: float) -> None:
        """Time passes: say a lone input, and a silence of both."""
        self._check_lone(now)
        self._check_silence(now)

    def _check_silence(self, now: float) -> None:
        timeout = self.config.silence_timeout
        if not timeout or not self.last_seen or self.silent_since is not None:
            return
        last = max(self.last_seen.values())
        if now - last < timeout:
            return
        self.silent_since = last
        self.notices.counters["silences"] += 1
        self.notices.say("silence", f"nothing on {self.config.u_name} or {self.config.y_name} for {now - last:.1f} s "
                         f"(silence_timeout {timeout:g} s): no sample to learn from; a stopped driver, or one that "
                         "publishes only on change while the robot stands still?")  # fmt: skip

    def _check_lone(self, now: float) -> None:
        for channel in (U, Y):
            alone = self.alone_for(channel, now)
            if alone < self.config.lone_timeout:
                continue
            topic, missing = (self.config.u_name, self.config.y_name)[:: 1 if channel == U else -1]
            lone = self.notices.counters[f"lone_{channel}"]
            head = f"{topic} has been arriving alone for {alone:.1f} s ({lone} messages)"
            count, last, why = self.unreadable.get(Y if channel == U else U, (0, -math.inf, ""))
            if now - last <= self.config.lone_timeout:
                text = (f"{head}: {count} messages arrived on {missing} but their field could not be read: {why}; "
                        "so no pairs form (fix the field path, or the type, to fit these messages)")  # fmt: skip
            else:
                text = (f"{head}: nothing on {missing}, so no pairs form (check {missing}'s topic name/remap, "
                        "type and QoS)")  # fmt: skip
            self.notices.say(f"lone_{channel}", text)


class ClockWatch:
    """Compare the inputs' (receive - time): see the module docstring."""

    def __init__(self, config: SessionConfig, notices: Notices) -> None:
        self.config, self.notices = config, notices
        self._lags: dict[str, deque[float]] = {U: deque(maxlen=CLOCK_WINDOW), Y: deque(maxlen=CLOCK_WINDOW)}
        self._stamped = {U: False, Y: False}
        self._checks = 0
        self.offset: float | None = None  # least lag of y_p minus that of u while it stands, s

    def observe(self, channel: str, time: float, received: float) -> None:
        """One half's time and arrival.

        A message timed by its arrival has time == received (the node and evaluate pass the
        same number), so its lag is 0 and the other input's least lag is the offset of its
        stamps. The least, not the median: on one host with one clock a loaded machine delays
        most messages by tens of ms, yet some still arrive at once, while a clock offset delays
        every one of them (a median above 50 ms under load was said as a clock offset). Taken
        every 16 halves once each input has half a window (the first messages after discovery
        can come late): cheap at kilohertz rates, and a burst delayed by a stall moves neither.
        """
        self._lags[channel].append(received - time)
        self._stamped[channel] = time != received
        counters = self.notices.counters
        if self.offset is not None:
            counters["clock_offset"] += 1
        self._checks += 1
        if self._checks % 16 or min(len(lags) for lags in self._lags.values()) < CLOCK_WINDOW // 2:
            return
        lag = {name: min(lags) for name, lags in self._lags.items()}
        offset = lag[Y] - lag[U]
        limit = self.config.max_clock_offset or max(0.5 * self.config.sample_period, 0.05)
        if self.offset is None and abs(offset) > limit:
            self.offset = offset
            counters["clock_offset"] += 1
            self.notices.say("clock_offset", self._text(lag, limit))
        elif self.offset is not None and abs(offset) <= 0.5 * limit:
            self.offset = None  # the clocks agree again (hysteresis: no notice per wobble)

    def _text(self, lag: dict[str, float], limit: float) -> str:
        config = self.config
        names = {U: config.u_name, Y: config.y_name}
        offset = abs(lag[Y] - lag[U])
        if all(self._stamped.values()):
            what = (
                f"the header stamps of {names[U]} and {names[Y]} lag their arrival by {lag[U]:.3f} and {lag[Y]:.3f} s "
                f"(at least, over their last {CLOCK_WINDOW} messages): two clocks"
            )
        else:
            stamped = Y if self._stamped[Y] else U
            side = "behind" if lag[stamped] > 0 else "ahead of"
            what = (
                f"{names[stamped]} is timed by its header stamps and {names[U if stamped == Y else Y]} by arrival, "
                f"and {names[stamped]}'s stamps are {abs(lag[stamped]):.3f} s {side} its arrival (every one of its "
                f"last {CLOCK_WINDOW} messages)"
            )
        return (
            f"{what}: each {names[U]} is paired with a {names[Y]} {offset:.3f} s away from it (more than "
            f"{limit * 1e3:.0f} ms: a clock offset, not a delay under load, which leaves some messages on time). "
            "Fix: -p use_header_stamp:=false (time "
            "both inputs by arrival), or synchronise the clocks (chrony/PTP; use_sim_time on every node or none). "
            "If the measurement really is taken that long before it arrives, the stamps are right: ignore this"
        )
