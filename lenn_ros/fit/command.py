"""``lenn-ros fit``: the command line's front-end, read, fit, write (``-o``), plot and report.

Thin on purpose: what each step does lives in its module (:mod:`~lenn_ros.fit.load`,
:mod:`~lenn_ros.fit.procedure`, :mod:`~lenn_ros.fit.export`, :mod:`~lenn_ros.fit.report`);
here are only the flags that say how the data become samples and the order of the steps.
"""

from __future__ import annotations

import sys
from typing import Any

from lenn_ros.fit.data import FitError
from lenn_ros.fit.export import write_outputs
from lenn_ros.fit.procedure import fit
from lenn_ros.fit.records import as_paths, data_name, load_records, split_of
from lenn_ros.fit.report import format_report, plot
from lenn_ros.service.reading import flags_of


def reading_flags(args: Any) -> dict[str, Any]:
    """What says how the data become samples, besides ``--u`` / ``--y``: a bag's reading flags (the same for
    fit, evaluate and bag-info: :mod:`lenn_ros.service.reading`), a CSV's time column."""
    flags = {key: value for key, value in flags_of(args).items() if key not in ("u", "y")}
    return {**flags, "time": getattr(args, "time", None)}


def main(args: Any) -> int:
    """``lenn-ros fit``: read, fit, write (``-o``), plot and report.

    ``args``: the Namespace of cli.py's parser; ``args.data`` the build records (a list of paths, or one path),
    ``args.test`` the records that only score (a list, or None), each a run of its own
    (:mod:`~lenn_ros.fit.records`)."""
    shown = sys.stderr.isatty() and not args.json  # a bar while a long recording is read
    paths, tests = as_paths(args.data), as_paths(getattr(args, "test", None))
    data = load_records(paths, tests, args.u, args.y, reading_flags(args), progress=shown)
    dt = args.dt or data.sample_period
    if args.dt and data.sample_period and abs(args.dt - data.sample_period) > 0.01 * data.sample_period:
        raise FitError(f"--dt {args.dt:g} s disagrees with the time column's sample period {data.sample_period:g} s")
    progress = None if args.json else (lambda text: print(text, file=sys.stderr, flush=True))
    network = getattr(args, "network", "lenn") or "lenn"
    # the first test sample by number, as asked, else as the bag recorded it (the node's test_start), else the
    # first --test record's
    test_from, recorded = split_of(data, args.test_from)
    solver = getattr(args, "solver", "ls") or "ls"
    result = fit(data, test_from, refine=not args.no_refine, network=network, solver=solver, progress=progress,
                 recorded=recorded)  # fmt: skip
    if args.output:
        result.files = write_outputs(args.output, result, data)
    if args.plot:
        plot(args.plot, result, data_name(paths))
    if args.json:
        print(result.to_json())
        return 0
    print(format_report(result, dt))
    return 0
