"""``lenn-ros demo``: the whole product in one command, nothing to configure.

Starts three real nodes as separate processes talking over DDS (recorder,
identifier, plant_simulator) on a private domain, kept on this machine; runs a
training and a test phase of the chosen example; stops the nodes as a user would
(SIGINT); then reads the recording back with the offline evaluator and prints the
live NMSE next to the offline one and the paper's, with the bag and a plot.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any

from lenn_ros.errors import UserError
from lenn_ros.paper.examples import get_example


def _node(module: str, parameters: dict, env: dict, log: Path) -> subprocess.Popen:
    arguments = [sys.executable, "-m", f"lenn_ros.nodes.{module}", "--ros-args"]
    for name, value in parameters.items():
        arguments += ["-p", f"{name}:={value}"]
    return subprocess.Popen(arguments, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)


def _last_status(log: Path) -> dict | None:
    for line in reversed(log.read_text(errors="replace").splitlines()):
        if line.startswith("identifier: {"):
            return json.loads(line.split(": ", 1)[1])
    return None


def _rss_kb(pid: int) -> int | None:
    """Resident set size of a process (Linux), for the flat-memory check of long runs."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def _stop(process: subprocess.Popen, timeout: float = 15.0) -> int:
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            return process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
    return process.wait()


class DemoError(UserError):
    """A node of the demo stopped or hung: one line naming the log that says why."""


def _environment() -> dict[str, str]:
    """A private domain, discovery kept on this machine (unless the caller chose otherwise)."""
    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(random.randint(30, 99)))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return env


def _start_nodes(
    run_dir: Path, example: int, network: str, samples: tuple[int, int], seed: int, rate: float
) -> tuple[dict[str, subprocess.Popen], Path]:
    """recorder, identifier, plant_simulator (in that order), and the identifier's params file."""
    env = _environment()
    # the identifier holds its first outputs until the recorder and the simulator have matched them
    identifier_params = {
        "example": example,
        "network": network,
        "seed": seed,
        "wait_for_y_hat_subscribers": 2,  # the recorder and the simulator (lockstep)
        "wait_for_error_subscribers": 1,  # the recorder
        "wait_for_samples_subscribers": 1,  # the recorder
    }
    params_file = run_dir / "identifier.yaml"
    params_file.write_text(json.dumps({"identifier": {"ros__parameters": identifier_params}}))
    simulator_params = {
        "example": example,
        "seed": seed,
        "train_samples": samples[0],
        "test_samples": samples[1],
        "rate_hz": rate,
        "wait_for_subscribers": 2,
        "exit_when_done": True,
    }
    nodes = {
        "recorder": _node("recorder", {"output": str(run_dir / "bag")}, env, run_dir / "recorder.log"),
        "identifier": _node("identifier", identifier_params, env, run_dir / "identifier.log"),
        "plant_simulator": _node("plant_simulator", simulator_params, env, run_dir / "plant_simulator.log"),
    }
    return nodes, params_file


def _wait_for_simulator(nodes: dict[str, subprocess.Popen], run_dir: Path, budget: float) -> list[tuple[float, int]]:
    """Until the simulator exits: the identifier's memory over time; a stopped or hung node is a DemoError."""
    started = time.monotonic()
    simulator, identifier = nodes["plant_simulator"], nodes["identifier"]
    rss: list[tuple[float, int]] = []
    while simulator.poll() is None:
        kb = _rss_kb(identifier.pid)
        if kb is not None:
            rss.append((round(time.monotonic() - started, 1), kb))
        for name in ("identifier", "recorder"):
            if nodes[name].poll() is not None:
                raise DemoError(f"the {name} stopped early; see {run_dir / (name + '.log')}")
        if time.monotonic() - started > budget:
            raise DemoError(f"no end after {budget:.0f} s; see the logs in {run_dir}")
        time.sleep(0.2)
    if simulator.returncode != 0:
        raise DemoError(f"plant_simulator failed; see {run_dir / 'plant_simulator.log'}")
    return rss


def run_demo(
    example: int = 1,
    network: str = "lenn",
    train_samples: int = 20_000,
    test_samples: int = 600,
    seed: int = 0,
    rate: float = 0.0,
    output: str = "demo_output",
) -> dict:
    """Run the three nodes, wait for the last sample, stop them, evaluate the bag."""
    from lenn_ros.bag import bag_info
    from lenn_ros.service.evaluation import evaluate_bag

    run_dir = Path(output) / datetime.now().strftime("run-%Y%m%d-%H%M%S")
    run_dir.mkdir(parents=True, exist_ok=True)
    bag = run_dir / "bag"
    total = train_samples + test_samples
    started = time.monotonic()
    nodes, params_file = _start_nodes(run_dir, example, network, (train_samples, test_samples), seed, rate)
    try:
        rss = _wait_for_simulator(nodes, run_dir, budget=120.0 + (total / rate if rate > 0 else total / 200.0))
    finally:
        for name in ("plant_simulator", "identifier", "recorder"):
            _stop(nodes[name])
    live = _last_status(run_dir / "identifier.log")
    if live is None:
        raise DemoError(f"the identifier printed no final status; see {run_dir / 'identifier.log'}")
    offline = evaluate_bag(str(bag), str(params_file))
    plot = _plot(run_dir / "identification.png", offline.evaluation, example, network, live["phase_nmse_db"])
    return {
        "example": example,
        "network": network,
        "samples": total,
        "seconds": round(time.monotonic() - started, 1),
        "live": live,
        "offline": offline.as_dict(),
        "paper_nmse_db": get_example(example).paper_nmse_db[network],
        "bag": str(bag),
        "bag_info": bag_info(bag),
        "plot": str(plot),
        "identifier_rss_kb": rss,
    }


def _plot(path: Path, evaluation: Any, example: int, network: str, live_nmse_db: float) -> Path:
    from lenn_ros.plotting import plot_identification

    title = f"Example {example}, {network.upper()}: online identification, test phase (NMSE {live_nmse_db:.2f} dB)"
    plot_identification(path, evaluation.y_test, evaluation.y_hat_test, title, evaluation.y_free_test)
    return path


def main(args) -> int:
    print(
        f"demo: example {args.example}, {args.network}, {args.train_samples} training + {args.test_samples} test "
        "samples; starting recorder, identifier and plant_simulator ...",
        flush=True,
    )
    result = run_demo(
        args.example, args.network, args.train_samples, args.test_samples, args.seed, args.rate, args.output
    )
    live, offline = result["live"], result["offline"]
    counters = live["counters"]
    print(f"done in {result['seconds']} s: {counters['paired']} samples paired, {counters['learned']} learnt from, "
          f"{counters['lost']} lost, {counters['duplicates'] + counters['stale']} duplicated/stale")  # fmt: skip
    print(f"  NMSE (test phase, one-step), live identifier:   {live['phase_nmse_db']:8.3f} dB")
    print(f"  NMSE (test phase, one-step), from the bag:      {offline['nmse_db']:8.3f} dB")
    print(f"  NMSE (test phase, free run), from the bag:      {offline['nmse_free_run_db']:8.3f} dB")
    print(f"  NMSE reported in the paper:                     {result['paper_nmse_db']:8.3f} dB")
    counts = ", ".join(f"{name} {topic['count']}" for name, topic in result["bag_info"]["topics"].items())
    print(f"  bag:  {result['bag']} (messages: {counts})")
    print(f"  plot: {result['plot']}")
    return 0
