"""Several identifiers in one fleet: one per plant, each in its own namespace, spread over worker processes.

    ros2 run lenn_ros fleet --ros-args -p plants:="[arm/joint1, arm/joint2, oven]" \\
        -p workers:=auto --params-file fleet.yaml

Identifier ``/arm/joint1/identifier`` reads ``/arm/joint1/u`` and ``/arm/joint1/y_p`` and
publishes ``/arm/joint1/y_hat``, ... as if it had been started alone with
``-r __ns:=/arm/joint1``: each keeps its own parameters (a params file's ``/**:`` section
applies to all, ``/arm/joint1/identifier:`` to one), model, counters and status.

``workers:=1``: every identifier in this one process, on one DDS participant and one
wait-set loop, which is what a Python interpreter per plant would cost otherwise; but one
process runs on one core. ``workers:=N`` (``auto``: the cores this process may use) spreads
the plants over N worker processes, each such a one-process fleet of its share, started
with the same ROS arguments (``--ros-args``, params files, remaps), so a plant's parameters
resolve as they would in one process. This node (``/fleet``) holds the list of plants and,
with workers, watches them: a worker that dies is said in one line naming its plants and
counted; SIGINT or SIGTERM stops them all, and a worker whose launcher died stops itself.
``bench/fleet.py`` measures what each buys on this machine.
"""

from __future__ import annotations

import json
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.validate_namespace import validate_namespace

from lenn_ros.nodes import executor_choice, run_node
from lenn_ros.nodes.identifier import EXECUTOR, IdentifierNode

#: The fleet's own parameters: a ``-p`` for them reaches every node of the process, where they are not unknown.
FLEET_PARAMETERS = ("plants", "workers")
#: How often the launcher looks for a worker that has ended (seconds).
WATCH_PERIOD = 0.2
#: How long a worker may take to stop after SIGTERM before it is killed: an identifier stops within
#: 2 s of the signal (issue 18); a worker still starting (numba's first compile) may take longer.
STOP_SECONDS = 15.0


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


def worker_count(value: Any, plants: int) -> int:
    """``workers`` as a number of processes, at most one per plant; a bad value stops the start with one line.

    ``auto`` counts the cores this process may run on (its affinity, as ``taskset`` or a
    container's cpuset leave it), not the machine's: a worker per core it cannot use only adds
    a process to share one core with.
    """
    if value == "auto":
        wanted = len(os.sched_getaffinity(0))
    elif isinstance(value, str) and value.strip().isdigit():  # a params file's "2"
        wanted = int(value)
    elif isinstance(value, int) and not isinstance(value, bool):
        wanted = value
    else:
        wanted = 0
    if wanted < 1:
        raise SystemExit(f"fleet: cannot start: workers must be 'auto' or a positive integer, not {value!r}")
    return min(wanted, plants)


def shares(namespaces: list[str], workers: int) -> list[list[str]]:
    """The plants of each worker: dealt round, so the shares differ by one plant at most."""
    return [namespaces[number::workers] for number in range(workers)]


def identifiers(namespaces: list[str]) -> list[Node]:
    """One identifier node per namespace, for one process's loop (they share its participant)."""
    return [IdentifierNode(namespace=ns, sibling_parameters=FLEET_PARAMETERS) for ns in namespaces]


def run_worker(number: int, namespaces: list[str], args: list[str], stderr: Connection) -> None:
    """A worker process: a one-process fleet of ``namespaces`` (``number`` names it in its lines); its stderr
    goes to the launcher through ``stderr`` (see :func:`_relay_lines`)."""
    os.dup2(stderr.fileno(), 2)
    stderr.close()
    _stop_with_launcher()
    run_node(lambda: identifiers(namespaces), f"fleet worker {number}", args, executor_choice(EXECUTOR), True)


def _stop_with_launcher() -> None:
    """SIGTERM to this worker when its launcher is gone, even SIGKILLed: no worker outlives the fleet.

    The launcher holds the write end of the pipe multiprocessing started this process through
    (its sentinel); the pipe reads as ended only once the launcher has exited.
    """
    launcher = multiprocessing.parent_process()
    if launcher is None:
        return

    def watch() -> None:
        multiprocessing.connection.wait([launcher.sentinel])
        os.kill(os.getpid(), signal.SIGTERM)  # run_node's graceful stop (or the default end, before it starts)

    threading.Thread(target=watch, name="launcher-watch", daemon=True).start()


