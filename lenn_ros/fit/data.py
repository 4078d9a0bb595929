"""What ``fit`` reads, apart from how it reads it: the loaded record and the one error type.

A module of its own so that the readers (CSV in :mod:`lenn_ros.fit.build`, bags in
:mod:`lenn_ros.fit.bag`) share it without importing each other.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: what ``fit -o DIR`` writes besides params.yaml and weights.npz: the report, as ``--json`` prints it;
#: ``lenn_ros.load_model``, the twin and ``evaluate`` read its residual statistics
REPORT_FILE = "fit.json"


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


@dataclass
class MimoData:
    """Paired samples with one column per channel: ``u`` (N, n_u), ``y`` (N, n_y).

    ``index``: the sample indices as the identifier counts them (a robot bag's, from its
    session; None: rows 1..N, a CSV or an import). Where it skips, the record has a gap,
    a break of the fit (:attr:`breaks`). ``interpretation``: the node values that say how
    the bag's topics became these samples (types, fields, names, pairing), written into
    the params file; empty for a CSV or an ``import-csv`` bag.
    """

    u: np.ndarray
    y: np.ndarray
    u_names: tuple[str, ...]
    y_names: tuple[str, ...]
    source: str
    test_start: int | None = None
    index: np.ndarray | None = None
    interpretation: dict[str, Any] = field(default_factory=dict)

    def sample_index(self) -> np.ndarray:
        """The sample indices (1..N when none were recorded)."""
        return np.arange(1, len(self.y) + 1) if self.index is None else np.asarray(self.index, dtype=np.int64)

    @property
    def breaks(self) -> list[int]:
        """0-based rows that start a new contiguous run: never joined across by the fit."""
        return [int(b) for b in np.flatnonzero(np.diff(self.sample_index()) != 1) + 1]
