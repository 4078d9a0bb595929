"""``lenn-ros fit DATA --u A --u B --y C --y D --test-from K``: a MIMO LeNN of logged data.

One MISO network per output over the lags of every channel (couplings ``full``: the
other outputs are measured, so in series-parallel they are inputs like u), and, for
comparison, one SISO network per output (couplings ``diagonal``, when there are as many
inputs as outputs): the user sees in one report whether the coupling matters.

How it differs from the SISO ``fit`` (:mod:`lenn_ros.fit.build`), and why:

1. **Structure**: a grid of lags L (y_lags = u_lags = L, for every channel) and full
   Legendre expansions (``order``, ``cross_degree``), shared by every output, because
   that is all the identifier node's MIMO mode reads: it builds each output's network
   from those parameters and takes no ``terms``. So FROLS term selection
   (:mod:`lenn_ros.fit.selection`) does not carry over; choosing among whole
   expansions does, with the selection's rules: every candidate's weights are least
   squares on the training samples before the held-out tail (the last 20 %), and it is
   judged by the free run of the **joint** model over that tail
   (:meth:`~lenn_ros.core.mimo.MimoIdentifier.free_run`: every output fed the model's
   own outputs, which is what a MIMO model is used for; each output's one-step fit
   can be excellent while the coupled simulation runs away). The score is the mean of
   the outputs' NMSE (each normalised by its own variance, so a channel in volts does
   not drown one in millivolts). Rejected: diverged, any clipped network input, or an
   output worse than its held-out mean; of the rest, the fewest weights within
   PARSIMONY of the lowest score. If nothing passes, the best that merely does not
   diverge is used, with a warning. One fold only (the SISO fit pools two): the
   Python free run of the joint model is the cost here.
2. **Weights**: least squares of the chosen structure on *all* training samples (the
   tail only chose the structure, and no iteration count depends on it, so refitting
   loses nothing it judged), with the RLS covariance of those features
   (:func:`lenn_ros.fit.build.rls_covariance`), so the node goes on adapting as if it had
   seen the training data. No simulation-error refinement: the refinement
   (:mod:`lenn_ros.fit.refinement`) runs the SISO compiled free run of a TermModel.
3. **Scaling** per channel, the SISO rule: centre of the training range, half-range
   plus 100 % margin onto 1.
4. ``-o DIR``: ``params.yaml`` with the node's MIMO parameters and ``weights.npz``
   (:meth:`~lenn_ros.core.mimo.MimoIdentifier.save_state`).

During selection the networks hold their expansion as explicit exponent rows
(``full_exponents``: the same columns, so the same predictions): the free run predicts
one sample at a time, 5-8x faster that way. The delivered model is the
``order``/``cross_degree`` network the node builds.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros import topics
from lenn_ros.core.evaluation import free_run_problems
from lenn_ros.core.expansions import full_exponents, term_features
from lenn_ros.core.metrics import nmse_db, rmse
from lenn_ros.core.mimo import MimoIdentifier, MimoStructure, build_mimo_identifier, parse_couplings
from lenn_ros.core.networks import FunctionalLinkNetwork
from lenn_ros.core.scaling import DEFAULT_MARGIN
from lenn_ros.fit.build import (
    MIN_VALIDATION,
    VALIDATION_FRACTION,
    FitError,
    _column,
    _jsonable,
    check_split,
    live_forgetting,
    read_csv_rows,
    rls_covariance,
    write_params,
    write_report,
)
from lenn_ros.fit.data import MimoData
from lenn_ros.fit.selection import PARSIMONY, Record, runs

#: (order, cross_degree) tried, linear ARX first: a nonlinear expansion must beat it in simulation
EXPANSIONS = ((1, 0), (2, 2), (3, 3), (4, 3))
LAGS = (1, 2, 3, 4, 5, 6, 8, 10)
#: longer lags are tried (per expansion) until this many in a row did not lower the held-out score:
#: each candidate costs one joint free run in Python, and past the plant's order longer lags only add noise
LAG_PATIENCE = 2
#: weights per output network at most this, and at most a tenth of the estimation samples
MAX_WEIGHTS = 400
#: the fallback's bound on clipped free-run inputs (the strict rule allows none), as in selection
LOOSE_CLIPPED_FRACTION = 0.01
BASIS = "legendre"


def load_mimo_data(
    path: str | Path, u_columns: list[str], y_columns: list[str], flags: dict[str, Any] | None = None
) -> MimoData:
    """Several channels from a bag or a CSV file.

    A bag the identifier was recorded beside (its ``identifier_config``), or one whose
    topics the flags name, is paired by the node's session (:func:`lenn_ros.fit.bag.load_bag`;
    ``--u`` / ``--y`` are then topics); an ``import-csv`` vector bag (``u`` / ``y_p`` of
    Float64MultiArray, no configuration) is read by message order, ``--u`` / ``--y``
    picking its channels by label.
    """
    path = Path(path)
    if not path.exists():
        raise FitError(f"{path} does not exist (expected a CSV file or a bag directory)")
    if path.is_dir() or path.suffix == ".mcap":
        if not _session_bag(path, flags or {}):
            return _load_bag(path, u_columns, y_columns)
        from lenn_ros.fit.bag import load_bag

        data = load_bag(path, {**(flags or {}), "u": u_columns, "y": y_columns})
        if not isinstance(data, MimoData):
            raise FitError(f"{path}: the topics give one channel each side; drop the repeated --u/--y")
        return data
    if not u_columns or not y_columns:
        raise FitError(f"{path}: pass --u COL and --y COL, each repeated once per channel (name or 0-based index)")
    return _load_csv(path, u_columns, y_columns)


def _session_bag(path: Path, flags: dict[str, Any]) -> bool:
    """Whether the bag is read by the node's session: an identifier_config, or flags that say how."""
    from lenn_ros.bag.vectors import is_vector_run
    from lenn_ros.fit.bag import has_identifier_config

    return has_identifier_config(path) or any(flags.values()) or not is_vector_run(path)


