"""``lenn-ros import-csv``: a run bag (``/u``, ``/y_p``, optional ``/test_start``) from logged data.

Errors name the file line and column, so a user can fix the CSV instead of guessing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from lenn_ros import topics
from lenn_ros.bag.errors import BagError
from lenn_ros.bag.vectors import write_vector_run
from lenn_ros.bag.writer import BagWriter
from lenn_ros.table import TableError, read_table

__all__ = ["import_csv"]


Column = str | int


def import_csv(
    csv_path: str | Path,
    u_column: Column | Sequence[Column],
    y_column: Column | Sequence[Column],
    dt: float,
    out_path: str | Path,
    test_from: int | None = None,
) -> Path:
    """Make a run bag (``/u``, ``/y_p`` at log time k*dt, optional latched ``/test_start``) from logged data.

    ``test_from`` is 1-based, like ``test_start`` on the live graph (the publication
    sequence number of the first test sample, i.e. row k of the data is sample k + 1).
    Columns are names or 0-based indices (a digit string counts as an index unless the
    header has a column of that name). The first row is a header when its cells are not
    all numbers. Errors name the file line, so a user can fix the CSV instead of guessing.
    A list of several u or y columns makes a vector run (:mod:`lenn_ros.bag.vectors`):
    Float64MultiArray samples labelled with the column names; one of each stays Float64.
    """
    csv_path, out_path = Path(csv_path), Path(out_path)
    u_columns, y_columns = _as_columns(u_column), _as_columns(y_column)
    if not (dt > 0 and math.isfinite(dt)):
        raise BagError(f"dt must be a positive number of seconds, got {dt}")
    if not csv_path.is_file():
        raise BagError(f"{csv_path}: no such file; pass the CSV with the logged input and output")
    named = any(isinstance(c, str) and not c.strip().isdigit() for c in (*u_columns, *y_columns))
    try:
        table = read_table(csv_path, named)
        indices = [table.column(column) for column in (*u_columns, *y_columns)]
        matrix, missing = table.values(indices)
    except TableError as error:
        raise BagError(str(error)) from None
    if missing:
        line = missing[0]
        raise BagError(
            f"{csv_path}: line {line} has no number in a column asked for (empty, NaN, inf or short): a run "
            f"bag has no gaps; drop or fill that row ({len(missing)} such rows; lenn-ros fit reads them as gaps)"
        )
    if not len(matrix):
        raise BagError(f"{csv_path}: no data rows after the header")
    if test_from is not None and not 1 <= test_from <= len(matrix):
        raise BagError(
            f"test_from={test_from} is outside samples 1..{len(matrix)} of {csv_path} (1-based, like test_start)"
        )
    if len(u_columns) == len(y_columns) == 1:
        _write_run_bag(out_path, matrix[:, 0].tolist(), matrix[:, 1].tolist(), dt, test_from)
        return out_path
    names = [table.header[index] if table.header else str(index) for index in indices]
    split = len(u_columns)
    _check_names(csv_path, names[:split], "--u")
    _check_names(csv_path, names[split:], "--y")
    u_rows, y_rows = matrix[:, :split], matrix[:, split:]
    return write_vector_run(out_path, u_rows, y_rows, (names[:split], names[split:]), dt, test_from)


def _as_columns(column: Column | Sequence[Column]) -> list[Column]:
    """One column or several, as a list (a str is one column name, not a sequence of letters)."""
    columns = [column] if isinstance(column, str | int) else list(column)
    if not columns:
        raise BagError("name at least one u and one y column")
    return columns


def _check_names(csv_path: Path, names: list[str], option: str) -> None:
    """Channel names go into a comma-joined label: each must be there once and hold no comma."""
    for name in names:
        if "," in name or not name:
            raise BagError(f"{csv_path}: column name {name!r} cannot name a channel (empty or with a comma); rename it")
        if names.count(name) > 1:
            raise BagError(f"{csv_path}: column {name!r} given twice as {option}; name each channel once")


def _write_run_bag(out_path: Path, u_vals: list[float], y_vals: list[float], dt: float, test_from: int | None) -> None:
    """/u and /y_p stamped at k*dt (the log's own clock), the latched /test_start first when given."""
    with BagWriter(out_path, flush_period=None) as bag:
        bag.add_topic("/" + topics.U)
        bag.add_topic("/" + topics.Y_P)
        if test_from is not None:
            bag.add_topic("/" + topics.TEST_START)
            bag.write_value("/" + topics.TEST_START, int(test_from), 0)
        for k, (u, y) in enumerate(zip(u_vals, y_vals, strict=True)):
            stamp = round(k * dt * 1e9)
            bag.write_value("/" + topics.U, u, stamp)
            bag.write_value("/" + topics.Y_P, y, stamp)
