"""The ``legendre`` family: the paper's LeNN expansion, P_1..P_15 of every lag alone (no products).

A static nonlinearity with several turns (the paper's example 1, sin(5 pi u)), which no
product of low degrees follows.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lenn_ros.fit.families.base import Builder, Dictionary

if TYPE_CHECKING:
    from lenn_ros.fit.families import Spec

#: the paper's expansion: Legendre polynomials of each lag alone, up to a high degree (no products)
LEGENDRE_LAGS = (1, 2, 4)
LEGENDRE_DEGREES = (15,)


def dictionary(spec: Spec, x: np.ndarray) -> Dictionary:
    """The bias and P_1..P_degree of every lag of every column, each alone: the paper's LeNN expansion. A
    static nonlinearity with several turns (sin(5 pi u)) needs a degree no product of low degrees reaches."""
    built = Builder(x.shape[1])
    built.add()
    for degree in range(1, spec.degree + 1):
        for i in range(x.shape[1]):
            built.add(built.power(i, degree))
    return built.build()
