"""Online speed through ROS: highest loss-free rate, latency, memory, per-message cost.

Run alone (``python bench/speed_online.py -h``) it compares chosen nodes in one run: a
search per node, or fixed-rate trials taking turns (``--at``); ``bench/speed.py`` runs
the full set (rates, latency, memory, profiles).

Setup of every trial: the node under test (the bare :mod:`echo node
<echo_node>`, spun three ways, or the real identifier under any of run_node's loops)
runs as a subprocess on a
private ROS domain, discovery kept on this machine. The driver, in this process,
publishes u(k) then y_p(k) (RELIABLE, depth ``topics.DATA_DEPTH``) on a wall-clock
schedule and counts the ``y_hat`` replies. Its own costs are kept small: the
messages are serialised in advance and published raw, and replies are taken in a
tight loop on a wait set of its own (no executor), raw, on a second thread.

A trial at rate r (``seconds`` long, after 200 warm-up samples at 500 Hz that are
answered before the clock starts) *passes* when
- every sample is answered exactly once (the identifier answers every pair from its
  ``warm_up``-th on; the echo every y_p),
- for the identifier, its ``status`` JSON reports lost == 0, duplicates == 0 and
  paired == samples sent,
- the node kept up: the reply to the last sample arrives within ``MAX_END_LAG`` of
  its publication (a node slower than r would build a backlog in its 10 000-deep
  queue and answer late, or lose samples when the queue overflows),
- and the driver really published at r (at least ``MIN_SEND_FRACTION`` of it;
  otherwise the trial measures the driver, and the search stops there).

Latency is per sample: from the driver's clock just before publishing y_p(k) to
the driver's clock when it takes the reply to k (``time.perf_counter_ns`` of this
process, both ends). The identifier publishes one y_hat per pair, in order, so the
reply with publication sequence number s answers sample s + warm_up - 1.
"""

from __future__ import annotations

import contextlib
import cProfile
import json
import math
import os
import pstats
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from speed_offline import example_series

from lenn_ros import topics
from lenn_ros.paper.examples import EXAMPLES

RATE_MIN = 500.0
RATE_MAX = 20_000.0
LATENCY_RATE = 1_000.0
LOW_LATENCY_RATE = 500.0  # latency is also reported here, a rate every node should sustain
WARM_UP_SAMPLES = 200
WARM_UP_RATE = 500.0
MAX_END_LAG = 0.25  # seconds
MIN_SEND_FRACTION = 0.97
STATUS_PERIOD = 0.25  # seconds, the identifier's status_period during the benchmark
PAYLOAD_SAMPLES = 20_000  # distinct (u, y_p) pairs published, cycled
BENCH = Path(__file__).resolve().parent
PACKAGE_ROOT = BENCH.parent


@dataclass(frozen=True)
class NodeUnderTest:
    name: str
    argv: list[str]
    reply_offset: int  # replies start at sample reply_offset + 1 (1-based)
    has_status: bool
    env: tuple[tuple[str, str], ...] = ()  # added to the child's environment (e.g. the executor choice)
    root: Path = PACKAGE_ROOT  # the source tree the node runs from (another one: a baseline)


#: The identifier's loops compared (``LENN_ROS_EXECUTOR``, see :func:`lenn_ros.nodes.run_node`).
IDENTIFIER_EXECUTORS = ("single", "waitset", "events")


def nodes_under_test(example: int = 1, network: str = "lenn") -> dict[str, NodeUnderTest]:
    """The echo ceilings and the identifier, the latter as it runs by default and with each loop forced.

    ``identifier`` is the node exactly as users start it (its default loop);
    ``identifier_<loop>`` forces one loop through ``LENN_ROS_EXECUTOR``, so each
    can be measured against the echo with the same loop in one run.
    """
    python = sys.executable
    echo = [python, str(BENCH / "echo_node.py")]
    identifier = [
        python,
        "-m",
        "lenn_ros.nodes.identifier",
        "--ros-args",
        "-p",
        f"example:={example}",
        "-p",
        f"network:={network}",
        "-p",
        f"status_period:={STATUS_PERIOD}",
    ]
    offset = EXAMPLES[example].structure.warm_up - 1
    nodes = {
        "echo": NodeUnderTest("echo", echo, 0, False),
        "echo_waitset": NodeUnderTest("echo_waitset", [*echo, "--waitset"], 0, False),
        "echo_events": NodeUnderTest("echo_events", [*echo, "--events"], 0, False),
        "identifier": NodeUnderTest("identifier", identifier, offset, True),
    }
    for loop in IDENTIFIER_EXECUTORS:
        name = f"identifier_{loop}"
        nodes[name] = NodeUnderTest(name, identifier, offset, True, (("LENN_ROS_EXECUTOR", loop),))
    return nodes


# --------------------------------------------------------------------------- environment


