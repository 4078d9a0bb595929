"""The process's console (stderr) through a bounded queue: a console nobody reads never stalls a node.

Why: rclpy logs through rcutils, which writes each line to stderr with a blocking ``write()``
on the node's own thread. Started with its stderr on a pipe that nobody reads (a harness's
``subprocess.Popen(stderr=PIPE)`` read only at the end, a supervisor that stopped draining),
a node fills the pipe's 64 KiB after some hundreds of warnings, and its next log line blocks
the thread that takes messages, pairs and learns, for good: the identifier went deaf after
25 minutes of a lone-input warning every 5 s, alive, publishing nothing, saying nothing
(issue 45; ``py-spy dump --native`` showed the main thread in ``write()`` under
``rcutils_logging_console_output_handler``).

So where stderr is a pipe or a socket, file descriptor 2 is replaced by a pipe of the
process's own: a reader thread drains it at once into a bounded queue (:data:`CAPACITY`
bytes; beyond it the oldest lines go, counted), and a writer thread passes the queue on to
the real stderr, blocking there instead of the node. A terminal or a file is left as it is
(a terminal keeps its colours; a file never blocks). What was dropped is said in one line
once the console takes lines again, and counted (:attr:`ConsoleGuard.dropped_lines`, the
identifier's ``status`` counter ``console_lines_lost``).
"""

from __future__ import annotations

import atexit
import os
import stat
import threading
import time
from collections import deque

#: Bytes of console output held while the real stderr does not take them (a few thousand lines).
CAPACITY = 256 * 1024


class ConsoleGuard:
    """Installed by :func:`guard_console`; see the module docstring."""

    def __init__(self, capacity: int = CAPACITY) -> None:
        self.capacity = capacity
        self.dropped_lines = 0
        self._said_dropped = 0
        self._queue: deque[bytes] = deque()
        self._held = 0
        self._lock = threading.Condition()
        self._closed = False
        self._real = os.dup(2)
        read, write = os.pipe()
        os.dup2(write, 2)
        os.close(write)
        self._read = read
        self._reader = threading.Thread(target=self._drain, name="console-reader", daemon=True)
        self._reader.start()
        self._writer = threading.Thread(target=self._pass_on, name="console-writer", daemon=True)
        self._writer.start()

    def _drain(self) -> None:
        """Read what the process writes to fd 2 at once, so no write there ever waits."""
        while True:
            try:
                chunk = os.read(self._read, 65536)
            except OSError:
                return
            if not chunk:  # every write end closed (close()): what was written is all in the queue
                with self._lock:
                    self._closed = True
                    self._lock.notify()
                return
            with self._lock:
                self._queue.append(chunk)
                self._held += len(chunk)
                while self._held > self.capacity and len(self._queue) > 1:
                    old = self._queue.popleft()
                    self._held -= len(old)
                    self.dropped_lines += old.count(b"\n")
                self._lock.notify()

    def _pass_on(self) -> None:
        """Write the queue to the real stderr, blocking here (not in the node) while nobody reads it."""
        while True:
            with self._lock:
                while not self._queue and not self._closed:
                    self._lock.wait()
                if not self._queue:
                    return
                chunk = self._queue.popleft()
                self._held -= len(chunk)
                note = self._dropped_note()
            try:
                for data in (note, chunk):
                    while data:
                        data = data[os.write(self._real, data) :]
            except OSError:  # the reader went away (EPIPE): nothing more can be shown
                with self._lock:
                    self.dropped_lines += chunk.count(b"\n") + sum(c.count(b"\n") for c in self._queue)
                    self._queue.clear()
                    self._held = 0

    def _dropped_note(self) -> bytes:
        """One line for the lines dropped since the last such line (called with the lock held)."""
        if self.dropped_lines == self._said_dropped:
            return b""
        count, self._said_dropped = self.dropped_lines - self._said_dropped, self.dropped_lines
        return (
            f"[console] {count} log line(s) dropped ({self.dropped_lines} so far): nobody read this process's "
            "stderr for a while (a pipe its launcher does not drain); the node went on working\n"
        ).encode()

    def close(self, timeout: float) -> bool:
        """The process ends: fd 2 becomes the real stderr again, and what was written before reaches it, waiting
        at most ``timeout`` s (a reader that never reads gets nothing more; the exit does not wait for it)."""
        import sys

        sys.stderr.flush()
        os.dup2(self._real, 2)  # the pipe's last write end closes: the reader drains it to the end
        end = time.monotonic() + timeout
        self._reader.join(max(0.0, end - time.monotonic()))
        self._writer.join(max(0.0, end - time.monotonic()))  # (it ends once the queue is written out)
        return not self._writer.is_alive()


_GUARD: ConsoleGuard | None = None


def _blocks(fd: int) -> bool:
    """Whether writes to ``fd`` can wait for a reader: a pipe or a socket (not a terminal, not a file)."""
    try:
        mode = os.fstat(fd).st_mode
    except OSError:
        return False
    return stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)


def guard_console() -> ConsoleGuard | None:
    """Install the guard once per process where stderr can block (see the module docstring); returns it."""
    global _GUARD
    if _GUARD is None and os.environ.get("LENN_ROS_CONSOLE_GUARD", "1") != "0" and _blocks(2):
        _GUARD = ConsoleGuard()
        atexit.register(flush)  # a normal exit too: the daemon threads die with the interpreter
    return _GUARD


def dropped_lines() -> int:
    """Console lines dropped so far because nobody read stderr (0 without the guard)."""
    return _GUARD.dropped_lines if _GUARD is not None else 0


def flush(timeout: float = 0.5) -> None:
    """Before the process ends: what was logged reaches the real stderr (at most ``timeout`` s), then stderr is the
    real one again. Once per process (the exit path and ``atexit`` both call it)."""
    global _GUARD
    if _GUARD is not None:
        guard, _GUARD = _GUARD, None
        guard.close(timeout)
