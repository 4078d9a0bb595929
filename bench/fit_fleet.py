"""A fleet's logs fitted on a Dask cluster against the serial ``lenn-ros fit`` one by one, in one run.

    python bench/fit_fleet.py                       # 12 logs of 4000 samples, local:2 (this machine's cores)
    python bench/fit_fleet.py --logs 24 --samples 8000 --cluster local:4
    python bench/fit_fleet.py --cluster loopback    # a running scheduler and two workers, as a user's cluster

The same logs (a plant with a cubic stiffness, one seed each) are fitted twice:

- ``serial``: one ``lenn-ros fit LOG ... -o MODELS/NAME`` process after another, as a user would;
- ``fleet``: one ``lenn-ros fit-fleet LOGS ... -o MODELS --cluster ...`` process, an embedded cluster's start
  included; ``--cluster loopback``: a scheduler and two plain ``dask worker --nthreads 1`` (no lenn_ros
  variables) started before the timing, their CPU seconds added to the fleet's;
- ``serial, one thread``: the serial fits confined to one thread each (``LENN_ROS_THREADS=1``, BLAS alike), as
  each fleet worker runs them: what the fleet's two workers do against one, where the serial ``fit`` already
  spreads its own candidates over the cores (its CPU seconds over its wall say how many it used).

Both write into the same folders (the fleet first; its files are read, then the serial fit writes over
them), so the models are compared as bytes: params.yaml whole, every array of weights.npz. One fit of
the first log runs before both (numba's cache on disk, the files in the page cache), untimed. On a
machine others share, the two alternate for ``--rounds`` and each is reported by its fastest round,
with the load average over its rounds and its CPU seconds (the processes and all they started).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
from test_fit_fleet import plant  # noqa: E402  (one definition of the logs' plant)

from lenn_ros.core.threads import LIBRARY_THREADS, worker_environment  # noqa: E402

FLAGS = ["--u", "input", "--y", "output"]


def write_logs(folder: Path, count: int, samples: int) -> list[Path]:
    folder.mkdir(parents=True)
    paths = []
    for seed in range(count):
        u, y = plant(samples, seed)
        path = folder / f"joint{seed:02d}.csv"
        np.savetxt(path, np.c_[np.arange(samples), u, y], delimiter=",", header="t,input,output", comments="")
        paths.append(path)
    return paths


def lenn_ros(*arguments: str, env: dict[str, str] | None = None) -> float:
    """Run ``lenn-ros ARGUMENTS`` (its output kept quiet; ``env`` added to the environment); its wall time in s."""
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "lenn_ros.cli", *arguments], capture_output=True, text=True,
                          env={**os.environ, **(env or {})})  # fmt: skip
    if done.returncode != 0:
        sys.exit(f"lenn-ros {arguments[0]} failed: {done.stderr.strip().splitlines()[-1:]}")
    return time.monotonic() - started


def measured(work) -> tuple[float, float, float]:
    """(wall seconds, CPU seconds of the processes it started, the 1-minute load average after) of ``work()``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall = work()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return wall, cpu, os.getloadavg()[0]


@contextlib.contextmanager
def loopback_cluster(workers: int = 2) -> Iterator[tuple[str, list[subprocess.Popen]]]:
    """A ``dask scheduler`` and ``workers`` plain ``dask worker --nthreads 1`` on 127.0.0.1, started (and joined) before
    any timing, as a user's cluster is: no lenn_ros variables in their environment (issue 44's check)."""
    import distributed

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    address, dask = f"tcp://127.0.0.1:{port}", str(Path(sys.executable).parent / "dask")
    env = {k: v for k, v in os.environ.items() if k not in ("LENN_ROS_THREADS", *LIBRARY_THREADS)}
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "env": env, "start_new_session": True}
    started = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                                **quiet)]  # fmt: skip
    started += [subprocess.Popen([dask, "worker", address, "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1"],
                                 **quiet) for _ in range(workers)]  # fmt: skip
    try:
        with distributed.Client(address, timeout=60) as client:
            client.wait_for_workers(workers, timeout=60)
        yield address, started
    finally:
        for process in started:
            os.killpg(process.pid, signal.SIGTERM)
            process.wait(timeout=30)


