"""The free run (simulation) of an identifier with any number of outputs: one path for all.

A single-output :class:`~lenn_ros.core.structure.Identifier` is the case of one output
reading one other column (u); a :class:`~lenn_ros.core.mimo.MimoIdentifier` has one
output per Identifier, each reading the columns its couplings name. Both describe each
output the same way (:class:`OutputRun`: its structure's channels in regressor order,
the columns they are read from, its known linear parts), so both run here:

- every output a functional-link network of one basis: one compiled call
  (:func:`~lenn_ros.core.term_kernels.free_run`, the package's only simulation loop);
- otherwise (an MLP): one sample at a time in Python, every output predicted before
  any is fed back, with the same inputs, clipping and divergence bound.

Why one path: the two identifiers had a Python and a compiled free run each, and the
copies had started to disagree (issue 19).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: a free-run output further than this many scale units from the offset is divergence:
#: the network's inputs span one unit each side, so ten is far beyond any output it was
#: built for (a model that only saturates at the clipped inputs shows as clipped inputs)
FREE_RUN_DIVERGENCE_BOUND = 10.0


@dataclass(frozen=True)
class OutputRun:
    """One output of a free run: its structure and model, its column of ``values`` and those its
    other channels are read from, in its structure's regressor order."""

    structure: Any  # a ModelStructure: input_channels(), known_parts(), output_offset, y_offset, y_scale
    model: Any
    column: int
    others: tuple[int, ...]

    def inputs(self) -> list[tuple[int, int, float, float]]:
        """(column, lag, offset, scale) of each network input, in regressor order."""
        columns = (self.column, *self.others)
        channels = self.structure.input_channels()
        return [
            (columns[c], lag, offset, scale) for c, (lags, offset, scale) in enumerate(channels) for lag in range(lags)
        ]

    def known(self) -> list[tuple[int, int, float]]:
        """(column, lag, weight) of each known linear term: the output's own lags first, then each channel's."""
        columns = (self.column, *self.others)
        return [
            (columns[c], lag, float(weight))
            for c, weights in enumerate(self.structure.known_parts())
            for lag, weight in enumerate(weights)
        ]


def free_run_outputs(runs: Sequence[OutputRun], values: np.ndarray, start: int) -> tuple[list[int], int | None]:
    """Simulate every run's column of ``values`` (N, columns) from ``start`` on, in place.

    The rows before ``start`` seed the history; the other columns are read as measured.
    Returns (clipped network inputs per output, first diverged row or None); every
    output from a diverged row on is NaN.
    """
    from lenn_ros.core import term_kernels

    models = [run.model for run in runs]
    compiled = (
        all(getattr(m, "term_exponents", None) is not None and m.basis in term_kernels.BASIS_CODES for m in models)
        and len({m.basis for m in models}) == 1
    )
    if compiled:
        return _compiled(runs, values, start)
    return _python(runs, values, start)


def _compiled(runs: Sequence[OutputRun], values: np.ndarray, start: int) -> tuple[list[int], int | None]:
    outputs = []
    for run in runs:
        if not run.model.is_initialised:
            run.model._initialise()
        exponents, branch = run.model.term_exponents()
        inputs, known = run.inputs(), run.known()
        outputs.append(
            OutputArrays(
                source=np.array([e[0] for e in inputs], dtype=np.int64),
                lag=np.array([e[1] for e in inputs], dtype=np.int64),
                offset=np.array([e[2] for e in inputs], dtype=np.float64),
                scale=np.array([e[3] for e in inputs], dtype=np.float64),
                exponents=exponents,
                factors=run.model.term_factors(),
                branch=branch,
                known=known,
                tanh=run.model.output == "tanh",
                output_scale=float(run.model.output_scale),
                constant=float(run.structure.output_offset),
                y_offset=float(run.structure.y_offset),
                y_scale=float(run.structure.y_scale),
            )
        )
    work = np.ascontiguousarray(values, dtype=np.float64)
    weights = np.concatenate([run.model.weights_.reshape(-1) for run in runs])
    clipped, diverged_at = CompiledRun.of(outputs, runs[0].model.basis).run(work, start, weights)
    if work is not values:
        values[:] = work
    return clipped.tolist(), (diverged_at if diverged_at >= 0 else None)


@dataclass(frozen=True)
class OutputArrays:
    """One output of a compiled free run as arrays: its network inputs (a column of the values, a lag,
    an offset and a scale each), its terms (exponent and factor rows, each term's branch), its known
    linear part ((column, lag, weight) each) and how its network's sum becomes the output."""

    source: np.ndarray
    lag: np.ndarray
    offset: np.ndarray
    scale: np.ndarray
    exponents: np.ndarray
    factors: np.ndarray  # (terms, inputs + 2), or no rows
    branch: np.ndarray | None = None  # each term's branch (None: all in branch 0)
    known: Sequence[tuple[int, int, float]] = ()
    tanh: bool = False
    output_scale: float = 1.0
    constant: float = 0.0
    y_offset: float = 0.0
    y_scale: float = 1.0


