"""Pairing u and y_p that come from different publishers: by stamp, or on a sample grid.

Sequence numbers pair only what one lockstep publisher sends (see
:mod:`lenn_ros.core.pairing`). On a robot the command and the measurement come from
different nodes, at their own rates and phases, so two other rules are offered:

- :class:`StampAligner` (``pairing: stamp``): pairs messages whose times agree
  within ``slop`` seconds, message_filters' ApproximateTime rule for two topics: a
  message is never paired with one farther away than a later candidate would be,
  and a message that can no longer find a partner within ``slop`` is dropped.
- :class:`GridSampler` (``pairing: sample``): a sampled-data identifier's view: one
  y_p per period T, with the u held at the time of that y_p. Grid points t_k =
  offset + k T sit on the measurements (the grid starts at the first y_p and follows
  the median phase of the recent ones), so each cell (t_k - T/2, t_k + T/2] holds
  one measurement even when stamps jitter: y(k) is the latest y_p stamped in it,
  u(k) the latest u with time <= that y_p's time (zero-order hold), and the
  sample's time is the y_p's. A cell without a new y_p is a gap (unless the last
  one is younger than ``y_max_age``, then it is reused): a lost or late
  measurement never becomes a repeated or shifted one.

Both keep at most ``max_queue`` halves per input (:data:`MAX_QUEUE`): while one input is
silent (a controller not yet started, a driver that stalled) the other's halves would
otherwise pile up without end. The oldest go first (the newest win) and are counted
``overflow``.

Both emit :class:`Pair` with an *index* that advances by the number of sample periods
elapsed, so a lost sample shows as a gap to the identifier (which then restarts its
regressor history) instead of silently joining two samples that were not adjacent.
Times are seconds on one clock (header stamps where the message has them, else
receive times; in simulation, the ROS clock). One input's time moving back by more
than ``jump_back`` seconds is a clock jump (a bag looped, a simulator reset): history
is dropped and pairing starts again. Two inputs on different clocks (stamps against
receive times, offset) are not a jump; the session detects that and says so.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field
from statistics import median
from typing import ClassVar

U, Y = "u", "y"
#: Halves kept per input while they wait for the other input: 10 s at 1 kHz, more than any
#: max_delay a pairing waits for a late partner, and a few hundred kB at most.
MAX_QUEUE = 10_000


@dataclass(slots=True)
class Pair:
    """One aligned sample: y(k) and the u(k) that acts with it.

    Not frozen, though nothing changes one: a frozen dataclass's ``__init__`` costs three
    times a slotted one's, and a pair is made for every sample (issue 19's step cost).
    """

    index: int
    time: float
    u: float
    y: float


@dataclass
class _Half:
    time: float
    value: float
    received: float


def _counters(*names: str) -> dict[str, int]:
    return dict.fromkeys(names, 0)


@dataclass
class StampAligner:
    """ApproximateTime for two topics; see the module docstring."""

    slop: float = 0.0
    max_delay: float = 0.5
    jump_back: float = 1.0
    max_queue: int = MAX_QUEUE
    counters: dict[str, int] = field(
        default_factory=lambda: _counters("paired", "dropped_u", "dropped_y", "stale", "clock_jumps", "overflow")
    )

    def __post_init__(self) -> None:
        self._queues: dict[str, deque[_Half]] = {U: deque(), Y: deque()}
        self._last_time: dict[str, float] = {}
        self._last_pair_time: float | None = None
        self._index = 0
        self._periods: deque[float] = deque(maxlen=31)
        self.restarted = False  # set on a clock jump; the caller restarts the model's history
        self.overflowed: str | None = None  # the input whose queue overflowed last

    def add(self, channel: str, value: float, time: float, received: float) -> list[Pair]:
        last = self._last_time.get(channel)
        if last is not None and time < last:
            if last - time > self.jump_back:
                self._clock_jump()
            else:
                self.counters["stale"] += 1
                return []
        self._last_time[channel] = time
        queue = self._queues[channel]
        queue.append(_Half(time, value, received))
        if len(queue) > self.max_queue:  # the other input is silent: the newest win
            queue.popleft()
            self.counters["overflow"] += 1
            self.overflowed = channel
        return self._match(now=received)

    @property
    def queued(self) -> int:
        """Halves waiting for a partner, both inputs."""
        return sum(len(queue) for queue in self._queues.values())

    def poll(self, now: float) -> list[Pair]:
        """Settle pairs that waited for a better candidate longer than ``max_delay``."""
        return self._match(now=now)

    def _clock_jump(self) -> None:
        self.counters["clock_jumps"] += 1
        self._queues = {U: deque(), Y: deque()}
        self._last_time = {}
        self._last_pair_time = None
        self._periods.clear()
        self.restarted = True

    def _drop(self, channel: str) -> None:
        self._queues[channel].popleft()
        self.counters["dropped_u" if channel == U else "dropped_y"] += 1

    def _match(self, now: float) -> list[Pair]:
        pairs: list[Pair] = []
        queues = self._queues
        while queues[U] and queues[Y]:
            head_u, head_y = queues[U][0], queues[Y][0]
            if head_u.time < head_y.time - self.slop:
                self._drop(U)  # every y to come is later still: u can find no partner
                continue
            if head_y.time < head_u.time - self.slop:
                self._drop(Y)
                continue
            earlier = U if head_u.time < head_y.time else Y
            later_time = (head_y if earlier == U else head_u).time
            queue = queues[earlier]
            if len(queue) > 1:
                if abs(queue[1].time - later_time) < abs(queue[0].time - later_time):
                    self._drop(earlier)  # its successor is the closer partner
                    continue
            elif head_u.time != head_y.time and now - queue[0].received < self.max_delay:
                break  # a closer successor may still come
            queues[U].popleft()
            queues[Y].popleft()
            pairs.append(self._emit(head_y.time, head_u.value, head_y.value))
        return pairs

    def _emit(self, time: float, u: float, y: float) -> Pair:
        step = 1
        if self._last_pair_time is not None:
            interval = time - self._last_pair_time
            if self._periods:
                period = median(self._periods)
                step = max(1, round(interval / period)) if period > 0 else 1
            if step == 1 and interval > 0:
                self._periods.append(interval)
        self._last_pair_time = time
        self._index += step
        self.counters["paired"] += 1
        return Pair(self._index, time, u, y)


@dataclass
class GridSampler:
    """Zero-order-hold sampling of two asynchronous streams; see the module docstring.

    The grid is aligned to the first y_p message (``offset``) and re-centred every
    ``TRACK_EVERY`` measurements on their median offset from their grid points: a
    driver's stamps jitter around its steps (and its clock may run a little off
    ``period``), and a grid point that sat exactly on them would see half of them
    fall just after it. Mid-cell, a stamp may be up to T/2 off before it lands in the
    wrong cell. A grid point closes once both streams have moved past its cell, or
    ``max_delay`` seconds of receive time after it (a command published only on
    change is simply held).
    """

    #: Measurements per re-centring of the grid (odd: the median is one of them).
    TRACK_EVERY: ClassVar[int] = 25

    period: float
    max_delay: float = 0.0  # 0: two periods, at least 50 ms
    y_max_age: float = 0.0  # an old y_p may be reused this long (0: every sample needs a new y_p)
    u_max_age: float = 0.0  # 0: no limit (a command holds until replaced)
    jump_back: float = 1.0
    max_queue: int = MAX_QUEUE
    counters: dict[str, int] = field(
        default_factory=lambda: _counters("paired", "grid_gaps", "late", "clock_jumps", "overflow")
    )

    def __post_init__(self) -> None:
        if not self.period > 0:
            raise ValueError("sample mode needs sample_period > 0 (seconds)")
        # Not below 10 us: times are seconds since 1970 as doubles (resolution ~0.24 us), so
        # a stamp exactly on a grid point may land a few ulp either side of it.
        self._epsilon = max(1e-6 * self.period, 1e-5)
        self._half = 0.5 * self.period
        self._delay = self.max_delay or max(2 * self.period, 0.05)
        self._y_age = self.y_max_age + self._epsilon if self.y_max_age else -math.inf
        self._u_age = self.u_max_age + self._epsilon if self.u_max_age else math.inf
        self.restarted = False
        self.overflowed: str | None = None  # the input whose queue overflowed last
        self._reset()

    def _reset(self) -> None:
        self._times: dict[str, list[float]] = {U: [], Y: []}
        self._values: dict[str, list[float]] = {U: [], Y: []}
        self._newest: dict[str, float] = {}
        self._offset: float | None = None
        self._first_k: int | None = None
        self._next_k: int | None = None
        self._last_y_time = -math.inf
        self._residuals: list[float] = []

    def grid_time(self, k: int) -> float:
        assert self._offset is not None
        return self._offset + k * self.period

    def _cell(self, time: float) -> int:
        """The grid point whose cell (t_k - T/2, t_k + T/2] holds ``time``."""
        assert self._offset is not None
        return math.ceil((time - self._half - self._offset) / self.period - 1e-6)

    def add(self, channel: str, value: float, time: float, received: float) -> list[Pair]:
        newest = self._newest.get(channel)
        if newest is not None and time < newest - self.jump_back:
            # This input's own clock went back: a stream behind the grid is merely late (or on another clock).
            self.counters["clock_jumps"] += 1
            self._reset()
            self.restarted = True
        self._newest[channel] = time if newest is None else max(newest, time)
        times, values = self._times[channel], self._values[channel]
        if self._next_k is not None:
            closed = self.grid_time(self._next_k - 1) + (self._half if channel == Y else 0.0)
            if time <= closed + self._epsilon:
                self.counters["late"] += 1  # its grid point is closed; it still holds for later ones
        position = bisect.bisect_right(times, time)
        times.insert(position, time)
        values.insert(position, value)
        if len(times) > self.max_queue:  # nothing closes grid points while an input is silent: the newest win
            del times[0], values[0]
            self.counters["overflow"] += 1
            self.overflowed = channel
        if self._offset is None and channel == Y:
            self._offset = math.fmod(time, self.period)
        if self._next_k is None and self._offset is not None and self._times[U]:
            self._first_k = max(self._cell(self._times[U][0]), self._cell(self._times[Y][0]))
            self._next_k = self._first_k
        return self._close(now=received)

    def poll(self, now: float) -> list[Pair]:
        return self._close(now=now)

    @property
    def queued(self) -> int:
        """Measurements and commands kept for grid points to come, both inputs."""
        return sum(len(times) for times in self._times.values())

    def _latest(self, channel: str, time: float) -> int:
        """Position of the latest sample of ``channel`` at or before ``time`` (-1: none)."""
        return bisect.bisect_right(self._times[channel], time + self._epsilon) - 1

    def _close(self, now: float) -> list[Pair]:
        pairs: list[Pair] = []
        while self._next_k is not None:
            k = self._next_k
            t_k = self.grid_time(k)
            end = t_k + self._half
            passed = all(times and times[-1] > end + self._epsilon for times in self._times.values())
            if not passed and now < t_k + self._delay:
                break  # a message for cell k may still be on its way
            i_y = self._latest(Y, end)
            y_time = self._times[Y][i_y] if i_y >= 0 else -math.inf
            # new, and measured in this cell (an older one closed late is not y(k))
            new = y_time > self._last_y_time and y_time > t_k - self._half + self._epsilon
            when = y_time if new else (t_k if t_k - y_time <= self._y_age else None)
            i_u = self._latest(U, when) if when is not None else -1
            if i_u >= 0 and when - self._times[U][i_u] <= self._u_age:
                if new:
                    self._last_y_time = y_time
                    self._track(y_time - t_k)
                pairs.append(Pair(k - self._first_k + 1, when, self._values[U][i_u], self._values[Y][i_y]))
                self.counters["paired"] += 1
                self._next_k = k + 1
            elif k == self._first_k and i_y >= 0 and when is not None and i_u < 0:
                self._first_k = self._next_k = k + 1  # its y_p came before the first command: not yet a start
            elif not self._skip_to_data(k):
                break  # no y_p after cell k yet: wait for data (a quiet plant is not a stream of gaps)
            self._trim()
        return pairs

    def _track(self, residual: float) -> None:
        """Re-centre the grid on the measurements' median phase (a step at most T/4: robust to one odd batch)."""
        self._residuals.append(residual)
        if len(self._residuals) < self.TRACK_EVERY:
            return
        shift = min(max(median(self._residuals), -0.5 * self._half), 0.5 * self._half)
        self._residuals.clear()
        if abs(shift) > self._epsilon:
            assert self._offset is not None
            self._offset += shift

    def _skip_to_data(self, k: int) -> bool:
        """Grid point k has no fresh data: a gap up to where y_p resumes (False: not yet known)."""
        times = self._times[Y]
        after = bisect.bisect_right(times, self.grid_time(k) + self._half + self._epsilon)
        if after == len(times):
            return False
        resume = max(self._cell(times[after]), k + 1)
        self.counters["grid_gaps"] += resume - k
        self._next_k = resume
        return True

    def _trim(self) -> None:
        """Keep only what a later grid point can still use (the held value and newer).

        A period of margin: the grid may since have been re-centred back by up to T/4.
        """
        t_kept = self.grid_time(self._next_k - 1) - self.period
        for channel in (U, Y):
            keep = max(self._latest(channel, t_kept), 0)
            if keep:
                del self._times[channel][:keep]
                del self._values[channel][:keep]

    def flush(self) -> list[Pair]:
        """End of data (offline): close every grid point both streams have reached."""
        if self._next_k is None or not (self._times[U] and self._times[Y]):
            return []
        last = min(self._times[U][-1], self._times[Y][-1])
        return self._close(now=last + self._delay - self._epsilon)
