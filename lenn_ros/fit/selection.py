"""Structure selection for a functional-link model of real data, judged by simulation.

A functional-link network is linear in its weights, so choosing its structure is
choosing columns of a feature matrix. Each candidate is a *family* of terms at some
lags (:mod:`lenn_ros.fit.families`: polynomials, hinges, increments with friction-like
terms of the velocity), a dictionary built from the training data; orthogonal forward
regression ranks its terms by error-reduction ratio (Billings' FROLS,
:mod:`lenn_ros.fit.regression`). Up to here this is FROLS. The difference is how a model
is judged: every prefix of every ranked list is fitted by least squares and *simulated*
(free run, the model fed its own outputs), and the lowest simulation error wins.
One-step error rewards models that lean on the measured past; simulation is what a
model is used for.

One held-out tail is a weak judge (a short tail can be simulated well by luck), so the
training samples are cut into contiguous blocks (:func:`~lenn_ros.fit.record.fold_blocks`):
each block is simulated from the measured outputs just before it by the weights fitted to
all the other blocks, and the score pools every block's simulation error. A prefix is
refused when any block's simulation diverges, leaves the training range (clipped inputs)
or does worse than the block's mean. The preferred prefix must then be sound
(:func:`~lenn_ros.fit.soundness.soundness_problem`: in-sample, and on its input shuffled
in blocks) before its candidate counts.

Degree-1 candidates (linear ARX, and the linear increment form) are always in the grid
and a nonlinear candidate must beat the best linear one by ``NONLINEAR_GAIN`` to be
chosen; among candidates within ``PARSIMONY`` of the lowest score the one with the
fewest terms is chosen, as within a candidate.

Records that are not one contiguous run (gaps in a recording) are handled by
``breaks`` (:class:`~lenn_ros.fit.record.Record`): no regression row reaches across a
break and every simulation restarts from the measured outputs after it.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from lenn_ros.core import term_kernels as kernels
from lenn_ros.core.expansions import term_features
from lenn_ros.core.free_run import FREE_RUN_DIVERGENCE_BOUND
from lenn_ros.core.threads import side_by_side
from lenn_ros.fit.families import Spec, candidate_specs
from lenn_ros.fit.families.base import Dictionary
from lenn_ros.fit.record import LOOSE_CLIPPED_FRACTION, Record, Simulation, fold_blocks
from lenn_ros.fit.regression import Folds, forward_regression_gram
from lenn_ros.fit.soundness import runs_from_predictions, soundness_problem, terms_reading_output
from lenn_ros.fit.termmodel import Layout, TermModel, simulate_joint

#: relative simulation error a term (or a candidate's extra terms) must buy to be kept
PARSIMONY = 0.01
#: a nonlinear candidate is chosen only if its score is below (1 - NONLINEAR_GAIN) x the best linear one's
NONLINEAR_GAIN = 0.03
#: samples of each block a prefix's free run is scored on (from the block's start): a long record's
#: blocks of 8 000 samples cost every prefix 40 000 simulated steps; scoring the first 4 000 of each
#: chose the same models on Bouc-Wen and the Silverbox (2 000 did not on Bouc-Wen), in 0.7x the time
MAX_SCORED = 4000
#: most terms a ranked list offers (FROLS stops there), and at most one term per this many samples. At 40
#: Bouc-Wen's model stopped at 38 terms, still improving on the blocks; 80 took it to 67 (test 6.37e-5 ->
#: 5.60e-5) and changed no other shared set's model
MAX_TERMS = 80
SAMPLES_PER_TERM = 10
#: prefixes scored past the best one so far (or, while none passes, from the first) before the rest of a
#: ranked list is left out: on every shared data set no candidate's first usable prefix came later than 12
PATIENCE = 12


# -- candidates --------------------------------------------------------------------------------


@dataclass
class Candidate:
    """One structure tried, with its verdict: every choice ``fit`` makes is one of these."""

    spec: Spec
    dictionary: int  # terms offered
    terms: int = 0  # terms kept (best prefix)
    rmse_validation: float = math.inf  # pooled free-run RMSE over the blocks
    block_rmse: list[float] = field(default_factory=list)
    rejected: str = ""  # why no prefix of this candidate was usable
    model: TermModel | None = None  # the kept terms with the weights of all training samples
    fold_weights: list[np.ndarray] = field(default_factory=list)  # each block's weights (without it)
    note: str = ""  # why it comes first although another scored lower
    refinement: dict | None = None
    fallback: tuple | None = field(default=None, repr=False)  # what :func:`loosen` needs

    @property
    def linear(self) -> bool:
        return self.spec.degree == 1

    @property
    def weights(self) -> int:
        """Weights of the model delivered: the kept terms, and the increment form's pass-through if added."""
        return len(self.model.exponents) if self.model is not None else 0

    def as_dict(self) -> dict:
        return {
            **self.spec.as_dict(),
            "dictionary": self.dictionary,
            "terms": self.terms,
            "weights": self.weights,
            "rmse_free_run_validation": _finite(self.rmse_validation),
            "rmse_free_run_blocks": [_finite(v) for v in self.block_rmse],
            "rejected": self.rejected,
            "note": self.note,
            **({"refinement": self.refinement} if self.refinement else {}),
        }


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


