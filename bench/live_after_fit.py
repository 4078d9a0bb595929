"""Live learning from a fitted model: does the free run survive it? (issue 42)

    python bench/live_after_fit.py                 # every case
    python bench/live_after_fit.py --only exchanger,joint-change

For each record: ``lenn-ros fit`` builds a model on the training part (its free-run figure on
the test part is the reference), then ``lenn-ros evaluate`` runs the identifier over the whole
record with fit's params, learning from fit's weights on the training samples as the node would,
and scores the test part:

- ``guard``: fit's params as written (``free_run_guard: true``);
- ``plain``: the same with ``free_run_guard: false`` (live RLS learning as before the guard);
- ``frozen``: ``learning: false`` (fit's model untouched; equals fit's figure).

The records: the shared real data sets (one output each; their README's splits), a robot's own
10-minute bag (``bench/robot_bag.py``, three seeds) and a plant that changes after the fit: the
friction joint of ``bench/robot_defaults.py`` (load 4 -> 5 N m), fitted on 120 s before the
change, evaluated over 120 s before and 180 s after it, tested on the last 30 s (there the frozen
model is wrong, and learning must follow the plant).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
ROBOT_FLAGS = [
    "--u", "/arm_controller/commands", "--u-field", "data[1]", "--y", "/joint_states",
    "--y-field", "position[elbow]", "--sample-period", "0.002",
]  # fmt: skip


def run(*args: str) -> str:
    done = subprocess.run(args, capture_output=True, text=True, check=False)
    if done.returncode:
        raise RuntimeError(f"{' '.join(args)}: {done.stderr.strip().splitlines()[-1:]}")
    return done.stdout


def csv_case(work: Path, name: str, file: str, u: str, y: str, dt: float, test_from: int) -> tuple[Path, list[str]]:
    """A shared CSV imported as a bag with its test start (import-csv), read as it was written."""
    bag = work / name
    if bag.exists():  # (--work kept from an earlier run)
        return bag, []
    run("lenn-ros", "import-csv", str(DATA / file), "--u", u, "--y", y, "--dt", str(dt),
        "--test-from", str(test_from), "-o", str(bag))  # fmt: skip
    return bag, []


def robot_case(work: Path, seed: int) -> tuple[Path, list[str]]:
    """A robot's own 10-minute log (rosbags' writer), tested from sample 240 001 (the last fifth)."""
    bag = work / f"robot{seed}"
    if not bag.exists():
        run(sys.executable, str(Path(__file__).with_name("robot_bag.py")), str(bag), "--seconds", "600",
            "--seed", str(seed))  # fmt: skip
    return bag, [*ROBOT_FLAGS, "--test-from", "240001"]


def joint_change_case(work: Path) -> tuple[Path, list[str], Path]:
    """(bag to evaluate, flags, bag to fit): the friction joint at 100 Hz, its load changed after the fit."""
    sys.path.insert(0, str(Path(__file__).parent))
    from robot_defaults import joint

    u_before, y_before = joint(0.01, 120.0, seed=1)
    u, y = joint(0.01, 300.0, seed=1, change_at=120.0)
    files = []
    for name, (uu, yy), test in (("joint-fit", (u_before, y_before), 9601), ("joint-change", (u, y), 27001)):
        files.append(work / name)
        if files[-1].exists():
            continue
        csv = work / f"{name}.csv"
        np.savetxt(csv, np.column_stack([uu, yy]), delimiter=",", header="u,y", comments="")
        run("lenn-ros", "import-csv", str(csv), "--u", "u", "--y", "y", "--dt", "0.01", "--test-from", str(test),
            "-o", str(work / name))  # fmt: skip
    return files[1], [], files[0]


def free_run_db(output: str) -> float:
    d = json.loads(output)
    return float(d["nmse_free_run_db"] if "nmse_free_run_db" in d else d["channels"][next(iter(d["channels"]))][
        "nmse_free_run_db"])  # fmt: skip


def variant(params: Path, name: str, **values: object) -> Path:
    text = yaml.safe_load(params.read_text())
    text["/**"]["ros__parameters"].update(values)
    path = params.with_name(f"{name}.yaml")
    path.write_text(yaml.safe_dump(text, sort_keys=False))
    return path


def case(work: Path, name: str, bag: Path, flags: list[str], fit_bag: Path | None = None) -> dict:
    model = work / f"{name}-model"
    started = time.perf_counter()
    if (model / "fit.json").exists() and (model / "params.yaml").exists():  # (--work kept from an earlier run)
        fitted = json.loads((model / "fit.json").read_text())
    else:
        fitted = json.loads(run("lenn-ros", "fit", str(fit_bag or bag), *flags, "--json", "-o", str(model)))
    fit_seconds = time.perf_counter() - started
    params = model / "params.yaml"
    row = {"case": name, "fit": fitted["nmse_free_run_db"], "fit_s": fit_seconds}
    for label, path in (
        ("guard", params),
        ("plain", variant(params, "plain", free_run_guard=False)),
        ("frozen", variant(params, "frozen", learning=False)),
    ):
        started = time.perf_counter()
        out = run("lenn-ros", "evaluate", str(bag), *flags, "--params", str(path), "--json")
        row[f"{label}_s"] = time.perf_counter() - started
        row[label] = free_run_db(out)
        if label == "guard":
            counters = json.loads(out)["counters"]
            row["adopted"] = f"{counters.get('guard_adopted', 0)}/{counters.get('guard_checks', 0)}"
    print(
        f"| {name} | {row['fit']:.2f} | {row['guard']:.2f} | {row['plain']:.2f} | {row['frozen']:.2f} | "
        f"{row['guard'] - row['fit']:+.2f} | {row['adopted']} | {row['guard_s']:.0f} / {row['plain_s']:.0f} |",
        flush=True,
    )
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="comma-separated case names")
    parser.add_argument("--work", type=Path, default=None, help="keep the bags and models here")
    args = parser.parse_args()
    only = set(filter(None, args.only.split(",")))
    work = args.work or Path(tempfile.mkdtemp(prefix="live_after_fit_"))
    work.mkdir(parents=True, exist_ok=True)
    cases = {
        "silverbox": lambda: csv_case(work, "silverbox", "silverbox_multisine.csv", "u", "y", 1 / 610.35, 65063),
        "bouc-wen": lambda: csv_case(work, "bouc-wen", "bouc_wen_multisine.csv", "u", "y", 1 / 750, 40961),
        "exchanger": lambda: csv_case(work, "exchanger", "daisy_exchanger.csv", "q", "th", 0.1, 2668),
        "robot-arm": lambda: csv_case(work, "robot-arm", "daisy_robot-arm.csv", "u", "y", 1.0, 684),
        "robot-bag-1": lambda: robot_case(work, 1),
        "robot-bag-2": lambda: robot_case(work, 2),
        "robot-bag-3": lambda: robot_case(work, 3),
    }
    print("free-run NMSE (dB) on the test part: fit's model, then after evaluate's live learning from it")
    print()
    print("| record | fit | guard | plain | frozen | guard - fit | adopted / checks | evaluate s (guard / plain) |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for name, make in cases.items():
        if only and name not in only:
            continue
        bag, flags = make()
        rows.append(case(work, name, bag, flags))
    if not only or "joint-change" in only:
        bag, flags, fit_bag = joint_change_case(work)
        rows.append(case(work, "joint-change", bag, flags, fit_bag))
    (work / "rows.json").write_text(json.dumps(rows, indent=1))
    print(f"\n(work in {work})")


if __name__ == "__main__":
    main()
