"""The identifier under overload: JointState bursts at 2x and 10x what it can process.

    python bench/overload.py                      # 5 s bursts
    python bench/overload.py --burst 10 --json

Starts the real ``identifier`` (a subprocess, README robot settings, ``pairing:=sample``
at 1 kHz, ``status_period:=0.2``) and a publisher subprocess (``--publisher``: this
script again) that sends ``/joint_states`` (JointState, stamped, BEST_EFFORT) and
``/cmd`` (Float64MultiArray, 50 Hz). This process only measures, so the publisher's
work does not delay its service calls:

1. capacity: 3 s of JointState as fast as the publisher can, with shedding off
   (``max_lag:=0``, set live): the rate of messages the node processed (``y_messages``);
2. the schedule: 1 kHz, then a burst at 2x capacity, 1 kHz, a burst at 10x capacity (or
   as fast as the publisher can, when that is less), 1 kHz;
3. throughout, a ``set_parameters`` call (``warn_period``, a live parameter) every 0.1 s:
   its latency, p50 and max per phase; the period of ``status`` per phase; ``shed`` per
   phase; recovery: seconds from a burst's end until ``status`` shows a lag under 50 ms;
4. SIGINT during a last burst at 10x: seconds until the process has exited.

Printed: one table and one JSON line (``--json``: only that).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from probe import Probe  # noqa: E402  (bench/, this script's folder)

NOMINAL_HZ = 1000.0
CALL_EVERY = 0.1  # s between parameter calls
RECOVERED_LAG = 0.05  # s: the node has caught up once status shows a lag under this
LOG = Path("/tmp/lenn_ros_overload_identifier.log")  # the identifier's output, for a look after the run


def identifier_command() -> list[str]:
    return [
        sys.executable, "-m", "lenn_ros.nodes.identifier", "--ros-args",
        "-r", "u:=/cmd", "-r", "y_p:=/joint_states",
        "-p", "u_type:=std_msgs/msg/Float64MultiArray", "-p", "u_field:=data[0]",
        "-p", "y_type:=sensor_msgs/msg/JointState", "-p", "y_field:=position[joint1]",
        "-p", "pairing:=sample", "-p", f"sample_period:={1.0 / NOMINAL_HZ}", "-p", "status_period:=0.2",
        "-p", "example:=0", "-p", "y_lags:=2", "-p", "u_lags:=2", "-p", "solver:=rls", "-p", "output:=linear",
        "-p", "y_scale:=3.2", "-p", "u_scale:=3.2",
    ]  # fmt: skip


# -- the publisher (a subprocess: --publisher) --------------------------------------------------
def publish_schedule(schedule: list[tuple[float, float]]) -> None:
    """(seconds, rate) phases, rate 0 = as fast as it can; prints each phase's start (monotonic) and count."""
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    rclpy.init()
    node = rclpy.create_node("overload_publisher")
    joints = node.create_publisher(JointState, "/joint_states", qos_profile_sensor_data)
    command = node.create_publisher(Float64MultiArray, "/cmd", qos_profile_sensor_data)
    deadline = time.monotonic() + 30.0
    while joints.get_subscription_count() < 1 or command.get_subscription_count() < 1:
        if time.monotonic() > deadline:
            raise SystemExit("overload publisher: no identifier subscribed within 30 s")
        time.sleep(0.05)
    time.sleep(1.0)  # the node's start-up line, discovery settled
    message, order = JointState(name=["joint0", "joint1"], position=[0.0, 0.0]), Float64MultiArray(data=[0.0])
    clock, sent = node.get_clock(), 0
    for seconds, rate in schedule:
        start, base = time.monotonic(), sent
        print(json.dumps({"start": start, "rate": rate, "sent": sent}), flush=True)
        next_command = start
        while (now := time.monotonic()) < start + seconds:
            if now >= next_command:
                order.data[0] = 0.5 * ((sent * 104729) % 1000) / 1000.0
                command.publish(order)
                next_command += 0.02
            due = sent + 1 if rate <= 0 else base + int((now - start) * rate) + 1  # 0: as fast as it can
            while sent < due:
                message.header.stamp = clock.now().to_msg()
                message.position[1] = 0.3 * ((sent * 7919) % 1000) / 1000.0
                joints.publish(message)
                sent += 1
            if rate > 0:
                time.sleep(0.0005)
        print(json.dumps({"end": time.monotonic(), "sent": sent}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


# -- the measuring side ---------------------------------------------------------------------------
class ScheduledProbe(Probe):
    """The probe calling ``warn_period`` every ``CALL_EVERY`` s while ``calling`` is set, each call kept."""

    def __init__(self) -> None:
        super().__init__("overload_probe")
        self.calls: list[tuple[float, float | None]] = []  # (sent at, latency or None: no answer in 5 s)
        self.calling = threading.Event()

    def call(self, value: float, name: str = "warn_period") -> float | None:
        return self.set(name, value)[0]

    def call_on_schedule(self) -> None:
        while self.calling.is_set():
            sent = time.monotonic()
            self.calls.append((sent, self.call(5.0 + 0.5 * (len(self.calls) % 2))))
            time.sleep(max(0.0, CALL_EVERY - (time.monotonic() - sent)))


def start_publisher(schedule: list[tuple[float, float]], env: dict[str, str]) -> subprocess.Popen[str]:
    argv = [sys.executable, __file__, "--publisher", json.dumps(schedule)]
    return subprocess.Popen(argv, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)


def read_phases(publisher: subprocess.Popen[str]) -> list[dict]:
    """The publisher's phase lines (start, rate, sent; then end, sent), read as it goes."""
    phases: list[dict] = []
    assert publisher.stdout is not None
    for line in publisher.stdout:
        record = json.loads(line)
        if "start" in record:
            phases.append(record)
        else:
            phases[-1].update({"end": record["end"], "sent_end": record["sent"]})
    return phases


def measure_capacity(probe: Probe, env: dict[str, str], seconds: float = 3.0) -> dict:
    """Messages per second the node processes when it sheds nothing (max_lag 0) and is flooded."""
    assert probe.call(0.0, "max_lag") is not None
    publisher = start_publisher([(seconds, 0.0)], env)
    phase = read_phases(publisher)[0]
    publisher.wait(timeout=30)
    time.sleep(0.5)  # the last status of the flood
    assert probe.call(0.5, "max_lag") is not None  # shedding on again (the default)
    wait_until_caught_up(probe)
    taken = probe.counter("y_messages", phase["end"]) - probe.counter("y_messages", phase["start"])
    shed = probe.counter("shed", phase["end"] + 0.3) - probe.counter("shed", phase["start"])
    sent = phase["sent_end"] - phase["sent"]
    duration = phase["end"] - phase["start"]
    return {"processed_hz": round(taken / duration), "published_hz": round(sent / duration), "shed": shed}


def wait_until_caught_up(probe: Probe, timeout: float = 60.0) -> None:
    """Until status shows the node caught up (the backlog of the unshed flood is worked off or overwritten)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if (
            probe.statuses
            and probe.statuses[-1][1]["lag_s"] < RECOVERED_LAG
            and probe.statuses[-1][0] > time.monotonic() - 0.5
        ):
            return
        time.sleep(0.05)


def phase_figures(probe: Probe, phase: dict) -> dict:
    start, end = phase["start"], phase["end"]
    latencies = [latency for sent, latency in probe.calls if start <= sent < end]
    answered = [latency for latency in latencies if latency is not None]
    times = [received for received, _ in probe.statuses if start <= received < end]
    periods = [b - a for a, b in itertools.pairwise(times)]
    recovered = next(
        (received - end for received, status in probe.statuses if received >= end and status["lag_s"] < RECOVERED_LAG),
        None,
    )
    return {
        "rate_hz": round((phase["sent_end"] - phase["sent"]) / (end - start)),
        "calls": len(latencies),
        "unanswered": len(latencies) - len(answered),
        "call_p50_ms": round(1e3 * statistics.median(answered), 1) if answered else None,
        "call_max_ms": round(1e3 * max(answered), 1) if answered else None,
        "status_period_p50_s": round(statistics.median(periods), 3) if periods else None,
        "status_period_max_s": round(max(periods), 3) if periods else None,
        "shed": probe.counter("shed", end + 0.25) - probe.counter("shed", start),
        "processed_hz": round((probe.counter("y_messages", end) - probe.counter("y_messages", start)) / (end - start)),
        "recovered_s": round(recovered, 2) if recovered is not None and phase["rate"] != NOMINAL_HZ else None,
    }


def sigint_exit(node: subprocess.Popen, env: dict[str, str], rate: float) -> float:
    """SIGINT in the middle of a burst; seconds until the process is gone (polled every 10 ms)."""
    if node.poll() is not None:
        raise SystemExit(f"overload: the identifier exited ({node.returncode}) before the SIGINT; see {LOG}")
    publisher = start_publisher([(6.0, rate)], env)
    assert publisher.stdout is not None
    start = json.loads(publisher.stdout.readline())["start"]
    while time.monotonic() < start + 2.0:
        time.sleep(0.01)
    sent = time.monotonic()
    node.send_signal(signal.SIGINT)
    while node.poll() is None and time.monotonic() < sent + 30.0:
        time.sleep(0.01)
    exit_s = time.monotonic() - sent
    publisher.kill()
    publisher.wait()
    return exit_s


def run(burst: float) -> dict:
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    os.environ.update(env)
    log = open(LOG, "w")  # noqa: SIM115 (closed once the node is started: the process keeps it)
    node = subprocess.Popen(identifier_command(), env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=log)
    log.close()
    probe = ScheduledProbe()
    try:
        if not probe.setter.wait_for_service(timeout_sec=60.0):
            raise SystemExit("overload: the identifier's parameter service never appeared")
        capacity = measure_capacity(probe, env)
        rates = {"2x": 2 * capacity["processed_hz"], "10x": 10 * capacity["processed_hz"]}
        schedule = [(3.0, NOMINAL_HZ), (burst, rates["2x"]), (5.0, NOMINAL_HZ), (burst, rates["10x"]),
                    (5.0, NOMINAL_HZ)]  # fmt: skip
        probe.calling.set()
        caller = threading.Thread(target=probe.call_on_schedule, daemon=True)
        caller.start()
        publisher = start_publisher(schedule, env)
        phases = read_phases(publisher)
        publisher.wait(timeout=30)
        time.sleep(0.5)
        probe.calling.clear()
        caller.join(timeout=10)
        names = ["1 kHz", "2x", "1 kHz after 2x", "10x", "1 kHz after 10x"]
        figures = {name: phase_figures(probe, phase) for name, phase in zip(names, phases, strict=True)}
        exit_s = sigint_exit(node, env, rates["10x"])
    finally:
        probe.close()
        if node.poll() is None:
            node.kill()
        node.wait(timeout=30)
    return {"capacity": capacity, "asked_hz": rates, "phases": figures, "sigint_exit_s": round(exit_s, 2)}


def print_table(result: dict) -> None:
    capacity = result["capacity"]
    print(f"capacity: {capacity['processed_hz']} JointState/s processed while the publisher sent "
          f"{capacity['published_hz']}/s ({capacity['shed']} shed)")  # fmt: skip
    print("| phase | published (Hz) | processed (Hz) | shed | param call p50 / max (ms) | unanswered | "
          "status period p50 / max (s) | recovered (s) |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, row in result["phases"].items():
        print(f"| {name} | {row['rate_hz']} | {row['processed_hz']} | {row['shed']} | {row['call_p50_ms']} / "
              f"{row['call_max_ms']} | {row['unanswered']} of {row['calls']} | {row['status_period_p50_s']} / "
              f"{row['status_period_max_s']} | {row['recovered_s']} |")  # fmt: skip
    print(f"SIGINT during a burst at 10x: exited after {result['sigint_exit_s']} s")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--burst", type=float, default=5.0, help="seconds of each burst")
    parser.add_argument("--json", action="store_true", help="print only the JSON result")
    parser.add_argument("--publisher", help=argparse.SUPPRESS)  # (the publisher subprocess: its schedule)
    args = parser.parse_args()
    if args.publisher:
        publish_schedule([tuple(phase) for phase in json.loads(args.publisher)])
        return 0
    if "ROS_DOMAIN_ID" in os.environ:
        result = run(args.burst)
    else:
        import domain_coordinator

        with domain_coordinator.domain_id() as domain:
            os.environ["ROS_DOMAIN_ID"] = str(domain)
            result = run(args.burst)
    if not args.json:
        print_table(result)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
