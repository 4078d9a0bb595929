"""Change alarm: has the plant changed under the model? A CUSUM on the one-step residuals.

Why this test, and not a textbook one on e_k / sigma_k: the residuals of an online
learner are neither white nor Gaussian (measured kurtosis 3-12 on the paper's examples)
and the model keeps adapting, so a change shows as a *rise of the residual level* that
lasts until the learning rule has re-learnt the plant, and then fades. The detector
therefore compares a fast statistic against a slow reference:

- the reference ``level`` is a slow EWMA of e^2 (memory ``reference_samples``), the
  residual scale the model has learnt to reach; it is frozen while the alarm is on, so
  the re-learning does not teach the detector that the change is normal;
- the statistic is a one-sided CUSUM of z_k = min(e_k^2 / level, ``clip``):
  S_k = max(0, S_{k-1} + z_k - ``drift``), raised when S_k > ``threshold``. z has mean
  1 on an unchanged plant; ``drift`` above 1 makes S fall back to 0 between the odd large
  residual, and ``clip`` bounds what one outlier can add (a heavy tail cannot raise it
  alone). A change that multiplies the mean square by r adds about (r - drift) per sample:
  a 6x rise crosses the default threshold in 50-100 samples (0.5-1 s at 100 Hz), long
  before RLS re-learns (its memory is thousands of samples);
- it clears once the model has re-learnt: the fast level (EWMA of e^2, memory
  ``fast_samples``) has stayed below ``clear_ratio`` x the reference for ``hold_samples``
  in a row. A change the model cannot learn back to the old level (a plant that became
  noisier) is accepted after ``accept_samples`` with the alarm on: the reference becomes
  the level now, said as such (``accepted``), so an alarm never stays on for good.

Nothing is tested for the first ``warm_up_samples`` (the reference is being learnt;
it starts as the running mean of e^2).

Standing still is normal (a robot at rest for minutes): with a constant command the
errors shrink to the quantisation level, and a reference learnt from them would take the
first seconds of motion afterwards for a change (the robot day raised two such alarms). So
``update`` is given the measured output too, and a :class:`RestGate` holds the detector
(reference, statistic, alarm) while the output does not move, as the identifier's
divergence guard learns its target variance only while the target moves.

Design false-alarm rate (:data:`DESIGN_RUN_LENGTH`): at the default threshold the mean
run length to a false alarm is at least 10^7 samples on i.i.d. Gaussian residuals
(measured by ``bench/change_alarm.py``: the run length grows exponentially with the
threshold, about x2.8 per +3, and the table in bench/RESULTS.md extrapolates it to 10^7 at
37), and no alarm is raised in 10^6 samples of an unchanged, online-identified plant per
seed (same bench): bursts of large residuals, not white noise, set the threshold.

Nothing here knows ROS: :class:`~lenn_ros.session.Session` owns a detector and
feeds it every scored a-priori error, live and offline alike.
"""

from __future__ import annotations

import math
from typing import Any

#: Mean run length to a false alarm (samples) the default threshold is designed for.
DESIGN_RUN_LENGTH = 1.0e7
#: CUSUM threshold: on i.i.d. Gaussian residuals 37 already gives DESIGN_RUN_LENGTH (bench/change_alarm.py), but the
#: residuals of an online learner come in bursts (the largest S in 10^6 unchanged samples of Ex. 3: 89), so the
#: default is set above the largest S measured on unchanged, online-identified plants, not on white noise.
DEFAULT_THRESHOLD = 120.0
RAISED, CLEARED, ACCEPTED = "raised", "cleared", "accepted"


