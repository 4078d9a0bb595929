"""``lenn-ros evaluate BAG``: the identifier's own computation over a recording.

No ROS graph: the bag's u and y_p are paired by message order (the order the
recorder received them, which is publication order for one RELIABLE publisher),
screened like the live node screens them, and run through the same
:class:`~lenn_ros.core.structure.Identifier` the node uses, configured from the same
params file. So the test-phase NMSE of a bag recorded online equals the one the
identifier reported live, to rounding.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from lenn_ros.bag import read_run
from lenn_ros.config import build_identifier, read_params_file, resolve
from lenn_ros.core.evaluation import Evaluation, Series, train_and_test
from lenn_ros.core.pairing import screen
from lenn_ros.core.structure import Identifier


@dataclass
class BagEvaluation:
    evaluation: Evaluation
    pairs: int
    unpaired: int
    rejected: int
    test_start: int  # 1-based sample index

    def as_dict(self) -> dict:
        return {
            **self.evaluation.as_dict(),
            "pairs": self.pairs,
            "unpaired": self.unpaired,
            "rejected": self.rejected,
            "test_start": self.test_start,
            "skipped": self.evaluation.skipped + self.unpaired + self.rejected,
        }


def identifier_from_params(path: str | None) -> tuple[Identifier, dict]:
    """The identifier a params file describes (the node's defaults without one)."""
    values = read_params_file(path) if path else {}
    resolved, network = resolve(values)
    identifier = build_identifier(resolved, network)
    node_values = {"u_limit": 1.0e3, "y_limit": 1.0e3, "out_of_range": "reject", **values}
    return identifier, node_values


def evaluate_bag(bag: str, params: str | None = None, test_from: int | None = None) -> BagEvaluation:
    """Train on the bag's training phase, score the frozen model on its test phase."""
    run = read_run(bag)
    identifier, node_values = identifier_from_params(params)
    test_start = test_from if test_from is not None else run.test_start
    if test_start is None:
        raise ValueError(f"{bag}: no test_start topic in the bag; pass --test-from K (1-based sample index)")
    pairs = min(len(run.u), len(run.y_p))
    if test_start < 2 or test_start > pairs:
        raise ValueError(f"test start {test_start} outside the bag's samples 2..{pairs}")
    u = run.u[:pairs].copy()
    y = run.y_p[:pairs].copy()
    rejected = 0
    for series, limit in ((u, node_values["u_limit"]), (y, node_values["y_limit"])):
        for k, value in enumerate(series):
            series[k], _ = screen(float(value), float(limit), node_values["out_of_range"])
    bad = np.isnan(u) | np.isnan(y)
    rejected = int(bad.sum())
    if rejected:
        raise ValueError(
            f"{bag}: {rejected} samples are NaN/inf or beyond the limits; "
            "evaluate a clean segment (--test-from) or raise u_limit/y_limit in the params file"
        )
    evaluation = train_and_test(identifier, Series(u=u, y=y, test_start=test_start - 1))
    return BagEvaluation(evaluation, pairs, abs(len(run.u) - len(run.y_p)), rejected, test_start)


def main(args) -> int:
    result = evaluate_bag(args.bag, args.params, args.test_from)
    if args.plot:
        from lenn_ros.plotting import plot_identification

        e = result.evaluation
        title = f"{args.bag}: NMSE {e.nmse_db:.2f} dB one-step, {e.nmse_free_run_db:.2f} dB free run"
        plot_identification(args.plot, e.y_test, e.y_hat_test, title, e.y_free_test)
    if args.json:
        print(json.dumps(result.as_dict(), indent=1))
        return 0
    d = result.as_dict()
    print(f"bag {args.bag}: {d['pairs']} pairs, test from sample {d['test_start']}")
    print(f"  trained on {d['trained']} samples, scored {d['samples']} test samples, skipped {d['skipped']}")
    for label, key, rmse in (("one-step", "nmse_db", "rmse"), ("free-run", "nmse_free_run_db", "rmse_free_run")):
        value = d[key]
        shown = f"{value:8.3f} dB" if math.isfinite(value) else str(value)
        print(f"  NMSE {label}: {shown}   RMSE {d[rmse]:.5g}")
    return 0
