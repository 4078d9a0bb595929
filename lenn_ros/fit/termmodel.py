"""One output's model as ``fit`` builds it: what it reads, its terms and weights, and its compiled free run.

A :class:`Layout` says what one output's model reads (its *view*: the output, then the
signals it reads, each at some lags, scaled); a :class:`TermModel` is the selected terms
over it with their weights, whatever family they came from; :class:`JointRun` packs one or
several of them for the compiled free run (one output's, or several outputs' simulated
together). A module apart from the selection: refinement, scoring, export and the dead-time
and sign steps use the model, not how it was chosen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lenn_ros.core.expansions import checked_factors, format_terms, term_features
from lenn_ros.core.free_run import FREE_RUN_DIVERGENCE_BOUND, CompiledRun, OutputArrays
from lenn_ros.core.scaling import Scaling
from lenn_ros.core.structure import ModelStructure


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
