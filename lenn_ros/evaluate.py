"""``lenn-ros evaluate BAG``: the identifier's own computation over a recording, printed.

The front-end of :func:`lenn_ros.service.evaluation.evaluate_bag` (which says what is read and how
the test part is chosen): it parses nothing itself and no library module imports it.
"""

from __future__ import annotations

import json
import math
import sys
from typing import Any

import numpy as np

from lenn_ros.service import RecordingError
from lenn_ros.service.evaluation import BagEvaluation, evaluate_bag
from lenn_ros.service.reading import flags_of
from lenn_ros.service.records import evaluate_bags
from lenn_ros.service.scoring import fit_free_run_widths


def one_step_lines(name: str, band: dict[str, Any]) -> list[str]:
    """The node's one-step bands over the test part: 1.96 y_hat_std, and the live band y_hat_band."""
    width, covered, live = band["median_half_width"], band["coverage_test"], band["live"]
    return [
        f"  {name}one-step 95 % band (1.96 y_hat_std, median +-{width:.4g}): covers {covered:.1%}",
        f"  {name}live 95 % band (y_hat_band, median +-{live['median_half_width']:.4g}): covers "
        f"{live['coverage_test']:.1%}",
    ]


def band_lines(intervals: dict[str, Any]) -> list[str]:
    """The one-step and free-run 95 % bands and their coverage of the test part, one line each."""
    lines = []
    one, run = intervals.get("one_step"), intervals.get("free_run")
    if one:
        lines += one_step_lines("", one)
    if run:
        how = "by steps since the run's start, median " if "by_horizon" in run else ""
        lines.append(
            f"  free-run 95 % band of the fit ({how}+-{run['half_width']:.4g}): covers {run['coverage_test']:.1%} here"
        )
    return lines


def main(args) -> int:
    progress = sys.stderr.isatty() and not args.json
    bags = [args.bag] if isinstance(args.bag, str) else list(args.bag)
    if len(bags) > 1:
        return _several(args, bags, progress)
    bag = bags[0]
    result = evaluate_bag(bag, args.params, args.test_from, getattr(args, "node", "/identifier"), flags_of(args),
                          progress)  # fmt: skip
    if args.plot:
        _plot(args, result, bag)
    d = result.as_dict()
    if args.json:
        print(json.dumps(d, indent=1, default=lambda value: None))
        return 0
    print(f"bag {bag}: {d['pairs']} samples from {d['source']}, test from sample {d['test_start']}")
    if result.test_default:
        print(f"  {result.test_default}")
    if d["weights_in"]:
        print(f"  learning started from the weights in {d['weights_in']} (weights_in)")
    for line in d["gaps"]:
        print(f"  {line}")
    print(f"  trained on {d['trained']} samples, scored {d['samples']} test samples, skipped {d['skipped']}")
    for line in _figure_lines(result, d):
        print(line)
    for warning in d["warnings"]:
        print(f"  WARNING: {warning}")
    for notice in d["notices"]:
        print(f"  note: {notice}")
    return 0


def _figure_lines(result: BagEvaluation, d: dict[str, Any]) -> list[str]:
    """The scores: one output's two lines and bands, or several outputs' table and bands."""
    lines = []
    if result.single:
        for label, key, rmse_key in (
            ("one-step", "nmse_db", "rmse"),
            ("free-run", "nmse_free_run_db", "rmse_free_run"),
        ):
            value = d[key]
            shown = f"{value:8.3f} dB" if value is not None and math.isfinite(value) else str(value)
            lines.append(f"  NMSE {label}: {shown}   RMSE {d[rmse_key]}")
        return lines + band_lines(d["intervals"])
    lines.append("  channel        NMSE one-step   NMSE free run   RMSE one-step   RMSE free run")
    for name, scores in result.channels.items():
        cells = [scores[key] for key in ("nmse_db", "nmse_free_run_db", "rmse", "rmse_free_run")]
        shown = [f"{value:13.3f}" if math.isfinite(value) else f"{'nan':>13s}" for value in cells]
        lines.append(f"  {name:12s} " + "   ".join(shown))
    for name, band in d["intervals"].get("one_step", {}).items():
        lines += one_step_lines(f"{name}: ", band)
    for name, band in d["intervals"].get("free_run", {}).items():
        width, covered = band["half_width"], band["coverage_test"]
        lines.append(f"  {name}: free-run 95 % band of the fit (+-{width:.4g}): covers {covered:.1%} here")
    return lines


