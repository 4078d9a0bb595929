"""Every use of rclpy's non-public API, in one place, behind a version check, with a public fallback.

Why internals at all: rclpy's executors rebuild their wait set in Python for every
callback they run, about 4 000 messages/s on this 2-core machine, less than a 1 kHz
JointState plus its command and a recorder's eleven topics. Two things rclpy's own
executor does internally make the difference (bench/RESULTS.md, "Loops"):

- taking a message straight from a subscription (the C handle's ``take_message``), so a
  node drains a burst in one wake-up and sheds a message without deserialising it;
- a wait set built once from the entities' handles (``rclpy_implementation.WaitSet``)
  instead of once per callback.

Neither is public API and either may change in any rclpy release. So they are used only
when rclpy's major version is the one they were written and tested against
(:data:`TESTED_MAJOR`, Jazzy) and every attribute used is there. Otherwise, or when
``LENN_ROS_RCLPY_INTERNALS=0`` asks for it, everything here falls back to the public API:
:func:`take` takes nothing (the executor hands each message to its callback instead),
:func:`takes_info` reads the callback's signature as rclpy does, and ``run_node`` runs
the single-threaded executor instead of :class:`WaitSetLoop` and says so in one line.
The behaviour is the same; only the cost per message rises.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.metadata
import inspect
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from rclpy.exceptions import InvalidHandle
from rclpy.executors import SingleThreadedExecutor, TimeoutException
from rclpy.node import Node
from rclpy.subscription import Subscription

#: The rclpy major version the internals below were written and tested against (Jazzy: 7.1).
TESTED_MAJOR = 7
#: Set to ``0`` to force the public fallback (trouble-shooting, and the tests of the fallback).
VARIABLE = "LENN_ROS_RCLPY_INTERNALS"


@functools.cache
def unavailable() -> str | None:
    """Why the internals cannot be used here (one phrase), or None when they can."""
    if os.environ.get(VARIABLE, "").strip().lower() in ("0", "false", "no", "off"):
        return f"{VARIABLE}=0"
    try:
        version = importlib.metadata.version("rclpy")
    except importlib.metadata.PackageNotFoundError:
        version = ""
    if version and version.split(".")[0] != str(TESTED_MAJOR):
        return f"rclpy {version} is not the tested {TESTED_MAJOR}.x"
    try:
        from rclpy.impl.implementation_singleton import rclpy_implementation as native
    except ImportError as error:
        return f"rclpy has no implementation singleton ({error})"
    needed = {
        "WaitSet": ("clear_entities", "add_subscription", "add_timer", "add_service", "wait", "get_ready_entities"),
        "Subscription": ("take_message",),
    }
    for name, methods in needed.items():
        kind = getattr(native, name, None)
        missing = [method for method in methods if not hasattr(kind, method)]
        if kind is None or missing:
            return f"rclpy's native {name} lacks {', '.join(missing) or 'itself'}"
    return None


def available() -> bool:
    """Whether :func:`take` takes and :class:`WaitSetLoop` can run (see the module's docstring)."""
    return unavailable() is None


def take(subscription: Subscription, raw: bool = True) -> tuple[Any, dict[str, int]] | None:
    """The next message waiting on ``subscription`` and its info, or None when none waits.

    Always None in the fallback: there the executor hands every message to the
    subscription's callback, one per wake-up, so nothing is lost by not taking.
    """
    if not available():
        return None
    with subscription.handle:
        return subscription.handle.take_message(subscription.msg_type, raw)


def takes_info(subscription: Subscription) -> bool:
    """Whether the subscription's callback takes the message info as a second argument.

    rclpy keeps its decision in ``_callback_type``; the fallback repeats its rule (the
    callback cannot be called with the message alone but can with two arguments).
    """
    if available():
        return subscription._callback_type is Subscription.CallbackType.WithMessageInfo
    signature = inspect.signature(subscription.callback)
    try:
        signature.bind(object())
    except TypeError:
        return True
    return False


class MessageInfoCallback:
    """A (message, info) callback as rclpy 7.1's events executor can call it.

    That executor hands a callback that takes the message info one tuple
    ``(message, info)`` instead of two arguments (the callback fails with a
    ``TypeError``, surfacing as ``SystemError: null argument to internal routine``).
    rclpy picks the calling convention from the signature, so this wrapper declares
    two parameters and accepts either form: it keeps working once the executor
    passes two arguments.
    """

    __signature__ = inspect.Signature(
        [inspect.Parameter(name, inspect.Parameter.POSITIONAL_ONLY) for name in ("message", "info")]
    )

    def __init__(self, callback: Callable[[Any, Any], Any]) -> None:
        self.callback = callback

    def __call__(self, *arguments: Any) -> Any:
        if len(arguments) == 1:
            return self.callback(*arguments[0])
        return self.callback(*arguments)


def pass_message_info(node: Node) -> None:
    """Wrap the node's (message, info) subscription callbacks for the events executor (see above)."""
    for subscription in node.subscriptions:
        if takes_info(subscription) and not isinstance(subscription.callback, MessageInfoCallback):
            subscription.callback = MessageInfoCallback(subscription.callback)


class WaitSet:
    """A native wait set over fixed subscriptions, timers and services, their handles entered once.

    Use as a context manager; :meth:`wait` blocks until one of them is ready. Entities
    destroyed before it is entered are left out (``entities`` holds those kept). Used by
    :class:`WaitSetLoop` and the benchmarks' own receivers. Needs the internals (:func:`available`).
    """

    def __init__(self, context: Any, subscriptions: Any, timers: Any = (), services: Any = ()) -> None:
        self.context = context
        self.entities: tuple[list[Any], list[Any], list[Any]] = (list(subscriptions), list(timers), list(services))
        self._stack = contextlib.ExitStack()
        self._native: Any = None
        self._handles: tuple[list[Any], list[Any], list[Any]] = ([], [], [])

    def __enter__(self) -> WaitSet:
        from rclpy.impl.implementation_singleton import rclpy_implementation as native

        alive: tuple[list[Any], list[Any], list[Any]] = ([], [], [])
        for group, kept in zip(self.entities, alive, strict=True):
            for entity in group:
                with contextlib.suppress(InvalidHandle):  # destroyed meanwhile
                    self._stack.enter_context(entity.handle)
                    kept.append(entity)
        self.entities = alive
        self._handles = ([s.handle for s in alive[0]], [t.handle for t in alive[1]], [s.handle for s in alive[2]])
        self._stack.enter_context(self.context.handle)
        counts = [len(handles) for handles in self._handles]
        self._native = native.WaitSet(counts[0], 0, counts[1], 0, counts[2], 0, self.context.handle)
        return self

    def __exit__(self, *_: Any) -> None:
        self._stack.close()

    def wait(self, timeout_ns: int) -> bool:
        """Until a message, a timer or a service request is ready; whether a timer or service is."""
        native = self._native
        subscriptions, timers, services = self._handles
        native.clear_entities()
        for handle in subscriptions:
            native.add_subscription(handle)
        for handle in timers:
            native.add_timer(handle)
        for handle in services:
            native.add_service(handle)
        native.wait(timeout_ns)
        return bool(native.get_ready_entities("timer") or native.get_ready_entities("service"))


def run_ready(executor: Any) -> bool:
    """One callback the executor has ready now, run (its exception raised); False when none was ready.

    Public API (``wait_for_ready_callbacks``): what the wait-set loop hands the executor, and
    what the identifier's exit drain does where the internals cannot be used.
    """
    try:
        handler, _, _ = executor.wait_for_ready_callbacks(timeout_sec=0)
    except TimeoutException:
        return False
    handler()
    if handler.exception() is not None:
        raise handler.exception()
    handler.result()
    return True


class WaitSetLoop:
    """Messages straight from the subscriptions; the executor only for timers, services and QoS events.

    The single-threaded executor's cost is rebuilding its wait set (every entity,
    entered through an ExitStack, every QoS event handler) for each callback. Here the
    wait set's handles are entered once and only re-added per turn; messages are taken
    until none is left and passed to the subscription's callback as the executor would
    (with or without the message info). Services, timers and waitables still go
    through ``executor`` (``wait_for_ready_callbacks(0)``, all that is ready), so
    their behaviour is rclpy's own. Needs the internals (:func:`available`).

    ``turn_seconds``: the executor's turn comes at least this often (QoS events,
    entities added since, the stop request); ``drain_seconds``: the longest one take or
    executor pass runs before the other has its turn.
    """

    def __init__(
        self, nodes: list[Node], executor: SingleThreadedExecutor, turn_seconds: float, drain_seconds: float
    ) -> None:
        self.nodes, self.executor = nodes, executor
        self.turn_seconds, self.drain_seconds = turn_seconds, drain_seconds
        for node in nodes:
            node.loop_takes_messages = True  # a callback need not take what waits: this loop does (_take_all)
        self._snapshot: tuple[tuple[Any, ...], ...] = ()
        self._subscriptions: list[tuple[Any, Any, Any, bool, bool]] = []
        self._wait_set: WaitSet | None = None

    def spin(self, stop: threading.Event) -> None:
        """Until a stop is requested or the context ends; the executor runs at least every ``turn_seconds``."""
        context = self.nodes[0].context
        period_ns = int(self.turn_seconds * 1e9)
        try:
            self._refresh()
            next_turn = time.monotonic_ns()
            while not stop.is_set() and context.ok():
                now = time.monotonic_ns()
                others_ready = self._wait_set.wait(max(0, min(period_ns, next_turn - now)))
                self._take_all()
                if others_ready or time.monotonic_ns() >= next_turn:
                    self._run_executor()
                    self._refresh()
                    next_turn = time.monotonic_ns() + period_ns
        finally:
            if self._wait_set is not None:
                self._wait_set.__exit__()

    def _refresh(self) -> None:
        """Enter the handles of the nodes' current entities (again, if any was added or destroyed)."""
        nodes = self.nodes
        snapshot = (
            tuple(s for node in nodes for s in node.subscriptions),
            tuple(t for node in nodes for t in node.timers),
            tuple(s for node in nodes for s in node.services),
        )
        if snapshot == self._snapshot:
            return
        if self._wait_set is not None:
            self._wait_set.__exit__()
        self._snapshot = snapshot
        self._wait_set = WaitSet(nodes[0].context, *snapshot).__enter__()
        self._subscriptions = [
            (s.handle, s.msg_type, s.callback, s.raw, not takes_info(s)) for s in self._wait_set.entities[0]
        ]

    def _take_all(self) -> None:
        """Every message waiting on every subscription, each to its callback, until none is left or
        ``drain_seconds`` have passed (then the timers, services and the stop request have their turn)."""
        taken = True
        deadline = time.monotonic() + self.drain_seconds
        while taken and time.monotonic() < deadline:
            taken = False
            for handle, msg_type, callback, raw, message_only in self._subscriptions:
                waiting = handle.take_message(msg_type, raw)
                if waiting is None:
                    continue
                taken = True
                if message_only:
                    callback(waiting[0])
                else:
                    callback(waiting[0], waiting[1])

    def _run_executor(self) -> None:
        """What the executor finds ready now (timers, services, QoS events), then back to the data.

        Also bounded by ``drain_seconds``: the executor sees the data subscriptions too, and
        under a flood they are always ready. Its handlers come one wait's ready list at a
        time, kept across calls, so a service or timer behind them is reached next turn.
        """
        deadline = time.monotonic() + self.drain_seconds
        while time.monotonic() < deadline and run_ready(self.executor):
            pass
