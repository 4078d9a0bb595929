"""The ``fir`` family: the output from the inputs alone, no output fed back.

The newest input lags and the inputs averaged over spans 16, 32, 64 up to the lags;
degree 2 adds tanh, v|v| and dead-zones (relu beyond one spread) of the averages over
FIR_SPANS. Where one-step least squares sets the feedback of a model's own past wrong (a
robot arm's angles, whose velocity follows the torque: the fitted poles sit on or outside
the unit circle and every free run drifts), a model that cannot run away simulates best;
the blocks decide. Its least squares already minimise its free-run error (its free run is
its one-step prediction), so it is never refined.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lenn_ros.fit.families.base import Builder, Dictionary, view_columns

if TYPE_CHECKING:
    from lenn_ros.fit.families import Spec

#: input-only models: lags tried (the longer with averages of the inputs over spans up to it)
FIR_LAGS = (10, 65)
#: newest input lags an input-only model reads one by one; spans of the averages its nonlinear terms take
FIR_RECENT = 10
FIR_SPANS = (8, 32, 64)


def dictionary(spec: Spec, x: np.ndarray) -> Dictionary:
    """The output from the columns read alone (none of its own lags): their FIR_RECENT newest lags, their
    averages over longer spans, and (degree 2) tanh, v|v| and dead-zones of their averages over FIR_SPANS."""
    lags = spec.lags
    built = Builder(x.shape[1])
    built.add()  # the bias
    read = [c * lags for c in range(1, view_columns(spec, x))]
    for start in read:
        for j in range(min(lags, FIR_RECENT)):
            built.add(built.power(start + j, 1))
        for s in (16, 32, 64, 128):
            if FIR_RECENT < s <= lags:
                w = np.zeros(x.shape[1])
                w[start : start + s] = 1.0 / s
                built.add(None, "lin", w)
    if spec.degree >= 2:
        for start in read:
            for s in FIR_SPANS:
                if s <= lags:
                    _average_terms(built, x, start, s)
    return built.build()


def _average_terms(built: Builder, x: np.ndarray, start: int, span: int) -> None:
    """tanh(z), z|z| and the dead-zones relu(z - 1), relu(-z - 1) of z, the average of one column over its
    ``span`` newest lags scaled to unit spread."""
    w = np.zeros(x.shape[1])
    w[start : start + span] = 1.0 / span
    # over the span's own columns: the whole row of a 65-lag view is 455 inputs, a pass over all of them each time
    spread = float(np.std(x[:, start : start + span] @ w[start : start + span])) or 1.0
    w /= spread
    built.add(None, "tanh", w)
    built.add(None, "sqabs", w)
    built.add(None, "relu", w, -1.0)
    built.add(None, "relu", -w, -1.0)
