"""The offline commands on a robot's own long recording, run as a user runs them: time and peak memory.

A 10-minute recording of ``bench/robot_bag.py`` (JointState at 500 Hz, three joints, and
Float64MultiArray commands at 100 Hz: 300 000 + 60 000 messages), in MCAP and in sqlite3, each read
by real ``lenn-ros`` subprocesses with robot_bag's topic flags:

* ``bag-info BAG FLAGS`` (the summary and the samples the identifier would form);
* ``fit BAG FLAGS --test-from K -o DIR`` (K: the first sample of the last fifth);
* ``evaluate BAG FLAGS --test-from K`` with the default model (the node's defaults), and with the
  model ``fit`` wrote (``--params DIR/params.yaml``).

``--hour``: also ``bag-info`` and ``evaluate`` on an hour of a six-joint robot at 1 kHz (3.6 M
JointState + 360 000 commands, about 1.2 GB; ``--hour-seconds`` for less). For each command: wall
and CPU seconds and peak RSS (``wait4``'s rusage of that process), the samples paired, the free-run
NMSE reported, and whether it finished within 15 minutes. Usage: ``nice python bench/long_bag.py
[--hour] [--json]``; ``--seconds 60`` for a quick run.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import robot_bag

#: what a command may take (the issue's bound)
LIMIT_S = 15 * 60


@dataclass
class Result:
    """One command's run."""

    bag: str
    command: str
    wall_s: float
    cpu_s: float
    peak_rss_mb: float
    returncode: int
    samples: int | None = None  # paired (fit: training + test)
    nmse_free_run_db: float | None = None
    nmse_db: float | None = None  # one-step
    detail: str = ""

    @property
    def within_limit(self) -> bool:
        return self.returncode == 0 and self.wall_s < LIMIT_S


def lenn_ros() -> str:
    """The lenn-ros of this interpreter's environment."""
    beside = Path(sys.executable).parent / "lenn-ros"
    return str(beside) if beside.exists() else shutil.which("lenn-ros") or "lenn-ros"


def timed(argv: list[str], cwd: Path) -> tuple[int, float, float, float, str, str]:
    """Run ``argv``; (returncode, wall s, CPU s, peak RSS MB, stdout, stderr), the rusage being that process's own.

    ``wait4`` gives the rusage of that child (and of the children it waited for) alone; its peak RSS starts from
    this process's at the fork (Linux carries the high-water mark through fork and exec), so this process stays
    small (the bags are written by a subprocess): its ~40 MB is the floor of every figure.
    """
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        start = time.perf_counter()
        process = subprocess.Popen(argv, stdout=out, stderr=err, cwd=cwd)
        _pid, status, usage = os.wait4(process.pid, 0)
        wall = time.perf_counter() - start
        process.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        cpu = usage.ru_utime + usage.ru_stime
        return process.returncode, wall, cpu, usage.ru_maxrss / 1024.0, out.read(), err.read()


def run_command(bag: str, name: str, argv: list[str], cwd: Path, say: Any) -> tuple[Result, dict[str, Any]]:
    """One command (its JSON output parsed); a failure keeps its last stderr line as the detail."""
    code, wall, cpu, rss, out, err = timed(argv, cwd)
    try:
        report = json.loads(out) if code == 0 else {}
    except json.JSONDecodeError:
        report = {}
    detail = "" if code == 0 else (err.strip().splitlines() or ["(no stderr)"])[-1][:200]
    result = Result(bag, name, wall, cpu, rss, code, detail=detail)
    say(f"{bag:16s} {name:28s} rc {code} {wall:7.1f} s wall {cpu:7.1f} s CPU {rss:7.0f} MB {detail}")
    return result, report


