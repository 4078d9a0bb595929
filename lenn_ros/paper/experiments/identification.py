"""The rows of the identification table: the paper's networks, RLS on their features, the winner.

One simulated series per (example, seed) is shared by every row, as in ``reproduce``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lenn_ros import progress as bars
from lenn_ros.core.networks import OnlineRegressor
from lenn_ros.core.structure import Identifier
from lenn_ros.paper.evaluation import least_squares_floor, simulate, train_and_test
from lenn_ros.paper.examples import EXAMPLES, PaperExample
from lenn_ros.paper.experiments import report
from lenn_ros.paper.experiments.candidates import candidates, winner
from lenn_ros.paper.experiments.convergence import checkpoints, learning_curve, samples_to_level, samples_to_within
from lenn_ros.presets import TEST_SAMPLES, TRAIN_SAMPLES


@dataclass
class Row:
    """One model of one example over the reported seeds."""

    example: int
    kind: str  # "paper LeNN", "paper MLP", "RLS, paper features", "beyond"
    name: str
    weights: int
    seeds: list[int] = field(default_factory=list)
    nmse: list[float] = field(default_factory=list)
    nmse_free_run: list[float] = field(default_factory=list)
    floor: list[float] = field(default_factory=list)
    samples_needed: list[int | None] = field(default_factory=list)
    samples_to_paper: list[int | None] = field(default_factory=list)
    curves: list[list[float]] = field(default_factory=list)
    checkpoints: list[int] = field(default_factory=list)
    config: dict[str, Any] = field(default_factory=dict)
    last: Any = None  # Evaluation of the last seed (plots)

    def as_dict(self) -> dict[str, Any]:
        paper = EXAMPLES[self.example].paper_nmse_db["lenn"]
        one, free = report.mean(self.nmse), report.mean(self.nmse_free_run)
        floor = report.mean(self.floor) if self.floor else None
        needed = [n for n in self.samples_needed if n is not None]
        return {
            "kind": "identification",
            "example": self.example,
            "row": self.kind,
            "model": self.name,
            "weights": self.weights,
            "config": self.config,
            "seeds": self.seeds,
            "nmse_db": report.rounded(self.nmse),
            "nmse_db_mean": one,
            "nmse_db_std": report.std(self.nmse),
            "nmse_free_run_db": report.rounded(self.nmse_free_run),
            "nmse_free_run_db_mean": free,
            "nmse_free_run_db_std": report.std(self.nmse_free_run),
            "paper_lenn_nmse_db": paper,
            "gain_over_paper_lenn_db": None if one is None else round(paper - one, 3),
            "gain_over_paper_lenn_free_run_db": None if free is None else round(paper - free, 3),
            "least_squares_floor_db": report.rounded(self.floor) if self.floor else None,
            "least_squares_floor_db_mean": floor,
            "gap_to_floor_db": None if floor is None or one is None else round(one - floor, 3),
            "checkpoints": self.checkpoints,
            "learning_curve_db": [report.rounded(c) for c in self.curves],
            "samples_to_1db": self.samples_needed,
            "samples_to_1db_median": float(np.median(needed)) if len(needed) == len(self.samples_needed) else None,
            "samples_to_1db_max": max(needed) if needed and len(needed) == len(self.samples_needed) else None,
            "samples_to_paper_lenn_nmse": self.samples_to_paper,
        }


@dataclass(frozen=True)
class RowSpec:
    """How one reported row builds its model; ``floor_features`` None: no LS floor (MLP)."""

    kind: str
    name: str
    make: Callable[[int], OnlineRegressor]
    config: dict[str, Any]
    floor_features: dict[str, Any] | None


def row_specs(example: PaperExample, networks: Sequence[str] = ("lenn", "mlp")) -> list[RowSpec]:
    """The rows reported for ``example``: the paper's networks, RLS alone, the winner.

    "RLS, paper features" changes only the learning rule (and the output, to linear),
    so the table separates what the rule buys from what the features buy.
    """
    specs = []
    for network in networks:
        params = example.network_params(network, "calibrated")
        label = "LeNN SGD" if network == "lenn" else "MLP backprop"
        specs.append(
            RowSpec(
                f"paper {'LeNN' if network == 'lenn' else 'MLP'}",
                f"{label}, calibrated alpha {params['alpha']:g} beta {params['beta']:g}",
                lambda seed, network=network: example.make_network(network, seed, "calibrated"),
                {"network": network, "parameters": "calibrated", **params},
                {} if network == "lenn" else None,
            )
        )
    for kind, candidate in (("RLS, paper features", candidates(example.number)[0]), ("beyond", winner(example.number))):
        specs.append(
            RowSpec(
                kind,
                candidate.name,
                lambda seed, candidate=candidate: candidate.make(example, seed),
                {"network": "lenn", **candidate.overrides()},
                candidate.feature_overrides(),
            )
        )
    return specs


def identification(
    examples: Sequence[int],
    seeds: int,
    train_samples: int = TRAIN_SAMPLES,
    networks: Sequence[str] = ("lenn", "mlp"),
    progress: bool = False,
) -> list[Row]:
    """The rows of :func:`row_specs` for every example, over seeds 0..seeds-1.

    One simulated series per (example, seed) is shared by every row, as in
    ``reproduce``. Each row trains twice: once through :func:`train_and_test` (the
    reported NMSE, divergence guard included) and once in checkpointed runs for the
    learning curve; both see the same samples.
    """
    at = checkpoints(train_samples)
    rows: dict[tuple[int, str], Row] = {}
    specs = {number: row_specs(EXAMPLES[number], networks) for number in examples}
    bar = bars.progress(sum(len(s) for s in specs.values()) * seeds, progress, "beyond: identification")
    for number in examples:
        example = EXAMPLES[number]
        for seed in range(seeds):
            series = simulate(example.plant(), example.noise_db, seed, train_samples, TEST_SAMPLES)
            floors: dict[str, float] = {}
            for spec in specs[number]:
                model = spec.make(seed)
                evaluation = train_and_test(Identifier(example.structure, model), series)
                curve = learning_curve(example.structure, spec.make(seed), series, at)
                row = rows.setdefault(
                    (number, spec.kind), Row(number, spec.kind, spec.name, model.n_weights, config=spec.config)
                )
                row.checkpoints = list(at)
                row.seeds.append(seed)
                row.nmse.append(evaluation.nmse_db)
                row.nmse_free_run.append(evaluation.nmse_free_run_db)
                if spec.floor_features is not None:
                    key = repr(sorted(spec.floor_features.items()))
                    if key not in floors:
                        floors[key] = least_squares_floor(example, series, **spec.floor_features)
                    row.floor.append(floors[key])
                row.curves.append(curve)
                row.samples_needed.append(samples_to_within(at, curve))
                row.samples_to_paper.append(samples_to_level(at, curve, example.paper_nmse_db["lenn"]))
                row.last = evaluation
                bar.update(1)
    bar.close()
    return list(rows.values())


def format_identification(rows: list[Row]) -> str:
    lines = [
        "| ex. | row | model | weights | NMSE one-step dB | NMSE free-run dB | vs paper LeNN dB (one-step / free) "
        "| LS floor of its features dB | samples to 1 dB, median [min–max] "
        "| samples to paper LeNN's NMSE, median [min–max] |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        d = row.as_dict()
        gains = (
            f"{d['gain_over_paper_lenn_db']:+.2f} / {d['gain_over_paper_lenn_free_run_db']:+.2f}"
            if d["gain_over_paper_lenn_db"] is not None and d["gain_over_paper_lenn_free_run_db"] is not None
            else "-"
        )
        floor = "-" if d["least_squares_floor_db_mean"] is None else f"{d['least_squares_floor_db_mean']:.2f}"
        lines.append(
            f"| {row.example} | {row.kind} | {row.name} | {row.weights} "
            f"| {report.mean_std(d['nmse_db_mean'], d['nmse_db_std'])} "
            f"| {report.mean_std(d['nmse_free_run_db_mean'], d['nmse_free_run_db_std'])} "
            f"| {gains} | {floor} | {report.spread(row.samples_needed)} | {report.spread(row.samples_to_paper)} |"
        )
    return "\n".join(lines)
