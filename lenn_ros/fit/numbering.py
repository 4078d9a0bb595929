"""The samples' numbers, as the user counts them: what ``--test-from`` means and what the report names.

One numbering for the node, ``fit``, ``evaluate``, ``import-csv`` and every report: a sample's
number is the node's (a bag's sample index, :attr:`Data.index <lenn_ros.fit.data.Data.index>`) or
a CSV's 1-based data row (a row missing a cell is a gap and keeps its number). The procedure
works on the rows of the record it holds, which are not the numbers once a sample is missing or a
rule left rows out; so every number a user reads or gives goes through here, at the boundary, and
nowhere else: ``--test-from K`` (and a bag's recorded ``test_start``) becomes the first test row,
and a row becomes the number the report names. A record whose rows are its numbers (a CSV without
missing rows, a bag without gaps from sample 1) reads exactly as it did when rows were all there was.

The split is honoured exactly or refused in one line: samples numbered below K build the model,
those numbered K and above score it; where K falls in a gap, the first scored sample is the next one
and the report says which.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lenn_ros.core.runs import split_row
from lenn_ros.fit.data import Data, FitError


def numbers(data: Data) -> np.ndarray:
    """Each row's sample number: the record's own (a bag's indices, a CSV's kept rows) or its 1-based rows."""
    return data.index if data.index is not None else np.arange(1, len(data.y) + 1)


def number(data: Data, row: int) -> int:
    """The sample number of 0-based ``row``."""
    return int(data.index[row]) if data.index is not None else int(row) + 1


def span(data: Data, first: int, last: int) -> str:
    """``"A..B"``: the numbers of 0-based rows ``first`` .. ``last`` (both included)."""
    return f"{number(data, first)}..{number(data, last)}"


def first_test_row(data: Data, test_from: int | None, recorded: bool = False) -> int:
    """0-based row of the first sample numbered ``test_from`` or above; every row before it is numbered below.

    Refused in one line (:class:`FitError`) when no sample would build the model or none would score it, and
    when the numbering starts again (a publisher's restart) so that samples numbered below K follow K.
    ``recorded``: K is the bag's recorded ``test_start``, not the user's ``--test-from``.
    """
    if test_from is None:
        raise FitError("pass --test-from K: the number of the first test sample (samples numbered below K build the "
                       "model; a CSV's are its data rows from 1, a bag's the node's sample indices)")  # fmt: skip
    asked = f"the recorded test start {test_from}" if recorded else f"--test-from {test_from}"
    try:
        return split_row(numbers(data), test_from)
    except ValueError as reason:
        fix = "; pass --test-from K" if recorded else ("; fit the runs apart" if "again" in str(reason) else "")
        joined = " " if str(reason).startswith("is ") else ": "
        raise FitError(f"{asked}{joined}{reason}{fix}") from None


def split_numbers(data: Data, start: int, test_from: int) -> dict[str, Any]:
    """The numbers of the training samples and of the first test sample (0-based row ``start``), where they are not
    what the rows say: {} when the training samples are numbered 1..start and the first test sample is K."""
    found = {"train": [number(data, 0), number(data, start - 1)], "first_test": number(data, start)}
    return {} if found == {"train": [1, start], "first_test": test_from} else found


def split_line(test_from: int, train: int, tested: int, numbered: dict[str, Any]) -> str:
    """The report's split: what was built on and what scored, by number (``numbered``: :func:`split_numbers`).

    "built on samples 1..3000, tested on 934 samples from 3001"; with numbers missing among the training
    samples their count too, and where K fell in a gap, which sample the test part starts at.
    """
    if not numbered:
        return f"built on samples 1..{train}, tested on {tested} samples from {test_from}"
    first, last = numbered["train"]
    built = f"samples {first}..{last}" if last - first + 1 == train else f"{train} samples numbered {first}..{last}"
    start = numbered["first_test"]
    shown = str(test_from) if start == test_from else f"{test_from} (the first is sample {start})"
    return f"built on {built}, tested on {tested} samples from {shown}"
