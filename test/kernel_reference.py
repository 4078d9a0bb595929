"""The functional-link kernels run on fixed inputs, for comparing compiled and pure-Python runs.

Run as a script under ``NUMBA_DISABLE_JIT=1`` it is the pure-Python reference: every
kernel and every helper it calls is plain Python then. (A compiled kernel's
``.py_func`` is not: it calls its helpers compiled.)
"""

from __future__ import annotations

import sys

import numpy as np

from lenn_ros.core import learning_rules

SOLVERS = ("sgd", "nlms", "rls")


def run(solver: str) -> tuple[np.ndarray, np.ndarray]:
    """Learned weights and a-priori outputs after 300 updates from a fixed start."""
    rng = np.random.default_rng(1)
    features = np.ascontiguousarray(rng.uniform(-1, 1, (300, 6)))
    targets = rng.uniform(-0.5, 0.5, 300)
    weights = np.full(6, 0.1)
    y = np.empty(300)
    if solver == "sgd":
        learning_rules.functional_link_sgd(
            weights, np.zeros(6), features, targets, np.zeros(6, np.int64), 1, 0.1, 0.5, True, 1.0, True, y
        )
    elif solver == "nlms":
        learning_rules.functional_link_nlms(weights, features, targets, 0.5, 1e-6, True, y)
    else:
        learning_rules.functional_link_rls(
            weights, np.eye(6) * 100.0, features, targets, 0.99, 1e6, True, y, np.empty(0)
        )
    return weights, y


if __name__ == "__main__":
    arrays = {}
    for solver in SOLVERS:
        arrays[f"{solver}_w"], arrays[f"{solver}_y"] = run(solver)
    np.savez(sys.argv[1], **arrays)