def cpu_of(processes: list[subprocess.Popen]) -> float:
    """CPU seconds so far of running processes and their children (a worker's nanny and the worker it started)."""
    import psutil

    total = 0.0
    for process in processes:
        parent = psutil.Process(process.pid)
        for each in [parent, *parent.children(recursive=True)]:
            times = each.cpu_times()
            total += times.user + times.system
    return total


def model_files(folder: Path) -> tuple[bytes, dict[str, np.ndarray]]:
    with np.load(folder / "weights.npz") as weights:
        return (folder / "params.yaml").read_bytes(), {key: weights[key] for key in weights.files}


def same(a: tuple[bytes, dict[str, np.ndarray]], b: tuple[bytes, dict[str, np.ndarray]]) -> bool:
    return a[0] == b[0] and a[1].keys() == b[1].keys() and all(np.array_equal(a[1][k], b[1][k]) for k in a[1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--logs", type=int, default=12, help="logs in the fleet (default 12)")
    parser.add_argument("--samples", type=int, default=4000, help="samples per log, the last fifth the test part")
    parser.add_argument("--cluster", default="local:2", help="fit-fleet's --cluster (default local:2), or loopback: "
                        "a scheduler and two plain one-thread workers started before the timing")  # fmt: skip
    parser.add_argument("--rounds", type=int, default=2, help="serial and fleet alternately (default 2)")
    options = parser.parse_args()
    flags = [*FLAGS, "--test-from", str(options.samples * 4 // 5 + 1)]
    runs: dict[str, list[tuple[float, float, float]]] = {"serial": [], "fleet": [], "serial, one thread": []}
    one_thread = worker_environment(1)
    with contextlib.ExitStack() as stack:
        if options.cluster == "loopback":
            address, cluster = stack.enter_context(loopback_cluster())
        else:
            address, cluster = options.cluster, []
        scratch = stack.enter_context(tempfile.TemporaryDirectory(prefix="fit-fleet-bench-"))
        root = Path(scratch)
        logs, models = write_logs(root / "logs", options.logs, options.samples), root / "models"
        lenn_ros("fit", str(logs[0]), *flags, "-o", str(root / "warm"))
        equal = 0
        fleet = ("fit-fleet", str(root / "logs"), *flags, "-o", str(models), "--cluster", address)
        serial = [("fit", str(log), *flags, "-o", str(models / log.stem)) for log in logs]
        for _ in range(options.rounds):
            workers_before = cpu_of(cluster)
            wall, cpu, load = measured(lambda: lenn_ros(*fleet, "--force"))
            runs["fleet"].append((wall, cpu + cpu_of(cluster) - workers_before, load))
            fleet_models = {log.stem: model_files(models / log.stem) for log in logs}
            runs["serial"].append(measured(lambda: sum(lenn_ros(*argv) for argv in serial)))
            equal = sum(same(fleet_models[log.stem], model_files(models / log.stem)) for log in logs)
            runs["serial, one thread"].append(measured(lambda: sum(lenn_ros(*a, env=one_thread) for a in serial)))
            equal = min(equal, sum(same(fleet_models[log.stem], model_files(models / log.stem)) for log in logs))
    print(f"{options.logs} logs of {options.samples} samples, fit-fleet --cluster {options.cluster}, "
          f"{os.cpu_count()} cores, best of {options.rounds} rounds")  # fmt: skip
    print("| | wall (best) | wall (each round) | CPU s | load avg |")
    print("|---|---|---|---|---|")
    for name, rows in runs.items():
        walls = ", ".join(f"{wall:.1f}" for wall, _, _ in rows)
        cpu, load = min(rows)[1], sum(row[2] for row in rows) / len(rows)
        print(f"| {name} | {min(rows)[0]:.1f} s | {walls} | {cpu:.1f} | {load:.1f} |")
    print(f"speed-up (best wall): {min(runs['serial'])[0] / min(runs['fleet'])[0]:.2f}x over serial fit, "
          f"{min(runs['serial, one thread'])[0] / min(runs['fleet'])[0]:.2f}x over it on one thread each; "
          f"models bit-identical: {equal} of {options.logs}")  # fmt: skip
    return 0 if equal == options.logs else 1


if __name__ == "__main__":
    sys.exit(main())
