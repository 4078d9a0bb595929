"""What ``fit`` reads: a CSV file's columns or a bag's channels, as one :class:`~lenn_ros.fit.data.Data` record.

A CSV file is read by :mod:`lenn_ros.table` (any delimiter; a row missing a sample and a
jump of its time column are gaps; each sample numbered by its data row, from 1); any rosbag2
bag by the identifier node's own session (:mod:`lenn_ros.fit.bag`, through
:func:`lenn_ros.service.recording.read_recording`, as every offline command reads one), each
sample numbered as the node numbers it. A module apart from the procedure, which sees the record
only: how the samples were read never changes how a model is built.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros.fit.data import Data, FitError
from lenn_ros.table import TableError, read_table


def load_data(
    path: str | Path,
    u_columns: str | list[str] | None = None,
    y_columns: str | list[str] | None = None,
    flags: dict[str, Any] | None = None,
    progress: bool = False,
) -> Data:
    """u and y from a bag (:func:`is_bag`) or a CSV file (columns by name or index), any number of each.

    A bag is read as the node reads it (:func:`lenn_ros.fit.bag.load_bag`: its ``identifier_config``, the
    topics the flags name, or its plain ``u`` / ``y_p``, whose channels ``--u`` / ``--y`` may pick by label);
    ``progress``: a bar on stderr while a long recording is read.
    """
    path = Path(path)
    u_columns, y_columns = columns(u_columns), columns(y_columns)
    flags = dict(flags or {})
    time_column = flags.pop("time", None)  # a CSV's; every other flag is a bag's
    if not path.exists():
        raise FitError(f"{path} does not exist (expected a CSV file or a bag directory)")
    if is_bag(path):
        if time_column:
            raise FitError("--time: for a CSV file; a bag's samples carry their stamps (--sample-period sets a grid)")
        from lenn_ros.fit.bag import load_bag

        return load_bag(path, {**flags, "u": u_columns or None, "y": y_columns or None}, progress)
    bag_only = sorted(key for key, value in flags.items() if value not in (None, [], "") and key not in ("u", "y"))
    if bag_only:
        raise FitError(f"{', '.join('--' + k.replace('_', '-') for k in bag_only)}: for a bag, not a CSV file")
    return _load_csv(path, u_columns, y_columns, time_column)


def is_bag(path: Path) -> bool:
    """Whether ``fit`` reads ``path`` as a rosbag2 recording: what :func:`~lenn_ros.bag.reader.open_bag` takes (a
    directory of MCAP or sqlite3 files, one or split; a ``.mcap`` file; a ``.db3`` file beside its metadata.yaml),
    which says in one line what is wrong with one it cannot read. Anything else is a data file."""
    return path.is_dir() or path.suffix in (".mcap", ".db3")


def columns(given: str | list[str] | None) -> list[str]:
    """``--u`` / ``--y`` as a list: the command line repeats them (several channels), a caller may pass one name."""
    if given is None:
        return []
    return [given] if isinstance(given, str) else list(given)


def _load_csv(path: Path, u_columns: list[str], y_columns: list[str], time_column: str | None = None) -> Data:
    """The columns asked for (:mod:`lenn_ros.table` reads any delimiter). A row missing a sample in one of
    them is a gap: dropped, the record broken there (never joined across), its rows still counted by
    ``--test-from`` (``Data.index``), and the lines named in the report's data line. ``time_column``: the
    samples' times, whose jumps are gaps too (:func:`_time_gaps`)."""
    named = any(not column.strip().isdigit() for column in (*u_columns, *y_columns))
    try:
        table = read_table(path, named)
        header, width = table.header, table.width
        if not u_columns or not y_columns:
            if header and "u" in header and "y" in header:
                u_columns, y_columns = u_columns or ["u"], y_columns or ["y"]
            elif width == 2:
                u_columns, y_columns = u_columns or ["0"], y_columns or ["1"]
            else:
                shown = ", ".join(header) if header else f"{width} unnamed columns"
                raise FitError(f"{path} has columns {shown}: pass --u COL --y COL (name or 0-based index)")
        wanted = [*u_columns, *y_columns]
        indices = [table.column(column) for column in wanted]
        timed = [table.column(time_column)] if time_column is not None else []
        values, missing = table.values(indices + timed)
    except TableError as error:
        raise FitError(str(error)) from None
    kept = np.isfinite(values).all(axis=1)
    if not kept.any():
        raise FitError(f"{path}: no data row holds a number in every column asked for")
    period, late, timing = None, [], ""
    if timed:
        name = header[timed[0]] if header else str(timed[0])
        lines = [table.rows[r][0] for r in np.flatnonzero(kept)]
        period, late, timing = _time_gaps(values[kept, -1], lines, f"{path}: time column {name!r}")
        values = values[:, :-1]
    names = tuple(header[i] if header else str(i) for i in indices)
    split = len(u_columns)
    u_names, y_names = names[:split], names[split:]
    plural = "s" if len(wanted) > 2 else ""
    source = f"CSV {path}: u = column{plural} {', '.join(u_names)}, y = column{plural} {', '.join(y_names)}"
    if missing:
        source += (
            f"; {len(missing)} row{'s' if len(missing) > 1 else ''} missing a sample (empty, NaN, inf or short; "
            f"line{'s' if len(missing) > 1 else ''} {_lines_shown(missing)}): gaps, never fitted or scored across"
        )
    u, y = values[:, :split], values[:, split:]
    data = Data(u[:, 0] if split == 1 else u, y[:, 0] if len(y_names) == 1 else y, source + timing,
                u_names=u_names, y_names=y_names, sample_period=period).kept(kept)  # fmt: skip
    return dataclasses.replace(data, breaks=sorted({*data.breaks, *late})) if late else data


