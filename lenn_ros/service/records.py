"""Several recordings, one model: ``lenn-ros evaluate bag1 bag2 ...`` (issue 44), each bag a record of its own.

Each bag is read as one is (:func:`~lenn_ros.service.recording.read_recording`) and split where one bag's
evaluate splits it (its frozen phase, its ``test_start``, else its last fifth: the rule of
:mod:`lenn_ros.service.evaluation`). The identifier of the configuration (``--params``, else the first bag's
recorded one, which every other bag's must equal) learns through the build parts of all bags, in the order
given, its history restarted at each bag's start as after a gap (:mod:`lenn_ros.core.runs`); then the frozen
model scores each bag's test part as one bag's evaluate does (one-step, and the free run from the measured
outputs before its test start), and all test parts together (pooled). ``--test-from K`` names no one sample
in several bags and is refused in one line; live parameter changes recorded in the bags are not replayed
across several (said in one line).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros.core.evaluation import Evaluation
from lenn_ros.core.metrics import nmse_db, rmse
from lenn_ros.service import RecordingError
from lenn_ros.service.building import recorded_changes
from lenn_ros.service.evaluation import NODE_ONLY_PARAMETERS, _learning_switch, _source, _test_part
from lenn_ros.service.reading import given
from lenn_ros.service.recording import read_recording
from lenn_ros.service.scoring import score

KEYS = ("nmse_db", "nmse_free_run_db", "rmse", "rmse_free_run")


@dataclass
class BagRecord:
    """One bag of several: its samples, its split and, once scored, each output's figures on its test part."""

    path: str
    index: np.ndarray
    u: np.ndarray
    y: np.ndarray
    train: np.ndarray  # rows learnt from
    start: int  # its first test sample, in its own numbering
    default: str  # why the test part is there, when nobody said
    evaluations: dict[str, Evaluation] | None = None

    def as_dict(self) -> dict[str, Any]:
        figures = {name: {key: _plain(getattr(e, key)) for key in (*KEYS, "samples")}
                   for name, e in (self.evaluations or {}).items()}  # fmt: skip
        return {"bag": self.path, "samples": len(self.index), "trained": int(self.train.sum()),
                "test_start": self.start, "test_default": self.default, "channels": figures}  # fmt: skip


@dataclass
class RecordsEvaluation:
    """What ``evaluate`` of several bags found: each bag's figures, and every test part's together."""

    records: list[BagRecord]
    overall: dict[str, dict[str, float]]
    notices: list[str]

    def as_dict(self) -> dict[str, Any]:
        overall = {name: {k: _plain(v) for k, v in figures.items()} for name, figures in self.overall.items()}
        return {"records": [r.as_dict() for r in self.records], "overall": overall, "notices": self.notices}


def evaluate_bags(
    paths: list[str | Path],
    params: str | None = None,
    test_from: int | None = None,
    node: str = "/identifier",
    flags: dict[str, Any] | None = None,
    progress: bool = False,
) -> RecordsEvaluation:
    """Learn through the build parts of every bag, score each bag's test part with the frozen model, and all of
    them together (see the module docstring)."""
    if test_from is not None:
        raise RecordingError(
            f"--test-from {test_from} with {len(paths)} bags: each numbers its samples from its own start, so K "
            "names a sample in several; evaluate one bag to split it at K"
        )
    named = given(flags)
    first = read_recording(paths[0], flags, params, node, model=True, recorded=True, progress=progress,
                           defaults=named)  # fmt: skip
    session, identifier, notices = first.session, first.identifier, []
    records = []
    for path in paths:
        read = first if path == paths[0] else _read_alike(path, flags, params, node, progress, named, first.values)
        samples = read.samples
        start, default = _test_part(Path(path), samples.index, read.learn, None, _source(read, named))
        switch = read.learn if read.learn is not None else _learning_switch(samples.index, read.values, [])
        records.append(BagRecord(str(path), samples.index, samples.u, samples.y, (samples.index < start) & switch,
                                 start, default))  # fmt: skip
        if recorded_changes(Path(path)):
            notices.append(f"{path}: its recorded live parameter changes are not replayed across several bags")
    after = _learn(session, records)
    window = identifier.structure.warm_up
    for record in records:  # each scored after everything before it, a sample missing between: its own run
        first_test = int(np.argmax(record.index >= record.start))
        rows = slice(max(0, first_test - window), len(record.index))
        shift = after + 2 - int(record.index[rows][0])
        index, u, y = record.index[rows] + shift, record.u[rows], record.y[rows]
        y_hat = session.run_samples(index, u, y, np.zeros(len(index), dtype=bool))
        record.evaluations = dict(zip(identifier.names, score(identifier, index, u, y, y_hat, record.start + shift),
                                      strict=True))  # fmt: skip
        after = int(index[-1])
    return RecordsEvaluation(records, _pooled(records, identifier.names), notices)


def _read_alike(path: str | Path, flags: Any, params: Any, node: str, progress: bool, named: bool,
                values: dict[str, Any]) -> Any:  # fmt: skip
    """A later bag read as the first: refused in one line where its recorded configuration differs."""
    read = read_recording(path, flags, params, node, model=True, recorded=True, progress=progress, defaults=named)
    for key in sorted({*values, *read.values} - set(NODE_ONLY_PARAMETERS)):
        if values.get(key) != read.values.get(key):
            raise RecordingError(
                f"{path}: {key} = {read.values.get(key)!r}, but the first bag's is {values.get(key)!r}: one model, "
                "one configuration (--params sets one for all)"
            )
    return read


def _learn(session: Any, records: list[BagRecord]) -> int:
    """One pass of the session over every bag's build rows, in order, each numbered after the one before with a
    sample missing between them, so that the identifier restarts its history there as after a gap; returns the
    last number given."""
    index, after = [], -1
    for record in records:
        rows = record.index[record.index < record.start]
        index.append(rows - int(rows[0]) + after + 2)
        after = int(index[-1][-1])
    build = [record.index < record.start for record in records]
    u, y = (np.concatenate([getattr(r, side)[rows] for r, rows in zip(records, build, strict=True)])
            for side in ("u", "y"))  # fmt: skip
    learn = np.concatenate([r.train[rows] for r, rows in zip(records, build, strict=True)])
    session.run_samples(np.concatenate(index), u, y, learn)
    return after


def _pooled(records: list[BagRecord], names: list[str]) -> dict[str, dict[str, float]]:
    """Each output's NMSE and RMSE over every bag's test samples together (where each was predicted, simulated)."""
    pooled = {}
    for name in names:
        parts = [record.evaluations[name] for record in records]
        y = np.concatenate([e.y_test for e in parts])
        figures = {}
        for key, series in (("", np.concatenate([e.y_hat_test for e in parts])),
                            ("_free_run", np.concatenate([e.y_free_test for e in parts]))):  # fmt: skip
            ran = np.isfinite(series) & np.isfinite(y)
            figures[f"nmse{key}_db"] = nmse_db(y[ran], series[ran]) if ran.any() else math.nan
            figures[f"rmse{key}"] = rmse(y[ran], series[ran]) if ran.any() else math.nan
        pooled[name] = figures
    return pooled


def _plain(value: Any) -> Any:
    return None if isinstance(value, float) and not math.isfinite(value) else value
