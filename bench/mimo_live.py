"""The two-output plant identified live, over seeds: MIMO LeNN against one SISO model per output.

    python bench/mimo_live.py                      # seeds 0-4, 5000 training + 600 test samples
    python bench/mimo_live.py --seeds 3 --train-samples 3000
    lenn-ros bench mimo-live --seeds 3             # the same through the CLI

Per seed, one ``plant_simulator`` (``mimo_plant:=narendra2x2``, lockstep) publishes u
and y_p as Float64MultiArray; two ``identifier`` processes learn from the same
messages: couplings ``full`` (the MIMO model) and, in namespace ``/siso``, couplings
``diagonal`` (output j from its own past and input j). Reported per output channel:
the test-phase NMSE each node reports in its final status (mean +- std over seeds),
and the largest difference from the same configuration run offline by the core on
the same seed's data (live equals offline: 0 expected).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lenn_ros.config import identifier_parameters  # noqa: E402
from lenn_ros.core.metrics import nmse_db  # noqa: E402
from lenn_ros.paper.evaluation import simulate_mimo  # noqa: E402
from lenn_ros.paper.plants import narendra_mimo_plant  # noqa: E402
from lenn_ros.service.building import build_identifier  # noqa: E402
from lenn_ros.service.params import read_params_file  # noqa: E402

NAMES = ("y1", "y2")
#: The SISO-per-output identifier listens to the same topics from namespace /siso, and its
#: y_hat goes to the simulator's too: the simulator exits once both have gone quiet (it counts
#: both, so it runs ahead of the slower one by up to twice its window: fine below the queue depth)
SISO_REMAPS = (
    *("-r", "__ns:=/siso", "-r", "u:=/u", "-r", "y_p:=/y_p"),
    *("-r", "test_start:=/test_start", "-r", "y_hat:=/y_hat"),
)
#: The identifier's configuration: the shipped params file (bench/make_configs.py writes it)
CONFIG = REPO / "config" / "narendra2x2_lenn.yaml"
MIMO_VALUES = read_params_file(CONFIG, "/identifier")  # the shipped file, as the node is given it


def _node(module: str, *params: str, params_file: Path | None = None, ros_args: tuple[str, ...] = ()):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    args = [sys.executable, "-m", f"lenn_ros.nodes.{module}", "--ros-args"]
    if params_file is not None:
        args += ["--params-file", str(params_file)]
    for param in params:
        args += ["-p", param]
    args += list(ros_args)
    return subprocess.Popen(args, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _params(path: Path, seed: int, couplings: str) -> Path:
    values = {**MIMO_VALUES, "couplings": couplings, "seed": seed, "wait_for_y_hat_subscribers": 1}
    path.write_text(json.dumps({"/**": {"ros__parameters": values}}))
    return path


def final_status(stderr: str) -> dict:
    for line in reversed(stderr.splitlines()):
        if line.startswith("identifier: {"):
            return json.loads(line.split(": ", 1)[1])
    raise RuntimeError(f"no final status in the identifier's output:\n{stderr[-2000:]}")


def run_live(seed: int, train: int, test: int, noise_db: float, workdir: Path) -> dict[str, dict]:
    """Final statuses of the full and the diagonal identifier after one lockstep run."""
    nodes = {
        "full": _node("identifier", params_file=_params(workdir / f"full{seed}.json", seed, "full")),
        "diagonal": _node(
            "identifier",
            params_file=_params(workdir / f"diagonal{seed}.json", seed, "diagonal"),
            ros_args=SISO_REMAPS,
        ),
    }
    simulator = _node(
        "plant_simulator",
        "mimo_plant:=narendra2x2",
        f"seed:={seed}",
        f"train_samples:={train}",
        f"test_samples:={test}",
        f"noise_db:={noise_db}",
        "rate_hz:=0.0",
        "wait_for_subscribers:=2",
        "exit_when_done:=true",
    )
    try:
        _, sim_err = simulator.communicate(timeout=600)
        if simulator.returncode != 0:
            raise RuntimeError(f"plant_simulator failed: {sim_err[-2000:]}")
    finally:
        statuses = {}
        for name, process in nodes.items():
            process.send_signal(signal.SIGINT)
            _, stderr = process.communicate(timeout=60)
            statuses[name] = final_status(stderr)
    return statuses


def run_offline(seed: int, train: int, test: int, noise_db: float, couplings: str) -> dict[str, float]:
    """The same configuration run by the core on the same seed's data."""
    defaults = {p.name: p.default for p in identifier_parameters(0, "lenn")}
    identifier = build_identifier({**defaults, **MIMO_VALUES, "couplings": couplings, "seed": seed}, "lenn")
    series = simulate_mimo(narendra_mimo_plant(), noise_db, seed, train, test)
    y_hat = identifier.run(series.u, series.y, np.arange(len(series.y)) < series.test_start)
    part = slice(series.test_start, None)
    return {name: nmse_db(series.y[part, j], y_hat[part, j]) for j, name in enumerate(NAMES)}


