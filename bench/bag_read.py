"""Read speed in messages/s: lenn_ros' reads beside rosbags' and mcap's own readers, on the same bags.

Three bags are written once a run, in a temporary directory:

* ``scalar``: ``lenn-ros import-csv`` of ``--samples`` rows (``/u``, ``/y_p`` std_msgs/Float64, MCAP);
* ``robot mcap`` / ``robot sqlite3``: ``bench/robot_bag.py``'s recording of ``--seconds`` (a robot's
  own topics as ``ros2 bag record`` writes them: JointState at 500 Hz, Float64MultiArray commands
  at 100 Hz; no sequence numbers), the same messages in each storage.

Every reader reads every message of the bag's two input topics, each in a fresh process (so its
peak RSS is its own; the rise is over the process before the read), where it can read that storage
(else "-"):

* ``lenn_ros read_recording``: what ``fit`` / ``evaluate`` / ``bag-info`` do with the topic flags
  (``robot_bag.flags()``; none for the scalar bag): read, screened and paired by the node's session;
* ``lenn_ros read_halves``: its read alone (the columns the session is then offered);
* ``lenn_ros iter_messages``: the general reader, every message deserialised;
* ``rosbags AnyReader``: every message deserialised with rosbags' typestore;
* ``rosbags Reader``: rosbags' rosbag2 reader, raw CDR bytes;
* ``mcap make_reader``: ``mcap.reader.make_reader(f).iter_messages()``, raw, in its default log-time order
  (a heap merge), and in file order (``log_time_order=False``, as ``read_halves`` reads);
* ``mcap_ros2 decoder``: ``make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()``.

Seconds are the reading process's CPU time (the machine is shared), the median of ``--repeats``;
wall time is in ``--json``. Usage: ``nice python bench/bag_read.py`` (a 10-minute robot bag and
300 000 scalar samples, a few minutes), ``--seconds 60 --samples 50000`` (quick), ``--json``.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import datetime
import json
import multiprocessing
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing import forkserver
from pathlib import Path
from typing import Any

import numpy as np
import robot_bag


@dataclass(frozen=True)
class Bag:
    """A bag of the run: its name in the table, directory, storage, the flags a command reads it with."""

    name: str
    path: Path
    storage: str
    flags: dict[str, Any] | None  # read_recording's flags (None: the bag's plain u / y_p)
    topics: tuple[str, ...]
    values: dict[str, Any] = field(default_factory=dict)  # the node values read_halves is given


def robot_flags(joints: int = 3, rate: float = robot_bag.STATE_RATE) -> dict[str, Any]:
    """robot_bag's command-line flags as read_recording's flags dict."""
    items = robot_bag.flags(joints, rate)
    given = dict(zip(items[::2], items[1::2], strict=True))
    return {
        "u": [given["--u"]],
        "y": [given["--y"]],
        "u_field": given["--u-field"],
        "y_field": given["--y-field"],
        "sample_period": float(given["--sample-period"]),
    }


def write_scalar_bag(path: Path, samples: int) -> Path:
    """``import-csv`` of a CSV of ``samples`` rows (u, y) at 1 kHz."""
    from lenn_ros.bag import import_csv

    k = np.arange(samples)
    csv = path.with_suffix(".csv")
    np.savetxt(csv, np.c_[np.sin(k * 1e-3), np.cos(k * 1.3e-3)], delimiter=",", header="u,y", comments="", fmt="%.9g")
    import_csv(csv, "u", "y", 1e-3, path)
    csv.unlink()
    return path


def node_values(bag_path: Path, flags: dict[str, Any] | None) -> dict[str, Any]:
    """The node values a command reads ``bag_path`` with (what read_recording would give read_halves)."""
    from lenn_ros.service.recording import read_recording

    return read_recording(bag_path, flags).values


def write_bags(directory: Path, samples: int, seconds: float) -> list[Bag]:
    """The run's three bags; each bag's node values come from a 2-second twin (the same topics and types)."""
    directory.mkdir(parents=True, exist_ok=True)
    flags = robot_flags()
    twin_scalar = write_scalar_bag(directory / "twin_scalar", 200)
    twin_robot = robot_bag.write_robot_bag(directory / "twin_robot", 2.0, "mcap")
    scalar_values, robot_values = node_values(twin_scalar, None), node_values(twin_robot, flags)
    robot_topics = (flags["u"][0], flags["y"][0])
    return [
        Bag("scalar", write_scalar_bag(directory / "scalar", samples), "mcap", None, ("/u", "/y_p"), scalar_values),
        Bag("robot mcap", robot_bag.write_robot_bag(directory / "robot_mcap", seconds, "mcap"), "mcap", flags,
            robot_topics, robot_values),
        Bag("robot sqlite3", robot_bag.write_robot_bag(directory / "robot_sqlite3", seconds, "sqlite3"), "sqlite3",
            flags, robot_topics, robot_values),
    ]  # fmt: skip


# The readers: each returns (messages read, samples paired or None).


def lenn_read_recording(bag: Bag) -> tuple[int, int | None]:
    from lenn_ros.service.recording import read_recording

    reading = read_recording(bag.path, bag.flags)
    counters = reading.session.all_counters()
    return int(counters["u_messages"] + counters["y_messages"]), int(reading.samples.index.size)


def lenn_read_halves(bag: Bag) -> tuple[int, int | None]:
    from lenn_ros.service.recording import read_halves

    return sum(int(h.received.size) for h in read_halves(bag.path, bag.values)), None


def lenn_iter_messages(bag: Bag) -> tuple[int, int | None]:
    from lenn_ros.bag.reader import iter_messages

    return sum(1 for _ in iter_messages(bag.path, list(bag.topics))), None


def rosbags_anyreader(bag: Bag) -> tuple[int, int | None]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    count = 0
    with AnyReader([bag.path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        connections = [c for c in reader.connections if c.topic in bag.topics]
        for connection, _time, raw in reader.messages(connections=connections):
            reader.deserialize(raw, connection.msgtype)
            count += 1
    return count, None


def rosbags_reader(bag: Bag) -> tuple[int, int | None]:
    from rosbags.rosbag2 import Reader

    count = 0
    with Reader(bag.path) as reader:
        connections = [c for c in reader.connections if c.topic in bag.topics]
        for _connection, _time, _raw in reader.messages(connections=connections):
            count += 1
    return count, None


def _mcap_files(bag: Bag) -> list[Path]:
    from lenn_ros.bag.reader import open_bag

    return list(open_bag(bag.path).files)


def mcap_raw(bag: Bag) -> tuple[int, int | None]:
    from mcap.reader import make_reader

    count = 0
    for file in _mcap_files(bag):
        with file.open("rb") as f:
            for _schema, _channel, _message in make_reader(f).iter_messages(topics=list(bag.topics)):
                count += 1
    return count, None


def mcap_raw_file_order(bag: Bag) -> tuple[int, int | None]:
    from mcap.reader import make_reader

    count = 0
    for file in _mcap_files(bag):
        with file.open("rb") as f:
            for _record in make_reader(f).iter_messages(topics=list(bag.topics), log_time_order=False):
                count += 1
    return count, None


def mcap_ros2_decoded(bag: Bag) -> tuple[int, int | None]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    count = 0
    for file in _mcap_files(bag):
        with file.open("rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for _decoded in reader.iter_decoded_messages(topics=list(bag.topics)):
                count += 1
    return count, None


#: name -> (reader, the storages it reads)
READERS: dict[str, tuple[Callable[[Bag], tuple[int, int | None]], tuple[str, ...]]] = {
    "lenn_ros read_recording (read + pair)": (lenn_read_recording, ("mcap", "sqlite3")),
    "lenn_ros read_halves (read)": (lenn_read_halves, ("mcap", "sqlite3")),
    "lenn_ros iter_messages (deserialised)": (lenn_iter_messages, ("mcap", "sqlite3")),
    "rosbags AnyReader (deserialised)": (rosbags_anyreader, ("mcap", "sqlite3")),
    "rosbags Reader (raw)": (rosbags_reader, ("mcap", "sqlite3")),
    "mcap make_reader (raw)": (mcap_raw, ("mcap",)),
    "mcap make_reader (raw, file order)": (mcap_raw_file_order, ("mcap",)),
    "mcap_ros2 decoder (deserialised)": (mcap_ros2_decoded, ("mcap",)),
}


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _import_readers() -> None:
    """Every reader's modules, so the RSS rise of a read is the read's, not its imports'."""
    import mcap.reader  # noqa: F401
    import mcap_ros2.decoder  # noqa: F401
    import rosbags.highlevel
    import rosbags.rosbag2  # noqa: F401

    import lenn_ros.service.recording  # noqa: F401


