"""Whether a model fitted to all training samples is sound: its free run in-sample and on its input shuffled.

The prefix the selection prefers must pass two checks before its candidate counts
(:func:`soundness_problem`): the weights fitted to all training samples simulate the
whole training record soundly, and they stay bounded when driven by the training input
cut into blocks and shuffled (an input like those the model was built for, but in an
order it has not seen: a model that runs away on it sits on the edge of stability and
will run away on new data). A model that integrates exactly (:func:`level_free`) is
judged there by its increments: an integrating plant driven by its input in another
order leaves the training range as surely. The refinement undoes iterations that fail
the same check, and the model delivered reads a level-free output wide (:func:`widened`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lenn_ros.core.expansions import round6
from lenn_ros.core.scaling import ranges
from lenn_ros.fit.record import Record, Simulation
from lenn_ros.fit.termmodel import Layout, TermModel

#: shuffled-input runs of the stress check, and how many blocks the input is cut into for them
STRESS_RUNS = 3
STRESS_BLOCKS = 10


def stress_views(record: Record, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """The view with what the output reads (columns 1..) cut into STRESS_BLOCKS blocks and shuffled,
    STRESS_RUNS times (fixed seed); column 0, the output, stays (only its first samples seed a run).

    Each view comes with its seams: the samples where the inputs' history stops being a
    stretch of one run of the record (a block's start, a break carried with its block)."""
    values, n = record.values, record.n
    rng = np.random.default_rng(seed)
    edges = np.linspace(0, n, STRESS_BLOCKS + 1).round().astype(int)
    views = []
    for _ in range(STRESS_RUNS):
        order = rng.permutation(STRESS_BLOCKS)
        shuffled = np.concatenate([values[edges[i] : edges[i + 1], 1:] for i in order])
        seams, position = [], 0
        for i in order:
            a, b = int(edges[i]), int(edges[i + 1])
            inner = record.breaks[(record.breaks > a) & (record.breaks < b)]
            seams.extend([position, *(position + inner - a).tolist()])
            position += b - a
        views.append((np.column_stack([values[:, 0], shuffled]), np.array(sorted(set(seams) - {0}), dtype=np.int64)))
    return views


def terms_reading_output(exponents: np.ndarray, factors: np.ndarray, lags: int) -> np.ndarray:
    """Per term: whether it reads the output fed back (column 0's ``lags`` inputs), by a polynomial or its
    factor (``factors``: rows per term, or none)."""
    reading = exponents[:, :lags].any(axis=1)
    return reading | factors[:, 2 : 2 + lags].any(axis=1) if len(factors) else reading


def reads_outputs(model: TermModel) -> bool:
    """Whether some term reads the output fed back: an input-only model does not."""
    return bool(terms_reading_output(model.exponents, model.factors, model.layout.lags).any())


def shuffled_run(model: TermModel, view: np.ndarray, seams: np.ndarray) -> tuple[int, int]:
    """(clipped, diverged_at or -1) of the free run of a shuffled view, ending outside the training range.

    An input-only model's output at a sample depends on the inputs' last lags alone, so
    wherever those are a stretch of the record the run repeats the in-sample run (which
    :func:`soundness_problem` checked first): only the samples within one warm-up after a
    seam are new, and only those are simulated, each seam's from its own warm-up. A model
    that reads its output is run whole: its state carries the seam's effect on."""
    warm = model.warm_up
    if reads_outputs(model):
        _, clipped, diverged_at = model.free_run(view, warm, bound=TRAINING_RANGE)
        return clipped, diverged_at
    for seam in seams.tolist():
        low, high = max(0, seam - warm), min(len(view), seam + warm)
        if high - low <= warm:
            continue
        _, clipped, diverged_at = model.free_run(view[low:high], warm, bound=TRAINING_RANGE)
        if clipped or diverged_at >= 0:
            return clipped, diverged_at
    return 0, -1


#: where a soundness free run has left the training range: an output further from its offset than its
#: scale (the training range widened by the scaling's margin), where its lags would clip
TRAINING_RANGE = 1.0


def output_rows(model: TermModel) -> np.ndarray:
    """Mask of the terms whose polynomial part reads the fed-back output: of a :func:`level_free` model, its
    pass-through ``y1`` alone (what :func:`widened` rescales and the refinement leaves alone)."""
    return model.exponents[:, : model.layout.lags].any(axis=1)


def level_free(model: TermModel) -> bool:
    """Whether the model integrates exactly: its output level enters only as y(k) passed through.

    Every term that reads the fed-back output reads differences of it (a factor whose
    weights on the output's lags sum to zero: ``lin(y1-y2)``, ``tanh(a*y1-a*y3)``), besides
    ``y1`` itself with weight exactly the output's scale (the increment form's pass-through).
    Shifting the whole output history by c then shifts the prediction by c: the model's
    dynamics are those of its increments, and its level is their sum, wherever it goes.
    """
    lags, exponents, factors = model.layout.lags, model.exponents, model.factors
    unit = np.zeros(exponents.shape[1], dtype=np.int64)
    unit[0] = 1
    plain = factors[:, 0] == 0 if len(factors) else np.ones(len(exponents), dtype=bool)
    through = (exponents == unit).all(axis=1) & plain
    if np.any(output_rows(model) & ~through) or not through.any():
        return False
    if len(factors):
        w = factors[:, 2 : 2 + lags]
        if np.any(np.abs(w.sum(axis=1)) > 1e-9 * np.abs(w).sum(axis=1)):
            return False
    return bool(abs(float(model.weights[through].sum()) - model.layout.y_scale) <= 1e-9 * model.layout.y_scale)


def widened(model: TermModel, width: float) -> TermModel:
    """The same function of a :func:`level_free` model with its output read over ``width`` times its range.

    The output's lags are scaled by ``width`` times more, and the terms reading them (the
    pass-through and the differences' factor weights) take ``width`` times the weight: the
    same prediction wherever the old scaling did not clip, and the output's level clips
    only ``width`` ranges away."""
    layout = model.layout
    lags = layout.lags
    wide = Layout(lags, layout.offsets, (layout.scales[0] * width, *layout.scales[1:]), layout.names)
    factors = np.array(model.factors)
    if len(factors):  # (kept to the six digits the params file writes: 10 x 0.988667 is 9.886669999999999)
        factors[:, 2 : 2 + lags] = [[round6(w * width) for w in row] for row in factors[:, 2 : 2 + lags]]
    weights = np.array(model.weights, dtype=np.float64)
    weights[output_rows(model)] *= width
    return TermModel(wide, model.exponents, model.basis, weights, factors if len(factors) else None)


#: a level-free model's soundness runs read its output over this many times the training range: its
#: level may go anywhere its increments take it (a joint without gravity, a wheel, a positioning axis)
LEVEL_FREE_WIDTH = 1e6


def increments_problem(model: TermModel, record: Record) -> str:
    """:func:`soundness_problem` of a :func:`level_free` model, judged by its increments.

    An integrating plant driven by its training input in another order goes where that
    order takes it, outside the training range as often as not: the plant itself would
    fail the level's rule. What must stay as the training record had it is the model's
    own dynamics, its increments: on the shuffled input they must stay within the training
    increments' range (widened by the scaling's margin, as the level's range is). Over the
    whole training record, where the level was measured, the free run must still beat the
    mean; only leaving the output's range is no fault of a model that integrates.
    """
    wide = widened(model, LEVEL_FREE_WIDTH)
    whole = record.simulate(wide, 0, record.n, bound=TRAINING_RANGE)
    problem = whole.problem("in-sample")
    if problem:
        return problem
    steps = np.diff(record.y)
    crossing = record.breaks[record.breaks < record.n] - 1
    (offset,), (scale,) = ranges(np.delete(steps, crossing), ("output increments",))
    warm = model.warm_up
    for shuffled, _ in stress_views(record):
        simulated, _, diverged_at = wide.free_run(shuffled, warm, bound=TRAINING_RANGE)
        increments = np.diff(np.concatenate([shuffled[warm - 1 : warm, 0], simulated]))
        if diverged_at >= 0 or not np.all(np.abs(increments - offset) <= TRAINING_RANGE * scale):
            return "free run on the training input shuffled in blocks left the training increments' range"
    return ""


def soundness_problem(
    model: TermModel, record: Record, predictions: tuple[np.ndarray, np.ndarray] | None = None
) -> str:
    """What is wrong with a model fitted to all training samples (``""``: nothing).

    Its free run over the whole training record (each contiguous run from its measured
    start) must stay in the training range and do better than the mean: this is the
    easiest simulation the model will ever face. And driven by the training input
    shuffled in blocks it must stay in the training range: an input like the ones it was
    built for, in an order it has not seen. One seed, fixed, so the verdict is repeatable.

    The inputs of these runs are training samples, so only a fed-back output can clip:
    each run ends at the first output outside the training range (``TRAINING_RANGE``),
    with the verdict a whole run would give. The prefixes that fail here are mostly the
    long ones that overshoot early, and they are tried one after another
    (:func:`_choose_prefix`): stopping there is what keeps that search cheap.

    ``predictions``: (samples, values) of an input-only model's one-step predictions over
    the record's regression rows, which are its in-sample free run (it feeds nothing
    back); given, that run is read from them instead of simulated again.
    """
    if level_free(model):
        return increments_problem(model, record)
    if predictions is not None:
        samples, values = predictions
        pieces = np.array([(a, b, 0) for a, b in record.pieces(0, record.n, model.warm_up)], dtype=np.int64)
        out = np.zeros((1, 5))
        runs_from_predictions(record, model.layout, samples, lambda _g, low, high: values[low:high],
                              tuple(pieces.reshape(-1, 3).T), TRAINING_RANGE, out)  # fmt: skip
        whole = Simulation.of_row(out[0], model.layout.n_inputs)
    else:
        whole = record.simulate(model, 0, record.n, bound=TRAINING_RANGE)
    if whole.diverged or whole.clipped:
        return "in-sample free run left the training range"
    problem = whole.problem("in-sample")
    if problem:
        return problem
    for shuffled, seams in stress_views(record):
        clipped, diverged_at = shuffled_run(model, shuffled, seams)
        if diverged_at >= 0 or clipped > 0:
            return "free run on the training input shuffled in blocks left the training range"
    return ""


def runs_from_predictions(
    record: Record, layout: Layout, samples: np.ndarray, predict: Callable, pieces: tuple, bound: float, out: np.ndarray
) -> None:
    """:func:`kernels.simulate_pieces` of a model that reads no output fed back, from its one-step predictions.

    Such a model's free run of a piece is its one-step prediction of each sample (nothing is
    fed back), so the runs are products of the design's rows: ``predict(g, low, high)`` gives
    those of rows low..high (``samples``: the sample each row predicts, sorted) by group g's
    weights. ``out`` gets what the kernel gives: squared errors, samples, squares about each
    piece's mean, clipped inputs, diverged (further than ``bound`` scales, or non-finite). The
    inputs read are training samples, inside the range, so what clips is the fed-back
    output's lags a term never reads: a sample outside the range is read by the next
    ``lags`` samples of its piece, and each counts it.
    """
    offset, scale = layout.y_offset, layout.y_scale
    for a, b, g in zip(*pieces, strict=True):
        low, high = np.searchsorted(samples, [a, b])
        simulated = predict(g, low, high)
        measured = record.y[a:b]
        if not np.all(np.abs(simulated - offset) <= bound * scale):
            out[g, 4] = 1.0  # non-finite or diverged: the kernel stops there, the block fails
        x = (simulated - offset) / scale
        outside = np.flatnonzero((x > 1.0) | (x < -1.0))
        out[g, 0] += float(np.sum((simulated - measured) ** 2))
        out[g, 1] += b - a
        out[g, 2] += float(np.sum((measured - measured.mean()) ** 2))
        out[g, 3] += float(np.minimum(layout.lags, b - 1 - (a + outside)).sum())
