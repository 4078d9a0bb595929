"""ROS 2 nodes: thin adapters between topics/parameters and :mod:`lenn_ros.core`."""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from lenn_ros.nodes import console, rclpy_internals

#: The loops :func:`run_node` can spin a node with (see its docstring).
EXECUTORS = ("single", "events", "waitset")
#: Environment variable that overrides a node's choice of loop (benchmarks, trouble-shooting).
EXECUTOR_VARIABLE = "LENN_ROS_EXECUTOR"
#: Longest wait in one loop turn: how soon a stop request (SIGINT, SIGTERM) is seen.
_TURN_SECONDS = 0.1
#: Longest a loop takes messages before timers, services and a stop request get their turn
#: (a flood never empties the queues: issue 18 measured parameter calls of 2.5 s without it).
#: A few handlers may run before a service's (bench/overload.py: 5 ms keeps a call within
#: 100 ms under a flood on 2 cores; the cost per turn of waiting again is ~0.1 ms).
DRAIN_SECONDS = 0.005


#: What a lockstep publisher says when it gives up waiting for :func:`latched_readers_matched`.
TEST_START_UNMATCHED = "a test_start reader unmatched at sample 1: it may learn from test samples"


def latched_readers_matched(node: Node, publisher: Any, data_topic: str, wanted: int) -> bool:
    """Every reader the graph shows on ``publisher``'s latched topic is matched, and has its message.

    A lockstep publisher (simulator, replay) checks this before sample 1: an identifier whose
    ``test_start`` comes after that sample has learnt from test samples, and a latched
    message reaches a reader only once the two have matched, each reader on its own time.
    ``wanted`` readers of ``data_topic`` in the graph first: then their nodes' other readers
    (created before the data readers) are in the graph too.
    """
    if node.count_subscribers(data_topic) < wanted:
        return False
    if publisher.get_subscription_count() < node.count_subscribers(publisher.topic_name):
        return False
    return bool(publisher.wait_for_all_acked(Duration(seconds=0)))


def watched_publishers(node: Node, subscriptions: Any, watchdog: Any) -> dict[str, list[str]]:
    """The input watchdog's view of the graph (core.watchdog): per subscribed topic whose rate it knows and that
    has matched publishers, those publishers' names, for its lines ("?" where the graph names none)."""
    publishers = {}
    for subscription in subscriptions:
        topic = subscription.topic_name
        if subscription.get_publisher_count() and watchdog.watched(topic):
            infos = node.get_publishers_info_by_topic(topic)
            publishers[topic] = sorted({f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in infos}) or ["?"]
    return publishers


def executor_choice(default: str) -> str:
    """The loop a node asked for, unless ``LENN_ROS_EXECUTOR`` names another one.

    Read by the nodes that offer the choice (the identifier), so that a benchmark or
    a user who suspects the loop can switch without a rebuild, and every other node
    keeps the loop its shutdown guarantees were written for.
    """
    return os.environ.get(EXECUTOR_VARIABLE, "").strip().lower() or default


def wait_for_acknowledgements(node: Node, timeout_s: float = 5.0) -> bool:
    """Block until every RELIABLE subscriber (e.g. a lagging recorder) has our messages.

    A DDS writer that goes away takes its unacknowledged samples with it, so a node
    that exits right after publishing would leave a recorder behind it short of its
    last messages. Called on the way out, before the node is destroyed.
    """
    from rclpy.duration import Duration

    deadline = time.monotonic() + timeout_s  # one wait for all of them: they are acknowledged side by side
    acked = True
    for publisher in node.publishers:
        left = max(deadline - time.monotonic(), 0.0)
        acked = publisher.wait_for_all_acked(Duration(seconds=left)) and acked
    return acked


