"""``fit``'s nominal 95 % bands: a one-step band that widens where the model extrapolates, a free-run band that
grows along the run, both calibrated on errors of samples the model was not fitted to.

One number per band (the 95 % quantile of |e| over the held-out blocks) covered its test part only when that
part was drawn like the training: a test part farther from the build data, or a free run longer than the blocks'
runs, has larger errors (on the shared sets one-step coverage fell to 76 % and free-run coverage to 80 %). So:

- **one step** (:func:`one_step_band`): a split-conformal band normalised per sample. Each error is divided by
  a scale s(x) of its regressor x, and the band is q s(x), q the 95 % quantile of the normalised errors of the
  held-out blocks. s(x) = l(x) sqrt(1 + r(x)): r = h / (p / N), the leverage h = f^T (F^T F)^-1 f of the
  regressor's features f against the build rows' features F (N rows, p features) over its mean p / N, i.e.
  how far x lies from the build data (about 1 among the build rows, tens where the model extrapolates:
  measured, test errors grow about as sqrt(1 + r) on every shared set that extrapolates); l(x) the local
  error level, a ridge regression of log e^2 on the standardised features, kept within the levels the blocks
  showed (an exchanger's errors are larger at some flows than at others). A held-out block's r and l are
  those of the rows it was not fitted to (its fold's Gram, the other blocks' errors), as a test sample's are.
- **free run** (:func:`horizon_band`): the half-width is a function of the steps since the run started
  (from measured outputs): errors of the blocks' free runs by horizon in doubling bins of at least
  HORIZON_BIN errors, their mean |e| made non-decreasing (isotonic), times the 95 % quantile of the
  errors normalised by it. Beyond the longest held-out run the band grows as the last bins did, at most as a
  random walk (the growth a free run's error cannot be shown to stay below where no block ran that long).

Apart from the procedure: the bands read the chosen candidate's blocks and the test samples, nothing of how
the candidate was chosen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lenn_ros.core.expansions import term_features
from lenn_ros.fit.record import Record, fold_blocks
from lenn_ros.fit.selection import Candidate
from lenn_ros.fit.termmodel import TermModel

#: the bands' nominal coverage
LEVEL = 0.95
#: ridge of the local error level's regression (log e^2 on standardised features), per row: a prior towards
#: one level everywhere (coverage on the shared sets moved by under 1 % between 1e-4 and 0.1)
SCALE_RIDGE = 0.01
#: fewest held-out free-run errors in one horizon bin (its mean |e| is then known to a few %)
HORIZON_BIN = 200
#: fastest growth (exponent of the steps) of the free-run band beyond the longest held-out run: a random walk's
MAX_GROWTH = 0.5
#: the report says the test part is not drawn like the build part when more than this share of its regressors
#: lie farther from the build data than 99 % of the build rows do: four times the 1 % of a part drawn alike
#: (measured 0-2.8 % on test parts drawn like the training, 5-69 % on test parts that extrapolate)
UNLIKE_SHARE = 0.04


@dataclass
class HeldOut:
    """One-step errors of the held-out blocks (each block run by the weights fitted without it), with the
    features of their regressors and each error's block: what the one-step band is calibrated on."""

    errors: np.ndarray
    features: np.ndarray
    blocks: np.ndarray


def held_out_one_step(candidate: Candidate, record: Record) -> HeldOut:
    """Every block's one-step errors (predicted minus measured) by the weights fitted without it, over the
    pieces :meth:`Record.one_step_residuals` scores. Empty without fold weights."""
    model = candidate.model
    if model is None or not candidate.fold_weights:
        return HeldOut(np.empty(0), np.empty((0, 0)), np.empty(0, dtype=np.int64))
    warm = model.warm_up
    errors, features, blocks = [], [], []
    for index, ((a, b), w) in enumerate(zip(fold_blocks(record.n, warm), candidate.fold_weights, strict=True)):
        for first, stop in record.pieces(a, b, warm):
            f, targets = model.regression(record.values[first - warm : stop])
            errors.append(f @ w - targets)
            features.append(f)
            blocks.append(np.full(len(targets), index))
    if not errors:
        return HeldOut(np.empty(0), np.empty((0, len(model.exponents))), np.empty(0, dtype=np.int64))
    return HeldOut(np.concatenate(errors), np.vstack(features), np.concatenate(blocks))


