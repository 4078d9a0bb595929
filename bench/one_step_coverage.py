"""Coverage of the identifier's live nominal 95 % one-step band (lenn_ros.core.spread), issue 20.

The band is y^(k) +- 1.96 y_hat_std(k), as the node publishes it. Each shared real data
set (../shared/data, the README splits of bench/peer_narx.py) is stepped sample by
sample through a Session, the node's path, with the node's defaults ("my own plant":
RLS LeNN, scales from the warm-up): learning on the build part, frozen on the held-back
test part, where the coverage and the band's mean half-width (over the test output's
std) are measured. The paper's examples: their preset network (SGD: no P, the EWMA
residual std alone) and the default RLS model, 3 seeds, noise on the test too.

    python bench/one_step_coverage.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peer_narx
from peer_narx import splits

from lenn_ros.config import resolve
from lenn_ros.core.metrics import coverage
from lenn_ros.core.spread import Z95
from lenn_ros.paper.evaluation import simulate
from lenn_ros.paper.examples import get_example
from lenn_ros.service.building import build_identifier
from lenn_ros.session import Session, SessionConfig


def stepped(values: dict, u: np.ndarray, y: np.ndarray, test_from: int) -> tuple[float, float]:
    """(coverage, mean half-width / std(y_test)) of the band on rows test_from-1.. (1-based test_from)."""
    values, network = resolve(values)
    session = Session(build_identifier(values, network), SessionConfig(follow_test_start=True))
    session.set_test_start(test_from)
    y_hat = np.full(len(y), np.nan)
    std = np.full(len(y), np.nan)
    for k in range(len(y)):
        session.offer("u", float(u[k]), k * 0.01, sequence=k + 1)
        for sample in session.offer("y", float(y[k]), k * 0.01, sequence=k + 1):
            result = sample.result
            if result is not None and result.y_hat_std is not None:
                y_hat[sample.index - 1], std[sample.index - 1] = result.y_hat, result.y_hat_std
    test = slice(test_from - 1, None)
    half = Z95 * std[test]
    return coverage(y[test], y_hat[test], half), float(np.nanmean(half) / np.std(y[test]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    quick = parser.parse_args().quick
    # a git worktree is not beside ../shared: LENN_ROS_DATA names the data directory then
    peer_narx.DATA = Path(os.environ.get("LENN_ROS_DATA", str(peer_narx.DATA)))
    began = time.perf_counter()
    print("| data set | test samples | coverage of the 95 % band | mean half-width / std(y_test) |\n|---|---|---|---|")
    for split in splits(quick):
        cover, width = stepped({"example": 0}, split.u, split.y, split.test_from)
        print(f"| {split.name} | {len(split.y) - split.test_from + 1} | {cover:.3f} | {width:.3f} |")
    print("\n| example | identifier | coverage mean | spread (std, 3 seeds) | half-width / std(y_test) |")
    print("|---|---|---|---|---|")
    train = 10_000 if quick else 50_000
    for number in (1, 2, 3, 4):
        example = get_example(number)
        for label, values in (("preset (SGD)", {"example": number}), ("RLS default", {"example": 0})):
            rows, skipped = [], []
            for seed in range(3):
                series = simulate(example.plant(), example.noise_db, seed, train, 2_000, test_noise=True)
                if not np.all(np.isfinite(series.y)):  # the plant itself left every range: no data to cover
                    skipped.append(seed)
                    continue
                rows.append(stepped(values, series.u, series.y, train + 1))
            covers, widths = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
            left_out = ", ".join(map(str, skipped))
            note = f" (seed {left_out}: the simulated plant's y is not finite, left out)" if skipped else ""
            print(f"| {number} | {label} | {covers.mean():.3f} | {covers.std():.3f} | {widths.mean():.3f}{note} |")
    print(f"\n{time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
