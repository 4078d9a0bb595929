"""The training samples as the selection sees them: one output's view, its contiguous runs and blocks.

Records that are not one contiguous run (gaps in a recording) are handled by ``breaks``:
no regression row reaches across a break and every simulation restarts from the measured
outputs after it (:meth:`Record.pieces`). The training samples are cut into contiguous
blocks (:func:`fold_blocks`), each simulated by the weights fitted to the others, and the
outcome of free runs is pooled (:class:`Simulation`), with what refuses a model's run. A
module of its own: the selection, the refinement, the dead-time test, the rest rule and
scoring all walk the record this way.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from lenn_ros.core.free_run import FREE_RUN_DIVERGENCE_BOUND
from lenn_ros.fit.termmodel import TermModel

#: largest share of a block's network inputs its free run may clip before the prefix is refused:
#: the scaling spans the training range plus a margin, so a measured input never clips; a
#: clipped one is the simulated output beyond range and margin, i.e. running away
MAX_CLIPPED_FRACTION = 0.0
#: the same for ``fit``'s fallback selection (``strict=False``)
LOOSE_CLIPPED_FRACTION = 0.01
#: most blocks the training samples are cut into, and the fewest samples a block may hold
MAX_FOLDS = 5
MIN_BLOCK = 60


def runs(start: int, stop: int, breaks: np.ndarray) -> list[tuple[int, int]]:
    """The contiguous pieces of samples [start, stop): cut at every break (a sample that starts a new run)."""
    cuts = [int(b) for b in breaks if start < b < stop]
    edges = [start, *cuts, stop]
    return [(a, b) for a, b in itertools.pairwise(edges) if b > a]


def fold_blocks(n: int, warm_up: int) -> list[tuple[int, int]]:
    """Contiguous blocks of samples [warm_up, n), each simulated by the weights of all the others.

    As many as ``MAX_FOLDS``, none shorter than ``MIN_BLOCK`` samples, at least two: a
    400-sample record gets 5 blocks of about 80, a 40 000-sample one 5 of 8 000.
    """
    usable = n - warm_up
    count = max(2, min(MAX_FOLDS, usable // MIN_BLOCK))
    edges = np.linspace(warm_up, n, count + 1).round().astype(int)
    return list(zip(edges[:-1].tolist(), edges[1:].tolist(), strict=True))


@dataclass
class Record:
    """The training samples as the selection sees them: one output's view (:class:`Layout`), breaks, blocks."""

    values: np.ndarray  # (N, columns): column 0 the output modelled, the others what it reads
    breaks: np.ndarray  # sample indices that start a new contiguous run (0 is implied)
    #: the blocks' free runs of prefixes already scored, by the exact bits of what a run depends on
    #: (:func:`_score_prefixes`): a family's degrees at the same lags often rank the same first terms
    runs: dict = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def of(cls, values: np.ndarray, breaks: np.ndarray | list[int] | None = None) -> Record:
        cuts = np.unique(np.asarray([] if breaks is None else breaks, dtype=np.int64))
        values = np.ascontiguousarray(np.asarray(values, dtype=np.float64).reshape(len(values), -1))
        return cls(values, cuts[cuts > 0])

    @property
    def y(self) -> np.ndarray:
        """The output modelled (column 0 of the view)."""
        return self.values[:, 0]

    @property
    def n(self) -> int:
        return len(self.y)

    def valid_rows(self, warm_up: int) -> np.ndarray:
        """Mask of regression rows (row r predicts sample warm_up + r) whose window crosses no break."""
        target = np.arange(warm_up, self.n)
        valid = np.ones(len(target), dtype=bool)
        for b in self.breaks:
            valid &= ~((target >= b) & (target - warm_up < b))
        return valid

    def pieces(self, start: int, stop: int, warm: int) -> list[tuple[int, int]]:
        """(first simulated sample, stop) of each contiguous piece of [start, stop), ``warm`` measured samples before.

        The first piece starts at ``start`` when the samples before it belong to the same
        run (a block simulated from the measured outputs just before it); a piece that
        starts at a break first spends ``warm`` of its own samples as history.
        """
        found = []
        for a, b in runs(start, stop, self.breaks):
            first = a if (a == start and a >= warm and not self._break_in(a - warm, a)) else a + warm
            if b - first > 0:
                found.append((first, b))
        return found

    def simulate(
        self,
        model: TermModel,
        start: int,
        stop: int,
        weights: np.ndarray | None = None,
        bound: float = FREE_RUN_DIVERGENCE_BOUND,
    ) -> Simulation:
        """Free run of samples [start, stop): one run per contiguous piece, each from its measured warm-up
        (``bound``: the scale units from its offset where the output counts as diverged and a run ends)."""
        result = Simulation()
        for measured, y_sim, clipped, diverged in self._free_runs(model, start, stop, weights, bound):
            result.add(measured, y_sim, clipped, diverged, model.layout.n_inputs)
        return result

    def residuals(self, model: TermModel, start: int, stop: int, weights: np.ndarray | None = None) -> np.ndarray:
        """Simulated minus measured over the pieces of [start, stop) that :meth:`simulate` runs (NaN: diverged)."""
        parts = [y_sim - measured for measured, y_sim, _, _ in self._free_runs(model, start, stop, weights)]
        return np.concatenate(parts) if parts else np.empty(0)

    def one_step_residuals(
        self, model: TermModel, start: int, stop: int, weights: np.ndarray | None = None
    ) -> np.ndarray:
        """Predicted minus measured one step ahead over the same pieces as :meth:`residuals`."""
        w = model.weights if weights is None else weights
        warm = model.warm_up
        parts = []
        for first, b in self.pieces(start, stop, warm):
            features, targets = model.regression(self.values[first - warm : b])
            parts.append(features @ w - targets)
        return np.concatenate(parts) if parts else np.empty(0)

    def _free_runs(
        self,
        model: TermModel,
        start: int,
        stop: int,
        weights: np.ndarray | None,
        bound: float = FREE_RUN_DIVERGENCE_BOUND,
    ):
        """(measured, simulated, clipped inputs, diverged) of each contiguous piece of [start, stop)."""
        w = model.weights if weights is None else weights
        warm = model.warm_up
        for first, b in self.pieces(start, stop, warm):
            y_sim, clipped, diverged_at = model.free_run(self.values[first - warm : b], warm, w, bound)
            yield self.y[first:b], y_sim, clipped, diverged_at >= 0

    def _break_in(self, a: int, b: int) -> bool:
        return bool(np.any((self.breaks > a) & (self.breaks <= b)))