def held_out_free_runs(candidate: Candidate, record: Record) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(errors, steps since the run's start, block) of every block's free run by the weights fitted without it, one
    run per contiguous piece from the measured outputs before it (NaN where a run diverged)."""
    model = candidate.model
    if model is None or not candidate.fold_weights:
        return np.empty(0), np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    warm = model.warm_up
    errors, steps, blocks = [], [], []
    for index, ((a, b), w) in enumerate(zip(fold_blocks(record.n, warm), candidate.fold_weights, strict=True)):
        for first, stop in record.pieces(a, b, warm):
            errors.append(record.residuals(model, first, stop, w))
            steps.append(np.arange(stop - first))
            blocks.append(np.full(stop - first, index))
    if not errors:
        return np.empty(0), np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    return np.concatenate(errors), np.concatenate(steps), np.concatenate(blocks)


def blocks_covered(scores: np.ndarray, blocks: np.ndarray) -> tuple[float, float] | None:
    """(lowest, highest) share of a block's normalised errors ``scores`` within the 95 % quantile of the other
    blocks' (None with fewer than two blocks): what a band calibrated as fit calibrates it covered of parts it was
    not calibrated on. Its spread says how far a test part's coverage may stray from 95 % when the record's parts
    differ (a drifting plant, another operating region); it is no bound, a test part unlike every block may go
    beyond it."""
    covered = []
    for block in np.unique(blocks).tolist():
        inside = blocks == block
        if inside.all():
            continue
        covered.append(float(np.mean(scores[inside] <= np.quantile(scores[~inside], LEVEL))))
    return (min(covered), max(covered)) if len(covered) >= 2 else None


def raw_features(model: TermModel, view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(features of the network inputs as measured, features as the model reads them: clipped to [-1, 1]) of
    every complete regressor of ``view``. The first say how far a regressor lies beyond the build range (a
    clipped one reads as the range's edge), the second where within it."""
    x, _ = model.layout.regressors(view)
    factors = model.factors if len(model.factors) else None
    raw = term_features(x, model.exponents, model.basis, factors)
    return raw, term_features(np.clip(x, -1.0, 1.0), model.exponents, model.basis, factors)


# -- one step ahead --------------------------------------------------------------------------------------------


@dataclass
class LocalLevel:
    """The local error level l(x) = exp(c0 + c . (f - mean) / sd / 2), kept within [low, high]: the levels the
    held-out rows were given (a regression of log e^2 is not extrapolated past what the blocks showed)."""

    mean: np.ndarray
    sd: np.ndarray
    coefficients: np.ndarray
    low: float = 0.0
    high: float = math.inf

    @classmethod
    def fit(cls, features: np.ndarray, errors: np.ndarray) -> LocalLevel:
        """The ridge regression (SCALE_RIDGE) of log e^2 on the standardised features."""
        mean, sd = features.mean(axis=0), features.std(axis=0)
        sd[sd <= 0.0] = 1.0
        design = np.column_stack([np.ones(len(features)), (features - mean) / sd])
        floor = 1e-6 * float(np.mean(errors**2)) or 1e-300  # an exact zero error is not -inf
        penalty = SCALE_RIDGE * len(features) * np.eye(design.shape[1])
        penalty[0, 0] = 0.0
        coefficients = np.linalg.solve(design.T @ design + penalty, design.T @ np.log(errors**2 + floor))
        level = cls(mean, sd, coefficients)
        seen = level(features)
        level.low, level.high = float(seen.min()), float(seen.max())
        return level

    def __call__(self, features: np.ndarray) -> np.ndarray:
        z = self.coefficients[0] + ((features - self.mean) / self.sd) @ self.coefficients[1:]
        return np.clip(np.exp(0.5 * z), self.low, self.high)


@dataclass
class OneStepBand:
    """The one-step band q s(x), s(x) = l(x) sqrt(1 + r(x)) (the module's docstring): ``inverse`` is the build
    rows' (F^T F)^-1, ``rows`` their N; ``typical_r`` the build rows' 99th percentile of r."""

    quantile: float
    inverse: np.ndarray
    rows: int
    level: LocalLevel | None
    typical_r: float
    blocks_covered: tuple[float, float] | None = None  # (:func:`blocks_covered`)

    def distance(self, raw: np.ndarray) -> np.ndarray:
        """r = h / (p / N) of each row of features: about 1 among the build rows, more the farther from them."""
        return _leverage(raw, self.inverse) * self.rows / max(raw.shape[1], 1)

    def half_width(self, raw: np.ndarray, clipped: np.ndarray) -> np.ndarray:
        """The band's half-width at each regressor (``raw``, ``clipped``: :func:`raw_features`)."""
        local = self.level(clipped) if self.level is not None else 1.0
        return self.quantile * local * np.sqrt(1.0 + self.distance(raw))


def one_step_band(held: HeldOut) -> OneStepBand | None:
    """The one-step band calibrated on ``held``: each block's errors normalised by the distance and local level
    it has from the other blocks (their Gram, their errors), q their 95 % quantile. None without errors."""
    finite = np.isfinite(held.errors) & np.all(np.isfinite(held.features), axis=1)
    errors, features, blocks = held.errors[finite], held.features[finite], held.blocks[finite]
    if len(errors) <= features.shape[1] or len(np.unique(blocks)) < 2:
        return None
    gram = features.T @ features
    scale = np.empty(len(errors))
    for block in np.unique(blocks):
        inside = blocks == block
        others = ~inside
        r = _leverage(features[inside], _inverse(gram - features[inside].T @ features[inside]))
        local = LocalLevel.fit(features[others], errors[others])(features[inside])
        scale[inside] = local * np.sqrt(1.0 + r * others.sum() / features.shape[1])
    scores = np.abs(errors) / scale
    quantile = float(np.quantile(scores, LEVEL))
    band = OneStepBand(quantile, _inverse(gram), len(errors), LocalLevel.fit(features, errors), 0.0)
    band.blocks_covered = blocks_covered(scores, blocks)
    band.typical_r = float(np.quantile(band.distance(features), 0.99))
    return band


def _inverse(gram: np.ndarray) -> np.ndarray:
    """(F^T F)^-1, a pseudo-inverse where some features are (nearly) collinear."""
    return np.linalg.pinv(gram, rcond=1e-12, hermitian=True)


def _leverage(features: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """h = f^T (F^T F)^-1 f of every row f."""
    return np.einsum("ij,ij->i", features @ inverse, features)


# -- free run --------------------------------------------------------------------------------------------------


@dataclass
class HorizonBand:
    """The free-run half-width by steps since the run's start: ``widths[i]`` from step ``starts[i]`` on, up to
    ``longest`` (the longest held-out run's steps), then growing as (steps / longest)^``growth``."""

    starts: np.ndarray
    widths: np.ndarray
    longest: int
    growth: float
    blocks_covered: tuple[float, float] | None = None  # (:func:`blocks_covered`; not part of :meth:`as_dict`)

    def at(self, steps: np.ndarray) -> np.ndarray:
        """The half-width at each of ``steps`` (0: the run's first simulated sample); non-decreasing in steps."""
        steps = np.asarray(steps)
        width = self.widths[np.clip(np.searchsorted(self.starts, steps, side="right") - 1, 0, len(self.widths) - 1)]
        beyond = np.maximum((steps + 1.0) / self.longest, 1.0)
        return width * beyond**self.growth

    @classmethod
    def from_dict(cls, figures: dict[str, Any]) -> HorizonBand:
        """The band as :meth:`as_dict` wrote it (fit.json's ``by_horizon``), as evaluate and a loaded model read it
        (:func:`lenn_ros.service.scoring.fit_free_run_widths`)."""
        return cls(
            np.asarray(figures["from_step"], dtype=np.int64),
            np.asarray(figures["half_width"], dtype=np.float64),
            int(figures["longest_held_out_run"]),
            float(figures["growth_beyond"]),
        )

    def as_dict(self) -> dict[str, object]:
        return {
            "from_step": self.starts.tolist(),
            "half_width": self.widths.tolist(),
            "longest_held_out_run": self.longest,
            "growth_beyond": self.growth,
        }


def horizon_band(errors: np.ndarray, steps: np.ndarray, blocks: np.ndarray | None = None) -> HorizonBand | None:
    """The free-run band from errors of runs and each one's steps since its run's start: mean |e| per horizon
    bin (:func:`horizon_bins`), isotonic in the steps, times the 95 % quantile of |e| over it; the growth beyond
    the longest run is that between the last two bins, within [0, MAX_GROWTH]. None without errors. With each
    error's held-out ``blocks``, the band's :func:`blocks_covered` too."""
    finite = np.isfinite(errors)
    errors, steps = np.abs(errors[finite]), steps[finite]
    blocks = blocks[finite] if blocks is not None else None
    if not len(errors):
        return None
    starts = horizon_bins(steps)
    where = np.searchsorted(starts, steps, side="right") - 1
    counts = np.bincount(where, minlength=len(starts))
    level = isotonic(np.bincount(where, errors, minlength=len(starts)) / counts, counts)
    positive = level > 0
    if not positive.any():
        return HorizonBand(starts, np.zeros(len(starts)), int(steps.max()) + 1, 0.0)
    level = np.maximum(level, level[positive][0])  # (a bin of exact zeros: the first level that is not)
    scores = errors / level[where]
    quantile = float(np.quantile(scores, LEVEL))
    growth = 0.0
    if len(starts) > 1:
        centres = np.bincount(where, steps + 1.0, minlength=len(starts)) / counts
        growth = math.log(level[-1] / level[-2]) / math.log(centres[-1] / centres[-2])
    band = HorizonBand(starts, quantile * level, int(steps.max()) + 1, float(np.clip(growth, 0.0, MAX_GROWTH)))
    band.blocks_covered = blocks_covered(scores, blocks) if blocks is not None else None
    return band


def horizon_bins(steps: np.ndarray) -> np.ndarray:
    """First steps of the horizon bins: [0, 1), [1, 2), [2, 4), [4, 8) ... merged with the next until each holds
    HORIZON_BIN errors (a last bin short of them joins the one before)."""
    top = int(steps.max()) + 1
    edges = [0, *(2**i for i in range(max(top - 1, 1).bit_length()) if 2**i < top)]
    counts = np.bincount(np.searchsorted(edges, steps, side="right") - 1, minlength=len(edges))
    starts, held = [0], 0
    for edge, count in zip(edges[1:], counts[:-1], strict=True):
        held += count
        if held >= HORIZON_BIN:
            starts.append(edge)
            held = 0
    if len(starts) > 1 and held + counts[-1] < HORIZON_BIN:
        starts.pop()
    return np.asarray(starts)


def isotonic(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The weighted least-squares non-decreasing fit to ``values`` (pool adjacent violators)."""
    pools: list[list[float]] = []  # [value, weight, members]
    for value, weight in zip(values.tolist(), weights.tolist(), strict=True):
        pools.append([value, weight, 1])
        while len(pools) > 1 and pools[-2][0] > pools[-1][0]:
            value, weight, members = pools.pop()
            last = pools[-1]
            last[0] = (last[0] * last[1] + value * weight) / (last[1] + weight)
            last[1] += weight
            last[2] += members
    return np.repeat([pool[0] for pool in pools], [pool[2] for pool in pools])


def run_steps(simulated: np.ndarray) -> np.ndarray:
    """Steps since the start of the run each sample belongs to (0: its first simulated sample), the runs being
    the stretches of finite ``simulated`` (a free run restarts from measured outputs after each gap)."""
    finite = np.isfinite(simulated)
    index = np.arange(len(simulated))
    begins = finite & ~np.r_[False, finite[:-1]]
    return index - np.maximum.accumulate(np.where(begins, index, 0))