@contextlib.contextmanager
def private_domain() -> Iterator[int]:
    """A ROS domain ID no concurrent user of domain_coordinator has, discovery on localhost only."""
    try:
        import domain_coordinator

        manager: Any = domain_coordinator.domain_id()
    except ImportError:  # pragma: no cover - domain_coordinator is in the 'ros' extra
        manager = contextlib.nullcontext(random.Random(os.getpid()).randint(50, 100))
    saved = {name: os.environ.get(name) for name in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    with manager as domain:
        os.environ["ROS_DOMAIN_ID"] = str(domain)
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        try:
            yield int(domain)
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value


def child_environment(extra: tuple[tuple[str, str], ...] = (), root: Path = PACKAGE_ROOT) -> dict[str, str]:
    env = dict(os.environ) | dict(extra)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(root), env.get("PYTHONPATH", "")) if p)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def read_memory_kb(pid: int) -> tuple[int, int] | None:
    """(VmRSS, VmHWM) of a process in kB, from /proc (None if gone)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    values = {}
    for line in text.splitlines():
        name, _, rest = line.partition(":")
        if name in ("VmRSS", "VmHWM"):
            values[name] = int(rest.split()[0])
    return values.get("VmRSS", 0), values.get("VmHWM", 0)


def read_cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process (all its threads), from /proc/PID/stat."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_until(condition: Callable[[], bool], timeout: float, poll: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll)
    return condition()


# --------------------------------------------------------------------------- the driver


class Driver:
    """Publishes pre-serialised u / y_p on a schedule; takes y_hat replies on its own thread."""

    _count = 0

    def __init__(self, context: Any, capacity: int, payload: tuple[list[bytes], list[bytes]]) -> None:
        from rclpy import create_node
        from std_msgs.msg import Float64, String

        Driver._count += 1
        self.context = context
        self.node = create_node(
            f"bench_driver_{os.getpid()}_{Driver._count}",
            context=context,
            start_parameter_services=False,
            enable_rosout=False,
        )
        qos = topics.data_qos()
        self.publisher_u = self.node.create_publisher(Float64, topics.U, qos)
        self.publisher_y = self.node.create_publisher(Float64, topics.Y_P, qos)
        self.replies_sub = self.node.create_subscription(Float64, topics.Y_HAT, _ignore, qos, raw=True)
        self.status_sub = self.node.create_subscription(String, topics.STATUS, _ignore, qos)
        self.payload_u, self.payload_y = payload
        self.send_ns = np.zeros(capacity, dtype=np.int64)  # by sample (0-based)
        self.reply_ns = np.zeros(capacity, dtype=np.int64)  # by reply sequence number - 1
        self.sent = 0
        self.replies = 0
        self.duplicate_replies = 0
        self.out_of_range_replies = 0
        self.last_reply_ns = 0
        self.status: dict[str, Any] | None = None
        self.status_ns = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def matched(self) -> bool:
        return (
            self.publisher_u.get_subscription_count() >= 1
            and self.publisher_y.get_subscription_count() >= 1
            and self.replies_sub.get_publisher_count() >= 1
        )

    def start(self) -> None:
        self._thread = threading.Thread(target=self._receive, name="bench-receiver", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def close(self) -> None:
        self.stop()
        self.node.destroy_node()

    def _receive(self) -> None:
        from lenn_ros.nodes import rclpy_internals

        replies_sub, status_sub, take = self.replies_sub, self.status_sub, rclpy_internals.take
        reply_ns, capacity = self.reply_ns, len(self.reply_ns)
        clock = time.perf_counter_ns
        with rclpy_internals.WaitSet(self.context, [replies_sub, status_sub]) as wait_set:
            while not self._stop.is_set():
                wait_set.wait(20_000_000)
                while True:
                    taken = take(replies_sub)
                    if taken is None:
                        break
                    now = clock()
                    sequence = taken[1]["publication_sequence_number"]
                    if not 0 < sequence <= capacity:
                        self.out_of_range_replies += 1
                    elif reply_ns[sequence - 1]:
                        self.duplicate_replies += 1
                    else:
                        reply_ns[sequence - 1] = now
                        self.replies += 1
                        self.last_reply_ns = now
                while True:
                    taken = take(status_sub, raw=False)
                    if taken is None:
                        break
                    with contextlib.suppress(ValueError):
                        self.status = json.loads(taken[0].data)
                        self.status_ns = clock()

    def send(self, count: int, rate: float) -> tuple[int, int]:
        """Publish the next ``count`` samples at ``rate`` per second; (first, last) send time in ns.

        Late samples go out at once (bursts), like the plant simulator catching up.
        """
        publish_u, publish_y = self.publisher_u.publish, self.publisher_y.publish  # bytes: published raw
        payload_u, payload_y, pool = self.payload_u, self.payload_y, len(self.payload_u)
        send_ns, clock = self.send_ns, time.perf_counter_ns
        period = 1e9 / rate
        first = self.sent
        end = first + count
        start = clock()
        k = first
        while k < end:
            due = min(end, first + int((clock() - start) / period) + 1)
            while k < due:
                publish_u(payload_u[k % pool])
                send_ns[k] = clock()
                publish_y(payload_y[k % pool])
                k += 1
            self.sent = k
            delay = start + (k - first) * period - clock()
            if delay > 0:
                time.sleep(delay / 1e9)
        return int(send_ns[first]), int(send_ns[end - 1])


def _ignore(_message: Any) -> None:
    pass


def make_payload(samples: int = PAYLOAD_SAMPLES) -> tuple[list[bytes], list[bytes]]:
    """Example 1's simulated (u, y_p), serialised as std_msgs/Float64 once."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64

    u, y = example_series(1, samples)
    return (
        [serialize_message(Float64(data=v)) for v in u.tolist()],
        [serialize_message(Float64(data=v)) for v in y.tolist()],
    )


# --------------------------------------------------------------------------- one trial


