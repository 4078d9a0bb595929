"""A fleet: several identifiers in one process, each its plant's own (topics, parameters, model, status)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rosutil import start_node, stop  # noqa: E402

from lenn_ros import topics  # noqa: E402
from lenn_ros.paper.evaluation import simulate  # noqa: E402
from lenn_ros.paper.examples import EXAMPLES  # noqa: E402

PLANTS = ("line1/press", "line2/oven", "idle")


def final_statuses(stderr: str) -> dict[str, dict]:
    """Every identifier's final status line, by its u topic's namespace."""
    statuses = {}
    for line in stderr.splitlines():
        if line.startswith("identifier: {"):
            status = json.loads(line.split(": ", 1)[1])
            statuses[status["topics"]["u"].rsplit("/", 1)[0]] = status
    return statuses


def descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (children, theirs, ...), from /proc."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue  # self, sys, ...
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue  # gone meanwhile
        parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def running(pids: set[int]) -> set[int]:
    """Those of ``pids`` still running (a zombie has ended: an orphan's is reaped by whoever adopted it, or not)."""
    alive = set()
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state not in ("Z", "X"):
            alive.add(pid)
    return alive


def wait_gone(pids: set[int], timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while running(pids):
        assert time.monotonic() < deadline, f"processes left running: {running(pids)}"
        time.sleep(0.05)


def read_parameters(node, names: dict[str, list[str]], timeout: float = 20) -> dict[str, dict]:
    """Each node's named parameters through its parameter services (``node`` spun elsewhere), as ``ros2 param get``."""
    clients = {target: AsyncParameterClient(node, target) for target in names}
    values = {}
    for target, client in clients.items():
        assert client.wait_for_services(timeout_sec=timeout), f"no parameter services of {target}"
        future = client.get_parameters(names[target])
        deadline = time.monotonic() + timeout
        while not future.done():
            assert time.monotonic() < deadline, f"no answer from {target}'s get_parameters"
            time.sleep(0.02)
        got = future.result().values
        values[target] = {
            name: rclpy.parameter.parameter_value_to_python(v) for name, v in zip(names[target], got, strict=True)
        }
    return values


def follow(node, plants: list[str]) -> tuple[dict[str, int], dict[str, int]]:
    """Each plant's learned count from its status topic and its y_hat messages counted, kept up to date."""
    learnt: dict[str, int] = {}
    predictions = dict.fromkeys(plants, 0)
    string, float64 = topics.message_class(topics.STRING), topics.message_class(topics.FLOAT64)
    for plant in plants:
        node.create_subscription(
            string, f"/{plant}/{topics.STATUS}",
            lambda message, plant=plant: learnt.__setitem__(plant, json.loads(message.data)["counters"]["learned"]),
            topics.data_qos(),
        )  # fmt: skip
        node.create_subscription(
            float64, f"/{plant}/{topics.Y_HAT}",
            lambda _, plant=plant: predictions.__setitem__(plant, predictions[plant] + 1), topics.data_qos(),
        )  # fmt: skip
    return learnt, predictions


def drive(publishers: dict[str, list], counts: dict[str, int]) -> None:
    """Each plant's first ``counts[plant]`` samples of Example 1, u then y_p, as a lockstep simulator sends them."""
    float64 = topics.message_class(topics.FLOAT64)
    series = simulate(EXAMPLES[1].plant(), EXAMPLES[1].noise_db, 2, max(counts.values()), 0)
    for plant, count in counts.items():
        u_pub, y_pub = publishers[plant]
        for k in range(count):
            u_pub.publish(float64(data=float(series.u[k])))
            y_pub.publish(float64(data=float(series.y[k])))


def poll_learnt(learnt: dict, predictions: dict, expected: dict[str, int], deadline: float) -> str | None:
    """Until each plant has learnt ``expected`` pairs and published one y_hat more (from the warm-up's last
    sample on): None, or what was reached by ``deadline`` (monotonic)."""
    published = {plant: count + 1 for plant, count in expected.items()}
    while learnt != expected or predictions != published:
        if time.monotonic() > deadline:
            return f"learnt {learnt}, y_hat {predictions}, expected {expected} in 30 s"
        time.sleep(0.05)
    return None


def assert_each_its_own(err: str, counts: dict[str, int]) -> None:
    """Every plant's final status: the driven ones paired and learnt all they were sent, the idle one nothing."""
    statuses = final_statuses(err)
    assert set(statuses) == {f"/{plant}" for plant in PLANTS}, err[-2000:]
    for plant, count in counts.items():
        counters = statuses[f"/{plant}"]["counters"]
        assert counters["paired"] == counters["samples"] == count and counters["lost"] == 0, (plant, counters)
        # all but the warm-up (no prediction yet): learnt, not merely received
        assert counters["learned"] == count - EXAMPLES[1].structure.warm_up, (plant, counters)
    assert statuses["/line1/press"]["network"] == "lenn" and statuses["/line2/oven"]["network"] == "mlp"
    assert statuses["/idle"]["counters"]["u_messages"] == 0
    assert "unknown parameter" not in err and "Traceback" not in err, err[-2000:]


@pytest.mark.parametrize(("workers", "signum"), [("1", signal.SIGINT), ("2", signal.SIGTERM)])
def test_fleet_identifies_each_plant_on_its_own(tmp_path: Path, domain: int, workers: str, signum: int) -> None:
    """Two plants driven with different data, one idle; a params file sets one plant's network.

    With two workers the plants are spread over two processes (/line1/press and /idle in one,
    /line2/oven in the other); each plant must still publish, answer for its parameters and take
    its own params-file section, and stopping the launcher must leave none of its processes.
    """
    sections = {
        "/**": {"ros__parameters": {"example": 1, "status_period": 0.2}},
        "/line2/oven/identifier": {"ros__parameters": {"network": "mlp"}},
    }
    (tmp_path / "fleet.yaml").write_text(json.dumps(sections))
    fleet = start_node(
        "fleet", f"plants:=[{', '.join(PLANTS)}]", f"workers:={workers}", params_file=tmp_path / "fleet.yaml"
    )
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("two_plants", context=context)  # one lockstep publisher per plant's pair
    float64 = topics.message_class(topics.FLOAT64)
    names = (topics.U, topics.Y_P)
    publishers = {
        plant: [node.create_publisher(float64, f"/{plant}/{name}", topics.data_qos()) for name in names]
        for plant in PLANTS[:2]
    }
    counts = {PLANTS[0]: 1500, PLANTS[1]: 900}
    learnt, predictions = follow(node, list(counts))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while min(p.get_subscription_count() for pair in publishers.values() for p in pair) < 1:
            assert time.monotonic() < deadline, "the fleet's identifiers never subscribed"
            time.sleep(0.05)
        drive(publishers, counts)
        wait = rclpy.duration.Duration(seconds=10)
        assert all(p.wait_for_all_acked(wait) for pair in publishers.values() for p in pair)
        # poll until every pair is learnt (held first: the graph check's grace), not a sleep tied to that grace
        expected = {plant: count - EXAMPLES[1].structure.warm_up for plant, count in counts.items()}
        deadline = time.monotonic() + 30
        stalled = poll_learnt(learnt, predictions, expected, deadline)  # on a timeout the fleet's last lines say why
        if stalled is None:
            wanted = {f"/{plant}/identifier": ["network", "status_period"] for plant in PLANTS}
            parameters = read_parameters(node, {**wanted, "/fleet": ["plants", "workers"]})
            processes = descendants(fleet.pid)
    finally:
        _, err = stop(fleet, signum)
        executor.shutdown()
        thread.join(timeout=5)
        node.destroy_node()
        context.try_shutdown()
    assert stalled is None, f"{stalled}; the fleet's last lines:\n{err[-3000:]}"
    assert_each_its_own(err, counts)
    for plant in PLANTS:  # the per-plant section applies to its plant only, the /** one to all
        network = "mlp" if plant == "line2/oven" else "lenn"
        assert parameters[f"/{plant}/identifier"] == {"network": network, "status_period": 0.2}, parameters
    assert parameters["/fleet"] == {"plants": list(PLANTS), "workers": int(workers)} and fleet.returncode == 0
    if workers == "2":
        assert "3 identifiers on 2 worker processes" in err and '"workers_died": 0' in err, err[-2000:]
        assert len(processes) >= 2  # the two workers (and multiprocessing's resource tracker)
    wait_gone(processes)


class StderrLines:
    """A running process's stderr, line by line, read on a thread so the test can poll it."""

    def __init__(self, process: subprocess.Popen[str]) -> None:
        self.lines: list[str] = []
        self.thread = threading.Thread(target=lambda: self.lines.extend(process.stderr), daemon=True)
        self.thread.start()

    def wait_for(self, pattern: str, timeout: float = 60) -> re.Match:
        deadline = time.monotonic() + timeout
        while True:
            for line in list(self.lines):
                found = re.search(pattern, line)
                if found:
                    return found
            assert time.monotonic() < deadline, f"no line matching {pattern!r} in:\n{''.join(self.lines)[-3000:]}"
            time.sleep(0.05)


def test_a_dead_worker_is_said_and_a_killed_launcher_leaves_no_worker(domain: int) -> None:
    """SIGKILL to one worker: one line naming its plants, counted; SIGKILL to the launcher: its workers stop."""
    fleet = start_node("fleet", "plants:=[a, b, c]", "workers:=2", "example:=1")
    lines = StderrLines(fleet)
    try:
        started = lines.wait_for(r"worker 1 \(pid (\d+)\): /a, /c; worker 2 \(pid (\d+)\): /b")
        first, second = int(started[1]), int(started[2])
        lines.wait_for(r"\[b\.identifier\]: lenn with")  # the worker is up, not still starting
        os.kill(second, signal.SIGKILL)
        lines.wait_for(
            rf"worker 2 \(pid {second}\) ended \(killed by SIGKILL\): plants /b are no longer identified "
            r"\(1 of 2 workers ended\)"
        )
        lines.wait_for(r"\[a\.identifier\]: lenn with")
        processes = descendants(fleet.pid)
        assert first in processes
        fleet.kill()
        fleet.wait(timeout=10)
        wait_gone(processes)  # the survivor saw its launcher go and stopped
    finally:
        if fleet.poll() is None:
            fleet.kill()
        fleet.wait()
    lines.thread.join(timeout=10)
    assert sum("no longer identified" in line for line in lines.lines) == 1, "".join(lines.lines)[-3000:]
    assert "Traceback" not in "".join(lines.lines), "".join(lines.lines)[-3000:]


@pytest.mark.parametrize(
    ("plants", "message"),
    [("[]", "no plants"), ("[a, a]", "plants named twice: /a"), ("['bad name']", "is not a namespace")],
)
def test_a_bad_plant_list_is_one_line(domain: int, plants: str, message: str) -> None:
    fleet = start_node("fleet", f"plants:={plants}")
    _, err = fleet.communicate(timeout=60)
    assert fleet.returncode == 2 and message in err and "Traceback" not in err, err


@pytest.mark.parametrize("workers", ["0", "many", "1.5", "-2"])
def test_a_bad_worker_count_is_one_line(domain: int, workers: str) -> None:
    fleet = start_node("fleet", "plants:=[a, b]", f"workers:={workers}")
    _, err = fleet.communicate(timeout=60)
    message = "fleet: cannot start: workers must be 'auto' or a positive integer"
    assert fleet.returncode == 2 and err.strip().splitlines() == [err.strip()] and message in err, err
