"""``lenn-ros fit DATA --test-from K``: build a good model of logged data, automatically.

One procedure for any number of inputs and outputs (a single channel is the 1 x 1 case),
each step reported:
1. reads u and y from a CSV file (one ``--u`` / ``--y`` column each, or several) or a
   bag; samples 1..K-1 (1-based) build the model, samples K.. only score it; gaps in a
   bag's record stay gaps (nothing is fitted or simulated across them);
2. takes offsets and scale factors of every channel from the training samples (with a
   margin: :func:`lenn_ros.core.scaling.ranges`);
3. for each output, selects the family (polynomial, hinge, rff, index, increment, stick,
   legendre, fir: :mod:`lenn_ros.fit.families`), the lags and the terms over that output's *view*:
   its own past and every input (:class:`~lenn_ros.fit.termmodel.Layout`). Orthogonal
   forward regression ranks the terms; every candidate is judged by the free runs of
   blocks of the training samples, each simulated by the weights of the other blocks,
   and rejected when it runs away, leaves the range or does worse than the mean anywhere
   (:mod:`lenn_ros.fit.selection`). An output's model reads the inputs and its own past
   only, never another output's, so the block free runs that choose it are exactly how
   it runs inside the several-output model's free run;
4. refines the weights of each output's best few candidates on simulation error, as
   many iterations as the blocks vouch for, zero included (:mod:`lenn_ros.fit.refinement`),
   and keeps the best; the weights delivered are those of all training samples;
5. scores the frozen model on the test samples: one-step and free run (the free run
   starts from the measured outputs just before sample K, as a live switch from
   series-parallel to parallel would; several outputs run together), counting clipped
   inputs and flagging divergence;
6. with ``-o DIR`` writes ``params.yaml`` and ``weights.npz`` from which the identifier
   node starts and keeps adapting live (RLS with forgetting): one channel each side as
   the node's single-channel parameters, several as its several-channel ones, with each
   output's selected terms (``y1: u0_2*y1_1``).

``--network mlp`` and ``--solver sgd`` train one input's and one output's selected
structure by epochs instead (:func:`fit_mlp`, :func:`fit_lenn_sgd`).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lenn_ros import topics
from lenn_ros.core.evaluation import free_run_problems, free_run_segments
from lenn_ros.core.metrics import band_half_width, coverage, nmse_db, rmse
from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.networks import FunctionalLinkNetwork
from lenn_ros.core.scaling import DEFAULT_MARGIN, ranges
from lenn_ros.core.structure import Identifier
from lenn_ros.core.threads import cores, side_by_side
from lenn_ros.fit.data import REPORT_FILE, Data, FitError
from lenn_ros.fit.delay import input_delays, shifted
from lenn_ros.fit.families import candidate_specs
from lenn_ros.fit.families.base import pass_through_weights
from lenn_ros.fit.memory import within_memory
from lenn_ros.fit.record import Record, fold_blocks
from lenn_ros.fit.refinement import Refinement, blocks_choice, fold_history, refine_on_folds
from lenn_ros.fit.rest import without_rest
from lenn_ros.fit.selection import (
    NONLINEAR_GAIN,
    PARSIMONY,
    Candidate,
    joint_block_score,
    loosen,
    order_candidates,
    out_of_fold_residuals,
    select_structure,
)
from lenn_ros.fit.signs import recover_signs
from lenn_ros.fit.soundness import level_free, output_rows, widened
from lenn_ros.fit.termmodel import Layout, TermModel, siso_view
from lenn_ros.table import TableError, read_table

#: share of the training samples the epochs of an MLP / SGD fit are early-stopped on
VALIDATION_FRACTION = 0.2
MIN_VALIDATION = 50
#: relative ridge on the live RLS start covariance (see build_identifier): condition number <= 1e7,
#: well inside the ~1/sqrt(machine epsilon) ~ 7e7 at which conventional RLS goes indefinite by round-off
RLS_RIDGE = 1e-7


def load_data(
    path: str | Path,
    u_columns: str | list[str] | None = None,
    y_columns: str | list[str] | None = None,
    flags: dict[str, Any] | None = None,
) -> Data:
    """u and y from a bag (directory or .mcap) or a CSV file (columns by name or index), any number of each.

    A bag the identifier was recorded beside (its ``identifier_config``), or whose topics the
    flags name, is paired by the node's session (:func:`lenn_ros.fit.bag.load_bag`: ``--u`` /
    ``--y`` are topics); an ``import-csv`` bag of Float64MultiArray samples (no configuration)
    is read by message order, ``--u`` / ``--y`` picking its channels by label.
    """
    path = Path(path)
    u_columns, y_columns = columns(u_columns), columns(y_columns)
    flags = dict(flags or {})
    time_column = flags.pop("time", None)  # a CSV's; every other flag is a bag's
    if not path.exists():
        raise FitError(f"{path} does not exist (expected a CSV file or a bag directory)")
    if path.is_dir() or path.suffix == ".mcap":
        if time_column:
            raise FitError("--time: for a CSV file; a bag's samples carry their stamps (--sample-period sets a grid)")
        flags = {**flags, "u": u_columns or None, "y": y_columns or None}
        if is_vector_bag(path) and not _configured(path, flags):
            return _load_vector_bag(path, u_columns, y_columns)
        from lenn_ros.fit.bag import load_bag

        return load_bag(path, {key: value[0] if isinstance(value, list) and len(value) == 1 else value
                               for key, value in flags.items()})  # fmt: skip
    bag_only = sorted(key for key, value in flags.items() if value)
    if bag_only:
        raise FitError(f"{', '.join('--' + k.replace('_', '-') for k in bag_only)}: for a bag, not a CSV file")
    return _load_csv(path, u_columns, y_columns, time_column)


def _configured(path: Path, flags: dict[str, Any]) -> bool:
    """Whether a bag is read by the node's session: an identifier_config, or bag flags that say how."""
    from lenn_ros.fit.bag import has_identifier_config

    return has_identifier_config(path) or any(value for key, value in flags.items() if key not in ("u", "y"))


def _load_csv(path: Path, u_columns: list[str], y_columns: list[str], time_column: str | None = None) -> Data:
    """The columns asked for (:mod:`lenn_ros.table` reads any delimiter). A row missing a sample in one of
    them is a gap: dropped, the record broken there (never joined across), its rows still counted by
    ``--test-from`` (``Data.index``), and the lines named in the report's data line. ``time_column``: the
    samples' times, whose jumps are gaps too (:func:`_time_gaps`)."""
    named = any(not column.strip().isdigit() for column in (*u_columns, *y_columns))
    try:
        table = read_table(path, named)
        header, width = table.header, table.width
        if not u_columns or not y_columns:
            if header and "u" in header and "y" in header:
                u_columns, y_columns = u_columns or ["u"], y_columns or ["y"]
            elif width == 2:
                u_columns, y_columns = u_columns or ["0"], y_columns or ["1"]
            else:
                shown = ", ".join(header) if header else f"{width} unnamed columns"
                raise FitError(f"{path} has columns {shown}: pass --u COL --y COL (name or 0-based index)")
        wanted = [*u_columns, *y_columns]
        indices = [table.column(column) for column in wanted]
        timed = [table.column(time_column)] if time_column is not None else []
        values, missing = table.values(indices + timed)
    except TableError as error:
        raise FitError(str(error)) from None
    kept = np.isfinite(values).all(axis=1)
    if not kept.any():
        raise FitError(f"{path}: no data row holds a number in every column asked for")
    period, late, timing = None, [], ""
    if timed:
        name = header[timed[0]] if header else str(timed[0])
        lines = [table.rows[r][0] for r in np.flatnonzero(kept)]
        period, late, timing = _time_gaps(values[kept, -1], lines, f"{path}: time column {name!r}")
        values = values[:, :-1]
    names = tuple(header[i] if header else str(i) for i in indices)
    split = len(u_columns)
    u_names, y_names = names[:split], names[split:]
    plural = "s" if len(wanted) > 2 else ""
    source = f"CSV {path}: u = column{plural} {', '.join(u_names)}, y = column{plural} {', '.join(y_names)}"
    if missing:
        source += (
            f"; {len(missing)} row{'s' if len(missing) > 1 else ''} missing a sample (empty, NaN, inf or short; "
            f"line{'s' if len(missing) > 1 else ''} {_lines_shown(missing)}): gaps, never fitted or scored across"
        )
    u, y = values[:, :split], values[:, split:]
    data = Data(u[:, 0] if split == 1 else u, y[:, 0] if len(y_names) == 1 else y, source + timing,
                u_names=u_names, y_names=y_names, sample_period=period).kept(kept)  # fmt: skip
    return dataclasses.replace(data, breaks=sorted({*data.breaks, *late})) if late else data


#: lines named in the report's data line for rows missing a sample or after a time jump (the count is always given)
MISSING_SHOWN = 5
#: a time step longer than this many sample periods (the median step) is a gap: samples were lost there
GAP_STEPS = 1.5
#: steps further than this share from the sample period are counted as irregular
JITTER = 0.1


def _lines_shown(lines: list[int]) -> str:
    """The first MISSING_SHOWN file lines, and "..." when there are more."""
    return ", ".join(map(str, lines[:MISSING_SHOWN])) + (", ..." if len(lines) > MISSING_SHOWN else "")