@dataclass(frozen=True)
class CompiledRun:
    """:func:`~lenn_ros.core.term_kernels.free_run`'s arguments for some outputs, packed once.

    The one place that packs them: an identifier's free run (:func:`free_run_outputs`) and
    ``fit``'s term models (``termmodel.simulate_joint``, and a refinement's hundreds of free
    runs of one model, where the packing costs as much as a 300-sample run) both build one.
    """

    head: tuple  # the kernel's arguments between ``start`` and the weights
    tail: tuple  # ... between the weights and the divergence bound
    n_y: int

    @classmethod
    def of(cls, outputs: Sequence[OutputArrays], basis: str) -> CompiledRun:
        """Every output's arrays side by side; one basis for all (the kernel's)."""
        from lenn_ros.core import term_kernels

        width = max(1, *(len(o.source) for o in outputs))
        n_terms = [len(o.exponents) for o in outputs]
        exponents = np.zeros((sum(n_terms), width), dtype=np.int64)
        factors = np.zeros((len(exponents), width + 2))
        branches = np.zeros(len(exponents), dtype=np.int64)
        row = 0
        for o, count in zip(outputs, n_terms, strict=True):
            exponents[row : row + count, : o.exponents.shape[1]] = o.exponents
            if len(o.factors):
                factors[row : row + count, : o.factors.shape[1]] = o.factors
            if o.branch is not None:
                branches[row : row + count] = o.branch
            row += count
        if not factors[:, 0].any():  # no term has a factor: the kernel's polynomial-only plan
            factors = factors[:0]
        known = [entry for o in outputs for entry in o.known]

        def starts(counts: list[int]) -> np.ndarray:
            return np.cumsum([0, *counts]).astype(np.int64)

        head = (
            len(outputs),
            starts([len(o.source) for o in outputs]),
            np.concatenate([o.source for o in outputs]).astype(np.int64),
            np.concatenate([o.lag for o in outputs]).astype(np.int64),
            np.concatenate([o.offset for o in outputs]).astype(np.float64),
            np.concatenate([o.scale for o in outputs]).astype(np.float64),
            starts([len(o.known) for o in outputs]),
            np.array([e[0] for e in known], dtype=np.int64),
            np.array([e[1] for e in known], dtype=np.int64),
            np.array([e[2] for e in known], dtype=np.float64),
            starts(n_terms),
            exponents,
            np.ascontiguousarray(factors),
        )
        tail = (
            branches,
            int(branches.max(initial=0)) + 1,
            np.array([o.tanh for o in outputs], dtype=np.bool_),
            np.array([o.output_scale for o in outputs], dtype=np.float64),
            np.array([o.constant for o in outputs], dtype=np.float64),
            np.array([o.y_offset for o in outputs], dtype=np.float64),
            np.array([o.y_scale for o in outputs], dtype=np.float64),
            term_kernels.BASIS_CODES[basis],
        )
        return cls(head, tail, len(outputs))

    def run(
        self, values: np.ndarray, start: int, weights: np.ndarray, bound: float = FREE_RUN_DIVERGENCE_BOUND
    ) -> tuple[np.ndarray, int]:
        """Simulate ``values`` (contiguous float64, [y, u] per sample) in place from ``start`` with the outputs'
        ``weights`` end to end: (clipped inputs per output, first diverged sample or -1)."""
        from lenn_ros.core import term_kernels

        clipped = np.zeros(self.n_y, dtype=np.int64)
        weights = np.ascontiguousarray(weights, dtype=np.float64)
        diverged_at = term_kernels.free_run(values, int(start), *self.head, weights, *self.tail, bound, clipped)
        return clipped, int(diverged_at)


def _python(runs: Sequence[OutputRun], values: np.ndarray, start: int) -> tuple[list[int], int | None]:
    """The free run one sample at a time: each output's known part, then its network on the clipped inputs."""
    inputs = [run.inputs() for run in runs]
    known = [run.known() for run in runs]
    bounds = [FREE_RUN_DIVERGENCE_BOUND * float(run.structure.y_scale) for run in runs]
    clipped = [0] * len(runs)
    outputs = np.empty(len(runs))
    for k in range(start - 1, len(values) - 1):
        for j, run in enumerate(runs):
            x = np.array([[(values[k - lag, c] - offset) / scale for c, lag, offset, scale in inputs[j]]])
            clipped[j] += int(np.count_nonzero(np.abs(x) > 1.0))
            linear = float(run.structure.output_offset)
            for c, lag, weight in known[j]:
                linear = linear + weight * values[k - lag, c]
            outputs[j] = float(linear + run.model.predict(np.clip(x, -1.0, 1.0))[0])
        for j, run in enumerate(runs):
            if not math.isfinite(outputs[j]) or abs(outputs[j] - run.structure.y_offset) > bounds[j]:
                values[k + 1 :, [r.column for r in runs]] = np.nan
                return clipped, k + 1
        for j, run in enumerate(runs):
            values[k + 1, run.column] = outputs[j]
    return clipped, None


def identifier_free_run(
    identifier: Any, u: np.ndarray, y: np.ndarray, start: int, seeds_signed: bool = False
) -> np.ndarray:
    """:meth:`Identifier.free_run <lenn_ros.core.structure.Identifier.free_run>` (see there; ``identifier`` is
    one, not imported: it imports this module): the one output's run through :func:`free_run_outputs`, its
    clipped inputs counted and its outcome kept in ``last_free_run``."""
    u = np.asarray(u, dtype=np.float64)
    structure = identifier.structure
    window = structure.warm_up
    if start < window:
        raise ValueError(f"free run needs {window} samples of history before it starts")
    values = np.column_stack([np.asarray(y, dtype=np.float64), u])
    read_abs = structure.y_abs and not seeds_signed  # |y| measured in, |y^| out
    if read_abs:
        values[:start, 0] = identifier.signed(u[:start], values[:start, 0])
    clipped, diverged_at = free_run_outputs([OutputRun(structure, identifier.model, 0, (1,))], values, int(start))
    identifier.counters["clipped_free_run"] += clipped[0]
    identifier.last_free_run = {
        "samples": len(u) - start,
        "clipped_inputs": clipped[0],
        "diverged": diverged_at is not None,
        "diverged_at": diverged_at,
    }
    return np.abs(values[start:, 0]) if read_abs else values[start:, 0]
