"""Re-record the shipped bags in ``bags/``: example 1-4, LeNN, 3000 training + 600 test samples.

Each is a real online run (recorder, identifier, plant_simulator as processes over
DDS, through :func:`lenn_ros.demo.run_demo`), so the bags hold what a user's recording
holds: u, y_p with their sequence numbers, the identifier's outputs, its ``samples``
and its ``identifier_config``. Run from the repository root:
``python bench/record_bags.py``.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

from lenn_ros.demo import run_demo

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    for example in (1, 2, 3, 4):
        with tempfile.TemporaryDirectory() as scratch:
            result = run_demo(example, "lenn", 3000, 600, seed=0, output=scratch)
            target = REPO / "bags" / f"example{example}"
            shutil.rmtree(target, ignore_errors=True)
            shutil.copytree(result["bag"], target)
            print(f"example {example}: live {result['live']['phase_nmse_db']:.3f} dB, "
                  f"offline {result['offline']['nmse_db']:.3f} dB -> {target}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
