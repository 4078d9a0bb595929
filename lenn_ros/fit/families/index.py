"""The ``index`` family: the linear terms plus hinges of one index z = h . (the inputs' lags), a filtered input.

The hinges relu(z - c) read z at its three newest lags and sit at knots on its training
quantiles. A static map between two filters (Wiener-Hammerstein: an amplifier stage, a
sensor or an actuator that saturates) acts on the first filter's output, a combination
of many input lags that no term of a few lags holds; h is found from the record
(:func:`index_direction`: Gauss-Newton on the one-step residual, the rest least
squares). The hinges read no output, so the model is as stable in free run as its
linear part.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lenn_ros.core.expansions import dictionary_exponents
from lenn_ros.fit.families.base import RECENT, Builder, Dictionary, round6

if TYPE_CHECKING:
    from lenn_ros.fit.families import Spec

#: the ``index`` family: lags tried, how many newest lags of the index its hinges read, their knots (quantiles
#: of the index over the training rows), and the Gauss-Newton iterations that find its direction
INDEX_LAGS = (17, 33)
INDEX_SHIFTS = 3
INDEX_KNOTS = (0.05, 0.2, 0.35, 0.5, 0.65, 0.8, 0.95)
INDEX_ITERATIONS = 60
#: rows of the view the direction is searched on (evenly spread; a direction needs far fewer than 40 000), and
#: the relative fall in the residual below which the search stops
INDEX_ROWS = 2000
INDEX_TOLERANCE = 1e-5


def dictionary(spec: Spec, x: np.ndarray) -> Dictionary:
    """Linear terms of every lag and hinges relu(z_j - c) of one index z, a filtered input (:func:`index_direction`),
    at its INDEX_SHIFTS newest lags j and INDEX_KNOTS quantiles c."""
    n = x.shape[1]
    built = Builder(n)
    for row in dictionary_exponents(n, 1):
        built.add(row)
    found = index_direction(x, spec.lags)
    if found is None:
        return built.build()
    columns, h, middle, spread, knots = found
    for j in range(INDEX_SHIFTS):
        w = np.zeros(n)
        w[columns + j] = h / spread
        for knot in knots:
            built.add(None, "relu", w, -(middle / spread + knot))
    return built.build()


def time_scale(spec: Spec) -> str:
    """What the report says of the lags: the output's enter linearly, the index reads the inputs' older ones."""
    return (
        f"lags {spec.lags} samples at the recorded rate; hinges of one filtered input over "
        f"{spec.lags - INDEX_SHIFTS} input lags (a static map between filters), the output's lags linear"
    )


def index_direction(x: np.ndarray, lags: int) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray] | None:
    """The filtered input a static map acts on: z(k) = h . (the inputs' lags), h found from the record.

    A static map between two filters (Wiener-Hammerstein: an amplifier stage, a sensor with a
    saturation) acts on the first filter's output, a combination of many input lags that no
    term of a few lags holds. Within each row of the view, the newest output lag is regressed
    on the older ones (the model's own problem one sample earlier): on the output's RECENT + 1
    lags before it, the inputs' as many, and hinges of z at its INDEX_SHIFTS lags. The hinges'
    knots sit at quantiles of z, so for a given h the rest is least squares, and h follows by
    Gauss-Newton on that residual (variable projection), from the least-squares FIR of the
    inputs' window. Returns (the window's columns at shift 0, h, z's middle and spread over the
    rows, the knots in units of the spread), or None where the view is too short or flat.
    """
    n = x.shape[1]
    columns_read, taps = n // lags, lags - INDEX_SHIFTS
    if columns_read < 2 or taps < 2 or len(x) < 10 * n:
        return None
    problem = _IndexProblem(x[:: -(-len(x) // INDEX_ROWS)], lags, taps)  # at most INDEX_ROWS rows, evenly spread
    start = np.column_stack([np.ones(len(problem.target)), problem.shifted[0]])
    found = problem.solve(np.linalg.lstsq(start, problem.target, rcond=None)[0][1:])
    if found is None:
        return None
    found = _gauss_newton(problem, found)
    # the model's own z reads the window one sample later than the sub-problem: columns `window`, not `window + 1`
    return problem.window, found.h, found.middle, found.spread, np.array([round6(k) for k in found.knots])


@dataclass
class _IndexFit:
    """One direction h and what least squares makes of it."""

    h: np.ndarray
    cost: float
    theta: np.ndarray
    residual: np.ndarray
    zs: list[np.ndarray]
    knots: np.ndarray
    middle: float
    spread: float


class _IndexProblem:
    """The sub-problem :func:`index_direction` solves over the rows of a view."""

    def __init__(self, x: np.ndarray, lags: int, taps: int) -> None:
        columns_read = x.shape[1] // lags
        self.window = np.array([c * lags + i for c in range(1, columns_read) for i in range(taps)])
        own = min(RECENT + 1, lags - 1)
        read = [x[:, c * lags + 1 : c * lags + 1 + own] for c in range(1, columns_read)]
        self.fixed = np.column_stack([np.ones(len(x)), x[:, 1 : 1 + own], *read])
        self.target = x[:, 0]
        self.shifted = [x[:, self.window + 1 + j] for j in range(INDEX_SHIFTS)]  # z at lag j, one sample back

    def solve(self, h: np.ndarray) -> _IndexFit | None:
        """Knots at z's quantiles, the rest by least squares; None where z is flat."""
        z0 = self.shifted[0] @ h
        middle, spread = float(np.mean(z0)), float(np.std(z0))
        if not spread > 0.0:
            return None
        knots = np.quantile((z0 - middle) / spread, INDEX_KNOTS)
        zs = [(block @ h - middle) / spread for block in self.shifted]
        features = np.column_stack([self.fixed, *(np.maximum(z[:, None] - knots[None, :], 0.0) for z in zs)])
        theta = np.linalg.lstsq(features, self.target, rcond=None)[0]
        residual = features @ theta - self.target
        return _IndexFit(h, float(residual @ residual), theta, residual, zs, knots, middle, spread)

    def slope(self, found: _IndexFit) -> np.ndarray:
        """d residual / d h, the knots and the least-squares weights held."""
        slope = np.zeros((len(self.target), len(found.h)))
        first, width = self.fixed.shape[1], len(found.knots)
        for j, z in enumerate(found.zs):
            weights = found.theta[first + j * width : first + (j + 1) * width]
            dz = (z[:, None] > found.knots[None, :]) @ weights
            slope += (dz / found.spread)[:, None] * self.shifted[j]
        return slope


def _gauss_newton(problem: _IndexProblem, found: _IndexFit) -> _IndexFit:
    """Damped Gauss-Newton steps on h while they lower the residual (INDEX_ITERATIONS at most)."""
    damping = 1e-3
    slope = problem.slope(found)
    gram, gradient = slope.T @ slope, slope.T @ found.residual  # of the current h: a refused step keeps them
    for _ in range(INDEX_ITERATIONS):
        ridge = damping * (np.trace(gram) / len(found.h)) * np.eye(len(found.h))
        trial = problem.solve(found.h + np.linalg.solve(gram + ridge, -gradient))
        if trial is None or trial.cost >= found.cost:
            damping *= 4.0
            if damping > 1e6:
                break
            continue
        converged = found.cost - trial.cost < INDEX_TOLERANCE * found.cost
        found, damping = trial, damping * 0.5
        if converged:
            break
        slope = problem.slope(found)
        gram, gradient = slope.T @ slope, slope.T @ found.residual
    return found