def step_costs(samples: int = 20_000) -> dict[str, float]:
    """Microseconds per sample of ``step`` (one process, one run): the MIMO model against one SISO output's.

    The MIMO path steps one Python :class:`Identifier` per output (no compiled per-sample
    step for a MIMO channel's regressor yet); the SISO row is the compiled step of the
    same network on one output, for the ratio.
    """
    from lenn_ros.core.mimo import MimoStructure, build_mimo_identifier, parse_couplings
    from lenn_ros.core.networks import FunctionalLinkNetwork
    from lenn_ros.core.structure import Identifier, ModelStructure

    series = simulate_mimo(narendra_mimo_plant(), -20.0, 0, samples, 0)

    def network(n_inputs: int, _output: int = 0) -> FunctionalLinkNetwork:
        return FunctionalLinkNetwork(n_inputs=n_inputs, order=4, cross_degree=3, solver="rls", output="linear")

    costs = {}
    for couplings in ("full", "diagonal"):
        structure = MimoStructure(2, 2, y_scale=(2.0, 1.6), couplings=parse_couplings(couplings, 2, 2))
        identifier = build_mimo_identifier(structure, network)
        start = time.perf_counter()
        for k in range(samples):
            identifier.step(k + 1, series.u[k], series.y[k])
        costs[f"MIMO step, couplings {couplings} (2 outputs)"] = (time.perf_counter() - start) / samples * 1e6
    siso = Identifier(ModelStructure(y_lags=1, u_lags=1, y_scale=2.0), network(2))
    start = time.perf_counter()
    for k in range(samples):
        siso.step(k + 1, float(series.u[k, 0]), float(series.y[k, 0]))
    costs["SISO step, one output (compiled)"] = (time.perf_counter() - start) / samples * 1e6
    return costs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--train-samples", type=int, default=5000)
    parser.add_argument("--test-samples", type=int, default=600)
    parser.add_argument("--noise-db", type=float, default=-20.0)
    parser.add_argument("--step-cost", action="store_true", help="only the per-sample cost of step, in process")
    args = parser.parse_args(argv)
    if args.step_cost:
        print("| path | µs per sample |\n|---|---|")
        for name, cost in step_costs().items():
            print(f"| {name} | {cost:.1f} |")
        return 0
    rows: dict[tuple[str, str], list[float]] = {}
    worst = 0.0
    with tempfile.TemporaryDirectory() as workdir:
        for seed in range(args.seeds):
            live = run_live(seed, args.train_samples, args.test_samples, args.noise_db, Path(workdir))
            for couplings, status in live.items():
                offline = run_offline(seed, args.train_samples, args.test_samples, args.noise_db, couplings)
                for name in NAMES:
                    value = status["channels"][name]["phase_nmse_db"]
                    rows.setdefault((name, couplings), []).append(value)
                    worst = max(worst, abs(value - offline[name]))
            print(f"seed {seed}: " + ", ".join(f"{k[0]} {k[1]} {v[-1]:.2f} dB" for k, v in rows.items()), flush=True)
    print(f"\n| output | model | live test NMSE, dB (mean ± std, seeds 0-{args.seeds - 1}) |")
    print("|---|---|---|")
    for (name, couplings), values in sorted(rows.items()):
        model = "MIMO LeNN (couplings full)" if couplings == "full" else "SISO LeNN per output (diagonal)"
        print(f"| {name} | {model} | {np.mean(values):.2f} ± {np.std(values):.2f} |")
    print(f"\nlargest |live - offline| over all seeds and channels: {worst:.2e} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
