"""Long rest in a training record: left out of the fit, so that every block holds motion.

A robot's log starts with its driver up and its controller not yet running, or stands
still for minutes between tasks: the inputs held, the outputs settled. Such a stretch
repeats one equation (the equilibrium) thousands of times and carries nothing else. It
does harm where it fills whole blocks of the selection (:func:`~lenn_ros.fit.record.fold_blocks`):
a block at rest cannot tell candidates apart (its mean predicts it to the noise, so any
model's equilibrium error fails it), and a block that holds the only motion is simulated
by weights fitted to rest alone. On a record that rests for its first 3 000 samples and
moves for 600, ``fit`` simulated the test part at -4 to -15 dB on three seeds of four;
without the rest, at -45 dB on all four.

So a rest stretch longer than half a block is cut to its first REST_HEAD samples (the
equilibrium, kept as rows) and its last REST_TAIL (the history of the motion after it):
the middle becomes a gap, never fitted across, like a missing sample. Only the training
part is cut; the test part and its seeding are as recorded. Shorter rest (a torque held
for a second, a joint stuck by stiction between moves) is the plant's own behaviour and
stays.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lenn_ros.fit.data import Data
from lenn_ros.fit.families import LONGEST_LAGS
from lenn_ros.fit.numbering import number
from lenn_ros.fit.record import MAX_FOLDS, runs

#: every signal within this share of its training range over the stretch: the plant rests
REST_BAND = 0.01
#: the longest lag span a candidate reads
SPAN = LONGEST_LAGS
#: samples kept at the start of a rest stretch (its equilibrium as rows, past any candidate's lags) and at its
#: end (the lags of the first samples that move again)
REST_HEAD = 2 * SPAN
REST_TAIL = SPAN
#: samples each signal is averaged over before the band is applied
SMOOTHING = 16


def rest_stretches(values: np.ndarray, stop: int, breaks: list[int], least: int) -> list[tuple[int, int]]:
    """The stretches [a, b) of rows < ``stop``, at least ``least`` long, in which every column of ``values``,
    averaged over SMOOTHING samples, stays within REST_BAND of its range over those rows; none crosses a break.

    Such a stretch holds a whole chunk of ``least // 2`` rows that stays within the band, so only around
    those chunks (found at once, by their ranges) is a stretch grown row by row: a record that moves costs
    one pass of numpy over its rows."""
    part = _smoothed(values[:stop])
    # plus the running sums' rounding (1e-14 of a signal's size after 50 000 rows): a channel held constant over
    # the whole record has no range, and its average must not break a rest by a hair
    width = REST_BAND * np.ptp(values[:stop], axis=0) + 1e-9 * np.abs(values[:stop]).max(axis=0)
    chunk = max(1, least // 2)
    found: list[tuple[int, int]] = []
    for a, b in runs(0, stop, np.asarray(breaks, dtype=np.int64)):
        count = (b - a) // chunk
        if count < 2:
            continue
        blocks = part[a : a + count * chunk].reshape(count, chunk, -1)
        calm = np.flatnonzero(np.all(np.ptp(blocks, axis=1) <= width, axis=1))
        for c in calm:
            first = a + int(c) * chunk
            if found and found[-1][1] >= first + chunk:
                continue  # inside the stretch already grown
            low, high = blocks[c].min(axis=0), blocks[c].max(axis=0)
            end = first + chunk
            while end < b and np.all(np.maximum(high, part[end]) - np.minimum(low, part[end]) <= width):
                low, high, end = np.minimum(low, part[end]), np.maximum(high, part[end]), end + 1
            begin = first
            while begin > a and np.all(np.maximum(high, part[begin - 1]) - np.minimum(low, part[begin - 1]) <= width):
                low, high, begin = np.minimum(low, part[begin - 1]), np.maximum(high, part[begin - 1]), begin - 1
            if end - begin >= least and not (found and begin < found[-1][1]):
                found.append((begin, end))
    return found


def _smoothed(values: np.ndarray) -> np.ndarray:
    """Each column's mean over SMOOTHING samples centred on each row (the ends: over the rows there are): a
    sensor's noise at rest (a tank's level read to 0.3 % of its range) would otherwise break the band."""
    n = len(values)
    total = np.vstack([np.zeros((1, values.shape[1])), np.cumsum(values, axis=0)])
    low = np.clip(np.arange(n) - SMOOTHING // 2, 0, n)
    high = np.clip(np.arange(n) + SMOOTHING - SMOOTHING // 2, 0, n)
    return (total[high] - total[low]) / (high - low)[:, None]


def without_rest(data: Data, test_from: int) -> tuple[Data, int, dict[str, Any]]:
    """(the record with each long rest of its training part cut to its head and tail, ``test_from`` in it, what
    was done: {} when nothing). A rest is long when it is longer than half a block of the selection."""
    u, y = data.matrices()
    start = test_from - 1
    least = max(REST_HEAD + REST_TAIL + SPAN, start // (2 * MAX_FOLDS))
    found = rest_stretches(np.column_stack([y, u]), start, data.breaks, least)
    if not found:
        return data, test_from, {}
    keep = np.ones(len(y), dtype=bool)
    for a, b in found:
        keep[a + REST_HEAD : b - REST_TAIL] = False
    trimmed = data.kept(keep)
    dropped = int(len(y) - len(trimmed.y))
    longest = max(b - a for a, b in found)
    text = (
        f"the plant rests (every signal within {REST_BAND:.0%} of its training range) in {len(found)} "
        f"stretch{'es' if len(found) > 1 else ''} of the training samples, up to {longest} samples long: "
        f"{dropped} samples in their middles are left out of the fit (gaps), each keeping its first {REST_HEAD} "
        f"and last {REST_TAIL}, so that every block holds motion"
    )
    stretches = [[number(data, a), number(data, b - 1)] for a, b in found]  # by number, as the user counts
    info = {"stretches": stretches, "samples_left_out": dropped, "text": text}
    return trimmed, int(np.count_nonzero(keep[:start])) + 1, info
