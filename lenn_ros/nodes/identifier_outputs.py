"""What the identifier publishes per sample: y_hat, error, y_hat_std, y_hat_band (plain and stamped), samples, nmse.

One message object per output, refilled for every sample: building messages was a good
part of the per-sample cost (a JointState constructs its Header and Time, the generated
``__init__`` re-imports their modules each time); ``publish`` serialises at once, so
refilling is safe. With several output channels ``y_hat`` / ``error`` / ``y_hat_std`` / ``y_hat_band`` are
Float64MultiArray (names in the layout label) and the stamped JointStates name every
channel (README, "Several inputs and outputs"); the one-step std and the live band's half-width are
every output's, as the session's monitors give them.

``samples``, ``error`` and the stamped outputs are VOLATILE: a publisher with no matched
reader delivers them to nobody, so their messages are not built then
(``get_subscription_count`` is a cheap call; a recorder or a plot is a reader). ``y_hat``
is always published, first: its publication sequence number counts samples, and a
lockstep plant is waiting for it.
"""

from __future__ import annotations

from array import array
from collections.abc import Callable
from typing import Any

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray

from lenn_ros import topics
from lenn_ros.session import Sample

#: The outputs a ``wait_for_<output>_subscribers`` parameter can hold the first pairs back for.
OUTPUTS = ("y_hat", "error", "samples")


def set_stamp(stamp: Any, seconds: float) -> None:
    """``stamp`` (builtin_interfaces/Time) := ``seconds``, as ``Time(nanoseconds=...).to_msg()`` gives it.

    Set in place on a reused message: building an rclpy Time and a Time message for
    every sample costs more than the arithmetic.
    """
    nanoseconds = round(seconds * 1e9)
    if nanoseconds < 0:
        raise ValueError("Nanoseconds value must not be negative")  # as rclpy's Time says it
    stamp.sec, stamp.nanosec = divmod(nanoseconds, 1_000_000_000)


class IdentifierOutputs:
    """The identifier node's output publishers and their reused messages."""

    def __init__(
        self,
        node: Node,
        outputs: list[str],
        sample_labels: tuple[str, ...],
        vector: bool,
        values: dict[str, Any],
        phase_nmse_db: Callable[[], float],
    ) -> None:
        """``outputs``: the output channels' names (the y_p topic's for one); ``vector``: the values are vectors
        (:mod:`lenn_ros.session.values`: one Float64MultiArray element per output, not a Float64); ``values``: the
        node's live parameter values (``report_every``); ``phase_nmse_db``: what ``nmse`` says."""
        self.values = values
        self.phase_nmse_db = phase_nmse_db
        qos = topics.data_qos()
        value_type = Float64MultiArray if vector else Float64
        self.y_hat = node.create_publisher(value_type, topics.Y_HAT, qos)
        self.error = node.create_publisher(value_type, topics.ERROR, qos)
        self.y_hat_stamped = node.create_publisher(JointState, topics.Y_HAT_STAMPED, qos)
        self.error_stamped = node.create_publisher(JointState, topics.ERROR_STAMPED, qos)
        self.samples = node.create_publisher(Float64MultiArray, topics.SAMPLES, qos)
        self.y_hat_std = node.create_publisher(value_type, topics.Y_HAT_STD, qos)  # the one-step std (the band)
        self.y_hat_std_stamped = node.create_publisher(JointState, topics.Y_HAT_STD_STAMPED, qos)
        self.y_hat_band = node.create_publisher(value_type, topics.Y_HAT_BAND, qos)  # the live band's half-width
        self.y_hat_band_stamped = node.create_publisher(JointState, topics.Y_HAT_BAND_STAMPED, qos)
        self.nmse = node.create_publisher(Float64, topics.NMSE, qos)
        self._sample_message = Float64MultiArray(layout=topics.vector_layout(sample_labels))
        self._messages = {
            publisher: Float64MultiArray(layout=topics.vector_layout(outputs)) if vector else Float64()
            for publisher in (self.y_hat, self.error, self.y_hat_std, self.y_hat_band)
        }
        self._data = _as_vector if vector else float
        self._joint_messages = {
            publisher: JointState(name=list(outputs), position=[0.0] * len(outputs))
            for publisher in (self.y_hat_stamped, self.error_stamped, self.y_hat_std_stamped, self.y_hat_band_stamped)
        }
        self.errors_since_report = 0

    def readers(self) -> dict[str, int]:
        """Matched readers of each output that can hold the first pairs back."""
        return {output: getattr(self, output).get_subscription_count() for output in OUTPUTS}

    def publish(self, samples: list[Sample]) -> None:
        """Every output of each sample, y_hat first (its publication sequence number counts samples)."""
        for sample in samples:
            result = sample.result
            if result is not None and result.y_hat_next is not None:
                self._send(self.y_hat, result.y_hat_next)
                if result.y_hat_next_std is not None and self.y_hat_std.get_subscription_count():
                    self._send(self.y_hat_std, result.y_hat_next_std)
                if result.y_hat_next_band is not None and self.y_hat_band.get_subscription_count():
                    self._send(self.y_hat_band, result.y_hat_next_band)
            if self.samples.get_subscription_count():
                learn = float(result.learned) if result is not None else 0.0
                values = (float(sample.index), sample.time, *np.ravel(sample.u), *np.ravel(sample.y), learn)
                self._sample_message.data = array("d", values)
                self.samples.publish(self._sample_message)
            if result is not None and result.error is not None and result.y_hat is not None:
                self._publish_error(sample.time, result)

    def _send(self, publisher: Any, value: Any) -> None:
        """A value as its plain message carries it: a Float64, or the outputs' vector (Float64MultiArray)."""
        message = self._messages[publisher]
        message.data = self._data(value)
        publisher.publish(message)

    def _publish_error(self, seconds: float, result: Any) -> None:
        """e(k), y^(k), its std and half-width of a scored sample (plain and stamped), and the NMSE every
        ``report_every``."""
        if self.error.get_subscription_count():
            self._send(self.error, result.error)
        stamped = ((self.y_hat_stamped, result.y_hat), (self.error_stamped, result.error))
        spread = ((self.y_hat_std_stamped, result.y_hat_std), (self.y_hat_band_stamped, result.y_hat_band))
        for publisher, value in (*stamped, *spread):
            if value is not None and publisher.get_subscription_count():
                message = self._joint_messages[publisher]
                set_stamp(message.header.stamp, seconds)
                message.position = array("d", np.ravel(value).tolist())
                publisher.publish(message)
        self.errors_since_report += 1
        if self.errors_since_report >= self.values["report_every"]:
            self.errors_since_report = 0
            self.nmse.publish(Float64(data=self.phase_nmse_db()))


def _as_vector(value: Any) -> array:
    return array("d", np.ravel(value).tolist())