def run_trial(
    node: NodeUnderTest,
    rate: float,
    seconds: float,
    context: Any,
    payload: tuple[list[bytes], list[bytes]],
    memory_period: float = 0.5,
) -> dict[str, Any]:
    """Start the node, warm it up, publish at ``rate`` for ``seconds``, drain, judge."""
    timed = max(1, round(rate * seconds))
    total = WARM_UP_SAMPLES + timed
    offset = node.reply_offset
    driver = Driver(context, total + 16, payload)
    with tempfile.TemporaryFile(mode="w+") as log:
        process = subprocess.Popen(
            node.argv,
            env=child_environment(node.env, node.root),
            cwd=node.root,
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
        )
        memory: list[tuple[float, int, int, int]] = []  # (time, samples sent, rss kB, hwm kB)
        sampling = threading.Event()
        try:
            if not wait_until(lambda: driver.matched() or process.poll() is not None, 60.0):
                raise RuntimeError(f"{node.name}: no match with the driver within 60 s")
            if process.poll() is not None:
                raise RuntimeError(f"{node.name} exited with status {process.returncode}: {_tail(log)}")
            time.sleep(0.5)  # both sides of every match settled
            driver.start()
            driver.send(WARM_UP_SAMPLES, WARM_UP_RATE)
            if not wait_until(lambda: driver.replies >= WARM_UP_SAMPLES - offset, 30.0):
                raise RuntimeError(
                    f"{node.name}: only {driver.replies} of {WARM_UP_SAMPLES - offset} warm-up samples answered"
                )

            def sample_memory() -> None:
                while not sampling.is_set():
                    values = read_memory_kb(process.pid)
                    if values is not None:
                        memory.append((time.monotonic(), driver.sent, *values))
                    sampling.wait(memory_period)

            sampler = threading.Thread(target=sample_memory, daemon=True)
            sampler.start()
            node_cpu, driver_cpu, load = read_cpu_seconds(process.pid), time.process_time(), os.getloadavg()[0]
            first_ns, last_ns = driver.send(timed, rate)
            expected = total - offset
            _drain(driver, expected)
            node_cpu = (read_cpu_seconds(process.pid) or math.nan) - (node_cpu or math.nan)
            driver_cpu = time.process_time() - driver_cpu
            cpu = {
                "node_cpu_us_per_sample": node_cpu / timed * 1e6,
                "driver_cpu_us_per_sample": driver_cpu / timed * 1e6,
                "load_average_1min": load,
            }
            sampling.set()
            sampler.join(timeout=5)
            if node.has_status:  # a status taken after the last reply, i.e. with every sample counted
                settled = driver.last_reply_ns + int(2 * STATUS_PERIOD * 1e9)
                wait_until(lambda: driver.status_ns > settled, 5.0)
        finally:
            sampling.set()
            driver.stop()
            final_status = _stop_process(process, log)
            driver.close()
    return _judge(node, rate, seconds, driver, total, first_ns, last_ns, final_status, memory) | cpu


def safe_trial(
    node: NodeUnderTest, rate: float, seconds: float, context: Any, payload: tuple[list[bytes], list[bytes]]
) -> dict[str, Any]:
    """:func:`run_trial`, with a node that did not start or never answered counted as a failed trial."""
    try:
        return run_trial(node, rate, seconds, context, payload)
    except RuntimeError as error:
        return {
            "node": node.name,
            "rate_hz": rate,
            "seconds": seconds,
            "passed": False,
            "driver_limited": False,
            "problems": [str(error)],
            "latency": {},
            "memory": {},
        }


def _drain(driver: Driver, expected: int, patience: float = 3.0, limit: float = 60.0) -> None:
    """Wait for the replies still under way: until all are in, or none came for ``patience`` s."""
    start = time.monotonic()
    last, last_change = driver.replies, time.monotonic()
    while driver.replies < expected and time.monotonic() - start < limit:
        time.sleep(0.02)
        if driver.replies != last:
            last, last_change = driver.replies, time.monotonic()
        elif time.monotonic() - last_change > patience:
            break


