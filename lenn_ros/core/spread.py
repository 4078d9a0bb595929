"""One-step spread: how far to trust y^(k+1), as a standard deviation, from what the model has learnt.

var(k+1) = s2 (1 + phi(k)' P phi(k)), the textbook one-step variance of least squares:
``P`` is the RLS covariance the compiled step keeps (it is the inverse of the weighted
information matrix, not scaled by the noise), so phi' P phi (``StepResult.leverage``)
is the share of the error the weights' own uncertainty adds; ``s2`` is the innovation
variance, an EWMA of the normalised a-priori errors e(k)^2 / (1 + phi(k-1)' P phi(k-1)),
so a pattern seen rarely (large leverage) widens the band and a familiar one does not.

SGD, NLMS and the MLP keep no P: their leverage is 0 and the std is the EWMA residual
std alone (README, "Prediction intervals"). The nominal 95 % band is y^ +- 1.96 std;
its coverage on the shared real data sets and the paper's examples is measured by
``bench/one_step_coverage.py`` (bench/RESULTS.md).

Nothing here knows ROS: :class:`~lenn_ros.session.Session` owns one and fills
``StepResult.y_hat_next_std`` / ``y_hat_std`` for the node to publish.

The live band (:class:`LiveBand`, published as ``y_hat_band``: its half-width) is m(k) std(k)
with a multiplier m that keeps the band's running coverage at 95 %: 1.96 std is right only
for Gaussian errors whose variance the EWMA has caught up with, and the residuals here have a
kurtosis of 3 to 12 and a level that drifts. m is an online quantile of the normalised score
|e| / std (the quantile tracker of adaptive conformal inference, Gibbs & Candes 2021; Angelopoulos
et al. 2023), in log space: log m += gamma (miss - 0.05) after each scored error, miss = 1 if
the error left the band it was published with. The misses then average 5 % over any stretch
longer than about 1 / (gamma f) samples (f the density of the score at m: 0.12 for Gaussian
errors), whatever the tails; it is O(1) (one compare, one multiply, about 1 us in Python).

Chosen by measurement (``bench/live_band.py``: the shared sets, the plant study's classes and the
paper's examples, learning on the build part, frozen on the test part) against 1.96 std, the
empirical 95 % quantile of the last 1 000 scores and ACI's alpha_t over that window. On the 17
records whose test part is drawn like the build part: 1.96 std 3 outside 93-97 % (92.8-99.6 %),
its lowest 1 000-sample window 92.3 % on average; the window quantile 3 outside (86.2 %: a window
lags a frozen model's drift), ACI 1; the tracker at gamma 0.003 / 0.01 / 0.03 / 0.05 2 / 1 / 1 / 0
outside, its lowest window 92.4 / 92.8 / 93.7 / 94.0 %. Hence ``BAND_GAIN`` 0.05: the fastest
measured, m's own wobble about 5 % of m on Gaussian errors.
"""

from __future__ import annotations

import math

#: Samples the innovation variance averages over (an EWMA; the running mean before that many).
SPREAD_MEMORY = 500
#: The nominal two-sided 95 % band is y^ +- this many std.
Z95 = 1.959963984540054
#: The live band's miss rate: its target coverage is 1 - this.
BAND_MISS = 0.05
#: The live band's step in log m per scored error (gamma): a larger one follows a drift sooner, a smaller
#: one wobbles less; chosen by measurement (the module docstring).
BAND_GAIN = 0.05
#: The multiplier's range: a run of exact predictions (a quantised sensor at rest) would drive it to 0, from where
#: the first errors would take thousands of samples to widen the band again.
BAND_RANGE = (0.2, 50.0)


class OneStepSpread:
    """The innovation variance ``s2`` and the std of each new prediction; see the module docstring."""

    def __init__(self, memory: int = SPREAD_MEMORY) -> None:
        self.rate = 1.0 / memory
        self.s2 = math.nan  # nan until the first error has been seen
        self.samples = 0
        self._leverage = 0.0  # of the prediction the next error scores

    def update(self, error: float) -> None:
        """e(k), the error of the last prediction :meth:`std` was asked for."""
        square = error * error / (1.0 + self._leverage)
        if not math.isfinite(square):
            return
        self.samples += 1
        if self.samples == 1:
            self.s2 = square
        else:
            self.s2 += max(self.rate, 1.0 / self.samples) * (square - self.s2)

    def std(self, leverage: float) -> float:
        """The std of a new prediction whose pattern has ``leverage`` phi' P phi (nan before any error)."""
        self._leverage = leverage if leverage > 0.0 else 0.0
        return math.sqrt(self.s2 * (1.0 + self._leverage))

    def restart(self) -> None:
        """The pending prediction was dropped (a gap): the next error scores none of ours."""
        self._leverage = 0.0


class LiveBand:
    """The live band's multiplier m: half-width m std, m tracking the 95 % quantile of |e| / std online.

    See the module docstring. m starts at :data:`Z95` (the nominal band until errors say otherwise);
    each scored error whose prediction had a band moves log m up by ``gain (1 - miss_rate)`` if the
    error left the band, down by ``gain miss_rate`` if not, within :data:`BAND_RANGE`.
    """

    def __init__(self, gain: float = BAND_GAIN, miss_rate: float = BAND_MISS) -> None:
        self.multiplier = Z95
        self.up = math.exp(gain * (1.0 - miss_rate))
        self.down = math.exp(-gain * miss_rate)
        self.low, self.high = BAND_RANGE
        self.scored = 0
        self.missed = 0

    def update(self, error: float, half_width: float | None) -> None:
        """e(k) of a prediction published with ``half_width`` (None or nan: it had none, nothing learnt)."""
        if half_width is None or math.isnan(half_width) or math.isnan(error):
            return
        self.scored += 1
        if abs(error) > half_width:
            self.missed += 1
            self.multiplier = min(self.multiplier * self.up, self.high)
        else:
            self.multiplier = max(self.multiplier * self.down, self.low)

    def half_width(self, std: float) -> float:
        """The band's half-width around a prediction of one-step ``std`` (nan while the std is)."""
        return self.multiplier * std
