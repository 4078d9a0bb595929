"""The fleet's run: a Dask client (an embedded LocalCluster or a running scheduler), the entries submitted,
each model put in place as it comes back, a progress bar, the summary.

Dask's public API only: :class:`distributed.Client`, :class:`distributed.LocalCluster`,
:func:`distributed.as_completed`, futures with ``retries``. A worker lost mid-run is Dask's to
handle: the scheduler gives its entries to the others (up to ``distributed.scheduler.allowed-failures``
losses per entry, then the entry fails as KilledWorker, said in its line). An entry's exception that is
not the user's is retried RETRIES times before it fails.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from lenn_ros.core.threads import cores, worker_environment
from lenn_ros.errors import UserError
from lenn_ros.fleet_fit.manifest import Entry
from lenn_ros.fleet_fit.shipping import IN_FLIGHT_PER_WORKER, ShippingError, pack
from lenn_ros.fleet_fit.store import Models
from lenn_ros.fleet_fit.task import Outcome, fit_entry
from lenn_ros.progress import progress

#: an entry's exception that is not the user's (a worker's disk, a bug) is tried this many more times
RETRIES = 2
#: the summary is rewritten at most this often while entries come back (and once at the end)
SUMMARY_EVERY = 5.0
#: seconds to reach a running scheduler
CONNECT_TIMEOUT = 30


class ClusterError(UserError):
    """A --cluster the fleet cannot use: one line saying what it expects."""


@dataclass(frozen=True)
class TLS:
    """The client's side of a tls:// cluster (``distributed.security.Security``): CA, certificate, key files."""

    ca_file: str
    cert: str
    key: str

    def security(self) -> Any:
        from distributed.security import Security

        return Security(tls_ca_file=self.ca_file, tls_client_cert=self.cert, tls_client_key=self.key,
                        require_encryption=True)  # fmt: skip


def check_cluster(cluster: str, tls: TLS | None = None) -> None:
    """Refuse a --cluster the fleet cannot use, before anything is read or fitted."""
    if cluster == "local" or cluster.startswith("local:"):
        _local_workers(cluster)
    elif not cluster.startswith(("tcp://", "tls://")):
        raise ClusterError(f"--cluster {cluster!r}: expected local, local:N, tcp://HOST:PORT or tls://HOST:PORT")
    if tls is not None and not cluster.startswith("tls://"):
        raise ClusterError(f"--cluster {cluster}: the TLS files are for a tls:// scheduler")


@contextlib.contextmanager
def open_client(cluster: str, tls: TLS | None = None) -> Iterator[Any]:
    """A Dask client, closed (with its LocalCluster) on leaving: ``local`` (one single-threaded worker process
    per core), ``local:N`` (N of them, the cores shared among them), or a running scheduler (tcp://, tls://)."""
    from distributed import Client, LocalCluster

    check_cluster(cluster, tls)
    if cluster.startswith(("tcp://", "tls://")):
        try:
            client = Client(cluster, security=tls.security() if tls else None, timeout=CONNECT_TIMEOUT)
        except OSError as error:
            raise ClusterError(f"--cluster {cluster}: no scheduler answered ({error})") from None
        with client:
            yield client
        return
    workers = _local_workers(cluster)
    threads = max(1, cores() // workers)  # set before each worker's numpy loads
    # its HTTP server on a free port: None still takes 8787 and warns when another cluster holds it
    options = {"dashboard_address": ":0", "silence_logs": logging.ERROR, "env": worker_environment(threads)}
    with (
        LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, **options) as local,
        Client(local) as client,
    ):
        yield client


def _local_workers(cluster: str) -> int:
    count = cluster.partition(":")[2]
    if not count:
        return cores()
    if not count.isdigit() or int(count) < 1:
        raise ClusterError(f"--cluster {cluster!r}: local:N takes a number of workers >= 1")
    return int(count)


def fit_fleet(
    entries: list[Entry],
    models: Models,
    connect: Callable[[], Any],
    fit_parser: Callable[[], argparse.ArgumentParser],
    force: bool = False,
    bar: bool = False,
    say: Callable[[str], None] = print,
    send_logs: bool = False,
) -> list[Outcome]:
    """Every entry's outcome, in the entries' order: whole models skipped (unless ``force``), the others fitted
    on the cluster ``connect()`` opens (a client, as a context; only when there is something to fit) and put in
    MODELS/NAME/ as each comes back; a failed entry said in one line by ``say``. ``send_logs``: each entry's logs
    go with its task (:mod:`~lenn_ros.fleet_fit.shipping`), a few entries per worker at a time."""
    outcomes = {e.name: models.skipped(e.name) for e in entries if not force and models.complete(e.name)}
    todo = [entry for entry in entries if entry.name not in outcomes]
    if todo:
        with connect() as client:
            workers = ready_workers(client)
            say(f"fit-fleet: {len(todo)} of {len(entries)} entries to fit on {workers} workers, into {models.root}")
            window = IN_FLIGHT_PER_WORKER * workers if send_logs else len(todo)
            outcomes.update(_fitted(todo, models, client, fit_parser, bar, say, entries, window, send_logs))
    ordered = [outcomes[entry.name] for entry in entries]
    models.write_summary(ordered)
    return ordered


