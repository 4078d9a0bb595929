"""Coverage of ``lenn-ros fit``'s nominal 95 % bands on every shared data set, a plant like its training, and the
paper's example plants (issue 20).

For each set: ``fit`` with its defaults on the README split, then the fraction of the
test samples inside the one-step band and inside the free-run band (both calibrated on the
errors of the selection's held-out blocks, see ``lenn_ros.fit.bands``), beside what the
one number per band the same blocks gave before (the 95 % quantile of |e|, kept in fit.json as
``held_out_half_width``) covers, with the bands' mean half-widths relative to the test output's
standard deviation and the share of test regressors farther from the build data than 99 % of the
build rows. A band is honest when its coverage sits near 95 % on data it was not built from;
the plant whose test part is drawn like its training (test_fit.py's cubic plant, seeds 3-8) must
stay within 93-97 %. The paper's plants are trained on a random input and tested on a sinusoid
(3000 + 1000 samples, seed 0, noise in both parts): test parts unlike the build part. Printed: the shared sets
with one row summing up every group (bench/RESULTS.md's table), then the cubic plant's and the paper's rows.

    python bench/intervals.py [--quick]    (about 5 min on two busy cores; --quick: the four small sets)
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from peer_narx import splits

from lenn_ros.core.metrics import coverage
from lenn_ros.fit.data import Data
from lenn_ros.fit.procedure import fit

#: the cubic plant's seeds (test_fit.py's, test_fit_bands.py's) and its split
CUBIC_SEEDS = range(3, 9)


def cases(quick: bool) -> Iterator[tuple[str, str, np.ndarray, np.ndarray, int]]:
    """(group, name, u, y, test_from) of every case: the shared sets, the cubic plant's seeds, the paper's plants."""
    from test_fit import cubic_plant

    from lenn_ros.paper.evaluation import simulate
    from lenn_ros.paper.examples import get_example

    for split in splits(quick):
        yield "shared sets", split.name, split.u, split.y, split.test_from
    for seed in CUBIC_SEEDS:
        yield "cubic plant", f"cubic plant, seed {seed}", *cubic_plant(2500, seed), 2001
    for number in (1, 2, 3, 4):
        example = get_example(number)
        series = simulate(example.plant(), example.noise_db, 0, 3000, 1000, test_noise=True)
        yield "paper's plants", f"paper Ex. {number}", series.u, series.y, 3001


def measure(name: str, u: np.ndarray, y: np.ndarray, test_from: int) -> dict:
    """One case's coverage and mean half-widths of both bands, now and as one number."""
    report = fit(Data(u, y, name), test_from)
    part, bands = report.only, report.intervals
    one, free = bands["one_step"], bands["free_run"]
    spread = float(np.std(report.y_test))
    return {
        "one_step_before": coverage(part.y_test, part.y_hat_test, one["held_out_half_width"]),
        "one_step": one["coverage_test"],
        "one_step_width": float(np.nanmean(part.one_step_half_width_test)) / spread,
        "free_run_before": coverage(part.y_test, part.y_free_test, free["held_out_half_width"]),
        "free_run": free["coverage_test"],
        "free_run_width": float(np.nanmean(part.free_run_half_width_test)) / spread,
        "far": one.get("far_from_build_test", float("nan")),
        "said": bool(bands.get("unlike_build")),
    }


def run(quick: bool) -> list[dict]:
    rows = []
    for group, name, u, y, test_from in cases(quick):
        began = time.perf_counter()
        rows.append({"group": group, "data": name, **measure(name, u, y, test_from)})
        print(f"{name}: done in {time.perf_counter() - began:.1f} s", file=sys.stderr, flush=True)
    return rows


def table(rows: list[dict]) -> str:
    """The shared sets' rows and one row of every group's summary (bench/RESULTS.md's table), then the rows of the
    cubic plant's seeds and of the paper's plants."""
    shared = [r for r in rows if r["group"] == "shared sets"]
    others = [r for r in rows if r["group"] != "shared sets"]
    groups = {group: [r for r in rows if r["group"] == group] for group in dict.fromkeys(r["group"] for r in rows)}
    one, free = ("; ".join(_summary(group, members, key) for group, members in groups.items())
                 for key in ("one_step", "free_run"))  # fmt: skip
    summary = f"| {'; '.join(map(_label, groups))} | {one} | | {free} | | |"
    return "\n".join([*_rows(shared), summary, "", *_rows(others)])


def _rows(rows: list[dict]) -> list[str]:
    lines = [
        "| data | one-step coverage: one number -> now | half-width / std(y) | free-run coverage: one number -> now "
        "| half-width / std(y) | test regressors far from the build data |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        said = " (said)" if r["said"] else ""
        lines.append(
            f"| {r['data']} | {r['one_step_before']:.1%} -> {r['one_step']:.1%} | {r['one_step_width']:.3f} | "
            f"{r['free_run_before']:.1%} -> {r['free_run']:.1%} | {r['free_run_width']:.3f} | {r['far']:.1%}{said} |"
        )
    return lines


def _label(group: str) -> str:
    return f"{group}, range" if group == "cubic plant" else f"{group}, mean ± std"


def _summary(group: str, rows: list[dict], key: str) -> str:
    """A group's coverage before -> now: the cubic plant's range over its seeds, another group's mean ± std."""
    now, before = np.array([r[key] for r in rows]), np.array([r[f"{key}_before"] for r in rows])
    if group == "cubic plant":
        return f"{before.min():.1%}-{before.max():.1%} -> {now.min():.1%}-{now.max():.1%}"
    return f"{before.mean():.1%} ± {before.std():.1%} -> {now.mean():.1%} ± {now.std():.1%}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the four small shared sets, the cubic plant, the paper")
    args = parser.parse_args()
    began = time.perf_counter()
    print(table(run(args.quick)))
    print(f"\n{time.perf_counter() - began:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
