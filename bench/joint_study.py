"""Free runs of `lenn-ros fit` on robot joints it was never developed on (issue 17): a table over seeds.

    python bench/joint_study.py                    # 200 Hz, 5 seeds, every joint variant
    python bench/joint_study.py --period 0.001     # 1 kHz
    python bench/joint_study.py --apart            # the test third recorded as a run of its own
    python bench/joint_study.py --ticks 4096       # a 12-bit encoder (1.5 mrad) instead of 0.1 mrad

A pendulum joint in radians (``paper.physical.FrictionJoint``: gravity, viscous and
Coulomb friction, stiction) under torque steps of +-2 N m (commands at 50 Hz, levels
held 0.2-1.2 s), measured with 0.2 mrad noise and 0.1 mrad resolution. Variants change
the physics, not the method: the default joint, a sticky one (Coulomb and stiction
three times larger), a horizontal one (no gravity: the angle drifts with the torque's
integral), a light one (half the inertia). 40 s at the rate given; the first two thirds
build the model with ``fit``'s defaults, the last third is simulated from its measured
start. The figures are the report's own (one-step and free-run NMSE over the test part).
``--apart``: the test third is another run (seed + 100, from rest at angle 0) appended to
the build part, as a benchmark file or two joined recordings have it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lenn_ros.fit.data import Data
from lenn_ros.fit.procedure import fit
from lenn_ros.fit.result import FitResult
from lenn_ros.paper.physical import FrictionJoint
from lenn_ros.paper.signals import Excitation

VARIANTS = {
    "default": {},
    "sticky": {"coulomb": 0.3, "stiction": 0.45},
    "horizontal": {"gravity": 0.0, "coulomb": 0.2, "stiction": 0.3},
    "light": {"inertia": 0.01},
}
COMMAND_PERIOD = 0.02  # 50 Hz controller


def record(
    variant: str, period: float, seconds: float, seed: int, resolution: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """(torques, measured angles) of one run: angle k is measured before torque k acts, in steps of
    ``resolution`` rad (an encoder's tick: 2 pi / 4096 = 1.5e-3 rad for a 12-bit one)."""
    n = round(seconds / period)
    hold = max(1, round(COMMAND_PERIOD / period))
    excitation = Excitation(seed, "steps")
    levels = [2.0 * excitation.sample(k)[0] for k in range(n // hold + 1)]
    torques = np.array([levels[k // hold] for k in range(n)])
    if variant == "horizontal":  # keep the angle bounded: the torque's mean removed per 4 s stretch
        stretch = round(4.0 / period)
        for a in range(0, n, stretch):
            torques[a : a + stretch] -= torques[a : a + stretch].mean()
    angles = FrictionJoint(period=period, **VARIANTS[variant]).run(torques)[:n]
    rng = np.random.default_rng(seed + 1000)
    return torques, np.round((angles + rng.normal(0.0, 2e-4, n)) / resolution) * resolution


def spread(values: list[float]) -> str:
    """'mean (min..max)' of a figure over seeds, as the tables give it."""
    return f"{np.mean(values):.1f} ({min(values):.1f}..{max(values):.1f})"


def timed_fit(u: np.ndarray, y: np.ndarray, name: str, test_from: int) -> tuple[FitResult, float]:
    """(``fit``'s result with its defaults, the seconds it took)."""
    began = time.perf_counter()
    report = fit(Data(u, y, name), test_from)
    return report, time.perf_counter() - began


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--period", type=float, default=0.005)
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--apart", action="store_true", help="the test third recorded as a run of its own")
    parser.add_argument("--ticks", type=int, default=0, help="an encoder of this many ticks per turn (0: 0.1 mrad)")
    args = parser.parse_args(argv)
    print(f"| joint ({1 / args.period:.0f} Hz, {args.seconds:.0f} s) | one-step NMSE dB, mean (min..max) | "
          "free-run NMSE dB, mean (min..max) | fit time s, mean | models chosen |")  # fmt: skip
    print("|---|---|---|---|---|")
    for variant in args.variants.split(","):
        one, free, seconds, models = [], [], [], []
        for seed in range(args.seeds):
            resolution = 2.0 * np.pi / args.ticks if args.ticks else 1e-4
            u, y = record(variant, args.period, args.seconds, seed, resolution)
            test_from = len(y) * 2 // 3 + 1
            if args.apart:
                u_test, y_test = record(variant, args.period, args.seconds / 3, seed + 100, resolution)
                u, y = np.r_[u[: test_from - 1], u_test], np.r_[y[: test_from - 1], y_test]
            report, took = timed_fit(u, y, f"{variant} seed {seed}", test_from)
            seconds.append(took)
            one.append(report.nmse_db)
            free.append(report.nmse_free_run_db)
            m = report.model
            models.append(f"{m['family']} {m['structure']['y_lags']}/{m['n_terms']}")
        print(
            f"| {variant} | {spread(one)} | {spread(free)} | {np.mean(seconds):.1f} | {', '.join(models)} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
