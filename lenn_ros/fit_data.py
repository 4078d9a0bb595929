"""What ``fit`` reads, apart from how it reads it: the loaded record and the one error type.

A module of its own so that the readers (CSV in :mod:`lenn_ros.fit`, bags in
:mod:`lenn_ros.fit_bag`) share it without importing each other.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np


class FitError(ValueError):
    """Data or options ``fit`` cannot work with; the message names the fix."""


@dataclass
class Data:
    u: np.ndarray
    y: np.ndarray
    source: str  # what was read, for the report
    test_start: int | None = None  # 1-based, recorded in a bag (its test_start topic)
    breaks: list[int] = dataclasses.field(default_factory=list)  # 0-based samples that start a new run (gaps)
    index: np.ndarray | None = None  # a bag's sample indices, as the node counts them (--test-from is one)
    interpretation: dict[str, Any] = dataclasses.field(default_factory=dict)  # node values: types, fields, pairing