def _time_gaps(times: np.ndarray, lines: list[int], where: str) -> tuple[float, list[int], str]:
    """(the sample period: the median step, the rows after a jump of more than GAP_STEPS periods, what the
    report's data line says). A time that does not increase is an error naming its line: rows out of order or
    repeated would be fitted as the plant's own dynamics."""
    steps = np.diff(times)
    if not len(steps):
        raise FitError(f"{where}: one row only")
    back = np.flatnonzero(steps <= 0.0)
    if len(back):
        i = int(back[0]) + 1
        raise FitError(
            f"{where}, line {lines[i]}: {times[i]:g} does not come after {times[i - 1]:g} (line {lines[i - 1]}): "
            "sort the rows or drop the repeats"
        )
    period = float(np.median(steps))
    late = [int(i) + 1 for i in np.flatnonzero(steps > GAP_STEPS * period)]
    irregular = int(np.count_nonzero(np.abs(steps - period) > JITTER * period)) - len(late)
    text = f"; {where.split(': ', 1)[1]}: sample period {period:.6g} s (the median step)"
    if late:
        text += (
            f", {len(late)} jump{'s' if len(late) > 1 else ''} longer than {GAP_STEPS:g} periods (before "
            f"line{'s' if len(late) > 1 else ''} {_lines_shown([lines[i] for i in late])}): gaps, never fitted or "
            "scored across"
        )
    if irregular:
        text += f", {irregular} step{'s' if irregular > 1 else ''} off it by more than {JITTER:.0%}"
    return period, late, text


def _load_vector_bag(path: Path, u_columns: list[str], y_columns: list[str]) -> Data:
    """An ``import-csv`` bag of labelled Float64MultiArray samples, its channels picked by label or index."""
    from lenn_ros.bag.vectors import read_vector_run

    run = read_vector_run(path)
    iu = [_channel(run.u_names, c, path, "u") for c in u_columns] or list(range(len(run.u_names)))
    iy = [_channel(run.y_names, c, path, "y_p") for c in y_columns] or list(range(len(run.y_names)))
    u_names, y_names = tuple(run.u_names[i] for i in iu), tuple(run.y_names[i] for i in iy)
    source = f"bag {path}: u = {', '.join(u_names)}; y_p = {', '.join(y_names)}"
    return Data(run.u[:, iu], run.y[:, iy], source, test_start=run.test_start, u_names=u_names, y_names=y_names)


def _channel(names: tuple[str, ...], column: str, path: Path, topic: str) -> int:
    """A bag channel by its label or 0-based index, as a CSV column is found."""
    if column in names:
        return names.index(column)
    if column.isdigit() and int(column) < len(names):
        return int(column)
    raise FitError(f"{path}: no {topic} channel {column!r}; channels are {', '.join(names)}")


def check_split(n: int, test_from: int) -> int:
    """0-based index of the first test sample from the 1-based ``--test-from``."""
    if test_from is None:
        raise FitError(
            "pass --test-from K: the 1-based index of the first test sample (samples 1..K-1 build the model)"
        )
    if not 2 <= test_from <= n:
        raise FitError(f"--test-from {test_from} is outside the data's samples 2..{n} (1-based)")
    start = test_from - 1
    if start < 100:
        raise FitError(f"only {start} samples before --test-from {test_from}; a model needs at least 100 to build on")
    return start


def live_forgetting(n_train: int) -> float:
    """RLS forgetting factor for live tracking: a memory of the training length, 1 000..10 000 samples."""
    return 1.0 - 1.0 / min(max(n_train, 1000), 10_000)


def rls_covariance(features: np.ndarray, forgetting: float) -> np.ndarray:
    """The RLS covariance as if live adaptation had seen ``features``, scaled to the forgetting's memory.

    A ridge of RLS_RIDGE times the largest eigenvalue of the features' Gram matrix bounds
    its condition number to 1 / RLS_RIDGE: lagged outputs are nearly collinear, and the
    robot arm's 29 terms gave a condition number of 7e10, at which the conventional RLS
    update loses positive definiteness by round-off (it stopped learning at its 97th sample).
    """
    gram = features.T @ features
    gram += max(RLS_RIDGE * float(np.linalg.eigvalsh(gram)[-1]), 1e-9) * np.eye(features.shape[1])
    memory = len(features) if forgetting >= 1.0 else min(len(features), 1.0 / (1.0 - forgetting))
    return np.linalg.inv(gram) * (len(features) / memory)


@dataclass
class OutputFit:
    """What the selection made of one output: its view of the training samples, candidates and choice."""

    name: str
    record: Record
    layout: Layout
    candidates: list[Candidate]
    chosen: Candidate
    refinement: dict[str, Any]
    warnings: list[str] = field(default_factory=list)
    columns: list[int] = field(default_factory=list)  # the view's columns in [y_0.., u_0..]
    sign: dict[str, Any] | None = None  # an output read as its absolute value: what :func:`_signed_view` did
    delays: tuple[int, ...] = ()  # dead time of each column after the output, in samples (() or 0: none)

    @property
    def model(self) -> TermModel:
        return self.chosen.model


def fit(
    data: Data,
    test_from: int,
    *,
    refine: bool = True,
    network: str = "lenn",
    solver: str = "ls",
    progress: Any = None,
) -> dict[str, Any]:
    """The whole procedure; returns the report (also what ``--json`` prints), the identifier and the models.

    Each output's structure is chosen on blocks of the training samples (each simulated by
    the weights of the others), the weights delivered are those of all training samples,
    refined on simulation error as many times as the blocks vouch for
    (:func:`~lenn_ros.fit.refinement.cross_validated_refinement`). ``solver="sgd"``
    trains the selected terms by SGD epochs instead (:func:`fit_lenn_sgd`), for a node
    that will learn by SGD; ``network="mlp"`` an MLP on the selected lags (one input, one output).
    """
    from threadpoolctl import threadpool_limits

    # the selection's linear algebra is thousands of small products: BLAS threads only
    # contend for the cores (a 2666 x 40 Gram took 1.8 ms threaded, 0.34 ms on one thread)
    with threadpool_limits(limits=1, user_api="blas"):
        part, part_test_from, said = data, check_split(len(data.y), test_from) + 1, {}
        for key, rule in LEFT_OUT.items():  # each rule on what the ones before left
            part, part_test_from, done = rule(part, part_test_from)
            if done:
                said[key] = done
                if progress:
                    progress(f"note: {done['text']}")
        result = _fit(part, part_test_from, refine, network, solver, progress, test_from - part_test_from)
    if said:  # the report counts samples as the user does
        result["report"].update(test_from=test_from, train_samples=test_from - 1, **said)
    return result


#: the rules that leave training rows out before the fit, in order, by the report's key for what each did
LEFT_OUT = {"rest": without_rest, "memory": within_memory}


def _fit(
    data: Data, test_from: int, refine: bool, network: str, solver: str, progress: Any, left_out: int = 0
) -> dict[str, Any]:
    began = time.perf_counter()
    say = progress or (lambda text: None)
    u, y = data.matrices()
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        bad = int(np.count_nonzero(~(np.isfinite(u).all(axis=1) & np.isfinite(y).all(axis=1))))
        raise FitError(f"{bad} samples hold NaN/inf: remove or interpolate them before fitting")
    single = data.n_u == 1 and data.n_y == 1
    if not single and (network != "lenn" or solver != "ls"):
        raise FitError(
            f"{data.n_u} inputs and {data.n_y} outputs: only the LeNN by least squares is fitted for several "
            "channels (drop --network/--solver)"
        )
    start = check_split(len(y), test_from)
    breaks = [b for b in data.breaks if 0 < b < start]
    try:
        u_offsets, u_scales = ranges(u[:start], data.u_names)
        y_offsets, y_scales = ranges(y[:start], data.y_names)
    except ValueError as error:
        raise FitError(str(error)) from None
    blocks = fold_blocks(start, 1)
    say(
        f"selecting a structure on samples 1..{start}: {len(blocks)} blocks, each simulated by the weights "
        f"of the others{f', {len(breaks)} gaps in the record' if breaks else ''}"
    )
    lenn_ls = network == "lenn" and solver == "ls"
    outputs, coupling = _fit_outputs(data, u[:start], y[:start], breaks, (y_offsets, y_scales, u_offsets, u_scales),
                                     refine and lenn_ls, say)  # fmt: skip
    if single and lenn_ls:
        outputs = _signed_view(data, u[:start], y[:start], breaks, (u_offsets, u_scales), outputs, refine, say)
    forgetting = live_forgetting(start)
    identifier, described, models = _identifiers(outputs, data, u[:start], y[:start], network, solver, forgetting, say)
    scored = score(identifier, data, start, models, [fitted.columns for fitted in outputs], left_out)
    report: dict[str, Any] = {"data": data.source, "test_from": test_from, "train_samples": start}
    held_out = lenn_ls
    parts = []
    bands = side_by_side(  # each output's bands are its own: on the cores side by side
        lambda j: fit_intervals(scored["per_output"][j], identifier if single else None, outputs[j], held_out),
        range(len(outputs)),
        cores(),
    )
    for j, (fitted, intervals) in enumerate(zip(outputs, bands, strict=True)):
        part = scored["per_output"][j]
        part["warnings"] = fitted.warnings + part["warnings"]
        part["intervals"] = intervals
        part["model"] = described if single else describe_model(fitted.model, fitted.chosen, forgetting)
        part["choices"] = _choices(fitted, len(blocks), len(breaks))
        parts.append(part)
    report.update(_joined(parts, scored, data, models, forgetting))
    if coupling:
        report["model"]["coupling"] = coupling
    report["seconds"] = round(time.perf_counter() - began, 2)
    return {"report": report, "identifier": identifier, "model": models[0] if single else None, "models": models,
            "outputs": outputs}  # fmt: skip


