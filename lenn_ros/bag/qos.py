"""QoS profiles as rosbag2 stores them (``offered_qos_profiles``), without importing rclpy."""

from __future__ import annotations

from typing import Any

import yaml
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos

from lenn_ros import topics

__all__ = ["as_qos_list", "default_qos", "dump_qos", "parse_qos", "qos_from_profile", "qos_yaml"]


def _qos_time(duration: Any) -> QosTime:
    sec, nsec = divmod(int(getattr(duration, "nanoseconds", duration)), 1_000_000_000)
    return QosTime(sec, nsec)


def qos_from_profile(profile: Any) -> Qos:
    """Convert an rclpy ``QoSProfile`` (duck-typed, so rclpy is not imported) to rosbags' ``Qos``.

    Policies are matched by name because that is what both enums promise; an unknown name
    becomes UNKNOWN rather than an error, as rosbag2 does.
    """

    def pick(enum: Any, policy: Any) -> Any:
        name = getattr(policy, "name", str(policy)).upper()
        return enum.__members__.get(name, enum.UNKNOWN)

    return Qos(
        history=pick(QosHistory, profile.history),
        depth=int(profile.depth),
        reliability=pick(QosReliability, profile.reliability),
        durability=pick(QosDurability, profile.durability),
        deadline=_qos_time(profile.deadline),
        lifespan=_qos_time(profile.lifespan),
        liveliness=pick(QosLiveliness, profile.liveliness),
        liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def default_qos(spec: topics.TopicSpec) -> Qos:
    """The QoS our publishers offer on ``spec``, without importing rclpy.

    Mirrors ``topics.data_qos()`` / ``topics.latched_qos()`` (a test checks they agree)
    so that ``import-csv`` on a machine without ROS stores the same offered QoS as a
    live recording; ``ros2 bag play`` then re-offers a latched ``test_start``.
    """
    zero = QosTime(0, 0)
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=1 if spec.latched else topics.DATA_DEPTH,
        reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL if spec.latched else QosDurability.VOLATILE,
        deadline=zero,
        lifespan=zero,
        liveliness=QosLiveliness.SYSTEM_DEFAULT,
        liveliness_lease_duration=zero,
        avoid_ros_namespace_conventions=False,
    )


def as_qos_list(qos: Any, spec: topics.TopicSpec | None) -> list[Qos]:
    """One rosbags ``Qos`` per publisher from None (the package default), a profile or a list."""
    if qos is None:
        return [default_qos(spec)] if spec is not None else []
    items = list(qos) if isinstance(qos, list | tuple) else [qos]
    return [q if isinstance(q, Qos) else qos_from_profile(q) for q in items]


def dump_qos(qos: list[Qos]) -> list[dict[str, Any]]:
    """rosbag2 v9's list-of-dicts form (metadata.yaml, ``bag-info``)."""
    return dump_qos_v9(qos)


def qos_yaml(qos: list[Qos]) -> str:
    """The YAML string rosbag2 puts in an MCAP channel's ``offered_qos_profiles`` metadata."""
    return yaml.safe_dump(dump_qos_v9(qos), default_flow_style=False).strip() if qos else ""
