"""Marginal end-to-end cost of ``lenn-ros reproduce`` (issue 12: at least 1 M samples/s).

    python bench/reproduce_marginal.py                       # N = 50 000 and 550 000, 5 repeats
    python bench/reproduce_marginal.py --source /tmp/old     # the same, against another checkout

The command is run as whole processes (``lenn-ros reproduce --example 1 --network
lenn --seeds 1 --iterations N``) at two N. Their difference in wall-clock seconds
is what the extra N2 - N1 training samples cost end to end: simulation, the
least-squares floor, online training and the test, while interpreter start-up,
imports, numba's cache loading and the 600-sample test cancel out. The two sizes
take turns within every repeat (a busy spell on a shared machine then slows both)
and each figure is the median over the repeats. A warm-up run at each size first
loads (or compiles) numba's cache, which the timed runs then find.

For the issue's second clause the same repeats also time the paper's rule as a plain
numpy loop, one sample at a time (``speed_offline.numpy_reference_loop``, on
features expanded beforehand, i.e. its rule alone), and the marginal rate is given
as a multiple of it. ``--source DIR`` puts DIR first on the children's PYTHONPATH,
so an older checkout (e.g. ``git archive HEAD lenn_ros | tar -x -C DIR``) is timed
with the same interpreter and packages.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))
import speed_offline as offline  # noqa: E402  (a script of bench/, next to this one)

SMALL, LARGE = 50_000, 550_000
TARGET = 1_000_000.0  # samples/s, issue 12


def command(iterations: int) -> list[str]:
    """The reproduce command for ``iterations`` training samples (the installed ``lenn-ros`` if found)."""
    script = Path(sys.executable).with_name("lenn-ros")  # this environment's, not another one on PATH
    entry = [str(script)] if script.exists() else [sys.executable, "-m", "lenn_ros.cli"]
    return [*entry, "reproduce", "--example", "1", "--network", "lenn", "--seeds", "1", "--iterations", str(iterations)]


def run_once(iterations: int, source: str | None = None) -> float:
    """Wall-clock seconds of one whole process; a failing run is an error, not a time."""
    env = dict(os.environ)
    if source:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(Path(source).resolve()), env.get("PYTHONPATH")) if p)
    start = time.perf_counter()
    done = subprocess.run(command(iterations), env=env, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    if done.returncode:
        raise RuntimeError(f"{' '.join(command(iterations))} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return seconds


def numpy_loop_seconds(samples: int) -> float:
    """Wall-clock seconds of the plain-numpy per-sample loop of the paper's rule over ``samples`` Ex. 1 samples."""
    example = offline.EXAMPLES[1]
    x, d = offline.training_pairs(example, samples)
    network = offline.fresh_network(example, "lenn", x, d)
    phi = network.features(x)
    start = time.perf_counter()
    offline.numpy_reference_loop(phi, d, network.weights_, float(network.alpha), float(network.beta))
    return time.perf_counter() - start


def measure(
    small: int, large: int, repeats: int, numpy_samples: int, source: str | None = None, warmup: bool = True
) -> dict[str, float]:
    """Median seconds at both sizes (taking turns), the marginal rate and the numpy loop's rate."""
    if warmup:
        run_once(small, source)
        run_once(large, source)
    times: dict[str, list[float]] = {"small": [], "large": [], "numpy": []}
    for _ in range(repeats):
        times["small"].append(run_once(small, source))
        times["large"].append(run_once(large, source))
        if numpy_samples:
            times["numpy"].append(numpy_loop_seconds(numpy_samples))
    result = {name: float(statistics.median(values)) for name, values in times.items() if values}
    extra = result["large"] - result["small"]
    result["marginal_samples_per_s"] = (large - small) / extra if extra > 0 else float("inf")
    if numpy_samples:
        result["numpy_samples_per_s"] = numpy_samples / result["numpy"]
        result["ratio_vs_numpy"] = result["marginal_samples_per_s"] / result["numpy_samples_per_s"]
    return result


def _count(value: float) -> str:
    return f"{value:,.0f}".replace(",", " ")


def format_table(small: int, large: int, repeats: int, result: dict[str, float]) -> str:
    """Markdown: seconds at both N, the marginal rate against the target and the numpy loop."""
    rate = result["marginal_samples_per_s"]
    verdict = "meets" if rate >= TARGET else "misses"
    lines = [
        f"`{' '.join(command(0)[:-1])} N`, wall clock, median of {repeats} (sizes taking turns)",
        "",
        "| N | seconds | marginal samples/s |",
        "|---|---|---|",
        f"| {_count(small)} | {result['small']:.3f} | |",
        f"| {_count(large)} | {result['large']:.3f} | {_count(rate)} ({verdict} {_count(TARGET)}) |",
    ]
    if "numpy_samples_per_s" in result:
        lines.append(
            f"| plain-numpy loop of the rule, per sample | | {_count(result['numpy_samples_per_s'])}: "
            f"the marginal rate is {result['ratio_vs_numpy']:.1f} x |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--small", type=int, default=SMALL, help=f"training samples of the short run ({SMALL})")
    parser.add_argument("--large", type=int, default=LARGE, help=f"training samples of the long run ({LARGE})")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs at each size (5)")
    parser.add_argument("--numpy-samples", type=int, default=20_000, help="samples of the numpy loop, 0: skip")
    parser.add_argument("--source", help="checkout to time instead (prepended to PYTHONPATH)")
    parser.add_argument("--no-warmup", action="store_true", help="skip the untimed first run at each size")
    args = parser.parse_args(argv)
    if not 0 < args.small < args.large or args.repeats < 1:
        parser.error("need 0 < --small < --large and --repeats >= 1")
    result = measure(args.small, args.large, args.repeats, args.numpy_samples, args.source, not args.no_warmup)
    if args.source:
        print(f"source: {Path(args.source).resolve()}")
    print(format_table(args.small, args.large, args.repeats, result))
    print(f"\nload average {' '.join(f'{v:.2f}' for v in os.getloadavg())}, numpy {np.__version__}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
