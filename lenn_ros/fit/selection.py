"""Structure selection for a functional-link model of real data, judged by simulation.

A functional-link network is linear in its weights, so choosing its structure is
choosing columns of a feature matrix. Each candidate is a *family* of terms at some
lags (:mod:`lenn_ros.fit.families`: polynomials, hinges, increments with friction-like
terms of the velocity), a dictionary built from the training data; orthogonal forward
regression ranks its terms by error-reduction ratio (Billings' FROLS). Up to here this
is FROLS. The difference is how a model is judged: every prefix of every ranked list is
fitted by least squares and *simulated* (free run, the model fed its own outputs), and
the lowest simulation error wins. One-step error rewards models that lean on the
measured past; simulation is what a model is used for.

One held-out tail is a weak judge (a short tail can be simulated well by luck), so the
training samples are cut into contiguous blocks (:func:`fold_blocks`): each block is
simulated from the measured outputs just before it by the weights fitted to all the
other blocks, and the score pools every block's simulation error. A prefix is refused
when any block's simulation diverges, leaves the training range (clipped inputs) or
does worse than the block's mean. The preferred prefix must then pass two checks
before its candidate counts (:func:`soundness_problem`): the weights fitted to all
training samples simulate the whole training record soundly, and they stay bounded
when driven by the training input cut into blocks and shuffled (an input like those
the model was built for, but in an order it has not seen: a model that runs away on it
sits on the edge of stability and will run away on new data). A model that integrates
exactly (:func:`level_free`) is judged there by its increments: an integrating plant
driven by its input in another order leaves the training range as surely.

Degree-1 candidates (linear ARX, and the linear increment form) are always in the grid
and a nonlinear candidate must beat the best linear one by ``NONLINEAR_GAIN`` to be
chosen; among candidates within ``PARSIMONY`` of the lowest score the one with the
fewest terms is chosen, as within a candidate.

Records that are not one contiguous run (gaps in a recording) are handled by
``breaks``: no regression row reaches across a break and every simulation restarts
from the measured outputs after it.
"""

from __future__ import annotations

import hashlib
import itertools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from lenn_ros.core import kernels
from lenn_ros.core.expansions import checked_factors, format_terms, term_features
from lenn_ros.core.free_run import FREE_RUN_DIVERGENCE_BOUND, CompiledRun, OutputArrays
from lenn_ros.core.scaling import Scaling, ranges
from lenn_ros.core.structure import ModelStructure
from lenn_ros.core.threads import side_by_side
from lenn_ros.fit.families import Spec, candidate_specs
from lenn_ros.fit.families.base import Dictionary

#: relative simulation error a term (or a candidate's extra terms) must buy to be kept
PARSIMONY = 0.01
#: a nonlinear candidate is chosen only if its score is below (1 - NONLINEAR_GAIN) x the best linear one's
NONLINEAR_GAIN = 0.03
#: largest share of a block's network inputs its free run may clip before the prefix is refused:
#: the scaling spans the training range plus a margin, so a measured input never clips; a
#: clipped one is the simulated output beyond range and margin, i.e. running away
MAX_CLIPPED_FRACTION = 0.0
#: the same for ``fit``'s fallback selection (``strict=False``)
LOOSE_CLIPPED_FRACTION = 0.01
#: most blocks the training samples are cut into, and the fewest samples a block may hold
MAX_FOLDS = 5
MIN_BLOCK = 60
#: samples of each block a prefix's free run is scored on (from the block's start): a long record's
#: blocks of 8 000 samples cost every prefix 40 000 simulated steps; scoring the first 4 000 of each
#: chose the same models on Bouc-Wen and the Silverbox (2 000 did not on Bouc-Wen), in 0.7x the time
MAX_SCORED = 4000
#: most terms a ranked list offers (FROLS stops there), and at most one term per this many samples. At 40
#: Bouc-Wen's model stopped at 38 terms, still improving on the blocks; 80 took it to 67 (test 6.37e-5 ->
#: 5.60e-5) and changed no other shared set's model
MAX_TERMS = 80
SAMPLES_PER_TERM = 10
#: shuffled-input runs of the stress check, and how many blocks the input is cut into for them
STRESS_RUNS = 3
STRESS_BLOCKS = 10
#: prefixes scored past the best one so far (or, while none passes, from the first) before the rest of a
#: ranked list is left out: on every shared data set no candidate's first usable prefix came later than 12
PATIENCE = 12
#: relative ridge on the normal equations (numerically singular columns must not break a solve)
RIDGE = 1e-10


@dataclass(frozen=True)
class Layout:
    """What one output's model reads: ``lags`` samples of each column of its *view*, scaled.

    A view is a matrix whose column 0 is the output the model predicts and whose other
    columns are the signals it reads besides its own past: the inputs u (and, for a plant
    of several outputs, whatever else that output is given), all measured. Network input
    ``c * lags + i`` is column c at lag i (0: the sample just before the one predicted), as
    (value - offsets[c]) / scales[c]. One output of one input is the view [y, u]: the NARX
    regressor y(k), ..., y(k-L+1), u(k), ..., u(k-L+1). ``names`` name the columns in the
    terms (``y``, ``u``: ``y1*u2``; ``y3``, ``u0``: ``y3_1*u0_2``).
    """

    lags: int
    offsets: tuple[float, ...]
    scales: tuple[float, ...]
    names: tuple[str, ...] = ("y", "u")

    @classmethod
    def of(cls, lags: int, scaling: Scaling) -> Layout:
        """One output of one input: the view [y, u] with ``scaling``'s offsets and scales."""
        return cls(lags, (scaling.y_offset, scaling.u_offset), (scaling.y_scale, scaling.u_scale))

    @property
    def n_columns(self) -> int:
        return len(self.offsets)

    @property
    def n_inputs(self) -> int:
        return self.n_columns * self.lags

    @property
    def warm_up(self) -> int:
        return max(self.lags, 1)

    @property
    def y_offset(self) -> float:
        return self.offsets[0]

    @property
    def y_scale(self) -> float:
        return self.scales[0]

    def with_lags(self, lags: int) -> Layout:
        return Layout(lags, self.offsets, self.scales, self.names)

    def channels(self) -> list[tuple[str, int]]:
        """(name, lags) of each column in regressor order, as terms are written and parsed."""
        return [(name, self.lags) for name in self.names]

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(column, lag, offset, scale) of every network input, as the compiled free runs take them."""
        c, lag = np.divmod(np.arange(self.n_inputs, dtype=np.int64), max(self.lags, 1))
        return c, lag, np.asarray(self.offsets)[c], np.asarray(self.scales)[c]

    def regressors(self, view: np.ndarray, read: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(network inputs x(k), unclipped, and the target: column 0 at k + 1) of every complete regressor.

        ``read``: only those network inputs, in that order (a model that reads a few of a long
        span's hundreds of inputs: the same values, none of the rest written).
        """
        view = np.asarray(view, dtype=np.float64).reshape(len(view), -1)
        n, first = len(view), self.warm_up - 1
        rows = max(n - 1 - first, 0)
        x = np.empty((rows, self.n_inputs if read is None else len(read)))
        if not rows:
            return x, view[self.warm_up :, 0]
        if read is not None:
            for k, entry in enumerate(np.asarray(read, dtype=np.int64).tolist()):
                c, i = divmod(entry, max(self.lags, 1))
                np.subtract(view[first - i : n - 1 - i, c], self.offsets[c], out=x[:, k])
                x[:, k] /= self.scales[c]
            return x, view[self.warm_up :, 0]
        # every input: written in place (a long span's inputs are hundreds of MB), each column's lags divided as
        # one block (a pass per input, as above: 0.13 s against 0.10 s for 455 inputs of 40 000 samples)
        for c in range(self.n_columns):
            for i in range(self.lags):
                np.subtract(view[first - i : n - 1 - i, c], self.offsets[c], out=x[:, c * self.lags + i])
            x[:, c * self.lags : (c + 1) * self.lags] /= self.scales[c]
        return x, view[self.warm_up :, 0]