def _identifiers(
    outputs: list[OutputFit],
    data: Data,
    u: np.ndarray,
    y: np.ndarray,
    network: str,
    solver: str,
    forgetting: float,
    say: Any,
) -> tuple[Identifier | MimoIdentifier, dict[str, Any] | None, list[TermModel]]:
    """(the identifier the node runs, a single output's model description, each output's model as it runs)
    from the training samples ``u``, ``y``."""
    if data.n_u == 1 and data.n_y == 1:
        if network == "lenn" and solver == "ls":  # epochs (MLP, SGD) train on the scaling as selected
            _read_wide(outputs[0].chosen)
        identifier, described = _single(outputs[0], u[:, 0], y[:, 0], network, solver, forgetting, say)
        if (outputs[0].sign or {}).get("used"):
            identifier.set_structure(dataclasses.replace(identifier.structure, y_abs=True))
            described["structure"]["y_abs"] = True
        return identifier, described, [outputs[0].model]
    for fitted in outputs:  # an output no other output reads is read as wide as a single output's
        if _read_alone(fitted.model, [other.model for other in outputs]):
            _read_wide(fitted.chosen)  # (an exact integrator only: the node then passes it through)
    identifier = build_mimo_identifier(outputs, data, forgetting)
    return identifier, None, common_lags([fitted.model for fitted in outputs])


