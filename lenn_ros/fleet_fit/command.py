"""``lenn-ros fit-fleet``: the front-end, entries, cluster, run, closing line.

Thin on purpose: what each step does lives in its module. fit's parser is handed in by the
command line (:func:`lenn_ros.cli.build_parser`), which this package must not import.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from lenn_ros.errors import UserError, require_extra


def main(args: Any, fit_parser: Callable[[], argparse.ArgumentParser]) -> int:
    """Fit every entry; 0 when none failed, 1 when some did (each said in its line and in summary.csv)."""
    require_extra("distributed", "fleet", "fit-fleet's cluster (Dask distributed)")
    from lenn_ros.fleet_fit.manifest import entries_from
    from lenn_ros.fleet_fit.run import check_cluster, fit_fleet, open_client
    from lenn_ros.fleet_fit.store import SUMMARY, Models

    started, tls = time.monotonic(), _tls(args)
    check_cluster(args.cluster, tls)
    entries = entries_from(args.source, list(args.fit_flags), fit_parser)
    models = Models(args.output)
    say = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    connect = functools.partial(open_client, args.cluster, tls)
    outcomes = fit_fleet(entries, models, connect, fit_parser, args.force, sys.stderr.isatty(), say, args.send_logs)
    counts = Counter(outcome.status for outcome in outcomes)
    told = ", ".join(f"{counts[status]} {status}" for status in ("done", "skipped", "failed") if counts[status])
    print(f"fit-fleet: {told} in {time.monotonic() - started:.1f} s; {models.root / SUMMARY}")
    return 1 if counts["failed"] else 0


def _tls(args: Any) -> Any:
    """The TLS files of a tls:// cluster, all three or none (else the cluster's configuration: docs/fleet.md)."""
    from lenn_ros.fleet_fit.run import TLS

    files = (args.tls_ca_file, args.tls_cert, args.tls_key)
    if not any(files):
        return None
    if not all(files):
        raise UserError("--tls-ca-file, --tls-cert and --tls-key go together: give all three")
    return TLS(*files)
