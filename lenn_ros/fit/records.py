"""Several files, one model: ``lenn-ros fit run1.csv run2.csv bagdir/ --test run3.csv``.

Robots log many short runs; benchmark data come as separate estimation and validation files.
Each file is read as one record is (:func:`~lenn_ros.fit.load.load_data`) and the records are
joined in the order given, each a run of its own: a break at every join (``Data.breaks``, the gap
rule of :mod:`lenn_ros.core.runs`), so no regression row, block free run or test free run reaches
from one record into the next, exactly as across a gap in one record. Everything after that is
the one procedure on the joined record: the scales come from every build record, the selection's
blocks are cut over all of them (:func:`~lenn_ros.fit.record.fold_blocks`), and a record given
with ``--test`` is scored whole, its free run and one-step pass seeded by its own first samples
(the test part starts at a break: :func:`~lenn_ros.fit.scoring.score`).

The joined record numbers its samples as the records do where their numbers run on from one to
the next (a recording cut into several bags); otherwise (every CSV numbers its rows from 1)
each record's numbers are shifted past the one before, so that every sample has one number and
the report can name it; the report lists each record's span. ``--test-from K`` with several
build records is taken only in the first case, where K names one sample.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros.core.metrics import nmse_db, rmse
from lenn_ros.fit.data import Data, FitError, RecordPart
from lenn_ros.fit.load import load_data
from lenn_ros.fit.numbering import numbers

#: a record's sample period may differ from the first record's by this share (the time column's median step)
PERIOD_TOLERANCE = 0.01


def load_records(
    paths: list[str | Path],
    tests: list[str | Path] | None = None,
    u_columns: str | list[str] | None = None,
    y_columns: str | list[str] | None = None,
    flags: dict[str, Any] | None = None,
    progress: bool = False,
) -> Data:
    """The build records ``paths`` and the ``tests`` records, each read by :func:`load_data` with the same
    columns and flags, joined (:func:`join`). One path and no test record: that record as it always was."""
    tests = list(tests or [])
    if len(paths) == 1 and not tests:
        return load_data(paths[0], u_columns, y_columns, flags, progress)
    roles = ["build"] * len(paths) + ["test"] * len(tests)
    read = [(str(path), role, load_data(path, u_columns, y_columns, flags, progress))
            for path, role in zip([*paths, *tests], roles, strict=True)]  # fmt: skip
    return join(read)


def join(read: list[tuple[str, str, Data]]) -> Data:
    """The records (name, role, data), in order, as one :class:`Data` with a break where each begins.

    Refused in one line where they cannot be one model's data: other channels, another sample period, a bag read
    through another configuration. A recorded test start is not taken (the split is ``--test`` or ``--test-from``).
    """
    (first_name, _, first), *_ = read
    # what a bag's reading says, and the sample period, from the first record that has them (a CSV has neither)
    interpretation = next((data.interpretation for _, _, data in read if data.interpretation), {})
    period = next((data.sample_period for _, _, data in read if data.sample_period), None)
    for name, _, data in read[1:]:
        _check_alike(first_name, first, name, data, period)
    parts, u, y, index, breaks, last = [], [], [], [], [], 0
    rows = 0
    for name, role, data in read:
        own = numbers(data)
        shift = 0 if int(own[0]) > last else last  # where they run on, the records' own numbers
        joined = own + shift
        parts.append(RecordPart(name, role, rows, len(own), (int(joined[0]), int(joined[-1])), data.source, shift))
        breaks += [rows + b for b in data.breaks] + ([rows] if rows else [])
        u.append(data.u)
        y.append(data.y)
        index.append(joined)
        rows, last = rows + len(own), int(joined[-1])
    index_all = np.concatenate(index)
    plain = np.array_equal(index_all, np.arange(1, rows + 1))
    builds = sum(part.role == "build" for part in parts)
    source = f"{len(parts)} records ({builds} to build on, {len(parts) - builds} to test on)"
    return Data(np.concatenate(u), np.concatenate(y), source, breaks=sorted(set(breaks)),
                index=None if plain else index_all, interpretation=interpretation, u_names=first.u_names,
                y_names=first.y_names, sample_period=period, records=tuple(parts))  # fmt: skip


def _check_alike(first_name: str, first: Data, name: str, data: Data, period: float | None) -> None:
    """FitError where record ``name`` cannot join ``first_name``'s in one model (``period``: the first known)."""
    if (data.u_names, data.y_names) != (first.u_names, first.y_names):
        raise FitError(
            f"{name}: u {', '.join(data.u_names)} and y {', '.join(data.y_names)}, but {first_name} holds u "
            f"{', '.join(first.u_names)} and y {', '.join(first.y_names)}: every record must hold the same channels"
        )
    if period and data.sample_period and abs(data.sample_period - period) > PERIOD_TOLERANCE * period:
        raise FitError(f"{name}: sample period {data.sample_period:g} s, but the first record's with one is "
                       f"{period:g} s: one model, one period")  # fmt: skip
    if not (first.interpretation and data.interpretation):
        return  # a CSV's samples are the file's; only two bags may have been read through different configurations
    for key in sorted({*first.interpretation, *data.interpretation}):
        if first.interpretation.get(key) != data.interpretation.get(key):
            raise FitError(
                f"{name}: read with {key} = {data.interpretation.get(key)!r}, but {first_name} with "
                f"{first.interpretation.get(key)!r}: the params file says one reading; fit records read alike"
            )