@dataclass
class Design:
    """A dictionary's regression over the record: features, the target its terms explain, normal equations."""

    dictionary: Dictionary
    features: np.ndarray
    targets: np.ndarray  # y(k+1), less the pass-through in the increment form
    predicted: np.ndarray  # the sample each row predicts
    gram: np.ndarray
    moment: np.ndarray
    energy: float

    @classmethod
    def of(cls, spec: Spec, record: Record, layout: Layout, inputs: tuple | None = None) -> Design:
        """``inputs``: :func:`valid_inputs` of the spec's lags when already at hand."""
        layout = layout.with_lags(spec.lags)
        x, targets, predicted = inputs if inputs is not None else valid_inputs(record, layout)
        dictionary = spec.dictionary(x)
        # column-major: each candidate gathers its ranked columns (a few dozen of hundreds) as contiguous copies
        features = term_features(x, dictionary.exponents, "legendre", dictionary.factors, order="F")
        targets = targets - dictionary.pass_through(x, layout)
        return cls(dictionary, features, targets, predicted, features.T @ features, features.T @ targets,
                   float(targets @ targets))  # fmt: skip

    def leading(self, dictionary: Dictionary) -> Design | None:
        """This design cut to ``dictionary`` when that is its start (a lower degree of the family), else None."""
        count = len(dictionary.exponents)
        mine = self.dictionary
        if not (
            count <= len(mine.exponents)
            and dictionary.increment == mine.increment
            and np.array_equal(mine.exponents[:count], dictionary.exponents)
            and np.array_equal(mine.factors[:count], dictionary.factors)
        ):
            return None
        return Design(dictionary, self.features[:, :count], self.targets, self.predicted,
                      self.gram[:count, :count], self.moment[:count], self.energy)  # fmt: skip