def _stop_process(process: subprocess.Popen, log: Any) -> dict[str, Any] | None:
    """SIGINT, wait; the identifier prints its final status JSON on the way out."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    log.seek(0)
    for line in reversed(log.read().splitlines()):
        if line.startswith("identifier: {"):
            with contextlib.suppress(ValueError):
                return json.loads(line.partition(": ")[2])
    return None


def _tail(log: Any, lines: int = 5) -> str:
    log.seek(0)
    return " | ".join(log.read().splitlines()[-lines:])


def _judge(
    node: NodeUnderTest,
    rate: float,
    seconds: float,
    driver: Driver,
    total: int,
    first_ns: int,
    last_ns: int,
    final_status: dict[str, Any] | None,
    memory: list[tuple[float, int, int, int]],
) -> dict[str, Any]:
    offset = node.reply_offset
    expected = total - offset
    timed = total - WARM_UP_SAMPLES
    send_rate = (timed - 1) / ((last_ns - first_ns) / 1e9) if timed > 1 and last_ns > first_ns else float("inf")
    # replies to the timed samples: sequence s answers sample s - 1 + offset (0-based)
    sequences = np.arange(WARM_UP_SAMPLES - offset, expected)  # 0-based reply index
    replied = driver.reply_ns[sequences] > 0
    latency_ns = driver.reply_ns[sequences][replied] - driver.send_ns[sequences + offset][replied]
    last_reply = int(driver.reply_ns[expected - 1]) if expected > 0 else 0
    end_lag = (last_reply - int(driver.send_ns[total - 1])) / 1e9 if last_reply else float("inf")
    reply_rate = (
        (len(latency_ns) - 1)
        / ((driver.reply_ns[sequences][replied].max() - driver.reply_ns[sequences][replied].min()) / 1e9)
        if len(latency_ns) > 1
        else 0.0
    )
    counters = (driver.status or {}).get("counters", {}) if node.has_status else {}
    problems = []
    if driver.replies != expected:
        problems.append(f"{expected - driver.replies} of {expected} replies missing")
    if driver.duplicate_replies or driver.out_of_range_replies:
        problems.append(f"{driver.duplicate_replies + driver.out_of_range_replies} unexpected replies")
    if node.has_status:
        problems += _status_problems(counters, total)
    if end_lag > MAX_END_LAG:
        problems.append(f"fell behind: last reply {end_lag:.3f} s after its sample")
    driver_limited = send_rate < MIN_SEND_FRACTION * rate
    if driver_limited:
        problems.append(f"driver reached only {send_rate:.0f}/s")
    percentiles = (
        {f"p{q}_ms": float(np.percentile(latency_ns, q) / 1e6) for q in (50, 90, 99)}
        | {"max_ms": float(latency_ns.max() / 1e6)}
        if len(latency_ns)
        else {}
    )
    return {
        "node": node.name,
        "rate_hz": rate,
        "seconds": seconds,
        "sent": total,
        "expected_replies": expected,
        "replies": driver.replies,
        "send_rate_hz": send_rate,
        "reply_rate_hz": reply_rate,
        "end_lag_s": end_lag,
        "latency": percentiles,
        "status_counters": counters,
        "final_status_counters": (final_status or {}).get("counters"),
        "memory": _memory_summary(memory, WARM_UP_SAMPLES),
        "driver_limited": driver_limited,
        "passed": not problems,
        "problems": problems,
    }


def _status_problems(counters: dict[str, Any], total: int) -> list[str]:
    """What the identifier's own status says went wrong (nothing lost or duplicated, all paired)."""
    if not counters:
        return ["no status received"]
    problems = []
    if counters.get("lost", -1) != 0:
        problems.append(f"status lost={counters.get('lost')}")
    if counters.get("duplicates", -1) != 0:
        problems.append(f"status duplicates={counters.get('duplicates')}")
    if counters.get("paired", -1) != total:
        problems.append(f"status paired={counters.get('paired')} != sent {total}")
    return problems


def _memory_summary(memory: list[tuple[float, int, int, int]], warm_up: int) -> dict[str, Any]:
    """RSS at start, middle and end, peak (VmHWM), and its trend in kB per 100k samples.

    The trend is the least-squares slope of RSS over samples sent, leaving out the first
    tenth of the run (allocator and DDS history warm-up); the growth of the second half
    alone shows whether what growth there is levels off.
    """
    if len(memory) < 2:
        return {}
    samples = np.array([m[1] for m in memory], dtype=float)
    rss = np.array([m[2] for m in memory], dtype=float)
    span = samples[-1] - samples[0]
    trend = float("nan")
    settled = samples >= samples[0] + 0.1 * span
    if span > 0 and settled.sum() >= 3 and np.ptp(samples[settled]) > 0:
        trend = float(np.polyfit(samples[settled], rss[settled], 1)[0] * 100_000)
    middle = int(np.searchsorted(samples, samples[0] + span / 2))
    half = samples[-1] - samples[middle]
    return {
        "samples": int(span),
        "rss_start_kb": int(rss[0]),
        "rss_middle_kb": int(rss[middle]),
        "rss_end_kb": int(rss[-1]),
        "rss_peak_kb": int(max(m[3] for m in memory)),
        "growth_kb_per_100k_samples": trend,
        "second_half_growth_kb_per_100k_samples": float((rss[-1] - rss[middle]) / half * 100_000) if half else None,
        "readings": len(memory),
        "series": [[int(m[1]), int(m[2])] for m in memory],  # (samples sent, VmRSS kB)
    }


# --------------------------------------------------------------------------- the search


def find_max_rate(
    node: NodeUnderTest,
    seconds: float,
    context: Any,
    payload: tuple[list[bytes], list[bytes]],
    bisections: int,
    log: Callable[[str], None],
) -> dict[str, Any]:
    """Double from RATE_MIN until a trial fails (or RATE_MAX passes), then bisect."""
    trials: list[dict[str, Any]] = []

    def attempt(rate: float) -> dict[str, Any]:
        trial = safe_trial(node, rate, seconds, context, payload)
        trial["memory"].pop("series", None)  # the memory run keeps its series; search trials are short
        trials.append(trial)
        verdict = "pass" if trial["passed"] else "FAIL: " + "; ".join(trial["problems"])
        log(f"  {node.name} {rate:8.0f} Hz: {verdict}")
        return trial

    best: float | None = None
    failed: float | None = None
    limited = False
    rate = RATE_MIN
    while True:
        trial = attempt(rate)
        if trial["passed"]:
            best = rate
            if rate >= RATE_MAX:
                break
            rate = min(2 * rate, RATE_MAX)
        else:
            failed, limited = rate, trial["driver_limited"]
            break
    steps = 0
    while best is not None and failed is not None and steps < bisections and failed / best > 1.05:
        rate = round((best + failed) / 2 / 50) * 50
        if rate in (best, failed):
            break
        trial = attempt(rate)
        steps += 1
        if trial["passed"]:
            best = rate
        else:  # a driver-limited failure bounds the search too: the driver may still reach a lower rate
            failed, limited = rate, trial["driver_limited"]
    return {"max_rate_hz": best, "first_failing_hz": failed, "driver_limited": limited, "trials": trials}


