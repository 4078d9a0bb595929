"""Change alarm: has the plant changed under the model? A test of a frozen *reference* model's free runs.

Why not the one-step errors (the alarm before this one: a CUSUM on e^2 against its learnt level): at the
rates a robot samples at, a one-step prediction is mostly y(k), so a plant that changed moves the one-step
error by little (a servo axis under its PD loop at 100 Hz, fitted the day before: -20 % gain 1.4x, +30 %
payload 0.85-1.2x in mean square), while a robot that only *moves differently* (another region, another
speed, motion after rest) moves it by 10-10^4x where the model extrapolates. That alarm missed 11 of 12
changes and fired on a healthy day. So the test is on what a change does change, the free run, and only
where the model knows the motion:

- **the reference**: a frozen copy of the model the session serves (:meth:`ChangeDetector.offer`: the
  weights a file gave, the free-run guard's kept state, or the learning model), taken every
  ``REFERENCE_SAMPLES`` samples and adopted while nothing is building up, never while an alarm is on (a
  change must not teach the test that it is normal);
- **the statistic**: every ``block / grids`` samples (50 by default) the reference simulates the last
  ``block`` samples (100) from the measured outputs before them, as fit's blocks are judged; m = its mean
  squared error. The blocks fall on ``grids`` grids offset by a stride (two: by half a block), each tested
  by its own CUSUM: a change that falls late in one grid's block is found by the other's block a stride
  sooner (the servo below: changes within 2 s 6 -> 8 of 12 and every payload change found, against one
  grid; no false alarm more). Counts of blocks (warm-up, hold, clear, accept) are blocks of time, each
  ``grids`` evaluations. The same servo's
  changes multiply m by 5-10 (payload), 30-100 (gain) and 70-400 (friction), an unchanged plant's single
  blocks by at most about 10-50 (a bad block, not a run of them);
- **the test**: a one-sided CUSUM over blocks of z = min(log(m / L) / s, ``clip``) - ``drift``, raised when
  it passes ``threshold``; L and s^2 are the learnt mean and variance of log m (their mean over the first
  ``warm_up_blocks`` after each start, then running over ``level_blocks``). Logs, because block errors
  spread over decades; standardised by s, because how far an unchanged plant's blocks scatter is the
  reference's own (a servo's about 0.7 in log, a pendulum's with stiction more: one threshold on the raw
  ratio fired on the pendulum or missed on the servo); the clip, so one bad block cannot raise it alone
  unless it is ``drift`` + ``threshold`` spreads out;
- **only where the reference knows the motion** (the excitation is not the plant): a block is *novel* and
  not tested when the reference's free run clipped an input (beyond the scales it was built on) or its
  regressors' mean leverage f' P f under the reference's own RLS covariance P exceeds ``novelty_margin``
  times the 99th percentile of the tested blocks' (a speed, amplitude or region the reference was not
  built on: measured 30-50x above it, while a changed plant's stay within 1.2-1.6x). After a novel block
  the test waits ``hold_blocks`` and then learns its level anew (the motion may now be another one). A
  change in that time would be learnt as the new level: so the level learnt anew is judged against the one
  before, and a rise of more than ``threshold`` of the old spreads raises the alarm (from the first novel
  block on). Measured (bench/change_alarm.py's logs): relearnt levels of unchanged plants, driven faster,
  elsewhere, with other amplitudes or rests, -0.8 to +1.5 spreads from the old; a pendulum joint changed
  during the hold +6.1 to +8.9 (missed before). At rest (:class:`RestGate`) nothing is tested;
- **material**: errors below -60 dB of the block's output variance count as -60 dB (a simulated plant's fit
  at -100 dB saw a 570x rise within rounding on an unchanged plant);
- **armed only by a reference that simulates**: a reference whose block free runs miss the output by more
  than ``ARM_DB`` (NMSE over its learnt level, against the blocks' own output variance) cannot tell a change
  from its own error: the test then waits, and says so (``armed`` False, ``why``);
- **what it says**: when (the first block of the rise), how large (m over its level), and what changed
  where it can tell: an offset of the output (the free-run error is a constant), a gain of the output (it
  is proportional to the output), else the dynamics (friction, inertia, an actuator's gain).

Measured (``bench/change_alarm.py``, bench/RESULTS.md): detection delay per change kind and plant, false
alarms in 10^6 unchanged samples and under excitation changes, and the threshold sweep.

Nothing here knows ROS: the session's monitors own one detector per output, fed every scored sample live
and offline alike, and the reference snapshots the learner takes at the same samples on both paths.
"""