def ready_workers(client: Any, timeout: float = CONNECT_TIMEOUT) -> int:
    """How many workers the cluster has, once at least one has joined and every one runs the client's lenn_ros;
    else :class:`ClusterError` in one line (nothing is submitted: N entries would otherwise fail N times on a
    worker that cannot import the fit, or wait in silence on a scheduler with no worker)."""
    try:
        client.wait_for_workers(1, timeout=timeout)
    except TimeoutError:
        raise ClusterError(
            f"--cluster {client.scheduler.address}: no worker joined the scheduler within {timeout:g} s "
            "(start some: dask worker ADDRESS --nthreads 1)"
        ) from None
    refusal = version_refusal(client.get_versions(packages=["lenn_ros"]))
    if refusal:
        raise ClusterError(f"--cluster {client.scheduler.address}: {refusal}")
    return len(client.scheduler_info().get("workers", {}))


def version_refusal(versions: dict[str, Any]) -> str:
    """'' when every worker has the client's lenn_ros version (Dask's ``get_versions``), else one line naming how
    many do not and one of them: the fit runs on the workers, so a model is the serial one only with the same
    package there."""
    mine = versions["client"]["packages"].get("lenn_ros")
    workers = versions.get("workers", {})
    odd = {address: info["packages"].get("lenn_ros") for address, info in workers.items()}
    odd = {address: found for address, found in odd.items() if found != mine}
    if not odd:
        return ""
    address, found = next(iter(sorted(odd.items())))
    has = "no lenn_ros" if found is None else f"lenn_ros {found}"
    return (
        f"{len(odd)} of {len(workers)} workers do not run this lenn_ros ({mine}): {address} has {has}; install the "
        "same version on every worker"
    )


def _fitted(
    todo: list[Entry],
    models: Models,
    client: Any,
    fit_parser: Callable[[], argparse.ArgumentParser],
    bar: bool,
    say: Callable[[str], None],
    entries: list[Entry],
    window: int,
    send_logs: bool,
) -> dict[str, Outcome]:
    """``todo`` submitted to ``client``, at most ``window`` at a time, each model put in place as it comes back (the
    summary kept current); ``send_logs``: each entry's logs read as it is submitted, sent with it."""
    from distributed import as_completed

    outcomes: dict[str, Outcome] = {}
    run, waiting = uuid.uuid4().hex[:8], iter(todo)
    futures: dict[Any, Entry] = {}

    def done(outcome: Outcome) -> None:
        if outcome.status == "failed":
            say(f"fit-fleet: {outcome.name}: failed: {outcome.reason}")
        outcomes[outcome.name] = outcome
        shown.update()

    def submit(source: Iterator[Entry], count: int) -> list[Any]:
        """The next ``count`` entries submitted (an entry whose logs cannot be read to send fails, the next is
        taken in its place)."""
        submitted: list[Any] = []
        for entry in source:
            try:
                logs = pack(entry) if send_logs else None
            except (OSError, ShippingError) as error:
                done(Outcome(entry.name, "failed", " ".join(str(error).split())))
                continue
            key = f"fit-{entry.name}-{run}"
            submitted.append(client.submit(fit_entry, entry, fit_parser, logs, key=key, pure=False, retries=RETRIES))
            futures[submitted[-1]] = entry
            if len(submitted) == count:
                break
        return submitted

    shown, written = progress(len(todo), bar, "fit-fleet", unit="model"), time.monotonic()
    started = as_completed(submit(waiting, max(1, window)))
    for future in started:
        done(_collected(future, futures.pop(future), models))
        future.release()
        for following in submit(waiting, 1):
            started.add(following)
        if time.monotonic() - written > SUMMARY_EVERY:
            models.write_summary(outcomes.get(e.name) or models.skipped(e.name) for e in entries)
            written = time.monotonic()
    shown.close()
    return outcomes


def _collected(future: Any, entry: Entry, models: Models) -> Outcome:
    """The entry's outcome from its future: its model put in place, or why it failed (in one line)."""
    try:
        outcome = future.result()
    except Exception as error:  # the task's own after its retries, KilledWorker, a cancelled future
        reason = " ".join(f"{type(error).__name__}: {error}".split())
        return Outcome(entry.name, "failed", reason)
    return models.install(outcome) if outcome.status == "done" else outcome