# --------------------------------------------------------------------------- in-process profile


#: (label, file suffix, function name) of the per-message path, for the profile table.
PROFILE_ROWS = (
    ("IdentifierNode._offer (one message, total)", "nodes/identifier.py", "_offer"),
    ("  Session.offer (screen, pair, model step)", "core/session.py", "offer"),
    ("    Identifier.step (model work)", "core/structure.py", "step"),
    ("      model.update_features (learn from the stored pattern)", "core/networks.py", "update_features"),
    ("      model.features (expansion, 1 sample)", "core/networks.py", "features"),
    ("    Pairer.add", "core/pairing.py", "add"),
    ("    screen", "core/pairing.py", "screen"),
    ("    RunningNMSE.add", "core/metrics.py", "add"),
    ("  IdentifierNode._publish (y_hat, error, samples)", "nodes/identifier.py", "_publish"),
    ("    Publisher.publish", "rclpy/publisher.py", "publish"),
    ("Float64() message construction", "msg/_float64.py", "__init__"),
)


def profile_identifier_callbacks(pairs: int, repeats: int) -> dict[str, Any]:
    """Cost of the identifier node's own per-pair work, in-process, without the transport.

    The real :class:`IdentifierNode` (example 1, LeNN, default parameters) in this
    process; its two subscription callbacks are called directly with example 1's data
    and the sequence numbers DDS would give, so everything the node does per pair is
    measured except taking the messages (the executor and DDS, measured by the echo
    node). Times are this thread's CPU time (``time.thread_time``, for cProfile too),
    so other work on a shared machine does not count; the breakdown is scaled to the
    unprofiled time per pair (profiling inflates small, frequent calls the most).
    """
    import rclpy
    from std_msgs.msg import Float64

    from lenn_ros.core.pairing import U, Y
    from lenn_ros.nodes.identifier import IdentifierNode

    own_init = not rclpy.ok()
    if own_init:
        rclpy.init(args=["--ros-args", "--log-level", "error"])
    node = IdentifierNode(separate_inputs=False)  # messages go to _offer directly: no subscriptions needed
    # No publisher of u / y_p exists in this process's graph: without this the node would
    # hold every pair (and look the graph up per message) for its 5 s start grace, and
    # the profile would measure holding, not learning.
    node.session.gate = None  # (publishers_known, nothing held)
    node.session.holding = False
    try:
        u, y = example_series(1, 500 + pairs * (repeats + 1))
        messages = [(Float64(data=a), Float64(data=b)) for a, b in zip(u.tolist(), y.tolist(), strict=True)]
        cursor = 0

        def feed(count: int) -> None:
            nonlocal cursor
            offer = node._offer  # what the node does per message once it has taken it
            for k in range(cursor, cursor + count):
                info = {"publication_sequence_number": k + 1}
                message_u, message_y = messages[k]
                offer(U, message_u, info)
                offer(Y, message_y, info)
            cursor += count

        feed(500)  # warm-up: kernels loaded, first NMSE report published
        times = []
        for _ in range(repeats):
            start = time.thread_time()
            feed(pairs)
            times.append(time.thread_time() - start)
        per_pair_us = statistics.median(times) / pairs * 1e6
        profiler = cProfile.Profile(time.thread_time)
        profiler.enable()
        feed(pairs)
        profiler.disable()
        stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
        total = sum(entry[2] for entry in stats.values())  # all own time = the profiled callbacks
        rows = []
        for label, suffix, function in PROFILE_ROWS:
            cumulative = sum(
                entry[3]
                for (file, _, name), entry in stats.items()
                if name == function and file.replace(os.sep, "/").endswith(suffix)
            )
            rows.append({"part": label, "share": cumulative / total, "us_per_pair": per_pair_us * cumulative / total})
        top = sorted(stats.items(), key=lambda item: -item[1][2])[:10]
        own = [
            {
                "function": f"{Path(file).parent.name}/{Path(file).name}:{line} {name}" if line else name,
                "calls_per_pair": entry[1] / pairs,
                "share": entry[2] / total,
                "us_per_pair": per_pair_us * entry[2] / total,
            }
            for (file, line, name), entry in top
        ]
        counters = dict(node.session.counters)
    finally:
        node.destroy_node()
        if own_init:
            rclpy.try_shutdown()
    return {
        "pairs": pairs,
        "us_per_pair": per_pair_us,
        "max_rate_hz": 1e6 / per_pair_us,
        "breakdown": rows,
        "top_own_time": own,
        "counters": counters,
    }


