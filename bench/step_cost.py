"""The node's per-sample cost for one channel, here and at a reference commit, in one run.

    python bench/step_cost.py                     # against 325f0e8 (before the one-model merge)
    python bench/step_cost.py --ref COMMIT --rounds 7 --samples 20000

Why: issue 19 merged the single- and several-channel paths and asks that the
single-channel per-sample cost does not rise. A ratio means something only when both
sides are timed on the same machine in the same minutes, so the reference commit is
checked out into a temporary git worktree and the two are timed in alternating
subprocesses (A B A B ...), each a fresh interpreter with its numba kernels compiled
before timing. What is timed is what the node does per message pair:
``Session.offer(U)`` then ``Session.offer(Y)`` in ``sequence`` pairing, learning on,
and the model's own ``Identifier.step`` without the session around it, for three
single-channel models (the default LeNN by SGD, the robot settings by RLS,
the paper's Ex. 1 preset). Each subprocess reports the median of its 1 000-sample
blocks; the table gives the median over rounds, their spread and the ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
REFERENCE = "325f0e8"  # main when issue 19 was filed: two paths, the per-sample cost to keep

#: the models timed: (name, parameter overrides on the identifier's defaults)
#: (the structure is pinned: the defaults themselves changed between the commits)
PINNED = {"example": 0, "y_lags": 2, "u_lags": 2, "order": 4, "cross_degree": 0, "y_scale": 3.0, "u_scale": 1.5}
CASES = {
    "lenn sgd, 2+2 lags, order 4": {**PINNED, "solver": "sgd", "output": "tanh"},
    "lenn rls, 2+2 lags, order 4 (robot settings)": {
        **PINNED,
        "solver": "rls",
        "output": "linear",
        "forgetting": 0.999,
    },
    "lenn Ex. 1 preset": {"example": 1},
}

#: runs inside the subprocess, against whichever lenn_ros is first on sys.path
PROBE = r"""
import json, sys, time
import numpy as np
from lenn_ros import config
from lenn_ros.core.pairing import U, Y
from lenn_ros.session import Session, SessionConfig
try:
    from lenn_ros.service.building import build_identifier
except ImportError:  # a reference commit from before the factory moved to the service layer
    build_identifier = config.build_identifier

overrides, samples = json.loads(sys.argv[1]), int(sys.argv[2])
example = overrides.get("example", 0)
table = config.identifier_parameters(example, "lenn") + config.NODE_PARAMETERS
values = {p.name: p.default for p in table}
values.update({k: v for k, v in overrides.items() if k != "example"})
values["example"] = example
identifier = build_identifier(values, "lenn")
session = Session(identifier, SessionConfig.from_values(values, follow_test_start=False, learning=True))
rng = np.random.default_rng(0)
u = np.sin(2 * np.pi * np.arange(samples + 2000) / 250) + 0.3 * rng.uniform(-1, 1, samples + 2000)
y = np.zeros_like(u)
for k in range(1, len(u) - 1):
    y[k + 1] = 0.3 * y[k] + 0.6 * y[k - 1] + 0.6 * np.sin(np.pi * u[k]) + 0.3 * np.sin(3 * np.pi * u[k])
y += 0.01 * rng.standard_normal(len(y))
t = 0.0
for k in range(2000):  # compile and settle
    t += 0.001
    session.offer(U, float(u[k]), t, sequence=k + 1)
    session.offer(Y, float(y[k]), t, sequence=k + 1)
blocks = []
for start in range(2000, 2000 + samples, 1000):
    begin = time.perf_counter()
    for k in range(start, start + 1000):
        t += 0.001
        session.offer(U, float(u[k]), t, sequence=k + 1)
        session.offer(Y, float(y[k]), t, sequence=k + 1)
    blocks.append((time.perf_counter() - begin) / 1000 * 1e6)
counters = session.status()["counters"]
model_alone = build_identifier(values, "lenn")  # the model's own step, without the session (scales given)
for k in range(2000):
    model_alone.step(k + 1, float(u[k]), float(y[k]), True)
steps = []
for start in range(2000, 2000 + samples, 1000):
    begin = time.perf_counter()
    for k in range(start, start + 1000):
        model_alone.step(k + 1, float(u[k]), float(y[k]), True)
    steps.append((time.perf_counter() - begin) / 1000 * 1e6)
print(json.dumps({"us_per_sample": float(np.median(blocks)), "learned": counters["learned"],
                  "weights": int(identifier.model.n_weights), "step_us": float(np.median(steps))}))
"""


def _probe(tree: Path, overrides: dict, samples: int) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, "-c", PROBE, json.dumps(overrides), str(samples)],
        cwd=tree, env=env, capture_output=True, text=True, check=False,
    )  # fmt: skip
    if done.returncode:
        raise SystemExit(f"step_cost: the probe failed in {tree}: {done.stderr.strip().splitlines()[-1]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ref", default=REFERENCE, help="the commit to compare with (default: %(default)s)")
    parser.add_argument("--rounds", type=int, default=5, help="alternating A/B subprocess pairs per model")
    parser.add_argument("--samples", type=int, default=20_000, help="timed samples per subprocess")
    parser.add_argument("--json", action="store_true", help="one JSON object instead of a markdown table")
    args = parser.parse_args()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()  # fmt: skip
    if subprocess.run(["git", "status", "--porcelain", "lenn_ros"], cwd=ROOT, capture_output=True, text=True,
                      check=True).stdout.strip():  # fmt: skip
        head += "+edits"  # the working tree is timed, not the commit
    with tempfile.TemporaryDirectory(prefix="step_cost_") as scratch:
        reference = Path(scratch) / "ref"
        subprocess.run(["git", "worktree", "add", "--detach", str(reference), args.ref], cwd=ROOT,
                       capture_output=True, check=True)  # fmt: skip
        try:
            rows = {}
            for name, overrides in CASES.items():
                here, there, here_step, there_step = [], [], [], []
                for round_ in range(args.rounds):
                    print(f"{name}: round {round_ + 1}/{args.rounds}", file=sys.stderr, flush=True)
                    old, new = _probe(reference, overrides, args.samples), _probe(ROOT, overrides, args.samples)
                    if (old["weights"], old["learned"]) != (new["weights"], new["learned"]):
                        raise SystemExit(f"step_cost: {name} is not the same model at both commits: {old} / {new}")
                    there.append(old["us_per_sample"])
                    here.append(new["us_per_sample"])
                    there_step.append(old["step_us"])
                    here_step.append(new["step_us"])
                rows[f"{name}: Session.offer (u, y_p)"] = {"ref": there, "head": here}
                rows[f"{name}: Identifier.step"] = {"ref": there_step, "head": here_step}
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(reference)], cwd=ROOT, check=False)
    if args.json:
        print(json.dumps({"ref": args.ref, "head": head, "rows": rows}, indent=1))
        return 0
    print(f"| model | {args.ref} us/sample | {head} us/sample | ratio {head}/{args.ref} |")
    print("|---|---|---|---|")
    for name, row in rows.items():
        ref, now = statistics.median(row["ref"]), statistics.median(row["head"])
        print(f"| {name} | {ref:.2f} ({min(row['ref']):.2f}-{max(row['ref']):.2f}) | "
              f"{now:.2f} ({min(row['head']):.2f}-{max(row['head']):.2f}) | {now / ref:.3f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
