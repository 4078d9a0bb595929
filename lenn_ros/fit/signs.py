"""The sign of an output whose sensor reads its absolute value (a pulse counter on a speed).

A NARX of |y| cannot carry the sign through a free run: after a zero crossing it cannot
tell which way the plant moves on, so it is near the mean at best. The signed output y
is what the plant's dynamics act on. Its sign can only change where |y| comes near
zero, so the record falls into runs between near-zero minima, each of one unknown sign;
the signs that make y the free run of one linear model of the inputs are taken as the
record's (:func:`recover_signs`). ``fit`` then builds its model on the signed record
beside the plain one, and keeps it only where it simulates |y| better
(:class:`~lenn_ros.core.structure.ModelStructure` ``y_abs``).

How the signs are found, and why each step:

1. A start that needs no guess: |y|^2 = y^2 is a quadratic form in the input's past. It
   is fitted by least squares on the products of the input through a bank of first-order
   filters (spans 1, 2, 4, .. samples, so slow and fast plants alike), and its leading
   eigenvector is a linear filter of the input whose output has the signs (up to one
   sign for all: y and -y read the same).
2. Alternation, as k-means does: a linear ARX fitted to the signed record, simulated
   from the input alone, gives each run the sign its simulation has over it; then refit.
   It settles where its start leads it, so it also runs from RESTARTS random starts, and
   the signs of the lowest misfit (the ARX's free run of |y| against |y|) go on.
3. Flipping one, two or three neighbouring runs at a time, kept when the ARX's free run
   of |y| fits better: alternation stops where a run's sign and the ARX agree with each
   other but not with the record. Within a budget (``SEARCH_BUDGET`` samples simulated),
   so a record of 40 000 samples stays within seconds.
4. All of it on means of a few samples where the record is sampled far faster than |y|
   moves (:func:`decimation`): the ARX judges at the time scale of the crossings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lenn_ros.core.jit import njit

#: a near-zero minimum lies below this fraction of |y|'s 99th percentile
NEAR_ZERO = 0.1
#: below this (a fraction of the 99th percentile) |y| is no absolute value: a negative reading
NEGATIVE_NOISE = 0.05
#: fewer near-zero minima than this: no sign changes to find (the output does not look like |y|)
MIN_CROSSINGS = 4
#: lags of the linear ARX that judges the signs, and the filter spans of the start
ARX_LAGS = 8
SPANS = (1, 2, 4, 8, 16, 32, 64, 128)
#: samples simulated by the flip search at most (evaluations x record length)
SEARCH_BUDGET = 40_000_000
#: random starts of the alternation beside the quadratic form's (the lowest misfit is searched on): the
#: alternation settles where the start leads it, and one start was a poor one (58 % of the runs right)
RESTARTS = 8


@dataclass(frozen=True)
class Signs:
    """The signed record and how it was found (what the report says)."""

    signed: np.ndarray
    runs: int
    flips: int
    arx_nmse_db: float  # the judging ARX's free run of |y| against |y|, dB
    averaged: int = 1  # samples averaged into one to find them (:func:`decimation`)

    def as_dict(self) -> dict:
        return {"runs": self.runs, "runs_flipped_by_search": self.flips, "arx_free_run_nmse_db": self.arx_nmse_db,
                "samples_averaged": self.averaged}  # fmt: skip


def looks_absolute(y: np.ndarray) -> bool:
    """Whether ``y`` reads like an absolute value: never clearly negative, and down near zero in a V
    again and again (where the sign may change).

    A V: |y| passing through zero between samples is no higher at its minimum than the step
    out of it (the far side is a whole step away from zero), where a level that only comes
    low, as a tank's does, turns in a U at a height far above its steps."""
    top = float(np.quantile(y, 0.99))
    if not top > 0.0 or float(np.min(y)) < -NEGATIVE_NOISE * top:
        return False
    minima = _near_zero_minima(y, NEAR_ZERO * top)
    steps = np.maximum(y[minima - 1], y[minima + 1]) - y[minima]
    return int(np.count_nonzero(y[minima] <= steps)) >= MIN_CROSSINGS


def _near_zero_minima(y: np.ndarray, level: float) -> np.ndarray:
    inner = y[1:-1]
    return np.flatnonzero((inner <= y[:-2]) & (inner <= y[2:]) & (inner < level)) + 1


def _runs(y: np.ndarray, breaks: list[int]) -> tuple[np.ndarray, int]:
    """Each sample's run: a near-zero minimum is a run of its own (the crossing is on one side of it or
    the other), and a break in the record starts a new one."""
    starts = np.zeros(len(y), dtype=bool)
    minima = _near_zero_minima(y, NEAR_ZERO * float(np.quantile(y, 0.99)))
    starts[minima] = True
    after = minima + 1
    starts[after[after < len(y)]] = True
    starts[[b for b in breaks if 0 < b < len(y)]] = True
    starts[0] = False
    labels = np.cumsum(starts)
    return labels, int(labels[-1]) + 1