def profile_identifier_process(
    seconds: float, context: Any, payload: tuple[list[bytes], list[bytes]], rate: float = 200.0
) -> dict[str, Any]:
    """The real identifier process under cProfile (thread CPU time) for one trial: loop vs callbacks.

    Shares are of the CPU the node's main thread spent in run_node's loop (whichever
    it is: ``LENN_ROS_EXECUTOR`` or the identifier's default), per pair of u / y_p.
    Profiling slows the node down about twice (hence the low rate) and inflates the
    executor's many small Python calls more than the numpy-heavy callbacks, so the
    loop's share is an upper estimate; the one-time load of the compiled kernel
    from numba's cache (first message) is left out.
    """
    with tempfile.TemporaryDirectory(prefix="lenn-bench-") as directory:
        output = Path(directory) / "identifier.prof"
        base = nodes_under_test()["identifier"]
        node = NodeUnderTest(
            "identifier_profiled",
            [sys.executable, str(BENCH / "profile_node.py"), str(output), *base.argv[3:]],
            base.reply_offset,
            True,
        )
        trial = safe_trial(node, rate, seconds, context, payload)
        if not output.exists():
            return {"skipped": "the profiled node wrote no profile", "problems": trial["problems"]}
        stats = pstats.Stats(str(output)).stats  # type: ignore[attr-defined]

    def cumulative(suffix: str, function: str) -> float:
        return sum(
            entry[3]
            for (file, _, name), entry in stats.items()
            if name == function and file.replace(os.sep, "/").endswith(suffix)
        )

    pairs = sum(
        entry[1] for (file, _, name), entry in stats.items() if name == "step" and file.endswith("structure.py")
    )
    if not pairs:
        return {"skipped": "no pair reached Identifier.step", "problems": trial["problems"]}
    compile_load = cumulative("numba/core/dispatcher.py", "_compile_for_args")
    spin = cumulative("lenn_ros/nodes/__init__.py", "_spin") - compile_load  # run_node's loop, any executor
    wait = cumulative("rclpy/executors.py", "wait_for_ready_callbacks")
    take = cumulative("rclpy/executors.py", "_take_subscription")
    callbacks = cumulative("nodes/identifier.py", "_on_message") - compile_load
    timer = cumulative("nodes/identifier.py", "_on_status_timer") + cumulative("nodes/identifier.py", "_on_poll_timer")
    step = cumulative("core/structure.py", "step") - compile_load
    publish = cumulative("rclpy/publisher.py", "publish")
    loop = _identifier_loop()
    parts = [
        (f"the loop ({loop}): wait, take, dispatch; all but the callbacks", max(0.0, spin - callbacks - timer)),
        ("  of which rclpy executor: rebuild the wait set, wait, find ready entities", wait),
        ("  of which rclpy executor: take + deserialise each message", take),
        ("node callbacks (_on_message: the identifier's own work, and the messages it takes itself)", callbacks),
        ("  of which Identifier.step (model)", step),
        ("  of which Publisher.publish (y_hat; the other outputs have no reader here)", publish),
        ("status and poll timers", timer),
    ]
    if spin <= 0:
        return {"skipped": "no time in run_node's loop (_spin) in the profile", "problems": trial["problems"]}
    return {
        "rate_hz": rate,
        "seconds": seconds,
        "loop": loop,
        "pairs": int(pairs),
        "profiled_us_per_pair": spin / pairs * 1e6,
        "breakdown": [
            {"part": label, "share": value / spin, "profiled_us_per_pair": value / pairs * 1e6}
            for label, value in parts
        ],
        "trial_passed": trial["passed"],
    }


def _identifier_loop() -> str:
    """The loop the identifier runs under when started by this benchmark (its default or the environment's)."""
    from lenn_ros.nodes import executor_choice
    from lenn_ros.nodes.identifier import EXECUTOR

    return executor_choice(EXECUTOR)


# --------------------------------------------------------------------------- all of it

#: Nodes searched by :func:`online` (``bench/speed.py``, whose tables show these), in this order.
ONLINE_NODES = ("echo", "echo_waitset", "identifier")
#: Nodes the command line compares when none is named: every echo and every loop of the identifier.
COMPARED_NODES = ("echo", "echo_waitset", "echo_events", "identifier_single", "identifier_waitset", "identifier_events")


def search_rates(
    names: Iterable[str],
    nodes: dict[str, NodeUnderTest],
    seconds: float,
    context: Any,
    payload: Any,
    bisections: int,
    log: Callable[[str], None],
) -> dict[str, dict[str, Any]]:
    """The highest loss-free rate of each named node, with its latency and cost summary, by name."""
    found = {}
    for name in names:
        log(f"online: highest loss-free rate of the {name} node, {seconds:g} s trials")
        found[name] = find_max_rate(nodes[name], seconds, context, payload, bisections, log)
        summarise_rates(found[name], nodes[name], seconds, context, payload, log)
    return found


def summarise_rates(
    entry: dict[str, Any],
    node: NodeUnderTest,
    seconds: float,
    context: Any,
    payload: tuple[list[bytes], list[bytes]],
    log: Callable[[str], None],
) -> None:
    """Latency at 500 Hz and 1 kHz, and the figures at the highest passing rate, into ``entry``.

    The search's own trials are used where it ran those rates; 1 kHz is run once more
    when the search stopped below it, so the latency target is judged on every node.
    """
    at = [t for t in entry["trials"] if t["rate_hz"] == LATENCY_RATE]
    if not at and node.name != "echo_waitset":
        log(f"online: latency of the {node.name} node at {LATENCY_RATE:g} Hz")
        at = [safe_trial(node, LATENCY_RATE, seconds, context, payload)]
        at[0]["memory"].pop("series", None)
    if at:
        entry["latency_at_1khz"] = {**at[0]["latency"], "passed": at[0]["passed"]}
    low = [t for t in entry["trials"] if t["rate_hz"] == LOW_LATENCY_RATE]
    if low:
        entry["latency_at_500hz"] = {**low[0]["latency"], "passed": low[0]["passed"]}
    passed = [t for t in entry["trials"] if t["passed"]]
    if passed:
        top = max(passed, key=lambda t: t["rate_hz"])
        entry["at_max_rate"] = {
            "rate_hz": top["rate_hz"],
            "node_cpu_us_per_sample": top.get("node_cpu_us_per_sample"),
            **top["latency"],
        }


