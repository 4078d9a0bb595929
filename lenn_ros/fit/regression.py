"""Least squares for the selection: FROLS's ranking of a dictionary's terms, and each block's fold of it.

Orthogonal forward regression ranks a dictionary's terms by error-reduction ratio
(Billings' FROLS) from the normal equations alone (:func:`forward_regression_gram`), and
:class:`Folds` solves every prefix of the ranking without each block of the training
samples (each fold's system the total less that block's rows). Apart from the selection's
judging by simulation, which is what sets ``fit`` apart from FROLS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: relative ridge on the normal equations (numerically singular columns must not break a solve)
RIDGE = 1e-10


def forward_regression(features: np.ndarray, targets: np.ndarray, max_terms: int) -> tuple[list[int], list[float]]:
    """Orthogonal forward regression: columns in order of error-reduction ratio.

    Every step scores all remaining columns by the share of the target's energy they
    explain beyond the terms already chosen (Billings' ERR); see :func:`forward_regression_gram`.
    Returns (column order, ERR of each).
    """
    features = np.asarray(features, dtype=np.float64)
    d = np.asarray(targets, dtype=np.float64)
    return forward_regression_gram(features.T @ features, features.T @ d, float(d @ d), max_terms)


def forward_regression_gram(
    gram: np.ndarray, moment: np.ndarray, energy: float, max_terms: int
) -> tuple[list[int], list[float]]:
    """:func:`forward_regression` from the normal equations: Gram-Schmidt in the columns' inner products.

    With A[s, j] = <q_s, f_j> for the orthonormalised chosen columns q_s, a column's
    part orthogonal to them has squared norm G_jj - sum_s A[s, j]^2 and inner product
    with the target c_j - sum_s A[s, j] <q_s, d>: each step costs (columns x chosen)
    instead of a pass over the N samples, and one Gram matrix serves a family's nested
    dictionaries (degree 1 is the start of degree 2's, which is the start of degree 3's).
    """
    n_columns = gram.shape[0]
    energy = energy or 1.0
    diagonal = np.diag(gram).copy()
    alive = diagonal > 1e-12 * max(float(diagonal.max(initial=0.0)), 1e-300)
    residual = diagonal.copy()
    projection = np.array(moment, dtype=np.float64, copy=True)
    inner = np.zeros((min(max_terms, n_columns), n_columns))
    chosen: list[int] = []
    ratios: list[float] = []
    for step in range(min(max_terms, n_columns)):
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.where(alive & (residual > 1e-10 * diagonal), projection**2 / (residual * energy), -1.0)
        best = int(np.argmax(err))
        if err[best] <= 0.0:
            break
        chosen.append(best)
        ratios.append(float(err[best]))
        alive[best] = False
        norm = math.sqrt(residual[best])
        row = (gram[best] - inner[:step, best] @ inner[:step]) / norm
        inner[step] = row
        along = projection[best] / norm
        residual -= row**2
        projection -= row * along
    return chosen, ratios


@dataclass
class Folds:
    """Normal equations of every block's rows, so each fold's system is the total minus one block."""

    blocks: list[tuple[int, int]]
    gram: np.ndarray  # over all valid rows
    moment: np.ndarray
    block_grams: list[np.ndarray]
    block_moments: list[np.ndarray]

    @classmethod
    def of(
        cls, features: np.ndarray, targets: np.ndarray, rows: np.ndarray, blocks, warm_up: int,
        normal: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Folds:  # fmt: skip
        """``rows``: the sample each row predicts; a block drops the rows predicting its samples and the
        ``warm_up`` after it (their regressors hold the block's measured outputs). ``normal``: (Gram, moment)
        of all rows when already at hand (the design's, cut to these columns: half the work otherwise)."""
        grams, moments = [], []
        for a, b in blocks:
            low, high = np.searchsorted(rows, [a, b + warm_up])  # rows come in the order of what they predict
            f = features[low:high]
            grams.append(f.T @ f)
            moments.append(f.T @ targets[low:high])
        gram, moment = normal if normal is not None else (features.T @ features, features.T @ targets)
        return cls(list(blocks), gram, moment, grams, moments)

    def __post_init__(self) -> None:
        # every fold's system at once: the total less each block
        self._fold_grams = self.gram[None] - np.array(self.block_grams)
        self._fold_moments = self.moment[None] - np.array(self.block_moments)
        self._eye = np.eye(len(self.gram))  # sliced for each prefix: a prefix is scored in tens of microseconds

    def all_weights(self, m: int) -> np.ndarray | None:
        """Every fold's least-squares weights of the first ``m`` columns, one row per fold, in one solve."""
        g = self._fold_grams[:, :m, :m]
        ridge = RIDGE * np.maximum(np.trace(g, axis1=1, axis2=2) / m, 1e-300)
        try:
            weights = np.linalg.solve(g + ridge[:, None, None] * self._eye[:m, :m], self._fold_moments[:, :m, None])
        except np.linalg.LinAlgError:
            return None
        return weights[:, :, 0]

    def weights(self, m: int, fold: int | None = None) -> np.ndarray | None:
        """Least-squares weights of the first ``m`` columns without block ``fold`` (None: all rows)."""
        g, v = self.gram[:m, :m], self.moment[:m]
        if fold is not None:
            g, v = g - self.block_grams[fold][:m, :m], v - self.block_moments[fold][:m]
        ridge = RIDGE * max(float(np.trace(g)) / max(m, 1), 1e-300)
        try:
            return np.linalg.solve(g + ridge * np.eye(m), v)
        except np.linalg.LinAlgError:
            return None
