"""The monitor stages of a session, one per output channel: the one-step band and the change alarm.

Every output of a model has its own (:class:`OutputMonitor`): a model of several outputs gets
the band and the alarm the one-output model has, each naming its channel. Live, each scored
error updates them in order (:meth:`Monitors.watch`); offline, the same calls in the same order
over a batch (:meth:`Monitors.watch_batch`), so a recording evaluated offline has the band the
node published and raises the alarms it raised.

- the band: the one-step std of each prediction (:mod:`lenn_ros.core.spread`: RLS covariance and
  innovation variance), published as ``y_hat_std``, and the live band's half-width (``LiveBand``: the std
  times a multiplier that keeps the running coverage at 95 %), published as ``y_hat_band``;
- the alarm: a CUSUM over blocks of a frozen reference model's free-run errors against their learnt
  level (:mod:`lenn_ros.core.change`), fed each scored sample with what the output's model reads, and the
  references the learner took; said when it rises (WARN on /diagnostics while on), when it clears, and
  whether it is armed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from lenn_ros.core.change import ACCEPTED, ARMED, RAISED, UNARMED, ChangeDetector, Reference
from lenn_ros.core.spread import LiveBand, OneStepSpread
from lenn_ros.session.config import ParameterChange, SessionConfig
from lenn_ros.session.notices import Notices


class OutputMonitor:
    """One output's band and alarm; ``name``: its channel, said in its lines when the model has several."""

    def __init__(self, name: str, config: SessionConfig, notices: Notices, named: bool) -> None:
        self.name, self.config, self.notices = name, config, notices
        self.where = f" on {name}" if named else ""
        self.spread = OneStepSpread()
        self.band = LiveBand()
        self.change = ChangeDetector(threshold=config.change_threshold)
        self.change_time: float | None = None  # time of the sample the alarm rose at (live; offline None)
        self.change_started: int | None = None  # the sample the last alarm rose at
        self.next_std: float | None = None  # of the pending prediction
        self.next_band: float | None = None  # its live band's half-width

    def watch(self, y: float, out: Any, index: int, time: float, u: Any) -> None:
        """One scored step of this output's result ``out``: the std and live half-width the scored prediction was
        published with (``y_hat_std``, ``y_hat_band``), and the next prediction's (``y_hat_next_*``); ``u``: what
        the output's model reads beside its output, for the alarm's reference."""
        error = out.error
        if error is not None:
            out.y_hat_std, out.y_hat_band = self.next_std, self.next_band
            self.spread.update(error)
            self.band.update(error, self.next_band)
            if self.config.change_alarm:
                event = self.change.update(u, y, index)
                if event:
                    self.say(event, index, time)
        if out.y_hat_next is not None:
            self.next_std = out.y_hat_next_std = self.spread.std(out.leverage)
            self.next_band = out.y_hat_next_band = self.band.half_width(self.next_std)

    def watch_batch(
        self,
        index: np.ndarray,
        y: np.ndarray,
        y_hat: np.ndarray,
        leverage: np.ndarray,
        changes: Sequence[ParameterChange],
        before: tuple[bool, float],
        u: np.ndarray,
        references: Sequence[tuple[int, Reference]] = (),
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`watch` over a batch: the std and the live half-width each y^(k) was published with (nan: none),
        the alarm's events said.

        ``before``: (change_alarm, change_threshold) when the batch started; recorded live changes of
        either take effect at their sample, as they did live. ``u``: what the output's model reads, per row;
        ``references``: (sample, reference) the learner took, each offered before that sample, as live.
        """
        bands = self._spread_batch(y, y_hat, leverage)
        self._change_batch(index, y, y_hat, changes, before, u, references)
        return bands

    def _spread_batch(self, y: np.ndarray, y_hat: np.ndarray, leverage: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The same OneStepSpread and LiveBand calls in the same order as live: each scored error updates them,
        then the next prediction asks for its std with its pattern's leverage (the batch RLS reports the same
        phi' P phi) and for its half-width."""
        stds, halves = np.full(len(y), np.nan), np.full(len(y), np.nan)
        errors = (y - y_hat).tolist()
        predicted = np.isfinite(y_hat).tolist()
        levers = leverage.tolist()
        next_std, next_band = self.next_std, self.next_band
        update, std = self.spread.update, self.spread.std
        learn, half_width = self.band.update, self.band.half_width
        for k, error in enumerate(errors):
            if error == error:  # finite where predicted (y is finite in a valid row)
                stds[k] = math.nan if next_std is None else next_std
                halves[k] = math.nan if next_band is None else next_band
                update(error)
                learn(error, next_band)
            if k + 1 < len(errors) and predicted[k + 1]:
                next_std = std(levers[k + 1])
                next_band = half_width(next_std)
        self.next_std, self.next_band = next_std, next_band
        return stds, halves

    def _change_batch(
        self,
        index: np.ndarray,
        y: np.ndarray,
        y_hat: np.ndarray,
        changes: Sequence[ParameterChange],
        before: tuple[bool, float],
        u: np.ndarray,
        references: Sequence[tuple[int, Reference]],
    ) -> None:
        detector = self.change
        watched, detector.threshold = before
        pending = sorted(
            (change for change in changes if {"change_alarm", "change_threshold"} & set(change.values)),
            key=lambda change: change.from_index,
        )
        offered = list(references)
        scored = np.flatnonzero(np.isfinite(y - y_hat))
        update, offer = detector.update, detector.offer
        measured, inputs = y.tolist(), u.tolist()
        for row in scored.tolist():
            sample = int(index[row])
            while offered and offered[0][0] <= sample:
                offer(offered.pop(0)[1])
            while pending and pending[0].from_index <= sample:
                values = pending.pop(0).values
                watched = bool(values.get("change_alarm", watched))
                detector.threshold = float(values.get("change_threshold", detector.threshold))
            if watched:
                event = update(inputs[row], measured[row], sample)
                if event:
                    self.say(event, sample, None)
        for _, reference in offered:
            offer(reference)
        detector.threshold = self.config.change_threshold

    def say(self, event: str, index: int, time: float | None) -> None:
        """The alarm rose (one WARN line: when, by how much, what changed) or cleared (one info line: how long it
        was on), or it armed or cannot arm (one line: why)."""
        detector = self.change
        when = f"sample {index}" + (f" (t={time:.3f} s)" if time is not None else "")
        if event == RAISED:
            self.notices.counters["change_alarms"] += 1
            self.change_time, self.change_started = time, index
            self.notices.say("change", self.text(index, time), self.name)
            return
        if event in (ARMED, UNARMED):
            reference = detector.reference.index if detector.reference is not None else None
            text = (
                f"{when}: change alarm{self.where} armed: the reference model (the model served at sample "
                f"{reference}) simulates the output at {detector.nmse_db:.1f} dB"
                if event == ARMED
                else f"{when}: change alarm{self.where} not armed: {detector.why}"
            )
            self.notices.say("change_armed", text, self.name)
            return
        started, self.change_time = self.change_started, None
        how = (
            f"the free run is back within {detector.clear_ratio:g}x its learnt level for {detector.clear_blocks} blocks"
            if event != ACCEPTED
            else f"the plant stayed changed for {detector.accept_blocks} blocks: the model served now is the "
            "reference, its level learnt anew"
        )
        self.notices.say(
            "change_cleared",
            f"{when}: plant change alarm{self.where} (raised at sample {started}, peak {detector.peak:.1f}x) "
            f"cleared: {how}",
            self.name,
        )

    def text(self, index: int, time: float | None) -> str:
        """The alarm in one line: when, where, by how much the reference's free run got worse, what changed."""
        detector = self.change
        when = f"sample {index}" + (f" (t={time:.3f} s)" if time is not None else "")
        return (
            f"plant changed{self.where} at {when}, from about sample {detector.since_sample}: the reference model's "
            f"free run misses by {detector.magnitude:.1f} times its learnt level; what changed: {detector.kind}; "
            f"raised by {detector.basis} (alarm {detector.count})"
        )

    def status(self) -> dict[str, Any]:
        watched = {"watched": True} if self.config.change_alarm else {"watched": False, "why": "change_alarm is false"}
        return {**self.change.status(), **watched, "since_time": self.change_time}


class Monitors:
    """An :class:`OutputMonitor` per output channel of the model."""

    def __init__(self, names: Sequence[str], config: SessionConfig, notices: Notices) -> None:
        self.outputs = [OutputMonitor(name, config, notices, len(names) > 1) for name in names]

    def watch(self, ys: list[float], result: Any, index: int, time: float, us: list[Any]) -> None:
        """One step's results, output by output; the stds and bands go into each output's result (published with
        y^); ``us``: what each output's model reads beside its output."""
        for monitor, y, out, u in zip(self.outputs, ys, result.outputs, us, strict=True):
            monitor.watch(y, out, index, time, u)
        result.gather_stds()

    def offer(self, references: list[tuple[int, dict[int, Reference]]]) -> None:
        """The references the learner took, to each output's alarm (live: before the sample they were taken at)."""
        for _, taken in references:
            for j, reference in taken.items():
                self.outputs[j].change.offer(reference)

    def watch_batch(
        self,
        index: np.ndarray,
        y: np.ndarray,
        y_hat: np.ndarray,
        leverage: np.ndarray,
        changes: Sequence[ParameterChange],
        before: tuple[bool, float],
        us: list[np.ndarray],
        references: list[tuple[int, dict[int, Reference]]],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every output over a batch: the stds and the live half-widths (N, outputs) each prediction was published
        with; ``us``: what each output's model reads, per row; ``references``: those the learner took."""
        columns, predicted = y.reshape(len(y), -1), y_hat.reshape(len(y), -1)
        pairs = [
            monitor.watch_batch(
                index,
                columns[:, j],
                predicted[:, j],
                leverage[:, j],
                changes,
                before,
                us[j],
                [(sample, taken[j]) for sample, taken in references if j in taken],
            )
            for j, monitor in enumerate(self.outputs)
        ]
        if not pairs:
            return np.empty((len(y), 0)), np.empty((len(y), 0))
        return np.stack([std for std, _ in pairs], axis=1), np.stack([band for _, band in pairs], axis=1)

    @property
    def alarm(self) -> OutputMonitor | None:
        """The first output whose alarm is on (None: none is)."""
        return next((monitor for monitor in self.outputs if monitor.change.alarm), None)

    def status(self) -> dict[str, Any]:
        """``status['change']``: the first output's (an alarm on any output wins), and every output's."""
        shown = self.alarm or self.outputs[0]
        return {**shown.status(), "channel": shown.name, "channels": {m.name: m.status() for m in self.outputs}}