def _joined(
    parts: list[dict[str, Any]], scored: dict[str, Any], data: Data, models: list[TermModel], forgetting: float
) -> dict[str, Any]:
    """The report's figures: one output's at the top level, several outputs' each in ``per_output``."""
    if len(parts) == 1 and data.n_u == 1:
        return {**{k: v for k, v in parts[0].items() if k != "name"}, "free_run": scored["free_run"]}
    for part in parts:
        for key in ("y_test", "y_hat_test", "y_free_test"):
            part.pop(key)
    return {
        "samples": parts[0]["samples"],
        "inputs": list(data.u_names),
        "outputs": list(data.y_names),
        "model": describe_mimo(models, forgetting),
        "per_output": parts,
        "free_run": scored["free_run"],
        "warnings": [f"{p['name']}: {text}" for p in parts for text in p.pop("warnings")],
        **{key: scored[key] for key in ("y_test", "y_hat_test", "y_free_test")},
    }


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
            tell(f"output {data.y_names[j]}: dead time {_dead_times(delays, names[1:])}; the terms read each input "
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

    spare = _refinement_jobs if refine else None
    fits, scores, ahead = _views_side_by_side(n_y, view, together, say, spare)
    own, coupled = scores["own"][0], scores["coupled"][0]
    kind = "coupled" if coupled < (1.0 - NONLINEAR_GAIN) * own else "own"
    say(f"outputs together on the blocks: mean NMSE {own:.4g} reading only their own past, {coupled:.4g} "
        f"reading the other outputs too: {'the latter' if kind == 'coupled' else 'the former'} is used")  # fmt: skip
    if refine:
        _refine_outputs(fits[kind], say, cores(), ahead if kind == "own" else {})
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
        _refine_outputs([late], say, workers)
    return late


def _dead_times(delays: tuple[int, ...], names: tuple[str, ...]) -> str:
    """``u 5 samples`` (the columns with one): what the report says of the inputs' dead times."""
    return ", ".join(f"{name} {d} samples" for name, d in zip(names, delays, strict=True) if d)


def _views_side_by_side(
    n_y: int, view: Any, together: Any, say: Any, spare: Any = None
) -> tuple[dict[str, list[OutputFit]], dict[str, tuple[float, list[float]]], dict[Any, Any]]:
    """Every output's two views on the machine's cores, each kind's :func:`joint_block_score`, and what was
    done ahead of the choice between them (``spare``: see :class:`_ViewQueue`).

    An output's view with the others' past is offered the structures that served it alone, so
    it waits for its own view. The twelve views of a six-joint robot are queued one by one as
    a core frees (:class:`_ViewQueue`); six pairs as tasks left a core idle at the end for the
    length of one output's two views. What each output says is printed in order, as soon as
    both its views are done.
    """
    from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

    queue, workers = _ViewQueue(n_y, view, together, spare), cores()
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: dict[Any, tuple[str, Any]] = {}
        while True:
            while len(pending) < workers and (task := queue.next_task()) is not None:
                pending[pool.submit(*task[0])] = task[1]
            if not pending:
                break
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                queue.finished(pending.pop(future), future.result())
            queue.tell(say)
    return queue.fits, queue.scores, queue.ahead


class _ViewQueue:
    """What :func:`_views_side_by_side` starts next: an output's second view as soon as its first is done,
    else the next output's first, and each kind's joint score as soon as all its views are in (the own
    views' beside the remaining views, not after them). On one core: the outputs in order, both views each.

    ``spare(own fits)``: (key, call) jobs worth doing before the choice between the kinds is known,
    started only when a core would otherwise wait (the last views and the coupled views' joint score
    leave one idle), never after both scores are in; their results are ``ahead``, by key. ``fit`` gives
    the own views' refinement blocks (:func:`_refinement_jobs`): the own views are the ones used
    unless reading the other outputs wins, and refining them waited for that choice on one core.
    """

    def __init__(self, n_y: int, view: Any, together: Any, spare: Any = None) -> None:
        self.n_y, self.view, self.together, self.spare = n_y, view, together, spare
        self.said: list[list[str]] = [[] for _ in range(n_y)]
        self.fits: dict[str, list[Any]] = {"own": [None] * n_y, "coupled": [None] * n_y}
        self.scores: dict[str, tuple[float, list[float]]] = {}
        self.ready: list[int] = []  # outputs whose own view is done and whose other view has not started
        self.started = self.told = 0
        self.scoring: set[str] = set()  # the kinds whose joint score has started
        self.spare_jobs: list[tuple[Any, Any]] | None = None  # made once the own views are all in
        self.ahead: dict[Any, Any] = {}

    def _score_task(self, kind: str) -> tuple[tuple, tuple[str, Any]] | None:
        if kind in self.scoring or any(f is None for f in self.fits[kind]):
            return None
        self.scoring.add(kind)
        return (self.together, self.fits[kind]), ("score", kind)

    def next_task(self) -> tuple[tuple, tuple[str, Any]] | None:
        """(the call, its tag) of the next task that can start, or None."""
        if (task := self._score_task("own")) is not None:
            return task
        if self.ready:
            j = self.ready.pop(0)
            return (self.view, j, "coupled", self.fits["own"][j], self.said[j]), ("coupled", j)
        if self.started < self.n_y:
            j = self.started
            self.started += 1
            return (self.view, j, "own", None, self.said[j]), ("own", j)
        if (task := self._score_task("coupled")) is not None:
            return task
        if self.spare is None or "own" not in self.scoring or len(self.scores) == 2:
            return None
        if self.spare_jobs is None:
            self.spare_jobs = list(self.spare(self.fits["own"]))
        if not self.spare_jobs:
            return None
        key, call = self.spare_jobs.pop(0)
        return (call,), ("ahead", key)

    def finished(self, tag: tuple[str, Any], result: Any) -> None:
        kind, j = tag
        if kind == "score":
            self.scores[j] = result
        elif kind == "ahead":
            self.ahead[j] = result
        else:
            self.fits[kind][j] = result
            if kind == "own":
                self.ready.append(j)

    def tell(self, say: Any) -> None:
        """Print what the outputs whose views are all done said, in order."""
        while self.told < self.n_y and self.fits["coupled"][self.told] is not None:
            for line in self.said[self.told]:
                say(line)
            self.told += 1


def _refinement_jobs(fits: list[OutputFit]) -> list[tuple[tuple[int, int], Any]]:
    """((candidate id, block), call) of every :func:`~lenn_ros.fit.refinement.fold_history` that
    :func:`_refine_outputs` needs for these outputs, in its order: each a pure function of the candidate's
    fold weights and the record, so done ahead (:class:`_ViewQueue`) it is what it would be done then."""
    return [
        ((id(candidate), fold), functools.partial(fold_history, candidate, fitted.record, fold))
        for fitted in fits
        for candidate in refinement_targets(fitted.candidates)
        for fold in range(len(candidate.fold_weights))
    ]


def _refine_outputs(fits: list[OutputFit], say: Any, workers: int, ahead: dict | None = None) -> None:
    """Refine each output's :func:`refinement_targets` on simulation error (iterations chosen on the blocks),
    then choose again among them and the input-only ones (:func:`_after_refinement`).

    Refinement can reorder candidates (a hinge model that least squares left behind may
    simulate best once refined), so every target's blocks are refined, side by side in one
    pool of ``workers`` threads (a candidate's blocks are independent: three candidates on two
    cores by candidate left one idle for a third of Bouc-Wen's refinement). The blocks' pooled
    error after the count they choose is each target's score. Only the candidate that then
    leads is refined on all its samples (:func:`~lenn_ros.fit.refinement.refine_on_folds`);
    if its soundness check undoes iterations, its score rises and the choice is made again,
    until the leader is one refined on all samples. The others keep their least-squares
    weights and the blocks' figure, reported as not applied: refining all samples of a model
    that is not used cost Bouc-Wen 3 s. ``ahead``: blocks' histories already done, by
    :func:`_refinement_jobs`' key.
    """
    targets = [(fitted, candidate) for fitted in fits for candidate in refinement_targets(fitted.candidates)]
    for fitted, candidate in targets:
        named = f"output {fitted.name}: " if len(fits) > 1 else ""
        say(f"{named}refining {candidate.spec.label} ({candidate.terms} terms) on simulation error")
    ahead = ahead or {}
    jobs = _refinement_jobs(fits)
    left = [job for job in jobs if job[0] not in ahead]
    computed = side_by_side(lambda job: job[1](), left, workers)
    done = {**ahead, **{key: history for (key, _), history in zip(left, computed, strict=True)}}
    history_of: dict[int, list] = {id(candidate): [] for _, candidate in targets}
    for key, _ in jobs:  # each candidate's blocks in order
        history_of[key[0]].append(done[key])
    for _fitted, candidate in targets:
        _score_refinement(candidate, blocks_choice(history_of[id(candidate)]))
    while leaders := [
        (fitted, leader)
        for fitted in fits
        for leader in _contenders(fitted, targets)[:1]
        if not (leader.refinement or {}).get("applied", True)
    ]:
        results = side_by_side(
            lambda pair: refine_on_folds(pair[1], pair[0].record, history_of[id(pair[1])]), leaders, workers
        )
        for (_fitted, candidate), result in zip(leaders, results, strict=True):
            _score_refinement(candidate, result)
    for fitted in fits:
        fitted.chosen, fitted.refinement = _after_refinement(fitted.candidates, _contenders(fitted, targets))


def _score_refinement(candidate: Candidate, result: Refinement) -> None:
    """Record what the refinement did (or what the blocks chose) as the candidate's score."""
    candidate.refinement = result.as_dict()
    candidate.rmse_validation = result.rmse_blocks_after


def _contenders(fitted: OutputFit, targets: list[tuple[OutputFit, Candidate]]) -> list[Candidate]:
    """An output's refined and input-only candidates, in the order :func:`_after_refinement` would choose."""
    refined = [candidate for owner, candidate in targets if owner is fitted]
    input_only = [c for c in fitted.candidates if c.model is not None and c.spec.registered.input_only]
    return order_candidates(refined + input_only)


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
        _refine_outputs([fitted], say, workers)
    return fitted


def _single(
    fitted: OutputFit, u: np.ndarray, y: np.ndarray, network: str, solver: str, forgetting: float, say: Any
) -> tuple[Identifier, dict[str, Any]]:
    """The identifier (and its description) of a model of one output of one input: the selected LeNN, or
    its structure trained by epochs (``--network mlp``, ``--solver sgd``)."""
    final, chosen, start = fitted.model, fitted.chosen, len(y)
    if network == "mlp":
        validation_start = start - max(MIN_VALIDATION, round(VALIDATION_FRACTION * start))
        say(f"training an MLP on lags {final.y_lags}/{final.u_lags} by epochs, early-stopped on the held-out tail")
        identifier, epochs = fit_mlp(final, u, y, validation_start)
        return identifier, describe_mlp(identifier, epochs)
    if solver == "sgd":
        validation_start = start - max(MIN_VALIDATION, round(VALIDATION_FRACTION * start))
        say(f"training the {len(final.exponents)} selected terms by SGD epochs, early-stopped on the held-out tail")
        identifier, epochs = fit_lenn_sgd(final, u, y, validation_start, chosen.spec.increment)
        return identifier, {**describe_model(final, chosen, forgetting), **describe_sgd(identifier, epochs)}
    return build_identifier(final, fitted.record, forgetting), describe_model(final, chosen, forgetting)


def _choices(fitted: OutputFit, blocks: int, gaps: int) -> dict[str, Any]:
    """How one output's model was chosen, as the report gives it."""
    layout = fitted.layout
    scaling: dict[str, Any] = {"from": f"training samples 1..{fitted.record.n}", "margin": DEFAULT_MARGIN}
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


#: structures (best first, from an output's own view) tried again reading the other outputs too, and the
#: longest lags of the polynomial family offered with them
COUPLED_SPECS = 4
COUPLED_LAGS = 3
#: candidates (best first) whose weights are refined on simulation error; the best refined one is kept
REFINED_CANDIDATES = 3


def refinement_targets(candidates: list[Candidate]) -> list[Candidate]:
    """The candidates refined on simulation error: the first REFINED_CANDIDATES usable ones that feed back
    their output (an input-only ``fir`` one's least squares already minimise its free-run error)."""
    return [c for c in candidates if c.model is not None and not c.spec.registered.input_only][:REFINED_CANDIDATES]


def _after_refinement(candidates: list[Candidate], contenders: list[Candidate]) -> tuple[Candidate, dict[str, Any]]:
    """Choose again among the refined candidates and the input-only ones (``contenders``, as :func:`_contenders`
    orders them); the report's list puts them first, the chosen one leading. An input-only model
    (``fir``) is never refined, nor does it take a refinement's place: its least squares already
    minimise its simulation error (its free run is its one-step prediction)."""
    for candidate in contenders:
        candidates.remove(candidate)
    candidates[:0] = contenders
    chosen = candidates[0]
    return chosen, {"done": True, **(chosen.refinement or {"iterations": 0, "tried": 0, "input_only": True})}


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


# -- the model the node runs -------------------------------------------------------------------


def build_identifier(model: TermModel, record: Record, forgetting: float) -> Identifier:
    """A model of one output of one input as the package's :class:`Identifier` (what the node runs), RLS-ready.

    The RLS covariance is the least-squares one of the training features, scaled to the
    forgetting factor's memory (:func:`rls_covariance`): live adaptation starts as if it
    had seen the training data.
    """
    factors = model.factors if len(model.factors) else None
    network = FunctionalLinkNetwork(
        n_inputs=model.layout.n_inputs,
        exponents=model.exponents.tolist(),
        factors=None if factors is None else factors.tolist(),
        order=max(1, int(model.exponents.max(initial=1))),
        basis=model.basis,
        output="linear",
        solver="rls",
        forgetting=forgetting,
        init_scale=0.0,
    )
    network._initialise()
    structure, weights = pass_through_outside(model)
    network.weights_ = weights
    features, _ = model.regression(record.values)
    network.covariance_ = rls_covariance(features[record.valid_rows(model.warm_up)], forgetting)
    return Identifier(structure, network, learning=False)


#: training ranges over which the network of a delivered exact integrator reads its output (:func:`_read_wide`)
DELIVERED_RANGES = 10.0


def _read_wide(chosen: Candidate) -> None:
    """An exact integrator (:func:`~lenn_ros.fit.soundness.level_free`) reads its output's differences over
    DELIVERED_RANGES training ranges (:func:`~lenn_ros.fit.soundness.widened`: the same model inside the
    range), its fold weights with it: a joint without gravity or a wheel goes where its input takes it, and
    there the network's differences, clipped at the range, would read zero."""
    if chosen.model is None or not level_free(chosen.model):
        return
    chosen.fold_weights = [widened(chosen.model.with_weights(w), DELIVERED_RANGES).weights for w in chosen.fold_weights]
    chosen.model = widened(chosen.model, DELIVERED_RANGES)


def pass_through_outside(model: TermModel) -> tuple[Any, np.ndarray]:
    """(the node's structure, the network's weights) of a model of one output of one input.

    A model that integrates exactly (:func:`~lenn_ros.fit.soundness.level_free`: a joint
    without gravity, a wheel, a positioning axis) passes y(k) through as ``y1`` at the
    output's scale plus the bias at its offset. Inside the network that y(k) is read scaled
    and clipped to the training range, so where the output goes beyond it (a wheel keeps
    turning) the prediction would stick at the range's edge. Taken out of the network as the
    known linear part ``known_a = [1]``, y(k) is passed through exactly at any level; the
    network keeps the rest (the same sum inside the range).
    """
    weights = np.array(model.weights, dtype=np.float64)
    if not level_free(model):
        return model.structure, weights
    layout = model.layout
    weights[output_rows(model)] -= layout.y_scale  # y(k) = y_scale x_1 + y_offset
    return dataclasses.replace(model.structure, known_a=(1.0,), output_offset=-layout.y_offset), weights


def common_lags(models: list[TermModel]) -> list[TermModel]:
    """Every output's model as the node's several-channel mode runs it: over the longest lags any of them chose
    (its one ``y_lags``/``u_lags``: the same terms and weights over a wider regressor), with a bias term
    (appended with weight 0 where the selection kept none: the node's output offset is taken off it)."""
    lags = max(model.layout.lags for model in models)
    wide = []
    for model in models:
        model = model.with_lags(lags)
        if not len(_bias_rows(model)):
            factors = np.vstack([model.factors, np.zeros(model.factors.shape[1])]) if len(model.factors) else None
            bias = np.zeros((1, model.layout.n_inputs), dtype=np.int64)
            exponents, weights = np.vstack([model.exponents, bias]), np.append(model.weights, 0.0)
            model = TermModel(model.layout, exponents, model.basis, weights, factors)
        wide.append(model)
    return wide


def _bias_rows(model: TermModel) -> np.ndarray:
    """Indices of the model's constant terms (no exponent, no factor)."""
    plain = model.factors[:, 0] == 0 if len(model.factors) else np.ones(len(model.exponents), dtype=bool)
    return np.flatnonzero(~model.exponents.any(axis=1) & plain)


def build_mimo_identifier(outputs: list[OutputFit], data: Data, forgetting: float) -> MimoIdentifier:
    """Several outputs as the node builds them from the params file ``fit -o`` writes, weights installed.

    Built by :func:`lenn_ros.config.build_identifier` from :func:`mimo_values`, so the
    model scored here is the node's by construction. The node's networks learn each output
    less its offset (:meth:`~lenn_ros.core.mimo.MimoStructure.channel`), so the offset comes
    off the bias weight; each output's RLS covariance is that of its training features
    (:func:`rls_covariance`).
    """
    from lenn_ros import config

    models = common_lags([fitted.model for fitted in outputs])
    values = {**_vector_reading(data), **mimo_values(models, data, forgetting)}
    resolved, network = config.resolve(values)
    identifier = config.build_identifier({**values, **resolved}, network)

    passed = values["y_pass_through"]

    def covariance(job: tuple[TermModel, OutputFit]) -> np.ndarray:
        model, fitted = job
        features, _ = model.regression(fitted.record.values)
        return rls_covariance(features[fitted.record.valid_rows(model.warm_up)], forgetting)

    covariances = side_by_side(covariance, list(zip(models, outputs, strict=True)), cores())
    for j, (network_j, model, covariance_j) in enumerate(zip(identifier.models, models, covariances, strict=True)):
        network_j._initialise()
        weights = np.array(model.weights, dtype=np.float64)
        weights[_bias_rows(model)[0]] -= model.layout.y_offset
        if passed[j]:  # y(k) comes as the known part: the network keeps the rest (pass_through_outside's rule)
            weights[output_rows(model)] -= model.layout.y_scale
        network_j.weights_ = weights
        network_j.covariance_ = covariance_j
    identifier.learning = False
    return identifier


def score(
    identifier: Identifier | MimoIdentifier,
    data: Data,
    start: int,
    models: list[TermModel],
    columns: list[list[int]],
    left_out: int = 0,
) -> dict[str, Any]:
    """Test-part figures of the frozen model, per output: one-step and free run from sample ``start``.

    ``data.breaks`` (samples that start a new run: gaps in a bag) are never crossed: the
    one-step pass and the free run restart from the measured outputs after each
    (:func:`~lenn_ros.core.evaluation.free_run_segments`, as ``evaluate`` does); the samples
    that seed them are not scored. Several outputs run their free run together, each fed the
    model's outputs. ``models``: each output's terms as the identifier runs them, over the
    ``columns`` of [y, u] of its view (clipped inputs and the training range are counted there).
    ``left_out``: training rows left out before the test part (long rest, :func:`~lenn_ros.fit.rest.without_rest`;
    the earliest rows beyond memory, :func:`~lenn_ros.fit.memory.within_memory`), added to the sample numbers the
    report names.
    """
    u, y = data.matrices()
    single = isinstance(identifier, Identifier)
    run_u, run_y = (u[:, 0], y[:, 0]) if single else (u, y)
    cuts = sorted(int(b) for b in data.breaks if 0 < b < len(y))
    y_hat = np.full(y.shape, np.nan)
    window = identifier.structure.warm_up
    for a, b in itertools.pairwise([0, *cuts, len(y)]):
        if b - a > window:
            y_hat[a:b] = identifier.run(run_u[a:b], run_y[a:b], learn=False).reshape(b - a, -1)
    values = np.column_stack([y, u])
    seedable = start not in cuts and len(y) - start > 2 * window  # its own seed leaves most of it to score
    views = [values[:, c] for c in columns]
    record_of_its_own = separate_test_record(models, views, start, cuts) if seedable else ""
    if record_of_its_own:  # the test part is seeded by its own first samples, as after a gap
        y_hat[start : start + window] = np.nan
        cuts = sorted([*cuts, start])
    index = np.arange(len(y)) + np.searchsorted(cuts, np.arange(len(y)), side="right")  # one lost per break
    y_free, info = free_run_segments(identifier, index, run_u, run_y, start)
    first = start + left_out  # the test's first sample as the user counts (rows left out before it)
    y_free = y_free.reshape(len(y) - start, -1)
    info = {
        **info,
        "starts_from": f"measured outputs of samples {first + 1}..{first + window}, not scored"
        if start in cuts
        else f"measured outputs before sample {first + 1}",
        "test_record_of_its_own": record_of_its_own,
    }
    healthy = not info["diverged"]
    per_output = []
    for j, (name, model) in enumerate(zip(data.y_names, models, strict=True)):
        y_test, free, one_step = y[start:, j], y_free[:, j], y_hat[start:, j]
        simulated, predicted = np.isfinite(free), np.isfinite(one_step)
        ok = healthy and bool(simulated.any())
        view = values[:, columns[j]]
        x_test, _ = model.layout.regressors(view[start - model.warm_up :])
        scaled = (view[start:] - np.asarray(model.layout.offsets)) / np.asarray(model.layout.scales)
        per_output.append(
            {
                "name": name,
                "samples": len(y_test),
                "rmse": rmse(y_test[predicted], one_step[predicted]),
                "nmse_db": nmse_db(y_test[predicted], one_step[predicted]),
                "rmse_free_run": rmse(y_test[simulated], free[simulated]) if ok else math.nan,
                "nmse_free_run_db": nmse_db(y_test[simulated], free[simulated]) if ok else math.nan,
                "free_run": info,
                "clipped_inputs_one_step": int(np.count_nonzero(np.abs(x_test) > 1.0)),
                "test_samples_outside_training_range": {
                    "u": int(np.count_nonzero(np.abs(scaled[:, 1:]) > 1.0)),
                    "y": int(np.count_nonzero(np.abs(scaled[:, 0]) > 1.0)),
                },
                "beyond_training_range": beyond_training_range(view, start, model.layout.names, y_test - free),
                "warnings": free_run_problems(y_test[simulated], free[simulated], info),
                "y_test": y_test,
                "y_hat_test": one_step,
                "y_free_test": free,
                "y_hat_train": y_hat[:start, j],
            }
        )
    return {"per_output": per_output, "free_run": info, "y_test": y[start:], "y_hat_test": y_hat[start:],
            "y_free_test": y_free}  # fmt: skip


def beyond_training_range(
    view: np.ndarray, start: int, names: tuple[str, ...], free_error: np.ndarray
) -> dict[str, Any]:
    """The test samples where a signal the model reads lies beyond the range its training samples span, and the
    share of the free run's squared error they carry (``free_error``: the free run's errors, NaN where it did
    not run). There the model extrapolates: a level the record never reached (a tank filled higher than in
    training) is where a polynomial bends away, however well it simulated inside (a tank at -16 dB carried 39 %
    of its error in the quarter of its test that was above its training levels)."""
    low, high = view[:start].min(axis=0), view[:start].max(axis=0)
    test = view[start:]
    outside = (test < low) | (test > high)
    rows = outside.any(axis=1)
    squared = np.where(np.isfinite(free_error), free_error, 0.0) ** 2
    total = float(squared.sum())
    return {
        "samples": int(rows.sum()),
        "by_signal": {name: int(count) for name, count in zip(names, outside.sum(axis=0), strict=True) if count},
        "free_run_error_share": float(squared[rows].sum()) / total if total > 0 else 0.0,
    }


#: how many times the largest one-step error on the build part the error across the split must exceed
#: (:func:`separate_test_record`): that largest is itself the extreme of thousands of errors
JOIN_FACTOR = 2.0


def separate_test_record(models: list[TermModel], views: list[np.ndarray], start: int, cuts: list[int]) -> str:
    """Why the test part is a record of its own, not the build part's continuation ('' if it continues).

    Benchmark files put a test experiment after the build experiments, and users join two
    recordings the same way. Simulated from the build part's last samples, such a test part
    starts from another experiment's state. A lightly damped plant (Bouc-Wen) then carries
    that transient for a thousand samples, and an integrating one keeps the offset for ever:
    the score measures the join, not the model. The join shows one step ahead. Each output's
    chosen structure, its weights fitted by least squares to the build part (the best one-step
    predictor of that structure: refined weights trade one-step error for simulation), errs
    across the split, where its regressors still hold the build part's samples, more than
    JOIN_FACTOR times the largest error it makes anywhere on the build part. Any output doing so
    marks the split. ``views``: each output's [y, u] columns over the whole record; rows whose
    regressors reach across one of the ``cuts`` (gaps) are neither fitted nor judged.
    """

    def verdict(job: tuple[TermModel, np.ndarray]) -> str:
        model, view = job
        record = Record.of(view, cuts)
        warm = model.warm_up
        features, targets = model.regression(record.values)
        sample = np.arange(warm, record.n)
        valid = record.valid_rows(warm)
        build, join = valid & (sample < start), valid & (sample >= start) & (sample < start + warm)
        if np.count_nonzero(build) <= 2 * features.shape[1] or not join.any():
            return ""
        weights = np.linalg.lstsq(features[build], targets[build], rcond=None)[0]
        error = np.abs(targets - features @ weights)
        largest, across = float(error[build].max()), float(error[join].max())
        if across <= JOIN_FACTOR * largest:
            return ""
        return (
            f"the test part is a record of its own: one step ahead across the split the model's structure, "
            f"fitted by least squares, errs {across / largest:.1f} times its largest error on the build part, "
            f"so the free run starts from the test part's own first {warm} samples, which are not scored"
        )

    jobs = list(zip(models, views, strict=True))
    return next((text for text in side_by_side(verdict, jobs, cores()) if text), "")


def fit_intervals(
    report: dict[str, Any], identifier: Identifier | None, fitted: OutputFit, held_out: bool
) -> dict[str, Any]:
    """Nominal 95 % bands of one output, one step ahead and in free run, and how much of the test part they cover.

    Both from errors on samples the model was not fitted to: the blocks the structure
    was chosen by, each run by the weights fitted without it (``held_out``), one step
    ahead and in free run. An MLP or SGD model, which the blocks did not run, takes its
    own errors over the training record (in-sample: optimistic, and said). A
    half-width is the 95 % quantile of |e|, not 1.96 sigma: free-run errors drift and
    have heavy tails. The one-step std is also the noise the twin node may add.
    """
    record = fitted.record
    y_train = record.y
    if held_out:
        one_step = out_of_fold_residuals(fitted.chosen, record, one_step=True)
        free = out_of_fold_residuals(fitted.chosen, record)
        source = "the selection's blocks, each run by the weights fitted without it"
    else:
        warm = identifier.structure.warm_up
        one_step = report["y_hat_train"][warm:] - y_train[warm:]
        free = identifier.free_run(record.values[:, 1], y_train, warm) - y_train[warm:]
        source = "the delivered model over the training record (in-sample: optimistic)"
    report.pop("y_hat_train")
    one_step = one_step[np.isfinite(one_step)]
    one_step_width, free_width = band_half_width(one_step), band_half_width(free)
    y_test = report["y_test"]
    return {
        "level": 0.95,
        "one_step": {
            "half_width": one_step_width,
            "std": float(np.std(one_step)) if len(one_step) else math.nan,
            "from": f"{len(one_step)} one-step errors of {source}",
            "coverage_test": coverage(y_test, report["y_hat_test"], one_step_width),
        },
        "free_run": {
            "half_width": free_width,
            "from": f"{int(np.count_nonzero(np.isfinite(free)))} errors of {source}",
            "coverage_test": coverage(y_test, report["y_free_test"], free_width),
        },
    }


def describe_model(model: TermModel, chosen: Candidate, forgetting: float) -> dict[str, Any]:
    refined = (chosen.refinement or {}).get("iterations", 0)
    names = model.layout.names
    return {
        "network": "lenn",
        "family": chosen.spec.family,
        "structure": {
            "y_lags": model.y_lags,
            "u_lags": model.u_lags,
            "predicts": f"{names[0]}(k) from {', '.join(f'{name}(k-1..)' for name in names)}",
            "form": chosen.spec.as_dict()["form"],
        },
        "expansion": {
            "basis": model.basis,
            "family": chosen.spec.family,
            "degree": chosen.spec.degree,
            "terms": model.terms,
            "dictionary": chosen.dictionary,
        },
        "n_terms": len(model.exponents),
        "weights": [float(w) for w in model.weights],
        "solver": "least squares on all training samples"
        + (f", then {refined} Levenberg-Marquardt iterations on free-run error" if refined else "")
        + " (offline); RLS live",
        "live": {"solver": "rls", "forgetting": forgetting},
    }


def describe_mimo(models: list[TermModel], forgetting: float) -> dict[str, Any]:
    """The several-output model as a whole; each output's own is in its ``per_output`` entry."""
    lags = max(model.layout.lags for model in models)
    return {
        "network": "lenn",
        "outputs": len(models),
        "y_lags": lags,
        "u_lags": lags,
        "couplings": _couplings(models),
        "predicts": "each output from its own past, every input and, where coupled, the other outputs' past "
        "(its own terms: per_output)",
        "n_terms": [len(model.exponents) for model in models],
        "y_pass_through": _passed_through(models),
        "solver": "least squares on all training samples, refined on free-run error as the blocks vouch for; RLS live",
        "live": {"solver": "rls", "forgetting": forgetting},
    }


def _couplings(models: list[TermModel]) -> str:
    """The node's ``couplings``: output j reads its own past and every input (the columns of its view)."""
    return "; ".join(" ".join(model.layout.names) for model in models)


#: MLP learning rate on the normalised target (y - offset) / scale; divided by scale^2 for y itself
MLP_ALPHA = 0.03
MLP_HIDDEN = [20, 10]


def fit_mlp(selected: TermModel, u: np.ndarray, y: np.ndarray, validation_start: int):
    """An MLP on the selected lags, trained by epochs with early stopping (SGD with momentum).

    The target is centred by ``output_offset`` and the tanh output spans the y scale, so
    one learning rate (on the normalised target) suits any units.
    """
    from lenn_ros.core.networks import MLP
    from lenn_ros.fit.training import train_epochs

    s = selected.layout
    structure = dataclasses.replace(selected.structure, output_offset=s.y_offset)
    network = MLP(
        n_inputs=structure.n_inputs,
        hidden=MLP_HIDDEN,
        output="tanh",
        output_scale=s.y_scale,
        alpha=MLP_ALPHA / s.y_scale**2,
        beta=0.5,
    )
    identifier = Identifier(structure, network, learning=False)
    epochs = train_epochs(identifier, u, y, validation_start, max_epochs=100, patience=10)
    return identifier, epochs


#: SGD momentum for the LeNN by epochs, and the share of the stability bound its step takes
SGD_BETA = 0.5
SGD_STEP = 0.5


def fit_lenn_sgd(selected: TermModel, u: np.ndarray, y: np.ndarray, validation_start: int, increment: bool):
    """The selected terms as an SGD LeNN (what the node runs with ``solver: sgd``), trained by epochs.

    One pass over a few hundred samples leaves SGD far from its optimum, so the estimation
    samples are passed repeatedly, early-stopped on the held-out free run
    (:func:`~lenn_ros.fit.training.train_epochs`). The step is unit-free: with momentum
    beta, alpha = SGD_STEP (1 - beta) / max ||phi||^2 over the training features keeps the
    update below its stability bound 2 (1 - beta) / ||phi||^2 for any data (Legendre terms
    of inputs in [-1, 1] have |phi| <= 1, but a factor of a velocity may reach several).
    The network learns y - y_offset (``output_offset``), so no weight has to climb to the
    signal's level; an increment-form model starts from its pass-through y(k) (weight
    y_scale on ``y1``), the part of the structure that is not learnt but given.
    """
    from lenn_ros.fit.training import train_epochs

    s = selected.layout
    structure = dataclasses.replace(selected.structure, output_offset=s.y_offset)
    features, _ = selected.regression(siso_view(u[:validation_start], y[:validation_start]))
    largest = float(np.max(np.einsum("ij,ij->i", features, features), initial=1.0))
    network = FunctionalLinkNetwork(
        n_inputs=structure.n_inputs,
        exponents=selected.exponents.tolist(),
        factors=selected.factors.tolist() if len(selected.factors) else None,
        order=max(1, int(selected.exponents.max(initial=1))),
        basis=selected.basis,
        output="linear",
        solver="sgd",
        alpha=SGD_STEP * (1.0 - SGD_BETA) / largest,
        beta=SGD_BETA,
        init_scale=0.0,
    )
    network._initialise()
    if increment:
        network.weights_ = pass_through_weights(selected.exponents, selected.factors, s, with_offset=False)
    identifier = Identifier(structure, network, learning=False)
    epochs = train_epochs(identifier, u, y, validation_start, max_epochs=200, patience=20)
    return identifier, epochs


def describe_sgd(identifier: Identifier, epochs: Any) -> dict[str, Any]:
    m = identifier.model
    return {
        "weights": [float(w) for w in m.weights_],
        "solver": f"sgd with momentum, alpha {m.alpha:.6g}, by epochs (terms from the LeNN selection)",
        "epochs": epochs.as_dict(),
        "live": {"solver": "sgd", "alpha": m.alpha, "beta": m.beta},
    }


def describe_mlp(identifier: Identifier, epochs: Any) -> dict[str, Any]:
    m = identifier.model
    return {
        "network": "mlp",
        "structure": {"y_lags": identifier.structure.y_lags, "u_lags": identifier.structure.u_lags},
        "expansion": {"hidden": list(m.hidden), "output": f"tanh x {m.output_scale:.6g} + output_offset"},
        "n_terms": m.n_weights,
        "solver": f"sgd with momentum, alpha {m.alpha:.6g}, by epochs (lags from the LeNN selection)",
        "epochs": epochs.as_dict(),
        "live": {"solver": "sgd", "alpha": m.alpha, "beta": m.beta},
    }


def params_values(identifier: Identifier, model: TermModel, forgetting: float, u: np.ndarray, y: np.ndarray):
    """``ros__parameters`` for the identifier node (and ``evaluate --params``)."""
    s = identifier.structure
    limit = _limit(u, y)
    if identifier.model._kind == "mlp":
        m = identifier.model
        return {
            "example": 0,
            "network": "mlp",
            "y_lags": s.y_lags,
            "u_lags": s.u_lags,
            "y_scale": float(s.y_scale),
            "u_scale": float(s.u_scale),
            "y_offset": float(s.y_offset),
            "u_offset": float(s.u_offset),
            "output_offset": float(s.output_offset),
            "hidden": [int(h) for h in m.hidden],
            "output": m.output,
            "output_scale": float(m.output_scale),
            "alpha": float(m.alpha),
            "beta": float(m.beta),
            "u_limit": limit,
            "y_limit": limit,
        }
    return {
        "example": 0,
        "network": "lenn",
        "y_lags": s.y_lags,
        "u_lags": s.u_lags,
        "known_a": list(s.known_a) or [0.0],
        "known_b": [0.0],
        "output_offset": float(s.output_offset),
        "y_scale": float(s.y_scale),
        "u_scale": float(s.u_scale),
        "y_offset": float(s.y_offset),
        "u_offset": float(s.u_offset),
        "y_abs": bool(s.y_abs),
        "separate": False,
        "order": int(identifier.model.order),
        "basis": model.basis,
        "cross_degree": 0,
        "terms": model.terms,
        "output": "linear",
        "output_scale": 1.0,
        **_learning_values(identifier, forgetting),
        "u_limit": limit,
        "y_limit": limit,
    }


def _learning_values(identifier: Identifier, forgetting: float) -> dict[str, Any]:
    """How the node goes on learning: RLS with forgetting, or SGD with the epochs' step."""
    m = identifier.model
    if m.solver == "sgd":
        return {
            "output_offset": float(identifier.structure.output_offset),
            "solver": "sgd",
            "alpha": float(m.alpha),
            "beta": float(m.beta),
        }
    return {"solver": "rls", "forgetting": float(forgetting)}


def mimo_values(models: list[TermModel], data: Data, forgetting: float) -> dict[str, Any]:
    """The node's several-channel model parameters of ``models`` (each output's terms over the common lags).

    Each output reads its own past and every input (``couplings``); its terms are
    written ``y1: u0_2*y1_1`` (:func:`lenn_ros.config.mimo_terms` reads them back).
    """
    u, y = data.matrices()
    limit = _limit(u, y)
    lags, first = models[0].layout.lags, models[0].layout
    inputs = [first.names.index(f"u{i}") for i in range(data.n_u)]
    u_offsets, u_scales = [first.offsets[c] for c in inputs], [first.scales[c] for c in inputs]
    return {
        "example": 0,
        "network": "lenn",
        "couplings": _couplings(models),
        "y_lags": lags,
        "u_lags": lags,
        "u_scales": [float(v) for v in u_scales],
        "u_offsets": [float(v) for v in u_offsets],
        "y_scales": [float(model.layout.y_scale) for model in models],
        "y_offsets": [float(model.layout.y_offset) for model in models],
        "y_pass_through": _passed_through(models),
        "order": max(1, *(int(model.exponents.max(initial=1)) for model in models)),
        "basis": models[0].basis,
        "cross_degree": 0,
        "terms": [f"y{j}: {term}" for j, model in enumerate(models) for term in model.terms],
        "output": "linear",
        "output_scale": 1.0,
        "solver": "rls",
        "forgetting": float(forgetting),
        "u_limit": limit,
        "y_limit": limit,
    }


def _passed_through(models: list[TermModel]) -> list[bool]:
    """Per output, whether the node passes y(k) through (``y_pass_through``): an exact integrator that no
    other output reads (:func:`_fit` has widened its reading, as :func:`_read_wide` does a single output's)."""
    return [level_free(model) and _read_alone(model, models) for model in models]


def _read_alone(model: TermModel, models: list[TermModel]) -> bool:
    """Whether no other output's model reads ``model``'s output (its layout's first column)."""
    name = model.layout.names[0]
    return not any(name in other.layout.names for other in models if other is not model)


def _limit(u: np.ndarray, y: np.ndarray) -> float:
    """``u_limit`` / ``y_limit``: a power of ten well above anything the record holds (absurd values beyond)."""
    return float(10.0 ** math.ceil(math.log10(max(1e3, 10.0 * float(max(np.abs(u).max(), np.abs(y).max()))))))


def _vector_reading(data: Data) -> dict[str, Any]:
    """How the node reads several channels: the bag's own interpretation, else u and y_p as Float64MultiArray
    samples, channels in the order of u_names / y_names (a CSV, an ``import-csv`` bag)."""
    return data.interpretation or {
        "u_type": topics.FLOAT64_ARRAY,
        "y_type": topics.FLOAT64_ARRAY,
        "u_field": "data[*]",
        "y_field": "data[*]",
        "u_names": list(data.u_names),
        "y_names": list(data.y_names),
    }


def write_outputs(directory: str | Path, result: dict[str, Any], data: Data) -> dict[str, str]:
    """``DIR/params.yaml`` (key ``/**``: any node name or namespace), ``DIR/weights.npz`` and ``DIR/fit.json``.

    The params file holds how the node reads its topics (a bag's types, fields, pairing,
    sample period: :mod:`lenn_ros.fit.bag`; for several channels of a CSV, Float64MultiArray
    samples), so the node started from it reads the topics the model was fitted on, the
    same way, and the model's parameters.

    ``weights_in`` in the params file is the absolute path of the weights: the node
    opens a relative path from its own working directory (it cannot know where the
    params file was), so only an absolute path makes the params file enough on its own,
    for the node and for ``lenn-ros evaluate`` alike, from any directory.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    report, identifier = result["report"], result["identifier"]
    weights = directory / "weights.npz"
    train = report["train_samples"]
    u, y = data.matrices()
    if isinstance(identifier, MimoIdentifier):
        identifier.save_state(weights)
        forgetting = report["model"]["live"]["forgetting"]
        values = {**_vector_reading(data), **mimo_values(result["models"], data, forgetting)}
        note = (
            "several channels, read as the bag's\n# topics were (or Float64MultiArray samples); weights_in is absolute"
        )
    else:
        identifier.model.save(weights)
        forgetting = report["model"]["live"].get("forgetting", 1.0)
        model_values = params_values(identifier, result["model"], forgetting, u[:train, 0], y[:, 0])
        values = {**data.interpretation, **model_values}
        note = "starts from weights_in below;\n# move the directory and weights_in must follow: it is absolute"
    values["weights_in"] = str(weights.resolve())
    params = write_params(directory, report, values, note)
    return {"params": str(params), "weights": str(weights), "report": str(write_report(directory, report))}


def write_report(directory: Path, report: dict[str, Any]) -> Path:
    """DIR/fit.json: the report as ``--json`` prints it, beside the weights.

    :func:`lenn_ros.load_model` and the twin node read it for the residual statistics
    (the bands, the twin's noise) and for what the model is.
    """
    path = directory / REPORT_FILE
    path.write_text(json.dumps(_jsonable(report), indent=1, allow_nan=False))
    return path


def write_params(directory: Path, report: dict[str, Any], values: dict[str, Any], note: str) -> Path:
    """DIR/params.yaml for every node (``/**``), headed by where it came from and how to start from it."""
    params = directory / "params.yaml"
    header = (
        f"# written by lenn-ros fit ({report['data']}, test from sample {report['test_from']})\n"
        f"# ros2 run lenn_ros identifier --ros-args --params-file {params}   ({note})\n"
    )
    params.write_text(header + yaml.safe_dump({"/**": {"ros__parameters": values}}, sort_keys=False))
    return params


def _jsonable(report: dict[str, Any]) -> dict[str, Any]:
    """Strict JSON: the series left out, numpy scalars as numbers, NaN/inf as null (a diverged run)."""

    def clean(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [clean(v) for v in value]
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, float) and not math.isfinite(value):
            return None
        return value

    return clean({k: v for k, v in report.items() if not k.endswith(("_test", "_train"))})


#: the command line's flags that say how the data become samples: a bag's topics (fit_bag.load_bag), a CSV's times
BAG_FLAGS = ("u_field", "y_field", "u_names", "y_names", "sample_period", "pairing", "time")


def bag_flags(args: Any) -> dict[str, Any]:
    return {key: getattr(args, key, None) for key in BAG_FLAGS}


def test_row(index: np.ndarray | None, given: int | None, recorded: int | None) -> int | None:
    """The 1-based row ``--test-from`` means: a bag's is a sample index, as the node counts (the row it
    starts), a CSV's a row; without it, the bag's recorded test start (a row already)."""
    if given is None:
        return recorded
    return given if index is None else int(np.searchsorted(index, given)) + 1


def main(args: Any) -> int:
    """``lenn-ros fit``: read, fit, write (``-o``), plot and report."""
    import sys

    data = load_data(args.data, args.u, args.y, bag_flags(args))
    dt = args.dt or data.sample_period
    if args.dt and data.sample_period and abs(args.dt - data.sample_period) > 0.01 * data.sample_period:
        raise FitError(f"--dt {args.dt:g} s disagrees with the time column's sample period {data.sample_period:g} s")
    progress = None if args.json else (lambda text: print(text, file=sys.stderr, flush=True))
    network = getattr(args, "network", "lenn") or "lenn"
    test_from = test_row(data.index, args.test_from, data.test_start)
    solver = getattr(args, "solver", "ls") or "ls"
    result = fit(data, test_from, refine=not args.no_refine, network=network, solver=solver, progress=progress)
    report = result["report"]
    if args.output:
        report["files"] = write_outputs(args.output, result, data)
    if args.plot:
        plot(args.plot, report, Path(args.data).name)
    if args.json:
        print(json.dumps(_jsonable(report), indent=1, allow_nan=False))
        return 0
    print(format_report(report, dt))
    return 0


def columns(given: str | list[str] | None) -> list[str]:
    """``--u`` / ``--y`` as a list: the command line repeats them (several channels), a caller may pass one name."""
    if given is None:
        return []
    return [given] if isinstance(given, str) else list(given)


def is_vector_bag(path: str | Path) -> bool:
    """A bag whose u holds Float64MultiArray samples (``import-csv`` with several columns)."""
    path = Path(path)
    if not (path.is_dir() or path.suffix == ".mcap") or not path.exists():
        return False
    from lenn_ros.bag.vectors import is_vector_run

    return is_vector_run(path)


def plot(path: str | Path, report: dict[str, Any], name: str) -> Path:
    """Plant against the model on the test part (one-step and free run), one panel per output; one output's
    with its free-run band. ``name``: the data's, for the title."""
    from lenn_ros.plotting import plot_channels, plot_identification

    if "per_output" not in report:
        title = f"{name}: free-run RMSE {report['rmse_free_run']:.4g} on the test part"
        band = report["intervals"]["free_run"]["half_width"]
        return plot_identification(path, report["y_test"], report["y_hat_test"], title, report["y_free_test"], band)
    title = f"{name}: model on the test part (free run from the measured outputs before it)"
    return plot_channels(path, report["outputs"], report["y_test"], report["y_hat_test"], title, report["y_free_test"])


def format_report(report: dict[str, Any], dt: float | None = None) -> str:
    """The text report: how each output's model was chosen, then its test figures."""
    lines = [
        f"{report['data']}: built on samples 1..{report['train_samples']}, "
        f"tested on {report['samples']} samples from {report['test_from']}",
    ]
    for left_out in LEFT_OUT:
        if report.get(left_out):
            lines.append(f"  note: {report[left_out]['text']}")
    if report["free_run"].get("test_record_of_its_own"):
        lines.append(f"  note: {report['free_run']['test_record_of_its_own']}")
    if "per_output" not in report:
        return "\n".join(lines + _model_lines(report, "  ") + _test_lines(report, dt))
    for part in report["per_output"]:
        lines.append(f"  output {part['name']}:")
        lines += _model_lines(part, "    ")
    lines += _table_lines(report)
    lines += _closing_lines(report, dt)
    return "\n".join(lines)


def _model_lines(part: dict[str, Any], indent: str) -> list[str]:
    """How one output's model was chosen and what it is."""
    m, c = part["model"], part["choices"]
    scaling = c["scaling"]
    if "offsets" in scaling:
        shown = ", ".join(f"{n} = {o:.6g} +- {scaling['scales'][n]:.6g}" for n, o in scaling["offsets"].items())
    else:
        shown = (
            f"y = {scaling['y_offset']:.6g} +- {scaling['y_scale']:.6g}, "
            f"u = {scaling['u_offset']:.6g} +- {scaling['u_scale']:.6g}"
        )
    lines = [
        f"{indent}scaling from the training samples, margin {scaling['margin']:.0%}: {shown}",
        f"{indent}structure judged by the free runs of {c['blocks']} blocks of the training samples"
        + (f" ({c['gaps']} gaps in the record, not joined)" if c.get("gaps") else "")
        + ":",
    ]
    lines += _candidate_lines(c, indent)
    lines.append(f"{indent}time scale: {c['time_scale']}")
    if dead := c.get("dead_time"):
        lines.append(
            f"{indent}dead time: {_dead_times(tuple(dead.values()), tuple(dead))} (the newest lags that add nothing "
            "to a least-squares model, up to a sharp onset): the terms read each input from there back"
        )
    if sign := c.get("sign"):
        blocks = sign["rmse_blocks"]
        lines.append(
            f"{indent}output read as |y|: fitted on its signed record too ({sign['runs']} runs between near-zero "
            f"minima; blocks' free-run RMSE {blocks['as_measured']:.5g} as read, {blocks['signed']:.5g} signed): "
            + ("the node signs each y_p as its model does (y_abs)" if sign["used"] else "kept as read")
        )
    if m["network"] == "lenn" and "epochs" in m:
        e = m["epochs"]
        lines.append(f"{indent}trained by SGD epochs: {e['epochs']} run, best {e['best_epoch']} ({e['stopped']})")
    if m["network"] == "mlp":
        e = m["epochs"]
        lines.append(f"{indent}model: MLP {m['structure']} hidden {m['expansion']['hidden']}, {m['n_terms']} weights")
        lines.append(f"{indent}trained by epochs: {e['epochs']} run, best {e['best_epoch']} ({e['stopped']})")
    else:
        terms = " + ".join(m["expansion"]["terms"])
        lines.append(f"{indent}model: {m['family']} ({m['expansion']['basis']}), {m['n_terms']} terms: {terms}")
    refinement = c["refinement"]
    if refinement.get("input_only"):
        lines.append(f"{indent}not refined: an input-only model's least squares already minimise its free-run error")
    elif refinement.get("done"):
        lines.append(
            f"{indent}refined on simulation error: {refinement['iterations']} of {refinement['tried']} iterations "
            f"(chosen on the blocks: held-out free-run RMSE {refinement['rmse_blocks_before']:.5g} -> "
            f"{refinement['rmse_blocks_after']:.5g})"
        )
        if refinement.get("unsound"):
            lines.append(f"{indent}  {refinement['unsound']} (the blocks vouch for the fit, not the stability)")
    live = m["live"]
    lines.append(
        f"{indent}live: RLS, forgetting {live['forgetting']:.6g}"
        if live["solver"] == "rls"
        else f"{indent}live: SGD, alpha {live['alpha']:.6g}, beta {live['beta']:.3g}"
    )
    return lines


def _table_lines(report: dict[str, Any]) -> list[str]:
    """Several outputs' test figures, one row each."""
    lines = [
        f"  test part ({report['samples']} samples; free run of all outputs together from the "
        f"{report['free_run']['starts_from']}):",
        "    output        one-step NMSE / RMSE      free-run NMSE / RMSE    95 % free-run band covers",
    ]
    for part in report["per_output"]:
        band = part["intervals"]["free_run"]
        lines.append(
            f"    {part['name']:<12} {part['nmse_db']:8.2f} dB {part['rmse']:10.4g}   "
            f"{part['nmse_free_run_db']:8.2f} dB {part['rmse_free_run']:10.4g}   "
            f"+-{band['half_width']:.4g}: {band['coverage_test']:.1%}"
        )
    for part in report["per_output"]:
        lines += [line.replace("note: ", f"note ({part['name']}): ", 1) for line in _beyond_lines(part, "  ")]
    return lines


#: candidates listed in the text report (the JSON has them all)
SHOWN_CANDIDATES = 12


def _candidate_lines(choices: dict[str, Any], indent: str = "  ") -> list[str]:
    lines = []
    listed = choices["candidates"]
    for index, candidate in enumerate(listed[:SHOWN_CANDIDATES]):
        mark = "->" if index == choices["chosen"] else "  "
        value = candidate["rmse_free_run_validation"]
        shown = f"free-run RMSE {value:.5g}" if value is not None else f"rejected: {candidate['rejected']}"
        if candidate.get("note"):
            shown += f" ({candidate['note']})"
        if candidate.get("refinement", {}).get("applied", True) is False:
            shown += f", the blocks chose {candidate['refinement']['iterations']} refinements (not applied: not chosen)"
        elif candidate.get("refinement"):
            shown += f", refined {candidate['refinement']['iterations']}x"
        lines.append(
            f"{indent} {mark} {candidate['family']} degree {candidate['degree']}, lags {candidate['y_lags']}/"
            f"{candidate['u_lags']}: {candidate['terms']} of {candidate['dictionary']} terms, {shown}"
        )
    if len(listed) > SHOWN_CANDIDATES:
        usable = sum(1 for c in listed if c["rmse_free_run_validation"] is not None)
        more = len(listed) - SHOWN_CANDIDATES
        lines.append(f"{indent}    ... {more} more ({usable} of {len(listed)} usable; --json lists all)")
    return lines


def _test_lines(report: dict[str, Any], dt: float | None) -> list[str]:
    lines = [f"  test part ({report['samples']} samples):"]
    lines.append(f"    one-step: RMSE {report['rmse']:.5g}, NMSE {report['nmse_db']:.2f} dB")
    free = report["free_run"]
    lines.append(
        f"    free run (from the {free['starts_from']}): "
        f"RMSE {report['rmse_free_run']:.5g}, NMSE {report['nmse_free_run_db']:.2f} dB, "
        f"{free['clipped_inputs']} inputs clipped"
    )
    bands = report.get("intervals")
    if bands:
        one, run = bands["one_step"], bands["free_run"]
        lines.append(
            f"    95 % bands (from held-out blocks of the training samples): one-step +-{one['half_width']:.4g} "
            f"covers {one['coverage_test']:.1%}, free run +-{run['half_width']:.4g} covers {run['coverage_test']:.1%}"
        )
    outside = report["test_samples_outside_training_range"]
    if outside["u"] or outside["y"]:
        lines.append(
            f"  note: {outside['u']} test u and {outside['y']} test y samples lie beyond the training range "
            "plus margin; their network inputs are clipped (counted above)"
        )
    lines += _beyond_lines(report, "  ")
    return lines + _closing_lines(report, dt)


def _beyond_lines(report: dict[str, Any], indent: str) -> list[str]:
    """One line when the test part leaves the training range: where, and what share of the error is there."""
    beyond = report["beyond_training_range"]
    if not beyond["samples"]:
        return []
    where = ", ".join(f"{name} {count}" for name, count in beyond["by_signal"].items())
    share = beyond["samples"] / report["samples"]
    return [
        f"{indent}note: {beyond['samples']} of {report['samples']} test samples ({share:.0%}) lie beyond the range "
        f"of the training samples ({where}): the model extrapolates there; they carry "
        f"{beyond['free_run_error_share']:.0%} of the free run's squared error"
    ]


def _closing_lines(report: dict[str, Any], dt: float | None) -> list[str]:
    """Warnings, the test part's length, the files written and how to start from them, the time taken."""
    lines = [f"  WARNING: {text}" for text in report["warnings"]]
    if dt:
        lines.append(f"  sample time {dt:g} s: test part {report['samples'] * dt:.4g} s")
    if "files" in report:
        files = report["files"]
        lines.append(f"  wrote {files['params']}, {files['weights']} and {files.get('report', 'no report')}")
        lines.append(
            f"  live: ros2 run lenn_ros identifier --ros-args --params-file {report['files']['params']} "
            "(its weights_in names the weights file)"
        )
        lines.append(f"  twin: ros2 run lenn_ros twin --ros-args -p model:={Path(files['params']).parent}")
    lines.append(f"  {report['seconds']} s")
    return lines
