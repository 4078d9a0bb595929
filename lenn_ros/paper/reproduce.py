"""``lenn-ros reproduce``: the paper's Section IV over several seeds, as a table.

Each (example, network, seed) is one full online run: 50 000 series-parallel training
samples, then 600 frozen test samples (eq. 11). Results are reported as mean and
standard deviation over seeds, next to the paper's figure, the least-squares bound
of the LeNN's features and Table I's operation counts.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lenn_ros import progress as bars
from lenn_ros.core.evaluation import Evaluation
from lenn_ros.core.structure import Identifier
from lenn_ros.paper.evaluation import least_squares_floor, simulate, train_and_test
from lenn_ros.paper.examples import EXAMPLES, get_example
from lenn_ros.paper.experiments import report
from lenn_ros.presets import TEST_SAMPLES, TRAIN_SAMPLES


@dataclass
class Row:
    """Aggregated result of one (example, network) over seeds."""

    example: int
    network: str
    parameters: str
    seeds: list[int]
    nmse: list[float] = field(default_factory=list)
    nmse_free_run: list[float] = field(default_factory=list)
    floor: list[float] = field(default_factory=list)
    last: Evaluation | None = None

    def as_dict(self) -> dict[str, Any]:
        example = get_example(self.example)
        params = example.network_params(self.network, self.parameters)
        return {
            "example": self.example,
            "network": self.network,
            "parameters": self.parameters,
            "alpha": params["alpha"],
            "beta": params["beta"],
            "seeds": self.seeds,
            "nmse_db": self.nmse,
            "nmse_db_mean": report.mean(self.nmse),
            "nmse_db_std": report.std(self.nmse),
            "nmse_free_run_db": self.nmse_free_run,
            "nmse_free_run_db_mean": report.mean(self.nmse_free_run),
            "nmse_free_run_db_std": report.std(self.nmse_free_run),
            "least_squares_floor_db_mean": report.mean(self.floor),
            "paper_nmse_db": example.paper_nmse_db[self.network],
            "complexity": example.complexity(self.network).as_dict(),
        }


def run(
    examples: list[int],
    networks: list[str],
    seeds: int,
    iterations: int = TRAIN_SAMPLES,
    test_samples: int = TEST_SAMPLES,
    parameters: str = "calibrated",
    progress: bool = False,
) -> list[Row]:
    """All requested runs; the data of one seed is shared by both networks."""
    rows = {(e, n): Row(e, n, parameters, list(range(seeds))) for e in examples for n in networks}
    jobs = [(e, s) for e in examples for s in range(seeds)]
    bar = bars.progress(len(jobs) * len(networks), progress, "reproduce")
    for number, seed in jobs:
        example = EXAMPLES[number]
        series = simulate(example.plant(), example.noise_db, seed, iterations, test_samples)
        floor = least_squares_floor(example, series)
        for network in networks:
            model = example.make_network(network, seed, parameters)
            evaluation = train_and_test(Identifier(example.structure, model), series)
            row = rows[(number, network)]
            row.nmse.append(evaluation.nmse_db)
            row.nmse_free_run.append(evaluation.nmse_free_run_db)
            row.floor.append(floor)
            row.last = evaluation
            bar.update(1)
    bar.close()
    return list(rows.values())


def _cell(mean: float | None, std: float | None) -> str:
    return report.mean_std(mean, std, padded=True)


def format_table(rows: list[Row]) -> str:
    """Markdown table: measured NMSE next to the paper's and Table I's counts."""
    lines = [
        "| example | network | alpha | beta | NMSE one-step dB | NMSE free-run dB | paper dB "
        "| LS floor dB | weights | mult. | add. | tanh |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        d = row.as_dict()
        c = d["complexity"]
        lines.append(
            f"| {d['example']} | {d['network']} | {d['alpha']:g} | {d['beta']:g} "
            f"| {_cell(d['nmse_db_mean'], d['nmse_db_std'])} "
            f"| {_cell(d['nmse_free_run_db_mean'], d['nmse_free_run_db_std'])} "
            f"| {d['paper_nmse_db']:.2f} | {d['least_squares_floor_db_mean']:.2f} "
            f"| {c['weights']} | {c['multiplications']} | {c['additions']} | {c['tanh']} |"
        )
    return "\n".join(lines)


def write_plots(rows: list[Row], directory: str | Path) -> list[Path]:
    """One PNG per example and network (last seed), like the paper's Figs. 4-7."""
    from lenn_ros.plotting import plot_identification

    paths = []
    for row in rows:
        evaluation = row.last
        if evaluation is None:
            continue
        title = (
            f"Example {row.example}, {row.network.upper()} (seed {row.seeds[-1]}): "
            f"NMSE {evaluation.nmse_db:.2f} dB one-step, {evaluation.nmse_free_run_db:.2f} dB free run"
        )
        path = Path(directory) / f"example{row.example}_{row.network}.png"
        paths.append(plot_identification(path, evaluation.y_test, evaluation.y_hat_test, title, evaluation.y_free_test))
    return paths


def main(args) -> int:
    """Entry point of the subcommand (arguments parsed by lenn_ros.cli)."""
    examples = [args.example] if args.example else sorted(EXAMPLES)
    networks = [args.network] if args.network else ["lenn", "mlp"]
    rows = run(
        examples,
        networks,
        args.seeds,
        args.iterations,
        parameters=args.parameters,
        progress=sys.stderr.isatty() and not args.json,
    )
    if args.json:
        print(json.dumps([row.as_dict() for row in rows], indent=1))
    else:
        print(
            f"{args.iterations} training samples, {TEST_SAMPLES} test samples, seeds 0..{args.seeds - 1}, "
            f"{args.parameters} alpha/beta; NMSE as mean ± std over seeds"
        )
        print(format_table(rows))
    if args.plots:
        for path in write_plots(rows, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    return 0
