"""The ``rff`` family: the linear terms plus random Fourier features cos(w . x + b) of the recent lags.

w is drawn with the spread of the training regressors (the median-distance rule): a
smooth nonlinearity of several lags at once, the feature map of a GP-NARX's
squared-exponential kernel, of which FROLS keeps the few that matter.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lenn_ros.core.expansions import dictionary_exponents
from lenn_ros.fit.families.base import Builder, Dictionary, recent_inputs, view_columns

if TYPE_CHECKING:
    from lenn_ros.fit.families import Spec

#: lags (equal for y and u) tried
RFF_LAGS = (2, 4)
#: random Fourier features offered, and the seed they are drawn with (fixed: a fit is repeatable)
RFF_FEATURES = 60
RFF_SEED = 0


def dictionary(spec: Spec, x: np.ndarray) -> Dictionary:
    """Linear terms and RFF_FEATURES cos(w . x_recent + b), w ~ N(0, 1 / l^2), l the regressors' median distance."""
    n = x.shape[1]
    built = Builder(n)
    for row in dictionary_exponents(n, 1):
        built.add(row)
    recent = recent_inputs(spec, view_columns(spec, x))
    rng = np.random.default_rng(RFF_SEED)
    sample = x[rng.choice(len(x), min(len(x), 400), replace=False)][:, recent]
    distances = np.sqrt(((sample[:, None, :] - sample[None, :, :]) ** 2).sum(axis=-1))
    length = float(np.median(distances[distances > 0])) if np.any(distances > 0) else 1.0
    for _ in range(RFF_FEATURES):
        w = np.zeros(n)
        w[recent] = rng.normal(0.0, 1.0 / length, len(recent))
        built.add(None, "cos", w, float(rng.uniform(0.0, 2.0 * np.pi)))
    return built.build()