from __future__ import annotations

import bisect
import collections
import copy
import math
from typing import Any

import numpy as np

from lenn_ros.core.free_run import OutputRun, free_run_outputs

#: CUSUM threshold on the clipped log ratios (minus the drift) of the block free runs; the sweep in
#: bench/RESULTS.md ("change_alarm.py") gives the detection rate and the false alarms on either side of it
DEFAULT_THRESHOLD = 3.0
#: free-run errors below this share of the block's output variance (-60 dB) count as this share: a near-perfect
#: reference (a simulated plant's fit: -100 dB) would otherwise call a rise within rounding a change
MATERIAL = math.log(1e-6)
#: the spread of log m is taken as at least this (a reference whose blocks all miss alike is not more sure)
MIN_SPREAD = 0.3
#: a reference snapshot is offered every this many samples (both paths take it before the same sample)
REFERENCE_SAMPLES = 3000
#: the test is armed while the reference's learnt block free-run error is below this NMSE (dB) of the blocks' output
ARM_DB = -20.0
#: ... and disarmed above it plus this margin (dB), so that a reference at the edge does not flicker
ARM_HYSTERESIS_DB = 3.0
RAISED, CLEARED, ACCEPTED, ARMED, UNARMED = "raised", "cleared", "accepted", "armed", "unarmed"


