"""The gap rule, written once: where a record of samples breaks into runs.

A sample index that is not one more than the one before (a lost message, a stalled
publisher, a grid point without a new measurement) is a gap; a sample whose u or y is not a
number (a refused value, an unreadable field) is a break too. Nothing joins the samples on
either side of one: the identifier restarts its regressor history there (live, when an
index jumps: :meth:`lenn_ros.core.structure.Identifier.step`), a batch pass and a free run
restart after it, and ``fit`` never fits a row whose window crosses it. Every offline path
(evaluate, fit, the twin's and ``load_model``'s free runs) asks this module, and what a gap is in
each pairing mode is said in its words here (:func:`describe_gaps`).
"""

from __future__ import annotations

import math

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


#: What missing sample indices mean in each pairing mode: only in ``sequence`` are they lost messages
#: (publication numbers skipped); on a grid they are time in which no new y_p came, a stall.
GAP_CAUSES = {
    "sequence": "lost: their messages never arrived (publication sequence numbers skipped) or found no partner",
    "stamp": "a stall or lost halves: no u / y_p pair within slop formed in that time",
    "sample": "a stall, not a loss: no new measurement arrived in that time (its publisher paused, unless over "
    "BEST_EFFORT every message of that time was lost)",
}


def gap_text(pairing: str, missing: int, seconds: float | None = None) -> str:
    """One gap (or the longest of several) in words: its length in samples and seconds, and what it is."""
    length = f"{missing} sample{'s' if missing != 1 else ''}"
    if seconds is not None and math.isfinite(seconds):
        length += f", {seconds:.3f} s without a sample"
    return f"{length}: {GAP_CAUSES.get(pairing, GAP_CAUSES['sequence'])}"


def describe_gaps(index: np.ndarray, pairing: str, sample_period: float = 0.0) -> list[str]:
    """The missing sample indices of a run (``evaluate``), in lines: how many, in how many gaps, the
    longest (in seconds too on a grid) and what they are in this pairing mode, a stall or lost messages."""
    index = np.asarray(index, dtype=np.int64)
    if index.size == 0:
        return []
    lines = []
    if index[0] > 1:
        lines.append(f"the samples start at index {index[0]}: the {index[0] - 1} before it are not in the recording")
    steps = np.diff(index)
    gaps = steps[steps > 1] - 1
    if gaps.size:
        longest = int(gaps.max())
        seconds = (longest + 1) * sample_period if pairing == "sample" and sample_period > 0 else None
        lines.append(
            f"{int(gaps.sum())} sample indices missing in {gaps.size} gap{'s' if gaps.size != 1 else ''}, "
            f"the longest {gap_text(pairing, longest, seconds)}"
        )
    return lines


def split_row(numbered: np.ndarray, k: int) -> int:
    """The split of a record at sample number ``k``: the 0-based row of the first sample numbered ``k`` or above,
    every row before it numbered below ``k`` (``--test-from K`` in fit and evaluate alike).

    ``ValueError`` with the reason, in words a message can follow with its fix, when no sample would come before
    ``k`` or none from it, and when the numbering starts again (a publisher's restart) so that samples numbered
    below ``k`` follow it: no split honours ``k`` then, and it is never moved.
    """
    numbered = np.asarray(numbered, dtype=np.int64)
    first, last = int(numbered.min()), int(numbered.max())
    if not first < k <= last:
        raise ValueError(
            f"is outside the samples, numbered {first}..{last}: K must be in {first + 1}..{last} "
            "(samples numbered below K are learnt from, K.. scored)"
        )
    row = int(np.argmax(numbered >= k))
    later = np.flatnonzero(numbered[row:] < k)
    if later.size:
        again = row + int(later[0])
        raise ValueError(
            f"the numbering starts again after sample {int(numbered[again - 1])} (a restart), so samples numbered "
            f"below K follow sample {int(numbered[row])}: no split honours it"
        )
    return row
