"""How a side's values (u or y_p) go out as messages: one place for the plant simulator and replay.

A plant or recording of one input and one output publishes Float64 messages (what the
identifier reads by default); one of several channels publishes one Float64MultiArray per
side, its channels named in the layout label (README, "Several inputs and outputs").
Chosen once, when the node knows what it publishes; every message then goes through
:meth:`Channels.message`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from std_msgs.msg import Float64, Float64MultiArray

from lenn_ros import topics


class Channels:
    """The message type of a node's u and y_p, and their messages. ``names``: each side's channel names."""

    def __init__(self, names: dict[str, list[str]], vector: bool) -> None:
        self.names, self.vector = names, vector
        self.message_type = Float64MultiArray if vector else Float64
        self.layouts = {side: topics.vector_layout(list(channels)) for side, channels in names.items()}

    @classmethod
    def numbered(cls, n_u: int, n_y: int, vector: bool) -> Channels:
        """Channels named u1, u2.. / y1, y2.. (a simulated plant's own names)."""
        return cls({side: [f"{side}{i + 1}" for i in range(count)] for side, count in (("u", n_u), ("y", n_y))}, vector)

    def value(self, values: Any) -> Any:
        """One side's sample as the model of it takes it: the vector, or its one float."""
        return np.asarray(values, dtype=np.float64) if self.vector else float(np.ravel(values)[0])

    def message(self, values: Any, side: str) -> Float64 | Float64MultiArray:
        """The ``side`` (``u``/``y``) message of one sample's values."""
        if self.vector:
            return Float64MultiArray(layout=self.layouts[side], data=np.asarray(values, dtype=np.float64).tolist())
        return Float64(data=self.value(values))
