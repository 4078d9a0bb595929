"""``lenn-ros fit DATA --test-from K``: build a good model of logged data, automatically.

One procedure for any number of inputs and outputs (a single channel is the 1 x 1 case),
each step reported:
1. reads u and y from a CSV file (one ``--u`` / ``--y`` column each, or several) or a
   bag (:mod:`lenn_ros.fit.load`); samples numbered below K build the model, samples K..
   only score it (:mod:`lenn_ros.fit.numbering`: a bag's sample indices, a CSV's data rows); gaps
   in the record stay gaps (nothing is fitted or simulated across them);
2. takes offsets and scale factors of every channel from the training samples (with a
   margin: :func:`lenn_ros.core.scaling.ranges`);
3. for each output, selects the family (:data:`lenn_ros.fit.families.FAMILIES`), the lags and
   the terms over that output's *view*: its own past and every input
   (:class:`~lenn_ros.fit.termmodel.Layout`). Orthogonal forward regression ranks the terms;
   every candidate is judged by the free runs of blocks of the training samples, each
   simulated by the weights of the other blocks, and rejected when it runs away, leaves the
   range or does worse than the mean anywhere (:mod:`lenn_ros.fit.selection`). An output's
   model reads the inputs and its own past only, never another output's, so the block free
   runs that choose it are exactly how it runs inside the several-output model's free run;
4. refines the weights of each output's best few candidates on simulation error, as
   many iterations as the blocks vouch for, zero included (:mod:`lenn_ros.fit.refinement`,
   run side by side by :mod:`lenn_ros.fit.schedule`), and keeps the best; the weights
   delivered are those of all training samples;
5. scores the frozen model on the test samples (:mod:`lenn_ros.fit.scoring`): one-step and
   free run (the free run starts from the measured outputs just before sample K, as a live
   switch from series-parallel to parallel would; several outputs run together), counting
   clipped inputs and flagging divergence;
6. with ``-o DIR`` writes ``params.yaml`` and ``weights.npz`` from which the identifier
   node starts and keeps adapting live (RLS with forgetting): one channel each side as
   the node's single-channel parameters, several as its several-channel ones, with each
   output's selected terms (``y1: u0_2*y1_1``) (:mod:`lenn_ros.fit.export`).

``--network mlp`` and ``--solver sgd`` train one input's and one output's selected
structure by epochs instead (:func:`~lenn_ros.fit.training.fit_mlp`,
:func:`~lenn_ros.fit.training.fit_lenn_sgd`).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from lenn_ros.core.scaling import DEFAULT_MARGIN, ranges
from lenn_ros.core.structure import Identifier
from lenn_ros.core.threads import cores, side_by_side
from lenn_ros.fit.data import Data, FitError
from lenn_ros.fit.delay import delays_text, input_delays, shifted
from lenn_ros.fit.export import describe_mimo, describe_model, identifiers, live_forgetting
from lenn_ros.fit.families import candidate_specs
from lenn_ros.fit.memory import within_memory
from lenn_ros.fit.numbering import first_test_row, number, span, split_numbers
from lenn_ros.fit.record import Record, fold_blocks
from lenn_ros.fit.records import records_report
from lenn_ros.fit.rest import without_rest
from lenn_ros.fit.result import FitResult, OutputFit
from lenn_ros.fit.schedule import refine_outputs, refinement_jobs, views_side_by_side
from lenn_ros.fit.scoring import TestPart, fit_intervals, score
from lenn_ros.fit.selection import NONLINEAR_GAIN, PARSIMONY, Candidate, joint_block_score, loosen, select_structure
from lenn_ros.fit.signs import recover_signs
from lenn_ros.fit.termmodel import Layout


def check_split(data: Data, test_from: int | None, recorded: bool = False) -> int:
    """0-based row of the first test sample: the first numbered ``test_from`` or above
    (:func:`~lenn_ros.fit.numbering.first_test_row`), with enough samples before it to build on."""
    start = first_test_row(data, test_from, recorded)
    if start < 100:
        asked = "the recorded test start" if recorded else "--test-from"
        raise FitError(f"only {start} samples before {asked} {test_from}; a model needs at least 100 to build on")
    return start


def fit(
    data: Data,
    test_from: int | None,
    *,
    refine: bool = True,
    network: str = "lenn",
    solver: str = "ls",
    progress: Any = None,
    recorded: bool = False,
) -> FitResult:
    """The whole procedure; returns its result: the report's figures (:meth:`FitResult.as_dict` is what
    ``--json`` prints), the identifier and the models.

    ``test_from``: the number of the first test sample (:mod:`~lenn_ros.fit.numbering`: a bag's sample index, a
    CSV's data row): samples numbered below it build the model, the others score it; ``recorded``: it is the
    bag's recorded test start (said so where refused).

    Each output's structure is chosen on blocks of the training samples (each simulated by
    the weights of the others), the weights delivered are those of all training samples,
    refined on simulation error as many times as the blocks vouch for
    (:func:`~lenn_ros.fit.refinement.cross_validated_refinement`). ``solver="sgd"``
    trains the selected terms by SGD epochs instead (:func:`~lenn_ros.fit.training.fit_lenn_sgd`), for a node
    that will learn by SGD; ``network="mlp"`` an MLP on the selected lags (one input, one output).
    """
    from threadpoolctl import threadpool_limits

    # the selection's linear algebra is thousands of small products: BLAS threads only
    # contend for the cores (a 2666 x 40 Gram took 1.8 ms threaded, 0.34 ms on one thread)
    with threadpool_limits(limits=1, user_api="blas"):
        start = check_split(data, test_from, recorded)
        part, part_test_from, said = data, start + 1, {}
        for key, rule in LEFT_OUT.items():  # each rule on what the ones before left
            part, part_test_from, done = rule(part, part_test_from)
            if done:
                said[key] = done
                if progress:
                    progress(f"note: {done['text']}")
        result = _fit(part, part_test_from - 1, refine, network, solver, progress)
    # the report counts samples as the user does: by number, the rows the rules left out included
    result.test_from, result.train_samples, result.left_out = int(test_from), start, said
    result.numbers = split_numbers(data, start, int(test_from))
    result.records = records_report(data, result.per_output) if data.records else []
    return result


#: the rules that leave training rows out before the fit, in order, by the report's key for what each did
LEFT_OUT = {"rest": without_rest, "memory": within_memory}


def _fit(data: Data, start: int, refine: bool, network: str, solver: str, progress: Any) -> FitResult:
    """The procedure on the rows the rules of LEFT_OUT left, the test part from 0-based row ``start``; the samples
    it names are numbered as ``data`` numbers them (its rows left out keep their numbers: :meth:`Data.kept`)."""
    began = time.perf_counter()
    say = progress or (lambda text: None)
    u, y = data.matrices()
    _check_channels(data, u, y, network, solver)
    single = data.n_u == 1 and data.n_y == 1
    breaks = [b for b in data.breaks if 0 < b < start]
    try:
        u_offsets, u_scales = ranges(u[:start], data.u_names)
        y_offsets, y_scales = ranges(y[:start], data.y_names)
    except ValueError as error:
        raise FitError(str(error)) from None
    blocks = fold_blocks(start, 1)
    say(
        f"selecting a structure on samples {span(data, 0, start - 1)}: {len(blocks)} blocks, each simulated by the "
        f"weights of the others{f', {len(breaks)} gaps in the record' if breaks else ''}"
    )
    lenn_ls = network == "lenn" and solver == "ls"
    outputs, coupling = _fit_outputs(data, u[:start], y[:start], breaks, (y_offsets, y_scales, u_offsets, u_scales),
                                     refine and lenn_ls, say)  # fmt: skip
    if single and lenn_ls:
        outputs = _signed_view(data, u[:start], y[:start], breaks, (u_offsets, u_scales), outputs, refine, say)
    forgetting = live_forgetting(start)
    identifier, described, models = identifiers(outputs, data, u[:start], y[:start], network, solver, forgetting, say)
    scored = score(identifier, data, start, models, [fitted.columns for fitted in outputs])
    made = (described, forgetting, len(blocks), len(breaks), span(data, 0, start - 1))
    _complete(scored, outputs, identifier if single else None, lenn_ls, made)
    coupled = {"coupling": coupling} if coupling else {}
    model = described if single else {**describe_mimo(models, forgetting), **coupled}
    return FitResult(
        data=data.source, test_from=number(data, start), train_samples=start, per_output=scored.outputs,
        free_run=scored.free_run, model=model, inputs=list(data.u_names), outputs=list(data.y_names),
        seconds=round(time.perf_counter() - began, 2), identifier=identifier, models=models, fits=outputs,
    )  # fmt: skip


def _check_channels(data: Data, u: np.ndarray, y: np.ndarray, network: str, solver: str) -> None:
    """FitError for samples that hold NaN/inf, and for several channels asked to be fitted other than by the
    LeNN by least squares."""
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        bad = int(np.count_nonzero(~(np.isfinite(u).all(axis=1) & np.isfinite(y).all(axis=1))))
        raise FitError(f"{bad} samples hold NaN/inf: remove or interpolate them before fitting")
    if not (data.n_u == 1 and data.n_y == 1) and (network != "lenn" or solver != "ls"):
        raise FitError(
            f"{data.n_u} inputs and {data.n_y} outputs: only the LeNN by least squares is fitted for several "
            "channels (drop --network/--solver)"
        )


def _complete(
    scored: TestPart, outputs: list[OutputFit], identifier: Identifier | None, held_out: bool, made: tuple
) -> None:
    """Each output's report beyond its test figures: its warnings first, its 95 % bands (each output's its own:
    on the cores side by side), its model and how it was chosen. ``identifier``: one input's and one output's
    (its in-sample bands when not ``held_out``); ``made``: (the single output's model description, the live
    forgetting, the blocks, the gaps, the training samples' numbers)."""
    described, forgetting, blocks, gaps, trained = made
    bands = side_by_side(
        lambda j: fit_intervals(scored.outputs[j], scored.y_hat_train[j], identifier, outputs[j], held_out),
        range(len(outputs)),
        cores(),
    )
    for fitted, part, intervals in zip(outputs, scored.outputs, bands, strict=True):
        part.warnings = fitted.warnings + part.warnings
        part.intervals = intervals
        part.model = described if described is not None else describe_model(fitted.model, fitted.chosen, forgetting)
        part.choices = _choices(fitted, blocks, gaps, trained)


def _fit_outputs(
    data: Data, u: np.ndarray, y: np.ndarray, breaks: list[int], scaling: tuple, refine: bool, say: Any
) -> tuple[list[OutputFit], dict[str, Any]]:
    """Each output's model, and how the outputs are coupled: (the fits, what was chosen and why).

    Output j's view is its own past and every input; with several outputs, also every other
    output's past (measured, as the node's series-parallel mode has them). Reading the other
    outputs helps when the plant couples them (a joint's load on the next joint), and can
    hurt in simulation, where each is fed the others' errors. So both are built and the
    two models of all outputs are judged as they are used, by their free runs *together* on
    the selection's blocks (:func:`~lenn_ros.fit.selection.joint_block_score`); reading the
    other outputs must win by NONLINEAR_GAIN. With the other outputs an output's view is
    several times wider, so it is offered the polynomial family (where a coupling such as
    y1 / (1 + y2^2) is expressed) and the COUPLED_SPECS structures that served the output
    best alone, not the whole grid again (which cost 1.5x the first pass on a six-joint
    robot). The two are judged on their least-squares models (the blocks' weights are
    those in either case), and only the outputs of the one used are refined on simulation
    error: refining the other's too cost a six-joint robot's fit a third of its time. The
    outputs are fitted side by side on the machine's cores (the kernels release the GIL);
    what each says is printed when it is done, in order.
    """
    y_offsets, y_scales, u_offsets, u_scales = scaling
    n_y, n_u = data.n_y, data.n_u
    single = n_u == 1 and n_y == 1
    values = np.column_stack([y, u])

    def view(j: int, kind: str, alone: OutputFit | None, said: list[str]) -> OutputFit:
        others = [k for k in range(n_y) if k != j] if kind == "coupled" else []
        where = [j, *others, *(n_y + i for i in range(n_u))]
        names = ("y", "u") if single else tuple(f"y{c}" if c < n_y else f"u{c - n_y}" for c in where)
        offsets = tuple(y_offsets[c] if c < n_y else u_offsets[c - n_y] for c in where)
        scales = tuple(y_scales[c] if c < n_y else u_scales[c - n_y] for c in where)
        if not single:
            reads = f"the other outputs' past and the {n_u} inputs" if others else f"the {n_u} inputs"
            said.append(f"output {data.y_names[j]} ({names[0]}): its own past and {reads}")
        record = Record.of(values[:, where], breaks)
        specs = None if alone is None else _coupled_specs(alone, record.n, len(where))
        layout = Layout(1, offsets, scales, names)
        workers = cores() if n_y == 1 else 1  # one output: its candidates side by side; several: the outputs
        # each input's dead time (the coupled view reads the inputs as the output's own view settled them; the
        # other outputs' past has none): :func:`_fit_behind_dead_time`
        own = input_delays(record.values, record.breaks) if alone is None else alone.delays
        delays = (0,) * len(others) + own
        tell = say if n_y == 1 else said.append
        if any(delays) and alone is None:
            tell(f"output {data.y_names[j]}: dead time {delays_text(delays, names[1:])}; the terms read each input "
                 "from its dead time back")  # fmt: skip
        fitted = _fit_behind_dead_time(data.y_names[j], record, layout, delays, refine and n_y == 1, tell, specs,
                                       workers)  # fmt: skip
        fitted.columns = where
        return fitted

    if n_y == 1:
        said: list[str] = []
        fitted = view(0, "own", None, said)
        for line in said:  # several inputs: which it reads
            say(line)
        return [fitted], {}

    def together(fits: list[OutputFit]) -> tuple[float, list[float]]:
        return joint_block_score([f.chosen for f in fits], [f.columns for f in fits], values, np.asarray(breaks))

    spare = refinement_jobs if refine else None
    fits, scores, ahead = views_side_by_side(n_y, view, together, say, spare)
    own, coupled = scores["own"][0], scores["coupled"][0]
    kind = "coupled" if coupled < (1.0 - NONLINEAR_GAIN) * own else "own"
    say(f"outputs together on the blocks: mean NMSE {own:.4g} reading only their own past, {coupled:.4g} "
        f"reading the other outputs too: {'the latter' if kind == 'coupled' else 'the former'} is used")  # fmt: skip
    if refine:
        refine_outputs(fits[kind], say, cores(), ahead if kind == "own" else {})
    coupling = {
        "reads_other_outputs": kind == "coupled",
        "judged_by": "mean over outputs of the NMSE of all outputs simulated together on the blocks, each by the "
        "weights fitted without its block; reading the other outputs must win by "
        f"{NONLINEAR_GAIN:.0%}",
        "nmse_blocks": {
            k: {"mean": _finite(v[0]), "per_output": [_finite(x) for x in v[1]]} for k, v in scores.items()
        },
    }
    return fits[kind], coupling


def _signed_view(
    data: Data,
    u: np.ndarray,
    y: np.ndarray,
    breaks: list[int],
    u_scaling: tuple,
    outputs: list[OutputFit],
    refine: bool,
    say: Any,
) -> list[OutputFit]:
    """An output that reads like an absolute value (a speed through a pulse counter) is also fitted on
    its signed record (:mod:`~lenn_ros.fit.signs`); the signed model is kept when its pooled free-run
    RMSE over the blocks is lower, and the node then runs it with ``y_abs``. (The signed model's block
    error is against the signed record: at least its error in |y|, so a tie keeps the plain model.)"""
    signs = recover_signs(u[:, 0], y[:, 0], breaks)
    if signs is None:
        return outputs
    say(
        f"the output reads like an absolute value ({signs.runs} runs between near-zero minima): fitting its "
        f"signed record too (signs from a linear model of the input, its free run of |y| {signs.arx_nmse_db:.1f} dB)"
    )
    signed = signs.signed[:, None]
    try:
        y_offsets, y_scales = ranges(signed, data.y_names)
    except ValueError:
        return outputs
    view, _ = _fit_outputs(data, u, signed, breaks, (y_offsets, y_scales, *u_scaling), refine, say)
    plain, other = outputs[0].chosen.rmse_validation, view[0].chosen.rmse_validation
    used = other < plain
    verdict = "the signed model is used (y_abs: the node signs each y as its model does)" if used else "kept as read"
    say(f"blocks' pooled free-run RMSE: {plain:.5g} on |y| as read, {other:.5g} on the signed record: {verdict}")
    kept = view if used else outputs
    kept[0].sign = {
        "read_as": "absolute value" if used else "as measured",
        "used": used,
        "rmse_blocks": {"as_measured": _finite(plain), "signed": _finite(other)},
        **signs.as_dict(),
    }
    return kept


def _fit_behind_dead_time(
    name: str,
    record: Record,
    layout: Layout,
    delays: tuple[int, ...],
    refine: bool,
    say: Any,
    specs: list | None,
    workers: int,
) -> OutputFit:
    """One output's fit with its inputs' dead times (``delays``, per column after the output): the families are
    built over the view with each input moved down by its dead time (:func:`~lenn_ros.fit.delay.shifted`), so
    the nonlinear terms' newest lags are those that act, and the models are then written over the view as
    measured (:meth:`~lenn_ros.fit.termmodel.TermModel.delayed`), which refinement, scoring and the node use."""
    if not any(delays):
        fitted = _fit_output(name, record, layout, refine, say, specs, workers)
        fitted.delays = delays
        return fitted
    late = _fit_output(name, Record.of(*shifted(record.values, record.breaks, delays)), layout, False, say, specs,
                       workers)  # fmt: skip
    for candidate in late.candidates:
        if candidate.model is not None:
            candidate.model = candidate.model.delayed((0, *delays))
    late.record, late.delays = record, delays
    if refine:
        refine_outputs([late], say, workers)
    return late


#: structures (best first, from an output's own view) tried again reading the other outputs too, and the
#: longest lags of the polynomial family offered with them
COUPLED_SPECS = 4
COUPLED_LAGS = 3


def _coupled_specs(alone: OutputFit, n: int, columns: int) -> list:
    """The grid of an output's view with the other outputs: the families offered there (a registry entry's
    ``coupled``: the polynomial family) up to COUPLED_LAGS, and the COUPLED_SPECS structures that served it best
    alone."""
    best = [c.spec for c in alone.candidates if c.model is not None][:COUPLED_SPECS]
    offered = [s for s in candidate_specs(n, columns) if s.registered.coupled and s.lags <= COUPLED_LAGS]
    return offered + [spec for spec in best if spec not in offered]


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _fit_output(
    name: str, record: Record, layout: Layout, refine: bool, say: Any, specs: list | None = None, workers: int = 1
) -> OutputFit:
    """Select (and refine) one output's model over its view of the training samples (``specs``: the grid's;
    ``workers``: threads for its candidates)."""
    candidates, warnings = _select(record, layout, say, specs, workers)
    fitted = OutputFit(name, record, layout, candidates, candidates[0], {"done": False}, warnings)
    if refine:
        refine_outputs([fitted], say, workers)
    return fitted


def _choices(fitted: OutputFit, blocks: int, gaps: int, trained: str) -> dict[str, Any]:
    """How one output's model was chosen, as the report gives it (``trained``: the training samples' numbers)."""
    layout = fitted.layout
    scaling: dict[str, Any] = {"from": f"training samples {trained}", "margin": DEFAULT_MARGIN}
    if layout.n_columns == 2:  # one output of one input: y_offset, y_scale, u_offset, u_scale
        for name, offset, scale in zip(("y", "u"), layout.offsets, layout.scales, strict=True):
            scaling.update({f"{name}_offset": offset, f"{name}_scale": scale})
    else:
        scaling["offsets"] = dict(zip(layout.names, layout.offsets, strict=True))
        scaling["scales"] = dict(zip(layout.names, layout.scales, strict=True))
    return {
        "scaling": scaling,
        "blocks": blocks,
        "gaps": gaps,
        "judged_by": f"pooled free-run RMSE over {blocks} blocks of the training samples, each "
        "simulated from its measured start by the weights fitted to the other blocks; rejected: diverged, "
        "clipped or worse than the block mean in any block, an unsound free run over the whole training "
        "record or on its input shuffled in blocks (a model that integrates exactly: its increments outside "
        "the training increments' range); a nonlinear candidate must beat the best linear one by "
        f"{NONLINEAR_GAIN:.0%}; of those within {PARSIMONY:.0%} of the lowest, the fewest terms",
        "candidates": [c.as_dict() for c in fitted.candidates],
        "chosen": fitted.candidates.index(fitted.chosen),
        "refinement": fitted.refinement,
        "time_scale": fitted.chosen.spec.time_scale,
        "dead_time": {name: d for name, d in zip(fitted.layout.names[1:], fitted.delays, strict=True) if d},
        **({"sign": fitted.sign} if fitted.sign else {}),
    }


def _select(
    record: Record, layout: Layout, say: Any, specs: list | None = None, workers: int = 1
) -> tuple[list[Candidate], list[str]]:
    """(candidates, warnings): the strict selection, else the loose one with a warning, else FitError."""

    def tell(candidate: Candidate) -> None:
        shown = (
            f"{candidate.terms} terms, free-run RMSE {candidate.rmse_validation:.5g}"
            if candidate.model is not None
            else f"rejected ({candidate.rejected})"
        )
        say(f"  {candidate.spec.label}: {shown}")

    candidates = select_structure(record, layout, specs, progress=tell, workers=workers)
    warnings = []
    if any(c.model is not None for c in candidates):
        for candidate in candidates:  # the loose rules are not needed: free each one's ranked features
            candidate.fallback = None
    else:
        # nothing passed the strict checks: the best that merely simulates the blocks,
        # flagged, beats no model at all (the user still learns the lags and what failed)
        strict_reasons = sorted(
            {reason for c in candidates for reason in c.rejected.removeprefix("every prefix: ").split("; ") if reason}
        )
        candidates = loosen(candidates, record)
        warnings.append(
            "no candidate structure passed the strict checks (free run better than the mean on every held-out "
            "block, sound on the whole training record and on its input shuffled, inside the training range): "
            f"the best held-out one is used, do not trust it far ({'; '.join(strict_reasons)})"
        )
    if not any(c.model is not None for c in candidates):
        reasons = sorted({c.rejected for c in candidates})
        raise FitError(f"no candidate structure simulates stably on the held-out blocks ({'; '.join(reasons)})")
    return candidates, warnings
