"""What ``fit`` reads, apart from how it reads it: the loaded record and the one error type.

A module of its own so that the readers (CSV in :mod:`lenn_ros.fit.load`, bags in
:mod:`lenn_ros.fit.bag`) share it without importing each other. One record type for
any number of channels.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

#: what ``fit -o DIR`` writes besides params.yaml and weights.npz: the report, as ``--json`` prints it;
#: ``lenn_ros.load_model``, the twin and ``evaluate`` read its residual statistics
REPORT_FILE = "fit.json"


class FitError(ValueError):
    """Data or options ``fit`` cannot work with; the message names the fix."""


@dataclass(frozen=True)
class RecordPart:
    """One file of several given to ``fit`` (:mod:`~lenn_ros.fit.records`): where its samples lie in the joined
    record and what they are for. ``role``: ``"build"`` (fitted and selected on) or ``"test"`` (scored only);
    ``first``: the 0-based row of its first sample; ``numbers``: its first and last samples' numbers in the joined
    record (what the report's other lines name), ``shift`` what was added to the record's own numbers to give
    them (0 where they run on from the record before); ``source``: what was read, as one record's report says it."""

    name: str
    role: str
    first: int
    samples: int
    numbers: tuple[int, int]
    source: str
    shift: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "role": self.role, "samples": self.samples, "numbers": list(self.numbers),
                "shift": self.shift, "source": self.source}  # fmt: skip


@dataclass
class Data:
    """Paired samples of any number of channels: ``u`` (N,) or (N, n_u), ``y`` (N,) or (N, n_y).

    ``breaks``: 0-based rows that start a new contiguous run (gaps in a bag's record, never
    joined across by the fit). ``index``: each row's sample number where it is not the row
    (:mod:`~lenn_ros.fit.numbering`): a bag's sample indices as the node counts them, a CSV's
    data rows once a row missing a cell was dropped; ``--test-from`` is one of these numbers,
    and so is ``test_start``, the one a bag recorded (its ``test_start`` topic). ``interpretation``:
    the node values that say how the bag's topics became these samples (types, fields, names,
    pairing, sample period), written into the params file; empty for a CSV. ``u_names`` /
    ``y_names``: the channels' names (default ``u``, ``y``, or ``u0``, ``u1``...). ``sample_period``: seconds
    between samples where the data say it (a CSV's time column), else None. ``records``: the files this record
    was joined from, each a run of its own (:mod:`~lenn_ros.fit.records`); empty for one file.
    """

    u: np.ndarray
    y: np.ndarray
    source: str  # what was read, for the report
    test_start: int | None = None  # the first test sample's number, recorded in a bag (its test_start topic)
    breaks: list[int] = dataclasses.field(default_factory=list)
    index: np.ndarray | None = None
    interpretation: dict[str, Any] = dataclasses.field(default_factory=dict)
    u_names: tuple[str, ...] = ()
    y_names: tuple[str, ...] = ()
    sample_period: float | None = None
    records: tuple[RecordPart, ...] = ()

    def __post_init__(self) -> None:
        self.u, self.y = np.asarray(self.u, dtype=np.float64), np.asarray(self.y, dtype=np.float64)
        for side, given in (("u", self.u_names), ("y", self.y_names)):
            count = self.n_u if side == "u" else self.n_y
            names = tuple(given) or ((side,) if count == 1 else tuple(f"{side}{i}" for i in range(count)))
            if len(names) != count:
                raise FitError(f"{len(names)} {side} names for {count} {side} channels")
            setattr(self, f"{side}_names", names)

    @property
    def n_u(self) -> int:
        return 1 if self.u.ndim == 1 else self.u.shape[1]

    @property
    def n_y(self) -> int:
        return 1 if self.y.ndim == 1 else self.y.shape[1]

    def matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """(u, y) with one column per channel: (N, n_u), (N, n_y)."""
        return self.u.reshape(len(self.u), -1), self.y.reshape(len(self.y), -1)

    def kept(self, keep: np.ndarray) -> Data:
        """The rows where ``keep``: a gap (a break) after each run of rows dropped, the breaks before kept, and
        ``index`` the kept rows' sample numbers (1-based rows where there was none), so that ``--test-from`` still
        counts every row. Itself where every row is kept."""
        if keep.all():
            return self
        rows = np.flatnonzero(keep)
        old = {int(np.searchsorted(rows, b)) for b in self.breaks if b < len(keep)}
        dropped = {int(i) + 1 for i in np.flatnonzero(np.diff(rows) > 1)}
        index = self.index[keep] if self.index is not None else rows + 1
        return dataclasses.replace(self, u=self.u[keep], y=self.y[keep], breaks=sorted(old | dropped), index=index)
