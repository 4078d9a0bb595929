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
#: The pairs the identifier formed, one message per sample: Float64MultiArray
#: ``[index, time_s, u, y_p, learn]`` (labels in ``SAMPLE_LABELS``; u, y_p NaN for a
#: refused sample; learn 1.0 if learnt from). A bag that holds it is evaluated from
#: exactly these samples, so offline equals live.
SAMPLES = "samples"
#: y^(k) and e(k) stamped with the time of sample k (JointState, one named channel),
#: so Foxglove / PlotJuggler overlay them on y_p without a one-sample shift.
Y_HAT_STAMPED = "y_hat_stamped"
ERROR_STAMPED = "error_stamped"
#: The one-step std of y^(k+1) (Float64, published right after y_hat; core.spread): the nominal 95 % band
#: is y_hat +- 1.96 y_hat_std; one message per y_hat, NaN until the first error has been seen.
#: ``y_hat_std_stamped``: the std of y^(k), stamped as y_hat_stamped is.
Y_HAT_STD = "y_hat_std"
Y_HAT_STD_STAMPED = "y_hat_std_stamped"
#: The half-width of the live 95 % band around y^(k+1) (core.spread.LiveBand: y_hat_std times a multiplier
#: that keeps the band's running coverage at 95 % as the noise or the plant drifts; Float64, published right
#: after y_hat_std): the band is y_hat +- y_hat_band. ``y_hat_band_stamped``: the half-width around y^(k),
#: stamped as y_hat_stamped is.
Y_HAT_BAND = "y_hat_band"
Y_HAT_BAND_STAMPED = "y_hat_band_stamped"
#: The identifier's resolved configuration (JSON, latched): ``evaluate`` reads it from a bag.
IDENTIFIER_CONFIG = "identifier_config"
#: key of the identifier_config JSON naming the topic each input resolved to (after remapping): u -> /arm/cmd
RESOLVED_TOPICS = "resolved_topics"
#: key of the identifier_config JSON listing the live parameter changes: [{"from_sample": k, "values": {...}}]
PARAMETER_CHANGES = "changes"
#: Standard ROS diagnostics (absolute name: rqt_robot_monitor and friends listen there).
DIAGNOSTICS = "/diagnostics"

FLOAT64 = "std_msgs/msg/Float64"
FLOAT64_ARRAY = "std_msgs/msg/Float64MultiArray"
INT64 = "std_msgs/msg/Int64"
STRING = "std_msgs/msg/String"
JOINT_STATE = "sensor_msgs/msg/JointState"
SAMPLE_LABELS = ("index", "time", "u", "y_p", "learn")


def sample_labels(u_names: list[str] | tuple[str, ...], y_names: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """``samples`` labels of a MIMO identifier: ``[index, time, u.<name>.., y_p.<name>.., learn]``.

    With several channels ``y_hat`` and ``error`` are Float64MultiArray (one element per
    output, the names comma-joined in ``layout.dim[0].label``) and ``y_hat_stamped`` /
    ``error_stamped`` JointState with one named position per output: README "MIMO".
    """
    return ("index", "time", *(f"{U}.{name}" for name in u_names), *(f"{Y_P}.{name}" for name in y_names), "learn")


def channel_layout_label(names: list[str] | tuple[str, ...]) -> str:
    """``layout.dim[0].label`` of a vector u, y_p, y_hat or error message: the channel names."""
    return ",".join(names)


def vector_layout(labels: list[str] | tuple[str, ...]):
    """The rclpy ``MultiArrayLayout`` of a vector message whose elements ``labels`` name (built once, reused)."""
    from std_msgs.msg import MultiArrayDimension, MultiArrayLayout

    size = len(labels)
    return MultiArrayLayout(dim=[MultiArrayDimension(label=channel_layout_label(labels), size=size, stride=size)])


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
    TopicSpec(SAMPLES, FLOAT64_ARRAY),
    TopicSpec(Y_HAT_STAMPED, JOINT_STATE),
    TopicSpec(ERROR_STAMPED, JOINT_STATE),
    TopicSpec(Y_HAT_STD, FLOAT64),
    TopicSpec(Y_HAT_BAND, FLOAT64),
    TopicSpec(IDENTIFIER_CONFIG, STRING, latched=True),
)


def run_topics(mimo: bool = False) -> tuple[TopicSpec, ...]:
    """:data:`RUN_TOPICS` of a run with one channel, or with several: then y_hat and error are vectors."""
    if not mimo:
        return RUN_TOPICS
    vectors = (Y_HAT, ERROR, Y_HAT_STD, Y_HAT_BAND)
    return tuple(TopicSpec(spec.name, FLOAT64_ARRAY) if spec.name in vectors else spec for spec in RUN_TOPICS)


def message_class(type_name: str):
    """The rclpy message class for a ROS type string such as ``sensor_msgs/msg/JointState``.

    Imported lazily (no rclpy needed to import this module); raises ``ValueError`` with
    a one-line reason for a malformed name or a package that is not installed.
    """
    import importlib

    parts = type_name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise ValueError(f"{type_name!r} is not a message type name like 'std_msgs/msg/Float64'")
    try:
        module = importlib.import_module(f"{parts[0]}.msg")
    except ImportError:
        raise ValueError(f"message package {parts[0]!r} is not installed (type {type_name!r})") from None
    cls = getattr(module, parts[2], None)
    if cls is None:
        raise ValueError(f"{parts[0]} has no message {parts[2]!r} (type {type_name!r})")
    return cls


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