#: lines named in the report's data line for rows missing a sample or after a time jump (the count is always given)
MISSING_SHOWN = 5
#: a time step longer than this many sample periods (the median step) is a gap: samples were lost there
GAP_STEPS = 1.5
#: steps further than this share from the sample period are counted as irregular
JITTER = 0.1


def _lines_shown(lines: list[int]) -> str:
    """The first MISSING_SHOWN file lines, and "..." when there are more."""
    return ", ".join(map(str, lines[:MISSING_SHOWN])) + (", ..." if len(lines) > MISSING_SHOWN else "")


def _time_gaps(times: np.ndarray, lines: list[int], where: str) -> tuple[float, list[int], str]:
    """(the sample period: the median step, the rows after a jump of more than GAP_STEPS periods, what the
    report's data line says). A time that does not increase is an error naming its line: rows out of order or
    repeated would be fitted as the plant's own dynamics."""
    steps = np.diff(times)
    if not len(steps):
        raise FitError(f"{where}: one row only")
    back = np.flatnonzero(steps <= 0.0)
    if len(back):
        i = int(back[0]) + 1
        raise FitError(
            f"{where}, line {lines[i]}: {times[i]:g} does not come after {times[i - 1]:g} (line {lines[i - 1]}): "
            "sort the rows or drop the repeats"
        )
    period = float(np.median(steps))
    late = [int(i) + 1 for i in np.flatnonzero(steps > GAP_STEPS * period)]
    irregular = int(np.count_nonzero(np.abs(steps - period) > JITTER * period)) - len(late)
    text = f"; {where.split(': ', 1)[1]}: sample period {period:.6g} s (the median step)"
    if late:
        text += (
            f", {len(late)} jump{'s' if len(late) > 1 else ''} longer than {GAP_STEPS:g} periods (before "
            f"line{'s' if len(late) > 1 else ''} {_lines_shown([lines[i] for i in late])}): gaps, never fitted or "
            "scored across"
        )
    if irregular:
        text += f", {irregular} step{'s' if irregular > 1 else ''} off it by more than {JITTER:.0%}"
    return period, late, text