def _several(args: Any, bags: list[str], progress: bool) -> int:
    """Several bags, each a record of its own (:mod:`lenn_ros.service.records`): each one's figures, then all."""
    if args.plot:
        raise RecordingError("--plot: for one bag (evaluate each bag apart to plot it)")
    result = evaluate_bags(bags, args.params, args.test_from, getattr(args, "node", "/identifier"), flags_of(args),
                           progress)  # fmt: skip
    d = result.as_dict()
    if args.json:
        print(json.dumps(d, indent=1, default=lambda value: None))
        return 0
    print(f"{len(bags)} bags, each a record of its own: one model learnt through their build parts in this order, "
          "frozen, scored on each test part (free run from the measured outputs before it) and on all "
          "together")  # fmt: skip
    header = "  {:<40s} {:>8s} {:>8s} {:>8s}   NMSE one-step / free run (dB), RMSE one-step / free run"
    print(header.format("bag (output)", "trained", "tested", "from"))
    for record in d["records"]:
        for name, figures in record["channels"].items():
            shown = f"{record['bag']} ({name})" if len(record["channels"]) > 1 else record["bag"]
            print(f"  {shown:<40s} {record['trained']:>8d} {figures['samples']:>8d} {record['test_start']:>8d}   "
                  + _figures_text(figures))  # fmt: skip
        if record["test_default"]:
            print(f"    {record['test_default']}")
    for name, figures in d["overall"].items():
        label = "all test parts" + ("" if len(d["overall"]) == 1 else f" ({name})")
        print(f"  {label:<67s}   " + _figures_text(figures))
    for notice in d["notices"]:
        print(f"  note: {notice}")
    return 0


def _figures_text(figures: dict[str, Any]) -> str:
    """NMSE one-step / free run, RMSE one-step / free run, one row of the several bags' table."""
    cells = [figures[key] for key in ("nmse_db", "nmse_free_run_db", "rmse", "rmse_free_run")]
    shown = [f"{value:.3f}" if value is not None and math.isfinite(value) else "nan" for value in cells[:2]]
    shown += [f"{value:.5g}" if value is not None and math.isfinite(value) else "nan" for value in cells[2:]]
    return f"{shown[0]} / {shown[1]}, {shown[2]} / {shown[3]}"


def _plot(args: Any, result: BagEvaluation, bag: str) -> None:
    """``--plot``: plant against the model on the test part over the errors (a pair of panels per output), with
    the fit's free-run band if known. The node's one-step band (``y_hat_std``) is not kept per sample here."""
    from lenn_ros.plotting import plot_channels, plot_identification

    free_run = result.intervals.get("free_run", {})
    if result.single:
        e = result.evaluation
        title = f"{bag}: NMSE {e.nmse_db:.2f} dB one-step, {e.nmse_free_run_db:.2f} dB free run"
        plot_identification(args.plot, e.y_test, e.y_hat_test, title, e.y_free_test,
                            fit_free_run_widths(free_run, e.y_free_test))  # fmt: skip
        return
    names = list(result.evaluations)
    stacked = [np.column_stack([getattr(e, key) for e in result.evaluations.values()])
               for key in ("y_test", "y_hat_test", "y_free_test")]  # fmt: skip
    # by output name; fit_band_coverage gives a lone "y"'s at the top level
    bands = [fit_free_run_widths(free_run if name == "y" and "half_width" in free_run else free_run.get(name, {}),
                                 e.y_free_test) for name, e in result.evaluations.items()]  # fmt: skip
    shown = ", ".join(f"{name} {e.nmse_db:.2f}" for name, e in result.evaluations.items())
    title = f"{bag}: one-step NMSE {shown} dB"
    path = plot_channels(args.plot, names, stacked[0], stacked[1], title, stacked[2], free_run_band=bands)
    print(f"  wrote {path}")
