"""Several records, one model (issue 44): ``fit`` on the shared sets that come as separate records.

Each case is a real ``lenn-ros fit --json`` subprocess; the table gives each test record's one-step and free-run
NMSE and RMSE. The previous way is one file split by ``--test-from`` (the free run starts from the measured
outputs before the test part, the build part's last samples); ``--test FILE`` scores a record of its own (its
one-step pass and free run seeded by its own first samples, not scored).

- Silverbox (``silverbox_multisine.csv``, ``silverbox_arrow.csv``: the same build rows 1..65 062, then the
  multisine test and the arrow head): the build rows and each test part written as records of their own; both test
  records with ``--test`` in one fit; and two build records (the multisine build rows and the arrow head's first
  half, a noise input of the amplitudes the build rows saw) scored on the multisine test and the arrow head's
  second half, against the multisine build rows alone on the same two records.
- The buck converter (``buck_converter_id.csv``, ``buck_converter_valid.csv``): the two files joined by hand with
  ``--test-from`` (the previous way; their time columns run on), against ``_id`` with ``--test _valid``.

Usage: ``nice python bench/several_records.py [--json]``. Several minutes (the Silverbox fits: 65 000+ rows).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = next(p / "shared" / "data" for p in REPO.parents if (p / "shared" / "data").is_dir())
#: the first Silverbox test row, 1-based (the data's README)
SILVERBOX_TEST = 65_063
KEYS = ("nmse_db", "rmse", "nmse_free_run_db", "rmse_free_run")


def fit(*arguments: str) -> dict[str, Any]:
    """One ``lenn-ros fit --json`` run's report."""
    command = [sys.executable, "-m", "lenn_ros.cli", "fit", *arguments, "--json"]
    done = subprocess.run(command, capture_output=True, text=True, cwd=REPO, check=False)
    if done.returncode:
        raise SystemExit(f"{' '.join(arguments)}: {done.stderr.strip()}")
    return json.loads(done.stdout)


def rows(report: dict[str, Any], case: str, set_name: str) -> list[dict[str, Any]]:
    """The table's rows of one report: its test part, or each of its test records."""
    tested = [r for r in report.get("records", []) if r["role"] == "test" and "scores" in r]
    if not tested:
        name = next((r["name"] for r in report.get("records", []) if r["role"] == "test"), "the test part")
        return [{"set": set_name, "case": case, "scored": Path(name).name, **{k: report[k] for k in KEYS}}]
    return [{"set": set_name, "case": case, "scored": Path(r["name"]).name, **r["scores"]["y"]} for r in tested]


def write(path: Path, table: np.ndarray) -> str:
    np.savetxt(path, table, delimiter=",", header="k,u,y", comments="", fmt="%.17g")
    return str(path)


def silverbox(work: Path) -> list[dict[str, Any]]:
    multisine = np.loadtxt(DATA / "silverbox_multisine.csv", delimiter=",", skiprows=1)
    arrow = np.loadtxt(DATA / "silverbox_arrow.csv", delimiter=",", skiprows=1)
    split = SILVERBOX_TEST - 1
    assert np.array_equal(multisine[:split], arrow[:split])  # the same build rows
    half = split + (len(arrow) - split) // 2
    build = write(work / "sb_build.csv", multisine[:split])
    ms_test = write(work / "sb_multisine_test.csv", multisine[split:])
    arrow_test = write(work / "sb_arrow_test.csv", arrow[split:])
    arrow_first, arrow_second = (write(work / f"sb_arrow_{n}.csv", part)
                                 for n, part in (("first", arrow[split:half]), ("second", arrow[half:])))  # fmt: skip
    found = []
    for name, file in (("multisine", "silverbox_multisine.csv"), ("arrow", "silverbox_arrow.csv")):
        report = fit(str(DATA / file), "--test-from", str(SILVERBOX_TEST))
        found += rows(report, f"one file, --test-from {SILVERBOX_TEST}", f"Silverbox {name}")
    for name, test in (("multisine", ms_test), ("arrow", arrow_test)):
        found += rows(fit(build, "--test", test), "build rows, --test the record", f"Silverbox {name}")
    found += rows(fit(build, "--test", ms_test, "--test", arrow_test), "build rows, --test both", "Silverbox")
    scored = ("--test", ms_test, "--test", arrow_second)
    found += rows(fit(build, *scored), "multisine build rows only", "Silverbox, 2 records")
    found += rows(fit(build, arrow_first, *scored), "+ arrow head's 1st half (2 records)", "Silverbox, 2 records")
    return found


def buck(work: Path) -> list[dict[str, Any]]:
    ident, valid = DATA / "buck_converter_id.csv", DATA / "buck_converter_valid.csv"
    lines = ident.read_text().splitlines() + valid.read_text().splitlines()[1:]
    joined = work / "buck_joined.csv"
    joined.write_text("\n".join(lines) + "\n")
    first = len(ident.read_text().splitlines())  # the header, then the rows: the first valid row's number
    flags = ("--u", "input", "--y", "y")
    found = rows(fit(str(joined), *flags, "--test-from", str(first)), f"joined by hand, --test-from {first}", "buck")
    found += rows(fit(str(ident), *flags, "--test", str(valid)), "_id, --test _valid", "buck")
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        table = buck(Path(folder)) + silverbox(Path(folder))
    if args.json:
        print(json.dumps(table, indent=1))
        return 0
    print("| set | fit | scored | one-step NMSE dB / RMSE | free-run NMSE dB / RMSE |")
    print("|---|---|---|---|---|")
    for r in table:
        print(f"| {r['set']} | {r['case']} | {r['scored']} | {r['nmse_db']:.2f} / {r['rmse']:.4g} | "
              f"{r['nmse_free_run_db']:.2f} / {r['rmse_free_run']:.4g} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
