"""The one reader of delimited text tables (``lenn_ros.table``) behind ``fit`` and ``import-csv``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_fit import cubic_plant

from lenn_ros.fit.data import Data, FitError
from lenn_ros.fit.load import load_data
from lenn_ros.fit.procedure import fit
from lenn_ros.table import TableError, read_table

NUMBERS = [[0.5, -1.25], [1e-3, 2.0], [-3.0, 4.5e2]]

SPELLINGS = {
    "comma": "u,y\n0.5,-1.25\n0.001,2\n-3,450\n",
    "CRLF and a byte-order mark": "\ufeffu,y\r\n0.5,-1.25\r\n1e-3,2\r\n-3,4.5e2\r\n",
    "semicolons and decimal commas": "u;y\n0,5;-1,25\n0,001;2\n-3;450\n",
    "Excel's sep= line": "sep=;\nu;y\n0,5;-1,25\n0,001;2\n-3;450\n",
    "tabs": "u\ty\n0.5\t-1.25\n0.001\t2\n-3\t450\n",
    "whitespace columns, comments": "% logged 2026-12-05\n# Ts = 0.01\n u   y\n  5.0e-01  -1.25e+00\n"
    "  1.0e-03   2.00e+00\n\n -3.0e+00   4.50e+02\n",
    "quoted header, spaces after commas": '"u", "y"\n0.5, -1.25\n0.001, 2\n-3, 450\n',
}


@pytest.mark.parametrize("spelling", list(SPELLINGS))
def test_every_spelling_of_a_table_reads_the_same_samples(tmp_path: Path, spelling: str) -> None:
    path = tmp_path / "log.txt"
    path.write_bytes(SPELLINGS[spelling].encode())
    table = read_table(path)
    values, missing = table.values([table.column("u"), table.column("y")])
    assert table.header == ["u", "y"]
    assert values.tolist() == NUMBERS and missing == []


def test_a_table_without_header_is_read_by_index_and_the_lines_are_the_files(tmp_path: Path) -> None:
    path = tmp_path / "log.dat"
    path.write_text("# a comment\n1 2 3\n\n4 5 6\n")
    table = read_table(path)
    assert table.header is None and table.delimiter == "" and table.width == 3
    assert [line for line, _ in table.rows] == [2, 4]
    assert table.values([2, 0])[0].tolist() == [[3.0, 1.0], [6.0, 4.0]]
    with pytest.raises(TableError, match=r"no column '3' \(columns: no header row, indices 0..2\)"):
        table.column(3)


def test_a_missing_sample_is_nan_with_its_line_and_text_is_an_error_naming_line_and_column(tmp_path: Path) -> None:
    path = tmp_path / "log.csv"
    path.write_text("t,u,y\n0,1,2\n1,,3\n2,NaN,4\n3,inf,5\n4,NA,6\n5,7\n6,8,9\n")
    table = read_table(path)
    values, missing = table.values([table.column("u"), table.column("y")])
    assert missing == [3, 4, 5, 6, 7]  # empty, NaN, inf, NA, a short row
    assert values[0].tolist() == [1.0, 2.0] and values[-1].tolist() == [8.0, 9.0]
    assert np.isnan(values[1:5, 0]).all() and values[5, 0] == 7.0 and np.isnan(values[5, 1])
    assert table.values([0])[1] == []  # the column t is complete
    path.write_text("u,y\n1,2\n3,volts\namps,4\n")
    table = read_table(path)
    with pytest.raises(TableError, match=r"log.csv: line 3, column 'y': 'volts' is not a number"):
        table.values([0, 1])  # the first in file order, though column u's comes first


def test_fit_reads_missing_samples_as_gaps_and_counts_test_from_by_data_row(tmp_path: Path) -> None:
    """A row with no number in a column used is a gap: dropped, the record broken there (the same fit as the
    kept rows with that break given), ``--test-from`` still counting it, its line named in the report's data
    line, and the test part's free run restarted after one in it."""
    u, y = cubic_plant(1200, 3)
    lines = [f"{a:.17g},{b:.17g}" for a, b in zip(u, y, strict=True)]
    lines[300] = f"{u[300]:.17g},"  # a build row (file line 302)
    lines[1000] = f"nan,{y[1000]:.17g}"  # a test row (file line 1002)
    path = tmp_path / "log.csv"
    path.write_text("u,y\n" + "\n".join(lines) + "\n")
    data = load_data(path)
    assert data.breaks == [300, 999] and len(data.y) == 1198
    assert "2 rows missing a sample (empty, NaN, inf or short; lines 302, 1002): gaps" in data.source
    report = fit(data, 801, refine=False)  # by number: the data rows, the missing one counted
    kept = np.delete(np.arange(1200), [300, 1000])
    alone = fit(Data(u[kept], y[kept], "x", breaks=[300, 999]), 800, refine=False)
    assert report.train_samples == 799  # rows 1..800 less the missing one
    assert report.nmse_free_run_db == alone.nmse_free_run_db < -30.0
    assert report.free_run["segments"] == 2
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(path), "--test-from", "801", "--no-refine"],
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    assert "lines 302, 1002" in done.stdout
    assert "built on 799 samples numbered 1..800, tested on 399 samples from 801" in done.stdout


def test_a_time_column_gives_the_sample_period_and_its_jumps_are_gaps(tmp_path: Path) -> None:
    """``--time``: the median step is the sample period (the report's test duration), a jump of more than
    1.5 periods is a gap like a missing row (the same fit as the rows with those breaks given), jitter is
    counted, and rows out of order are refused naming the line; a bag or a CSV refuses the other's flags."""
    u, y = cubic_plant(1000, 4)
    times = 0.01 * np.arange(1000)
    times[400:] += 0.05  # five samples lost before row 401: a jump of 6 periods
    times[700] += 0.002  # jitter: 0.012 and 0.008 s steps around it, within the gap limit
    path = tmp_path / "log.csv"
    path.write_text("t,u,y\n" + "".join(f"{t:.6f},{a:.17g},{b:.17g}\n" for t, a, b in zip(times, u, y, strict=True)))
    data = load_data(path, flags={"time": "t"})
    assert data.breaks == [400] and data.index is None and data.sample_period == pytest.approx(0.01)
    assert "time column 't': sample period 0.01 s (the median step), 1 jump longer than 1.5 periods (before " in (
        data.source
    )
    assert "line 402): gaps, never fitted or scored across, 2 steps off it by more than 10%" in data.source
    report = fit(data, 801, refine=False)
    alone = fit(Data(u, y, "x", breaks=[400]), 801, refine=False)
    assert report.nmse_free_run_db == alone.nmse_free_run_db < -30.0
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(path), "--time", "t", "--test-from", "801", "--no-refine"],
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    assert "sample time 0.01 s: test part 2 s" in done.stdout
    wrong = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(path), "--time", "t", "--dt", "0.005", "--test-from", "801"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert wrong.returncode == 2
    assert "--dt 0.005 s disagrees with the time column's sample period 0.01 s" in wrong.stderr
    times[500] = times[499]
    path.write_text("t,u,y\n" + "".join(f"{t:.6f},{a:.17g},{b:.17g}\n" for t, a, b in zip(times, u, y, strict=True)))
    with pytest.raises(FitError, match=r"time column 't', line 502: 5.04 does not come after 5.04 \(line 501\)"):
        load_data(path, flags={"time": "t"})
    with pytest.raises(FitError, match=r"--u-field: for a bag, not a CSV file"):
        load_data(path, flags={"u_field": "data[0]"})
