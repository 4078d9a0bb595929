"""The ``hinge`` family: the linear terms plus hinges relu(x - c) of the most recent output and input.

The knots sit at the training quantiles of each column's newest samples: saturation,
overflow, dead zones and absolute values (|x - c| is a combination of a hinge and the
linear terms) are piecewise linear, which no low-degree polynomial follows.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lenn_ros.core.expansions import dictionary_exponents
from lenn_ros.fit.families.base import Builder, Dictionary, recent_inputs, round6, view_columns

if TYPE_CHECKING:
    from lenn_ros.fit.families import Spec

#: lags (equal for y and u) tried
HINGE_LAGS = (1, 2, 4, 8)
#: training quantiles at which the hinges' knots sit
KNOT_QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9)


def dictionary(spec: Spec, x: np.ndarray) -> Dictionary:
    """Linear terms, the recent lags' squares and products (degree 2), and hinges of each column's newest
    sample (and the lag before)."""
    columns, lags = view_columns(spec, x), spec.lags
    built = Builder(x.shape[1])
    for row in dictionary_exponents(x.shape[1], spec.degree, recent_inputs(spec, columns)):
        built.add(row)
    newest = [c * lags for c in range(columns)]
    for i in newest + ([i + 1 for i in newest] if lags > 1 else []):
        for knot in np.unique([round6(q) for q in np.quantile(x[:, i], KNOT_QUANTILES)]):
            built.add(None, "relu", built.unit(i), -knot)
    return built.build()
