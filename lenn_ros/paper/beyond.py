"""``lenn-ros reproduce --beyond``: what the paper's LeNN leaves on the table.

The paper trains a single tanh node by gradient descent on a per-input Legendre
expansion. Two things limit it, and each has a standard remedy:

- *the learning rule*: with a linear output the model is linear in its weights, so
  recursive least squares (RLS) reaches the least-squares fit of its features after
  a few hundred samples instead of tens of thousands of hand-tuned gradient steps,
  and with a forgetting factor it tracks a plant that changes;
- *the features*: a per-input expansion is a sum of one-variable functions, which
  cannot represent Ex. 2's y1*y2 or Ex. 4's products of inputs; tensor-product cross
  terms (or another basis) can.

For every example the experiments (:mod:`lenn_ros.paper.experiments`) evaluate a small set of
such configurations with the paper's protocol (50 000 training and 600 test samples)
and report the best one next to the paper's LeNN and MLP, with how fast each learns
(:mod:`~lenn_ros.paper.experiments.convergence`) and how it tracks a plant that changes
(:mod:`~lenn_ros.paper.experiments.tracking`). This module runs them and prints the tables.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from lenn_ros.paper.examples import EXAMPLES
from lenn_ros.paper.experiments.candidates import CALIBRATION_SEEDS
from lenn_ros.paper.experiments.convergence import WITHIN_DB, checkpoints
from lenn_ros.paper.experiments.identification import Row, format_identification, identification
from lenn_ros.paper.experiments.tracking import (
    GAIN_AFTER_CHANGE,
    REFERENCE_SAMPLES,
    SMOOTHING_WINDOW,
    TrackingRow,
    format_tracking,
    plot_tracking,
    tracking,
)
from lenn_ros.presets import TEST_SAMPLES, TRAIN_SAMPLES


def write_plots(rows: list[Row], tracks: list[TrackingRow], change_at: int, directory: str | Path) -> list[Path]:
    """The beyond winner's test plot per example (last seed), and the tracking curves."""
    from lenn_ros.plotting import plot_identification

    paths = []
    for row in rows:
        if row.kind != "beyond" or row.last is None:
            continue
        evaluation = row.last
        title = (
            f"Example {row.example}, {row.name} (seed {row.seeds[-1]}): NMSE {evaluation.nmse_db:.2f} dB one-step, "
            f"{evaluation.nmse_free_run_db:.2f} dB free run"
        )
        path = Path(directory) / f"example{row.example}_beyond.png"
        paths.append(plot_identification(path, evaluation.y_test, evaluation.y_hat_test, title, evaluation.y_free_test))
    if tracks:
        paths.append(plot_tracking(tracks, change_at, Path(directory) / "tracking_example1.png"))
    return paths


def main(args) -> int:
    """``lenn-ros reproduce --beyond`` (arguments parsed by lenn_ros.cli)."""
    examples = [args.example] if args.example else sorted(EXAMPLES)
    networks = [args.network] if args.network else ["lenn", "mlp"]
    progress = sys.stderr.isatty() and not args.json
    rows = identification(examples, args.seeds, args.iterations, networks, progress)
    change_at = args.iterations // 2
    tracks = tracking(args.seeds, args.iterations, change_at, progress=progress) if 1 in examples else []
    if args.json:
        objects = [row.as_dict() for row in rows] + [row.as_dict(change_at, args.iterations) for row in tracks]
        print(json.dumps(objects, indent=1))
    else:
        print(
            f"Beyond the paper: {args.iterations} training samples, {TEST_SAMPLES} test samples, "
            f"seeds 0..{args.seeds - 1}; mean ± std over seeds. Beyond rows chosen on seeds "
            f"{', '.join(map(str, CALIBRATION_SEEDS))} (bench/beyond_search.py). Samples to 1 dB: first of "
            f"checkpoints {', '.join(map(str, checkpoints(args.iterations)))} from which the one-step test NMSE "
            f"stays within {WITHIN_DB:g} dB of its final value; samples to paper LeNN's NMSE: the same, staying at "
            f"or below the paper's reported LeNN figure. Command: lenn-ros reproduce --beyond --seeds {args.seeds}"
            + (f" --example {args.example}" if args.example else "")
            + (f" --iterations {args.iterations}" if args.iterations != TRAIN_SAMPLES else "")
            + "."
        )
        print(format_identification(rows))
        if tracks:
            print()
            print(
                f"Tracking: example 1, g's gain 1.0 -> {GAIN_AFTER_CHANGE:g} at k = {change_at} of {args.iterations}, "
                f"learning throughout; recovery = samples from the change to the end of the first "
                f"{SMOOTHING_WINDOW}-sample window after it whose mean a-priori e² is within {WITHIN_DB:g} dB of "
                f"the {min(REFERENCE_SAMPLES, change_at // 2)} samples before the change (minimum {SMOOTHING_WINDOW})."
            )
            print(format_tracking(tracks, change_at, args.iterations))
    if args.plots:
        for path in write_plots(rows, tracks, change_at, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    return 0
