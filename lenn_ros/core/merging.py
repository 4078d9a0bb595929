"""Several topics on one side: the parts of u (or of y_p) merged into one vector half.

A robot's joints may come from one driver per joint, its command from one controller
per actuator: each topic carries some channels of u or y_p, and a sample needs all of
them at once. The :class:`TopicMerger` of a side takes each topic's message (a "part")
and hands the session whole vector halves, which it then pairs as if they had come on
one topic. How parts belong together follows the pairing mode:

- ``sequence``: one lockstep publisher of every topic (the DDS publication sequence
  numbers agree): parts with the same number form a half; a number whose parts do not
  all arrive within ``window`` later numbers is dropped (counted ``merge_dropped``).
- ``stamp``: parts whose stamps agree within ``slop`` (one reading published on several
  topics); a group that stays incomplete for ``max_delay`` of receive time is dropped.
- ``sample``: zero-order hold, as the grid sampler treats u: every part's newest value,
  emitted whenever one part arrives, once every part has arrived at least once and
  none is older than ``max_age`` (receive time) than the newest: a silent topic stops
  the merged stream (``merge_stale``) instead of feeding a value frozen long ago.

At most ``window`` groups wait at once in every mode; beyond that the oldest is dropped
(counted ``overflow``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Half:
    """One merged half: the channels of every part, in topic order."""

    value: np.ndarray
    time: float
    received: float
    sequence: int | None = None
    source_time: float | None = None


@dataclass
class _Group:
    time: float
    received: float
    parts: dict[int, np.ndarray] = field(default_factory=dict)
    sources: dict[int, float | None] = field(default_factory=dict)


@dataclass
class TopicMerger:
    """Parts in, whole halves out; see the module docstring."""

    sizes: tuple[int, ...]  # channels per topic
    mode: str = "sample"
    slop: float = 0.0
    max_delay: float = 0.5
    max_age: float = 0.5
    window: int = 1000
    counters: dict[str, int] = field(
        default_factory=lambda: {"merged": 0, "merge_dropped": 0, "merge_stale": 0, "overflow": 0}
    )

    def __post_init__(self) -> None:
        self._groups: dict[object, _Group] = {}
        self._opened = 0  # stamp groups opened so far (their keys)
        self._latest: dict[int, tuple[np.ndarray, float, float]] = {}
        self.stale_part: int | None = None  # sample mode: the part that held the stream back last

    def add(
        self,
        part: int,
        value: np.ndarray,
        time: float,
        received: float,
        sequence: int | None = None,
        source_time: float | None = None,
    ) -> list[Half]:
        value = np.asarray(value, dtype=np.float64).reshape(-1)
        if value.size != self.sizes[part]:
            value = np.full(self.sizes[part], np.nan)  # (the extractor already said why)
        if self.mode == "sample":
            return self._hold(part, value, time, received)
        key: object = sequence if self.mode == "sequence" else self._stamp_key(part, time)
        group = self._groups.setdefault(key, _Group(time, received))
        if len(self._groups) > self.window:  # (a long max_delay at a high rate): the oldest group goes
            del self._groups[next(iter(self._groups))]
            self.counters["overflow"] += 1
        group.parts[part] = value
        group.sources[part] = source_time
        released = []
        if len(group.parts) == len(self.sizes):
            del self._groups[key]
            released.append(self._whole(group, sequence))
        self._expire(key, received)
        return released

    def _stamp_key(self, part: int, time: float) -> object:
        """The open group this stamp belongs to (within slop, not yet holding this part), else a new one."""
        for key, group in self._groups.items():
            if part not in group.parts and abs(group.time - time) <= self.slop:
                return key
        self._opened += 1
        return ("stamp", self._opened)  # a key of its own: a repeated part opens a group, never overwrites one

    def _whole(self, group: _Group, sequence: int | None) -> Half:
        self.counters["merged"] += 1
        value = np.concatenate([group.parts[part] for part in range(len(self.sizes))])
        sources = [s for s in group.sources.values() if s is not None]
        return Half(value, group.time, group.received, sequence, max(sources) if sources else None)

    def _expire(self, newest: object, received: float) -> None:
        """Drop groups that can no longer complete (older sequence numbers / too long waiting)."""
        if self.mode == "sequence" and isinstance(newest, int):
            old = [key for key in self._groups if isinstance(key, int) and key < newest - self.window]
        else:
            old = [key for key, group in self._groups.items() if received - group.received > self.max_delay]
        for key in old:
            del self._groups[key]
        self.counters["merge_dropped"] += len(old)

    def _hold(self, part: int, value: np.ndarray, time: float, received: float) -> list[Half]:
        self._latest[part] = (value, time, received)
        if len(self._latest) < len(self.sizes):
            return []
        oldest = min(range(len(self.sizes)), key=lambda p: self._latest[p][2])
        if received - self._latest[oldest][2] > self.max_age:
            self.counters["merge_stale"] += 1
            self.stale_part = oldest
            return []
        self.counters["merged"] += 1
        value = np.concatenate([self._latest[p][0] for p in range(len(self.sizes))])
        return [Half(value, time, received)]

    @property
    def queued(self) -> int:
        """Incomplete groups waiting for their other parts."""
        return len(self._groups)

    def flush(self) -> None:
        dropped = len(self._groups)
        self._groups.clear()
        self.counters["merge_dropped"] += dropped


def default_max_age(sample_period: float) -> float:
    """How old a held part may be (receive time) in sample mode: two periods, at least 50 ms."""
    return max(2.0 * sample_period, 0.05) if sample_period > 0 else math.inf