def _load_bag(path: Path, u_columns: list[str], y_columns: list[str]) -> MimoData:
    from lenn_ros.bag.vectors import read_vector_run

    run = read_vector_run(path)
    iu = [_channel(run.u_names, c, path, "u") for c in u_columns] or list(range(len(run.u_names)))
    iy = [_channel(run.y_names, c, path, "y_p") for c in y_columns] or list(range(len(run.y_names)))
    u_names, y_names = tuple(run.u_names[i] for i in iu), tuple(run.y_names[i] for i in iy)
    source = f"bag {path}: u = {', '.join(u_names)}; y_p = {', '.join(y_names)}"
    return MimoData(run.u[:, iu], run.y[:, iy], u_names, y_names, source, run.test_start)


def _channel(names: tuple[str, ...], column: str, path: Path, topic: str) -> int:
    """A bag channel by its label or 0-based index, as a CSV column is found."""
    if column in names:
        return names.index(column)
    if column.isdigit() and int(column) < len(names):
        return int(column)
    raise FitError(f"{path}: no {topic} channel {column!r}; channels are {', '.join(names)}")


def _load_csv(path: Path, u_columns: list[str], y_columns: list[str]) -> MimoData:
    header, body, width = read_csv_rows(path)
    columns = [*u_columns, *y_columns]
    indices = [_column(header, column, width, path) for column in columns]
    values = np.empty((len(body), len(indices)))
    for n, row in enumerate(body):
        try:
            values[n] = [float(row[i]) for i in indices]
        except (ValueError, IndexError):
            line = n + (2 if header else 1)
            raise FitError(f"{path}, line {line}: not a number in column(s) {', '.join(columns)}: {row}") from None
    names = tuple(header[i] if header else str(i) for i in indices)
    split = len(u_columns)
    u_names, y_names = names[:split], names[split:]
    source = f"CSV {path}: u = columns {', '.join(u_names)}; y = columns {', '.join(y_names)}"
    return MimoData(values[:, :split], values[:, split:], u_names, y_names, source)


