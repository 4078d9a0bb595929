"""Coverage of the identifier's live 95 % one-step band (issue 43): the old y^ +- 1.96 y_hat_std against the live
band y^ +- y_hat_band (lenn_ros.core.spread.LiveBand), and the calibrations it was chosen from.

    python bench/live_band.py            # every shared set, the plant study's classes and the paper's examples
    python bench/live_band.py --quick    # the four small shared sets, 1 seed, short paper runs

Each record is stepped sample by sample through a Session, the node's path, with the node's defaults
(RLS LeNN, scales from the warm-up): learning on the build part, frozen on the test part, where the coverage
is measured, with the band each prediction was published with. "worst 1000" is the running coverage's
lowest over any 1 000 consecutive test samples (the whole test part when it is shorter). The
candidates are run on the same (error, std) stream the node's monitors see: the tracker at other
gains, a windowed empirical 95 % quantile of the last 1 000 normalised scores |e| / std, and ACI
(Gibbs & Candes 2021: alpha_t += gamma (0.05 - miss), the 1 - alpha_t quantile of that window).
Where the test part is not drawn like the build part the table says so: the paper's examples test on a
sinusoid after a uniform random training input, silverbox_arrow's end extrapolates.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peer_narx
import plant_study
from peer_narx import splits

from lenn_ros.config import resolve
from lenn_ros.core.spread import BAND_GAIN, BAND_MISS, Z95, LiveBand
from lenn_ros.paper.evaluation import simulate
from lenn_ros.paper.examples import get_example
from lenn_ros.service.building import build_identifier
from lenn_ros.session import Session, SessionConfig

WINDOW = 1000
#: the plant study's default classes and the two added after fit was fixed
PLANTS = ("tanks", "belt", "axis", "axis-p2p", "backlash", "wiener-hammerstein", "heater", "hammerstein-dead-time",
          "ph", "cstr")  # fmt: skip
UNLIKE_BUILD = {"silverbox_arrow (all test)": "end extrapolates"}


@dataclass
class Run:
    """What the node published for each sample of a record: y, y^, std and the live half-width (nan: none)."""

    y: np.ndarray
    y_hat: np.ndarray
    std: np.ndarray
    band: np.ndarray
    test_from: int  # 1-based


def stepped(u: np.ndarray, y: np.ndarray, test_from: int, values: dict | None = None) -> Run:
    """The record through a Session as the node steps it: learning before test_from, frozen from it."""
    values, network = resolve(values or {"example": 0})
    session = Session(build_identifier(values, network), SessionConfig(follow_test_start=True))
    session.set_test_start(test_from)
    y_hat, std, band = (np.full(len(y), np.nan) for _ in range(3))
    for k in range(len(y)):
        session.offer("u", float(u[k]), k * 0.01, sequence=k + 1)
        for sample in session.offer("y", float(y[k]), k * 0.01, sequence=k + 1):
            result = sample.result
            if result is not None and result.y_hat_std is not None:
                row = sample.index - 1
                y_hat[row], std[row], band[row] = result.y_hat, result.y_hat_std, result.y_hat_band
    return Run(np.asarray(y, float), y_hat, std, band, test_from)


def tracker(gain: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """LiveBand at ``gain`` over a stream of errors and stds: the half-width each prediction was published with."""

    def run(errors: np.ndarray, stds: np.ndarray) -> np.ndarray:
        band, out = LiveBand(gain), np.full(len(errors), np.nan)
        for k, (error, std) in enumerate(zip(errors.tolist(), stds.tolist(), strict=True)):
            if std == std and error == error:
                out[k] = band.half_width(std)
                band.update(error, out[k])
        return out

    return run


def window_quantile(aci_gain: float | None) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """The 95 % (ACI: 1 - alpha_t) empirical quantile of the last WINDOW scores |e| / std, times the std."""

    def run(errors: np.ndarray, stds: np.ndarray) -> np.ndarray:
        out, scores, alpha = np.full(len(errors), np.nan), [], BAND_MISS
        for k, (error, std) in enumerate(zip(errors.tolist(), stds.tolist(), strict=True)):
            if not (std == std and error == error):
                continue
            if len(scores) < 20:
                out[k] = Z95 * std
            else:
                level = min(max(1.0 - alpha, 0.0), 1.0)
                out[k] = float(np.quantile(scores[-WINDOW:], level)) * std
            if aci_gain is not None:
                alpha += aci_gain * (BAND_MISS - float(abs(error) > out[k]))
            scores.append(abs(error) / std if std > 0 else 0.0)
            if len(scores) > 2 * WINDOW:
                del scores[:WINDOW]
        return out

    return run


CANDIDATES: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "1.96 std": lambda errors, stds: Z95 * stds,
    **{f"tracker gamma {g:g}": tracker(g) for g in (0.003, 0.01, 0.02, 0.03, 0.05)},
    "window quantile": window_quantile(None),
    "ACI gamma 0.005": window_quantile(0.005),
}


def scored(run: Run, half: np.ndarray) -> tuple[float, float]:
    """(coverage, worst running coverage over WINDOW consecutive scored samples) on the test part."""
    test = slice(run.test_from - 1, None)
    e, h = run.y[test] - run.y_hat[test], half[test]
    keep = np.isfinite(e) & np.isfinite(h)
    inside = (np.abs(e[keep]) <= h[keep]).astype(float)
    if len(inside) <= WINDOW:
        return float(inside.mean()), float(inside.mean())
    sums = np.convolve(inside, np.ones(WINDOW), "valid") / WINDOW
    return float(inside.mean()), float(sums.min())


def measured(run: Run) -> dict[str, tuple[float, float]]:
    """Every candidate's (coverage, worst window) and the live band's as the session published it."""
    errors = run.y - run.y_hat
    out = {name: scored(run, make(errors, run.std)) for name, make in CANDIDATES.items()}
    out["live (y_hat_band)"] = scored(run, run.band)
    assert np.allclose(run.band, CANDIDATES[f"tracker gamma {BAND_GAIN:g}"](errors, run.std), equal_nan=True)
    return out


def records(quick: bool) -> list[tuple[str, str, list[Run]]]:
    """(group, name, one run per seed) of every record."""
    out = [("shared", s.name, [stepped(s.u, s.y, s.test_from)]) for s in splits(quick)]
    seeds = range(1 if quick else 3)
    for name in PLANTS[:2] if quick else PLANTS:
        runs = []
        for seed in seeds:
            u, y = plant_study.PLANTS[name](seed)
            runs.append(stepped(u, y, len(y) * 2 // 3 + 1))
        out.append(("plant", name, runs))
    train = 10_000 if quick else 50_000
    for number in (1, 2, 3, 4):
        example, runs = get_example(number), []
        for seed in seeds:
            series = simulate(example.plant(), example.noise_db, seed, train, 2_000, test_noise=True)
            if np.all(np.isfinite(series.y)):  # a plant that left every range gives no data to cover
                runs.append(stepped(series.u, series.y, train + 1))
        out.append(("paper", f"Ex. {number}", runs))
    return out


def cell(values: list[float]) -> str:
    return f"{100 * np.mean(values):.1f}" + (f" +- {100 * np.std(values):.1f}" if len(values) > 1 else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    quick = parser.add_argument("--quick", action="store_true") and parser.parse_args().quick
    peer_narx.DATA = Path(os.environ.get("LENN_ROS_DATA", str(peer_narx.DATA)))
    began = time.perf_counter()
    table = [(group, name, runs, [measured(run) for run in runs]) for group, name, runs in records(quick)]
    print("| record | test samples | seeds | 1.96 std % | worst 1000 | live band % | worst 1000 | test part |")
    print("|---|---|---|---|---|---|---|---|")
    for group, name, runs, results in table:
        old = [r["1.96 std"] for r in results]
        new = [r["live (y_hat_band)"] for r in results]
        drawn = "not like build: sinusoid after uniform" if group == "paper" else UNLIKE_BUILD.get(name, "like build")
        test = len(runs[0].y) - runs[0].test_from + 1
        print(f"| {name} | {test} | {len(runs)} | {cell([c for c, _ in old])} | {cell([w for _, w in old])} | "
              f"{cell([c for c, _ in new])} | {cell([w for _, w in new])} | {drawn} |")  # fmt: skip
    names = [*CANDIDATES]
    print("\nEach candidate per record: coverage % / worst 1000 % (mean over seeds)\n")
    print("| record | " + " | ".join(names) + " |\n|---|" + "---|" * len(names))
    for _, name, _, results in table:
        cells = [f"{100 * np.mean([r[c][0] for r in results]):.1f} / {100 * np.mean([r[c][1] for r in results]):.1f}"
                 for c in names]  # fmt: skip
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("\nCandidates over the records drawn like their build part (mean over seeds per record):\n")
    print("| calibration | mean coverage % | records outside 93-97 % | lowest | highest | mean worst 1000 |")
    print("|---|---|---|---|---|---|")
    like = [(g, n, r) for g, n, _, r in table if g != "paper" and n not in UNLIKE_BUILD]
    for name in [*CANDIDATES, "live (y_hat_band)"]:
        covers = [np.mean([r[name][0] for r in results]) for _, _, results in like]
        worst = [np.mean([r[name][1] for r in results]) for _, _, results in like]
        outside = sum(not 0.93 <= c <= 0.97 for c in covers)
        print(f"| {name} | {100 * np.mean(covers):.1f} | {outside} of {len(covers)} | {100 * min(covers):.1f} | "
              f"{100 * max(covers):.1f} | {100 * np.mean(worst):.1f} |")  # fmt: skip
    print(f"\n{time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
