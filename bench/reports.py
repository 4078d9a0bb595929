"""fit's and evaluate's reports on the shared records, to compare byte for byte before and after a restructure.

    python bench/reports.py snapshot /tmp/before          # at the old commit
    python bench/reports.py snapshot /tmp/after           # at the new one
    python bench/reports.py compare /tmp/before /tmp/after

Runs the real ``lenn-ros`` commands (subprocesses) on: four shared data sets (the DaISy
robot arm, ball and beam, heat exchanger, the buck converter with its validation record
appended), four plants of ``plant_study.py`` (tanks, heater, positioning axis,
Wiener-Hammerstein), a slice of the industrial robot (several channels), the bags that
``import-csv`` makes of two of them (``fit BAG``, and ``evaluate BAG`` with the params
``fit -o`` wrote) and the four recorded example bags of ``bags/``. Each command's
output (text, and ``--json`` where it has one) is written to one file with timings
and the snapshot's own folder masked, so two snapshots differ only where a figure or
a sentence does. ``compare`` prints a unified diff per differing file and exits 1 if any.
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = next(p / "shared" / "data" for p in REPO.parents if (p / "shared" / "data").is_dir())
LENN = [sys.executable, "-m", "lenn_ros.cli"]
#: Timings in text reports ("0.41 s", "took 12.3 s") and JSON keys that hold one.
_SECONDS = re.compile(r"\b\d+(\.\d+)? s\b|peak memory \d+ MiB")
_TIME_KEYS = ("seconds", "time_s", "fit_seconds", "elapsed_s")


def _write_csv(path: Path, columns: dict[str, np.ndarray]) -> Path:
    names = list(columns)
    table = np.column_stack([np.asarray(columns[name], dtype=float) for name in names])
    np.savetxt(path, table, delimiter=",", header=",".join(names), comments="", fmt="%.17g")
    return path


def records(work: Path) -> list[tuple[str, Path, list[str]]]:
    """(name, CSV, fit's flags) of every record fitted from a file."""
    sys.path.insert(0, str(REPO / "bench"))
    import plant_study

    found = []
    for name, u, y in (
        ("daisy_robot-arm", "u", "y"),
        ("daisy_ball-and-beam", "u", "y"),
        ("daisy_exchanger", "q", "th"),
    ):
        rows = sum(1 for line in (DATA / f"{name}.csv").read_text().splitlines()[1:] if line.strip())
        found.append((name, DATA / f"{name}.csv", ["--u", u, "--y", y, "--test-from", str(rows * 2 // 3 + 1)]))
    ident = np.genfromtxt(DATA / "buck_converter_id.csv", delimiter=",", names=True)
    valid = np.genfromtxt(DATA / "buck_converter_valid.csv", delimiter=",", names=True)
    buck = _write_csv(
        work / "buck.csv", {"u": np.r_[ident["input"], valid["input"]], "y": np.r_[ident["y"], valid["y"]]}
    )
    found.append(("buck_converter", buck, ["--test-from", str(len(ident) + 1)]))
    for plant, seed in (("tanks", 0), ("heater", 1), ("axis", 0), ("wiener-hammerstein", 0)):
        u, y = plant_study.PLANTS[plant](seed)
        path = _write_csv(work / f"{plant}.csv", {"u": u, "y": y})
        found.append((f"{plant}-{seed}", path, ["--test-from", str(len(y) * 2 // 3 + 1)]))
    robot = np.genfromtxt(DATA / "industrial_robot.csv", delimiter=",", names=True)[:3000]
    path = _write_csv(work / "robot.csv", {name: robot[name] for name in ("u1", "u2", "y1", "y2")})
    found.append(("robot-2x2", path, ["--u", "u1", "--u", "u2", "--y", "y1", "--y", "y2", "--test-from", "2401"]))
    return found


def _run(command: list[str], work: Path) -> str:
    env = {**os.environ, "PYTHONPATH": str(REPO), "NUMBA_NUM_THREADS": os.environ.get("NUMBA_NUM_THREADS", "2")}
    done = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True)
    text = f"$ {' '.join(command[3:])}\nexit {done.returncode}\n--- stdout\n{done.stdout}--- stderr\n{done.stderr}"
    return _masked(text, work)


def _masked(text: str, work: Path) -> str:
    text = text.replace(str(work), "<work>").replace(str(REPO), "<repo>")
    text = _SECONDS.sub("<s>", text)
    try:  # a JSON report: drop its timing keys before comparing
        start = text.index("--- stdout\n") + len("--- stdout\n")
        end = text.index("--- stderr\n")
        report = json.loads(text[start:end])
    except ValueError:
        return text
    return text[:start] + json.dumps(_without_times(report), indent=1, sort_keys=True) + "\n" + text[end:]


def _without_times(value):
    if isinstance(value, dict):
        return {key: _without_times(item) for key, item in value.items() if key not in _TIME_KEYS}
    if isinstance(value, list):
        return [_without_times(item) for item in value]
    return value


def snapshot(out: Path) -> int:
    out.mkdir(parents=True, exist_ok=True)
    work = out / "work"
    work.mkdir(exist_ok=True)
    outputs: dict[str, str] = {}
    for name, path, flags in records(work):
        outputs[f"fit-{name}.txt"] = _run([*LENN, "fit", str(path), *flags], work)
        outputs[f"fit-{name}.json"] = _run([*LENN, "fit", str(path), *flags, "--json"], work)
        print(f"fit {name}", flush=True)
        if name not in ("daisy_robot-arm", "tanks-0", "robot-2x2"):
            continue
        model, bag = work / f"{name}-model", work / f"{name}-bag"
        _run([*LENN, "fit", str(path), *flags, "-o", str(model)], work)
        columns = ["--u", "u", "--y", "y"] if "--u" not in flags else flags[: flags.index("--test-from")]
        test_from = flags[flags.index("--test-from") + 1]
        _run([*LENN, "import-csv", str(path), *columns, "--dt", "0.01", "--test-from", test_from, "-o", str(bag)], work)
        outputs[f"fit-bag-{name}.txt"] = _run([*LENN, "fit", str(bag)], work)
        for suffix, extra in (("txt", []), ("json", ["--json"])):
            outputs[f"evaluate-{name}.{suffix}"] = _run(
                [*LENN, "evaluate", str(bag), "--params", str(model / "params.yaml"), *extra], work
            )
        print(f"bag {name}", flush=True)
    for example in sorted((REPO / "bags").iterdir()):
        for suffix, extra in (("txt", []), ("json", ["--json"])):
            outputs[f"evaluate-{example.name}.{suffix}"] = _run([*LENN, "evaluate", str(example), *extra], work)
        print(f"evaluate {example.name}", flush=True)
    for file, text in outputs.items():
        (out / file).write_text(text)
    print(f"{len(outputs)} reports in {out}")
    return 0


def compare(before: Path, after: Path) -> int:
    names = sorted({p.name for p in before.glob("*.*")} | {p.name for p in after.glob("*.*")})
    differing = 0
    for name in names:
        old = (before / name).read_text().splitlines(keepends=True) if (before / name).exists() else []
        new = (after / name).read_text().splitlines(keepends=True) if (after / name).exists() else []
        if old != new:
            differing += 1
            sys.stdout.writelines(difflib.unified_diff(old, new, f"before/{name}", f"after/{name}", n=1))
    print(
        f"{len(names) - differing} of {len(names)} reports identical" + (f", {differing} differ" if differing else "")
    )
    return 1 if differing else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    verbs = parser.add_subparsers(dest="verb", required=True)
    verbs.add_parser("snapshot").add_argument("out", type=Path)
    pair = verbs.add_parser("compare")
    pair.add_argument("before", type=Path)
    pair.add_argument("after", type=Path)
    args = parser.parse_args()
    return snapshot(args.out) if args.verb == "snapshot" else compare(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())
