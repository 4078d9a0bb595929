"""The one place that knows topic names, message types and QoS of the package.

Names are relative, so a namespace or a ``--ros-args -r u:=/robot/cmd`` remap moves
them. This module imports no rclpy at module level: the offline tools (bag reading,
``lenn-ros evaluate``) use the names and ROS type strings without a ROS install.

Sample convention: at step k the plant simulator publishes u(k) on ``u`` and the
plant output y_p(k) (shown before u(k) acts) on ``y_p``, once each, from one node, so
the publication sequence numbers of the two topics agree: that number *is* the
sample index k + 1 and is how the identifier pairs them. ``test_start`` carries the
index of the first test-phase sample (learning frozen from there on).
"""

from __future__ import annotations

from dataclasses import dataclass

U = "u"
Y_P = "y_p"
Y_HAT = "y_hat"
ERROR = "error"
NMSE = "nmse"
TEST_START = "test_start"
STATUS = "status"

FLOAT64 = "std_msgs/msg/Float64"
INT64 = "std_msgs/msg/Int64"
STRING = "std_msgs/msg/String"

#: Depth of the RELIABLE data queues: 10 s at 1 kHz, so a subscriber that stalls
#: for a garbage-collection pause or a disk flush loses nothing.
DATA_DEPTH = 10_000


@dataclass(frozen=True)
class TopicSpec:
    name: str
    type_name: str
    latched: bool = False


#: Every topic the package publishes, in the order the recorder lists them.
RUN_TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec(U, FLOAT64),
    TopicSpec(Y_P, FLOAT64),
    TopicSpec(Y_HAT, FLOAT64),
    TopicSpec(ERROR, FLOAT64),
    TopicSpec(NMSE, FLOAT64),
    TopicSpec(TEST_START, INT64, latched=True),
    TopicSpec(STATUS, STRING),
)


def message_class(type_name: str):
    """The rclpy message class for a ROS type string (imports std_msgs lazily)."""
    from std_msgs.msg import Float64, Int64, String

    return {FLOAT64: Float64, INT64: Int64, STRING: String}[type_name]


def data_qos():
    """RELIABLE, KEEP_LAST(DATA_DEPTH), VOLATILE: for samples that must not be lost."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=DATA_DEPTH, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)


def latched_qos():
    """RELIABLE + TRANSIENT_LOCAL depth 1: a late joiner still gets the last value."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def qos_for(spec: TopicSpec):
    return latched_qos() if spec.latched else data_qos()
