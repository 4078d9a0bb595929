"""Pairing u and y_p that come from different publishers: by stamp, or on a sample grid.

Sequence numbers pair only what one lockstep publisher sends (see
:mod:`lenn_ros.core.pairing`). On a robot the command and the measurement come from
different nodes, at their own rates and phases, so two other rules are offered:

- :class:`StampAligner` (``pairing: stamp``): pairs messages whose times agree
  within ``slop`` seconds, message_filters' ApproximateTime rule for two topics: a
  message is never paired with one farther away than a later candidate would be,
  and a message that can no longer find a partner within ``slop`` is dropped.
- :class:`GridSampler` (``pairing: sample``): a sampled-data identifier's view. At
  each grid time t_k = offset + k T the pair is the latest u and the latest y_p with
  time <= t_k (zero-order hold). y_p must be a new measurement, taken after the
  previous grid point (unless younger than ``y_max_age``), or the sample is a
  gap: a lost or late measurement never becomes a repeated or shifted one.

Both emit :class:`Pair` with an *index* that advances by the number of sample periods
elapsed, so a lost sample shows as a gap to the identifier (which then restarts its
regressor history) instead of silently joining two samples that were not adjacent.
Times are seconds on one clock (header stamps where the message has them, else
receive times; in simulation, the ROS clock). Time moving back by more than
``jump_back`` seconds is a clock jump (a bag looped, a simulator reset): history is
dropped and pairing starts again.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field
from statistics import median

U, Y = "u", "y"


@dataclass(frozen=True)
class Pair:
    """One aligned sample: y(k) and the u(k) that acts with it."""

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
    counters: dict[str, int] = field(
        default_factory=lambda: _counters("paired", "dropped_u", "dropped_y", "stale", "clock_jumps")
    )

    def __post_init__(self) -> None:
        self._queues: dict[str, deque[_Half]] = {U: deque(), Y: deque()}
        self._last_time: dict[str, float] = {}
        self._last_pair_time: float | None = None
        self._index = 0
        self._periods: deque[float] = deque(maxlen=31)
        self.restarted = False  # set on a clock jump; the caller restarts the model's history

    def add(self, channel: str, value: float, time: float, received: float) -> list[Pair]:
        last = self._last_time.get(channel)
        if last is not None and time < last:
            if last - time > self.jump_back:
                self._clock_jump()
            else:
                self.counters["stale"] += 1
                return []
        self._last_time[channel] = time
        self._queues[channel].append(_Half(time, value, received))
        return self._match(now=received)

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

    The grid is aligned to the first y_p message (``offset``), so when y_p is stamped
    at the plant's own steps every grid point falls on a measurement. A grid point
    closes once both streams have moved past it, or ``max_delay`` seconds of
    receive time after it (a command published only on change is simply held).
    """

    period: float
    max_delay: float = 0.0  # 0: two periods, at least 50 ms
    y_max_age: float = 0.0  # an old y_p may be reused this long (0: every sample needs a new y_p)
    u_max_age: float = 0.0  # 0: no limit (a command holds until replaced)
    jump_back: float = 1.0
    counters: dict[str, int] = field(
        default_factory=lambda: _counters("paired", "grid_gaps", "late", "clock_jumps")
    )

    def __post_init__(self) -> None:
        if not self.period > 0:
            raise ValueError("sample mode needs sample_period > 0 (seconds)")
        # Not below 10 us: times are seconds since 1970 as doubles (resolution ~0.24 us), so
        # a stamp exactly on a grid point may land a few ulp either side of it.
        self._epsilon = max(1e-6 * self.period, 1e-5)
        self._delay = self.max_delay or max(2 * self.period, 0.05)
        self._y_age = self.y_max_age + self._epsilon if self.y_max_age else -math.inf
        self._u_age = self.u_max_age + self._epsilon if self.u_max_age else math.inf
        self.restarted = False
        self._reset()

    def _reset(self) -> None:
        self._times: dict[str, list[float]] = {U: [], Y: []}
        self._values: dict[str, list[float]] = {U: [], Y: []}
        self._offset: float | None = None
        self._first_k: int | None = None
        self._next_k: int | None = None
        self._last_y_time = -math.inf

    def grid_time(self, k: int) -> float:
        assert self._offset is not None
        return self._offset + k * self.period

    def add(self, channel: str, value: float, time: float, received: float) -> list[Pair]:
        if self._next_k is not None and time < self.grid_time(self._next_k - 1) - self.jump_back:
            self.counters["clock_jumps"] += 1
            self._reset()
            self.restarted = True
        times, values = self._times[channel], self._values[channel]
        if self._next_k is not None and time <= self.grid_time(self._next_k - 1) + self._epsilon:
            self.counters["late"] += 1  # its grid point is closed; it still holds for later ones
        position = bisect.bisect_right(times, time)
        times.insert(position, time)
        values.insert(position, value)
        if self._offset is None and channel == Y:
            self._offset = math.fmod(time, self.period)
        if self._next_k is None and self._offset is not None and self._times[U]:
            start = max(self._times[U][0], self._times[Y][0])
            self._first_k = math.ceil((start - self._offset) / self.period - 1e-6)
            self._next_k = self._first_k
        return self._close(now=received)

    def poll(self, now: float) -> list[Pair]:
        return self._close(now=now)

    def _latest(self, channel: str, time: float) -> int:
        """Position of the latest sample of ``channel`` at or before ``time`` (-1: none)."""
        return bisect.bisect_right(self._times[channel], time + self._epsilon) - 1

    def _close(self, now: float) -> list[Pair]:
        pairs: list[Pair] = []
        while self._next_k is not None:
            k = self._next_k
            t_k = self.grid_time(k)
            passed = all(times and times[-1] > t_k + self._epsilon for times in self._times.values())
            if not passed and now < t_k + self._delay:
                break  # a message for t_k may still be on its way
            i_u, i_y = self._latest(U, t_k), self._latest(Y, t_k)
            fresh = i_u >= 0 and i_y >= 0 and t_k - self._times[U][i_u] <= self._u_age
            if fresh:
                y_time = self._times[Y][i_y]
                # new, and measured since the previous grid point (an older one closed late is not y(k))
                new = y_time > self._last_y_time and y_time > t_k - self.period + self._epsilon
                fresh = new or t_k - y_time <= self._y_age
            if fresh:
                self._last_y_time = self._times[Y][i_y]
                pairs.append(Pair(k - self._first_k + 1, t_k, self._values[U][i_u], self._values[Y][i_y]))
                self.counters["paired"] += 1
                self._next_k = k + 1
            elif not self._skip_to_data(k):
                break  # no y_p after t_k yet: wait for data (a quiet plant is not a stream of gaps)
            self._trim()
        return pairs

    def _skip_to_data(self, k: int) -> bool:
        """Grid point k has no fresh data: a gap up to where y_p resumes (False: not yet known)."""
        t_k = self.grid_time(k)
        later = [t for t in self._times[Y] if t > t_k + self._epsilon]
        if not later:
            return False
        resume = max(math.ceil((later[0] - self._offset) / self.period - 1e-6), k + 1)
        self.counters["grid_gaps"] += resume - k
        self._next_k = resume
        return True

    def _trim(self) -> None:
        """Keep only what a later grid point can still use (the held value and newer)."""
        t_closed = self.grid_time(self._next_k - 1)
        for channel in (U, Y):
            keep = max(self._latest(channel, t_closed), 0)
            if keep:
                del self._times[channel][:keep]
                del self._values[channel][:keep]

    def flush(self) -> list[Pair]:
        """End of data (offline): close every grid point both streams have reached."""
        if self._next_k is None or not (self._times[U] and self._times[Y]):
            return []
        last = min(self._times[U][-1], self._times[Y][-1])
        return self._close(now=last + self._delay - self._epsilon)