def measure(reader: str, bag: Bag, repeats: int) -> dict[str, Any]:
    """One reader on one bag, ``repeats`` times in this process: median CPU and wall seconds, peak RSS."""
    work = READERS[reader][0]
    _import_readers()
    before = _rss_mb()
    cpu, wall, messages, pairs = [], [], 0, None
    for _ in range(repeats):
        start_cpu, start_wall = time.process_time(), time.perf_counter()
        messages, pairs = work(bag)
        cpu.append(time.process_time() - start_cpu)
        wall.append(time.perf_counter() - start_wall)
    seconds = statistics.median(cpu)
    return {
        "bag": bag.name,
        "reader": reader,
        "messages": messages,
        "pairs": pairs,
        "seconds": seconds,
        "wall_seconds": statistics.median(wall),
        "messages_per_s": messages / seconds if seconds > 0 else float("inf"),
        "peak_rss_mb": _rss_mb(),
        "rss_rise_mb": _rss_mb() - before,
    }


def run(
    samples: int = 300_000,
    seconds: float = 600.0,
    repeats: int = 1,
    isolate: bool = True,
    readers: list[str] | None = None,
    directory: Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Write the bags, then every reader on every bag it can read (each in its own process where ``isolate``)."""
    chosen = list(READERS) if readers is None else readers
    # Each reader in a process forked from a server started now, while this one is small: a child's peak RSS
    # (ru_maxrss) starts from its parent's, and this process grows by writing the bags.
    context = multiprocessing.get_context("forkserver")
    if isolate:
        forkserver.ensure_running()
    with tempfile.TemporaryDirectory(dir=directory) as tmp:
        start = time.perf_counter()
        bags = write_bags(Path(tmp), samples, seconds)
        written = time.perf_counter() - start
        if progress:
            progress(f"wrote the bags in {written:.0f} s")
        rows = []
        for bag in bags:
            for reader in chosen:
                if bag.storage not in READERS[reader][1]:
                    rows.append({"bag": bag.name, "reader": reader, "messages": None})
                    continue
                if isolate:
                    with concurrent.futures.ProcessPoolExecutor(1, mp_context=context) as pool:
                        row = pool.submit(measure, reader, bag, repeats).result()
                else:
                    row = measure(reader, bag, repeats)
                rows.append(row)
                if progress:
                    progress(f"{bag.name:14s} {reader:40s} {row['messages_per_s']:12,.0f} msg/s")
        sizes = {bag.name: sum(f.stat().st_size for f in bag.path.iterdir()) for bag in bags}
    return {
        "samples": samples,
        "seconds": seconds,
        "repeats": repeats,
        "isolated": isolate,
        "bag_bytes": sizes,
        "write_seconds": written,
        "rows": rows,
        **machine(),
    }


def machine() -> dict[str, Any]:
    """When, where and on what the run was made."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent, check=False).stdout.strip()  # fmt: skip
    except OSError:
        commit = ""
    from importlib.metadata import PackageNotFoundError, version

    versions = {"python": sys.version.split()[0]}
    for name in ("numpy", "rosbags", "mcap", "mcap-ros2-support"):
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = "-"
    return {
        "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
        "commit": commit,
        "load_average": os.getloadavg(),
        "cpus": os.cpu_count(),
        "versions": versions,
    }


def markdown(report: dict[str, Any]) -> str:
    """The table: one row per bag and reader, "-" where the reader does not read that storage."""
    lines = [
        "| bag | reader | messages | seconds | messages/s | peak RSS (rise), MB |",
        "|---|---|---|---|---|---|",
    ]
    for row in report["rows"]:
        if row["messages"] is None:
            lines.append(f"| {row['bag']} | {row['reader']} | - | - | - | - |")
            continue
        pairs = f" ({row['pairs']:,} pairs)" if row.get("pairs") is not None else ""
        lines.append(
            f"| {row['bag']} | {row['reader']} | {row['messages']:,}{pairs} | {row['seconds']:.2f} | "
            f"{row['messages_per_s']:,.0f} | {row['peak_rss_mb']:.0f} ({row['rss_rise_mb']:+.0f}) |"
        )
    return "\n".join(lines)


def wide(report: dict[str, Any]) -> str:
    """The same, a row per bag (as bench/RESULTS.md holds it): messages/s (CPU s, RSS rise MB) per reader."""
    bags = list(dict.fromkeys(row["bag"] for row in report["rows"]))
    readers = list(dict.fromkeys(row["reader"] for row in report["rows"]))
    lines = ["| bag (messages) | " + " | ".join(readers) + " |", "|---" * (len(readers) + 1) + "|"]
    for bag in bags:
        rows = {row["reader"]: row for row in report["rows"] if row["bag"] == bag}
        counted = max((row["messages"] or 0) for row in rows.values())
        cells = [
            "-" if rows[r]["messages"] is None else
            f"{_spaced(rows[r]['messages_per_s'])} ({rows[r]['seconds']:.2f} s, {rows[r]['rss_rise_mb']:+.0f} MB)"
            for r in readers
        ]  # fmt: skip
        lines.append(f"| {bag} ({_spaced(counted)}) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _spaced(number: float) -> str:
    return f"{number:,.0f}".replace(",", " ")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=300_000, help="rows of the import-csv scalar bag")
    parser.add_argument("--seconds", type=float, default=600.0, help="length of the robot bag (500 Hz JointState)")
    parser.add_argument("--repeats", type=int, default=1, help="runs of each reader (the median is shown)")
    parser.add_argument("--readers", nargs="*", choices=list(READERS), metavar="NAME", help="only these readers")
    parser.add_argument("--in-process", action="store_true", help="every reader in this process (no peak RSS each)")
    parser.add_argument("--dir", type=Path, help="where to write the bags (default: the temporary directory)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--wide", action="store_true", help="a row per bag (bench/RESULTS.md's table)")
    args = parser.parse_args()

    def say(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    report = run(args.samples, args.seconds, args.repeats, not args.in_process, args.readers, args.dir, say)
    if args.json:
        print(json.dumps(report, indent=1, default=str))
        return 0
    load = ", ".join(f"{x:.2f}" for x in report["load_average"])
    print(f"{report['date']}, commit {report['commit']}, load average {load} ({report['cpus']} CPUs)")
    print(f"scalar bag {args.samples} samples, robot bags {args.seconds:g} s; {report['versions']}\n")
    print(wide(report) if args.wide else markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
