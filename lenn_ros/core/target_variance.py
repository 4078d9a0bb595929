"""The variance of an identifier's network target, learnt while the target moved.

The divergence guard (:class:`~lenn_ros.core.structure.Identifier`) measures a block's
mean squared error against the variance of the network's target (y_p minus the known
linear part), i.e. against what predicting its mean would cost. A plant at rest has a
block variance of nothing (a constant command, a quantised encoder), and a guard measured
against that rolled back every healthy model that stood still. So the reference is the
larger of the block's own variance and the one learnt here; kept apart from the guard
because it is a statistic of the target with rules of its own (what counts as standing
still, how long it remembers), not a decision about the model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar


@dataclass
class TargetVariance:
    """The mean target variance over the passed blocks in which the target moved.

    A block moved when its variance is at least ``REST_FRACTION`` of the learnt one; the
    last ``SCALE_MEMORY`` such blocks weigh most, so standing still neither lowers nor
    raises it. Until the target has moved, the declared range ``y_scale`` squared stands in.
    """

    value: float = 0.0  # learnt while the target moved (0: not yet)
    moving_blocks: int = 0

    #: A block whose target variance is below this fraction of the learnt one stands still.
    REST_FRACTION: ClassVar[float] = 1e-2
    #: Moving blocks the learnt target variance averages over (an exponential memory after them).
    SCALE_MEMORY: ClassVar[int] = 16

    def reference(self, variance: float, y_scale: float) -> float:
        """What a block whose target has this ``variance`` is measured against."""
        return max(variance, self.value or y_scale**2)

    def learn(self, variance: float, y_scale: float) -> None:
        """A passed block's target variance into the learnt one, unless the target stood still in it.

        Before anything is learnt, "still" is measured against 1e-4 of the declared range
        squared (an RMS of a tenth of a percent of ``y_scale``: well above a quantised
        encoder's flicker at rest, well below any motion).
        """
        known = self.value or 1e-4 * y_scale**2
        if not variance >= self.REST_FRACTION * known:
            return
        self.moving_blocks += 1
        self.value += (variance - self.value) / min(self.moving_blocks, self.SCALE_MEMORY)
