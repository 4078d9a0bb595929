"""Coverage of ``lenn-ros fit``'s nominal 95 % bands on every shared data set (issue 20).

For each set: ``fit`` with its defaults on the README split, then the fraction of the
test samples inside the one-step band and inside the free-run band (both from the
errors of the selection's held-out blocks, see ``lenn_ros.fit.scoring.fit_intervals``), with the
band half-widths relative to the test output's standard deviation. A band is honest when
its coverage sits near 95 % on data it was not built from.

    python bench/intervals.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peer_narx import splits

from lenn_ros.fit.data import Data
from lenn_ros.fit.procedure import fit


def run(quick: bool) -> list[dict]:
    rows = []
    for split in splits(quick):
        began = time.perf_counter()
        report = fit(Data(split.u, split.y, split.name), split.test_from)
        bands = report.intervals
        spread = float(np.std(report.y_test))
        rows.append(
            {
                "data": split.name,
                "one_step": bands["one_step"]["coverage_test"],
                "one_step_width": bands["one_step"]["half_width"] / spread,
                "free_run": bands["free_run"]["coverage_test"],
                "free_run_width": bands["free_run"]["half_width"] / spread,
                "rmse_free_run": report.rmse_free_run,
                "seconds": time.perf_counter() - began,
            }
        )
        print(f"{split.name}: done in {rows[-1]['seconds']:.1f} s", file=sys.stderr, flush=True)
    return rows


def table(rows: list[dict]) -> str:
    lines = [
        "| data | one-step coverage | half-width / std(y) | free-run coverage | half-width / std(y) | free-run RMSE |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['data']} | {r['one_step']:.1%} | {r['one_step_width']:.3f} | {r['free_run']:.1%} | "
            f"{r['free_run_width']:.3f} | {r['rmse_free_run']:.4g} |"
        )
    one = np.array([r["one_step"] for r in rows])
    free = np.array([r["free_run"] for r in rows])
    lines.append(
        f"| mean ± std over sets | {one.mean():.1%} ± {one.std():.1%} | | {free.mean():.1%} ± {free.std():.1%} | | |"
    )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the four small sets only")
    args = parser.parse_args()
    print(table(run(args.quick)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
