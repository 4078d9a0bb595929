"""What live RLS does to a model refined on simulation error: its free run before and after (issue 17).

    python bench/live_drift.py        # ~30 s

``fit`` refines its weights on simulation error; the identifier node then learns live by
RLS, which minimises the one-step error. Where the two optima differ (noisy regressors: the
equation-error bias the refinement removes), live learning pulls the model back toward
least squares. Each row: ``fit`` on the build part, the free run of the second half of the
test part with the fitted weights, then the same identifier run with learning over every
sample before that half (as a node would have learnt them) and the same free run again.
"""

from __future__ import annotations

import numpy as np
from peer_narx import DATA
from plant_study import axis_p2p

from lenn_ros.core.metrics import nmse_db
from lenn_ros.fit.data import Data
from lenn_ros.fit.procedure import fit


def _row(name: str, u: np.ndarray, y: np.ndarray, start: int) -> str:
    identifier = fit(Data(u, y, name), start + 1).identifier
    half = start + (len(y) - start) // 2

    before = nmse_db(y[half:], identifier.free_run(u, y, half))
    identifier.run(u[:half], y[:half], learn=True)
    return f"| {name} | {before:.1f} | {nmse_db(y[half:], identifier.free_run(u, y, half)):.1f} |"


def main() -> int:
    print("| data | free-run NMSE dB, fitted weights | after live RLS over the samples before |")
    print("|---|---|---|")
    table = np.genfromtxt(DATA / "silverbox_multisine.csv", delimiter=",", names=True)
    print(_row("silverbox_multisine", np.asarray(table["u"], float), np.asarray(table["y"], float), 65_062))
    u, y = axis_p2p(1)
    print(_row("plant_study axis-p2p, seed 1", u, y, len(y) * 2 // 3), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
