"""Dead time: how many samples pass before an input first moves the output.

A heated pipe, a conveyor, a pump's long hose or a driver's command pipeline delay the
input by several samples. The families' nonlinear terms read the three newest lags of
each signal (``families.base.RECENT``), so behind a dead time of d samples they read inputs
that have not yet acted, and the newest input that has is out of their reach: measured on
a Hammerstein plant, a dead time of 8 samples cost 7.5 dB of free run (-37.6 to -30.1).
Every system-identification toolbox estimates it (the ``nk`` of an ARX); ``fit`` does too,
and then builds each input's terms from its lags d, d + 1, ... (:func:`shifted`), and the
model delivered reads them there (:meth:`~lenn_ros.fit.termmodel.TermModel.delayed`): the
node runs it as any other model of longer lags.

The estimate is a test, not a guess: input c's dead time is the longest d for which its
lags 0..d-1 add nothing significant to a least-squares model of y(k+1) on the output's
lags and on every input's lags and squares (the squares see an input that acts through an
even map, which no linear coefficient shows). The test's residuals are correlated (the
model is linear, the plant may not be), which makes lags look *more* significant: an
estimate errs towards a shorter dead time, i.e. towards reading the input as before. An
input whose window explains nothing gets no dead time: there is nothing to place.

A dead time is a sharp onset, and only a sharp one is claimed (SHARP_SHARE, SHARP_CHANCE).
A filter's response, or a drive's third-order one sampled at 1 kHz, also starts below the
test's level for a few samples; taken for a dead time, shifting it moved a 1 kHz belt
drive's free run by +11 dB on one seed and -22 dB on another, and the blocks could not tell
which. Such an onset is left to the families' own lags.
"""

from __future__ import annotations

import math

import numpy as np

from lenn_ros.fit.families.base import RECENT
from lenn_ros.fit.record import Record, runs

#: longest dead time looked for, in samples (shorter in a short record), the shortest that counts (one the
#: families' RECENT newest lags would not reach), and the input lags the test reads beyond the longest (a third
#: of its span in a short record)
MAX_DELAY = 30
MIN_DELAY = RECENT
DELAY_WINDOW = 10
#: output lags of the test's linear model
DELAY_Y_LAGS = 6
#: one-sided normal quantile of the test (p = 0.001): a dead time is only claimed when the lags it drops
#: explain less than chance would at that level
DELAY_Z = 3.09
#: a dead time's first acting lag explains at least this share of what the input's whole window does, and
#: this many times what chance would at the test's level: measured 0.49-0.76 and 430-660x on plants behind a
#: transport delay, 0.01-0.41 and 1.6-6.3x where a filter's or a drive's response starts smoothly
SHARP_SHARE = 0.1
SHARP_CHANCE = 20.0
#: inputs tested in one model (six: 487 regressors); beyond, each input is tested alone with the output's lags,
#: as the regressors' normal equations would grow with their square and the solves with their cube
JOINT_INPUTS = 6
#: rows the test is fitted on (evenly spread; a few thousand pin a dead time down), and the fewest per
#: regressor it needs
DELAY_ROWS = 20000
ROWS_PER_REGRESSOR = 10


def _chi2_limit(dof: int) -> float:
    """Upper DELAY_Z quantile of a chi-square of ``dof`` degrees of freedom (Wilson-Hilferty)."""
    a = 2.0 / (9.0 * dof)
    return dof * (1.0 - a + DELAY_Z * math.sqrt(a)) ** 3


def input_delays(values: np.ndarray, breaks: np.ndarray | list[int] | None = None) -> tuple[int, ...]:
    """Dead time in samples of each column after the first of ``values`` (column 0: the output).

    A column that is an output's past (several outputs, each reading the others) is tested
    as an input; it rarely has one. Records too short for the test (fewer than ROWS_PER_REGRESSOR
    rows per regressor) get none.
    """
    values = np.asarray(values, dtype=np.float64)
    inputs = values.shape[1] - 1
    if inputs > JOINT_INPUTS:  # each input on its own (the others' share is then noise to its test)
        return tuple(input_delays(values[:, [0, 1 + c]], breaks)[0] for c in range(inputs))
    if inputs < 1:
        return ()
    test = _DelayTest(values, breaks)
    if len(test.target) < ROWS_PER_REGRESSOR * test.width or test.noise <= 0.0:
        return (0,) * inputs
    return tuple(test.dead_time(c) for c in range(inputs))


