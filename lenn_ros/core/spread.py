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
"""

from __future__ import annotations

import math

#: Samples the innovation variance averages over (an EWMA; the running mean before that many).
SPREAD_MEMORY = 500
#: The nominal two-sided 95 % band is y^ +- this many std.
Z95 = 1.959963984540054


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
