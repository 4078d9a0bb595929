"""ROS 2 nodes: thin adapters between topics/parameters and :mod:`lenn_ros.core`."""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions


def wait_for_acknowledgements(node: Node, timeout_s: float = 5.0) -> bool:
    """Block until every RELIABLE subscriber (e.g. a lagging recorder) has our messages.

    A DDS writer that goes away takes its unacknowledged samples with it, so a node
    that exits right after publishing would leave a recorder behind it short of its
    last messages. Called on the way out, before the node is destroyed.
    """
    from rclpy.duration import Duration

    return all(publisher.wait_for_all_acked(Duration(seconds=timeout_s)) for publisher in node.publishers)


def run_node(factory: Callable[[], Node], name: str, args: list[str] | None = None) -> int:
    """The Jazzy ``main`` of ros2/demos, with a graceful stop and one-line startup errors.

    SIGINT and SIGTERM only request the stop: rclpy's own handlers would shut the
    context down at once, and a node could then neither save its final state through
    ``shutdown()`` nor wait until its last messages are acknowledged by a recorder.
    A node refuses a bad configuration by raising ``SystemExit("reason")`` in its
    constructor; rclpy's own refusals (an override outside a declared range, a
    params file it cannot parse) arrive as exceptions. Either way the user gets one
    line naming the problem and exit status 2, not a traceback.
    """
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as error:
        print(_cannot_start(name, error), file=sys.stderr)
        return 2
    stop = _stop_requested_by_signals()
    node = None
    code = 0
    executor = SingleThreadedExecutor()
    try:
        node = factory()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    except SystemExit as exit_request:
        if isinstance(exit_request.code, str):
            print(exit_request.code, file=sys.stderr)
            code = 2
    except Exception as error:
        if node is not None:
            raise
        print(_cannot_start(name, error), file=sys.stderr)
        code = 2
    finally:
        if node is not None:
            _close_node(node, executor)
        executor.shutdown()
        rclpy.try_shutdown()
    return code


def _cannot_start(name: str, error: Exception) -> str:
    """The one line shown for a refused start: the first line of rclpy's message is the reason, the rest noise."""
    return f"{name}: cannot start: {str(error).strip().splitlines()[0]}"


def _stop_requested_by_signals() -> threading.Event:
    """An event SIGINT and SIGTERM set, instead of rclpy's handlers that would shut the context down at once."""
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    return stop


def _close_node(node: Node, executor: SingleThreadedExecutor) -> None:
    """Take in what is still queued, save the final state, wait for the recorder, and only then destroy the node.

    The order matters: a node destroyed before its publishers are acknowledged takes
    its last messages with it, and ``shutdown()`` may still publish.
    """
    drain = getattr(node, "drain", None)  # e.g. the recorder takes what DDS still holds
    if drain is not None and rclpy.ok():
        drain(executor)
    shutdown = getattr(node, "shutdown", None)
    if shutdown is not None:
        shutdown()
    if rclpy.ok():
        wait_for_acknowledgements(node)
    executor.remove_node(node)
    node.destroy_node()