def run_node(
    factory: Callable[[], Node | list[Node]],
    name: str,
    args: list[str] | None = None,
    executor: str = "single",
    exit_process: bool = False,
) -> int:
    """The Jazzy ``main`` of ros2/demos, with a graceful stop and one-line startup errors.

    SIGINT and SIGTERM only request the stop: rclpy's own handlers would shut the
    context down at once, and a node could then neither save its final state through
    ``shutdown()`` nor wait until its last messages are acknowledged by a recorder.
    A node refuses a bad configuration by raising ``SystemExit("reason")`` in its
    constructor; rclpy's own refusals (an override outside a declared range, a
    params file it cannot parse) arrive as exceptions. Either way the user gets one
    line naming the problem and exit status 2, not a traceback.

    ``executor`` picks the loop that hands messages to the node:

    - ``"single"``: rclpy's ``SingleThreadedExecutor``, which rebuilds its wait set in
      Python for every callback it runs (most of the CPU per message at kilohertz);
    - ``"events"``: ``rclpy.experimental.EventsExecutor`` (C++, the middleware's
      "new message" callbacks, no wait set), several times cheaper per message;
    - ``"waitset"``: this module's loop: one wait set of the node's subscriptions,
      timers and services, built once; messages taken and dispatched directly, and
      the single-threaded executor run only when a timer or service is ready (and
      every ``_TURN_SECONDS``, for QoS events and entities added since). It needs rclpy
      internals (:mod:`lenn_ros.nodes.rclpy_internals`); where they cannot be used the
      single-threaded executor runs instead, said in one line.

    All three run timers, parameter services and the ``drain`` / ``shutdown`` hooks
    the same way; the choice changes the cost per message, not the behaviour.
    ``factory`` may return several nodes (a fleet of identifiers): one loop serves them all.

    ``exit_process``: once everything the node owes is done (final state saved, last
    messages acknowledged, nodes destroyed, rclpy shut down), end the process at once
    instead of returning: under a flood the interpreter's own teardown waits over a
    second for the middleware's receiving threads, and the exit must come within 2 s of
    SIGINT (issue 18: 1.0-1.3 s with it, 2.2-3.4 s without, on 2 loaded cores).
    """
    console.guard_console()  # before anything logs: a stderr nobody reads must not stall the node
    executor = _loop_to_run(name, executor)
    if not executor:
        return 2
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as error:
        print(_cannot_start(name, error), file=sys.stderr)
        return 2
    loop = _new_executor(executor)
    stop = _stop_requested_by_signals()  # after the executor: nothing it sets up may take the signals over
    nodes: list[Node] = []
    code = 0
    try:
        made = factory()
        nodes = list(made) if isinstance(made, list | tuple) else [made]
        for node in nodes:
            loop.add_node(node)
        _freeze_start_up_objects()
        _spin(nodes, loop, executor, stop)
    except ExternalShutdownException:
        pass
    except SystemExit as exit_request:
        if isinstance(exit_request.code, str):
            print(exit_request.code, file=sys.stderr)
            code = 2
    except Exception as error:
        if nodes:
            raise
        print(_cannot_start(name, error), file=sys.stderr)
        code = 2
    finally:
        if nodes:
            _close_nodes(nodes, loop)
        loop.shutdown()
        rclpy.try_shutdown()
    return _end(code, exit_process)


def _loop_to_run(name: str, executor: str) -> str:
    """The loop ``run_node`` runs for the one asked (see there), or "" when none can (said in one line)."""
    if executor not in EXECUTORS:
        print(f"{name}: cannot start: unknown executor {executor!r} (one of: {', '.join(EXECUTORS)})", file=sys.stderr)
        return ""
    if executor == "waitset" and not rclpy_internals.available():
        print(
            f"{name}: the wait-set loop needs rclpy internals ({rclpy_internals.unavailable()}): "
            "running rclpy's single-threaded executor instead (same behaviour, more CPU per message)",
            file=sys.stderr,
        )
        return "single"
    return executor


def _freeze_start_up_objects() -> None:
    """Keep the garbage collector's full passes off everything start-up built (``gc.freeze``).

    rclpy, numpy, numba and the node leave ~130 000 long-lived objects, and each of the
    collector's full (generation 2) passes walks all of them: 170-200 ms on this
    2-core machine at rest, 0.7 s and more under load, during which no service request,
    timer or SIGINT is answered (a 0.76 s parameter call during a flood, in CI). Frozen
    objects are never scanned again; what the node allocates afterwards is collected as
    before. Nothing frozen is freed by a cycle later, which costs nothing here: start-up
    objects live as long as the process.
    """
    gc.collect()
    gc.freeze()