def fractions_of_echo(result: dict[str, Any]) -> dict[str, float]:
    """Every identifier variant's loss-free rate over every echo's, all from this one run."""
    fractions = {}
    for name, entry in result.items():
        if not name.startswith("identifier") or not isinstance(entry, dict) or "max_rate_hz" not in entry:
            continue
        for echo in ("echo", "echo_waitset", "echo_events"):
            ceiling = result.get(echo, {}).get("max_rate_hz")
            if ceiling and entry["max_rate_hz"]:
                fractions[f"{name}_fraction_of_{echo}"] = entry["max_rate_hz"] / ceiling
    return fractions


def compare(
    names: list[str],
    seconds: float,
    bisections: int,
    log: Callable[[str], None],
    extra: dict[str, NodeUnderTest] | None = None,
) -> dict[str, Any]:
    """Highest loss-free rate and latency of the named nodes only, in one run (``python bench/speed_online.py``).

    The quick way to compare loops: no profile and no memory run, and ratios are
    formed between nodes measured minutes apart on the same machine, not across runs.
    ``extra`` adds nodes by name (a baseline identifier from another source tree).
    """
    import rclpy
    from rclpy.context import Context

    nodes = nodes_under_test() | (extra or {})
    result: dict[str, Any] = {"trial_seconds": seconds, "bisections": bisections, "load_at_start": os.getloadavg()}
    with private_domain() as domain:
        result["domain_id"] = domain
        context = Context()
        rclpy.init(context=context, domain_id=domain)
        try:
            payload = make_payload()
            result |= search_rates(names, nodes, seconds, context, payload, bisections, log)
        finally:
            context.try_shutdown()
    result["load_at_end"] = os.getloadavg()
    return result | fractions_of_echo(result)


def interleaved(
    names: list[str],
    rates: list[float],
    repeats: int,
    seconds: float,
    log: Callable[[str], None],
    extra: dict[str, NodeUnderTest] | None = None,
) -> dict[str, Any]:
    """Fixed-rate trials taking turns (node after node, ``repeats`` rounds): the fairest comparison on a busy machine.

    A search runs one node's trials back to back, so a neighbour's build can land on
    one node only; here every round gives each node a trial at each rate within
    minutes, and the medians over rounds are compared.
    """
    import rclpy
    from rclpy.context import Context

    nodes = nodes_under_test() | (extra or {})
    trials: dict[str, dict[float, list[dict[str, Any]]]] = {name: {rate: [] for rate in rates} for name in names}
    with private_domain() as domain:
        context = Context()
        rclpy.init(context=context, domain_id=domain)
        try:
            payload = make_payload()
            for round_ in range(repeats):
                for rate in rates:
                    for name in names:
                        trial = safe_trial(nodes[name], rate, seconds, context, payload)
                        trial["memory"].pop("series", None)
                        trials[name][rate].append(trial)
                        verdict = "pass" if trial["passed"] else "FAIL: " + "; ".join(trial["problems"])
                        log(f"  round {round_ + 1} {name} {rate:6.0f} Hz: {verdict}")
        finally:
            context.try_shutdown()
    return {"trial_seconds": seconds, "repeats": repeats, "trials": trials}