def run_bag(
    label: str, bag: Path, flags: list[str], test_from: int, commands: tuple[str, ...], work: Path, say: Any
) -> list[Result]:
    """``commands`` (of bag-info, fit, evaluate, evaluate-fitted) on one bag."""
    exe = lenn_ros()
    results = []
    model = work / f"model_{label.replace(' ', '_')}"
    for name in commands:
        if name == "bag-info":
            result, report = run_command(label, "bag-info", [exe, "bag-info", str(bag), *flags, "--json"], work, say)
            samples = report.get("samples", {})
            result.samples = samples.get("count")
        elif name == "fit":
            argv = [exe, "fit", str(bag), *flags, "--test-from", str(test_from), "-o", str(model), "--json"]
            result, report = run_command(label, f"fit --test-from {test_from}", argv, work, say)
            if report:
                result.samples = int(report["train_samples"]) + int(report["samples"])
                result.nmse_free_run_db = _finite(report.get("nmse_free_run_db"))
                result.nmse_db = _finite(report.get("nmse_db"))
                result.detail = f"model {report['model'].get('family', '')}, {report['model'].get('n_terms')} terms"
        else:
            fitted = name == "evaluate-fitted"
            if fitted and not (model / "params.yaml").exists():
                continue
            params = ["--params", str(model / "params.yaml")] if fitted else []
            argv = [exe, "evaluate", str(bag), *flags, "--test-from", str(test_from), *params, "--json"]
            shown = f"evaluate --test-from {test_from}" + (" (fit's model)" if fitted else " (default model)")
            result, report = run_command(label, shown, argv, work, say)
            if report:
                result.samples = report.get("pairs")
                result.nmse_free_run_db = _finite(report.get("nmse_free_run_db"))
                result.nmse_db = _finite(report.get("nmse_db"))
                diverged = [w for w in report.get("free_run_warnings", []) if "diverged" in w]
                result.detail = diverged[0].split(":")[0] if diverged else ""
        results.append(result)
    return results


def write(path: Path, seconds: float, storage: str, joints: int, rate: float, say: Any) -> dict[str, Any]:
    """Write one recording, timed; its size and messages."""
    argv = [sys.executable, str(Path(robot_bag.__file__)), str(path), "--seconds", repr(seconds), "--storage", storage]
    argv += ["--joints", str(joints), "--rate", repr(rate)]
    start = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL)  # (this process stays small: see timed)
    wall = time.perf_counter() - start
    size = sum(file.stat().st_size for file in path.iterdir())
    messages = int(seconds * rate) + int(seconds * robot_bag.COMMAND_RATE)
    say(f"wrote {path.name}: {messages} messages, {size / 2**20:.0f} MiB in {wall:.0f} s")
    return {"bytes": size, "messages": messages, "write_seconds": wall}


def run(
    seconds: float = 600.0,
    storages: tuple[str, ...] = ("mcap", "sqlite3"),
    hour: bool = False,
    hour_seconds: float = 3600.0,
    hour_storages: tuple[str, ...] = ("mcap",),
    directory: Path | None = None,
    say: Any = print,
) -> dict[str, Any]:
    """The 10-minute bags (each storage: bag-info, fit, evaluate twice), then the hour's (bag-info, evaluate)."""
    results: list[Result] = []
    bags: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(dir=directory) as tmp:
        work = Path(tmp)
        plan = [(f"{seconds / 60:g} min {s}", seconds, s, 3, robot_bag.STATE_RATE) for s in storages]
        if hour:
            plan += [
                (f"{hour_seconds / 60:g} min 6 joints 1 kHz {s}", hour_seconds, s, 6, 1000.0) for s in hour_storages
            ]
        for label, length, storage, joints, rate in plan:
            path = work / label.replace(" ", "_")
            bags[label] = write(path, length, storage, joints, rate, say)
            samples = int(length * rate)
            test_from = samples - samples // 5 + 1
            commands = ("bag-info", "fit", "evaluate", "evaluate-fitted") if joints == 3 else ("bag-info", "evaluate")
            results += run_bag(label, path, robot_bag.flags(joints, rate), test_from, commands, work, say)
            shutil.rmtree(path)
    return {"bags": bags, "results": [asdict(r) | {"within_limit": r.within_limit} for r in results], **machine()}


