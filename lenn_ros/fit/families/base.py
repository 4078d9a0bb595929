"""What the families share: the dictionary they build and the builder of its rows.

:class:`Dictionary` (with the increment form's pass-through of y(k)), :class:`Builder`
(rows of exponents and factors, the factors' parameters rounded as ``format_terms`` writes
them) and which network inputs a nonlinear term reads (:func:`recent_inputs`). A module
apart from the registry (:mod:`lenn_ros.fit.families`) so that each family's module
imports these and none of the other families.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from lenn_ros.core.expansions import FACTOR_KINDS, round6

if TYPE_CHECKING:
    from lenn_ros.fit.families import Spec

#: nonlinear terms involve the 3 most recent lags of each signal (the usual home of a static nonlinearity)
RECENT = 3


class OutputScaling(Protocol):
    """What the increment form's pass-through needs of a view's scaling (a :class:`~lenn_ros.fit.termmodel.Layout`)."""

    @property
    def y_offset(self) -> float: ...

    @property
    def y_scale(self) -> float: ...


@dataclass
class Dictionary:
    """Candidate terms: exponent rows, factor rows, and whether the target is the increment."""

    exponents: np.ndarray
    factors: np.ndarray
    increment: bool = False

    def pass_through(self, x: np.ndarray, scaling: OutputScaling) -> np.ndarray:
        """The part of the target the terms need not explain: y(k) in the increment form, else 0."""
        if not self.increment:
            return np.zeros(len(x))
        return x[:, 0] * scaling.y_scale + scaling.y_offset

    def with_pass_through(
        self, chosen: list[int], weights: np.ndarray, scaling: OutputScaling
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(exponents, factors, weights) of the chosen terms; in the increment form plus y(k) itself.

        y(k) = y_scale * x_1 + y_offset, i.e. weight y_scale on the term ``y1`` and
        y_offset on the bias, added to those terms' weights (appended if not chosen).
        """
        exponents = self.exponents[chosen]
        factors = self.factors[chosen]
        weights = np.array(weights, dtype=np.float64)
        if not self.increment:
            return exponents, factors, weights
        n = exponents.shape[1]
        for row in _pass_through_rows(n):
            if not len(_matching(exponents, factors, row)):
                exponents = np.vstack([exponents, row])
                factors = np.vstack([factors, np.zeros(n + 2)])
                weights = np.append(weights, 0.0)
        return exponents, factors, weights + pass_through_weights(exponents, factors, scaling)


def _pass_through_rows(n: int) -> list[np.ndarray]:
    """Exponent rows of the bias and of ``y1`` (P1 of the scaled y(k): x_1 itself)."""
    bias, first = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    first[0] = 1
    return [bias, first]


def _matching(exponents: np.ndarray, factors: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Indices of the terms that are exactly ``row`` with no factor."""
    plain = factors[:, 0] == 0 if len(factors) else np.ones(len(exponents), dtype=bool)
    return np.flatnonzero((exponents == row).all(axis=1) & plain)


def pass_through_weights(
    exponents: np.ndarray, factors: np.ndarray, scaling: OutputScaling, with_offset: bool = True
) -> np.ndarray:
    """Weights that make the terms compute y(k) = y_scale x_1 + y_offset (the bias part only ``with_offset``).

    The increment form's given part, in the basis the node runs: the terms must hold
    ``y1`` (and the bias, for the offset) without factors.
    """
    weights = np.zeros(len(exponents))
    bias, first = _pass_through_rows(exponents.shape[1])
    for row, value in ((first, scaling.y_scale), (bias, scaling.y_offset if with_offset else 0.0)):
        match = _matching(exponents, factors, row)
        if not len(match):
            raise ValueError("the increment form needs the terms y1 and 1")
        weights[match[0]] += value
    return weights


class Builder:
    """Rows of a dictionary under construction, over ``n`` network inputs."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.exponents: list[list[int]] = []
        self.factors: list[np.ndarray] = []

    def add(self, exponents: list[int] | np.ndarray | None = None, kind: str = "", w=None, b: float = 0.0) -> None:
        row = np.zeros(self.n, dtype=np.int64) if exponents is None else np.asarray(exponents, dtype=np.int64)
        factor = np.zeros(self.n + 2)
        if kind:
            factor[0] = FACTOR_KINDS[kind]
            factor[1] = round6(b)
            used = np.flatnonzero(w)  # a long view's weight rows are mostly zeros
            factor[2 + used] = [round6(float(w[i])) for i in used]
        self.exponents.append(row.tolist())
        self.factors.append(factor)

    def power(self, i: int, degree: int) -> list[int]:
        row = [0] * self.n
        row[i] = degree
        return row

    def unit(self, i: int) -> np.ndarray:
        return np.eye(self.n)[i]

    def build(self, increment: bool = False) -> Dictionary:
        exponents = np.array(self.exponents, dtype=np.int64).reshape(len(self.exponents), self.n)
        return Dictionary(exponents, np.array(self.factors).reshape(len(self.factors), self.n + 2), increment)


def view_columns(spec: Spec, x: np.ndarray) -> int:
    """Columns of the view the dictionary is built over: the output and what it reads."""
    return x.shape[1] // spec.lags


def recent_inputs(spec: Spec, columns: int) -> list[int]:
    """Network inputs the nonlinear terms involve: the RECENT most recent lags of the output, then of each
    column it reads (fewer of each when it reads several: RECENT shared among them, at least one)."""
    own = min(spec.lags, RECENT)
    each = own if columns <= 2 else min(spec.lags, max(1, RECENT // (columns - 1)))
    return list(range(own)) + [c * spec.lags + i for c in range(1, columns) for i in range(each)]
