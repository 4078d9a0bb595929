"""The change alarm (lenn_ros.core.change) measured: false alarms and detection delay, over seeds (issue 20).

1. i.i.d. Gaussian errors: the mean run length to a false alarm per threshold (10^6
   samples each), and its log-linear extrapolation to the design rate 10^7.
2. Unchanged plants identified online, 10^6 samples per seed: alarms raised, largest S.
3. An actuator gain step of -20 % at a seed-dependent sample: delay to the alarm
   (samples; 200 = 2 s at 100 Hz) and to its clearing.

    python bench/change_alarm.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from test_change import SCENARIOS, run  # (one definition of the scenarios and of a run)

from lenn_ros.core.change import DEFAULT_THRESHOLD, DESIGN_RUN_LENGTH, RAISED, ChangeDetector


def gaussian_table(samples: int) -> list[tuple[float, int, float]]:
    errors = np.random.default_rng(0).standard_normal(samples).tolist()
    rows = []
    for threshold in (9.0, 12.0, 15.0, 18.0, 21.0):
        detector = ChangeDetector(threshold=threshold)
        alarms = sum(detector.update(e, k) == RAISED for k, e in enumerate(errors))
        rows.append((threshold, alarms, samples / max(alarms, 1)))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    quick = parser.parse_args().quick
    began = time.perf_counter()
    rows = gaussian_table(200_000 if quick else 1_000_000)
    print("| threshold | false alarms | mean run length (samples) |\n|---|---|---|")
    for threshold, alarms, length in rows:
        print(f"| {threshold:g} | {alarms} | {length:.3g} |")
    slope, intercept = np.polyfit([r[0] for r in rows], np.log([r[2] for r in rows]), 1)
    needed = (np.log(DESIGN_RUN_LENGTH) - intercept) / slope
    at_default = np.exp(intercept + slope * DEFAULT_THRESHOLD)
    print(f"\nlog-linear fit: x{np.exp(3 * slope):.2f} per +3; 10^7 at threshold {needed:.1f}; at the default "
          f"{DEFAULT_THRESHOLD:g}: {at_default:.2g} samples\n")  # fmt: skip
    length = 200_000 if quick else 1_000_000
    print("| plant (identifier) | seed | samples | false alarms |\n|---|---|---|---|")
    for scenario in sorted(SCENARIOS):
        for seed in range(3):
            live = run(scenario, 100 + seed, length, length, input_gain=1.0)
            print(f"| {scenario} | {100 + seed} | {length} | {live.change.count} |")
    head = "| plant (identifier) | seeds | detected within 200 | delay mean | spread (std) | max | cleared (median) |"
    print(f"\n{head}")
    print("|---|---|---|---|---|---|---|")
    for scenario in sorted(SCENARIOS):
        delays, clears = [], []
        seeds = range(3 if quick else 8)
        for seed in seeds:
            change_at = 20_000 + 1_013 * seed
            live = run(scenario, seed, change_at + 20_000, change_at)
            notices = [n for n in live.take_notices() if n.kind.startswith("change")]
            raised = [int(n.text.split("sample ")[1].split(":")[0].split()[0]) for n in notices if n.kind == "change"]
            after = [r for r in raised if r > change_at]
            if after:
                delays.append(after[0] - change_at - 1)
            cleared = [n for n in notices if n.kind == "change_cleared"]
            if cleared:
                clears.append(int(cleared[0].text.split("sample ")[1].split(":")[0]) - change_at)
        d = np.array(delays)
        print(f"| {scenario} | {len(seeds)} | {np.sum(d <= 200)}/{len(seeds)} | {d.mean():.0f} | {d.std():.0f} | "
              f"{d.max()} | {np.median(clears) if clears else 'never'} ({len(clears)} of {len(seeds)}) |")  # fmt: skip
    print(f"\n{time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
