"""ROS 2 nodes: thin adapters between topics/parameters and :mod:`lenn_ros.core`."""

from __future__ import annotations

import sys
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


def run_node(factory: Callable[[], Node], name: str, args: list[str] | None = None) -> int:
    """The Jazzy ``main`` of ros2/demos, plus one-line startup errors.

    A node refuses a bad configuration by raising ``SystemExit("reason")`` in its
    constructor; rclpy's own refusals (an override outside a declared range, a
    params file it cannot parse) arrive as exceptions. Either way the user gets one
    line naming the problem and exit status 2, not a traceback.
    """
    try:
        rclpy.init(args=args)
    except Exception as error:
        print(f"{name}: cannot start: {str(error).strip().splitlines()[0]}", file=sys.stderr)
        return 2
    node = None
    code = 0
    try:
        node = factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except SystemExit as stop:
        if isinstance(stop.code, str):
            print(stop.code, file=sys.stderr)
            code = 2
    except Exception as error:
        if node is not None:
            raise
        print(f"{name}: cannot start: {str(error).strip().splitlines()[0]}", file=sys.stderr)
        code = 2
    finally:
        if node is not None:
            shutdown = getattr(node, "shutdown", None)
            if shutdown is not None:
                shutdown()
            node.destroy_node()
        rclpy.try_shutdown()
    return code
