"""Delimited text tables of logged samples: the one reader behind ``fit`` and ``import-csv``.

Logged data comes in several spellings of the same table: CSV from a logger or a script
(commas), from a spreadsheet set to a language whose decimal mark is a comma (semicolons
and ``1,5``), TSV, and whitespace-aligned columns (MATLAB's ``save -ascii``, the DaISy
files), with a byte-order mark, Windows line ends, Excel's ``sep=;`` line, comment lines
(``#`` or ``%``) and blank lines. All of them are read here, the delimiter found from the file itself, so that
no user converts a file by hand and no two commands disagree on what a file holds.

A cell with no number (empty, ``NaN``, ``NA``, ``inf``) or a row too short to hold a
column asked for is a *missing* sample, kept as NaN with its line: a logger's dropout or
the last line of a killed one. What to do with it is the caller's decision (``fit``
makes it a gap in the record, never joined across; a run bag cannot hold one). A cell
that is text is an error naming its line and column.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Table", "TableError", "is_number", "read_table"]

#: delimiters tried, in this order ("" is runs of whitespace): a semicolon or tab first, as a file that uses
#: one may hold decimal commas, which a comma would split into a consistent but wrong number of cells
DELIMITERS = (";", "\t", ",", "")
#: first characters of a comment line
COMMENTS = ("#", "%")
#: cells that mark a sample as missing (compared lower-case; inf and nan are refused as values too)
MISSING = frozenset({"", "nan", "-nan", "na", "n/a", "#n/a", "null", "none"})
#: data lines the delimiter is judged on
SNIFFED_LINES = 50

_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+([eE][+-]?\d+)?$")


class TableError(ValueError):
    """A table that cannot be read as samples; the message names the file, line and column to fix."""


def is_number(text: str) -> bool:
    """Whether a cell is a number (a first row of numbers is data, not a header)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


@dataclass
class Table:
    """The rows of a delimited text file: ``header`` (None when the first row is data) and the data rows,
    each with its 1-based line in the file, so that every later message can name the line."""

    path: Path
    header: list[str] | None
    rows: list[tuple[int, list[str]]]
    delimiter: str  # one of DELIMITERS

    @property
    def width(self) -> int:
        return len(self.header) if self.header is not None else max((len(r) for _, r in self.rows), default=0)

    def column(self, column: str | int) -> int:
        """The 0-based index of a column given by header name or 0-based index (a name first: a header may
        name a column "1")."""
        text = str(column).strip()
        if self.header is not None and text in self.header:
            return self.header.index(text)
        if text.isdigit() and int(text) < self.width:
            return int(text)
        shown = ", ".join(self.header) if self.header is not None else f"no header row, indices 0..{self.width - 1}"
        raise TableError(f"{self.path}: no column {text!r} (columns: {shown}); pass a column name or 0-based index")

    def values(self, columns: list[int]) -> tuple[np.ndarray, list[int]]:
        """(one row per data row, one column per index asked, NaN where a sample is missing; the 1-based
        lines of the rows with a missing sample). A cell that is text raises TableError naming the first one
        in file order."""
        out = np.empty((len(self.rows), len(columns)))
        text: list[tuple[int, int, int]] = []  # (row, column position, index) of the first text cell per column
        for c, index in enumerate(columns):
            cells = [row[index] if index < len(row) else "" for _, row in self.rows]
            try:  # numpy parses a column of plain numbers in one call; anything else cell by cell
                out[:, c] = np.array(cells, dtype=np.float64)
            except ValueError:
                parsed = [_number(cell, decimal_comma=self.delimiter != ",") for cell in cells]
                bad = next((r for r, value in enumerate(parsed) if isinstance(value, str)), None)
                if bad is not None:
                    text.append((bad, c, index))
                    continue
                out[:, c] = [math.nan if value is None else value for value in parsed]
        if text:
            r, _, index = min(text)
            name = self.header[index] if self.header is not None else str(index)
            shown = self.rows[r][1][index].strip()
            raise TableError(f"{self.path}: line {self.rows[r][0]}, column {name!r}: {shown!r} is not a number")
        out[~np.isfinite(out)] = np.nan
        missing = [self.rows[r][0] for r in np.flatnonzero(np.isnan(out).any(axis=1))]
        return out, missing


def _number(cell: str, decimal_comma: bool) -> float | str | None:
    """A cell's finite value, None when it marks a missing sample, or "text"."""
    text = cell.strip()
    if text.lower() in MISSING:
        return None
    if decimal_comma and _DECIMAL_COMMA.match(text):
        text = text.replace(",", ".")
    try:
        value = float(text)
    except ValueError:
        return "text"
    return value if math.isfinite(value) else None


def read_table(path: str | Path, named: bool = False) -> Table:
    """The table in ``path``. The first row is a header when some cell of it is not a number, or when
    ``named`` (the caller asks for columns by name)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise TableError(f"{path}: not a text file (expected delimited text: CSV, TSV or whitespace columns)") from None
    lines = [(n, line) for n, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not line.lstrip().startswith(COMMENTS)]  # fmt: skip
    if not lines:
        raise TableError(f"{path}: the file has no rows")
    if lines[0][1].strip().lower().startswith("sep=") and len(lines[0][1].strip()) == 5:  # Excel's own line
        delimiter, lines = lines[0][1].strip()[4], lines[1:]
    else:
        delimiter = _delimiter([line for _, line in lines[:SNIFFED_LINES]])
    if not lines:
        raise TableError(f"{path}: the file has no rows")
    rows = [(n, row) for (n, _), row in zip(lines, _cells([line for _, line in lines], delimiter), strict=True)]
    first = [cell.strip() for cell in rows[0][1]]
    if named or not all(is_number(cell) for cell in first if cell):
        return Table(path, first, rows[1:], delimiter)
    return Table(path, None, rows, delimiter)


def _cells(lines: list[str], delimiter: str) -> Iterator[list[str]]:
    """Each line's cells: csv's reading of ``delimiter`` (quotes, spaces after it), or runs of whitespace."""
    if not delimiter:
        return (line.split() for line in lines)
    return csv.reader(lines, delimiter=delimiter, skipinitialspace=True)


def _delimiter(lines: list[str]) -> str:
    """The first delimiter that splits every line into the same number (>= 2) of cells; else the one that
    splits the data lines (after a header) so; else a comma (a file of one column)."""
    for candidates in (lines, lines[1:]):
        for delimiter in DELIMITERS:
            widths = {len(row) for row in _cells(candidates, delimiter)}
            if candidates and len(widths) == 1 and widths.pop() >= 2:
                return delimiter
    return ","
