"""A driver at 1 kHz with the controller not yet started: what the identifier takes, and its memory, over time.

    python bench/silent_topic.py --seconds 3600                 # sample pairing, one hour
    python bench/silent_topic.py --seconds 300 --pairing stamp  # stamp pairing, five minutes
    python bench/silent_topic.py --seconds 2400 --load 2        # both cores kept busy (two loops at nice 5)
    python bench/silent_topic.py --seconds 2400 --load 2 --no-guard   # without the console guard (issue 45)

Starts the real ``identifier`` (a subprocess, its own domain, discovery on this machine)
reading ``/joint_states`` (``sensor_msgs/JointState``, stamped, BEST_EFFORT, published
here at ``--rate`` Hz, joints in another order than the field names them) and ``/cmd``,
which nobody publishes. Every ``--every`` seconds it reads the node's resident memory
(VmRSS, /proc) and its latest ``status``: messages taken, halves dropped from a full
pairing queue (``overflow``) and what is queued. Issue 18 measured +4.4 MB in 50 s and
still rising before the queues had a cap; with the cap the queue fills in its first
10 s (MAX_QUEUE = 10 000 at 1 kHz) and memory must stay flat after that.

The node's stderr is a pipe this script reads only at the end, as a harness often does: its
warnings (a lone-input line every ``warn_period``) fill that pipe after about 25 minutes. Before
the console guard (``lenn_ros.nodes.console``) the node then blocked in ``write()`` and took
nothing more (issue 45); ``--no-guard`` runs it that way again. ``--participant shared`` puts the
inputs on the node's own DDS participant (``LENN_ROS_INPUTS_PARTICIPANT=0``).

Printed: the samples as they come (``--json``: only the result), then one JSON line with what was
taken against what was sent, the watchdog's and the console's counters, and the memory growth over
the run's second half, in kB and kB per minute.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from speed_online import read_memory_kb  # noqa: E402  (a script of bench/, beside this one)

from lenn_ros import topics  # noqa: E402


def identifier_command(pairing: str, rate: float) -> list[str]:
    """The identifier as a robot user starts it: remaps, types, fields and pairing, nothing else."""
    command_type = "sensor_msgs/msg/JointState" if pairing == "stamp" else "std_msgs/msg/Float64MultiArray"
    command_field = "position[joint1]" if pairing == "stamp" else "data[0]"
    return [
        sys.executable, "-m", "lenn_ros.nodes.identifier", "--ros-args",
        "-r", "u:=/cmd", "-r", "y_p:=/joint_states",
        "-p", f"u_type:={command_type}", "-p", f"u_field:={command_field}",
        "-p", "y_type:=sensor_msgs/msg/JointState", "-p", "y_field:=position[joint1]",
        "-p", f"pairing:={pairing}", "-p", f"sample_period:={1.0 / rate}", "-p", f"slop:={0.2 / rate}",
        "-p", "example:=0", "-p", "status_period:=1.0",
    ]  # fmt: skip


class Driver:
    """Publishes JointState at the rate from a thread of its own; keeps the identifier's latest status."""

    def __init__(self, domain: int, rate: float) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("silent_topic_driver", context=self.context)
        self.publisher = self.node.create_publisher(JointState, "/joint_states", qos_profile_sensor_data)
        self.message = JointState(name=["joint0", "joint1"], position=[0.0, 0.0])
        self.rate = rate
        self.status: dict = {}
        self.node.create_subscription(String, topics.STATUS, self._on_status, topics.data_qos())
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.spinner = threading.Thread(target=self.executor.spin, daemon=True)
        self.spinner.start()
        self.stop = threading.Event()
        self.sent = 0
        self.late = 0

    def _on_status(self, message) -> None:
        self.status = json.loads(message.data)

    def matched(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not self.stop.is_set():
            if self.publisher.get_subscription_count() >= 1:
                return True
            self.stop.wait(0.1)
        return False

    def publish(self) -> None:
        """Until ``stop``: one message per period, on a schedule (a late tick catches up, and is counted)."""
        period, start = 1.0 / self.rate, time.monotonic()
        clock = self.node.get_clock()
        while not self.stop.is_set():
            wait = start + self.sent * period - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            elif wait < -period:
                self.late += 1
            self.message.header.stamp = clock.now().to_msg()
            self.message.position[1] = 0.5 * ((self.sent * 7919) % 1000) / 1000.0
            self.publisher.publish(self.message)
            self.sent += 1

    def close(self) -> None:
        self.stop.set()
        self.executor.shutdown()
        self.spinner.join(timeout=5)
        self.node.destroy_node()
        self.context.try_shutdown()


def sample_row(elapsed: float, pid: int, driver: Driver) -> dict:
    status = driver.status
    counters = status.get("counters", {})
    return {
        "t_s": round(elapsed, 1),
        "rss_kb": (read_memory_kb(pid) or (0, 0))[0],
        "sent": driver.sent,
        "y_messages": counters.get("y_messages", 0),
        "overflow": counters.get("overflow", 0),
        "queued": sum(status.get("queued", {}).values()),
    }


def run(
    seconds: float, pairing: str, rate: float, every: float, domain: int, options: argparse.Namespace | None = None
) -> dict:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    if options is not None and options.no_guard:
        env["LENN_ROS_CONSOLE_GUARD"] = "0"
    if options is not None and options.participant == "shared":
        env["LENN_ROS_INPUTS_PARTICIPANT"] = "0"
    hogs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"], preexec_fn=lambda: os.nice(5))
        for _ in range(options.load if options is not None else 0)
    ]
    node = subprocess.Popen(
        identifier_command(pairing, rate), env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    driver = Driver(domain, rate)
    rows: list[dict] = []
    try:
        if not driver.matched(timeout=60.0):
            raise SystemExit("silent_topic: the identifier never subscribed to /joint_states")
        publisher = threading.Thread(target=driver.publish, daemon=True)
        start = time.monotonic()
        publisher.start()
        while (elapsed := time.monotonic() - start) < seconds and node.poll() is None:
            rows.append(sample_row(elapsed, node.pid, driver))
            if options is not None and not options.json:
                print_row(rows[-1])
            driver.stop.wait(min(every, max(seconds - elapsed, 0.0)))
        rows.append(sample_row(time.monotonic() - start, node.pid, driver))
        driver.stop.set()
        publisher.join(timeout=5)
    finally:
        for hog in hogs:
            hog.kill()
        driver.close()
        node.send_signal(signal.SIGINT)
        _, stderr = node.communicate(timeout=30)
    return summary(rows, pairing, rate, seconds, driver.late, stderr)


def print_row(row: dict) -> None:
    print(f"| {row['t_s']:.0f} | {row['rss_kb']} | {row['sent']} | {row['y_messages']} | {row['overflow']} | "
          f"{row['queued']} |", flush=True)  # fmt: skip


def summary(rows: list[dict], pairing: str, rate: float, seconds: float, late: int, stderr: str) -> dict:
    """Growth over the second half: the queue has long been full by then, so any growth is a leak."""
    half = [row for row in rows if row["t_s"] >= rows[-1]["t_s"] / 2]
    growth = half[-1]["rss_kb"] - half[0]["rss_kb"]
    minutes = max((half[-1]["t_s"] - half[0]["t_s"]) / 60.0, 1e-9)
    final = next((line for line in reversed(stderr.splitlines()) if line.startswith("identifier: {")), "")
    counters = json.loads(final.split(": ", 1)[1])["counters"] if final else {}
    return {
        "taken_share": round(counters.get("y_messages", 0) / max(rows[-1]["sent"], 1), 5),
        "console_lines_lost": counters.get("console_lines_lost"),
        "input_stalls": counters.get("input_stalls"),
        "pairing": pairing,
        "rate_hz": rate,
        "seconds": seconds,
        "rate_reached_hz": round(rows[-1]["sent"] / max(rows[-1]["t_s"], 1e-9), 1),
        "late_ticks": late,
        "rss_kb_first": rows[1]["rss_kb"] if len(rows) > 1 else rows[0]["rss_kb"],
        "rss_kb_max": max(row["rss_kb"] for row in rows),
        "rss_kb_end": rows[-1]["rss_kb"],
        "growth_kb_second_half": growth,
        "growth_kb_per_min_second_half": round(growth / minutes, 1),
        "final_counters": counters or None,
        "rows": rows,
    }


def print_table(result: dict) -> None:
    """The closing lines (the rows were printed as they came)."""
    print(
        f"RSS first {result['rss_kb_first']} kB, max {result['rss_kb_max']} kB, end {result['rss_kb_end']} kB; "
        f"second half: {result['growth_kb_second_half']:+d} kB ({result['growth_kb_per_min_second_half']:+.1f} "
        f"kB/min); publisher reached {result['rate_reached_hz']} Hz ({result['late_ticks']} late ticks)"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3600.0)
    parser.add_argument("--pairing", choices=("sample", "stamp"), default="sample")
    parser.add_argument("--rate", type=float, default=1000.0, help="JointState messages per second")
    parser.add_argument("--every", type=float, default=0.0, help="seconds between samples (0: seconds / 12)")
    parser.add_argument("--domain", type=int, default=0, help="ROS domain (0: one no concurrent run uses)")
    parser.add_argument("--json", action="store_true", help="print only the JSON result")
    parser.add_argument("--load", type=int, default=0, help="busy processes at nice 5 beside the run (2: both cores)")
    parser.add_argument("--no-guard", action="store_true", help="without the console guard (LENN_ROS_CONSOLE_GUARD=0)")
    parser.add_argument("--participant", choices=("separate", "shared"), default="separate",
                        help="the inputs on a DDS participant of their own (default) or on the node's")  # fmt: skip
    args = parser.parse_args()
    every = args.every or args.seconds / 12
    if not args.json:
        print(f"pairing {args.pairing}, {args.rate:.0f} Hz JointState, /cmd silent, {args.seconds:.0f} s, load "
              f"{args.load}, inputs {args.participant}{', no console guard' if args.no_guard else ''}")  # fmt: skip
        print("| t (s) | RSS (kB) | sent | taken (y_messages) | overflow | queued |")
        print("|---:|---:|---:|---:|---:|---:|")
    if args.domain:
        result = run(args.seconds, args.pairing, args.rate, every, args.domain, args)
    else:
        import domain_coordinator

        with domain_coordinator.domain_id() as domain:
            result = run(args.seconds, args.pairing, args.rate, every, domain, args)
    if not args.json:
        print_table(result)
    print(json.dumps({key: value for key, value in result.items() if key != "rows"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
