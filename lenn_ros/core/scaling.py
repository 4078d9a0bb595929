"""Offsets and scale factors from training data, so any signal meets the LeNN's [-1, 1].

The Legendre recursion is only bounded on [-1, 1]; the paper picks a scale factor SF
by hand per example. Real data sit anywhere (a heat exchanger at 98 degrees, a buck
converter at 15 V), so ``lenn-ros fit`` centres each signal on the middle of its
training range and scales the half-range plus a margin onto 1: the training data
land in [-1 / (1 + margin), 1 / (1 + margin)] and a test signal may exceed the seen
range by ``margin`` before its inputs are clipped (and counted).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: headroom beyond the training range, as a fraction of its half-width
DEFAULT_MARGIN = 1.0


@dataclass(frozen=True)
class Scaling:
    """Network input = (signal - offset) / scale, for y and for u."""

    y_offset: float
    y_scale: float
    u_offset: float
    u_scale: float
    margin: float = DEFAULT_MARGIN

    @classmethod
    def from_training(cls, u: np.ndarray, y: np.ndarray, margin: float = DEFAULT_MARGIN) -> Scaling:
        """Centre and half-range of each training signal, widened by ``margin``."""
        (y_offset, u_offset), (y_scale, u_scale) = ranges(np.column_stack([y, u]), ("y", "u"), margin)
        return cls(y_offset, y_scale, u_offset, u_scale, margin)

    def outside(self, u: np.ndarray, y: np.ndarray) -> dict[str, int]:
        """How many samples of u and y fall outside [-1, 1] once scaled (they will be clipped)."""
        return {
            "u": int(np.count_nonzero(np.abs((np.asarray(u) - self.u_offset) / self.u_scale) > 1.0)),
            "y": int(np.count_nonzero(np.abs((np.asarray(y) - self.y_offset) / self.y_scale) > 1.0)),
        }


def ranges(
    values: np.ndarray, names: tuple[str, ...] | list[str], margin: float = DEFAULT_MARGIN
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(offsets, scales) of each column of ``values``: the centre of its range, and its half-range widened by
    ``margin``. One rule for every channel of every model ``fit`` builds; ValueError naming a constant or
    non-finite column."""
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    values = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
    offsets, scales = [], []
    for column, name in zip(values.T, names, strict=True):
        if column.size == 0 or not np.all(np.isfinite(column)):
            raise ValueError(f"training {name} is empty or holds NaN/inf: clean the data first")
        low, high = float(column.min()), float(column.max())
        if high == low:
            raise ValueError(f"training {name} is constant ({low:g}): nothing to identify; check the --u/--y columns")
        offsets.append((high + low) / 2.0)
        scales.append((high - low) / 2.0 * (1.0 + margin))
    return tuple(offsets), tuple(scales)