class Workers:
    """A fleet's worker processes: started with the launcher's ROS arguments, watched, stopped.

    The 'spawn' start method: a fresh interpreter per worker, never a fork of a process whose
    middleware threads (rclpy.init) are running.
    """

    def __init__(self, plant_shares: list[list[str]], args: list[str]) -> None:
        context = multiprocessing.get_context("spawn")
        self.shares = plant_shares
        self.processes = []
        self.relays = []
        console_lock = threading.Lock()
        for number, share in enumerate(plant_shares, 1):
            read, write = context.Pipe(duplex=False)
            process = context.Process(
                target=run_worker, args=(number, share, args, write), name=f"fleet worker {number}"
            )
            process.start()
            write.close()  # the worker's copy is the last: the relay reads the end once the worker has ended
            relay = threading.Thread(
                target=_relay_lines, args=(read, console_lock), name=f"relay {number}", daemon=True
            )
            relay.start()
            self.processes.append(process)
            self.relays.append(relay)
        self.died = 0
        self._reported: set[int] = set()

    def ended(self) -> list[str]:
        """One line per worker that has ended since the last call, naming its plants (counted in ``died``)."""
        lines = []
        for number, process in enumerate(self.processes, 1):
            if number in self._reported or process.exitcode is None:
                continue
            self._reported.add(number)
            self.died += 1
            lines.append(
                f"fleet: worker {number} (pid {process.pid}) ended ({_exit_reason(process.exitcode)}): plants "
                f"{', '.join(self.shares[number - 1])} are no longer identified "
                f"({self.died} of {len(self.processes)} workers ended)"
            )
        return lines

    def running(self) -> int:
        return sum(process.exitcode is None for process in self.processes)

    def stop(self, timeout: float = STOP_SECONDS) -> list[str]:
        """SIGTERM to every worker (each stops as a node does), a wait for all, SIGKILL to any left: a line each."""
        for process in self.processes:
            if process.exitcode is None:
                os.kill(process.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        waiting = [process for process in self.processes if process.exitcode is None]
        while waiting and time.monotonic() < deadline:
            multiprocessing.connection.wait([p.sentinel for p in waiting], deadline - time.monotonic())
            waiting = [process for process in waiting if process.exitcode is None]
        lines = []
        for process in waiting:
            process.kill()
            process.join()
        for relay in self.relays:  # the workers' last lines (final statuses) out before the launcher's
            relay.join(timeout=2.0)
        for process in waiting:
            lines.append(f"fleet: {process.name} (pid {process.pid}) not stopped {timeout:.0f} s after SIGTERM: killed")
        return lines


def _relay_lines(source: Connection, lock: threading.Lock) -> None:
    """A worker's stderr on to this process's, a whole line per write, until the worker has ended.

    Workers writing to one shared stderr interleave: a worker's final status line had another
    worker's log line spliced into it before its newline. Each worker writes to a pipe of its
    own instead; here its lines are cut whole and written one at a time, one relay at a time.
    """
    fd, pending = source.fileno(), b""
    while True:
        try:
            chunk = os.read(fd, 65536)
        except OSError:
            chunk = b""
        if not chunk:
            break
        pending += chunk
        *lines, pending = pending.split(b"\n")
        _write_lines(lines, lock)
    _write_lines([pending] if pending else [], lock)
    source.close()


def _write_lines(lines: list[bytes], lock: threading.Lock) -> None:
    with lock:
        for line in lines:
            data = line + b"\n"
            try:
                while data:
                    data = data[os.write(2, data) :]
            except OSError:  # nobody reads this process's stderr any more: nothing more can be shown
                return


def _exit_reason(code: int) -> str:
    """A process's exit code in words: a negative one is the signal that ended it."""
    if code < 0:
        return f"killed by {signal.Signals(-code).name}"
    return f"exit status {code}"


class FleetNode(Node):
    """Holds ``plants`` and ``workers``; the identifiers are nodes of their own beside it or in its workers."""

    def __init__(self, worker_args: list[str]) -> None:
        """``worker_args``: the command line the workers start with (this process's ROS arguments)."""
        super().__init__("fleet")
        described = ParameterDescriptor(
            description="one identifier per entry, in that namespace (e.g. [arm/joint1, oven])", read_only=True
        )
        self.declare_parameter("plants", Parameter.Type.STRING_ARRAY, described)
        described = ParameterDescriptor(
            description="processes the plants are spread over: auto (one per core this process may use) or a "
            "positive integer; 1 = every identifier in this process",
            read_only=True,
            dynamic_typing=True,  # "auto" or a number
        )
        self.declare_parameter("workers", "auto", described)
        try:
            value = self.get_parameter("plants").value
        except ParameterUninitializedException:  # not given, or given as [] (no type to infer)
            value = []
        self.namespaces = plant_namespaces(list(value or []))
        self.worker_count = worker_count(self.get_parameter("workers").value, len(self.namespaces))
        self.workers: Workers | None = None
        if self.worker_count > 1:
            self.workers = Workers(shares(self.namespaces, self.worker_count), worker_args)
            self.create_timer(WATCH_PERIOD, self._watch)

    def describe(self) -> str:
        """The start line: which plants run where."""
        if self.workers is None:
            return f"{len(self.namespaces)} identifiers: {', '.join(self.namespaces)}"
        placed = "; ".join(
            f"worker {number} (pid {process.pid}): {', '.join(share)}"
            for number, (process, share) in enumerate(zip(self.workers.processes, self.workers.shares, strict=True), 1)
        )
        return f"{len(self.namespaces)} identifiers on {self.worker_count} worker processes: {placed}"

    def _watch(self) -> None:
        """Say each worker that ended; with none left the fleet identifies nothing and stops."""
        assert self.workers is not None
        for line in self.workers.ended():
            self.get_logger().error(line)
        if not self.workers.running():
            raise SystemExit("fleet: every worker has ended: no plant is identified")

    def shutdown(self) -> None:
        """Stop the workers (run_node calls this on the way out), then the fleet's final line."""
        if self.workers is None:
            return
        for line in self.workers.stop():
            self.get_logger().error(line)
        status = {"plants": len(self.namespaces), "workers": self.worker_count, "workers_died": self.workers.died}
        print(f"fleet: {json.dumps(status)}", file=sys.stderr, flush=True)


def make_fleet(worker_args: list[str]) -> list[Node]:
    fleet = FleetNode(worker_args)
    nodes = identifiers(fleet.namespaces) if fleet.workers is None else []
    fleet.get_logger().info(fleet.describe())
    return [fleet, *nodes]


def main(args: list[str] | None = None) -> int:
    worker_args = list(sys.argv if args is None else args)
    return run_node(lambda: make_fleet(worker_args), "fleet", args, executor_choice(EXECUTOR), exit_process=True)


if __name__ == "__main__":
    sys.exit(main())
