"""Plants identified at 100 Hz with zero loss: a fleet on one core, a fleet on every core, a process per plant.

    python bench/fleet.py                          # N = 4, 8, 16, 32, 64 plants, 10 s trials
    python bench/fleet.py --counts 128,160,192,224,256 --setups fleet,workers   # the capacity, 1 and all
    lenn-ros bench fleet --counts 8,16             # the same through the CLI

For each N, the set-ups identify the same N plants (Example 1, LeNN, sequence pairing):

- ``fleet``: one ``lenn_ros fleet`` process, ``plants:=[p0, ..., pN-1] workers:=1``: N
  identifier nodes on one wait-set loop, one DDS participant, one interpreter, one core;
- ``workers``: the same with ``workers:=auto``: the plants spread over one worker process
  per core this process may use, each such a one-process fleet;
- ``processes``: N ``lenn_ros identifier`` processes, ``-r __ns:=/pI`` each.

A driver in this process (its own private domain, discovery on this machine) publishes
u(k) then y_p(k) for every plant every 10 ms (one lockstep publisher node for all
plants, RELIABLE, depth ``topics.DATA_DEPTH``) for ``--seconds``, after a 1 s warm-up. A
set-up *passes* at N when every identifier's final status reports all samples paired and
learnt from (all but the warm-up's), none lost, none stale, every plant's ``status`` had caught up (paired == sent)
within ``CATCH_UP`` seconds of the last publication (an identifier that falls behind
would otherwise only build a backlog), and the driver really published at the rate
(``MIN_RATE_FRACTION`` of it: on a saturated machine it cannot, and the plants then run
slower than 100 Hz). Also reported: the CPU time the node processes (a fleet's workers
included) used per plant-sample over the timed part (utime + stime from /proc, both cores
counted), their resident memory at the end, and the CPU the driver itself took over the
timed part (this process, in % of one core): on two cores it shares the machine with the
identifiers, so a set-up's capacity here is what the cores left to it identify. The set-ups
take turns at each N (a load that drifts over the run weighs on all of them alike); a
set-up's search stops at its first failing N.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from speed_online import read_cpu_seconds, read_memory_kb  # noqa: E402  (a script of bench/, beside this one)

from lenn_ros import topics  # noqa: E402
from lenn_ros.paper.examples import EXAMPLES  # noqa: E402

RATE_HZ = 100.0
CATCH_UP = 3.0  # s after the last sample by which every plant must have paired everything
WARM_UP = 1.0  # s at the rate before the timed part (discovery, first compile of the step)
MIN_RATE_FRACTION = 0.98  # of RATE_HZ the driver must reach in the timed part, or the trial is not at the rate
SETUP_WORKERS = {"fleet": "1", "workers": "auto"}  # the fleet set-ups and their workers parameter


@dataclass
class Trial:
    """One set-up at one N: what was sent, what the identifiers said, what they cost."""

    setup: str
    plants: int
    sent: int = 0
    passed: bool = False
    reason: str = ""
    cpu_us_per_sample: float = 0.0
    rss_mb: float = 0.0
    worst_lag_samples: int = 0
    driver_late_ticks: int = 0
    rate_hz: float = 0.0  # what the driver reached in the timed part
    driver_cpu_percent: float = 0.0  # this process's CPU over the timed part, in % of one core
    processes: int = 0  # node processes (a fleet's launcher, its workers and multiprocessing's resource tracker)
    counters: dict[str, int] = field(default_factory=dict)


def plant_names(count: int) -> list[str]:
    return [f"p{i}" for i in range(count)]


def start_nodes(setup: str, plants: list[str], env: dict[str, str], logs: Path) -> list[subprocess.Popen]:
    common = ["-p", "status_period:=0.5", "-p", "example:=1"]
    if setup in SETUP_WORKERS:
        argv = [sys.executable, "-m", "lenn_ros.nodes.fleet", "--ros-args", "-p", f"plants:=[{', '.join(plants)}]"]
        commands = [[*argv, "-p", f"workers:={SETUP_WORKERS[setup]}", *common]]
    else:
        commands = [
            [sys.executable, "-m", "lenn_ros.nodes.identifier", "--ros-args", "-r", f"__ns:=/{plant}", *common]
            for plant in plants
        ]
    processes = []
    for number, argv in enumerate(commands):
        log = open(logs / f"node{number}.log", "w")  # noqa: SIM115 (closed with the process)
        processes.append(subprocess.Popen(argv, env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=log))
        log.close()
    return processes


def process_tree(processes: list[subprocess.Popen]) -> list[int]:
    """The node processes and every process below them (a fleet's workers), from /proc."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rpartition(")")[2].split()[1])
            except OSError:
                continue  # gone meanwhile
    found = {process.pid for process in processes}
    frontier = set(found)
    while frontier:
        frontier = {pid for pid, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return sorted(found)


def cpu_seconds(pids: list[int]) -> float:
    """User + system CPU seconds of these processes together (a process gone counts 0)."""
    return sum(read_cpu_seconds(pid) or 0.0 for pid in pids)


def rss_mb(pids: list[int]) -> float:
    """Their resident memory together."""
    return sum((read_memory_kb(pid) or (0, 0))[0] for pid in pids) / 1024


def final_statuses(logs: Path) -> dict[str, dict]:
    statuses = {}
    for log in sorted(logs.glob("node*.log")):
        for line in log.read_text().splitlines():
            if line.startswith("identifier: {"):
                status = json.loads(line.split(": ", 1)[1])
                statuses[status["topics"]["u"].split("/")[1]] = status
    return statuses


class Driver:
    """Publishes every plant's u and y_p at the rate; keeps every plant's latest status."""

    def __init__(self, plants: list[str], domain: int) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("fleet_driver", context=self.context)
        self.float64 = topics.message_class(topics.FLOAT64)
        self.publishers = {
            plant: [self.node.create_publisher(self.float64, f"/{plant}/{n}", topics.data_qos()) for n in ("u", "y_p")]
            for plant in plants
        }
        self.paired: dict[str, int] = dict.fromkeys(plants, 0)
        string = topics.message_class(topics.STRING)
        for plant in plants:
            self.node.create_subscription(
                string, f"/{plant}/status", lambda m, p=plant: self._on_status(p, m), topics.data_qos()
            )
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.stopping = threading.Event()  # the spin ends before the executor does (rclpy raised in a shut-down spin)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        self.sent = 0

    def _spin(self) -> None:
        while not self.stopping.is_set():
            self.executor.spin_once(timeout_sec=0.1)

    def _on_status(self, plant: str, message: object) -> None:
        self.paired[plant] = int(json.loads(message.data)["counters"]["paired"])

    def matched(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(p.get_subscription_count() >= 1 for pair in self.publishers.values() for p in pair):
                return True
            time.sleep(0.1)
        return False

    def run(self, seconds: float) -> tuple[int, float]:
        """Publish for ``seconds`` at the rate; (ticks started over a period late, rate reached in Hz)."""
        period = 1.0 / RATE_HZ
        start = time.monotonic()
        late = 0
        ticks = int(seconds * RATE_HZ)
        u_message, y_message = self.float64(), self.float64()  # refilled: publish serialises at once
        for tick in range(ticks):
            due = start + tick * period
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            elif wait < -period:
                late += 1
            u_message.data = 0.5 * ((self.sent * 7919) % 1000) / 1000.0  # a fixed pseudo-random input in [0, 0.5)
            y_message.data = 0.3 * u_message.data
            for u_pub, y_pub in self.publishers.values():
                u_pub.publish(u_message)
                y_pub.publish(y_message)
            self.sent += 1
        return late, ticks / (time.monotonic() - start)

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def run_trial(setup: str, count: int, seconds: float, domain: int) -> Trial:
    plants = plant_names(count)
    trial = Trial(setup, count)
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    with tempfile.TemporaryDirectory() as directory:
        logs = Path(directory)
        processes = start_nodes(setup, plants, env, logs)
        driver = Driver(plants, domain)
        try:
            if not driver.matched(timeout=60.0 + 2.0 * count):
                trial.reason = "the identifiers never all subscribed"
                return trial
            driver.run(WARM_UP)
            pids = process_tree(processes)  # the workers are up: their identifiers subscribed
            cpu_before, driver_before, timed_at = cpu_seconds(pids), read_cpu_seconds(os.getpid()), time.monotonic()
            timed_from = driver.sent
            trial.driver_late_ticks, trial.rate_hz = driver.run(seconds)
            cpu = cpu_seconds(pids) - cpu_before
            driver_cpu = read_cpu_seconds(os.getpid()) - driver_before
            trial.driver_cpu_percent = 100 * driver_cpu / (time.monotonic() - timed_at)
            deadline = time.monotonic() + CATCH_UP
            while time.monotonic() < deadline and min(driver.paired.values()) < driver.sent:
                time.sleep(0.05)
            trial.worst_lag_samples = driver.sent - min(driver.paired.values())
            trial.rss_mb, trial.processes = rss_mb(pids), len(pids)
            trial.sent = driver.sent
            trial.cpu_us_per_sample = cpu / ((driver.sent - timed_from) * count) * 1e6
        finally:
            driver.close()
            for process in processes:
                process.send_signal(signal.SIGINT)
            for process in processes:
                try:
                    process.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
        judge(trial, final_statuses(logs), plants)
    return trial


def judge(trial: Trial, statuses: dict[str, dict], plants: list[str]) -> None:
    """Zero loss for every plant and every plant caught up, else the first reason."""
    missing = [plant for plant in plants if plant not in statuses]
    totals = {"paired": 0, "learned": 0, "lost": 0, "stale": 0, "samples": 0}
    for status in statuses.values():
        for key in totals:
            totals[key] += int(status["counters"][key])
    trial.counters = totals
    expected = trial.sent * len(plants)
    if trial.reason:
        return
    if trial.rate_hz < MIN_RATE_FRACTION * RATE_HZ:
        trial.reason = f"not at {RATE_HZ:.0f} Hz: the driver reached {trial.rate_hz:.0f} Hz (the machine is saturated)"
    elif missing:
        trial.reason = f"no final status from {len(missing)} plants"
    elif totals["paired"] != expected or totals["lost"] or totals["stale"]:
        trial.reason = f"paired {totals['paired']} of {expected}, lost {totals['lost']}, stale {totals['stale']}"
    elif totals["learned"] != expected - EXAMPLES[1].structure.warm_up * len(plants):  # the warm-up has no prediction
        trial.reason = f"learnt from {totals['learned']} of {expected} samples"
    elif trial.worst_lag_samples > 0:
        trial.reason = f"fell behind: a plant was {trial.worst_lag_samples} samples short {CATCH_UP:.0f} s after"
    else:
        trial.passed = True


def table(trials: list[Trial]) -> str:
    lines = [
        "| set-up | plants at 100 Hz | result | node CPU us per plant-sample | node RSS MB (total) "
        "| node processes | driver rate Hz | driver CPU % of a core |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for t in trials:
        result = "zero loss" if t.passed else f"FAIL: {t.reason}"
        cost = (
            f"{t.cpu_us_per_sample:.0f} | {t.rss_mb:.0f} | {t.processes} | {t.rate_hz:.1f} | {t.driver_cpu_percent:.0f}"
        )
        lines.append(f"| {t.setup} | {t.plants} | {result} | {cost} |")
    setups = list(dict.fromkeys(t.setup for t in trials))
    best = {s: max((t.plants for t in trials if t.setup == s and t.passed), default=0) for s in setups}
    said = ", ".join(f"{setup} {count}" for setup, count in best.items())
    lines += ["", f"Most plants identified with zero loss (of the counts tried): {said}."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--counts", default="4,8,16,32,64", help="numbers of plants to try, rising (default 4..64)")
    parser.add_argument("--seconds", type=float, default=10.0, help="timed part of each trial (default 10)")
    parser.add_argument(
        "--setups", default="fleet,workers,processes", help="which set-ups: fleet, workers, processes (default all)"
    )
    parser.add_argument("--json", type=Path, help="also write every trial as JSON here")
    args = parser.parse_args(argv)
    import domain_coordinator

    counts = [int(text) for text in args.counts.split(",")]
    trials: list[Trial] = []
    started = time.monotonic()
    load = os.getloadavg()[0]
    with domain_coordinator.domain_id() as domain:
        searching = args.setups.split(",")  # taken in turn at each N: a load that drifts over the run hits all alike
        for count in counts:
            for setup in list(searching):
                trial = run_trial(setup, count, args.seconds, domain)
                trials.append(trial)
                verdict = "pass" if trial.passed else f"FAIL: {trial.reason}"
                print(f"  {setup:9s} {count:4d} plants: {verdict}", file=sys.stderr, flush=True)
                if not trial.passed:
                    searching.remove(setup)
    print(table(trials))
    print(
        f"\n{args.seconds:.0f} s trials, {time.monotonic() - started:.0f} s in all, "
        f"load {load:.1f} at start, {os.getloadavg()[0]:.1f} at end; workers:=auto = "
        f"{len(os.sched_getaffinity(0))} worker processes here"
    )
    if args.json:
        args.json.write_text(json.dumps([t.__dict__ for t in trials], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