def channel_scaling(values: np.ndarray, names: tuple[str, ...]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(offsets, scales) per column: the SISO rule (:class:`~lenn_ros.core.scaling.Scaling`) channel by channel."""
    offsets, scales = [], []
    for column, name in zip(values.T, names, strict=True):
        low, high = float(column.min()), float(column.max())
        if high == low:
            raise FitError(f"training {name} is constant ({low:g}): nothing to identify; check the --u/--y columns")
        offsets.append((high + low) / 2.0)
        scales.append((high - low) / 2.0 * (1.0 + DEFAULT_MARGIN))
    return tuple(offsets), tuple(scales)


@dataclass(frozen=True)
class Scalings:
    """Per-channel offsets and scales taken from the training samples."""

    u_offset: tuple[float, ...]
    u_scale: tuple[float, ...]
    y_offset: tuple[float, ...]
    y_scale: tuple[float, ...]

    @classmethod
    def from_training(cls, u: np.ndarray, y: np.ndarray, names: tuple[tuple[str, ...], tuple[str, ...]]) -> Scalings:
        return cls(*channel_scaling(u, names[0]), *channel_scaling(y, names[1]))

    def structure(self, lags: int, couplings: str) -> MimoStructure:
        n_u, n_y = len(self.u_scale), len(self.y_scale)
        return MimoStructure(
            n_u=n_u,
            n_y=n_y,
            y_lags=lags,
            u_lags=lags,
            y_scale=self.y_scale,
            y_offset=self.y_offset,
            u_scale=self.u_scale,
            u_offset=self.u_offset,
            couplings=parse_couplings(couplings, n_u, n_y),
        )


@dataclass
class MimoCandidate:
    """One structure tried (lags, expansion), with its held-out verdict."""

    lags: int
    order: int
    cross_degree: int
    weights: int  # per output network, largest over the outputs
    inputs: int = 0  # network inputs of all outputs together: what one free-run step may clip
    score: float = math.inf  # mean over outputs of the held-out free-run NMSE (linear)
    nmse_db: list[float] = field(default_factory=list)  # held-out free run, per output
    clipped: int = 0
    rejected: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {
            "lags": self.lags,
            "order": self.order,
            "cross_degree": self.cross_degree,
            "weights_per_output": self.weights,
            "nmse_free_run_validation_db": _db(self.score),
            "per_output_db": self.nmse_db,
            "clipped_inputs": self.clipped,
            "rejected": self.rejected,
        }


def _db(value: float) -> float | None:
    return float(10.0 * math.log10(value)) if math.isfinite(value) and value > 0 else None


def candidate_grid(scalings: Scalings, couplings: str, n_estimation: int, max_lag: int) -> list[list[MimoCandidate]]:
    """Per expansion, the lags to try, shortest first, while the largest output network stays within
    MAX_WEIGHTS and a tenth of the estimation samples."""
    limit = min(MAX_WEIGHTS, n_estimation // 10)
    structures = [scalings.structure(lags, couplings) for lags in LAGS if lags <= max_lag]
    grid = []
    for order, cross in EXPANSIONS:
        row = []
        for structure in structures:
            channels = [structure.channel(j) for j in range(structure.n_y)]
            weights = len(full_exponents(max(c.n_inputs for c in channels), order, cross))
            if weights <= limit:
                total = sum(c.n_inputs for c in channels)
                row.append(MimoCandidate(structure.y_lags, order, cross, weights, total))
        grid.append(row)
    return grid


def _training_features(
    structure: MimoStructure, output: int, rows: np.ndarray, u: np.ndarray, y: np.ndarray, breaks: list[int]
) -> tuple[np.ndarray, np.ndarray]:
    """Output ``output``'s series-parallel least-squares system: (features of each regressor, target).

    A regressor whose window crosses a break (a gap in the record) is left out: its lags
    would join samples that were not adjacent (:meth:`Record.valid_rows`, the SISO fit's rule).
    """
    channel = structure.channel(output)
    x, linear = channel.regressors(structure.other_values(output, u, y), y[:, output])
    inputs, targets, _ = channel.pairs_from_regressors(x, linear, y[:, output])
    valid = Record.of(u, y, breaks).valid_rows(channel.warm_up)
    return term_features(np.clip(inputs[valid], -1.0, 1.0), rows, BASIS), targets[valid]


def least_squares_identifier(
    structure: MimoStructure,
    expansion: tuple[int, int],
    u: np.ndarray,
    y: np.ndarray,
    forgetting: float | None = None,
    names: tuple[str, ...] = (),
    breaks: list[int] | None = None,
) -> MimoIdentifier:
    """Every output's network by least squares on (u, y), never across ``breaks``; frozen (learning off).

    ``forgetting=None``: the selection's fast networks (explicit exponent rows); else
    the node's network (``order``/``cross_degree``), RLS-ready with that forgetting.
    """
    order, cross = expansion

    def make_model(n_inputs: int, output: int) -> FunctionalLinkNetwork:
        rows = full_exponents(n_inputs, order, cross)
        features, targets = _training_features(structure, output, rows, u, y, breaks or [])
        network = FunctionalLinkNetwork(
            n_inputs=n_inputs,
            order=order,
            basis=BASIS,
            cross_degree=0 if forgetting is None else cross,
            exponents=rows.tolist() if forgetting is None else None,
            output="linear",
            solver="rls",
            forgetting=1.0 if forgetting is None else forgetting,
            init_scale=0.0,
        )
        network._initialise()
        network.weights_ = np.linalg.lstsq(features, targets, rcond=None)[0]
        if forgetting is not None:
            network.covariance_ = rls_covariance(features, forgetting)
        return network

    identifier = build_mimo_identifier(structure, make_model, names)
    identifier.learning = False
    return identifier


def segmented_free_run(
    identifier: MimoIdentifier, u: np.ndarray, y: np.ndarray, start: int, index: np.ndarray
) -> tuple[np.ndarray, dict[str, Any], np.ndarray]:
    """The joint free run from ``start``, restarted from the measured outputs after every gap in ``index``.

    (y_free from ``start`` on, its info, which of those rows were simulated.) The
    evaluate path's (:func:`lenn_ros.core.evaluation.free_run_segments`): a simulation never
    crosses a gap; the ``warm_up`` measured samples after one seed it again, unscored.
    """
    from lenn_ros.core.evaluation import free_run_segments

    y_free, info = free_run_segments(identifier, index, u, y, start)
    return y_free, info, np.isfinite(y_free).all(axis=1)


def judge(
    candidate: MimoCandidate,
    identifier: MimoIdentifier,
    u: np.ndarray,
    y: np.ndarray,
    start: int,
    index: np.ndarray | None = None,
) -> None:
    """The candidate's held-out joint free run from ``start`` (restarted after gaps): its score, or why it
    is rejected."""
    index = np.arange(1, len(y) + 1) if index is None else index
    y_free, info, simulated = segmented_free_run(identifier, u, y, start, index)
    held_out = y[start:]
    candidate.clipped = int(info["clipped_inputs"])
    if info["diverged"]:
        candidate.rejected = f"held-out free run diverged at sample {info['diverged_at'] + 1}"
        return
    if not simulated.any():
        candidate.rejected = "no held-out sample to simulate (gaps closer than the lags)"
        return
    held_out, y_free = held_out[simulated], y_free[simulated]
    spread = np.maximum(np.var(held_out, axis=0), 1e-300)
    nmse = np.mean((y_free - held_out) ** 2, axis=0) / spread
    candidate.nmse_db = [float(10.0 * np.log10(max(value, 1e-300))) for value in nmse]
    candidate.score = float(np.mean(nmse))


def _verdict(candidate: MimoCandidate, names: tuple[str, ...], samples: int, strict: bool) -> str:
    """Why a judged candidate may not be chosen (``""``: it may), by the selection's strict or loose rule."""
    if candidate.rejected:
        return candidate.rejected
    allowed = 0.0 if strict else LOOSE_CLIPPED_FRACTION * samples * candidate.inputs
    if candidate.clipped > allowed:
        return f"held-out free run left the training range ({candidate.clipped} inputs clipped)"
    worse = [name for name, value in zip(names, candidate.nmse_db, strict=True) if value > 0.0]
    if strict and worse:
        return f"held-out free run of {', '.join(worse)} worse than its mean"
    return ""


def select(
    u: np.ndarray,
    y: np.ndarray,
    validation_start: int,
    scalings: Scalings,
    couplings: str,
    names: tuple[str, ...],
    max_lag: int = 10,
    index: np.ndarray | None = None,
) -> tuple[list[MimoCandidate], list[str]]:
    """Every candidate judged, the one to use first; (candidates, warnings). FitError when none simulates.

    Per expansion the lags grow from 1 while they help (LAG_PATIENCE), so the judged
    candidates are those listed, not the whole grid. ``index``: the samples' indices
    (None: 1..N); where it skips, neither the estimation nor the held-out free run joins.
    """
    index = np.arange(1, len(y) + 1) if index is None else np.asarray(index, dtype=np.int64)
    breaks = [int(b) for b in np.flatnonzero(np.diff(index[:validation_start]) != 1) + 1]
    candidates = []
    for row in candidate_grid(scalings, couplings, validation_start, max_lag):
        best, misses = math.inf, 0
        for candidate in row:
            structure = scalings.structure(candidate.lags, couplings)
            expansion = (candidate.order, candidate.cross_degree)
            identifier = least_squares_identifier(
                structure, expansion, u[:validation_start], y[:validation_start], breaks=breaks
            )
            judge(candidate, identifier, u, y, validation_start, index)
            candidates.append(candidate)
            best, misses = (candidate.score, 0) if candidate.score < best else (best, misses + 1)
            if misses == LAG_PATIENCE:
                break
    samples = len(y) - validation_start
    warnings = []
    for strict in (True, False):
        usable = [c for c in candidates if not _verdict(c, names, samples, strict)]
        if usable:
            break
    else:
        reasons = sorted({_verdict(c, names, samples, False) for c in candidates})
        raise FitError(f"no candidate structure simulates stably on the held-out tail ({'; '.join(reasons)})")
    if not strict:
        warnings.append(
            "no candidate passed the strict checks (held-out free run inside the training range and better than "
            "the mean on every output): the best held-out one is used, do not trust it far"
        )
    for candidate in candidates:
        candidate.rejected = _verdict(candidate, names, samples, strict)
    return _simplest_first(candidates, usable), warnings


def _simplest_first(candidates: list[MimoCandidate], usable: list[MimoCandidate]) -> list[MimoCandidate]:
    """Usable ones by score, the fewest weights within PARSIMONY of the lowest first; then the rejected."""
    usable = sorted(usable, key=lambda c: c.score)
    close = [c for c in usable if c.score <= usable[0].score * (1.0 + PARSIMONY)]
    simplest = min(close, key=lambda c: (c.weights, c.score))
    ordered = [simplest, *(c for c in usable if c is not simplest)]
    return ordered + [c for c in candidates if c not in usable]


def score(
    identifier: MimoIdentifier, u: np.ndarray, y: np.ndarray, start: int, index: np.ndarray | None = None
) -> dict[str, Any]:
    """Test-part figures per output of the frozen model: one-step and joint free run from ``start``.

    Neither crosses a gap in ``index`` (None: none): one step ahead, each contiguous run
    starts its history afresh, as the node's session does; the free run restarts from
    the measured outputs after each gap. The samples neither predicts are NaN, unscored.
    """
    index = np.arange(1, len(y) + 1) if index is None else np.asarray(index, dtype=np.int64)
    breaks = np.flatnonzero(np.diff(index) != 1) + 1
    y_hat = np.full(y.shape, np.nan)
    for a, b in runs(0, len(y), breaks):
        if b - a > identifier.structure.warm_up:
            y_hat[a:b] = identifier.run(u[a:b], y[a:b], learn=False)
    y_hat = y_hat[start:]
    y_free, info, simulated = segmented_free_run(identifier, u, y, start, index)
    y_test = y[start:]
    predicted = np.isfinite(y_hat).all(axis=1)
    if info["diverged"]:
        simulated = np.ones(len(y_test), dtype=bool)  # its NaN make the figures NaN, and it is said
    outputs = []
    for j, name in enumerate(identifier.names):
        finite = bool(np.all(np.isfinite(y_free[simulated, j])))
        scored_free = (y_test[simulated, j], y_free[simulated, j])
        outputs.append(
            {
                "name": name,
                "rmse": rmse(y_test[predicted, j], y_hat[predicted, j]),
                "nmse_db": nmse_db(y_test[predicted, j], y_hat[predicted, j]),
                "rmse_free_run": rmse(*scored_free) if finite else math.nan,
                "nmse_free_run_db": nmse_db(*scored_free) if finite else math.nan,
                "warnings": [f"{name}: {text}" for text in free_run_problems(*scored_free, info)],
            }
        )
    return {"per_output": outputs, "free_run": info, "y_test": y_test, "y_hat_test": y_hat, "y_free_test": y_free}


def fit_couplings(
    data: MimoData, start: int, couplings: str, max_lag: int, say: Any
) -> tuple[dict[str, Any], MimoIdentifier]:
    """Select, re-estimate on all training samples and score one kind of model (``full`` or ``diagonal``)."""
    u_train, y_train = data.u[:start], data.y[:start]
    scalings = Scalings.from_training(u_train, y_train, (data.u_names, data.y_names))
    validation_start = start - max(MIN_VALIDATION, round(VALIDATION_FRACTION * start))
    index, breaks = data.sample_index(), [b for b in data.breaks if b < start]
    gaps = f" ({len(breaks)} gaps in the training record, not joined)" if breaks else ""
    say(
        f"couplings {couplings}: judging structures by the joint free run on samples {validation_start + 1}..{start}"
        + gaps
    )
    candidates, warnings = select(
        u_train, y_train, validation_start, scalings, couplings, data.y_names, max_lag, index[:start]
    )
    chosen = candidates[0]
    forgetting = live_forgetting(start)
    structure = scalings.structure(chosen.lags, couplings)
    expansion = (chosen.order, chosen.cross_degree)
    identifier = least_squares_identifier(structure, expansion, u_train, y_train, forgetting, data.y_names, breaks)
    scored = score(identifier, data.u, data.y, start, index)
    model = {
        "couplings": couplings,
        "y_lags": chosen.lags,
        "u_lags": chosen.lags,
        "order": chosen.order,
        "cross_degree": chosen.cross_degree,
        "basis": BASIS,
        "weights_per_output": [int(m.n_weights) for m in identifier.models],
        "channels_per_output": [list(c) for c in structure.couplings],
        "solver": f"least squares on training samples 1..{start}; RLS live",
        "live": {"solver": "rls", "forgetting": forgetting},
        "scaling": {
            "margin": DEFAULT_MARGIN,
            "u_offsets": list(scalings.u_offset),
            "u_scales": list(scalings.u_scale),
            "y_offsets": list(scalings.y_offset),
            "y_scales": list(scalings.y_scale),
        },
        "estimation_samples": validation_start,
        "validation_samples": start - validation_start,
        "gaps": len(breaks),
        "candidates": [c.as_dict() for c in candidates],
    }
    scored["warnings"] = warnings + [text for output in scored["per_output"] for text in output.pop("warnings")]
    return {"model": model, **scored}, identifier


def fit_mimo(data: MimoData, test_from: int | None, max_lag: int = 10, progress: Any = None) -> dict[str, Any]:
    """The MIMO model (couplings full) and, when n_u == n_y, one SISO model per output to compare with."""
    began = time.perf_counter()
    say = progress or (lambda text: None)
    if not (np.all(np.isfinite(data.u)) and np.all(np.isfinite(data.y))):
        bad = int(np.count_nonzero(~(np.isfinite(data.u).all(axis=1) & np.isfinite(data.y).all(axis=1))))
        raise FitError(f"{bad} samples hold NaN/inf: remove or interpolate them before fitting")
    start = check_split(len(data.y), test_from)
    mimo, identifier = fit_couplings(data, start, "full", max_lag, say)
    comparison: dict[str, Any] = {"skipped": "one SISO model per output needs as many inputs as outputs"}
    if data.u.shape[1] == data.y.shape[1]:
        siso, _ = fit_couplings(data, start, "diagonal", max_lag, say)
        comparison = {k: v for k, v in siso.items() if not k.endswith("_test")}
    report = {
        "data": data.source,
        "test_from": test_from,
        "train_samples": start,
        "samples": len(data.y) - start,
        "inputs": list(data.u_names),
        "outputs": list(data.y_names),
        **mimo,
        "comparison": comparison,
        "seconds": round(time.perf_counter() - began, 2),
    }
    return {"report": report, "identifier": identifier}


def params_values(
    report: dict[str, Any], u: np.ndarray, y: np.ndarray, interpretation: dict[str, Any] | None = None
) -> dict[str, Any]:
    """``ros__parameters`` of the identifier node's MIMO mode (README "Several inputs and outputs").

    ``interpretation``: how the bag's topics became the samples (types, fields, names,
    pairing, sample period: :data:`lenn_ros.fit.bag.INTERPRETATION`), so the node reads the
    robot's own topics the way they were read for the fit; without one (a CSV, an
    ``import-csv`` bag), u and y_p carry Float64MultiArray samples, channels in the
    order of u_names / y_names.
    """
    model = report["model"]
    scaling = model["scaling"]
    limit = float(10.0 ** math.ceil(math.log10(max(1e3, 10.0 * float(max(np.abs(u).max(), np.abs(y).max()))))))
    reading = interpretation or {
        "u_type": topics.FLOAT64_ARRAY,
        "y_type": topics.FLOAT64_ARRAY,
        "u_field": "data[*]",
        "y_field": "data[*]",
        "u_names": list(report["inputs"]),
        "y_names": list(report["outputs"]),
    }
    return {
        "example": 0,
        "network": "lenn",
        **reading,
        "couplings": model["couplings"],
        "y_lags": int(model["y_lags"]),
        "u_lags": int(model["u_lags"]),
        "u_scales": [float(v) for v in scaling["u_scales"]],
        "u_offsets": [float(v) for v in scaling["u_offsets"]],
        "y_scales": [float(v) for v in scaling["y_scales"]],
        "y_offsets": [float(v) for v in scaling["y_offsets"]],
        "order": int(model["order"]),
        "basis": model["basis"],
        "cross_degree": int(model["cross_degree"]),
        "output": "linear",
        "output_scale": 1.0,
        "solver": "rls",
        "forgetting": float(model["live"]["forgetting"]),
        "u_limit": limit,
        "y_limit": limit,
    }


def write_outputs(
    directory: str | Path,
    result: dict[str, Any],
    u: np.ndarray,
    y: np.ndarray,
    interpretation: dict[str, Any] | None = None,
) -> dict[str, str]:
    """``DIR/params.yaml`` (key ``/**``) and ``DIR/weights.npz``; ``weights_in`` absolute, as in the SISO fit.

    ``interpretation``: a bag's (see :func:`params_values`): the node started from the
    file with the bag's remaps reads the same topics the same way.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    report = result["report"]
    weights = directory / "weights.npz"
    result["identifier"].save_state(weights)
    values = {**params_values(report, u, y, interpretation), "weights_in": str(weights.resolve())}
    note = (
        "MIMO: u and y_p read as\n# the bag's topics were (types, fields, names, pairing); weights_in is absolute"
        if interpretation
        else "MIMO: u and y_p carry\n# Float64MultiArray samples, channels in the order of u_names / y_names; "
        "weights_in is absolute"
    )
    params = write_params(directory, report, values, note)
    return {"params": str(params), "weights": str(weights), "report": str(write_report(directory, report))}


def format_report(report: dict[str, Any], dt: float | None = None) -> str:
    """The text report: the choices, then one-step and free-run figures per output, MIMO against SISO."""
    lines = [
        f"{report['data']}: built on samples 1..{report['train_samples']}, "
        f"tested on {report['samples']} samples from {report['test_from']}",
        *_scaling_lines(report),
        *_choice_lines("MIMO (couplings full)", report),
    ]
    comparison = report["comparison"]
    if "model" in comparison:
        lines += _choice_lines("SISO per output (couplings diagonal)", comparison)[-2:]
    lines += _table_lines(report)
    lines += [f"  WARNING: {text}" for text in report["warnings"]]
    lines += [f"  WARNING (SISO comparison): {text}" for text in comparison.get("warnings", [])]
    if dt:
        lines.append(f"  sample time {dt:g} s: test part {report['samples'] * dt:.4g} s")
    if "files" in report:
        lines.append(f"  wrote {report['files']['params']} and {report['files']['weights']}")
        lines.append(f"  live: ros2 run lenn_ros identifier --ros-args --params-file {report['files']['params']}")
    lines.append(f"  {report['seconds']} s")
    return "\n".join(lines)


def _scaling_lines(report: dict[str, Any]) -> list[str]:
    s = report["model"]["scaling"]
    names = [*report["inputs"], *report["outputs"]]
    offsets, scales = [*s["u_offsets"], *s["y_offsets"]], [*s["u_scales"], *s["y_scales"]]
    channels = [f"{n} = {o:.6g} +- {v:.6g}" for n, o, v in zip(names, offsets, scales, strict=True)]
    return [f"  scaling per channel from the training samples, margin {s['margin']:.0%}: {', '.join(channels)}"]


def _choice_lines(title: str, part: dict[str, Any]) -> list[str]:
    m = part["model"]
    lines = [
        f"  {title}: structures judged by the joint free run on training samples "
        f"{m['estimation_samples'] + 1}..{m['estimation_samples'] + m['validation_samples']} "
        "(mean NMSE over outputs)"
        + (f", {m['gaps']} gaps in the training record, not joined" if m.get("gaps") else "")
        + ":"
    ]
    for index, c in enumerate(m["candidates"]):
        mark = "->" if index == 0 else "  "
        value = c["nmse_free_run_validation_db"]
        shown = f"rejected: {c['rejected']}" if c["rejected"] else f"{value:.2f} dB"
        outputs = ", ".join(f"{v:.1f}" for v in c["per_output_db"])
        lines.append(
            f"   {mark} lags {c['lags']}, order {c['order']}, cross degree {c['cross_degree']}: "
            f"{c['weights_per_output']} weights per output, {shown}" + (f" (per output {outputs})" if outputs else "")
        )
    lines.append(
        f"  {title}: lags {m['y_lags']}, order {m['order']}, cross degree {m['cross_degree']}, "
        f"weights {m['weights_per_output']}, by least squares on all training samples"
    )
    lines.append(f"    live: RLS, forgetting {m['live']['forgetting']:.6g}")
    return lines


def _table_lines(report: dict[str, Any]) -> list[str]:
    lines = [
        f"  test part ({report['samples']} samples)        one-step NMSE / RMSE     free run NMSE / RMSE",
    ]
    rows = [("MIMO", report)]
    if "per_output" in report["comparison"]:
        rows.append(("SISO per output", report["comparison"]))
    for j, name in enumerate(report["outputs"]):
        for label, part in rows:
            o = part["per_output"][j]
            lines.append(
                f"    {name:<10} {label:<16} {o['nmse_db']:8.2f} dB {o['rmse']:10.4g}   "
                f"{o['nmse_free_run_db']:8.2f} dB {o['rmse_free_run']:10.4g}"
            )
    if "skipped" in report["comparison"]:
        lines.append(f"    (no SISO comparison: {report['comparison']['skipped']})")
    return lines


def plot(path: str | Path, report: dict[str, Any]) -> Path:
    """Plant against the MIMO model (one-step and free run) on the test part, one panel per output."""
    from lenn_ros.errors import require_extra

    require_extra("matplotlib", "plot", "plots")  # one line naming the extra, not a traceback
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from lenn_ros.plotting import save

    outputs = report["outputs"]
    figure = Figure(figsize=(8.0, 2.6 * len(outputs)), dpi=110)
    FigureCanvasAgg(figure)
    k = np.arange(report["samples"])
    for j, name in enumerate(outputs):
        axis = figure.add_subplot(len(outputs), 1, j + 1)
        axis.plot(k, report["y_test"][:, j], color="black", linewidth=1.4, label="plant")
        axis.plot(k, report["y_hat_test"][:, j], color="tab:red", linestyle="--", linewidth=1.1, label="one step")
        axis.plot(k, report["y_free_test"][:, j], color="tab:green", linestyle=":", linewidth=1.2, label="free run")
        axis.set_ylabel(name)
        axis.grid(alpha=0.3)
        axis.legend(loc="upper right", fontsize=8, ncol=3)
    axis.set_xlabel("discrete time k (test phase)")
    figure.suptitle(f"{report['data']}: MIMO model on the test part", fontsize=10)
    return save(figure, path)


def main(args: Any, u_columns: list[str], y_columns: list[str]) -> int:
    """``lenn-ros fit`` with several channels (or a vector bag); the SISO options that do not apply are refused."""
    from lenn_ros.fit.build import bag_flags

    return run(args, load_mimo_data(args.data, u_columns, y_columns, bag_flags(args)))


def run(args: Any, data: MimoData) -> int:
    """Fit, write (``-o``), plot and report the loaded channels: what ``main`` does once they are read."""
    from lenn_ros.fit.build import test_row

    if (getattr(args, "network", "lenn") or "lenn") != "lenn" or (getattr(args, "solver", "ls") or "ls") != "ls":
        raise FitError("several channels: only the LeNN by least squares is fitted (drop --network/--solver)")
    progress = None if args.json else (lambda text: print(text, file=sys.stderr, flush=True))
    test_from = test_row(data.index, args.test_from, data.test_start)
    result = fit_mimo(data, test_from, progress=progress)
    report = result["report"]
    if args.output:
        train = data.u[: report["train_samples"]]
        report["files"] = write_outputs(args.output, result, train, data.y, data.interpretation)
    if args.plot:
        plot(args.plot, report)
    if args.json:
        print(json.dumps(_jsonable(report), indent=1, allow_nan=False))
        return 0
    print(format_report(report, args.dt))
    return 0
