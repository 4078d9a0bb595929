"""One entry's fit, as it runs on a worker: ``lenn-ros fit``'s own entry point, its files returned as bytes.

The fit is the serial command's (fit's parser, then :func:`lenn_ros.fit.command.main`) with the
argv a serial ``lenn-ros fit`` of the entry gets, so its model is the serial one. It writes into a
scratch folder of the worker's, whose files travel back to the client with the result: the
workers need to read the logs, not to share a disk with the client for the models
(:mod:`~lenn_ros.fleet_fit.store` puts them in place). Its report text (stdout) is kept; its
progress lines (stderr) are not, a worker has no one to tell.

A user error (a corrupt log, a flag fit refuses) fails the entry as a value, in fit's one line,
and is not retried: it would fail the same on any worker. Anything else is raised, so Dask's
``retries`` try it again (elsewhere when a worker is to blame).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lenn_ros.core.threads import THREADS_VARIABLE
from lenn_ros.errors import user_error_types
from lenn_ros.fleet_fit.manifest import Entry
from lenn_ros.fleet_fit.shipping import unpack

#: the report text fit prints, kept beside what ``fit -o`` writes
REPORT_TEXT = "fit.txt"
#: the figures of fit's report the summary shows, per output
FIGURES = ("rmse_free_run", "nmse_free_run_db", "rmse", "nmse_db")
#: a worker process fits one entry at a time: fit's report is its stdout, which is the process's, and fit
#: spreads its own work over the cores it is given (LENN_ROS_THREADS: :mod:`lenn_ros.core.threads`)
_ONE_AT_A_TIME = threading.Lock()


@dataclass
class Outcome:
    """What became of one entry: ``status`` done or failed (``reason``: one line); ``files`` (name: bytes) as fit
    wrote them into ``written_to`` (the worker's folder, which their texts name); the report's figures."""

    name: str
    status: str
    reason: str = ""
    files: dict[str, bytes] = field(default_factory=dict, repr=False)
    written_to: str = ""
    figures: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    worker: str = ""
    #: the records' copies the worker fitted (``--send-logs``) -> the records' own paths, which the files must name
    read_from: dict[str, str] = field(default_factory=dict)


def fit_entry(
    entry: Entry, fit_parser: Callable[[], argparse.ArgumentParser], logs: dict[str, bytes] | None = None
) -> Outcome:
    """Fit ``entry`` here (on a worker, or in this process) as the serial ``lenn-ros fit`` would; ``logs``: its
    records' files sent with it (``--send-logs``: :mod:`~lenn_ros.fleet_fit.shipping`), fitted from a copy here."""
    from lenn_ros.fit import command

    with _ONE_AT_A_TIME, _the_workers_threads(), tempfile.TemporaryDirectory(prefix="lenn-ros-fleet-") as scratch:
        started, worker = time.monotonic(), _worker()
        output = Path(scratch) / entry.name
        read_from: dict[str, str] = {}
        if logs is not None:
            entry, read_from = unpack(entry, logs, Path(scratch) / "logs")
        args = fit_parser().parse_args(entry.argv(str(output)))
        report = io.StringIO()
        try:
            with contextlib.redirect_stdout(report), contextlib.redirect_stderr(io.StringIO()):
                command.main(args)
        except user_error_types() as error:
            reason = " ".join(str(error).split())
            for copy, given in read_from.items():  # (a sent log is named as the entry gave it)
                reason = reason.replace(copy, given)
            return Outcome(entry.name, "failed", reason, seconds=time.monotonic() - started, worker=worker)
        files = {path.name: path.read_bytes() for path in sorted(output.iterdir()) if path.is_file()}
        files[REPORT_TEXT] = report.getvalue().encode()
        figures = report_figures(json.loads(files["fit.json"]))
        seconds = time.monotonic() - started
        return Outcome(entry.name, "done", "", files, str(output), figures, seconds, worker, read_from)


def report_figures(report: dict[str, Any]) -> dict[str, str]:
    """The summary's figures from fit's JSON report: each output's (several joined by ';', in their order)."""
    parts = report.get("per_output", [report])
    figures = {key: ";".join(_number(part.get(key)) for part in parts) for key in FIGURES}
    return {**figures, "samples": str(report.get("samples", ""))}


def _number(value: Any) -> str:
    return "" if value is None else f"{value:.6g}"


@contextlib.contextmanager
def _the_workers_threads() -> Iterator[None]:
    """On a Dask worker, the fit spreads its work (and BLAS's) over the worker's own threads (``--nthreads``) unless
    its environment sets LENN_ROS_THREADS (``--cluster local`` does): a ``dask worker --nthreads 1`` started as
    docs/fleet.md's plain line (no variables) would otherwise fit on every core, and two such workers on a host
    would each run twice their share of threads. Outside a worker, nothing changes (the serial fit's threads)."""
    threads = _worker_threads()
    if threads is None or os.environ.get(THREADS_VARIABLE):
        yield
        return
    from threadpoolctl import threadpool_limits

    os.environ[THREADS_VARIABLE] = str(threads)
    try:
        with threadpool_limits(limits=threads):
            yield
    finally:
        del os.environ[THREADS_VARIABLE]


def _worker_threads() -> int | None:
    """The task threads of the Dask worker this runs on (None outside one)."""
    try:
        from distributed import get_worker

        return max(1, int(get_worker().state.nthreads))
    except (ImportError, ValueError, AttributeError):
        return None


def _worker() -> str:
    """The worker's address (its host and port), or 'here' outside a Dask worker."""
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return "here"
