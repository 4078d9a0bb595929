"""Vector runs (MIMO): ``u`` and ``y_p`` as ``std_msgs/msg/Float64MultiArray``, one message per sample.

The channel names travel in every message, as ``layout.dim[0].label`` (comma-joined,
``size`` = ``stride`` = the channel count): a bag then says which column is which in
``ros2 bag``, Foxglove or PlotJuggler too, without a side file that can get lost. A
SISO run stays ``std_msgs/msg/Float64`` (:mod:`lenn_ros.bag.csv_import`), so every
existing bag and consumer is untouched.

Written here; read like every other recording, by the node's own session
(:func:`lenn_ros.service.recording.read_recording`: a plain ``u`` / ``y_p`` of
Float64MultiArray is read whole, its channels named by these labels).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lenn_ros import topics
from lenn_ros.bag.msgtypes import TYPESTORE
from lenn_ros.bag.reader import find_topic, topic_types
from lenn_ros.bag.scalars import topic_series
from lenn_ros.bag.writer import BagWriter

__all__ = ["read_test_start", "vector_message", "write_vector_run"]


def vector_message(values: Sequence[float], names: Sequence[str]):
    """One sample as a Float64MultiArray whose single dimension's label names the channels."""
    types = TYPESTORE.types
    dim = types["std_msgs/msg/MultiArrayDimension"](label=",".join(names), size=len(names), stride=len(names))
    layout = types["std_msgs/msg/MultiArrayLayout"](dim=[dim], data_offset=0)
    return types[topics.FLOAT64_ARRAY](layout=layout, data=np.ascontiguousarray(values, dtype=np.float64))


def write_vector_run(
    out_path: str | Path,
    u_rows: np.ndarray,
    y_rows: np.ndarray,
    names: tuple[Sequence[str], Sequence[str]],
    dt: float,
    test_from: int | None = None,
) -> Path:
    """/u and /y_p (rows: samples, columns: channels) stamped at k*dt, the latched /test_start first."""
    u_names, y_names = names
    out_path = Path(out_path)
    with BagWriter(out_path, flush_period=None) as bag:
        bag.add_topic("/" + topics.U, topics.FLOAT64_ARRAY)
        bag.add_topic("/" + topics.Y_P, topics.FLOAT64_ARRAY)
        if test_from is not None:
            bag.add_topic("/" + topics.TEST_START)
            bag.write_value("/" + topics.TEST_START, int(test_from), 0)
        for k, (u, y) in enumerate(zip(u_rows, y_rows, strict=True)):
            stamp = round(k * dt * 1e9)
            bag.write_message("/" + topics.U, vector_message(u, u_names), stamp)
            bag.write_message("/" + topics.Y_P, vector_message(y, y_names), stamp)
    return out_path


def read_test_start(path: str | Path) -> int | None:
    """The last ``test_start`` in a bag, whatever its u / y_p are (None: none recorded)."""
    path = Path(path)
    return _test_start(path, topic_types(path))


def _test_start(path: Path, available: dict[str, str]) -> int | None:
    start = find_topic(available, topics.TEST_START)
    starts = topic_series(path, start).values if start else None
    return int(starts[-1]) if starts is not None and len(starts) else None
