"""What a SIGKILLed recorder really loses, counted at the publisher.

Each run: a recorder process (``flush_period`` F), a publisher in this process sending
``u`` and ``y_p`` (Float64, RELIABLE, like the simulator) at RATE Hz; after a random
2-4 s the recorder is SIGKILLed *while* samples are flowing. Loss per topic =
published before the kill - messages in the bag after ``bag-repair``. That includes
the unflushed tail of the writer *and* whatever DDS had delivered to the recorder's
reader queue (or still had in flight) and the recorder had not written yet.

Usage: ``nice python bench/recorder_kill.py --runs 8 --rate 1000 --flush-period 0.5 --seed 1``.
Prints each run and the max / mean loss in samples and in milliseconds of data, next
to the bound ``1.25 x F`` (flush period plus the flush timer's quarter period).
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


class PacedTalker:
    """u(k) = k and y_p(k) = -k at a fixed rate from one node, in a background thread."""

    def __init__(self, domain_id: int, rate: float) -> None:
        import rclpy
        from rclpy.context import Context

        from lenn_ros import topics

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("kill_talker", context=self.ctx)
        self.msg = topics.message_class(topics.FLOAT64)
        self.pubs = [self.node.create_publisher(self.msg, name, topics.data_qos()) for name in (topics.U, topics.Y_P)]
        self.rate, self.sent, self.running = rate, 0, threading.Event()
        self.lock = threading.Lock()
        self.thread = threading.Thread(target=self._loop, daemon=True)

    def matched(self, timeout: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout
        while min(p.get_subscription_count() for p in self.pubs) < 1:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        return True

    def start(self) -> None:
        self.running.set()
        self.thread.start()

    def _loop(self) -> None:
        start = time.monotonic()
        while self.running.is_set():
            due = int((time.monotonic() - start) * self.rate)
            with self.lock:
                while self.sent < due:
                    self.pubs[0].publish(self.msg(data=float(self.sent)))
                    self.pubs[1].publish(self.msg(data=-float(self.sent)))
                    self.sent += 1
            time.sleep(0.0005)

    def kill_while_sending(self, proc: subprocess.Popen[str]) -> int:
        """SIGKILL ``proc`` between two samples; returns how many samples were published before."""
        with self.lock:
            proc.kill()
            return self.sent

    def close(self) -> None:
        self.running.clear()
        if self.thread.is_alive():
            self.thread.join(timeout=5)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def start_recorder(out: Path, flush_period: float) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    args = [sys.executable, "-m", "lenn_ros.nodes.recorder", "--ros-args", "-p", f"output:={out}"]
    args += ["-p", f"flush_period:={flush_period}", "-p", "topics:=[u, y_p]"]
    return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def one_run(out: Path, rate: float, flush_period: float, seconds: float, domain_id: int) -> dict[str, float]:
    """Published-before-kill minus recovered (the worse of u and y_p). ROS_DOMAIN_ID must be ``domain_id``."""
    from lenn_ros.bag import recover

    talker = PacedTalker(domain_id, rate)
    proc = start_recorder(out, flush_period)
    try:
        if not talker.matched():
            raise RuntimeError("recorder did not subscribe")
        talker.start()
        time.sleep(seconds)
        published = talker.kill_while_sending(proc)
    finally:
        proc.kill()
        proc.communicate(timeout=10)
        talker.close()
    report = recover(out)
    counts = [report.messages.get("/u", 0), report.messages.get("/y_p", 0)]
    return {"published": published, "recovered": min(counts), "lost": published - min(counts)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--flush-period", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    import domain_coordinator

    rng = random.Random(args.seed)
    losses = []
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    with tempfile.TemporaryDirectory() as tmp, domain_coordinator.domain_id() as domain_id:
        os.environ["ROS_DOMAIN_ID"] = str(domain_id)
        for run in range(args.runs):
            seconds = rng.uniform(2.0, 4.0)
            result = one_run(Path(tmp) / f"run{run}", args.rate, args.flush_period, seconds, domain_id)
            losses.append(result["lost"])
            ms = 1000 * result["lost"] / args.rate
            print(f"run {run}: published {result['published']}, recovered {result['recovered']}, lost {result['lost']} "
                  f"({ms:.0f} ms)", flush=True)  # fmt: skip
    bound = 1.25 * args.flush_period * args.rate
    print(
        f"loss over {args.runs} runs at {args.rate:.0f} Hz, flush_period {args.flush_period} s: "
        f"max {max(losses)} samples ({1000 * max(losses) / args.rate:.0f} ms), "
        f"mean {statistics.mean(losses):.0f} ± {statistics.pstdev(losses):.0f}; "
        f"writer bound 1.25 x flush_period = {bound:.0f} samples"
    )


if __name__ == "__main__":
    main()