@njit(cache=True)
def _arx_normal_equations(u: np.ndarray, s: np.ndarray, starts: np.ndarray, lags: int) -> tuple:
    """(Gram matrix, right-hand side) of y(k) = sum a_i y(k-i) + sum b_i u(k-i) within each run of the record
    (solved outside: numba's own solver would need scipy, which the package does not depend on)."""
    width = 2 * lags
    gram = np.zeros((width, width))
    cross = np.zeros(width)
    row = np.empty(width)
    for r in range(len(starts) - 1):
        for k in range(starts[r] + lags, starts[r + 1]):
            for i in range(lags):
                row[i] = s[k - 1 - i]
                row[lags + i] = u[k - 1 - i]
            cross += row * s[k]
            gram += np.outer(row, row)
    return gram, cross


@njit(cache=True)
def _arx_simulation(u: np.ndarray, s: np.ndarray, starts: np.ndarray, lags: int, w: np.ndarray) -> np.ndarray:
    """The ARX of weights ``w`` simulated from u (seeded at each run of the record by its first samples);
    NaN from where it diverged."""
    bound = 1e3 * (np.max(np.abs(s)) + 1e-300)
    sim = s.copy()
    for r in range(len(starts) - 1):
        for k in range(starts[r] + lags, starts[r + 1]):
            value = 0.0
            for i in range(lags):
                value += w[i] * sim[k - 1 - i] + w[lags + i] * u[k - 1 - i]
            if not abs(value) < bound:
                sim[k:] = np.nan
                return sim
            sim[k] = value
    return sim


def _arx_free_run(u: np.ndarray, s: np.ndarray, starts: np.ndarray, lags: int) -> np.ndarray:
    """The least-squares ARX of the signed record ``s``, simulated from u (NaN from where it diverged)."""
    gram, cross = _arx_normal_equations(u, s, starts, lags)
    gram += 1e-9 * (np.trace(gram) / len(cross) + 1e-300) * np.eye(len(cross))
    return _arx_simulation(u, s, starts, lags, np.linalg.solve(gram, cross))


def _misfit(u: np.ndarray, y: np.ndarray, signs: np.ndarray, labels: np.ndarray, starts: np.ndarray) -> float:
    simulated = _arx_free_run(u, y * signs[labels], starts, ARX_LAGS)
    if not np.all(np.isfinite(simulated)):
        return np.inf
    return float(np.mean((np.abs(simulated) - y) ** 2))


@njit(cache=True)
def _low_pass(x: np.ndarray, span: float) -> np.ndarray:
    """First-order low-pass of ``x`` with a time constant of ``span`` samples, from 0."""
    out = np.empty(len(x))
    level = 0.0
    for k in range(len(x)):
        level += (x[k] - level) / span
        out[k] = level
    return out


def _start(u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A linear filter of u whose output has y's signs (step 1 of the module's note)."""
    shifted = np.r_[0.0, u[:-1]]
    spans = [s for s in SPANS if s <= max(1, len(y) // 8)]
    bank = np.column_stack([shifted] + [_low_pass(shifted, float(s)) for s in spans[1:]])
    p = bank.shape[1]
    upper = np.triu_indices(p)
    products = np.column_stack([bank[:, i] * bank[:, j] for i, j in zip(*upper, strict=True)] + [np.ones(len(y))])
    keep = np.ones(len(y), dtype=bool)
    keep[: max(spans)] = False  # the filters' start-up
    weights, *_ = np.linalg.lstsq(products[keep], y[keep] ** 2, rcond=None)
    form = np.zeros((p, p))
    form[upper] = weights[:-1]
    _, vectors = np.linalg.eigh((form + form.T) / 2.0)
    return bank @ vectors[:, -1]


def _alternated(u: np.ndarray, y: np.ndarray, labels: np.ndarray, starts: np.ndarray, signs: np.ndarray) -> np.ndarray:
    """Step 2: each run takes the sign the ARX's free run has over it, until no run changes."""
    n_runs = len(signs)
    for _ in range(50):  # it settles within a few rounds
        simulated = _arx_free_run(u, y * signs[labels], starts, ARX_LAGS)
        if not np.all(np.isfinite(simulated)):
            break
        new = np.where(np.bincount(labels, y * simulated, n_runs) < 0.0, -1.0, 1.0)
        if np.array_equal(new, signs):
            break
        signs = new
    return signs


