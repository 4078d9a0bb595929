"""The monitor stages of a session, one per output channel: the one-step band and the change alarm.

Every output of a model has its own (:class:`OutputMonitor`): a model of several outputs gets
the band and the alarm the one-output model has, each naming its channel. Live, each scored
error updates them in order (:meth:`Monitors.watch`); offline, the same calls in the same order
over a batch (:meth:`Monitors.watch_batch`), so a recording evaluated offline has the band the
node published and raises the alarms it raised.

- the band: the one-step std of each prediction (:mod:`lenn_ros.core.spread`: RLS covariance and
  innovation variance), published as ``y_hat_std``;
- the alarm: a CUSUM on e^2 against its learnt level (:mod:`lenn_ros.core.change`), said when it
  rises (WARN on /diagnostics while on) and when it clears.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from lenn_ros.core.change import ACCEPTED, RAISED, ChangeDetector
from lenn_ros.core.spread import OneStepSpread
from lenn_ros.session.config import ParameterChange, SessionConfig
from lenn_ros.session.notices import Notices


class OutputMonitor:
    """One output's band and alarm; ``name``: its channel, said in its lines when the model has several."""

    def __init__(self, name: str, config: SessionConfig, notices: Notices, named: bool) -> None:
        self.name, self.config, self.notices = name, config, notices
        self.where = f" on {name}" if named else ""
        self.spread = OneStepSpread()
        self.change = ChangeDetector(threshold=config.change_threshold)
        self.change_time: float | None = None  # time of the sample the alarm rose at (live; offline None)
        self.change_started: int | None = None  # the sample the last alarm rose at
        self.next_std: float | None = None  # of the pending prediction

    def watch(self, y: float, error: float | None, leverage: float, next_exists: bool, index: int, time: float) -> Any:
        """One scored step: (the std the scored prediction was published with, the next prediction's std)."""
        scored_std = None
        if error is not None:
            scored_std = self.next_std
            self.spread.update(error)
            if self.config.change_alarm:
                event = self.change.update(error, index, y)
                if event:
                    self.say(event, index, time)
        if next_exists:
            self.next_std = self.spread.std(leverage)
        return scored_std, (self.next_std if next_exists else None)

    def watch_batch(
        self,
        index: np.ndarray,
        y: np.ndarray,
        y_hat: np.ndarray,
        leverage: np.ndarray,
        changes: Sequence[ParameterChange],
        before: tuple[bool, float],
    ) -> np.ndarray:
        """:meth:`watch` over a batch: the std each y^(k) was published with (nan: none), the alarm's events said.

        ``before``: (change_alarm, change_threshold) when the batch started; recorded live changes of
        either take effect at their sample, as they did live.
        """
        stds = self._spread_batch(y, y_hat, leverage)
        self._change_batch(index, y, y_hat, changes, before)
        return stds

    def _spread_batch(self, y: np.ndarray, y_hat: np.ndarray, leverage: np.ndarray) -> np.ndarray:
        """The same OneStepSpread calls in the same order as live: each scored error updates it, then the next
        prediction asks for its std with its pattern's leverage (the batch RLS reports the same phi' P phi)."""
        spread = self.spread
        out = np.full(len(y), np.nan)
        errors = (y - y_hat).tolist()
        predicted = np.isfinite(y_hat).tolist()
        levers = leverage.tolist()
        next_std = self.next_std
        update, std = spread.update, spread.std
        for k, error in enumerate(errors):
            if error == error:  # finite where predicted (y is finite in a valid row)
                out[k] = math.nan if next_std is None else next_std
                update(error)
            if k + 1 < len(errors) and predicted[k + 1]:
                next_std = std(levers[k + 1])
        self.next_std = next_std
        return out

    def _change_batch(
        self,
        index: np.ndarray,
        y: np.ndarray,
        y_hat: np.ndarray,
        changes: Sequence[ParameterChange],
        before: tuple[bool, float],
    ) -> None:
        detector = self.change
        watched, detector.threshold = before
        pending = sorted(
            (change for change in changes if {"change_alarm", "change_threshold"} & set(change.values)),
            key=lambda change: change.from_index,
        )
        errors = y - y_hat
        scored = np.flatnonzero(np.isfinite(errors))
        update = detector.update
        measured = y.tolist()
        for row, error in zip(scored.tolist(), errors[scored].tolist(), strict=True):
            sample = int(index[row])
            while pending and pending[0].from_index <= sample:
                values = pending.pop(0).values
                watched = bool(values.get("change_alarm", watched))
                detector.threshold = float(values.get("change_threshold", detector.threshold))
            if watched:
                event = update(error, sample, measured[row])
                if event:
                    self.say(event, sample, None)
        detector.threshold = self.config.change_threshold

    def say(self, event: str, index: int, time: float | None) -> None:
        """The alarm rose (one WARN line: when, by how much) or cleared (one info line: how long it was on)."""
        detector = self.change
        when = f"sample {index}" + (f" (t={time:.3f} s)" if time is not None else "")
        if event == RAISED:
            self.notices.counters["change_alarms"] += 1
            self.change_time, self.change_started = time, index
            self.notices.say("change", self.text(index, time), self.name)
            return
        started, self.change_time = self.change_started, None
        how = (
            "the model has re-learnt: residual level back within "
            f"{detector.clear_ratio:g}x its learnt level for {detector.hold_samples} samples"
            if event != ACCEPTED
            else f"the model did not get back to the old level in {detector.accept_samples} samples: its level now "
            "is taken as the learnt one"
        )
        self.notices.say(
            "change_cleared",
            f"{when}: plant change alarm{self.where} (raised at sample {started}, peak {detector.peak:.1f}x) "
            f"cleared: {how}",
            self.name,
        )

    def text(self, index: int, time: float | None) -> str:
        """The alarm in one line: when, where, and by how much the residual level rose."""
        detector = self.change
        when = f"sample {index}" + (f" (t={time:.3f} s)" if time is not None else "")
        return (
            f"plant changed{self.where} at {when}: residual level {detector.magnitude:.1f} times its learnt level "
            f"(RMS one-step error; CUSUM over change_threshold {detector.threshold:g}; alarm {detector.count})"
        )

    def status(self) -> dict[str, Any]:
        watched = {"watched": True} if self.config.change_alarm else {"watched": False, "why": "change_alarm is false"}
        return {**self.change.status(), **watched, "since_time": self.change_time}


