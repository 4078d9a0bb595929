"""``lenn-ros``: the command line of the package (offline work and the demo).

Each subcommand lives in its own module and is imported only when used, so
``lenn-ros reproduce`` starts without loading rclpy. Expected failures (a missing
bag, a malformed params file, a weights file of another network) end in one line
on stderr naming the problem and the fix, and exit status 2; a traceback means a bug
(which exceptions count as the user's: :mod:`lenn_ros.errors`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from lenn_ros.errors import user_error_types
from lenn_ros.presets import PARAMETER_SETS, TRAIN_SAMPLES
from lenn_ros.service.reading import add_flags as add_reading_flags


def _reproduce(args: argparse.Namespace) -> int:
    from lenn_ros.paper import reproduce

    if args.beyond:
        from lenn_ros.paper import beyond

        return beyond.main(args)
    return reproduce.main(args)


def _evaluate(args: argparse.Namespace) -> int:
    from lenn_ros import evaluate

    return evaluate.main(args)


def _fit(args: argparse.Namespace) -> int:
    from lenn_ros.fit import command

    return command.main(args)


def _import_csv(args: argparse.Namespace) -> int:
    from lenn_ros.bag import import_csv

    report = import_csv(args.file, args.u, args.y, args.dt, args.output, test_from=args.test_from)
    print(report if isinstance(report, str) else f"wrote {args.output}")
    return 0


def _bag_info(args: argparse.Namespace) -> int:
    import json

    from lenn_ros.bag.info import bag_info, format_info
    from lenn_ros.service.reading import flags_of, given

    info = bag_info(args.bag)
    flags = flags_of(args)
    if given(flags):
        from lenn_ros.service.recording import samples_summary

        info["samples"] = samples_summary(args.bag, flags, progress=sys.stderr.isatty() and not args.json)
    if args.json:
        print(json.dumps(info, indent=1, default=str))
        return 0
    print(format_info(info))
    if "samples" in info:
        from lenn_ros.service.recording import format_samples

        print(format_samples(info["samples"]))
    return 0


def _bag_repair(args: argparse.Namespace) -> int:
    from lenn_ros.bag import recover

    print(recover(args.bag))
    return 0


def _demo(args: argparse.Namespace) -> int:
    from lenn_ros import demo

    return demo.main(args)


def build_parser() -> argparse.ArgumentParser:
    """The ``lenn-ros`` parser: one sub-parser per command, each built by its own ``_add_*``."""
    parser = argparse.ArgumentParser(
        prog="lenn-ros",
        description="Online LeNN / MLP identification of nonlinear dynamic systems (ROS 2).",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_reproduce(commands)
    _add_reproduce_mimo(commands)
    _add_evaluate(commands)
    _add_fit(commands)
    _add_fit_fleet(commands)
    _add_import_csv(commands)
    _add_bag_info(commands)
    _add_bag_repair(commands)
    _add_demo(commands)
    _add_bench(commands)
    return parser


def _add_reproduce(commands: Any) -> None:
    p = commands.add_parser("reproduce", help="the paper's four examples offline, over several seeds")
    p.add_argument("--example", type=int, choices=[1, 2, 3, 4], help="one example (default: all four)")
    p.add_argument("--network", choices=["lenn", "mlp"], help="one network (default: both)")
    p.add_argument("--seeds", type=_positive_int, default=5, help="seeds 0..K-1 (default 5)")
    p.add_argument("--iterations", type=_positive_int, default=TRAIN_SAMPLES, help="training samples (50000)")
    p.add_argument(
        "--parameters",
        choices=PARAMETER_SETS,
        default="calibrated",
        help="alpha/beta: 'calibrated' for this implementation (default) or as printed in the 'paper'",
    )
    p.add_argument("--plots", metavar="DIR", help="write one PNG per example and network (Figs. 4-7 style)")
    p.add_argument("--json", action="store_true", help="print a JSON list instead of a table")
    p.add_argument("--beyond", action="store_true", help="RLS, cross terms and other expansions vs the paper")
    p.set_defaults(handler=_reproduce)


def _reproduce_mimo(args: argparse.Namespace) -> int:
    from lenn_ros.paper.experiments import mimo

    return mimo.main(args)


def _add_reproduce_mimo(commands: Any) -> None:
    from lenn_ros.paper.experiments.mimo import NOISE_DB, SEEDS, TEST_SAMPLES, TRAIN_SAMPLES

    p = commands.add_parser(
        "reproduce-mimo",
        help="the 2x2 Narendra plant offline: MIMO LeNN vs one SISO LeNN per output vs an MLP, over seeds",
    )
    p.add_argument("--seeds", type=_positive_int, default=SEEDS, help=f"seeds 0..K-1 (default {SEEDS})")
    p.add_argument("--train-samples", type=_positive_int, default=TRAIN_SAMPLES, help=f"default {TRAIN_SAMPLES}")
    p.add_argument("--test-samples", type=_positive_int, default=TEST_SAMPLES, help=f"default {TEST_SAMPLES}")
    p.add_argument(
        "--noise-db", type=float, default=NOISE_DB, help=f"training plant-input noise (default {NOISE_DB:g})"
    )
    p.add_argument("--plot", metavar="DIR", help="write the last seed's figure as DIR/mimo_narendra2x2.png")
    p.add_argument("--json", action="store_true", help="print JSON (settings and one row per output and model)")
    p.set_defaults(handler=_reproduce_mimo)


def _add_evaluate(commands: Any) -> None:
    p = commands.add_parser(
        "evaluate",
        help="run the identifier over a recorded bag, no ROS graph needed",
        description="Learn on the bag's training samples as the identifier node would, then score the frozen "
        "model on the test samples (one-step and free run). Clipped network inputs, divergence and a free run "
        "worse than the mean are printed as WARNING lines (and listed in the JSON's warnings).",
    )
    p.add_argument(
        "bag",
        nargs="+",
        help="rosbag2 bag: a directory (MCAP or sqlite3, one file or split) or its .mcap file. Several: each a "
        "record of its own, one model learnt through their build parts, scored on each test part and on all",
    )
    p.add_argument(
        "--params",
        metavar="FILE",
        help="identifier params file (ros__parameters YAML; default: the configuration the identifier recorded "
        "in the bag). If either names weights_in (as lenn-ros fit -o writes), learning starts from those weights, "
        "as in the node: a relative weights_in is taken from the current directory, as the node does",
    )
    p.add_argument(
        "--node",
        default="/identifier",
        metavar="NAME",
        help="fully qualified name of the identifier whose sections of --params apply, by ROS's own rules "
        "(default /identifier; e.g. /robot1/identifier: a /robot2/identifier: section is not its)",
    )
    p.add_argument(
        "--test-from",
        type=int,
        metavar="K",
        help="1-based index of the first test sample, in the node's numbering: samples before K are learnt from, "
        "K.. are scored "
        "(the same meaning as in fit and import-csv; default: the recorded frozen phase or test_start, else the "
        "last fifth of the samples, said in the first line)",
    )
    p.add_argument("--plot", metavar="PNG", help="write plant vs model output and error")
    p.add_argument("--json", action="store_true", help="print a JSON object")
    add_reading_flags(p)
    p.set_defaults(handler=_evaluate)


def _add_fit(commands: Any) -> None:
    p = commands.add_parser(
        "fit",
        help="build a model of logged data automatically (family, structure, terms, weights) and score it",
        description="Choose the model family (polynomial, hinge, RFF, increment form, stick, FIR, ...), lags and "
        "terms by the free runs of blocks of the training samples, each simulated by the weights of the others; "
        "refine on simulation error as far as the blocks vouch for; score on the test part. A bag is read as the "
        "identifier read it (its identifier_config, or --u/--u-field/--y/--y-field/--sample-period). "
        "-o DIR writes a params file and weights the identifier node starts from.",
    )
    p.add_argument(
        "data",
        nargs="+",
        help="one or several records to build on, each a run of its own (never fitted across a join; the scales "
        "and the selection's blocks from all of them), each a CSV file (columns by name or 0-based index; commas, "
        "semicolons, tabs or whitespace; # and %% comment lines; a row with a cell empty, NaN or inf is a gap) or a "
        "rosbag2 bag (a directory of MCAP or sqlite3 "
        "files, one or split; a .mcap file; a .db3 file beside its metadata.yaml): its u / y_p topics as the "
        "identifier read them (identifier_config: types, fields, pairing, remapped topics), or the topics named "
        "by --u/--y; of a bag of plain Float64MultiArray u / y_p (import-csv's), --u/--y may name channels by label",
    )
    add_reading_flags(p, csv=True)
    p.add_argument("--dt", type=float, help="sample time in seconds (reported only)")
    p.add_argument(
        "--time",
        metavar="COL",
        help="CSV: the column of the samples' times in seconds; a jump of more than 1.5 sample periods (the "
        "median step) is a gap, never fitted across; rows out of order are refused",
    )
    p.add_argument(
        "--test-from",
        type=int,
        metavar="K",
        help="the number of the first test sample: samples numbered below K build the model, K.. score it. A "
        "sample's number is the node's: in a bag its sample index, in a CSV its data row from 1 (a header not "
        "counted; a row missing a cell keeps its number). The same meaning as in evaluate, import-csv and "
        "bag-info; honoured exactly or refused. Required for a CSV; a bag's recorded test start is the default. "
        "With several records only where their numbers run on from one to the next (else --test)",
    )
    p.add_argument(
        "--test",
        action="append",
        metavar="FILE",
        help="a record (CSV file or bag, read as the others) that only scores the model, whole: its one-step pass "
        "and free run start from its own first samples. Repeatable; instead of --test-from",
    )
    p.add_argument("--json", action="store_true", help="print the report as a JSON object")
    p.add_argument("--plot", metavar="FILE", help="write plant vs model (one-step and free run) on the test part")
    p.add_argument("-o", "--output", metavar="DIR", help="write DIR/params.yaml and DIR/weights.npz")
    p.add_argument("--no-refine", action="store_true", help="skip the simulation-error refinement")
    p.add_argument(
        "--network",
        choices=["lenn", "mlp"],
        default="lenn",
        help="lenn (default: selected Legendre terms, least squares + simulation-error refinement, RLS live) "
        "or mlp (same lags, SGD by epochs with early stopping)",
    )
    p.add_argument(
        "--solver",
        choices=["ls", "sgd"],
        default="ls",
        help="LeNN weights: ls (default: least squares + simulation-error refinement; the node adapts by RLS) "
        "or sgd (the selected terms trained by SGD with momentum, several epochs early-stopped on the held-out "
        "tail; the node adapts by SGD with the same step)",
    )
    p.set_defaults(handler=_fit)


def _fit_fleet(args: argparse.Namespace) -> int:
    from lenn_ros.fleet_fit import command

    return command.main(args, build_parser)


def _add_fit_fleet(commands: Any) -> None:
    p = commands.add_parser(
        "fit-fleet",
        allow_abbrev=False,
        help="one model per entry of a fleet's logs (a manifest or a folder), fitted side by side on a Dask cluster",
        description="Each entry (one or several records and fit's flags, from a YAML manifest; or each log of a "
        "folder, with the flags given here) is fitted by lenn-ros fit itself, on a worker: MODELS/NAME/ holds what "
        "fit -o writes and the report (fit.txt), bit for bit a serial fit's; MODELS/summary.csv a row per entry. "
        "Whole models are skipped (unless --force), a failed entry is said and the others go on, a lost worker's "
        "entries are fitted elsewhere. Flags not listed here are fit's, given to every entry (docs/fleet.md)",
    )
    p.add_argument("source", metavar="MANIFEST.yaml|DIR", help="a manifest of entries, or a folder of logs")
    p.add_argument("-o", "--output", required=True, metavar="MODELS", help="the models' folder (made if missing)")
    p.add_argument(
        "--cluster",
        default="local",
        help="local (default: a worker process per core, one thread each), local:N (N workers), or a running "
        "scheduler's address, tcp://HOST:PORT or tls://HOST:PORT (dask scheduler; dask worker ADDRESS)",
    )
    p.add_argument("--force", action="store_true", help="fit the entries whose model is already whole too")
    p.add_argument(
        "--send-logs",
        action="store_true",
        help="send each entry's logs to its worker with the task (workers that do not share this disk); without "
        "it the workers read the logs at the manifest's paths",
    )
    p.add_argument("--tls-ca-file", metavar="PEM", help="tls:// cluster: the CA that signed the cluster's certificates")
    p.add_argument("--tls-cert", metavar="PEM", help="tls:// cluster: this client's certificate")
    p.add_argument("--tls-key", metavar="PEM", help="tls:// cluster: this client's private key")
    p.set_defaults(handler=_fit_fleet, fit_flags=[])


def _add_import_csv(commands: Any) -> None:
    p = commands.add_parser("import-csv", help="make a bag (u, y_p) from a logged CSV file")
    p.add_argument("file", help="delimited text: commas, semicolons, tabs or whitespace; # and %% comment lines")
    p.add_argument(
        "--u",
        required=True,
        action="append",
        help="column of the plant input (name or 0-based index); repeat for several inputs: u and y_p then "
        "carry Float64MultiArray samples labelled with the column names",
    )
    p.add_argument("--y", required=True, action="append", help="column of the plant output; repeat for several outputs")
    p.add_argument("--dt", type=float, required=True, help="sample time in seconds")
    p.add_argument(
        "--test-from",
        type=int,
        metavar="K",
        help="the number of the first test sample (its data row from 1; row k is the bag's sample k), stored in "
        "the bag as test_start: fit and evaluate of the bag split there",
    )
    p.add_argument("-o", "--output", required=True, help="bag directory to create")
    p.set_defaults(handler=_import_csv)


def _add_bag_info(commands: Any) -> None:
    p = commands.add_parser(
        "bag-info",
        help="what a bag holds: duration, topics, types, counts, rates, pauses, lost messages",
        description="A summary as ros2 bag info prints it, for any rosbag2 bag (MCAP or sqlite3). With the topics "
        "named (--u/--y and their fields, --sample-period...), also the samples the identifier would form from "
        "them: how many, their numbers, their gaps.",
    )
    p.add_argument("bag", help="rosbag2 bag: a directory (MCAP or sqlite3, one file or split) or its .mcap file")
    p.add_argument("--json", action="store_true", help="print a JSON object (for scripts)")
    add_reading_flags(p)
    p.set_defaults(handler=_bag_info)


def _add_bag_repair(commands: Any) -> None:
    p = commands.add_parser("bag-repair", help="recover what a killed recorder left into a readable bag")
    p.add_argument("bag")
    p.set_defaults(handler=_bag_repair)


def _add_demo(commands: Any) -> None:
    p = commands.add_parser("demo", help="plant simulator + identifier + recorder over DDS, example 1 by default")
    p.add_argument("--example", type=int, choices=[1, 2, 3, 4], default=1)
    p.add_argument("--network", choices=["lenn", "mlp"], default="lenn")
    p.add_argument("--train-samples", type=_positive_int, default=20_000)
    p.add_argument("--test-samples", type=_positive_int, default=600)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rate", type=float, default=0.0, help="plant steps per second (0: as fast as kept up with)")
    p.add_argument("--output", default="demo_output", help="directory for the bag and the plot")
    p.set_defaults(handler=_demo)


#: ``lenn-ros bench NAME``: the benchmark scripts of the source tree's bench/ (tables in bench/RESULTS.md)
BENCHMARKS = {
    "speed": ("speed.py", "everything: offline costs and throughput, online loops, memory (bench/RESULTS.md)"),
    "online": ("speed_online.py", "loss-free rate and latency through ROS, nodes compared in one run"),
    "reproduce": ("reproduce_marginal.py", "marginal end-to-end cost of `lenn-ros reproduce`"),
    "evaluate": ("evaluate_large.py", "`evaluate` of a 10^6-sample bag, read to result"),
    "fleet": ("fleet.py", "plants at 100 Hz with zero loss: a fleet on one core, on every core, a process per plant"),
    "soak": ("soak.py", "a long live run (10^6 samples) through simulator, identifier and recorder"),
    "bag-read": ("bag_read.py", "bag reading speed (messages/s) beside rosbags' and mcap's own readers"),
    "peers": ("peer_narx.py", "against SysIdentPy's FROLS polynomial NARX on real data"),
    "mimo-live": ("mimo_live.py", "the 2x2 plant identified live over seeds: MIMO against one SISO model per output"),
}


def _add_bench(commands: Any) -> None:
    listing = "; ".join(f"{name}: {text}" for name, (_, text) in BENCHMARKS.items())
    p = commands.add_parser(
        "bench",
        help="run a benchmark of the source tree's bench/ (default: speed)",
        description=f"Benchmarks ({listing}). Arguments after NAME go to the script (e.g. -h).",
    )
    p.add_argument("name", nargs="?", choices=list(BENCHMARKS), default="speed", metavar="NAME")
    p.add_argument("script_args", nargs=argparse.REMAINDER, help="passed to the benchmark script")
    p.set_defaults(handler=_bench)


def _bench(args: argparse.Namespace) -> int:
    """The scripts live beside the package in a source checkout; an installed wheel has none."""
    import subprocess
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "bench" / BENCHMARKS[args.name][0]
    if not script.is_file():
        print(f"lenn-ros bench: error: {script} not found: benchmarks run from a source checkout", file=sys.stderr)
        return 2
    return subprocess.call([sys.executable, str(script), *args.script_args], cwd=script.parents[1])


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


#: Commands whose closing line on stderr says how long they took and the memory they needed (a day-long log).
MEASURED = ("fit", "evaluate", "bag-info")


def _measured(command: str, started: float) -> None:
    """One line on stderr: the command's wall time and its peak resident memory (``ru_maxrss``)."""
    import resource
    import time

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux
    print(f"lenn-ros {command}: {time.monotonic() - started:.1f} s, peak memory {peak:.0f} MiB", file=sys.stderr)


def _parsed(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """The arguments; the flags fit-fleet does not know are fit's, for every entry (refused by any other command)."""
    args, unknown = parser.parse_known_args(argv)
    if unknown and not hasattr(args, "fit_flags"):
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if hasattr(args, "fit_flags"):
        args.fit_flags = unknown
    return args


def main(argv: Sequence[str] | None = None) -> int:
    import time

    started = time.monotonic()
    args = _parsed(build_parser(), argv)
    try:
        code = int(args.handler(args) or 0)
        if args.command in MEASURED:
            _measured(args.command, started)
        return code
    except KeyboardInterrupt:
        return 130
    except Exception as error:
        if not isinstance(error, user_error_types()):
            raise  # a bug: the traceback says where
        print(f"lenn-ros {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
