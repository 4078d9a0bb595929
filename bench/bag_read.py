"""Reading a run bag: lenn_ros' numpy fast path vs rosbags' AnyReader vs lenn_ros' per-message reader.

Writes one bag of N samples (``/u``, ``/y_p`` Float64 and ``/samples`` Float64MultiArray
[index, time, u, y_p, learn], as a live run records them), then times on that same file:

* ``read_run`` (u and y_p through :mod:`lenn_ros.bag.scalars`) and ``read_samples``;
* rosbags ``AnyReader``: every u / y_p message deserialised (what bag.py did before);
* ``iter_messages`` on u / y_p (the general path, any type).

Samples/s = N / seconds (a sample = one u and one y_p message). Usage:
``nice python bench/bag_read.py --samples 1000000 --repeats 3`` (the median is printed).
"""

from __future__ import annotations

import argparse
import statistics
import struct
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from lenn_ros.bag import BagWriter, iter_messages, read_run, read_samples

_CDR = b"\x00\x01\x00\x00"
#: Float64MultiArray with one labelled dimension, as the identifier publishes ``samples``.
_LAYOUT = _CDR + struct.pack("<I", 1) + struct.pack("<I", 6) + b"index\x00" + b"\x00\x00" + struct.pack("<III", 5, 5, 0)


def write_bag(path: Path, n: int) -> None:
    """n samples at 1 kHz log time; raw CDR built with struct (writing is not what is measured)."""
    with BagWriter(path, flush_period=None) as bag:
        for name in ("/u", "/y_p", "/samples"):
            bag.add_topic(name)
        for k in range(n):
            t = k * 1_000_000
            u, y = np.sin(k * 1e-3), np.cos(k * 1e-3)
            bag.write_raw("/u", _CDR + struct.pack("<d", u), t, publish_time_ns=t, sequence=k + 1)
            bag.write_raw("/y_p", _CDR + struct.pack("<d", y), t + 1, publish_time_ns=t, sequence=k + 1)
            row = _LAYOUT + struct.pack("<I", 5) + struct.pack("<5d", k + 1, k * 1e-3, u, y, 1.0)
            bag.write_raw("/samples", row, t + 2)


def anyreader(path: Path) -> int:
    count = 0
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic in ("/u", "/y_p")]
        for conn, _t, raw in reader.messages(connections=conns):
            reader.deserialize(raw, conn.msgtype).data  # noqa: B018 (the decoded value is the work)
            count += 1
    return count


def general(path: Path) -> int:
    return sum(1 for m in iter_messages(path, ["/u", "/y_p"]) if m.message.data is not None)


def median_seconds(work: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--slow-repeats", type=int, default=1, help="repeats for the per-message readers")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench"
        start = time.perf_counter()
        write_bag(path, args.samples)
        print(f"wrote {args.samples} samples ({3 * args.samples} messages) in {time.perf_counter() - start:.1f} s")
        run = read_run(path)
        samples = read_samples(path)
        assert run.u.size == args.samples and samples is not None and samples.index[-1] == args.samples
        assert anyreader(path) == 2 * args.samples
        rows = [
            ("read_run (numpy fast path, u + y_p)", lambda: read_run(path), args.repeats),
            ("read_samples (numpy fast path)", lambda: read_samples(path), args.repeats),
            ("rosbags AnyReader, deserialise u + y_p", lambda: anyreader(path), args.slow_repeats),
            ("iter_messages (general path), u + y_p", lambda: general(path), args.slow_repeats),
        ]
        print(f"{'reader':44s} {'seconds':>9s} {'samples/s':>12s}")
        for name, work, repeats in rows:
            seconds = median_seconds(work, repeats)
            print(f"{name:44s} {seconds:9.3f} {args.samples / seconds:12.3g}")


if __name__ == "__main__":
    main()
