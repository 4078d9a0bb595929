"""The one place where a model of one channel and one of several differ: how a sample's values look.

One output and one input carry plain floats (no numpy call per sample: the per-sample cost at
kilohertz rates, issue 19); several channels carry a vector per side. Everything else in the
session, the node and the offline path works per output over :meth:`Values.split` and never asks
how many channels there are.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from lenn_ros.core.pairing import screen, screen_values


class Values:
    """One channel per side: floats."""

    vector = False

    @staticmethod
    def screen(value: Any, limit: float, policy: str) -> tuple[Any, str]:
        """(value to use, verdict) of one half: see :func:`lenn_ros.core.pairing.screen`."""
        return screen(float(value), limit, policy)

    @staticmethod
    def refused(u: Any, y: Any) -> bool:
        """Whether a pair is not a sample (a half screened to NaN)."""
        return math.isnan(u) or math.isnan(y)

    @staticmethod
    def split(value: Any) -> list[Any]:
        """Per output channel."""
        return [value]

    @staticmethod
    def inputs(identifier: Any, u: Any, y: Any) -> list[Any]:
        """Per output channel, what its model reads beside its own output (one sample or rows of samples)."""
        return [u]

    @staticmethod
    def shown(raw: Any, screened: Any) -> Any:
        """What a screening notice shows of a half: one channel's screened value."""
        return screened

    @staticmethod
    def zeros(identifier: Any) -> tuple[Any, Any]:
        """A sample of zeros the model can step (to compile it ahead); a model whose scales the warm-up is
        to learn gets any (1) on the way: the scratch copy it is given is thrown away."""
        if not identifier.structure.scaled:
            identifier.set_structure(dataclasses.replace(identifier.structure, y_scale=1.0, u_scale=1.0))
        return 0.0, 0.0


class VectorValues(Values):
    """Several channels: a vector per side, screened as one (a sample is learnt from every channel or none)."""

    vector = True

    @staticmethod
    def screen(value: Any, limit: float, policy: str) -> tuple[Any, str]:
        return screen_values(value, limit, policy)

    @staticmethod
    def refused(u: Any, y: Any) -> bool:
        return bool(np.isnan(u).any() or np.isnan(y).any())

    @staticmethod
    def split(value: Any) -> list[Any]:
        return [float(v) for v in np.ravel(value)]

    @staticmethod
    def inputs(identifier: Any, u: Any, y: Any) -> list[Any]:
        u, y = np.asarray(u, dtype=np.float64), np.asarray(y, dtype=np.float64)
        return [identifier.structure.other_values(j, u, y) for j in range(len(identifier.outputs))]

    @staticmethod
    def shown(raw: Any, screened: Any) -> Any:
        """Several channels' values as they came (the screened vector is all NaN)."""
        return np.asarray(raw).tolist()

    @staticmethod
    def zeros(identifier: Any) -> tuple[Any, Any]:
        return np.zeros(identifier.structure.n_u), np.zeros(identifier.structure.n_y)


def values_for(identifier: Any) -> type[Values]:
    """The values a model's samples carry: vectors where the model says so (several channels)."""
    return VectorValues if identifier.vector else Values
