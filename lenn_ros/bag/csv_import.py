"""``lenn-ros import-csv``: a run bag (``/u``, ``/y_p``, optional ``/test_start``) from logged data.

Errors name the file line and column, so a user can fix the CSV instead of guessing.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros import topics
from lenn_ros.bag.errors import BagError
from lenn_ros.bag.vectors import write_vector_run
from lenn_ros.bag.writer import BagWriter

__all__ = ["import_csv"]


def _column_index(header: list[str] | None, column: str | int, csv_path: Path) -> int:
    if isinstance(column, int) or (header is None and str(column).isdigit()):
        index = int(column)
    elif header is not None and column in header:
        return header.index(column)
    elif header is not None and str(column).isdigit():
        index = int(column)
    else:
        shown = ", ".join(header) if header else "no header row"
        raise BagError(f"{csv_path}: no column {column!r} (columns: {shown}); pass a column name or 0-based index")
    width = len(header) if header is not None else None
    if index < 0 or (width is not None and index >= width):
        raise BagError(f"{csv_path}: column index {index} out of range (0..{(width or 1) - 1})")
    return index


def is_number(text: str) -> bool:
    """Whether a CSV cell is a number (a first row of numbers is data, not a header)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


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
    rows = _read_rows(csv_path)
    first = [cell.strip() for cell in rows[0][1]]
    named = any(isinstance(c, str) and not c.isdigit() for c in (*u_columns, *y_columns))
    has_header = named or not all(is_number(c) for c in first if c)
    header = first if has_header else None
    columns = [(_column_index(header, column, csv_path), column) for column in (*u_columns, *y_columns)]
    values = _read_values(csv_path, rows[1:] if has_header else rows, tuple(columns))
    if not values[0]:
        raise BagError(f"{csv_path}: no data rows after the header")
    if test_from is not None and not 1 <= test_from <= len(values[0]):
        raise BagError(
            f"test_from={test_from} is outside samples 1..{len(values[0])} of {csv_path} (1-based, like test_start)"
        )
    if len(u_columns) == len(y_columns) == 1:
        _write_run_bag(out_path, values[0], values[1], dt, test_from)
        return out_path
    names = [header[index] if header else str(index) for index, _ in columns]
    split = len(u_columns)
    _check_names(csv_path, names[:split], "--u")
    _check_names(csv_path, names[split:], "--y")
    matrix = np.array(values, dtype=np.float64).T
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


def _read_rows(csv_path: Path) -> list[tuple[int, list[str]]]:
    """The non-empty rows, each with its 1-based file line, so every later error can name the line."""
    text = csv_path.read_text(encoding="utf-8-sig")
    try:
        dialect: Any = csv.Sniffer().sniff(text[:4096], delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    rows = [(n, row) for n, row in enumerate(csv.reader(text.splitlines(), dialect), start=1) if any(row)]
    if not rows:
        raise BagError(f"{csv_path}: the file has no rows")
    return rows


def _read_values(
    csv_path: Path, data: list[tuple[int, list[str]]], columns: tuple[tuple[int, str | int], ...]
) -> list[list[float]]:
    """One list of floats per (index, name) column, row by row, so the first bad cell in file order is reported."""
    values: list[list[float]] = [[] for _ in columns]
    for line, row in data:
        for (index, column), column_values in zip(columns, values, strict=True):
            column_values.append(_cell_value(csv_path, line, row, index, column))
    return values


def _cell_value(csv_path: Path, line: int, row: list[str], index: int, column: str | int) -> float:
    """The finite number in one cell; a short row, a non-number or an inf/nan is refused with its line and column."""
    if index >= len(row):
        raise BagError(f"{csv_path}: line {line} has {len(row)} cells, no column {column!r}; fix that row")
    cell = row[index].strip()
    try:
        value = float(cell)
    except ValueError:
        raise BagError(f"{csv_path}: line {line}, column {column!r}: {cell!r} is not a number") from None
    if not math.isfinite(value):
        raise BagError(f"{csv_path}: line {line}, column {column!r}: {cell!r} is not finite")
    return value


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