class Monitors:
    """An :class:`OutputMonitor` per output channel of the model."""

    def __init__(self, names: Sequence[str], config: SessionConfig, notices: Notices) -> None:
        self.outputs = [OutputMonitor(name, config, notices, len(names) > 1) for name in names]

    def watch(self, ys: list[float], result: Any, index: int, time: float) -> None:
        """One step's results, output by output; the stds go into each output's result (published with y^)."""
        for monitor, y, out in zip(self.outputs, ys, result.outputs, strict=True):
            scored, following = monitor.watch(y, out.error, out.leverage, out.y_hat_next is not None, index, time)
            if out.error is not None:
                out.y_hat_std = scored
            if out.y_hat_next is not None:
                out.y_hat_next_std = following
        result.gather_stds()

    def watch_batch(
        self,
        index: np.ndarray,
        y: np.ndarray,
        y_hat: np.ndarray,
        leverage: np.ndarray,
        changes: Sequence[ParameterChange],
        before: tuple[bool, float],
    ) -> np.ndarray:
        """Every output over a batch: the stds (N, outputs) each prediction was published with."""
        columns, predicted = y.reshape(len(y), -1), y_hat.reshape(len(y), -1)
        stds = [
            monitor.watch_batch(index, columns[:, j], predicted[:, j], leverage[:, j], changes, before)
            for j, monitor in enumerate(self.outputs)
        ]
        return np.stack(stds, axis=1) if stds else np.empty((len(y), 0))

    @property
    def alarm(self) -> OutputMonitor | None:
        """The first output whose alarm is on (None: none is)."""
        return next((monitor for monitor in self.outputs if monitor.change.alarm), None)

    def status(self) -> dict[str, Any]:
        """``status['change']``: the first output's (an alarm on any output wins), and every output's."""
        shown = self.alarm or self.outputs[0]
        return {**shown.status(), "channel": shown.name, "channels": {m.name: m.status() for m in self.outputs}}