def _end(code: int, exit_process: bool) -> int:
    """``code`` returned, or (``exit_process``) the process ended with it, its output flushed (see run_node)."""
    if exit_process:
        sys.stdout.flush()
        sys.stderr.flush()
        console.flush()
        os._exit(code)
    return code


def _new_executor(kind: str) -> Any:
    """The executor behind the chosen loop (the wait-set loop keeps a single-threaded one for the rest)."""
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    return SingleThreadedExecutor()


def _spin(nodes: list[Node], executor: Any, kind: str, stop: threading.Event) -> None:
    """Hand messages and timer ticks to ``node`` until a stop is requested or the context ends.

    Always ``spin_once`` with a timeout: the events executor of rclpy 7.1.6 busy-loops
    and delivers nothing when ``spin_once()`` is called without one (so ``rclpy.spin``
    cannot drive it); with a timeout it runs one event per call.
    """
    if kind == "waitset":
        rclpy_internals.WaitSetLoop(nodes, executor, _TURN_SECONDS, DRAIN_SECONDS).spin(stop)
        return
    if kind == "events":
        for node in nodes:
            rclpy_internals.pass_message_info(node)  # subscriptions created later (none here) are not wrapped
    ok, spin_once = nodes[0].context.ok, executor.spin_once
    while not stop.is_set() and ok():
        spin_once(timeout_sec=_TURN_SECONDS)


class InputsNode(Node):
    """A node of its own DDS participant (rclpy ``Context``) that only holds a flooded node's input subscriptions.

    Why: a participant receives all its traffic through the same middleware ports and
    threads. Under a flood of input messages (a driver publishing as fast as it can) those
    overflow, and what is dropped with the flood includes the requests of the node's
    parameter services: a reliable request dropped is only resent after the client's
    next heartbeat, so ``ros2 param set`` took 1.9-2.8 s, while the node's own loop was
    idle enough to run its executor 100 times a second (bench/overload.py, issue 18). With
    the inputs on a participant of their own, the services' traffic never queues behind
    them (the same bench: at most 87 ms).

    Everything else stays on the owner: parameters (the QoS overrides of the inputs
    included), services, outputs, the graph queries; the subscriptions are created here
    with the topic names and QoS the owner resolved. Its context has no
    command-line arguments (the owner's remaps and node name are applied already) and no
    signal handlers (``run_node`` owns them), and ends with the node (:meth:`destroy_node`).
    """

    def __init__(self, owner: Node) -> None:
        context = Context()
        domain = owner.context.get_domain_id()
        rclpy.init(args=[], context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        super().__init__(f"{owner.get_name()}_inputs", namespace=owner.get_namespace(), context=context)
        self.owner = owner

    def destroy_node(self) -> None:
        context = self.context
        super().destroy_node()
        context.try_shutdown()


def _cannot_start(name: str, error: Exception) -> str:
    """The one line shown for a refused start: the first line of rclpy's message is the reason, the rest noise."""
    return f"{name}: cannot start: {str(error).strip().splitlines()[0]}"


def _stop_requested_by_signals() -> threading.Event:
    """An event SIGINT and SIGTERM set, instead of rclpy's handlers that would shut the context down at once."""
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    return stop


def _close_nodes(nodes: list[Node], executor: Any) -> None:
    """Take in what is still queued, save the final state, wait for the recorder, and only then destroy the nodes.

    The order matters: a node destroyed before its publishers are acknowledged takes
    its last messages with it, and ``shutdown()`` may still publish. The executor is
    shut down before the nodes are destroyed: the events executor drops its callbacks
    on a node's subscriptions and timers only then.
    """
    for node in nodes:
        drain = getattr(node, "drain", None)  # e.g. the recorder takes what DDS still holds
        if drain is not None and rclpy.ok():
            drain(executor)
        shutdown = getattr(node, "shutdown", None)
        if shutdown is not None:
            shutdown()
    for node in nodes:
        timeout = float(getattr(node, "ack_timeout", 5.0))
        if rclpy.ok() and not wait_for_acknowledgements(node, timeout):
            node.get_logger().warning(
                f"not every subscriber had acknowledged our last messages after {timeout:.0f} s: "
                "a lagging reader (a recorder) may lack them"
            )
        executor.remove_node(node)
    executor.shutdown()
    for node in nodes:
        node.destroy_node()
