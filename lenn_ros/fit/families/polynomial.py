"""The ``polynomial`` family: Legendre polynomials of the lags and their products up to a degree.

Degree 1 is a linear ARX; degrees 2 and 3 follow smooth nonlinearities such as a hardening
spring. The products involve the few newest lags of each column
(:func:`~lenn_ros.fit.families.base.recent_inputs`), so a wide view's dictionary stays small.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lenn_ros.core.expansions import dictionary_exponents
from lenn_ros.fit.families.base import Dictionary, recent_inputs, view_columns

if TYPE_CHECKING:
    from lenn_ros.fit.families import Spec

#: lags (equal for y and u) tried
POLYNOMIAL_LAGS = (1, 2, 3, 4, 6, 8, 10)


def dictionary(spec: Spec, x: np.ndarray) -> Dictionary:
    """The Legendre terms of the recent lags and their products up to ``spec.degree``."""
    n = x.shape[1]
    rows = dictionary_exponents(n, spec.degree, recent_inputs(spec, view_columns(spec, x)))
    return Dictionary(rows, np.zeros((len(rows), n + 2)))