class ChangeDetector:
    """CUSUM on e^2 against a slow learnt level; see the module docstring.

    Plain attributes a status or a test reads: ``alarm``, ``count`` (alarms raised),
    ``since_sample`` (the sample the alarm rose at, None when off), ``magnitude`` (RMS
    residual level over the learnt one when it rose), ``peak`` (its largest while on),
    ``level`` (the learnt mean square), ``fast`` (the fast one), ``statistic`` (S).
    """

    def __init__(
        self,
        threshold: float = DEFAULT_THRESHOLD,
        drift: float = 2.0,
        clip: float = 25.0,
        reference_samples: int = 5000,
        fast_samples: int = 50,
        warm_up_samples: int = 2000,
        clear_ratio: float = 2.0,
        hold_samples: int = 500,
        accept_samples: int = 60_000,
    ) -> None:
        if not threshold > 0 or not drift > 1.0 or not clip > drift:
            raise ValueError("the change detector needs threshold > 0, drift > 1 and clip > drift")
        self.threshold = float(threshold)
        self.drift = float(drift)
        self.clip = float(clip)
        self.reference_rate = 1.0 / reference_samples
        self.fast_rate = 1.0 / fast_samples
        self.warm_up_samples = int(warm_up_samples)
        self.clear_ratio = float(clear_ratio)
        self.hold_samples = int(hold_samples)
        self.accept_samples = int(accept_samples)
        self.reset()
        self.count = 0

    def reset(self) -> None:
        """Forget the learnt level and any alarm (a new model); ``count`` stays."""
        self.gate = RestGate()
        self.level = 0.0
        self.fast = 0.0
        self.samples = 0
        self.statistic = 0.0
        self.alarm = False
        self.since_sample: int | None = None
        self.magnitude = 0.0
        self.peak = 0.0
        self._quiet = 0

    def update(self, error: float, index: int, y: float | None = None) -> str:
        """One a-priori error e(k) of sample ``index`` (``y``: its measured output, for the rest gate):
        '' or the event it caused (RAISED, CLEARED, ACCEPTED)."""
        square = error * error
        if square == math.inf or square != square:  # (not math.isfinite: this runs for every sample)
            return ""
        if y is not None and not self.gate.update(y):
            return ""  # at rest: nothing learnt, nothing tested, the alarm (if on) as it was
        samples = self.samples = self.samples + 1
        fast = self.fast = self.fast + self.fast_rate * (square - self.fast) if samples > 1 else square
        if self.alarm:
            return self._while_on(fast, index)
        level = self.level
        rate = self.reference_rate
        if samples * rate < 1.0:
            rate = 1.0 / samples
        self.level = level + rate * (square - level)
        if samples <= self.warm_up_samples or level <= 0.0:
            return ""
        z = square / level
        statistic = self.statistic + (z if z < self.clip else self.clip) - self.drift
        if statistic <= self.threshold:
            self.statistic = statistic if statistic > 0.0 else 0.0
            return ""
        self.statistic = statistic
        self.level = level  # (this sample is the change's: not in the reference)
        self.alarm = True
        self.count += 1
        self.since_sample = index
        self.magnitude = self.peak = math.sqrt(max(fast, square) / level)
        self._quiet = 0
        return RAISED

    def _while_on(self, fast: float, index: int) -> str:
        """Alarm on: the reference stays frozen; clear once the fast level is back near it for the hold."""
        ratio = math.sqrt(fast / self.level)
        if ratio > self.peak:
            self.peak = ratio
        self._quiet = self._quiet + 1 if fast < self.clear_ratio * self.level else 0
        if self._quiet >= self.hold_samples:
            self._off()
            return CLEARED
        if self.since_sample is not None and index - self.since_sample >= self.accept_samples:
            self.level = fast  # the model cannot get back to the old level: the new one is the reference
            self._off()
            return ACCEPTED
        return ""

    def _off(self) -> None:
        self.alarm = False
        self.statistic = 0.0
        self.since_sample = None
        self._quiet = 0

    @property
    def ratio(self) -> float:
        """RMS residual level now (fast) over the learnt one (0 until it is learnt)."""
        return math.sqrt(self.fast / self.level) if self.level > 0.0 else 0.0

    def status(self) -> dict[str, Any]:
        """What ``status['change']`` shows."""
        return {
            "alarm": self.alarm,
            "count": self.count,
            "since_sample": self.since_sample,
            "magnitude": self.magnitude if self.count else None,
            "peak": self.peak if self.count else None,
            "ratio": self.ratio,
            "threshold": self.threshold,
            "testing": self.samples > self.warm_up_samples,
        }


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
