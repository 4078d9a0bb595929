"""The free run (simulation) of an identifier with any number of outputs: one path for all.

A single-output :class:`~lenn_ros.core.structure.Identifier` is the case of one output
reading one other column (u); a :class:`~lenn_ros.core.mimo.MimoIdentifier` has one
output per Identifier, each reading the columns its couplings name. Both describe each
output the same way (:class:`OutputRun`: its structure's channels in regressor order,
the columns they are read from, its known linear parts), so both run here:

- every output a functional-link network of one basis: one compiled call
  (:func:`~lenn_ros.core.kernels.free_run`, the package's only simulation loop);
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
    from lenn_ros.core import kernels

    models = [run.model for run in runs]
    compiled = (
        all(getattr(m, "term_exponents", None) is not None and m.basis in kernels.BASIS_CODES for m in models)
        and len({m.basis for m in models}) == 1
    )
    if compiled:
        return _compiled(runs, values, start)
    return _python(runs, values, start)


def _compiled(runs: Sequence[OutputRun], values: np.ndarray, start: int) -> tuple[list[int], int | None]:
    from lenn_ros.core import kernels

    inputs = [run.inputs() for run in runs]
    known = [run.known() for run in runs]
    terms = []
    for run in runs:
        if not run.model.is_initialised:
            run.model._initialise()
        terms.append(run.model.term_exponents())
    width = max(1, max(len(rows) for rows in inputs))
    exponents = np.zeros((sum(len(t[0]) for t in terms), width), dtype=np.int64)
    factors = np.zeros((len(exponents), width + 2))
    row = 0
    for (rows, _branch), run in zip(terms, runs, strict=True):
        exponents[row : row + len(rows), : rows.shape[1]] = rows
        own = run.model.term_factors()
        if len(own):
            factors[row : row + len(rows), : own.shape[1]] = own
        row += len(rows)
    if not factors[:, 0].any():
        factors = factors[:0]
    flat = [entry for rows in inputs for entry in rows]
    flat_known = [entry for rows in known for entry in rows]
    branches = np.concatenate([t[1] for t in terms]).astype(np.int64)
    clipped = np.zeros(len(runs), dtype=np.int64)
    work = np.ascontiguousarray(values, dtype=np.float64)
    diverged_at = kernels.free_run(
        work,
        int(start),
        len(runs),
        np.cumsum([0] + [len(rows) for rows in inputs]).astype(np.int64),
        np.array([e[0] for e in flat], dtype=np.int64),
        np.array([e[1] for e in flat], dtype=np.int64),
        np.array([e[2] for e in flat], dtype=np.float64),
        np.array([e[3] for e in flat], dtype=np.float64),
        np.cumsum([0] + [len(rows) for rows in known]).astype(np.int64),
        np.array([e[0] for e in flat_known], dtype=np.int64),
        np.array([e[1] for e in flat_known], dtype=np.int64),
        np.array([e[2] for e in flat_known], dtype=np.float64),
        np.cumsum([0] + [len(t[0]) for t in terms]).astype(np.int64),
        exponents,
        factors,
        np.ascontiguousarray(np.concatenate([run.model.weights_.reshape(-1) for run in runs]), dtype=np.float64),
        branches,
        int(branches.max(initial=0)) + 1,
        np.array([run.model.output == "tanh" for run in runs]),
        np.array([float(run.model.output_scale) for run in runs]),
        np.array([float(run.structure.output_offset) for run in runs]),
        np.array([float(run.structure.y_offset) for run in runs]),
        np.array([float(run.structure.y_scale) for run in runs]),
        kernels.BASIS_CODES[runs[0].model.basis],
        FREE_RUN_DIVERGENCE_BOUND,
        clipped,
    )
    if work is not values:
        values[:] = work
    return clipped.tolist(), (int(diverged_at) if diverged_at >= 0 else None)


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
