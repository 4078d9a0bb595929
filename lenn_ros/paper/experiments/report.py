"""Results over seeds as the tables print them: mean ± std, spreads, progress bars.

Shared by ``reproduce`` and ``reproduce --beyond`` so both report a row the same way: a
mean or std is None (printed "diverged") as soon as one seed gave no finite figure,
never an average over the seeds that happened to work.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np


def rounded(values: Iterable[float]) -> list[float | None]:
    """Each value to 3 decimals, non-finite ones as None (strict JSON)."""
    return [round(float(v), 3) if np.isfinite(v) else None for v in values]


def mean(values: Sequence[float]) -> float | None:
    """Mean over seeds (3 decimals); None if any seed has no finite value."""
    array = np.asarray(values, dtype=float)
    return round(float(array.mean()), 3) if len(array) and np.all(np.isfinite(array)) else None


def std(values: Sequence[float]) -> float | None:
    """Sample standard deviation over seeds (ddof=1); None below two seeds or with a non-finite one."""
    array = np.asarray(values, dtype=float)
    return round(float(array.std(ddof=1)), 3) if len(array) > 1 and np.all(np.isfinite(array)) else None


def mean_std(mean: float | None, std: float | None, padded: bool = False) -> str:
    """A table cell "mean ± std" (dB); "diverged" when the mean is None."""
    if mean is None:
        return "diverged"
    if std is None:
        return f"{mean:7.2f}" if padded else f"{mean:.2f}"
    return f"{mean:7.2f} ± {std:4.2f}" if padded else f"{mean:.2f} ± {std:.2f}"


def spread(values: Sequence[int | None]) -> str:
    """Median [min–max] of sample counts, saying on how many seeds a count was never reached."""
    if not values:
        return "-"
    known = [v for v in values if v is not None]
    if len(known) < len(values):
        return f"never on {len(values) - len(known)} of {len(values)}" + (f", {spread(known)}" if known else "")
    return f"{np.median(known):g} [{min(known)}–{max(known)}]"