def machine() -> dict[str, Any]:
    """When, on what commit, the machine's load."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent, check=False).stdout.strip()  # fmt: skip
    return {
        "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
        "commit": commit,
        "load_average": os.getloadavg(),
        "cpus": os.cpu_count(),
        "python": sys.version.split()[0],
    }


def _finite(value: float | None) -> float | None:
    """A figure, None where the command reported none (NaN: a diverged free run)."""
    return value if value is not None and math.isfinite(value) else None


def _db(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def markdown(report: dict[str, Any]) -> str:
    """One row per command: bag, command, wall and CPU time, peak RSS, samples, NMSEs, within 15 min."""
    lines = [
        "| bag | command | wall s | CPU s | peak RSS MB | samples | NMSE free run / one-step dB | < 15 min |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in report["results"]:
        samples = "-" if row["samples"] is None else f"{row['samples']:,}"
        nmse = "-" if row["nmse_db"] is None else f"{_free_run(row)} / {_db(row['nmse_db'])}"
        ok = (
            "yes"
            if row["within_limit"]
            else f"**no** (rc {row['returncode']}{': ' + row['detail'] if row['detail'] else ''})"
        )
        lines.append(
            f"| {row['bag']} | `{row['command']}` | {row['wall_s']:.1f} | {row['cpu_s']:.1f} | "
            f"{row['peak_rss_mb']:.0f} | {samples} | {nmse} | {ok} |"
        )
    return "\n".join(lines)


def _free_run(row: dict[str, Any]) -> str:
    if row["nmse_free_run_db"] is None and "diverged" in row["detail"]:
        return "diverged"
    return _db(row["nmse_free_run_db"])


#: wide(): a column per command
COLUMNS = ("bag-info", "fit", "evaluate, default model", "evaluate, fit's model")


def wide(report: dict[str, Any]) -> str:
    """A row per bag (bench/RESULTS.md's table): each command's wall s (CPU s), peak RSS, NMSE free run / one-step."""
    heads = list(COLUMNS)
    lines = ["| bag (messages, MiB) | samples paired | " + " | ".join(heads) + " |", "|---" * (len(heads) + 2) + "|"]
    for bag, info in report["bags"].items():
        rows = [row for row in report["results"] if row["bag"] == bag]
        cells = []
        for name in COLUMNS:
            row = next((r for r in rows if _column(r["command"]) == name), None)
            if row is None:
                cells.append("-")
                continue
            cell = f"{row['wall_s']:.0f} s ({row['cpu_s']:.0f} s CPU), {row['peak_rss_mb']:.0f} MB"
            if row["nmse_db"] is not None:
                cell += f", {_free_run(row)} / {_db(row['nmse_db'])} dB"
            if not row["within_limit"]:
                cell += f" **over 15 min or failed** ({row['detail']})"
            cells.append(cell)
        paired = {row["samples"] for row in rows} - {None}
        samples = " / ".join(f"{n:,}".replace(",", " ") for n in sorted(paired)) or "-"
        messages = f"{info['messages']:,}".replace(",", " ")
        lines.append(f"| {bag} ({messages}, {info['bytes'] / 2**20:.0f}) | {samples} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _column(command: str) -> str:
    if command.startswith("evaluate"):
        return "evaluate, fit's model" if "fit's model" in command else "evaluate, default model"
    return command.split()[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=600.0, help="the robot bag's length (500 Hz, 3 joints)")
    parser.add_argument("--storage", nargs="*", choices=("mcap", "sqlite3"), default=["mcap", "sqlite3"],
                        help="the 10-minute bag's storages (none: only the hour's)")  # fmt: skip
    parser.add_argument("--hour", action="store_true", help="also bag-info + evaluate on an hour at 1 kHz, 6 joints")
    parser.add_argument("--hour-seconds", type=float, default=3600.0, help="that recording's length (default 3600)")
    parser.add_argument("--hour-storage", nargs="+", choices=("mcap", "sqlite3"), default=["mcap"])
    parser.add_argument("--dir", type=Path, help="where to write the bags (default: the temporary directory)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--wide", action="store_true", help="a row per bag (bench/RESULTS.md's table)")
    args = parser.parse_args()

    def say(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    report = run(args.seconds, tuple(args.storage), args.hour, args.hour_seconds, tuple(args.hour_storage), args.dir,
                 say)  # fmt: skip
    if args.json:
        print(json.dumps(report, indent=1, allow_nan=False))
        return 0
    load = ", ".join(f"{x:.2f}" for x in report["load_average"])
    print(f"{report['date']}, commit {report['commit']}, load average {load} ({report['cpus']} CPUs)\n")
    print(wide(report) if args.wide else markdown(report))
    return 0 if all(row["within_limit"] for row in report["results"]) else 1


if __name__ == "__main__":
    sys.exit(main())