class Reference:
    """A frozen copy of one output's model: its structure and weights (and RLS covariance, for the leverage)."""

    def __init__(self, structure: Any, model: Any, index: int) -> None:
        self.structure = structure
        self.model = copy.deepcopy(model)
        self.index = index
        covariance = getattr(self.model, "covariance_", None)
        self.covariance = covariance if covariance is not None and np.size(covariance) else None

    def simulate(self, u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Its free run over y[warm_up:] seeded by the measured outputs before: (errors, simulated, clipped)."""
        start = self.structure.warm_up
        values = np.column_stack([y, u])
        run = OutputRun(self.structure, self.model, 0, tuple(range(1, values.shape[1])))
        clipped, diverged_at = free_run_outputs([run], values, start)
        simulated = values[start:, 0]
        if diverged_at is not None:
            return np.full(len(simulated), np.inf), simulated, max(1, clipped[0])
        return y[start:] - simulated, simulated, clipped[0]

    def leverage(self, u: np.ndarray, y: np.ndarray, rows: int) -> float:
        """Mean f' P f of the regressors predicting the last ``rows`` samples (0 without a covariance)."""
        if self.covariance is None or not hasattr(self.model, "features"):
            return 0.0
        x, _ = self.structure.regressors(u, y)
        features = self.model.features(np.clip(x[-rows - 1 : -1], -1.0, 1.0))
        return float(np.mean(np.einsum("ij,jk,ik->i", features, self.covariance, features)))


class ChangeDetector:
    """The reference model's block free-run test; see the module docstring.

    Plain attributes a status or a test reads: ``alarm``, ``count`` (alarms raised), ``since_sample`` (the
    first sample of the rise, None when off), ``raised_at``, ``magnitude`` (m over its level when it rose),
    ``peak`` (the largest while on), ``kind`` (what changed, where it can tell), ``statistic`` (S),
    ``armed`` and ``why``.
    """

    def __init__(
        self,
        threshold: float = DEFAULT_THRESHOLD,
        drift: float = 3.0,
        clip: float = 8.0,
        block: int = 100,
        warm_up_blocks: int = 20,
        level_blocks: int = 100,
        novelty_margin: float = 2.0,
        novelty_window: int = 400,
        hold_blocks: int = 40,
        clear_ratio: float = 2.0,
        clear_blocks: int = 20,
        accept_blocks: int = 600,
        grids: int = 2,
    ) -> None:
        if not threshold > 0 or not drift > 0 or not clip > drift or block < 2:
            raise ValueError("the change detector needs threshold > 0, clip > drift > 0 and block >= 2")
        if grids < 1 or block % grids:
            raise ValueError(f"the change detector needs grids >= 1 dividing the block ({block}), not {grids}")
        self.threshold, self.drift, self.clip, self.block = float(threshold), float(drift), float(clip), int(block)
        self.grids, self.stride = int(grids), int(block) // int(grids)
        # counts of blocks are kept in evaluations (a block every ``stride`` samples), rates per evaluation
        self.warm_up_blocks, self.level_rate = int(warm_up_blocks), 1.0 / (level_blocks * self.grids)
        self.novelty_margin, self.novelty_window = float(novelty_margin), novelty_window * self.grids
        self.hold_blocks = hold_blocks
        self.clear_ratio, self.clear_blocks, self.accept_blocks = float(clear_ratio), clear_blocks, accept_blocks
        self.count = 0
        self.reference: Reference | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the reference, the learnt level and any alarm (a new model); ``count`` stays."""
        self.reference = None
        self._pending: Reference | None = None
        self.gate = RestGate()
        self._u: list[Any] = []
        self._y: list[float] = []
        self._moves: list[bool] = []  # the rest gate's word on each sample of the buffer
        self._turn = 0  # the grid the next block belongs to
        self._last_index: int | None = None
        self.alarm = False
        self.since_sample: int | None = None
        self.raised_at: int | None = None
        self.magnitude = self.peak = self.ratio = 0.0
        self.kind = ""
        self.armed = self._said = False
        self.blocks = 0  # blocks of samples the reference could simulate
        self._why = ""  # why not armed, once its level is learnt
        self.nmse_db: float | None = None
        self.tested = self.novel = 0
        self.basis = ""  # what raised the last alarm: the CUSUM, or the level learnt anew after novel motion
        self.relearnt_rise: float | None = None  # the last level learnt anew over the one before, in its spreads
        self._before: tuple[float, float, int] | None = None  # (level, spread, first novel sample) before a hold
        self._restart_level()
        self._leverages: collections.deque[float] = collections.deque(maxlen=self.novelty_window)
        self._sorted: list[float] = []
        self._variance: float | None = None  # learnt log of the blocks' output variance
        self._on_blocks = self._calm = 0

    def _restart_level(self) -> None:
        self.level: float | None = None  # learnt log mean square of the block free runs
        self.spread = 0.0  # learnt variance of log m about the level
        self._level_blocks = 0
        self._hold = 0
        self._reset_cusums()

    def _reset_cusums(self) -> None:
        self._statistics = [0.0] * self.grids  # one CUSUM per grid of blocks
        self._rises: list[int | None] = [None] * self.grids  # the first sample of each one's rise

    @property
    def _level_learnt(self) -> bool:
        """Whether the level is learnt: ``warm_up_blocks`` blocks of time (``grids`` evaluations each) since a start."""
        return self.level is not None and self._level_blocks >= self.warm_up_blocks * self.grids

    @property
    def statistic(self) -> float:
        """S: the largest of the grids' CUSUMs (the alarm rises when one passes the threshold)."""
        return max(self._statistics)

    # -- the reference -----------------------------------------------------------------------------
    def offer(self, candidate: Reference) -> None:
        """A snapshot of the served model (the learner takes one at the same samples on both paths).

        Adopted at once when there is none or its structure is another (a new model: any alarm about the old
        one ends); else at the next block while nothing builds up and no alarm is on (kept pending till then)."""
        if self.reference is None or self.reference.structure is not candidate.structure:
            if self.alarm:
                self._off()
            self.reference = candidate
            self._pending = None
            self._before = None
            self._restart_level()
            self._sorted.clear()
            self._leverages.clear()
            return
        self._pending = candidate

    # -- the samples -------------------------------------------------------------------------------
    def update(self, u: Any, y: float, index: int) -> str:
        """One scored sample (u as the output's model reads it, y measured): '' or the event a block caused."""
        if self._last_index is not None and index != self._last_index + 1:
            self._drop(len(self._y))  # a gap: a free run never crosses one
        self._last_index = index
        if y != y or y in (math.inf, -math.inf):
            return ""
        self._u.append(u)
        self._y.append(y)
        self._moves.append(self.gate.update(y))
        if self.reference is None:
            if len(self._y) > 4 * self.block:  # (bounded while there is nothing to simulate them with)
                self._drop(self.block)
            return ""
        seed = self.reference.structure.warm_up
        extra = len(self._y) - seed - self.block
        if extra < 0:
            return ""
        if extra:  # samples from before the reference came: the block is the last ones
            self._drop(extra)
        event = self._block(index, seed)
        self._drop(self.stride)  # the next block starts a stride later: blocks of the grids overlap
        return event

    def _drop(self, count: int) -> None:
        del self._u[:count]
        del self._y[:count]
        del self._moves[:count]

    def _block(self, index: int, seed: int) -> str:
        reference = self._adopted()
        self.blocks += 1
        grid, self._turn = self._turn, (self._turn + 1) % self.grids
        if getattr(reference.structure, "y_abs", False):
            return self._cannot_simulate()
        if sum(self._moves[-self.block :]) < self.block // 2:
            return ""  # at rest: nothing to tell
        u = np.asarray(self._u, dtype=np.float64)
        y = np.asarray(self._y, dtype=np.float64)
        errors, simulated, clipped = reference.simulate(u, y)
        square = float(np.mean(errors * errors))
        if self._is_novel(square, clipped, reference.leverage(u, y, self.block)):
            return self._novel()
        if self._hold > 0:
            self._hold -= 1
            return ""
        variance = math.log(max(float(np.var(y[seed:])), 1e-300))
        x = max(math.log(max(square, 1e-300)), variance + MATERIAL)
        if self.alarm:
            return self._while_on(x, index)
        if not self._level_learnt:
            return self._learn_level(x, variance, index, errors, simulated)
        assert self._variance is not None
        self.ratio = math.exp(x - self.level)
        deviation = x - self.level
        if self.armed:
            self.tested += 1
            z = min(deviation / max(math.sqrt(self.spread), MIN_SPREAD), self.clip) - self.drift
            if self._statistics[grid] <= 0.0 and z > 0.0:
                self._rises[grid] = index - self.block + 1
            self._statistics[grid] = max(0.0, self._statistics[grid] + z)
            if self._statistics[grid] > self.threshold:
                self.basis = f"its CUSUM over change_threshold {self.threshold:g}"
                return self._raise(index, errors, simulated, self._rises[grid])
        self.level += self.level_rate * deviation
        self.spread += self.level_rate * (min(deviation * deviation, 9.0 * self.spread) - self.spread)
        self._variance += self.level_rate * (variance - self._variance)
        return self._arming()

    def _adopted(self) -> Reference:
        """The reference this block is tested with: the pending snapshot once nothing builds up and no alarm is on."""
        if self._pending is not None and not self.alarm and self.statistic == 0.0:
            self.reference, self._pending = self._pending, None
        assert self.reference is not None
        return self.reference

    def _cannot_simulate(self) -> str:
        """A model of an output its sensor reads as |y| (``y_abs``): its free run would start from the measured |y|,
        not from the signed output it models, so no block can be tested; UNARMED once, with why."""
        if self._said:
            return ""
        self._said = True
        self._why = (
            "the model reads its output as an absolute value (y_abs): a free run of the reference would start from "
            "the measured |y|, not from the signed output it models, so the alarm cannot test it"
        )
        return UNARMED

    def _learn_level(self, x: float, variance: float, index: int, errors: np.ndarray, simulated: np.ndarray) -> str:
        """The first blocks after a start: the level is their running mean; armed or not once it is learnt, and
        judged against the level before when novel motion made it learnt anew (:meth:`_relearnt`)."""
        self._level_blocks += 1
        rate = 1.0 / self._level_blocks
        if self.level is not None:  # Welford: the running mean and variance of log m over these blocks
            step = x - self.level
            self.level += rate * step
            self.spread += rate * (step * (x - self.level) - self.spread)
        else:
            self.level, self.spread = x, 0.0
        self._variance = variance if self._variance is None else self._variance + rate * (variance - self._variance)
        if not self._level_learnt:
            return ""
        if self._before is not None:  # judged once, and only by an armed test (else forgotten)
            raised = self.armed and self._relearnt(index, errors, simulated)
            self._before = None
            if raised:
                return RAISED
        return self._arming()

    def _relearnt(self, index: int, errors: np.ndarray, simulated: np.ndarray) -> bool:
        """Whether the level learnt anew after novel motion rose more than ``threshold`` of the old spreads over the
        old level (the plant changed while the test waited): then the alarm rises, from the first novel block, and
        the old level stays the one the blocks are judged by while it is on."""
        assert self._before is not None and self.level is not None
        level, spread, since = self._before
        rise = self.relearnt_rise = (self.level - level) / max(math.sqrt(spread), MIN_SPREAD)
        if not rise > self.threshold:
            return False
        self.ratio = math.exp(self.level - level)
        self.level, self.spread = level, spread
        self.basis = (
            f"its level learnt anew after novel motion, {rise:.1f} spreads over the one before "
            f"(change_threshold {self.threshold:g})"
        )
        self._raise(index, errors, simulated, since)
        return True

    def _is_novel(self, square: float, clipped: int, leverage: float) -> bool:
        """Whether the reference does not know this block's motion: its free run clipped an input or diverged, or
        the regressors' leverage is far above the tested blocks' (remembered when not)."""
        if not math.isfinite(square) or clipped:
            return True
        if len(self._sorted) >= 50:
            limit = self._sorted[min(len(self._sorted) - 1, int(0.99 * len(self._sorted)))]
            if leverage > self.novelty_margin * limit:
                return True
        self._remember(leverage)
        return False

    def _novel(self) -> str:
        """The reference does not know this motion: not tested; the level is learnt anew after the hold (an alarm
        on stays on, its level kept)."""
        self.novel += 1
        if self.alarm:
            return ""
        if self._level_learnt:
            self._before = (self.level, self.spread, self._last_index - self.block + 1)  # (kept till judged)
        self._restart_level()
        self._hold = self.hold_blocks * self.grids
        return ""

    def _remember(self, leverage: float) -> None:
        if len(self._leverages) == self._leverages.maxlen:
            old = self._leverages[0]
            del self._sorted[bisect.bisect_left(self._sorted, old)]
        self._leverages.append(leverage)
        bisect.insort(self._sorted, leverage)

    def _arming(self) -> str:
        """Armed while the reference's learnt level is below ARM_DB of the output's variance (with hysteresis):
        ARMED / UNARMED when that changes (UNARMED also the first time it is found unarmed), else ''."""
        assert self.level is not None and self._variance is not None
        nmse_db = 10.0 / math.log(10.0) * (self.level - self._variance)
        self.nmse_db = nmse_db
        if not self.armed and nmse_db < ARM_DB:
            self.armed, self._why = True, ""
            self._said = True
            return ARMED
        if self.armed and nmse_db < ARM_DB + ARM_HYSTERESIS_DB:
            return ""
        if self.armed or not self._said:
            self.armed, self._said = False, True
            self._why = (
                f"the reference model's free run misses the output by {nmse_db:.1f} dB (NMSE of its "
                f"{self.block}-sample block runs); the alarm arms below {ARM_DB:g} dB"
            )
            return UNARMED
        return ""

    def _raise(self, index: int, errors: np.ndarray, simulated: np.ndarray, rise: int | None) -> str:
        self.alarm = True
        self.count += 1
        self.raised_at = index
        self.since_sample = rise if rise is not None else index - self.block + 1
        self.magnitude = self.peak = self.ratio
        self.kind = change_kind(errors, simulated)
        self._on_blocks = self._calm = 0
        return RAISED

    def _while_on(self, x: float, index: int) -> str:
        """Alarm on: the reference and its level stay; clear once the blocks are back near the level."""
        assert self.level is not None
        self.ratio = math.exp(x - self.level)
        self.peak = max(self.peak, self.ratio)
        self._on_blocks += 1
        self._calm = self._calm + 1 if self.ratio < self.clear_ratio else 0
        if self._calm >= self.clear_blocks * self.grids:
            self._off()
            return CLEARED
        if self._on_blocks >= self.accept_blocks * self.grids:
            self._off()
            if self._pending is not None:  # the model the session serves now is the reference
                self.reference, self._pending = self._pending, None
            self._restart_level()
            return ACCEPTED
        return ""

    def _off(self) -> None:
        self.alarm = False
        self._reset_cusums()
        self.since_sample = None

    @property
    def why(self) -> str:
        """Why the alarm is not armed ('' when it is)."""
        if self.armed:
            return ""
        if self.reference is None:
            return "no reference model yet"
        if not self.blocks:
            return f"no run of {self.reference.structure.warm_up + self.block} consecutive samples yet (a gap ends one)"
        if self._why:
            return self._why
        return (
            f"its level is being learnt from blocks where the plant moves as the reference knows ({self.novel} of "
            f"{self.blocks} blocks so far novel: the reference's free run left its scales, or the motion was unlike "
            "what it was built on)"
        )

    def status(self) -> dict[str, Any]:
        """What ``status['change']`` shows."""
        return {
            "alarm": self.alarm,
            "count": self.count,
            "since_sample": self.since_sample,
            "raised_at": self.raised_at if self.count else None,
            "magnitude": self.magnitude if self.count else None,
            "peak": self.peak if self.count else None,
            "kind": self.kind if self.count else None,
            "ratio": self.ratio,
            "threshold": self.threshold,
            "armed": self.armed,
            "reference_nmse_db": self.nmse_db,
            "why": self.why or None,
            "testing": self.armed and self._level_learnt,
            "reference_sample": self.reference.index if self.reference is not None else None,
            "blocks_tested": self.tested,
            "blocks_novel": self.novel,
            "basis": self.basis if self.count else None,
            "relearnt_rise": self.relearnt_rise,
        }


def change_kind(errors: np.ndarray, simulated: np.ndarray) -> str:
    """What changed, where the free-run error of the raising block tells: an offset of the output (the error is
    about constant), a gain of the output (about proportional to the output), else the dynamics."""
    total = float(np.mean(errors * errors))
    if not total > 0.0 or not math.isfinite(total):
        return "the dynamics"
    mean = float(np.mean(errors))
    if mean * mean > 0.8 * total:
        return f"a nearly constant error ({mean:+.4g}): an offset of the output or input, or friction holding it"
    centred = simulated - np.mean(simulated)
    spread = float(np.mean(centred * centred))
    if spread > 0.0:
        slope = float(np.mean(centred * (errors - mean))) / spread
        residual = errors - mean - slope * centred
        if float(np.mean(residual * residual)) < 0.2 * total and abs(mean) < abs(slope) * math.sqrt(spread):
            return f"an error proportional to the output (x{1.0 + slope:.3g}): a gain of the output or the input"
    return "the dynamics (friction, inertia, an actuator's gain: the free run departs where the plant moves)"


class RestGate:
    """Whether the plant moves: the fast mean square of the output's increments against its level while moving.

    At rest (a constant command, an encoder quantised to its last step) the increments
    fall to nothing; the gate says ``False`` once their fast mean square (memory
    ``fast_samples``) is below ``rest_fraction`` of the level learnt while moving (memory
    ``reference_samples``, the running mean at first), and ``True`` again within a few
    samples of motion. Before anything has moved it says ``True``.
    """

    def __init__(self, fast_samples: int = 50, reference_samples: int = 5000, rest_fraction: float = 1e-2) -> None:
        self.fast_rate = 1.0 / fast_samples
        self.reference_rate = 1.0 / reference_samples
        self.rest_fraction = float(rest_fraction)
        self.fast = 0.0
        self.level = 0.0
        self.moving_samples = 0
        self._last: float | None = None

    def update(self, y: float) -> bool:
        """The output y(k) of the next scored sample: whether the plant moves now."""
        last, self._last = self._last, y
        if last is None:
            return True
        step = y - last
        square = step * step
        if square != square or square == math.inf:
            return True
        fast = self.fast = self.fast + self.fast_rate * (square - self.fast)
        if fast < self.rest_fraction * self.level:
            return False
        count = self.moving_samples = self.moving_samples + 1
        rate = self.reference_rate if count * self.reference_rate >= 1.0 else 1.0 / count
        self.level += rate * (fast - self.level)
        return True