@dataclass
class Simulation:
    """Pooled outcome of one or more free runs."""

    squared: float = 0.0
    samples: int = 0
    deviation: float = 0.0  # sum of squares of the measured samples about each run's mean
    clipped: int = 0
    inputs: int = 0
    diverged: bool = False

    def add(self, measured: np.ndarray, simulated: np.ndarray, clipped: int, diverged: bool, width: int) -> None:
        self.diverged |= diverged
        self.clipped += clipped
        self.inputs += len(measured) * width
        if not diverged:
            self.squared += float(np.sum((simulated - measured) ** 2))
        self.deviation += float(np.sum((measured - measured.mean()) ** 2))
        self.samples += len(measured)

    @classmethod
    def of_row(cls, row: np.ndarray, width: int) -> Simulation:
        """A group's row of :func:`kernels.simulate_pieces` (or :func:`runs_from_predictions`), inputs ``width``
        per sample."""
        return cls(row[0], int(row[1]), row[2], int(row[3]), int(row[1]) * width, bool(row[4]))

    @property
    def rmse(self) -> float:
        return math.sqrt(self.squared / self.samples) if self.samples and not self.diverged else math.inf

    @property
    def mean_rmse(self) -> float:
        """The score of predicting each run's mean: a model above it is worth nothing."""
        return math.sqrt(self.deviation / self.samples) if self.samples else math.inf

    def problem(self, where: str, strict: bool = True) -> str:
        """What disqualifies this simulation (``""``: nothing); not strict: only divergence and leaving the range."""
        if self.diverged:
            return f"{where} free run diverged"
        if self.clipped > (MAX_CLIPPED_FRACTION if strict else LOOSE_CLIPPED_FRACTION) * self.inputs:
            return f"{where} free run left the training range"
        if strict and self.rmse > self.mean_rmse:
            return f"{where} free run worse than its mean"
        return ""