def _flip_search(
    u: np.ndarray, y: np.ndarray, labels: np.ndarray, starts: np.ndarray, signs: np.ndarray
) -> tuple[np.ndarray, float, int]:
    """Step 3: (signs, the ARX's misfit of |y|, runs flipped), flipping 1-3 neighbouring runs while it helps."""
    misfit = _misfit(u, y, signs, labels, starts)
    flips, budget = 0, SEARCH_BUDGET // len(y)
    improved = True
    while improved and budget > 0:
        improved = False
        for width, first in ((w, f) for w in (1, 2, 3) for f in range(len(signs) - w + 1)):
            if budget <= 0:
                break
            budget -= 1
            trial = signs.copy()
            trial[first : first + width] *= -1.0
            value = _misfit(u, y, trial, labels, starts)
            if value < misfit:
                signs, misfit, improved, flips = trial, value, True, flips + 1
    return signs, misfit, flips


def decimation(y: np.ndarray) -> int:
    """Samples averaged into one for finding the signs: the fewest (a power of two) at which |y| moves from one
    averaged sample to the next (lag-one autocorrelation at most STILL). A linear ARX judges signs at the
    time scale of the crossings: on a record sampled far faster (a 1 kHz drive) its one-step least squares
    fit the noise, and its free run missed the crossings (67 % of the signs right)."""
    q = 1
    while len(y) // (2 * q) >= 8 * ARX_LAGS and _lag_one(_averaged(y, q)) > STILL:
        q *= 2
    return q


#: lag-one autocorrelation above which |y| barely moves per sample (a 50 Hz belt drive: 0.95-0.97)
STILL = 0.97


def _averaged(x: np.ndarray, q: int) -> np.ndarray:
    """Means of ``q`` samples at a time (the last, shorter block included)."""
    if q == 1:
        return x
    edges = np.arange(0, len(x), q)
    return np.add.reduceat(x, edges) / np.diff(np.r_[edges, len(x)])


def _lag_one(x: np.ndarray) -> float:
    x = x - np.mean(x)
    energy = float(np.dot(x, x))
    return float(np.dot(x[1:], x[:-1]) / energy) if energy > 0 else 1.0


def recover_signs(u: np.ndarray, y: np.ndarray, breaks: list[int] | None = None) -> Signs | None:
    """The signed record of an output read as its absolute value, or None when ``y`` does not look
    like one (:func:`looks_absolute`) or no linear model of the input follows its signs at all.

    On a record sampled far faster than |y| moves, the signs are found on means of
    :func:`decimation` samples, or half as many where the judging ARX's misfit is lower there
    (a 1 kHz belt drive: 93 % of the signs right at 32 samples, 99 % at 16), and each sample
    takes its block's (a crossing inside a block signs a few samples near zero wrongly: they
    weigh little)."""
    u, y = np.asarray(u, dtype=np.float64), np.asarray(y, dtype=np.float64)
    breaks = sorted(b for b in (breaks or []) if 0 < b < len(y))
    if len(y) < 8 * ARX_LAGS or not looks_absolute(y):
        return None
    q = decimation(y)
    tried = {}
    for rate in {q, max(1, q // 2)}:  # (the search settles better at one than the other: the lower misfit)
        found = _signs(_averaged(u, rate), _averaged(y, rate), sorted({b // rate for b in breaks} - {0}))
        if found is not None:
            tried[rate] = found
    if not tried:
        return None
    rate = min(tried, key=lambda r: tried[r][3])
    signs, runs, flips, misfit = tried[rate]
    return Signs(y * np.repeat(signs, rate)[: len(y)], runs, flips, misfit, rate)


def _signs(u: np.ndarray, y: np.ndarray, breaks: list[int]) -> tuple[np.ndarray, int, int, float] | None:
    """(each sample's sign, runs, runs flipped by the search, the ARX's free-run NMSE of |y| in dB) at one rate."""
    labels, n_runs = _runs(y, breaks)
    starts = np.array([0, *breaks, len(y)], dtype=np.int64)
    guess = _start(u, y)
    rng = np.random.default_rng(0)  # (the same signs on every run of fit)
    first = [np.where(np.bincount(labels, y * guess, n_runs) < 0.0, -1.0, 1.0)]
    first += [rng.choice([-1.0, 1.0], n_runs) for _ in range(RESTARTS)]
    settled = [_alternated(u, y, labels, starts, signs) for signs in first]
    signs = min(settled, key=lambda signs: _misfit(u, y, signs, labels, starts))
    signs, misfit, flips = _flip_search(u, y, labels, starts, signs)
    if not np.isfinite(misfit):
        return None
    each = signs[labels]
    if np.mean(y * each * guess) < 0.0:  # one sign for all is free: take the start's
        each = -each
    nmse_db = float(10.0 * np.log10(misfit / np.var(y))) if np.var(y) > 0 else float("nan")
    return each, n_runs, flips, round(nmse_db, 2)
