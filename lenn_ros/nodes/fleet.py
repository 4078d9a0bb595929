"""Several identifiers in one process: one per plant, each in its own namespace.

    ros2 run lenn_ros fleet --ros-args -p plants:="[arm/joint1, arm/joint2, oven]" \\
        --params-file fleet.yaml

Identifier ``/arm/joint1/identifier`` reads ``/arm/joint1/u`` and ``/arm/joint1/y_p`` and
publishes ``/arm/joint1/y_hat``, ... as if it had been started alone with
``-r __ns:=/arm/joint1``: each keeps its own parameters (a params file's ``/**:`` section
applies to all, ``/arm/joint1/identifier:`` to one), model, counters and status.
What they share is one process, one DDS participant and one wait-set loop, instead of a
Python interpreter, a participant and a loop per plant: ``bench/fleet.py`` measures what
that buys on this machine. This node (``/fleet``) only holds the list of plants.
"""

from __future__ import annotations

import sys

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.validate_namespace import validate_namespace

from lenn_ros.nodes import executor_choice, run_node
from lenn_ros.nodes.identifier import EXECUTOR, IdentifierNode


def plant_namespaces(plants: list[str]) -> list[str]:
    """Absolute, checked, distinct namespaces; a bad list stops the start with one line."""
    if not plants:
        raise SystemExit('fleet: cannot start: no plants: pass -p plants:="[plant1, plant2]" (namespaces)')
    namespaces = ["/" + plant.strip("/") for plant in plants]
    for plant, namespace in zip(plants, namespaces, strict=True):
        try:
            validate_namespace(namespace)
        except Exception as error:  # rclpy's InvalidNamespaceException, with the rule broken
            raise SystemExit(f"fleet: cannot start: plant {plant!r} is not a namespace: {error}") from None
    repeated = sorted({n for n in namespaces if namespaces.count(n) > 1})
    if repeated:
        raise SystemExit(f"fleet: cannot start: plants named twice: {', '.join(repeated)}")
    return namespaces


class FleetNode(Node):
    """Holds ``plants``; the identifiers are nodes of their own beside it."""

    def __init__(self) -> None:
        super().__init__("fleet")
        self.declare_parameter(
            "plants",
            Parameter.Type.STRING_ARRAY,
            ParameterDescriptor(
                description="one identifier per entry, in that namespace (e.g. [arm/joint1, oven])", read_only=True
            ),
        )
        try:
            value = self.get_parameter("plants").value
        except ParameterUninitializedException:  # not given, or given as [] (no type to infer)
            value = []
        self.namespaces = plant_namespaces(list(value or []))


def make_fleet() -> list[Node]:
    fleet = FleetNode()
    identifiers = [IdentifierNode(namespace=ns, sibling_parameters=("plants",)) for ns in fleet.namespaces]
    fleet.get_logger().info(f"{len(identifiers)} identifiers: {', '.join(fleet.namespaces)}")
    return [fleet, *identifiers]


def main(args: list[str] | None = None) -> int:
    return run_node(make_fleet, "fleet", args, executor=executor_choice(EXECUTOR), exit_process=True)


if __name__ == "__main__":
    sys.exit(main())