def interleaved_markdown(result: dict[str, Any]) -> list[str]:
    """Per node and rate: trials passed, and the medians of latency and CPU per sample over the rounds."""

    def median(values: list[float]) -> str:
        values = [v for v in values if v is not None and math.isfinite(v)]
        return f"{statistics.median(values):.2f}" if values else "n/a"

    out = [
        "| node | rate (Hz) | passed | p50 ms (median) | p99 ms (median) | p99 ms (each trial) | node CPU us/sample |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, by_rate in result["trials"].items():
        for rate, trials in by_rate.items():
            p99 = [t["latency"].get("p99_ms") for t in trials]
            out.append(
                f"| {name} | {rate:g} | {sum(t['passed'] for t in trials)}/{len(trials)} "
                f"| {median([t['latency'].get('p50_ms') for t in trials])} | {median(p99)} "
                f"| {', '.join(f'{v:.2f}' if v is not None else 'n/a' for v in p99)} "
                f"| {median([t.get('node_cpu_us_per_sample') for t in trials])} |"
            )
    return out


def compare_markdown(result: dict[str, Any], names: list[str]) -> list[str]:
    """One row per node: highest loss-free rate, CPU there, latency at 500 Hz and 1 kHz."""

    def latency(entry: dict[str, Any] | None) -> str:
        if not entry or "p50_ms" not in entry:
            return "n/a"
        return f"{entry['p50_ms']:.2f} / {entry['p99_ms']:.2f}" + ("" if entry.get("passed") else " (failed)")

    out = [
        "| node | highest loss-free rate (Hz) | first failing (Hz) | node CPU us/sample there | "
        "p50 / p99 ms at 500 Hz | p50 / p99 ms at 1 kHz |",
        "|---|---|---|---|---|---|",
    ]
    for name in names:
        entry = result[name]
        cpu = entry.get("at_max_rate", {}).get("node_cpu_us_per_sample")
        out.append(
            f"| {name} | {entry['max_rate_hz'] or '< 500'}{' (driver limit)' if entry['driver_limited'] else ''} "
            f"| {entry['first_failing_hz'] or '-'} | {f'{cpu:.0f}' if cpu else 'n/a'} "
            f"| {latency(entry.get('latency_at_500hz'))} | {latency(entry.get('latency_at_1khz'))} |"
        )
    out += ["", *(f"- {key}: {value:.0%}" for key, value in result.items() if "_fraction_of_" in key)]
    return out


def _log_stderr(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    """Compare chosen nodes' loss-free rates and latency in one run (the full benchmark is bench/speed.py)."""
    import argparse

    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="e.g. python bench/speed_online.py --seconds 5 echo echo_events identifier_single identifier_events",
    )
    parser.add_argument(
        "nodes",
        nargs="*",
        default=list(COMPARED_NODES),
        help=f"of {', '.join(nodes_under_test())} (default: every echo and every identifier loop)",
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="length of each trial (default 30)")
    parser.add_argument("--bisections", type=int, default=3, help="bisection steps after the doubling (default 3)")
    parser.add_argument("--json", type=Path, help="also write every trial as JSON to this file")
    parser.add_argument(
        "--baseline",
        type=Path,
        help="a source tree (e.g. `git archive HEAD | tar -x -C DIR`) whose identifier runs as node "
        "'identifier_baseline', for a before/after in one run",
    )
    parser.add_argument(
        "--at",
        type=lambda text: [float(rate) for rate in text.split(",")],
        help="no search: fixed-rate trials at these rates (e.g. 1000,3000), the nodes taking turns",
    )
    parser.add_argument("--repeats", type=int, default=3, help="rounds of --at trials (default 3)")
    args = parser.parse_args(argv)
    extra = {}
    if args.baseline:
        base = nodes_under_test()["identifier"]
        extra["identifier_baseline"] = NodeUnderTest(
            "identifier_baseline", base.argv, base.reply_offset, True, root=args.baseline.resolve()
        )
    unknown = sorted(set(args.nodes) - set(nodes_under_test()) - set(extra))
    if unknown:
        parser.error(f"unknown node(s): {', '.join(unknown)}")
    started = time.perf_counter()
    load = os.getloadavg()[0]
    if args.at:
        result = interleaved(args.nodes, args.at, args.repeats, args.seconds, _log_stderr, extra)
        result["load_at_start"], result["load_at_end"] = [load], os.getloadavg()
        lines = interleaved_markdown(result)
    else:
        result = compare(args.nodes, args.seconds, args.bisections, _log_stderr, extra)
        lines = compare_markdown(result, args.nodes)
    result["seconds"] = time.perf_counter() - started
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=str))
    print("\n".join(lines))
    print(
        f"\n{args.seconds:g} s trials, {result['seconds']:.0f} s in all, load {result['load_at_start'][0]:.1f} "
        f"at start, {result['load_at_end'][0]:.1f} at end"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())


def online(seconds: float, quick: bool, log: Callable[[str], None]) -> dict[str, Any]:
    """Echo ceiling, identifier max rate, latency at 1 kHz, memory over a long run, profile."""
    try:
        import rclpy
        from rclpy.context import Context
    except ImportError as error:
        return {"skipped": f"rclpy not importable ({error})"}
    result: dict[str, Any] = {"trial_seconds": seconds}
    nodes = nodes_under_test()
    bisections = 2 if quick else 3
    with private_domain() as domain:
        result["domain_id"] = domain
        log("online: in-process profile of the identifier's callbacks")
        result["callback_profile"] = profile_identifier_callbacks(pairs=1000 if quick else 5000, repeats=3)
        context = Context()
        rclpy.init(context=context, domain_id=domain)
        try:
            payload = make_payload()
            result |= search_rates(ONLINE_NODES, nodes, seconds, context, payload, bisections, log)
            best = result["identifier"]["max_rate_hz"] or RATE_MIN
            memory_rate = max(RATE_MIN / 2, 0.8 * best)
            memory_seconds = 10 * seconds
            log(f"online: identifier memory over {memory_seconds:g} s at {memory_rate:g} Hz")
            trial = safe_trial(nodes["identifier"], memory_rate, memory_seconds, context, payload)
            result["memory"] = {"rate_hz": memory_rate, "seconds": memory_seconds, "passed": trial["passed"]}
            result["memory"] |= trial["memory"]
            log("online: the identifier process under cProfile (executor vs callbacks)")
            result["process_profile"] = profile_identifier_process(min(seconds, 20.0), context, payload)
        finally:
            context.try_shutdown()
    echo, identifier = result["echo"]["max_rate_hz"], result["identifier"]["max_rate_hz"]
    result["identifier_fraction_of_echo"] = identifier / echo if echo and identifier else float("nan")
    result |= fractions_of_echo(result)
    # what the echo's rate says one pair costs in rclpy + DDS, plus the node's own work
    if echo:
        transport_us = 1e6 / echo
        own_us = result["callback_profile"]["us_per_pair"]
        result["predicted_identifier_max_hz"] = 1e6 / (transport_us + own_us)
    return result
