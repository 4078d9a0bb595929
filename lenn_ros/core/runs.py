"""The gap rule, written once: where a record of samples breaks into runs.

A sample index that is not one more than the one before (a lost message, a stalled
publisher, a grid point without a new measurement) is a gap; a sample whose u or y is not a
number (a refused value, an unreadable field) is a break too. Nothing joins the samples on
either side of one: the identifier restarts its regressor history there (live, when an
index jumps: :meth:`lenn_ros.core.structure.Identifier.step`), a batch pass and a free run
restart after it, and ``fit`` never fits a row whose window crosses it. Every offline path
(evaluate, fit, the twin's and ``load_model``'s free runs) asks this module.
"""

from __future__ import annotations

import numpy as np


def finite_rows(values: np.ndarray) -> np.ndarray:
    """Per sample (row): every channel a number. A 1-D series is one channel."""
    return np.isfinite(np.asarray(values, dtype=np.float64)).reshape(len(values), -1).all(axis=1)


def breaks(index: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """0-based rows (never row 0) that start a new run: after a gap in ``index``, or at or after an invalid row."""
    index = np.asarray(index, dtype=np.int64)
    joined = np.diff(index) == 1
    if valid is not None:
        joined &= valid[1:] & valid[:-1]
    return np.flatnonzero(~joined) + 1


def runs(index: np.ndarray, valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(starts, stops) of the runs :func:`breaks` cuts a record into (an invalid row is a run of its own)."""
    cuts = breaks(index, valid)
    return np.r_[0, cuts], np.r_[cuts, len(index)]


def missing(index: np.ndarray) -> tuple[int, int]:
    """(gaps, sample indices missing in them) between the first sample and the last."""
    steps = np.diff(np.asarray(index, dtype=np.int64))
    return int(np.count_nonzero(steps > 1)), int(np.sum(np.clip(steps - 1, 0, None)))
