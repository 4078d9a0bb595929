"""The figures of docs/using.md: an alarm over a day with one change, and the live band over a test part.

Both on the servo axis of bench/change_alarm.py, fitted the day before and run as the node runs it:

- ``docs/alarm_day.png``: 10 minutes at 100 Hz, rests and moves, the friction up 50 % at minute 6;
  panels: the axis, each block's free-run error over its learnt level (novel blocks marked), the statistic
  against the threshold with the alarm shaded;
- ``docs/band_test.png``: the last 6 s of the test part (frozen), the measured output, y^ and y^ +- y_hat_band.

    python bench/docs_figures.py
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from change_alarm import RATE, fitted, plant_log  # noqa: E402  (this folder: one definition of the plant)

from lenn_ros.plotting import save  # noqa: E402
from lenn_ros.service.building import identifier_from_params, make_session  # noqa: E402

CHANGE_AT = 36_000  # minute 6


def alarm_day(params: Path, path: Path) -> None:
    pieces = [(12_000, {}), (3_000, {"rest": True}), (15_000, {"amplitude": 0.5}), (30_000, {})]
    u, y = plant_log("servo_axis", 21, 60_000, pieces=pieces)
    _, changed = plant_log("servo_axis", 21, 60_000, "friction", CHANGE_AT, 0.5, pieces=pieces)
    y[CHANGE_AT:] = changed[CHANGE_AT:]  # (the same drive and noise; the plant changed from CHANGE_AT on)
    identifier, values = identifier_from_params(str(params))
    session = make_session(identifier, values)
    detector = session.monitors.outputs[0].change
    blocks: list[tuple[int, float, float, bool]] = []
    block = detector._block

    def watched(index: int, seed: int) -> str:
        novel, tested = detector.novel, detector.tested
        event = block(index, seed)
        if detector.novel > novel or detector.tested > tested or detector.alarm:
            blocks.append((index, detector.ratio, detector.statistic, detector.novel > novel))
        return event

    detector._block = watched
    session.run_samples(np.arange(1, len(u) + 1), u, y, np.ones(len(u), bool))
    status = session.status()["change"]
    figure = Figure(figsize=(8.0, 6.4), dpi=110)
    FigureCanvasAgg(figure)
    top, middle, bottom = figure.subplots(3, 1, sharex=True)
    t = np.arange(len(y)) / RATE
    top.plot(t, u, color="tab:gray", linewidth=0.7, label="setpoint u")
    top.plot(t, y, color="black", linewidth=0.8, label="load angle y")
    top.axvline(CHANGE_AT / RATE, color="tab:red", linestyle="--", linewidth=1.0, label="friction +50 %")
    top.set_ylabel("rad")
    top.legend(loc="lower left", ncols=3, fontsize=8, bbox_to_anchor=(0.0, 1.0))
    at = np.array([b[0] for b in blocks]) / RATE
    ratio = np.array([b[1] for b in blocks])
    novel = np.array([b[3] for b in blocks])
    middle.semilogy(at[~novel], ratio[~novel], ".", markersize=3, color="tab:blue", label="tested block")
    if novel.any():
        middle.semilogy(at[novel], np.full(novel.sum(), max(ratio.max(), 1.0)), "x", color="tab:orange",
                        markersize=4, label="novel: not tested")  # fmt: skip
    middle.set_ylabel("free-run error /\nlearnt level")
    middle.legend(loc="upper left", fontsize=8)
    statistic = np.array([b[2] for b in blocks])
    bottom.plot(at, statistic, color="tab:purple", linewidth=1.0, label="CUSUM statistic")
    bottom.axhline(detector.threshold, color="tab:red", linewidth=0.8, label=f"threshold {detector.threshold:g}")
    if status["raised_at"] is not None:
        bottom.axvspan(status["raised_at"] / RATE, t[-1], color="tab:red", alpha=0.12, label="alarm on")
    bottom.set_ylim(0.0, max(2.0 * detector.threshold, min(float(statistic.max()), 20.0)))
    bottom.set_ylabel("statistic")
    bottom.set_xlabel("time (s)")
    bottom.legend(loc="upper left", fontsize=8)
    raised = status["raised_at"]
    delay = "none" if raised is None else f"{(raised - CHANGE_AT) / RATE:.2f} s after"
    figure.suptitle(f"a day of a servo axis: alarm {delay} the change; {status['count']} alarm(s)", fontsize=10)
    save(figure, path)
    print(f"{path}: alarms {status['count']}, raised at {raised}, change at {CHANGE_AT}, kind {status['kind']}")


def band_test(params: Path, path: Path) -> None:
    u, y = plant_log("servo_axis", 22, 30_000)
    identifier, values = identifier_from_params(str(params))
    session = make_session(identifier, values)
    learn = np.arange(len(y)) < 24_000
    y_hat = session.run_samples(np.arange(1, len(y) + 1), u, y, learn)
    band = session.last_y_hat_band
    test = slice(24_000, None)
    inside = np.abs(y[test] - y_hat[test]) <= band[test]
    scored = np.isfinite(band[test])
    coverage = float(np.mean(inside[scored]))
    shown = slice(len(y) - 600, len(y))
    t = np.arange(len(y))[shown] / RATE
    figure = Figure(figsize=(8.0, 4.8), dpi=110)
    FigureCanvasAgg(figure)
    top, bottom = figure.subplots(2, 1, sharex=True, height_ratios=(1, 1.3))
    top.plot(t, y[shown], color="black", linewidth=1.2, label="measured y")
    top.plot(t, y_hat[shown], color="tab:red", linewidth=0.8, label="one-step y^")
    top.set_ylabel("rad")
    top.legend(loc="lower left", ncols=2, fontsize=8, bbox_to_anchor=(0.0, 1.0))
    error = (y - y_hat)[shown]
    bottom.fill_between(t, -band[shown], band[shown], color="tab:red", alpha=0.2, linewidth=0,
                        label="+- y_hat_band (live 95 %)")  # fmt: skip
    bottom.plot(t, error, color="black", linewidth=0.7, label="error y - y^")
    outside = np.abs(error) > band[shown]
    bottom.plot(t[outside], error[outside], "o", color="tab:red", markersize=3, label="outside the band")
    bottom.set_ylabel("rad")
    bottom.set_xlabel("time (s)")
    bottom.legend(loc="lower left", ncols=3, fontsize=8)
    figure.suptitle(f"the live band over a test part: covers {coverage:.1%} of its {int(scored.sum())} samples",
                    fontsize=10)  # fmt: skip
    save(figure, path)
    print(f"{path}: coverage {coverage:.3f} over {int(scored.sum())} test samples, half-width median "
          f"{np.nanmedian(band[test]):.3g} rad")  # fmt: skip


def main() -> None:
    params = fitted("servo_axis", Path(tempfile.mkdtemp(prefix="docs_figures_")))
    alarm_day(params, REPO / "docs" / "alarm_day.png")
    band_test(params, REPO / "docs" / "band_test.png")


if __name__ == "__main__":
    main()
