"""The change alarm (lenn_ros.core.change) measured on plants it never saw, fitted the day before (issue 43).

Two plant classes, each fitted by ``fit`` on a 10-minute log of "the day before" (its own seed), then run
through the session as the node runs it (``make_session`` over fit's params) on 10-minute logs at 100 Hz:

- ``servo_axis``: a belt drive under its own PD loop, driven point to point (``paper.physical.ServoAxis``);
- ``friction_joint``: a pendulum joint with Coulomb friction and stiction under torque steps.

Per class: changes of gain -20 %, friction +50 %, payload +30 % and an output offset of +0.01 rad at a
seed-dependent sample (seeds 0-3); the unchanged plant driven differently (faster, another region, small
then large moves, rests; seeds 0-3); and the unchanged plant for 10^6 samples (17 logs). Printed: the delay
to each alarm, the false alarms, and the threshold sweep: the detection rate (within 2 s, and at all) against
the false alarms per hour. The sweep is exact for first alarms: before its first alarm the detector's state
does not depend on the threshold, so one run per log (threshold infinite, the statistic after every tested
block kept) gives each threshold's first alarm.

    python bench/change_alarm.py [--quick]
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lenn_ros.core.change import DEFAULT_THRESHOLD
from lenn_ros.fit.data import Data
from lenn_ros.fit.export import write_outputs
from lenn_ros.fit.procedure import fit
from lenn_ros.paper.physical import FrictionJoint, ServoAxis, changed_run
from lenn_ros.paper.signals import point_to_point
from lenn_ros.service.building import identifier_from_params, make_session

RATE = 100.0
NOISE, TICK = 2e-4, 1e-4
CHANGES = {"gain": -0.2, "friction": 0.5, "payload": 0.3, "offset": 0.01}
WITHIN = 200  # samples: 2 s
THRESHOLDS = (1.5, 2.0, 3.0, 4.0, 6.0, 8.0)


def torque_steps(rng: np.random.Generator, samples: int, amplitude: float = 2.0, hold=(0.2, 1.2), centre=0.0):
    out, k = np.empty(samples), 0
    while k < samples:
        count = max(1, int(rng.uniform(*hold) * RATE))
        out[k : k + count] = centre + amplitude * rng.uniform(-1.0, 1.0)
        k += count
    return out


#: excitation changes of an unchanged plant, per class: pieces of (samples, keywords), "rest": input held
DRIVEN = {
    "servo_axis": {
        "faster": [(30_000, {"speed": 0.5}), (30_000, {"speed": 4.0})],
        "region": [(30_000, {"amplitude": 0.4, "centre": -0.5}), (30_000, {"amplitude": 0.4, "centre": 0.5})],
        "small then large": [(30_000, {"amplitude": 0.3}), (30_000, {"amplitude": 1.0})],
        "rests": [(20_000, {}), (6_000, {"rest": True}), (10_000, {}), (3_000, {"rest": True}), (21_000, {})],
    },
    "friction_joint": {
        "faster": [(30_000, {"hold": (1.0, 3.0)}), (30_000, {"hold": (0.05, 0.3)})],
        "region": [(30_000, {"amplitude": 0.8, "centre": -1.0}), (30_000, {"amplitude": 0.8, "centre": 1.0})],
        "small then large": [(30_000, {"amplitude": 0.6}), (30_000, {"amplitude": 2.0})],
        "rests": [(20_000, {}), (6_000, {"rest": True}), (10_000, {}), (3_000, {"rest": True}), (21_000, {})],
    },
}


def plant_log(plant: str, seed: int, samples: int, kind="gain", at=None, size=0.0, pieces=None):
    rng = np.random.default_rng(seed)
    drive = (lambda n, **k: point_to_point(rng, n, 1.0 / RATE, **k)) if plant == "servo_axis" else (
        lambda n, **k: torque_steps(rng, n, **k))  # fmt: skip
    if pieces is None:
        u = drive(samples)
    else:
        parts: list[np.ndarray] = []
        for count, keywords in pieces:
            held = np.full(count, (parts[-1][-1] if parts else 0.0) if plant == "servo_axis" else 0.0)
            parts.append(held if keywords.get("rest") else drive(count, **keywords))
        u = np.concatenate(parts)[:samples]
    model = ServoAxis(period=1.0 / RATE) if plant == "servo_axis" else FrictionJoint(period=1.0 / RATE)
    y = changed_run(model, u, at, kind, size)
    return u, np.round((y + rng.normal(0.0, NOISE, len(y))) / TICK) * TICK


def fitted(plant: str, folder: Path) -> Path:
    u, y = plant_log(plant, 1000, 60_000)
    data = Data(u=u, y=y, source=f"{plant}, the day before")
    return Path(write_outputs(folder / plant, fit(data, test_from=48_000), data)["params"])


def trace(params: Path, u: np.ndarray, y: np.ndarray) -> tuple[list[tuple[int, float]], dict]:
    """The statistic after every tested block (threshold infinite: no alarm changes the state), and the status."""
    identifier, values = identifier_from_params(str(params))
    session = make_session(identifier, values)
    detector = session.monitors.outputs[0].change
    detector.threshold = math.inf
    kept: list[tuple[int, float]] = []
    block = detector._block

    def watched(index: int, seed: int) -> str:
        tested, rise = detector.tested, detector.relearnt_rise
        event = block(index, seed)
        if detector.tested > tested:
            kept.append((index, detector.statistic))
        if detector.relearnt_rise is not rise:  # a level learnt anew after novel motion, judged as S is
            kept.append((index, detector.relearnt_rise))
        return event

    detector._block = watched
    session.run_samples(np.arange(1, len(u) + 1), u, y, np.ones(len(u), bool))
    return kept, session.status()["change"]


def first_alarm(kept: list[tuple[int, float]], threshold: float, after: int = 0) -> int | None:
    return next((index for index, statistic in kept if statistic > threshold and index >= after), None)


def main() -> None:  # noqa: C901, PLR0915  (a report: one pass, its tables)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 seeds, 3 unchanged logs per class")
    quick = parser.parse_args().quick
    seeds = range(2) if quick else range(4)
    unchanged = range(10, 13) if quick else range(10, 27)
    began = time.perf_counter()
    folder = Path(tempfile.mkdtemp(prefix="change_alarm_"))
    changed: dict = {}  # (plant, kind) -> [(delay or None, false before)]
    nulls: dict = {}  # plant -> [(kept, samples, label)]
    status_rows = []
    for plant in ("servo_axis", "friction_joint"):
        params = fitted(plant, folder)
        for kind, size in CHANGES.items():
            for seed in seeds:
                at = 15_000 + int(np.random.default_rng(seed + 77).integers(0, 35_000))
                kept, status = trace(params, *plant_log(plant, seed, 60_000, kind, at, size))
                changed.setdefault((plant, kind), []).append((kept, at))
                status_rows.append((plant, kind, seed, status["armed"], status["reference_nmse_db"]))
        for label, pieces in DRIVEN[plant].items():
            for seed in seeds:
                kept, status = trace(params, *plant_log(plant, seed, 60_000, pieces=pieces))
                nulls.setdefault(plant, []).append((kept, 60_000, label, status["blocks_novel"]))
        for seed in unchanged:
            kept, status = trace(params, *plant_log(plant, seed, 60_000))
            nulls[plant].append((kept, 60_000, "unchanged", status["blocks_novel"]))
    print(f"threshold {DEFAULT_THRESHOLD:g} (the default): delay from the change to the alarm, samples at 100 Hz "
          f"(- = none in the log; * = an alarm before the change)\n")  # fmt: skip
    print("| plant | change | delays per seed | within 2 s | detected |\n|---|---|---|---|---|")
    for (plant, kind), runs in changed.items():
        cells, within, found = [], 0, 0
        for kept, at in runs:
            before = first_alarm(kept, DEFAULT_THRESHOLD)
            alarm = first_alarm(kept, DEFAULT_THRESHOLD, at)
            false = before is not None and before < at
            delay = None if alarm is None else alarm - at
            cells.append(("*" if false else "") + ("-" if delay is None else str(delay)))
            within += delay is not None and delay <= WITHIN and not false
            found += delay is not None and not false
        print(
            f"| {plant} | {kind} {CHANGES[kind]:+g} | {' '.join(cells)} | {within}/{len(runs)} | {found}/{len(runs)} |"
        )
    print("\n| plant | unchanged plant driven | logs | samples | logs with an alarm | novel blocks (mean) |")
    print("|---|---|---|---|---|---|")
    for plant, runs in nulls.items():
        for label in dict.fromkeys(label for _, _, label, _ in runs):
            mine = [r for r in runs if r[2] == label]
            alarmed = sum(first_alarm(kept, DEFAULT_THRESHOLD) is not None for kept, *_ in mine)
            novel = np.mean([r[3] for r in mine])
            print(f"| {plant} | {label} | {len(mine)} | {sum(r[1] for r in mine)} | {alarmed} | {novel:.0f} |")
    print("\nthreshold sweep (first alarms; changes gain, friction, payload; false alarms on every unchanged log, "
          "the excitation changes included, per hour at 100 Hz)\n")  # fmt: skip
    print("| threshold | plant | detected within 2 s | detected | median delay | false alarms per hour |")
    print("|---|---|---|---|---|---|")
    for threshold in THRESHOLDS:
        for plant in nulls:
            delays = []
            for kind in ("gain", "friction", "payload"):
                for kept, at in changed[(plant, kind)]:
                    before = first_alarm(kept, threshold)
                    alarm = first_alarm(kept, threshold, at)
                    delays.append(None if alarm is None or (before is not None and before < at) else alarm - at)
            hours = sum(r[1] for r in nulls[plant]) / RATE / 3600
            false = sum(first_alarm(kept, threshold) is not None for kept, *_ in nulls[plant])
            false += sum(  # changed logs: an alarm before the change
                (b := first_alarm(kept, threshold)) is not None and b < at
                for kind in ("gain", "friction", "payload", "offset") for kept, at in changed[(plant, kind)]
            )  # fmt: skip
            hours += sum(at for kind in CHANGES for _, at in changed[(plant, kind)]) / RATE / 3600
            found = [d for d in delays if d is not None]
            print(
                f"| {threshold:g}{' (default)' if threshold == DEFAULT_THRESHOLD else ''} | {plant} | "
                  f"{sum(d <= WITHIN for d in found)}/{len(delays)} | {len(found)}/{len(delays)} | "
                  f"{np.median(found) if found else '-'} | {false / hours:.2f} ({false} in {hours:.1f} h) |"
            )  # fmt: skip
    armed = {plant: np.mean([r[4] for r in status_rows if r[0] == plant]) for plant in nulls}
    print(
        f"\nreferences (fit's models) simulate at: {', '.join(f'{p} {v:.1f} dB' for p, v in armed.items())}; "
        f"{time.perf_counter() - began:.0f} s"
    )


if __name__ == "__main__":
    main()