class _DelayTest:
    """The least-squares model of y(k+1) on the output's DELAY_Y_LAGS lags and every input's span of lags and their
    squares, as normal equations: the residual of any subset of its regressors costs one small solve."""

    def __init__(self, values: np.ndarray, breaks: np.ndarray | list[int] | None) -> None:
        n, columns = values.shape
        # a short record is tested over a shorter span (a 400-sample one up to 6 samples), so that it still holds
        # ROWS_PER_REGRESSOR rows per regressor
        span = MAX_DELAY + DELAY_WINDOW
        while span > 1 and n - max(DELAY_Y_LAGS, span) < ROWS_PER_REGRESSOR * (
            1 + DELAY_Y_LAGS + 2 * (columns - 1) * span
        ):
            span -= 1
        self.span = span
        self.longest = span - min(DELAY_WINDOW, span // 3)  # the longest dead time looked for
        warm = max(DELAY_Y_LAGS, span)
        self.width = 1 + DELAY_Y_LAGS + 2 * (columns - 1) * span
        self.target = target = np.arange(warm, n)[Record.of(values, breaks).valid_rows(warm)]
        self.noise = 0.0
        if len(target) < ROWS_PER_REGRESSOR * self.width or self.longest < MIN_DELAY:
            return
        if len(target) > DELAY_ROWS:
            target = target[np.linspace(0, len(target) - 1, DELAY_ROWS).round().astype(np.int64)]
        spread = values.std(axis=0)
        scaled = (values - values.mean(axis=0)) / np.where(spread > 0, spread, 1.0)
        x = np.empty((len(target), self.width))
        x[:, 0] = 1.0
        for i in range(DELAY_Y_LAGS):
            x[:, 1 + i] = scaled[target - 1 - i, 0]
        for c in range(columns - 1):
            first = self._first(c)
            for i in range(span):
                lagged = scaled[target - 1 - i, 1 + c]
                x[:, first + i] = lagged
                x[:, first + span + i] = lagged * lagged - 1.0
        d = scaled[target, 0]
        self.gram, self.moment, self.energy = x.T @ x, x.T @ d, float(d @ d)
        self.ridge = 1e-9 * float(np.trace(self.gram)) / self.width
        self.full = self.rss(np.arange(self.width))
        self.noise = self.full / max(len(target) - self.width, 1)

    def _first(self, c: int) -> int:
        return 1 + DELAY_Y_LAGS + 2 * c * self.span

    def rss(self, keep: np.ndarray) -> float:
        g = self.gram[np.ix_(keep, keep)] + self.ridge * np.eye(len(keep))
        return max(self.energy - float(self.moment[keep] @ np.linalg.solve(g, self.moment[keep])), 0.0)

    def gain(self, c: int, lags: int) -> float:
        """How much input c's lags 0..lags-1 (and their squares) explain beyond the rest, in noise variances."""
        first, span = self._first(c), self.span
        gone = np.r_[first : first + lags, first + span : first + span + lags]
        return (self.rss(np.setdiff1d(np.arange(self.width), gone)) - self.full) / self.noise

    def dead_time(self, c: int) -> int:
        whole = self.gain(c, self.span)
        if whole <= _chi2_limit(2 * self.span):
            return 0  # the input explains nothing the test can see: no dead time to place
        delay = 0
        while delay < self.longest and self.gain(c, delay + 1) <= _chi2_limit(2 * (delay + 1)):
            delay += 1
        if delay < MIN_DELAY or delay == self.longest:
            # shorter than MIN_DELAY: the nonlinear terms' newest lags reach an input lag that acts, and the linear
            # terms read every lag (shifting a 1 kHz axis by the 1 sample its force takes to show changed its
            # selection for the worse: -34.8 to -31.1 dB over 5 seeds). The longest: nothing within it acts, yet
            # the window does: a slow drift shared by input and output, not a dead time this test can place
            return 0
        # a dead time is a sharp onset: the first lag that acts explains SHARP_SHARE of what the whole window
        # does, far beyond chance. A smooth one (a filter's, a third-order drive's at 1 kHz) crosses the test's
        # level gradually, and is left to the families' own lags
        onset = self.gain(c, delay + 1) - self.gain(c, delay)
        return delay if onset >= SHARP_SHARE * whole and onset >= SHARP_CHANCE * _chi2_limit(2) else 0


def shifted(
    values: np.ndarray, breaks: np.ndarray | list[int] | None, delays: tuple[int, ...]
) -> tuple[np.ndarray, list[int]]:
    """(rows, breaks) of ``values`` with column c + 1 moved down by ``delays[c]``: row r holds the output at r
    and each input where it acts on it. Each contiguous run of the record is shifted on its own and loses
    its first max(delays) rows, so no row pairs an output with an input from across a gap."""
    values = np.asarray(values, dtype=np.float64)
    shifts = (0, *delays)
    longest = max(shifts)
    pieces, starts, at = [], [], 0
    for a, b in runs(0, len(values), np.asarray([] if breaks is None else breaks, dtype=np.int64)):
        if b - a <= longest:
            continue
        piece = np.column_stack([values[a + longest - s : b - s, c] for c, s in enumerate(shifts)])
        starts.append(at)
        pieces.append(piece)
        at += len(piece)
    rows = np.vstack(pieces) if pieces else np.empty((0, values.shape[1]))
    return rows, starts[1:]


def delays_text(delays: tuple[int, ...], names: tuple[str, ...]) -> str:
    """``u 5 samples`` (the columns with one): what the report says of the inputs' dead times."""
    return ", ".join(f"{name} {d} samples" for name, d in zip(names, delays, strict=True) if d)
