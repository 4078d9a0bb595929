"""What the identifier publishes per sample: y_hat, error (plain and stamped), y_hat_std, samples, nmse.

One message object per output, refilled for every sample: building messages was a good
part of the per-sample cost (a JointState constructs its Header and Time, the generated
``__init__`` re-imports their modules each time); ``publish`` serialises at once, so
refilling is safe. With several output channels (MIMO) ``y_hat`` / ``error`` are
Float64MultiArray (names in the layout label) and the stamped JointStates name every
channel (README, "Several inputs and outputs").

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
        mimo: bool,
        values: dict[str, Any],
        phase_nmse_db: Callable[[], float],
    ) -> None:
        """``outputs``: the output channels' names (the y_p topic's for one); ``values``: the
        node's live parameter values (``report_every``); ``phase_nmse_db``: what ``nmse`` says."""
        self.mimo = mimo
        self.values = values
        self.phase_nmse_db = phase_nmse_db
        qos = topics.data_qos()
        value_type = Float64MultiArray if mimo else Float64
        self.y_hat = node.create_publisher(value_type, topics.Y_HAT, qos)
        self.error = node.create_publisher(value_type, topics.ERROR, qos)
        self.y_hat_stamped = node.create_publisher(JointState, topics.Y_HAT_STAMPED, qos)
        self.error_stamped = node.create_publisher(JointState, topics.ERROR_STAMPED, qos)
        self.samples = node.create_publisher(Float64MultiArray, topics.SAMPLES, qos)
        # the one-step std (core.spread): one output only, a MIMO model's channels have none
        self.y_hat_std = None if mimo else node.create_publisher(Float64, topics.Y_HAT_STD, qos)
        self.y_hat_std_stamped = None if mimo else node.create_publisher(JointState, topics.Y_HAT_STD_STAMPED, qos)
        self._std_message = Float64()
        self.nmse = node.create_publisher(Float64, topics.NMSE, qos)
        self._sample_message = Float64MultiArray(layout=topics.vector_layout(sample_labels))
        if mimo:
            self._y_hat_message = Float64MultiArray(layout=topics.vector_layout(outputs))
            self._error_message = Float64MultiArray(layout=topics.vector_layout(outputs))
        else:
            self._y_hat_message, self._error_message = Float64(), Float64()
        self._joint_messages = {
            publisher: JointState(name=list(outputs), position=[0.0] * len(outputs))
            for publisher in (self.y_hat_stamped, self.error_stamped, self.y_hat_std_stamped)
            if publisher is not None
        }
        self.errors_since_report = 0

    def readers(self) -> dict[str, int]:
        """Matched readers of each output that can hold the first pairs back."""
        return {output: getattr(self, output).get_subscription_count() for output in OUTPUTS}

    def publish(self, samples: list[Sample]) -> None:
        """Every output of each sample, y_hat first: one output as Float64, several as one vector message
        (and the one-step std, which only a single output has)."""
        for sample in samples:
            result = sample.result
            if result is not None and result.y_hat_next is not None:
                self._y_hat_message.data = self._data(result.y_hat_next)
                self.y_hat.publish(self._y_hat_message)
                if self.y_hat_std and result.y_hat_next_std is not None and self.y_hat_std.get_subscription_count():
                    self._std_message.data = result.y_hat_next_std
                    self.y_hat_std.publish(self._std_message)
            if self.samples.get_subscription_count():
                learn = float(result.learned) if result is not None else 0.0
                values = (float(sample.index), sample.time, *np.ravel(sample.u), *np.ravel(sample.y), learn)
                self._sample_message.data = array("d", values)
                self.samples.publish(self._sample_message)
            if result is not None and result.error is not None and result.y_hat is not None:
                self._publish_error(sample.time, result.y_hat, result.error)
                std = None if self.mimo else result.y_hat_std
                if std is not None and self.y_hat_std_stamped.get_subscription_count():
                    message = self._joint_messages[self.y_hat_std_stamped]
                    set_stamp(message.header.stamp, sample.time)
                    message.position[0] = std
                    self.y_hat_std_stamped.publish(message)

    def _data(self, value: Any) -> Any:
        """A value as its plain message carries it: a float (Float64), or the outputs' vector (Float64MultiArray)."""
        return array("d", np.ravel(value).tolist()) if self.mimo else value

    def _publish_error(self, seconds: float, y_hat: Any, error: Any) -> None:
        """e(k) and y^(k) of a learnt sample (plain and stamped), and the NMSE every ``report_every`` errors."""
        if self.error.get_subscription_count():
            self._error_message.data = self._data(error)
            self.error.publish(self._error_message)
        for publisher, value in ((self.y_hat_stamped, y_hat), (self.error_stamped, error)):
            if publisher.get_subscription_count():
                message = self._joint_messages[publisher]
                set_stamp(message.header.stamp, seconds)
                if self.mimo:
                    message.position = array("d", value.tolist())
                else:
                    message.position[0] = value  # in place: the array the message serialises
                publisher.publish(message)
        self.errors_since_report += 1
        if self.errors_since_report >= self.values["report_every"]:
            self.errors_since_report = 0
            self.nmse.publish(Float64(data=self.phase_nmse_db()))
