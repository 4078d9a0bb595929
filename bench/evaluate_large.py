"""``evaluate`` of a 10^6-sample recording, read to result (issue 12's target: >= 1 M samples/s).

Writes a bag holding the identifier's ``samples`` topic for Example 1 (simulated,
seed 0; the test phase is its last 600 samples), then times ``evaluate_bag`` on it
twice (the second run has numba's cache warm). Run: ``python bench/evaluate_large.py``.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from lenn_ros.bag import BagWriter
from lenn_ros.paper.evaluation import simulate
from lenn_ros.paper.examples import get_example
from lenn_ros.service.evaluation import evaluate_bag

REPO = Path(__file__).resolve().parents[1]


def write_bag(path: Path, samples: int) -> None:
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64MultiArray

    example = get_example(1)
    series = simulate(example.plant(), example.noise_db, 0, samples - 600, 600)
    with BagWriter(path) as writer:
        writer.add_topic("/samples")
        writer.add_topic("/test_start")
        writer.write_value("/test_start", samples - 600 + 1, 1)
        message = Float64MultiArray()
        for k in range(samples):
            learn = 1.0 if k < samples - 600 else 0.0
            message.data = [float(k + 1), k * 1e-3, float(series.u[k]), float(series.y[k]), learn]
            writer.write_raw("/samples", serialize_message(message), 10 + k * 1000, sequence=k + 1)


def main(samples: int = 1_000_000) -> int:
    with tempfile.TemporaryDirectory() as scratch:
        bag = Path(scratch) / "bag"
        write_bag(bag, samples)
        print("| run | seconds | samples/s | NMSE dB |\n|---|---|---|---|")
        for run in (1, 2):
            started = time.perf_counter()
            result = evaluate_bag(str(bag), str(REPO / "config" / "example1_lenn.yaml"))
            seconds = time.perf_counter() - started
            print(f"| {run} | {seconds:.2f} | {samples / seconds:,.0f} | {result.evaluation.nmse_db:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000))