def evaluate_candidate(spec: Spec, record: Record, layout: Layout, design: Design, strict: bool = True) -> Candidate:
    """Rank the dictionary's terms by FROLS, score every prefix by blocked free runs, keep the preferred sound one.

    ``strict=False`` (``fit``'s fallback, with a warning, when nothing passes) refuses
    only divergence and leaving the range, and skips :func:`soundness_problem`.
    """
    dictionary = design.dictionary
    candidate = Candidate(spec, len(dictionary.exponents))
    base = TermModel(layout.with_lags(spec.lags), dictionary.exponents, "legendre", factors=dictionary.factors)
    warm = base.warm_up
    limit = min(MAX_TERMS, len(dictionary.exponents), max(1, len(design.targets) // SAMPLES_PER_TERM))
    ranked, _ = forward_regression_gram(design.gram, design.moment, design.energy, limit)
    if not ranked:
        candidate.rejected = "no usable term"
        return candidate
    prefixes = Prefixes(base, dictionary, ranked, design, fold_blocks(record.n, warm))
    scores, loose_scores, reasons, loose_reasons = _score_prefixes(prefixes, record)
    _choose_prefix(candidate, prefixes, record, scores if strict else loose_scores,
                   reasons if strict else loose_reasons, strict)  # fmt: skip
    prefixes.design = None  # every prefix scored is gathered; the design (N x all terms) need not outlive this
    candidate.fallback = (prefixes, loose_scores, loose_reasons)
    return candidate


def loosen(candidates: list[Candidate], record: Record) -> list[Candidate]:
    """The candidates again under the loose rules (``fit``'s fallback, with a warning, when none passed).

    Only divergence and leaving the range refuse a prefix, and the soundness check is
    skipped; the prefixes' scores are those already computed, so nothing is simulated again.
    """
    loose = []
    for old in candidates:
        candidate = Candidate(old.spec, old.dictionary)
        if old.fallback is None:
            candidate.rejected = old.rejected
        else:
            prefixes, scores, reasons = old.fallback
            _choose_prefix(candidate, prefixes, record, list(scores), list(reasons), strict=False)
        loose.append(candidate)
    return order_candidates(loose)


@dataclass
class Prefixes:
    """A candidate's ranked terms, and the model each prefix of them makes.

    In the increment form every prefix also holds the pass-through y(k) (the bias and
    ``y1`` with fixed weights): appended as two more terms while prefixes are scored
    (the same function as folding them into equal terms of the prefix), folded in for
    the model delivered (:meth:`Dictionary.with_pass_through`).
    """

    base: TermModel
    dictionary: Dictionary
    ranked: list[int]
    design: Design | None  # where the ranked terms' features are gathered from, while prefixes are scored
    blocks: list[tuple[int, int]]
    #: the first ranked terms' features over the design's rows, and their normal equations per fold
    features: np.ndarray = field(init=False, repr=False)
    folds: Folds = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.predicted = self.design.predicted  # the sample each row predicts
        self._gather(min(len(self.ranked), 2 * PATIENCE))
        d, n = self.dictionary, self.base.layout.n_inputs
        lags = self.base.layout.lags
        reading = terms_reading_output(d.exponents[self.ranked], d.factors[self.ranked], lags)
        #: the prefixes of up to this many terms read no output fed back: input-only (:meth:`input_only`)
        self.reading_from = 0 if d.increment else (int(np.argmax(reading)) if reading.any() else len(reading))
        rows = d.exponents[self.ranked]
        factors = d.factors[self.ranked]
        self.passing = np.zeros(0)
        if d.increment:
            rows = np.vstack([rows, np.zeros((2, n), dtype=np.int64)])
            rows[-1, 0] = 1  # y1; the row before is the bias
            factors = np.vstack([factors, np.zeros((2, n + 2))])
            self.passing = np.array([self.base.layout.y_offset, self.base.layout.y_scale])
        self.rows, self.factor_rows = rows, factors

    def _gather(self, width: int) -> None:
        """The first ``width`` ranked terms' features and folds.

        Gathered as they are needed, not all ranked terms at once: scoring stops PATIENCE
        prefixes past the best, typically near 20 of up to 80, and a gather of 80 columns of a
        40 000-row design into fresh memory was a tenth of a six-joint robot's selection.
        """
        design, columns = self.design, self.ranked[:width]
        self.features = design.features[:, columns]  # column-major: contiguous copies
        normal = (design.gram[np.ix_(columns, columns)], design.moment[columns])
        self.folds = Folds.of(self.features, design.targets, design.predicted, self.blocks, self.base.warm_up, normal)

    def reach(self, m: int) -> None:
        """Gather (doubling) until prefix ``m``'s terms are at hand."""
        if m > self.features.shape[1]:
            self._gather(min(len(self.ranked), max(m, 2 * self.features.shape[1])))

    def arrays(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        """(exponents, factors) of prefix ``m`` as scored (the pass-through appended)."""
        if len(self.rows) == len(self.ranked):  # no pass-through rows: the prefix is the first m rows
            rows, factors = self.rows[:m], self.factor_rows[:m]
        else:
            keep = np.concatenate([np.arange(m), np.arange(len(self.ranked), len(self.rows))])
            rows, factors = self.rows[keep], self.factor_rows[keep]
        return np.ascontiguousarray(rows), factors if factors[:, 0].any() else factors[:0]

    def fold_weights(self, m: int) -> np.ndarray | None:
        """Each block's least-squares weights of prefix ``m`` as scored, one row per block (None: singular)."""
        self.reach(m)
        weights = self.folds.all_weights(m)
        if weights is None or not len(self.passing):
            return weights
        return np.hstack([weights, np.broadcast_to(self.passing, (len(weights), len(self.passing)))])

    def input_only(self, m: int) -> bool:
        """Whether prefix ``m`` reads no output fed back (nor passes y(k) through): its free run from any
        start is its one-step prediction."""
        return m <= self.reading_from

    def in_sample(self, m: int, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(samples, one-step predictions) of prefix ``m`` with ``weights`` over the record when that is its
        in-sample free run (:meth:`input_only`), else None."""
        return (self.predicted, self.features[:, :m] @ weights) if self.input_only(m) else None

    def model(self, m: int, weights: np.ndarray) -> TermModel:
        """The model delivered for prefix ``m`` with its own (least-squares) weights, the pass-through folded in."""
        exponents, factors, weights = self.dictionary.with_pass_through(self.ranked[:m], weights, self.base.layout)
        b = self.base
        return TermModel(b.layout, exponents, b.basis, weights, factors)


def _block_pieces(record: Record, blocks: list[tuple[int, int]], warm: int) -> tuple[np.ndarray, ...]:
    """(first, stop, block) of every piece of every block, as :func:`kernels.simulate_pieces` takes them."""
    found = [
        (first, stop, index)
        for index, (a, b) in enumerate(blocks)
        for first, stop in record.pieces(a, min(b, a + MAX_SCORED), warm)
    ]
    return tuple(np.array([piece[i] for piece in found], dtype=np.int64) for i in range(3))


def _score_prefixes(prefixes: Prefixes, record: Record) -> tuple[list[tuple], list[tuple], list[str], list[str]]:
    """(m, pooled RMSE, per-block RMSE) of every prefix usable under the strict rules, the same under the
    loose ones, and why the others failed under each.

    Each prefix's blocks are simulated in one compiled call (:func:`kernels.simulate_pieces`),
    or for an input-only prefix read from its one-step predictions (:func:`runs_from_predictions`).
    """
    base, blocks = prefixes.base, prefixes.blocks
    warm = base.warm_up
    first, stop, group = _block_pieces(record, blocks, warm)
    width = base.layout.n_inputs
    # a block that clips more than this fails both rules: the blocks after it cannot save the prefix
    clip_limit = LOOSE_CLIPPED_FRACTION * np.bincount(group, stop - first, len(blocks)) * width
    source, lag, offset, scale = base.layout.arrays()
    # what a prefix's block runs depend on besides the record, its terms and weights (the blocks follow from warm)
    scaled = (warm, base.basis, _digest(source, lag, offset, scale))
    scores, loose, reasons, loose_reasons = [], [], [], []
    best_m, lowest = 0, math.inf
    for m in range(1, len(prefixes.ranked) + 1):
        if m > best_m + PATIENCE:
            break  # the ranked list's later terms are what FROLS could least vouch for; none yet: from 0
        weights = prefixes.fold_weights(m)
        if weights is None:
            reasons.append("singular")
            loose_reasons.append("singular")
            continue
        out = np.zeros((len(blocks), 5))
        if prefixes.input_only(m):
            runs_from_predictions(
                record, base.layout, prefixes.predicted,
                lambda g, low, high, m=m, weights=weights: prefixes.features[low:high, :m] @ weights[g, :m],
                (first, stop, group), FREE_RUN_DIVERGENCE_BOUND, out,
            )  # fmt: skip
        else:
            exponents, factors = prefixes.arrays(m)
            key = (scaled, _digest(exponents, factors, weights))
            if (known := record.runs.get(key)) is not None:
                out[:] = known
            else:
                kernels.simulate_pieces(
                    record.values, first, stop, group, warm, source, lag, offset, scale, exponents, factors, weights,
                    kernels.BASIS_CODES[base.basis], FREE_RUN_DIVERGENCE_BOUND, out, clip_limit,
                )  # fmt: skip
                record.runs[key] = out.copy()
        runs_of = [Simulation.of_row(row, width) for row in out]
        pooled = math.sqrt(float(out[:, 0].sum()) / float(out[:, 1].sum()))
        entry = (m, pooled, [run.rmse for run in runs_of])
        for strict, kept, why in ((True, scores, reasons), (False, loose, loose_reasons)):
            failed = next((p for p in (run.problem("held-out", strict=strict) for run in runs_of) if p), "")
            if failed:
                why.append(failed)
            else:
                kept.append(entry)
        if scores and scores[-1] is entry and pooled < lowest:
            best_m, lowest = m, pooled
        elif not scores and loose and loose[-1] is entry and pooled < lowest:
            best_m, lowest = m, pooled  # nothing strict yet: patience counts from the best loose prefix
    return scores, loose, reasons, loose_reasons


def _digest(*arrays: np.ndarray) -> bytes:
    """The exact bits of ``arrays`` (shapes included), as a short key for :attr:`Record.runs`: a long span's
    terms are hundreds of inputs wide, and thousands of prefixes are scored."""
    digest = hashlib.blake2b(digest_size=16)
    for array in arrays:
        digest.update(np.asarray(array.shape, dtype=np.int64).tobytes())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.digest()


def _choose_prefix(candidate, prefixes: Prefixes, record: Record, scores, reasons, strict: bool) -> None:
    """The fewest terms within PARSIMONY of the lowest score that passes :func:`soundness_problem`."""
    folds = prefixes.folds
    while scores:
        lowest = min(entry[1] for entry in scores)
        preferred = next(entry for entry in scores if entry[1] <= lowest * (1.0 + PARSIMONY))
        m = preferred[0]
        weights = folds.weights(m)
        if weights is None:
            problem = "singular"
        else:
            model = prefixes.model(m, weights)
            problem = soundness_problem(model, record, prefixes.in_sample(m, weights)) if strict else ""
        if not problem:
            candidate.terms, candidate.rmse_validation, candidate.block_rmse = m, preferred[1], preferred[2]
            candidate.fold_weights = [prefixes.model(m, folds.weights(m, f)).weights for f in range(len(folds.blocks))]
            candidate.model = model
            return
        reasons.append(problem)
        scores = [entry for entry in scores if entry is not preferred]
    candidate.rejected = f"every prefix: {'; '.join(sorted(set(reasons)))}" if reasons else "no usable term"


def select_structure(
    record: Record,
    layout: Layout,
    specs: list[Spec] | None = None,
    progress: Callable[[Candidate], None] | None = None,
    workers: int = 1,
) -> list[Candidate]:
    """Every candidate of the grid for the record's output, judged; sorted with the one to use first
    (:func:`order_candidates`). ``layout`` gives the view's scaling and names (its lags are each spec's).

    ``workers``: candidates judged side by side on that many threads (each is independent
    and the kernels release the GIL); the verdicts and ``progress`` come in the grid's order.
    """
    specs = specs if specs is not None else candidate_specs(record.n, layout.n_columns)
    # the designs are built on this thread while the pool judges those already built (building them all
    # first was 1.7 of Bouc-Wen's 9.4 s of selection, with both cores but one idle); they come in the
    # designs' order, and are told in the grid's as soon as each one's predecessors are in
    judged = side_by_side(
        lambda job: evaluate_candidate(job[0], record, layout, job[1]), _designs(specs, record, layout), workers
    )
    done: dict[Spec, Candidate] = {}
    candidates: list[Candidate] = []
    for candidate in judged:
        done[candidate.spec] = candidate
        while len(candidates) < len(specs) and specs[len(candidates)] in done:
            candidates.append(done.pop(specs[len(candidates)]))
            if progress:
                progress(candidates[-1])
    return order_candidates(candidates)


def valid_inputs(record: Record, layout: Layout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(network inputs clipped, target y(k+1), the sample each row predicts) of every regressor of the
    layout's lags whose window crosses no break: what every design over those lags starts from."""
    base = TermModel(layout, np.zeros((1, layout.n_inputs), dtype=np.int64))
    x, targets = base.inputs(record.values)
    valid = record.valid_rows(base.warm_up)
    predicted = np.arange(base.warm_up, record.n)
    if valid.all():  # no break: no copy (a 65-lag view of twelve columns is 250 MB on a 40 000-sample record)
        return x, targets, predicted
    return x[valid], targets[valid], predicted[valid]


def _designs(specs: list[Spec], record: Record, layout: Layout) -> Iterator[tuple[Spec, Design]]:
    """(spec, design) of each spec, as each is built; a family's lower degrees at the same lags reuse its
    highest degree's features.

    The network inputs are built once per lag span, not once per spec: on a 40 000-sample
    record of seven columns, building them was a third of the designs' time."""
    tops: dict[tuple[str, int], Design] = {}
    inputs: dict[int, tuple] = {}
    for spec in sorted(specs, key=lambda s: (s.lags, s.family, -s.degree)):
        if spec.lags not in inputs:
            inputs.clear()  # one span at a time: a long span's inputs are hundreds of MB
            tops.clear()
            inputs[spec.lags] = valid_inputs(record, layout.with_lags(spec.lags))
        top = tops.get((spec.family, spec.lags))
        if top is not None:
            shared = top.leading(spec.dictionary(inputs[spec.lags][0]))
            if shared is not None:
                yield spec, shared
                continue
        design = Design.of(spec, record, layout, inputs[spec.lags])
        tops.setdefault((spec.family, spec.lags), design)
        yield spec, design


def order_candidates(candidates: list[Candidate]) -> list[Candidate]:
    """Sorted by score, then the one to use moved first.

    A nonlinear candidate must beat the best linear one by NONLINEAR_GAIN (linear models
    extrapolate gracefully; a nonlinearity the blocks barely vouch for may not); and of
    the candidates within PARSIMONY of the lowest score the one with the fewest terms is
    used (it has fitted the least noise and has the fewest terms that can run away); the
    increment form's pass-through terms count, as the weights the node will adapt.
    """
    ordered = sorted(candidates, key=lambda c: c.rmse_validation)
    for candidate in ordered:
        candidate.note = ""
    usable = [c for c in ordered if c.model is not None]
    if not usable:
        return ordered
    linear = [c for c in usable if c.linear]
    bar = linear[0].rmse_validation * (1.0 - NONLINEAR_GAIN) if linear else math.inf
    eligible = [c for c in usable if c.linear or c.rmse_validation <= bar] or usable
    best = eligible[0]
    close = [c for c in eligible if c.rmse_validation <= best.rmse_validation * (1.0 + PARSIMONY)]
    chosen = min(close, key=lambda c: (c.weights, c.rmse_validation))
    if chosen is not ordered[0]:
        top = ordered[0]
        chosen.note = f"chosen over {top.spec.label} ({top.rmse_validation:.5g}): " + (
            f"fewest terms within {PARSIMONY:.0%} of the lowest score"
            if top in eligible
            else f"a nonlinear candidate must beat the best linear one by {NONLINEAR_GAIN:.0%}"
        )
        ordered.remove(chosen)
        ordered.insert(0, chosen)
    return ordered


# -- several outputs simulated together --------------------------------------------------------


def joint_block_score(
    candidates: list[Candidate], columns: list[list[int]], values: np.ndarray, breaks: np.ndarray
) -> tuple[float, list[float]]:
    """How several outputs' chosen candidates simulate *together* on the selection's blocks.

    Each block is simulated from the measured outputs just before it, every output by
    its candidate's weights fitted without that block, each fed the others' simulated
    outputs: what a model of several outputs is used for, which each output's own score
    (the others measured, when it reads them) cannot tell. Returns (the outputs' mean
    NMSE pooled over the blocks, each output's NMSE); inf where a block diverges, leaves
    the range or is worse than its mean for some output.
    """
    lags = max(c.model.layout.lags for c in candidates)
    models = [c.model.with_lags(lags) for c in candidates]
    record = Record.of(values, breaks)
    warm = models[0].warm_up
    blocks = fold_blocks(record.n, warm)
    n_y = len(models)
    squared, deviation = np.zeros(n_y), np.zeros(n_y)
    for fold, (a, b) in enumerate(blocks):
        weights = [np.asarray(c.fold_weights[fold]) for c in candidates]
        for first, stop in record.pieces(a, b, warm):
            simulated, clipped, diverged_at = simulate_joint(
                models, columns, weights, values[first - warm : stop], warm
            )
            if diverged_at >= 0 or clipped:
                return math.inf, [math.inf] * n_y
            measured = values[first:stop, :n_y]
            squared += ((simulated[warm:, :n_y] - measured) ** 2).sum(axis=0)
            deviation += ((measured - measured.mean(axis=0)) ** 2).sum(axis=0)
    nmse = squared / np.maximum(deviation, 1e-300)
    if np.any(nmse > 1.0):
        return math.inf, [float(v) for v in nmse]
    return float(np.mean(nmse)), [float(v) for v in nmse]