def split_of(data: Data, test_from: int | None) -> tuple[int | None, bool]:
    """(the number of the first test sample, whether it is a bag's recorded one) for :func:`~lenn_ros.fit.
    procedure.fit`: ``--test-from`` or the recorded test start of one record; with several, the first ``--test``
    record's first sample, or ``--test-from K`` where the build records' numbers run on (K names one sample).
    Any other combination is refused in one line."""
    if not data.records:
        recorded = test_from is None and data.test_start is not None
        return (data.test_start if recorded else test_from), recorded
    tests = [part for part in data.records if part.role == "test"]
    builds = len(data.records) - len(tests)
    if tests and test_from is not None:
        raise FitError(f"--test-from {test_from} and --test: the test part is the records given with --test or the "
                       "samples from K of the build records, not both")  # fmt: skip
    if tests:
        return tests[0].numbers[0], False
    if test_from is None:
        raise FitError(f"{builds} records to build on and none to score: pass --test FILE (a record of its own)")
    if any(part.shift for part in data.records):
        raise FitError(
            f"--test-from {test_from} with {builds} records to build on: each numbers its samples from its own "
            "start, so K names a sample in several; pass the test record with --test FILE"
        )
    return test_from, False


def record_lines(records: list[dict[str, Any]]) -> list[str]:
    """The report's lines on the records: what each holds and, of several test records, each one's figures."""
    if not records:
        return []
    lines = ["  records, each a run of its own (never fitted, simulated or scored across a join):"]
    for part in records:
        first, last = part["numbers"]
        shift = part.get("shift", 0)
        own = f" (its own {first - shift}..{last - shift})" if shift else ""
        lines.append(f"    {part['role']:<5} {part['name']}: {part['samples']} samples, numbered {first}..{last}{own}")
        for output, figures in part.get("scores", {}).items():
            label = "" if output == "y" and len(part["scores"]) == 1 else f" {output}"
            lines.append(
                f"      {label.strip() + ': ' if label else ''}one-step NMSE {figures['nmse_db']:.2f} dB, RMSE "
                f"{figures['rmse']:.5g}; free run NMSE {figures['nmse_free_run_db']:.2f} dB, RMSE "
                f"{figures['rmse_free_run']:.5g}"
            )
    return lines


def records_report(data: Data, per_output: list[Any]) -> list[dict[str, Any]]:
    """Each record as the report gives it; with several test records, each one's figures per output (its
    one-step and free run, both seeded by its own first samples as the test part's first record is)."""
    found = [part.as_dict() for part in data.records]
    tests = [part for part in data.records if part.role == "test"]
    if len(tests) < 2:
        return found
    first = tests[0].first
    for entry, part in zip(found, data.records, strict=True):
        if part.role != "test":
            continue
        rows = slice(part.first - first, part.first - first + part.samples)
        entry["scores"] = {report.name: _figures(report, rows) for report in per_output}
    return found


def _figures(report: Any, rows: slice) -> dict[str, float]:
    """One output's one-step and free-run NMSE and RMSE over ``rows`` of the test part (where each ran)."""
    y, one, free = report.y_test[rows], report.y_hat_test[rows], report.y_free_test[rows]
    figures = {}
    for key, series in (("", one), ("_free_run", free)):
        ran = np.isfinite(series)
        figures[f"nmse{key}_db"] = nmse_db(y[ran], series[ran]) if ran.any() else float("nan")
        figures[f"rmse{key}"] = rmse(y[ran], series[ran]) if ran.any() else float("nan")
    return figures


def data_name(paths: list[str | Path]) -> str:
    """The data's name for a plot's title: the one file's, or how many records."""
    return Path(paths[0]).name if len(paths) == 1 else f"{len(paths)} records"


def as_paths(given: str | Path | list[str | Path] | None) -> list[str | Path]:
    """``args.data`` / ``args.test`` as a list: the command line gives lists, an in-process caller may give one."""
    if given is None:
        return []
    return [given] if isinstance(given, str | Path) else list(given)
