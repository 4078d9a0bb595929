"""Coverage of ``lenn-ros fit``'s nominal 95 % bands on every shared data set, a plant like its training, the
paper's example plants and the plant study's classes (issues 20 and 43).

For each set: ``fit`` with its defaults on the README split (the plant study's: its last third), then the
fraction of the test samples inside the one-step band and inside the free-run band (both calibrated on the
errors of the selection's held-out blocks, see ``lenn_ros.fit.bands``), with the range each band covered of
the held-out blocks when calibrated on the other blocks (how far a test part's coverage may stray), the bands'
mean half-widths relative to the test output's standard deviation and the share of test regressors farther
from the build data than 99 % of the build rows. A band is honest when its coverage sits near 95 % on data it
was not built from; the plant whose test part is drawn like its training (test_fit.py's cubic plant, seeds 3-8)
must stay within 93-97 %. The paper's plants are trained on a random input and tested on a sinusoid (3000 +
1000 samples, seed 0, noise in both parts): test parts unlike the build part. Printed: the shared sets with one
row summing up every group (bench/RESULTS.md's tables), then each plant's seeds in one row.

    python bench/intervals.py [--quick]    (about 12 min on two busy cores; --quick: the four small sets, no
                                            plant study)
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

from lenn_ros.fit.data import Data
from lenn_ros.fit.procedure import fit

#: the cubic plant's seeds (test_fit.py's, test_fit_bands.py's) and its split
CUBIC_SEEDS = range(3, 9)
#: plant_study.py's classes (a variant of each kind) and seeds, split as it splits them (the last third tested)
STUDY_PLANTS = ("tanks", "belt", "axis", "axis-p2p", "backlash", "wiener-hammerstein", "hammerstein", "heater", "ph",
                "cstr")  # fmt: skip
STUDY_SEEDS = (0, 1, 2)


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
    if quick:
        return
    from plant_study import PLANTS

    for name in STUDY_PLANTS:
        for seed in STUDY_SEEDS:
            u, y = PLANTS[name](seed)[:2]
            yield "plant study", f"{name} {seed}", u, y, len(y) * 2 // 3 + 1


def measure(name: str, u: np.ndarray, y: np.ndarray, test_from: int) -> dict:
    """One case's coverage and mean half-widths of both bands, now and as one number."""
    report = fit(Data(u, y, name), test_from)
    part, bands = report.only, report.intervals
    one, free = bands["one_step"], bands["free_run"]
    spread = float(np.std(report.y_test))
    return {
        "one_step": one["coverage_test"],
        "one_step_width": float(np.nanmean(part.one_step_half_width_test)) / spread,
        "free_run": free["coverage_test"],
        "free_run_width": float(np.nanmean(part.free_run_half_width_test)) / spread,
        "far": one.get("far_from_build_test", float("nan")),
        "said": bool(bands.get("unlike_build")),
        "one_step_blocks": one.get("held_out_blocks_covered"),
        "free_run_blocks": free.get("held_out_blocks_covered"),
    }


def run(quick: bool) -> list[dict]:
    rows = []
    for group, name, u, y, test_from in cases(quick):
        began = time.perf_counter()
        rows.append({"group": group, "data": name, **measure(name, u, y, test_from)})
        print(f"{name}: done in {time.perf_counter() - began:.1f} s", file=sys.stderr, flush=True)
    return rows


def table(rows: list[dict]) -> str:
    """bench/RESULTS.md's tables: the shared sets' rows, one row summing up every group, then one row per plant of
    the others (its seeds' coverage in turn, * where the report said the test part is unlike the build part)."""
    shared = [r for r in rows if r["group"] == "shared sets"]
    groups = {group: [r for r in rows if r["group"] == group] for group in dict.fromkeys(r["group"] for r in rows)}
    one, free = ("; ".join(_summary(members, key) for members in groups.values()) for key in ("one_step", "free_run"))
    summary = f"| {'; '.join(groups)}: mean ± std, within 92-98 % where not said unlike | {one} | | {free} | | |"
    plants: dict[str, list[dict]] = {}
    for r in rows:
        if r["group"] != "shared sets":
            plants.setdefault(
                r["data"].rsplit(" ", 1)[0] if r["group"] != "paper's plants" else "paper Ex. 1-4", []
            ).append(r)
    lines = ["", "| plant (seeds) | one-step coverage | free-run coverage |", "|---|---|---|"]
    for plant, members in plants.items():
        one, free = (
            ", ".join(f"{r[key]:.1%}{'*' if r['said'] else ''}" for r in members) for key in ("one_step", "free_run")
        )
        lines.append(f"| {plant} | {one} | {free} |")
    return "\n".join([*_rows(shared), summary, *lines])


def _rows(rows: list[dict]) -> list[str]:
    lines = [
        "| data | one-step coverage (held-out blocks) | half-width / std(y) | free-run coverage (held-out blocks) "
        "| half-width / std(y) | test regressors far from the build data |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        said = " (said)" if r["said"] else ""
        lines.append(
            f"| {r['data']} | {r['one_step']:.1%} ({_range(r['one_step_blocks'])}) | {r['one_step_width']:.3f} | "
            f"{r['free_run']:.1%} ({_range(r['free_run_blocks'])}) | {r['free_run_width']:.3f} | {r['far']:.1%}{said} |"
        )
    return lines


def _range(covered: list[float] | None) -> str:
    return f"{covered[0]:.1%}-{covered[1]:.1%}" if covered else "-"


def _summary(rows: list[dict], key: str) -> str:
    """A group's coverage, mean ± std, and how many of its records drawn like their build part are within 92-98 %."""
    now = np.array([r[key] for r in rows])
    alike = [r[key] for r in rows if not r["said"]]
    within = sum(0.92 <= value <= 0.98 for value in alike)
    return f"{now.mean():.1%} ± {now.std():.1%}, {within} of {len(alike)}"


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