def siso_view(u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The view [y, u] of one output of one input (:class:`Layout`)."""
    return np.column_stack([np.asarray(y, dtype=np.float64), np.asarray(u, dtype=np.float64)])


@dataclass
class TermModel:
    """y(k+1) = sum_t w_t prod_i P_{e_ti}(x_i(k)) [g_t(b_t + w_t . x(k))], x the layout's scaled lags."""

    layout: Layout
    exponents: np.ndarray
    basis: str = "legendre"
    weights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    factors: np.ndarray | None = None  # (terms, n_inputs + 2) factor rows, None: polynomials only

    def __post_init__(self) -> None:
        self.exponents = np.ascontiguousarray(self.exponents, dtype=np.int64)
        self.factors = checked_factors(self.factors, len(self.exponents), self.layout.n_inputs)

    @property
    def y_lags(self) -> int:
        return self.layout.lags

    @property
    def u_lags(self) -> int:
        return self.layout.lags

    @property
    def structure(self) -> ModelStructure:
        """The node's structure of a model of one output of one input (the view [y, u])."""
        layout = self.layout
        if layout.n_columns != 2:
            raise ValueError("a ModelStructure is one output of one input: this model reads several columns")
        return ModelStructure(
            y_lags=layout.lags,
            u_lags=layout.lags,
            y_scale=layout.scales[0],
            u_scale=layout.scales[1],
            y_offset=layout.offsets[0],
            u_offset=layout.offsets[1],
        )

    @property
    def warm_up(self) -> int:
        return self.layout.warm_up

    @property
    def terms(self) -> list[str]:
        return format_terms(self.exponents, self.layout.channels(), self.factors)

    def with_weights(self, weights: np.ndarray) -> TermModel:
        return TermModel(self.layout, self.exponents, self.basis, np.asarray(weights), self.factors)

    def with_lags(self, lags: int) -> TermModel:
        """The same terms and weights over ``lags`` >= the model's lags of every column (the extra lags unused)."""
        return self._placed(lags, (0,) * self.layout.n_columns)

    def delayed(self, shifts: tuple[int, ...] | list[int]) -> TermModel:
        """The same terms and weights, column c's lag i read at lag i + shifts[c]: a model fitted on a view whose
        inputs were shifted by their dead times (:func:`lenn_ros.fit.delay.shifted`), over the view as
        measured. Its lags grow by the longest shift; the lags before a column's shift are unused."""
        return self._placed(self.layout.lags + max(shifts), tuple(shifts))

    def _placed(self, lags: int, shifts: tuple[int, ...]) -> TermModel:
        old = self.layout.lags
        columns = self.layout.n_columns
        if len(shifts) != columns or min(shifts) < 0 or lags < old + max(shifts):
            raise ValueError(f"a model of lags {old} cannot be written over {lags} with shifts {shifts}")
        where = np.array([c * lags + i + shifts[c] for c in range(columns) for i in range(old)], dtype=np.int64)
        exponents = np.zeros((len(self.exponents), columns * lags), dtype=np.int64)
        exponents[:, where] = self.exponents
        factors = self.factors
        if len(factors):
            wide = np.zeros((len(factors), columns * lags + 2))
            wide[:, :2] = factors[:, :2]
            wide[:, 2 + where] = factors[:, 2:]
            factors = wide
        return TermModel(self.layout.with_lags(lags), exponents, self.basis, np.array(self.weights), factors)

    def inputs(self, view: np.ndarray, read: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(network inputs x(k) clipped to [-1, 1], target y(k+1)) of every complete regressor of ``view``
        (``read``: those inputs only, :meth:`Layout.regressors`)."""
        x, targets = self.layout.regressors(view, read)
        return np.clip(x, -1.0, 1.0, out=x), targets

    def regression(self, view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(features of every complete regressor, target y(k+1)).

        Over the inputs the terms read only: a model of a dozen terms over a 65-lag span of
        seven columns reads a few dozen of its 455 inputs (the same features, bit for bit: the
        expansion visits each term's inputs in order either way).
        """
        factors = self.factors
        read = self.exponents.any(axis=0)
        if len(factors):
            read |= (factors[:, 2:] != 0.0).any(axis=0)
        read = np.flatnonzero(read)
        x, targets = self.inputs(view, read)
        narrow = factors[:, np.concatenate([[0, 1], 2 + read])] if len(factors) else None
        return term_features(x, self.exponents[:, read], self.basis, narrow), targets

    def _packs(self) -> tuple:
        """What a packed free run of this model is made from."""
        return (self.layout, self.exponents, self.factors)

    def free_run(
        self, view: np.ndarray, start: int, weights: np.ndarray | None = None, bound: float = FREE_RUN_DIVERGENCE_BOUND
    ) -> tuple[np.ndarray, int, int]:
        """Compiled simulation of column 0 from ``start`` (measured before it): (y^(start..), clipped, diverged_at).

        The one-output case of :func:`simulate_joint`, every column of the view read in its place."""
        view = np.asarray(view, dtype=np.float64).reshape(len(view), -1)
        w = self.weights if weights is None else weights
        # packed once per view width (a refinement runs hundreds); packed anew when the model has been given other
        # terms or another layout since (the cache keeps the very objects it packed; arrays are never changed in place)
        runs = self.__dict__.setdefault("_runs", {})
        packed_from, packed = runs.get(view.shape[1], ((), None))
        if packed is None or any(a is not b for a, b in zip(packed_from, self._packs(), strict=True)):
            packed = JointRun.of([self], [list(range(view.shape[1]))])
            runs[view.shape[1]] = (self._packs(), packed)
        values, clipped, diverged_at = packed.run(view, start, [w], bound)
        return values[start:, 0], clipped, diverged_at


def forward_regression(features: np.ndarray, targets: np.ndarray, max_terms: int) -> tuple[list[int], list[float]]:
    """Orthogonal forward regression: columns in order of error-reduction ratio.

    Every step scores all remaining columns by the share of the target's energy they
    explain beyond the terms already chosen (Billings' ERR); see :func:`forward_regression_gram`.
    Returns (column order, ERR of each).
    """
    features = np.asarray(features, dtype=np.float64)
    d = np.asarray(targets, dtype=np.float64)
    return forward_regression_gram(features.T @ features, features.T @ d, float(d @ d), max_terms)


def forward_regression_gram(
    gram: np.ndarray, moment: np.ndarray, energy: float, max_terms: int
) -> tuple[list[int], list[float]]:
    """:func:`forward_regression` from the normal equations: Gram-Schmidt in the columns' inner products.

    With A[s, j] = <q_s, f_j> for the orthonormalised chosen columns q_s, a column's
    part orthogonal to them has squared norm G_jj - sum_s A[s, j]^2 and inner product
    with the target c_j - sum_s A[s, j] <q_s, d>: each step costs (columns x chosen)
    instead of a pass over the N samples, and one Gram matrix serves a family's nested
    dictionaries (degree 1 is the start of degree 2's, which is the start of degree 3's).
    """
    n_columns = gram.shape[0]
    energy = energy or 1.0
    diagonal = np.diag(gram).copy()
    alive = diagonal > 1e-12 * max(float(diagonal.max(initial=0.0)), 1e-300)
    residual = diagonal.copy()
    projection = np.array(moment, dtype=np.float64, copy=True)
    inner = np.zeros((min(max_terms, n_columns), n_columns))
    chosen: list[int] = []
    ratios: list[float] = []
    for step in range(min(max_terms, n_columns)):
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.where(alive & (residual > 1e-10 * diagonal), projection**2 / (residual * energy), -1.0)
        best = int(np.argmax(err))
        if err[best] <= 0.0:
            break
        chosen.append(best)
        ratios.append(float(err[best]))
        alive[best] = False
        norm = math.sqrt(residual[best])
        row = (gram[best] - inner[:step, best] @ inner[:step]) / norm
        inner[step] = row
        along = projection[best] / norm
        residual -= row**2
        projection -= row * along
    return chosen, ratios


# -- the record: contiguous runs, blocks ------------------------------------------------------


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


# -- least squares on folds --------------------------------------------------------------------


@dataclass
class Folds:
    """Normal equations of every block's rows, so each fold's system is the total minus one block."""

    blocks: list[tuple[int, int]]
    gram: np.ndarray  # over all valid rows
    moment: np.ndarray
    block_grams: list[np.ndarray]
    block_moments: list[np.ndarray]

    @classmethod
    def of(
        cls, features: np.ndarray, targets: np.ndarray, rows: np.ndarray, blocks, warm_up: int,
        normal: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Folds:  # fmt: skip
        """``rows``: the sample each row predicts; a block drops the rows predicting its samples and the
        ``warm_up`` after it (their regressors hold the block's measured outputs). ``normal``: (Gram, moment)
        of all rows when already at hand (the design's, cut to these columns: half the work otherwise)."""
        grams, moments = [], []
        for a, b in blocks:
            low, high = np.searchsorted(rows, [a, b + warm_up])  # rows come in the order of what they predict
            f = features[low:high]
            grams.append(f.T @ f)
            moments.append(f.T @ targets[low:high])
        gram, moment = normal if normal is not None else (features.T @ features, features.T @ targets)
        return cls(list(blocks), gram, moment, grams, moments)

    def __post_init__(self) -> None:
        # every fold's system at once: the total less each block
        self._fold_grams = self.gram[None] - np.array(self.block_grams)
        self._fold_moments = self.moment[None] - np.array(self.block_moments)
        self._eye = np.eye(len(self.gram))  # sliced for each prefix: a prefix is scored in tens of microseconds

    def all_weights(self, m: int) -> np.ndarray | None:
        """Every fold's least-squares weights of the first ``m`` columns, one row per fold, in one solve."""
        g = self._fold_grams[:, :m, :m]
        ridge = RIDGE * np.maximum(np.trace(g, axis1=1, axis2=2) / m, 1e-300)
        try:
            weights = np.linalg.solve(g + ridge[:, None, None] * self._eye[:m, :m], self._fold_moments[:, :m, None])
        except np.linalg.LinAlgError:
            return None
        return weights[:, :, 0]

    def weights(self, m: int, fold: int | None = None) -> np.ndarray | None:
        """Least-squares weights of the first ``m`` columns without block ``fold`` (None: all rows)."""
        g, v = self.gram[:m, :m], self.moment[:m]
        if fold is not None:
            g, v = g - self.block_grams[fold][:m, :m], v - self.block_moments[fold][:m]
        ridge = RIDGE * max(float(np.trace(g)) / max(m, 1), 1e-300)
        try:
            return np.linalg.solve(g + ridge * np.eye(m), v)
        except np.linalg.LinAlgError:
            return None


# -- candidates --------------------------------------------------------------------------------


@dataclass
class Candidate:
    """One structure tried, with its verdict: every choice ``fit`` makes is one of these."""

    spec: Spec
    dictionary: int  # terms offered
    terms: int = 0  # terms kept (best prefix)
    rmse_validation: float = math.inf  # pooled free-run RMSE over the blocks
    block_rmse: list[float] = field(default_factory=list)
    rejected: str = ""  # why no prefix of this candidate was usable
    model: TermModel | None = None  # the kept terms with the weights of all training samples
    fold_weights: list[np.ndarray] = field(default_factory=list)  # each block's weights (without it)
    note: str = ""  # why it comes first although another scored lower
    refinement: dict | None = None
    fallback: tuple | None = field(default=None, repr=False)  # what :func:`loosen` needs

    @property
    def linear(self) -> bool:
        return self.spec.degree == 1

    @property
    def weights(self) -> int:
        """Weights of the model delivered: the kept terms, and the increment form's pass-through if added."""
        return len(self.model.exponents) if self.model is not None else 0

    def as_dict(self) -> dict:
        return {
            **self.spec.as_dict(),
            "dictionary": self.dictionary,
            "terms": self.terms,
            "weights": self.weights,
            "rmse_free_run_validation": _finite(self.rmse_validation),
            "rmse_free_run_blocks": [_finite(v) for v in self.block_rmse],
            "rejected": self.rejected,
            "note": self.note,
            **({"refinement": self.refinement} if self.refinement else {}),
        }


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def stress_views(record: Record, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """The view with what the output reads (columns 1..) cut into STRESS_BLOCKS blocks and shuffled,
    STRESS_RUNS times (fixed seed); column 0, the output, stays (only its first samples seed a run).

    Each view comes with its seams: the samples where the inputs' history stops being a
    stretch of one run of the record (a block's start, a break carried with its block)."""
    values, n = record.values, record.n
    rng = np.random.default_rng(seed)
    edges = np.linspace(0, n, STRESS_BLOCKS + 1).round().astype(int)
    views = []
    for _ in range(STRESS_RUNS):
        order = rng.permutation(STRESS_BLOCKS)
        shuffled = np.concatenate([values[edges[i] : edges[i + 1], 1:] for i in order])
        seams, position = [], 0
        for i in order:
            a, b = int(edges[i]), int(edges[i + 1])
            inner = record.breaks[(record.breaks > a) & (record.breaks < b)]
            seams.extend([position, *(position + inner - a).tolist()])
            position += b - a
        views.append((np.column_stack([values[:, 0], shuffled]), np.array(sorted(set(seams) - {0}), dtype=np.int64)))
    return views


def terms_reading_output(exponents: np.ndarray, factors: np.ndarray, lags: int) -> np.ndarray:
    """Per term: whether it reads the output fed back (column 0's ``lags`` inputs), by a polynomial or its
    factor (``factors``: rows per term, or none)."""
    reading = exponents[:, :lags].any(axis=1)
    return reading | factors[:, 2 : 2 + lags].any(axis=1) if len(factors) else reading


def reads_outputs(model: TermModel) -> bool:
    """Whether some term reads the output fed back: an input-only model does not."""
    return bool(terms_reading_output(model.exponents, model.factors, model.layout.lags).any())


def shuffled_run(model: TermModel, view: np.ndarray, seams: np.ndarray) -> tuple[int, int]:
    """(clipped, diverged_at or -1) of the free run of a shuffled view, ending outside the training range.

    An input-only model's output at a sample depends on the inputs' last lags alone, so
    wherever those are a stretch of the record the run repeats the in-sample run (which
    :func:`soundness_problem` checked first): only the samples within one warm-up after a
    seam are new, and only those are simulated, each seam's from its own warm-up. A model
    that reads its output is run whole: its state carries the seam's effect on."""
    warm = model.warm_up
    if reads_outputs(model):
        _, clipped, diverged_at = model.free_run(view, warm, bound=TRAINING_RANGE)
        return clipped, diverged_at
    for seam in seams.tolist():
        low, high = max(0, seam - warm), min(len(view), seam + warm)
        if high - low <= warm:
            continue
        _, clipped, diverged_at = model.free_run(view[low:high], warm, bound=TRAINING_RANGE)
        if clipped or diverged_at >= 0:
            return clipped, diverged_at
    return 0, -1


#: where a soundness free run has left the training range: an output further from its offset than its
#: scale (the training range widened by the scaling's margin), where its lags would clip
TRAINING_RANGE = 1.0


def output_rows(model: TermModel) -> np.ndarray:
    """Mask of the terms whose polynomial part reads the fed-back output: of a :func:`level_free` model, its
    pass-through ``y1`` alone (what :func:`widened` rescales and the refinement leaves alone)."""
    return model.exponents[:, : model.layout.lags].any(axis=1)


def level_free(model: TermModel) -> bool:
    """Whether the model integrates exactly: its output level enters only as y(k) passed through.

    Every term that reads the fed-back output reads differences of it (a factor whose
    weights on the output's lags sum to zero: ``lin(y1-y2)``, ``tanh(a*y1-a*y3)``), besides
    ``y1`` itself with weight exactly the output's scale (the increment form's pass-through).
    Shifting the whole output history by c then shifts the prediction by c: the model's
    dynamics are those of its increments, and its level is their sum, wherever it goes.
    """
    lags, exponents, factors = model.layout.lags, model.exponents, model.factors
    unit = np.zeros(exponents.shape[1], dtype=np.int64)
    unit[0] = 1
    plain = factors[:, 0] == 0 if len(factors) else np.ones(len(exponents), dtype=bool)
    through = (exponents == unit).all(axis=1) & plain
    if np.any(output_rows(model) & ~through) or not through.any():
        return False
    if len(factors):
        w = factors[:, 2 : 2 + lags]
        if np.any(np.abs(w.sum(axis=1)) > 1e-9 * np.abs(w).sum(axis=1)):
            return False
    return bool(abs(float(model.weights[through].sum()) - model.layout.y_scale) <= 1e-9 * model.layout.y_scale)


def widened(model: TermModel, width: float) -> TermModel:
    """The same function of a :func:`level_free` model with its output read over ``width`` times its range.

    The output's lags are scaled by ``width`` times more, and the terms reading them (the
    pass-through and the differences' factor weights) take ``width`` times the weight: the
    same prediction wherever the old scaling did not clip, and the output's level clips
    only ``width`` ranges away."""
    layout = model.layout
    lags = layout.lags
    wide = Layout(lags, layout.offsets, (layout.scales[0] * width, *layout.scales[1:]), layout.names)
    factors = np.array(model.factors)
    if len(factors):
        factors[:, 2 : 2 + lags] *= width
    weights = np.array(model.weights, dtype=np.float64)
    weights[output_rows(model)] *= width
    return TermModel(wide, model.exponents, model.basis, weights, factors if len(factors) else None)


#: a level-free model's soundness runs read its output over this many times the training range: its
#: level may go anywhere its increments take it (a joint without gravity, a wheel, a positioning axis)
LEVEL_FREE_WIDTH = 1e6


def increments_problem(model: TermModel, record: Record) -> str:
    """:func:`soundness_problem` of a :func:`level_free` model, judged by its increments.

    An integrating plant driven by its training input in another order goes where that
    order takes it, outside the training range as often as not: the plant itself would
    fail the level's rule. What must stay as the training record had it is the model's
    own dynamics, its increments: on the shuffled input they must stay within the training
    increments' range (widened by the scaling's margin, as the level's range is). Over the
    whole training record, where the level was measured, the free run must still beat the
    mean; only leaving the output's range is no fault of a model that integrates.
    """
    wide = widened(model, LEVEL_FREE_WIDTH)
    whole = record.simulate(wide, 0, record.n, bound=TRAINING_RANGE)
    problem = whole.problem("in-sample")
    if problem:
        return problem
    steps = np.diff(record.y)
    crossing = record.breaks[record.breaks < record.n] - 1
    (offset,), (scale,) = ranges(np.delete(steps, crossing), ("output increments",))
    warm = model.warm_up
    for shuffled, _ in stress_views(record):
        simulated, _, diverged_at = wide.free_run(shuffled, warm, bound=TRAINING_RANGE)
        increments = np.diff(np.concatenate([shuffled[warm - 1 : warm, 0], simulated]))
        if diverged_at >= 0 or not np.all(np.abs(increments - offset) <= TRAINING_RANGE * scale):
            return "free run on the training input shuffled in blocks left the training increments' range"
    return ""


def soundness_problem(
    model: TermModel, record: Record, predictions: tuple[np.ndarray, np.ndarray] | None = None
) -> str:
    """What is wrong with a model fitted to all training samples (``""``: nothing).

    Its free run over the whole training record (each contiguous run from its measured
    start) must stay in the training range and do better than the mean: this is the
    easiest simulation the model will ever face. And driven by the training input
    shuffled in blocks it must stay in the training range: an input like the ones it was
    built for, in an order it has not seen. One seed, fixed, so the verdict is repeatable.

    The inputs of these runs are training samples, so only a fed-back output can clip:
    each run ends at the first output outside the training range (``TRAINING_RANGE``),
    with the verdict a whole run would give. The prefixes that fail here are mostly the
    long ones that overshoot early, and they are tried one after another
    (:func:`_choose_prefix`): stopping there is what keeps that search cheap.

    ``predictions``: (samples, values) of an input-only model's one-step predictions over
    the record's regression rows, which are its in-sample free run (it feeds nothing
    back); given, that run is read from them instead of simulated again.
    """
    if level_free(model):
        return increments_problem(model, record)
    if predictions is not None:
        samples, values = predictions
        pieces = np.array([(a, b, 0) for a, b in record.pieces(0, record.n, model.warm_up)], dtype=np.int64)
        out = np.zeros((1, 5))
        runs_from_predictions(record, model.layout, samples, lambda _g, low, high: values[low:high],
                              tuple(pieces.reshape(-1, 3).T), TRAINING_RANGE, out)  # fmt: skip
        whole = Simulation.of_row(out[0], model.layout.n_inputs)
    else:
        whole = record.simulate(model, 0, record.n, bound=TRAINING_RANGE)
    if whole.diverged or whole.clipped:
        return "in-sample free run left the training range"
    problem = whole.problem("in-sample")
    if problem:
        return problem
    for shuffled, seams in stress_views(record):
        clipped, diverged_at = shuffled_run(model, shuffled, seams)
        if diverged_at >= 0 or clipped > 0:
            return "free run on the training input shuffled in blocks left the training range"
    return ""


@dataclass
class Design:
    """A dictionary's regression over the record: features, the target its terms explain, normal equations."""

    dictionary: Dictionary
    features: np.ndarray
    targets: np.ndarray  # y(k+1), less the pass-through in the increment form
    predicted: np.ndarray  # the sample each row predicts
    gram: np.ndarray
    moment: np.ndarray
    energy: float

    @classmethod
    def of(cls, spec: Spec, record: Record, layout: Layout, inputs: tuple | None = None) -> Design:
        """``inputs``: :func:`valid_inputs` of the spec's lags when already at hand."""
        layout = layout.with_lags(spec.lags)
        x, targets, predicted = inputs if inputs is not None else valid_inputs(record, layout)
        dictionary = spec.dictionary(x)
        # column-major: each candidate gathers its ranked columns (a few dozen of hundreds) as contiguous copies
        features = term_features(x, dictionary.exponents, "legendre", dictionary.factors, order="F")
        targets = targets - dictionary.pass_through(x, layout)
        return cls(dictionary, features, targets, predicted, features.T @ features, features.T @ targets,
                   float(targets @ targets))  # fmt: skip

    def leading(self, dictionary: Dictionary) -> Design | None:
        """This design cut to ``dictionary`` when that is its start (a lower degree of the family), else None."""
        count = len(dictionary.exponents)
        mine = self.dictionary
        if not (
            count <= len(mine.exponents)
            and dictionary.increment == mine.increment
            and np.array_equal(mine.exponents[:count], dictionary.exponents)
            and np.array_equal(mine.factors[:count], dictionary.factors)
        ):
            return None
        return Design(dictionary, self.features[:, :count], self.targets, self.predicted,
                      self.gram[:count, :count], self.moment[:count], self.energy)  # fmt: skip


def evaluate_candidate(spec: Spec, record: Record, layout: Layout, design: Design, strict: bool = True) -> Candidate:
    """Rank the dictionary's terms by FROLS, score every prefix by blocked free runs, keep the preferred sound one.

    ``strict=False`` (``fit``'s fallback, with a warning, when nothing passes) refuses
    only divergence and leaving the range, and skips :func:`soundness_problem`.
    """
    dictionary = design.dictionary
    candidate = Candidate(spec, len(dictionary.exponents))
    base = TermModel(layout.with_lags(spec.lags), dictionary.exponents, "legendre", factors=dictionary.factors)
    warm = base.warm_up
    limit = min(MAX_TERMS, len(dictionary.exponents), max(1, len(design.targets) // SAMPLES_PER_TERM))
    ranked, _ = forward_regression_gram(design.gram, design.moment, design.energy, limit)
    if not ranked:
        candidate.rejected = "no usable term"
        return candidate
    prefixes = Prefixes(base, dictionary, ranked, design, fold_blocks(record.n, warm))
    scores, loose_scores, reasons, loose_reasons = _score_prefixes(prefixes, record)
    _choose_prefix(candidate, prefixes, record, scores if strict else loose_scores,
                   reasons if strict else loose_reasons, strict)  # fmt: skip
    prefixes.design = None  # every prefix scored is gathered; the design (N x all terms) need not outlive this
    candidate.fallback = (prefixes, loose_scores, loose_reasons)
    return candidate


def loosen(candidates: list[Candidate], record: Record) -> list[Candidate]:
    """The candidates again under the loose rules (``fit``'s fallback, with a warning, when none passed).

    Only divergence and leaving the range refuse a prefix, and the soundness check is
    skipped; the prefixes' scores are those already computed, so nothing is simulated again.
    """
    loose = []
    for old in candidates:
        candidate = Candidate(old.spec, old.dictionary)
        if old.fallback is None:
            candidate.rejected = old.rejected
        else:
            prefixes, scores, reasons = old.fallback
            _choose_prefix(candidate, prefixes, record, list(scores), list(reasons), strict=False)
        loose.append(candidate)
    return order_candidates(loose)


@dataclass
class Prefixes:
    """A candidate's ranked terms, and the model each prefix of them makes.

    In the increment form every prefix also holds the pass-through y(k) (the bias and
    ``y1`` with fixed weights): appended as two more terms while prefixes are scored
    (the same function as folding them into equal terms of the prefix), folded in for
    the model delivered (:meth:`Dictionary.with_pass_through`).
    """

    base: TermModel
    dictionary: Dictionary
    ranked: list[int]
    design: Design | None  # where the ranked terms' features are gathered from, while prefixes are scored
    blocks: list[tuple[int, int]]
    #: the first ranked terms' features over the design's rows, and their normal equations per fold
    features: np.ndarray = field(init=False, repr=False)
    folds: Folds = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.predicted = self.design.predicted  # the sample each row predicts
        self._gather(min(len(self.ranked), 2 * PATIENCE))
        d, n = self.dictionary, self.base.layout.n_inputs
        lags = self.base.layout.lags
        reading = terms_reading_output(d.exponents[self.ranked], d.factors[self.ranked], lags)
        #: the prefixes of up to this many terms read no output fed back: input-only (:meth:`input_only`)
        self.reading_from = 0 if d.increment else (int(np.argmax(reading)) if reading.any() else len(reading))
        rows = d.exponents[self.ranked]
        factors = d.factors[self.ranked]
        self.passing = np.zeros(0)
        if d.increment:
            rows = np.vstack([rows, np.zeros((2, n), dtype=np.int64)])
            rows[-1, 0] = 1  # y1; the row before is the bias
            factors = np.vstack([factors, np.zeros((2, n + 2))])
            self.passing = np.array([self.base.layout.y_offset, self.base.layout.y_scale])
        self.rows, self.factor_rows = rows, factors

    def _gather(self, width: int) -> None:
        """The first ``width`` ranked terms' features and folds.

        Gathered as they are needed, not all ranked terms at once: scoring stops PATIENCE
        prefixes past the best, typically near 20 of up to 80, and a gather of 80 columns of a
        40 000-row design into fresh memory was a tenth of a six-joint robot's selection.
        """
        design, columns = self.design, self.ranked[:width]
        self.features = design.features[:, columns]  # column-major: contiguous copies
        normal = (design.gram[np.ix_(columns, columns)], design.moment[columns])
        self.folds = Folds.of(self.features, design.targets, design.predicted, self.blocks, self.base.warm_up, normal)

    def reach(self, m: int) -> None:
        """Gather (doubling) until prefix ``m``'s terms are at hand."""
        if m > self.features.shape[1]:
            self._gather(min(len(self.ranked), max(m, 2 * self.features.shape[1])))

    def arrays(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        """(exponents, factors) of prefix ``m`` as scored (the pass-through appended)."""
        if len(self.rows) == len(self.ranked):  # no pass-through rows: the prefix is the first m rows
            rows, factors = self.rows[:m], self.factor_rows[:m]
        else:
            keep = np.concatenate([np.arange(m), np.arange(len(self.ranked), len(self.rows))])
            rows, factors = self.rows[keep], self.factor_rows[keep]
        return np.ascontiguousarray(rows), factors if factors[:, 0].any() else factors[:0]

    def fold_weights(self, m: int) -> np.ndarray | None:
        """Each block's least-squares weights of prefix ``m`` as scored, one row per block (None: singular)."""
        self.reach(m)
        weights = self.folds.all_weights(m)
        if weights is None or not len(self.passing):
            return weights
        return np.hstack([weights, np.broadcast_to(self.passing, (len(weights), len(self.passing)))])

    def input_only(self, m: int) -> bool:
        """Whether prefix ``m`` reads no output fed back (nor passes y(k) through): its free run from any
        start is its one-step prediction."""
        return m <= self.reading_from

    def in_sample(self, m: int, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(samples, one-step predictions) of prefix ``m`` with ``weights`` over the record when that is its
        in-sample free run (:meth:`input_only`), else None."""
        return (self.predicted, self.features[:, :m] @ weights) if self.input_only(m) else None

    def model(self, m: int, weights: np.ndarray) -> TermModel:
        """The model delivered for prefix ``m`` with its own (least-squares) weights, the pass-through folded in."""
        exponents, factors, weights = self.dictionary.with_pass_through(self.ranked[:m], weights, self.base.layout)
        b = self.base
        return TermModel(b.layout, exponents, b.basis, weights, factors)


def _block_pieces(record: Record, blocks: list[tuple[int, int]], warm: int) -> tuple[np.ndarray, ...]:
    """(first, stop, block) of every piece of every block, as :func:`kernels.simulate_pieces` takes them."""
    found = [
        (first, stop, index)
        for index, (a, b) in enumerate(blocks)
        for first, stop in record.pieces(a, min(b, a + MAX_SCORED), warm)
    ]
    return tuple(np.array([piece[i] for piece in found], dtype=np.int64) for i in range(3))


def _score_prefixes(prefixes: Prefixes, record: Record) -> tuple[list[tuple], list[tuple], list[str], list[str]]:
    """(m, pooled RMSE, per-block RMSE) of every prefix usable under the strict rules, the same under the
    loose ones, and why the others failed under each.

    Each prefix's blocks are simulated in one compiled call (:func:`kernels.simulate_pieces`),
    or for an input-only prefix read from its one-step predictions (:func:`runs_from_predictions`).
    """
    base, blocks = prefixes.base, prefixes.blocks
    warm = base.warm_up
    first, stop, group = _block_pieces(record, blocks, warm)
    width = base.layout.n_inputs
    # a block that clips more than this fails both rules: the blocks after it cannot save the prefix
    clip_limit = LOOSE_CLIPPED_FRACTION * np.bincount(group, stop - first, len(blocks)) * width
    source, lag, offset, scale = base.layout.arrays()
    # what a prefix's block runs depend on besides the record, its terms and weights (the blocks follow from warm)
    scaled = (warm, base.basis, _digest(source, lag, offset, scale))
    scores, loose, reasons, loose_reasons = [], [], [], []
    best_m, lowest = 0, math.inf
    for m in range(1, len(prefixes.ranked) + 1):
        if m > best_m + PATIENCE:
            break  # the ranked list's later terms are what FROLS could least vouch for; none yet: from 0
        weights = prefixes.fold_weights(m)
        if weights is None:
            reasons.append("singular")
            loose_reasons.append("singular")
            continue
        out = np.zeros((len(blocks), 5))
        if prefixes.input_only(m):
            runs_from_predictions(
                record, base.layout, prefixes.predicted,
                lambda g, low, high, m=m, weights=weights: prefixes.features[low:high, :m] @ weights[g, :m],
                (first, stop, group), FREE_RUN_DIVERGENCE_BOUND, out,
            )  # fmt: skip
        else:
            exponents, factors = prefixes.arrays(m)
            key = (scaled, _digest(exponents, factors, weights))
            if (known := record.runs.get(key)) is not None:
                out[:] = known
            else:
                kernels.simulate_pieces(
                    record.values, first, stop, group, warm, source, lag, offset, scale, exponents, factors, weights,
                    kernels.BASIS_CODES[base.basis], FREE_RUN_DIVERGENCE_BOUND, out, clip_limit,
                )  # fmt: skip
                record.runs[key] = out.copy()
        runs_of = [Simulation.of_row(row, width) for row in out]
        pooled = math.sqrt(float(out[:, 0].sum()) / float(out[:, 1].sum()))
        entry = (m, pooled, [run.rmse for run in runs_of])
        for strict, kept, why in ((True, scores, reasons), (False, loose, loose_reasons)):
            failed = next((p for p in (run.problem("held-out", strict=strict) for run in runs_of) if p), "")
            if failed:
                why.append(failed)
            else:
                kept.append(entry)
        if scores and scores[-1] is entry and pooled < lowest:
            best_m, lowest = m, pooled
        elif not scores and loose and loose[-1] is entry and pooled < lowest:
            best_m, lowest = m, pooled  # nothing strict yet: patience counts from the best loose prefix
    return scores, loose, reasons, loose_reasons


def _digest(*arrays: np.ndarray) -> bytes:
    """The exact bits of ``arrays`` (shapes included), as a short key for :attr:`Record.runs`: a long span's
    terms are hundreds of inputs wide, and thousands of prefixes are scored."""
    digest = hashlib.blake2b(digest_size=16)
    for array in arrays:
        digest.update(np.asarray(array.shape, dtype=np.int64).tobytes())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.digest()


def runs_from_predictions(
    record: Record, layout: Layout, samples: np.ndarray, predict: Callable, pieces: tuple, bound: float, out: np.ndarray
) -> None:
    """:func:`kernels.simulate_pieces` of a model that reads no output fed back, from its one-step predictions.

    Such a model's free run of a piece is its one-step prediction of each sample (nothing is
    fed back), so the runs are products of the design's rows: ``predict(g, low, high)`` gives
    those of rows low..high (``samples``: the sample each row predicts, sorted) by group g's
    weights. ``out`` gets what the kernel gives: squared errors, samples, squares about each
    piece's mean, clipped inputs, diverged (further than ``bound`` scales, or non-finite). The
    inputs read are training samples, inside the range, so what clips is the fed-back
    output's lags a term never reads: a sample outside the range is read by the next
    ``lags`` samples of its piece, and each counts it.
    """
    offset, scale = layout.y_offset, layout.y_scale
    for a, b, g in zip(*pieces, strict=True):
        low, high = np.searchsorted(samples, [a, b])
        simulated = predict(g, low, high)
        measured = record.y[a:b]
        if not np.all(np.abs(simulated - offset) <= bound * scale):
            out[g, 4] = 1.0  # non-finite or diverged: the kernel stops there, the block fails
        x = (simulated - offset) / scale
        outside = np.flatnonzero((x > 1.0) | (x < -1.0))
        out[g, 0] += float(np.sum((simulated - measured) ** 2))
        out[g, 1] += b - a
        out[g, 2] += float(np.sum((measured - measured.mean()) ** 2))
        out[g, 3] += float(np.minimum(layout.lags, b - 1 - (a + outside)).sum())


def _choose_prefix(candidate, prefixes: Prefixes, record: Record, scores, reasons, strict: bool) -> None:
    """The fewest terms within PARSIMONY of the lowest score that passes :func:`soundness_problem`."""
    folds = prefixes.folds
    while scores:
        lowest = min(entry[1] for entry in scores)
        preferred = next(entry for entry in scores if entry[1] <= lowest * (1.0 + PARSIMONY))
        m = preferred[0]
        weights = folds.weights(m)
        if weights is None:
            problem = "singular"
        else:
            model = prefixes.model(m, weights)
            problem = soundness_problem(model, record, prefixes.in_sample(m, weights)) if strict else ""
        if not problem:
            candidate.terms, candidate.rmse_validation, candidate.block_rmse = m, preferred[1], preferred[2]
            candidate.fold_weights = [prefixes.model(m, folds.weights(m, f)).weights for f in range(len(folds.blocks))]
            candidate.model = model
            return
        reasons.append(problem)
        scores = [entry for entry in scores if entry is not preferred]
    candidate.rejected = f"every prefix: {'; '.join(sorted(set(reasons)))}" if reasons else "no usable term"


def select_structure(
    record: Record,
    layout: Layout,
    specs: list[Spec] | None = None,
    progress: Callable[[Candidate], None] | None = None,
    workers: int = 1,
) -> list[Candidate]:
    """Every candidate of the grid for the record's output, judged; sorted with the one to use first
    (:func:`order_candidates`). ``layout`` gives the view's scaling and names (its lags are each spec's).

    ``workers``: candidates judged side by side on that many threads (each is independent
    and the kernels release the GIL); the verdicts and ``progress`` come in the grid's order.
    """
    specs = specs if specs is not None else candidate_specs(record.n, layout.n_columns)
    # the designs are built on this thread while the pool judges those already built (building them all
    # first was 1.7 of Bouc-Wen's 9.4 s of selection, with both cores but one idle); they come in the
    # designs' order, and are told in the grid's as soon as each one's predecessors are in
    judged = side_by_side(
        lambda job: evaluate_candidate(job[0], record, layout, job[1]), _designs(specs, record, layout), workers
    )
    done: dict[Spec, Candidate] = {}
    candidates: list[Candidate] = []
    for candidate in judged:
        done[candidate.spec] = candidate
        while len(candidates) < len(specs) and specs[len(candidates)] in done:
            candidates.append(done.pop(specs[len(candidates)]))
            if progress:
                progress(candidates[-1])
    return order_candidates(candidates)


def valid_inputs(record: Record, layout: Layout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(network inputs clipped, target y(k+1), the sample each row predicts) of every regressor of the
    layout's lags whose window crosses no break: what every design over those lags starts from."""
    base = TermModel(layout, np.zeros((1, layout.n_inputs), dtype=np.int64))
    x, targets = base.inputs(record.values)
    valid = record.valid_rows(base.warm_up)
    predicted = np.arange(base.warm_up, record.n)
    if valid.all():  # no break: no copy (a 65-lag view of twelve columns is 250 MB on a 40 000-sample record)
        return x, targets, predicted
    return x[valid], targets[valid], predicted[valid]


def _designs(specs: list[Spec], record: Record, layout: Layout) -> Iterator[tuple[Spec, Design]]:
    """(spec, design) of each spec, as each is built; a family's lower degrees at the same lags reuse its
    highest degree's features.

    The network inputs are built once per lag span, not once per spec: on a 40 000-sample
    record of seven columns, building them was a third of the designs' time."""
    tops: dict[tuple[str, int], Design] = {}
    inputs: dict[int, tuple] = {}
    for spec in sorted(specs, key=lambda s: (s.lags, s.family, -s.degree)):
        if spec.lags not in inputs:
            inputs.clear()  # one span at a time: a long span's inputs are hundreds of MB
            tops.clear()
            inputs[spec.lags] = valid_inputs(record, layout.with_lags(spec.lags))
        top = tops.get((spec.family, spec.lags))
        if top is not None:
            shared = top.leading(spec.dictionary(inputs[spec.lags][0]))
            if shared is not None:
                yield spec, shared
                continue
        design = Design.of(spec, record, layout, inputs[spec.lags])
        tops.setdefault((spec.family, spec.lags), design)
        yield spec, design


def out_of_fold_residuals(candidate: Candidate, record: Record, one_step: bool = False) -> np.ndarray:
    """Errors of ``candidate`` on every block, each block run by the weights fitted without it.

    Free run (what the selection scored the candidate by, kept sample by sample), or
    ``one_step`` ahead: errors of a model on samples it was not fitted to, so their spread
    is an honest uncertainty (``fit``'s bands). Empty when the candidate has no fold weights.
    """
    if candidate.model is None or not candidate.fold_weights:
        return np.empty(0)
    run = record.one_step_residuals if one_step else record.residuals
    blocks = fold_blocks(record.n, candidate.model.warm_up)
    parts = [run(candidate.model, a, b, w) for (a, b), w in zip(blocks, candidate.fold_weights, strict=True)]
    return np.concatenate(parts) if parts else np.empty(0)


def order_candidates(candidates: list[Candidate]) -> list[Candidate]:
    """Sorted by score, then the one to use moved first.

    A nonlinear candidate must beat the best linear one by NONLINEAR_GAIN (linear models
    extrapolate gracefully; a nonlinearity the blocks barely vouch for may not); and of
    the candidates within PARSIMONY of the lowest score the one with the fewest terms is
    used (it has fitted the least noise and has the fewest terms that can run away); the
    increment form's pass-through terms count, as the weights the node will adapt.
    """
    ordered = sorted(candidates, key=lambda c: c.rmse_validation)
    for candidate in ordered:
        candidate.note = ""
    usable = [c for c in ordered if c.model is not None]
    if not usable:
        return ordered
    linear = [c for c in usable if c.linear]
    bar = linear[0].rmse_validation * (1.0 - NONLINEAR_GAIN) if linear else math.inf
    eligible = [c for c in usable if c.linear or c.rmse_validation <= bar] or usable
    best = eligible[0]
    close = [c for c in eligible if c.rmse_validation <= best.rmse_validation * (1.0 + PARSIMONY)]
    chosen = min(close, key=lambda c: (c.weights, c.rmse_validation))
    if chosen is not ordered[0]:
        top = ordered[0]
        chosen.note = f"chosen over {top.spec.label} ({top.rmse_validation:.5g}): " + (
            f"fewest terms within {PARSIMONY:.0%} of the lowest score"
            if top in eligible
            else f"a nonlinear candidate must beat the best linear one by {NONLINEAR_GAIN:.0%}"
        )
        ordered.remove(chosen)
        ordered.insert(0, chosen)
    return ordered


# -- several outputs simulated together --------------------------------------------------------


def simulate_joint(
    models: list[TermModel],
    columns: list[list[int]],
    weights: list[np.ndarray],
    values: np.ndarray,
    start: int,
    bound: float = FREE_RUN_DIVERGENCE_BOUND,
) -> tuple[np.ndarray, int, int]:
    """Free run of several outputs together: output j is ``models[j]``, its view's column c column
    ``columns[j][c]`` of ``values`` (whose first len(models) columns are the outputs, each fed the model's own
    from ``start`` on). Every model over the same lags. (values simulated, clipped inputs, diverged_at or -1;
    an output further than ``bound`` of its scales from its offset diverges and ends the run).
    """
    return JointRun.of(models, columns).run(values, start, weights, bound)


@dataclass
class JointRun:
    """Term models over some columns as one :class:`~lenn_ros.core.free_run.CompiledRun` (the package's one
    packing of the compiled free run's arguments): what :func:`simulate_joint` runs, and what a model refined
    on simulation error reuses for the hundreds of runs of one refinement."""

    packed: CompiledRun

    @classmethod
    def of(cls, models: list[TermModel], columns: list[list[int]]) -> JointRun:
        outputs = []
        for model, where in zip(models, columns, strict=True):
            c, lag, offset, scale = model.layout.arrays()
            outputs.append(
                OutputArrays(
                    source=np.asarray(where, dtype=np.int64)[c], lag=lag, offset=offset, scale=scale,
                    exponents=model.exponents, factors=model.factors,
                    y_offset=float(model.layout.y_offset), y_scale=float(model.layout.y_scale),
                )
            )  # fmt: skip
        return cls(CompiledRun.of(outputs, models[0].basis))

    def run(
        self, values: np.ndarray, start: int, weights: list[np.ndarray], bound: float = FREE_RUN_DIVERGENCE_BOUND
    ) -> tuple[np.ndarray, int, int]:
        """:func:`simulate_joint` with these models: (a copy of ``values`` simulated, clipped inputs,
        diverged_at or -1)."""
        values = np.array(values, dtype=np.float64, copy=True)
        clipped, diverged_at = self.packed.run(values, start, np.concatenate(weights), bound)
        return values, int(clipped.sum()), diverged_at


def joint_block_score(
    candidates: list[Candidate], columns: list[list[int]], values: np.ndarray, breaks: np.ndarray
) -> tuple[float, list[float]]:
    """How several outputs' chosen candidates simulate *together* on the selection's blocks.

    Each block is simulated from the measured outputs just before it, every output by
    its candidate's weights fitted without that block, each fed the others' simulated
    outputs: what a model of several outputs is used for, which each output's own score
    (the others measured, when it reads them) cannot tell. Returns (the outputs' mean
    NMSE pooled over the blocks, each output's NMSE); inf where a block diverges, leaves
    the range or is worse than its mean for some output.
    """
    lags = max(c.model.layout.lags for c in candidates)
    models = [c.model.with_lags(lags) for c in candidates]
    record = Record.of(values, breaks)
    warm = models[0].warm_up
    blocks = fold_blocks(record.n, warm)
    n_y = len(models)
    squared, deviation = np.zeros(n_y), np.zeros(n_y)
    for fold, (a, b) in enumerate(blocks):
        weights = [np.asarray(c.fold_weights[fold]) for c in candidates]
        for first, stop in record.pieces(a, b, warm):
            simulated, clipped, diverged_at = simulate_joint(
                models, columns, weights, values[first - warm : stop], warm
            )
            if diverged_at >= 0 or clipped:
                return math.inf, [math.inf] * n_y
            measured = values[first:stop, :n_y]
            squared += ((simulated[warm:, :n_y] - measured) ** 2).sum(axis=0)
            deviation += ((measured - measured.mean(axis=0)) ** 2).sum(axis=0)
    nmse = squared / np.maximum(deviation, 1e-300)
    if np.any(nmse > 1.0):
        return math.inf, [float(v) for v in nmse]
    return float(np.mean(nmse)), [float(v) for v in nmse]
