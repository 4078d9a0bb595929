"""Refinement on simulation error, with its length chosen by the held-out blocks.

Least squares gives the best one-step predictor, which is not the best simulator when
the data are noisy (the regressors carry the noise: equation-error bias) or when a
small one-step error compounds over a long free run. Levenberg-Marquardt on the
free-run error itself removes that bias; its Jacobian comes from one compiled free run
that carries the outputs' sensitivities to the weights along (forward sensitivity).

Refining on the training samples always lowers the training simulation error, and on
a small record it fits the noise as surely (a 680-sample robot arm refined 20 times
simulated its test part worse). So the number of iterations is chosen like the
structure: on every block of :func:`~lenn_ros.fit.record.fold_blocks`, the weights
fitted without that block are refined on the others (at most MAX_FOLD_TRAINING of them,
the nearest it) and the block's own free run is scored after every iteration; the count
with the lowest pooled score over all blocks wins, and zero, no refinement, is one of
the counts. Only then are the weights of all training samples refined that many times,
and the latest iterations undone if the refined model fails the selection's soundness
check. What was done is reported either way. ``fit`` refines all samples of the candidate
it is about to choose only (:func:`blocks_choice` scores the others).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lenn_ros.core import term_kernels as kernels
from lenn_ros.core.free_run import FREE_RUN_DIVERGENCE_BOUND
from lenn_ros.fit.record import Record, fold_blocks, runs
from lenn_ros.fit.selection import Candidate
from lenn_ros.fit.soundness import level_free, output_rows, soundness_problem
from lenn_ros.fit.termmodel import TermModel

#: most Levenberg-Marquardt iterations tried per fold (and then on all samples)
ITERATIONS = 15
#: a fold stops once its held-out error has not improved for this many iterations
PATIENCE = 6
#: the held-out blocks of a long record are simulated on at most this many samples each
#: (the refinement's cost is iterations x weights x samples free-run steps)
MAX_REFINED_SAMPLES = 30_000
#: samples each fold refines on, the nearest its block: the count the blocks choose is as well determined by
#: 12 000 samples as by 32 000 (Bouc-Wen: the same 15 iterations, the same test figure; the Silverbox: 9
#: iterations for 15, the same test figure to 4 digits), at a third and a sixth of the time
MAX_FOLD_TRAINING = 12_000


@dataclass
class Refinement:
    """What the refinement did (reported by ``fit``)."""

    iterations: int  # iterations run on all training samples (the count the blocks chose)
    tried: int  # iterations tried per block
    rmse_blocks_before: float  # pooled held-out free-run RMSE without refinement
    rmse_blocks_after: float  # ... after the chosen number of iterations
    rmse_training_before: float = math.nan  # free-run RMSE over all training samples
    rmse_training_after: float = math.nan
    unsound: str = ""  # iterations the blocks chose but undone, and why (:func:`_soundest`)
    applied: bool = True  # False: the blocks' choice only, the weights left as least squares fitted them

    def as_dict(self) -> dict:
        return {k: (round(v, 9) if isinstance(v, float) and math.isfinite(v) else v) for k, v in self.__dict__.items()}


def residuals(
    model: TermModel, record: Record, pieces: list[tuple[int, int]], weights: np.ndarray
) -> np.ndarray | None:
    """Measured minus simulated over the pieces (each from its measured warm-up), None if any diverged."""
    out = []
    warm = model.warm_up
    for start, stop in pieces:
        for a, b in runs(start, stop, record.breaks):
            if b - a <= warm:
                continue
            y_sim, _, diverged_at = model.free_run(record.values[a:b], warm, weights)
            if diverged_at >= 0:
                return None
            out.append(record.y[a + warm : b] - y_sim)
    return np.concatenate(out) if out else np.zeros(0)


def levenberg_marquardt(
    model: TermModel,
    record: Record,
    pieces: list[tuple[int, int]],
    weights: np.ndarray,
    iterations: int,
    after_each=None,
) -> np.ndarray:
    """Up to ``iterations`` LM steps on the free-run error over ``pieces``; ``after_each(weights)`` per step.

    Stops early when no damping lowers the cost (a minimum, or a model on the edge of
    stability, where the linearisation means nothing), or when ``after_each`` returns True.
    """
    weights = np.array(weights, dtype=np.float64, copy=True)
    frozen = pass_through(model.with_weights(weights))
    found = jacobian(model, record, pieces, weights)
    if found is None or not len(found[0]):
        return weights
    residual, slope = found
    cost, damping = float(residual @ residual), 1e-3
    for iteration in range(iterations):
        if iteration:
            found = jacobian(model, record, pieces, weights)
            if found is None:
                break
            residual, slope = found
        slope[:, frozen] = 0.0  # the step leaves them as they are
        step = _damped_step(model, record, pieces, weights, slope, residual, cost, damping)
        if step is None:
            break
        weights, residual, cost, damping = step
        if after_each is not None and after_each(weights):
            break
    return weights


def pass_through(model: TermModel) -> np.ndarray:
    """Mask of the weights the refinement leaves alone: a :func:`~lenn_ros.fit.soundness.level_free` model's
    ``y1`` at exactly the output's scale. Refined, it would leak or run away by a hair and the model would
    no longer integrate exactly, which the selection chose it for (and judged it as)."""
    if not level_free(model):
        return np.zeros(len(model.weights), dtype=bool)
    return output_rows(model)


def jacobian(
    model: TermModel, record: Record, pieces: list[tuple[int, int]], weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """(measured - simulated, d simulated / d w) over the pieces, by forward sensitivity in one compiled
    pass per run (:func:`~lenn_ros.core.term_kernels.free_run_jacobian`); None if a run diverges."""
    warm = model.warm_up
    source, lag, offset, scale = model.layout.arrays()
    residual_parts, slope_parts = [], []
    for start, stop in pieces:
        for a, b in runs(start, stop, record.breaks):
            if b - a <= warm:
                continue
            values = np.array(record.values[a:b], copy=True)
            slope = np.zeros((b - a - warm, len(weights)))
            _, diverged_at = kernels.free_run_jacobian(
                values, warm, model.layout.lags, source, lag, offset, scale, model.exponents, model.factors,
                np.ascontiguousarray(weights, dtype=np.float64), kernels.BASIS_CODES[model.basis],
                FREE_RUN_DIVERGENCE_BOUND, slope,
            )  # fmt: skip
            if diverged_at >= 0:
                return None
            residual_parts.append(record.y[a + warm : b] - values[warm:, 0])
            slope_parts.append(slope)
    if not residual_parts:
        return np.zeros(0), np.zeros((0, len(weights)))
    return np.concatenate(residual_parts), np.vstack(slope_parts)


def _damped_step(model, record, pieces, weights, jacobian, residual, cost, damping):
    """One LM step: (weights, residual, cost, damping) after it, or None if no damping lowers the cost, or
    if the sensitivities are too large for their normal equations (an output that stays bounded while its
    sensitivity to a weight grows without bound: the linearisation means nothing there)."""
    with np.errstate(over="ignore", invalid="ignore"):
        normal = jacobian.T @ jacobian
        gradient = jacobian.T @ residual
    if not (np.all(np.isfinite(normal)) and np.all(np.isfinite(gradient))):
        return None
    while damping < 1e8:
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                delta = np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-12), gradient)
        except np.linalg.LinAlgError:
            damping *= 10.0
            continue
        if not np.all(np.isfinite(delta)):
            damping *= 10.0
            continue
        r = residuals(model, record, pieces, weights + delta)
        if r is not None and float(r @ r) < cost:
            return weights + delta, r, float(r @ r), max(damping / 3.0, 1e-9)
        damping *= 10.0
    return None


def _held_out(block: tuple[int, int], n: int) -> tuple[int, int]:
    """The part of a block that is scored: at most MAX_REFINED_SAMPLES from its start."""
    a, b = block
    return a, min(b, a + MAX_REFINED_SAMPLES, n)


def _training_pieces(blocks: list[tuple[int, int]], fold: int, n: int) -> list[tuple[int, int]]:
    """The samples a fold refines on: everything but its block, split around it, at most MAX_FOLD_TRAINING of
    them, the nearest the block (half each side where both sides have them)."""
    a, b = blocks[fold]
    before, after = a, n - b
    keep_before = min(before, max(MAX_FOLD_TRAINING // 2, MAX_FOLD_TRAINING - after))
    keep_after = min(after, MAX_FOLD_TRAINING - keep_before)
    return [piece for piece in ((a - keep_before, a), (b, b + keep_after)) if piece[1] > piece[0]]


def iterations_for(candidate: Candidate) -> int:
    """Most iterations tried for ``candidate``: ITERATIONS, or its family's own where its least-squares start is
    known to lie far from its simulation-error fit (its registry entry's ``iterations``)."""
    return candidate.spec.registered.iterations or ITERATIONS


def cross_validated_refinement(candidate: Candidate, record: Record, iterations: int | None = None) -> Refinement:
    """Choose the iteration count on the blocks, then refine ``candidate.model`` (all samples) that many times.

    ``candidate.model.weights`` are replaced by the refined weights (unchanged if the
    blocks chose zero). The two stages are :func:`fold_history` (each block, independent of
    the others: ``fit`` runs every candidate's blocks side by side) and :func:`refine_on_folds`.
    """
    histories = [fold_history(candidate, record, fold, iterations) for fold in range(len(candidate.fold_weights))]
    return refine_on_folds(candidate, record, histories)


@dataclass
class FoldHistory:
    """One block's refinement: the squared free-run error of the block after 0..iterations iterations of the
    weights fitted without it, the samples scored, and those weights after each iteration (``path[0]``: the
    least-squares ones; shorter when the refinement stopped early, its last weights then standing)."""

    errors: np.ndarray
    samples: int
    path: list[np.ndarray]

    def weights_after(self, iterations: int) -> np.ndarray:
        return self.path[min(iterations, len(self.path) - 1)]


def fold_history(candidate: Candidate, record: Record, fold: int, iterations: int | None = None) -> FoldHistory:
    """Block ``fold``'s :class:`FoldHistory`: the weights fitted without it are refined on the other blocks, the
    block only scored. ``iterations``: :func:`iterations_for` the candidate unless given."""
    iterations = iterations_for(candidate) if iterations is None else iterations
    model = candidate.model
    blocks = fold_blocks(record.n, model.warm_up)
    scored = _held_out(blocks[fold], record.n)
    history: list[float] = []
    weights = candidate.fold_weights[fold]
    path = [np.asarray(weights)]

    def score(w: np.ndarray) -> bool:
        """Record the block's error; True (stop) once it has not improved for PATIENCE iterations."""
        r = residuals(model, record, [scored], w)
        history.append(math.inf if r is None else float(r @ r))
        path.append(np.array(w, copy=True))
        return len(history) - 1 - int(np.argmin(history)) >= PATIENCE

    first = residuals(model, record, [scored], weights)
    history.append(math.inf if first is None else float(first @ first))
    levenberg_marquardt(model, record, _training_pieces(blocks, fold, record.n), weights, iterations, score)
    history += [history[-1]] * (iterations + 1 - len(history))  # stopped early: its last score stands
    return FoldHistory(np.array(history), 0 if first is None else len(first), path)


def refine_on_folds(candidate: Candidate, record: Record, histories: list[FoldHistory]) -> Refinement:
    """The count with the lowest pooled held-out error over every block's :func:`fold_history` (in block order),
    then the weights of all samples refined that many times, less the iterations that make the model unsound.

    The per-block histories are pooled as squared errors, so a block that diverges after
    some iteration makes that count lose everywhere. Each block's weights become those refined as many times
    as the delivered ones: the bands are calibrated on the blocks' errors, which must be the errors of the model
    delivered, not of its least-squares start (its free-run band was 1.5 times too wide where the refinement
    helped most: a servo axis's test part 99-100 % covered).
    """
    model = candidate.model
    pooled, chosen = _pooled(histories)
    whole = [(0, record.n)]
    before = residuals(model, record, whole, model.weights)
    unsound = ""
    if chosen:
        steps: list[np.ndarray] = []

        def keep(weights: np.ndarray) -> bool:
            steps.append(weights)
            return False

        levenberg_marquardt(model, record, whole, model.weights, chosen, keep)
        chosen, weights, unsound = _soundest(model, record, steps[:chosen])
        model.weights = weights
    candidate.fold_weights = [history.weights_after(chosen) for history in histories]
    after = residuals(model, record, whole, model.weights)
    return Refinement(
        iterations=chosen,
        tried=len(pooled) - 1,
        rmse_blocks_before=float(pooled[0]),
        rmse_blocks_after=float(pooled[chosen]),
        rmse_training_before=_rms(before),
        rmse_training_after=_rms(after),
        unsound=unsound,
    )


def _pooled(histories: list[FoldHistory]) -> tuple[np.ndarray, int]:
    """(pooled held-out RMSE after 0, 1, ... iterations, as far as the histories go; the count with the lowest)."""
    tried = len(histories[0].errors) if histories else 1
    squared = np.zeros(tried)
    counts = np.zeros(tried)
    for history in histories:
        squared += history.errors
        counts += history.samples
    pooled = np.sqrt(squared / np.maximum(counts, 1))
    return pooled, int(np.argmin(pooled))


def blocks_choice(histories: list[FoldHistory]) -> Refinement:
    """What the blocks choose (:func:`refine_on_folds`' count and score), not applied to the model's weights:
    the score of a candidate before, or instead of, its refinement on all samples."""
    pooled, chosen = _pooled(histories)
    return Refinement(
        iterations=chosen,
        tried=len(pooled) - 1,
        rmse_blocks_before=float(pooled[0]),
        rmse_blocks_after=float(pooled[chosen]),
        applied=False,
    )


def _soundest(model: TermModel, record: Record, steps: list[np.ndarray]) -> tuple[int, np.ndarray, str]:
    """(iterations, weights, why more were refused) of the most refined weights that still pass the selection's
    :func:`~lenn_ros.fit.soundness.soundness_problem`.

    The blocks vouch for the refinement's fit, not for its stability: an iteration can lower
    every block's error and leave a model that runs away on the training input shuffled (seen on
    a buck converter, which then diverged 41 samples into its test). Such steps are undone,
    latest first; none left is the least-squares model, which the selection found sound.
    """
    problems = []
    for count in range(len(steps), 0, -1):
        problem = soundness_problem(model.with_weights(steps[count - 1]), record)
        if not problem:
            break
        problems.append(problem)
    else:
        count = 0
    weights = steps[count - 1] if count else model.weights
    why = f"{len(problems)} iteration(s) undone: {'; '.join(sorted(set(problems)))}" if problems else ""
    return count, weights, why


def _rms(residual: np.ndarray | None) -> float:
    return math.sqrt(float(residual @ residual) / len(residual)) if residual is not None and len(residual) else math.nan
