"""``lenn-ros fit DATA --test-from K``: build a good model of logged data, automatically.

What it does, each step reported:
1. reads u and y from a CSV file or a bag; samples 1..K-1 (1-based) build the model,
   samples K.. only score it; gaps in a bag's record stay gaps (nothing is fitted or
   simulated across them);
2. takes offsets and scale factors from the training samples (with a margin);
3. selects the family (polynomial, hinge, increment: :mod:`lenn_ros.fit.families`),
   the lags and the terms by orthogonal forward regression, judging every candidate by
   the free runs of blocks of the training samples, each simulated by the weights of
   the other blocks, and rejecting those that run away, leave the range or do worse than
   the mean anywhere (:mod:`lenn_ros.fit.selection`);
4. refines the weights of the best few candidates on simulation error, as many
   iterations as the blocks vouch for, zero included (:mod:`lenn_ros.fit.refinement`),
   and keeps the best; the weights delivered are those of all training samples;
5. scores the frozen model on the test samples: one-step and free run (the free run
   starts from the measured outputs just before sample K, as a live switch from
   series-parallel to parallel would), counting clipped inputs and flagging divergence;
6. with ``-o DIR`` writes ``params.yaml`` and ``weights.npz`` from which the
   identifier node starts and keeps adapting live (RLS with forgetting).

Several ``--u`` / ``--y`` columns, or a vector bag, go to :mod:`lenn_ros.fit.mimo` (the command line decides).
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lenn_ros.bag.csv_import import is_number
from lenn_ros.core.evaluation import free_run_problems, free_run_segments
from lenn_ros.core.metrics import band_half_width, coverage, nmse_db, rmse
from lenn_ros.core.networks import FunctionalLinkNetwork
from lenn_ros.core.scaling import Scaling
from lenn_ros.core.structure import Identifier
from lenn_ros.fit.data import REPORT_FILE, Data, FitError
from lenn_ros.fit.families import INCREMENT_LAGS, pass_through_weights
from lenn_ros.fit.refinement import cross_validated_refinement
from lenn_ros.fit.selection import (
    NONLINEAR_GAIN,
    PARSIMONY,
    Candidate,
    Record,
    TermModel,
    fold_blocks,
    loosen,
    order_candidates,
    out_of_fold_residuals,
    select_structure,
)

#: share of the training samples the epochs of an MLP / SGD fit are early-stopped on
VALIDATION_FRACTION = 0.2
MIN_VALIDATION = 50
#: relative ridge on the live RLS start covariance (see build_identifier): condition number <= 1e7,
#: well inside the ~1/sqrt(machine epsilon) ~ 7e7 at which conventional RLS goes indefinite by round-off
RLS_RIDGE = 1e-7


def load_data(
    path: str | Path, u_column: str | None = None, y_column: str | None = None, flags: dict[str, Any] | None = None
) -> Data | Any:
    """u and y from a bag (directory or .mcap: :mod:`lenn_ros.fit.bag`) or a CSV file (columns by name or index).

    A bag whose identifier read several channels gives a :class:`~lenn_ros.fit.mimo.MimoData`.
    """
    path = Path(path)
    if not path.exists():
        raise FitError(f"{path} does not exist (expected a CSV file or a bag directory)")
    if path.is_dir() or path.suffix == ".mcap":
        from lenn_ros.fit.bag import load_bag

        return load_bag(path, {**(flags or {}), "u": u_column, "y": y_column})
    return _load_csv(path, u_column, y_column)


def read_csv_rows(path: Path) -> tuple[list[str] | None, list[list[str]], int]:
    """(header or None, the data rows, the width): blank lines dropped; a first row of numbers is data."""
    with path.open(newline="") as stream:
        rows = [row for row in csv.reader(stream) if row and any(cell.strip() for cell in row)]
    if not rows:
        raise FitError(f"{path} is empty")
    header = None if all(is_number(cell) for cell in rows[0]) else [cell.strip() for cell in rows[0]]
    return header, rows[1:] if header else rows, len(rows[0])


def _load_csv(path: Path, u_column: str | None, y_column: str | None) -> Data:
    header, body, width = read_csv_rows(path)
    if u_column is None or y_column is None:
        if header and "u" in header and "y" in header:
            u_column, y_column = u_column or "u", y_column or "y"
        elif width == 2:
            u_column, y_column = u_column or "0", y_column or "1"
        else:
            shown = ", ".join(header) if header else f"{width} unnamed columns"
            raise FitError(f"{path} has columns {shown}: pass --u COL --y COL (name or 0-based index)")
    iu, iy = _column(header, u_column, width, path), _column(header, y_column, width, path)
    u, y = np.empty(len(body)), np.empty(len(body))
    for n, row in enumerate(body):
        try:
            u[n], y[n] = float(row[iu]), float(row[iy])
        except (ValueError, IndexError):
            line = n + (2 if header else 1)
            raise FitError(f"{path}, line {line}: not a number in column {u_column} or {y_column}: {row}") from None
    names = (header[iu], header[iy]) if header else (str(iu), str(iy))
    return Data(u, y, f"CSV {path}: u = column {names[0]}, y = column {names[1]}")


def _column(header: list[str] | None, column: str, width: int, path: Path) -> int:
    if header and column in header:
        return header.index(column)
    if column.lstrip("-").isdigit() and 0 <= int(column) < width:
        return int(column)
    shown = ", ".join(header) if header else f"indices 0..{width - 1}"
    raise FitError(f"{path}: no column {column!r}; columns are {shown}")


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


def build_identifier(model: TermModel, record: Record, forgetting: float) -> Identifier:
    """The fitted model as the package's :class:`Identifier` (what the node runs), RLS-ready.

    The RLS covariance is the least-squares one of the training features, scaled to the
    forgetting factor's memory: live adaptation starts as if it had seen the training data.
    A ridge of RLS_RIDGE times the largest eigenvalue of the features' Gram matrix bounds
    its condition number to 1 / RLS_RIDGE: lagged outputs are nearly collinear, and the
    robot arm's 29 terms gave a condition number of 7e10, at which the conventional RLS
    update loses positive definiteness by round-off (it stopped learning at its 97th sample).
    """
    factors = model.factors if len(model.factors) else None
    network = FunctionalLinkNetwork(
        n_inputs=model.y_lags + model.u_lags,
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
    network.weights_ = np.array(model.weights, dtype=np.float64)
    features, _ = model.regression(record.u, record.y)
    network.covariance_ = rls_covariance(features[record.valid_rows(model.warm_up)], forgetting)
    return Identifier(model.structure, network, learning=False)


def rls_covariance(features: np.ndarray, forgetting: float) -> np.ndarray:
    """The RLS covariance as if live adaptation had seen ``features`` (see :func:`build_identifier`)."""
    gram = features.T @ features
    gram += max(RLS_RIDGE * float(np.linalg.eigvalsh(gram)[-1]), 1e-9) * np.eye(features.shape[1])
    memory = len(features) if forgetting >= 1.0 else min(len(features), 1.0 / (1.0 - forgetting))
    return np.linalg.inv(gram) * (len(features) / memory)


def fit(
    data: Data,
    test_from: int,
    *,
    refine: bool = True,
    network: str = "lenn",
    solver: str = "ls",
    progress: Any = None,
) -> dict[str, Any]:
    """The whole procedure; returns the report (also what ``--json`` prints) and the identifier.

    The structure is chosen on blocks of the training samples (each simulated by the
    weights of the others), the weights delivered are those of all training samples,
    refined on simulation error as many times as the blocks vouch for
    (:func:`~lenn_ros.fit.refinement.cross_validated_refinement`). ``solver="sgd"``
    trains the selected terms by SGD epochs instead (:func:`fit_lenn_sgd`), for a node
    that will learn by SGD; ``network="mlp"`` an MLP on the selected lags.
    """
    from threadpoolctl import threadpool_limits

    # the selection's linear algebra is thousands of small products: BLAS threads only
    # contend for the cores (a 2666 x 40 Gram took 1.8 ms threaded, 0.34 ms on one thread)
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit(data, test_from, refine, network, solver, progress)


def _fit(data: Data, test_from: int, refine: bool, network: str, solver: str, progress: Any) -> dict[str, Any]:
    began = time.perf_counter()
    say = progress or (lambda text: None)
    u, y = data.u, data.y
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        bad = int(np.count_nonzero(~(np.isfinite(u) & np.isfinite(y))))
        raise FitError(f"{bad} samples hold NaN/inf: remove or interpolate them before fitting")
    start = check_split(len(y), test_from)
    u_train, y_train = u[:start], y[:start]
    breaks = [b for b in data.breaks if 0 < b < start]
    try:
        scaling = Scaling.from_training(u_train, y_train)
    except ValueError as error:
        raise FitError(str(error)) from None
    record = Record.of(u_train, y_train, breaks)
    blocks = fold_blocks(start, 1)
    say(
        f"selecting a structure on samples 1..{start}: {len(blocks)} blocks, each simulated by the weights "
        f"of the others{f', {len(breaks)} gaps in the record' if breaks else ''}"
    )
    candidates, selection_warnings = _select(record, scaling, say)
    chosen = candidates[0]
    refinement: dict[str, Any] = {"done": False}
    if refine and solver == "ls" and network == "lenn":
        chosen, refinement = _refine_best(candidates, record, say)
    final = chosen.model
    forgetting = live_forgetting(start)
    identifier = build_identifier(final, record, forgetting)
    described = describe_model(final, chosen, forgetting)
    if network == "mlp":
        validation_start = start - max(MIN_VALIDATION, round(VALIDATION_FRACTION * start))
        say(f"training an MLP on lags {final.y_lags}/{final.u_lags} by epochs, early-stopped on the held-out tail")
        identifier, epochs = fit_mlp(final, u_train, y_train, validation_start)
        described = describe_mlp(identifier, epochs)
    elif solver == "sgd":
        validation_start = start - max(MIN_VALIDATION, round(VALIDATION_FRACTION * start))
        say(f"training the {len(final.exponents)} selected terms by SGD epochs, early-stopped on the held-out tail")
        identifier, epochs = fit_lenn_sgd(final, u_train, y_train, validation_start, chosen.spec.increment)
        described = {**describe_model(final, chosen, forgetting), **describe_sgd(identifier, epochs)}
    report = score(identifier, u, y, start, data.breaks)
    report["warnings"] = selection_warnings + report["warnings"]
    report["intervals"] = fit_intervals(report, identifier, chosen, record, network == "lenn" and solver == "ls")
    report.update(
        {
            "data": data.source,
            "test_from": test_from,
            "train_samples": start,
            "model": described,
            "choices": {
                "scaling": {
                    "from": f"training samples 1..{start}",
                    "margin": scaling.margin,
                    "y_offset": scaling.y_offset,
                    "y_scale": scaling.y_scale,
                    "u_offset": scaling.u_offset,
                    "u_scale": scaling.u_scale,
                },
                "blocks": len(blocks),
                "gaps": len(breaks),
                "judged_by": f"pooled free-run RMSE over {len(blocks)} blocks of the training samples, each "
                "simulated from its measured start by the weights fitted to the other blocks; rejected: diverged, "
                "clipped or worse than the block mean in any block, an unsound free run over the whole training "
                "record or on its input shuffled in blocks; a nonlinear candidate must beat the best linear one by "
                f"{NONLINEAR_GAIN:.0%}; of those within {PARSIMONY:.0%} of the lowest, the fewest terms",
                "candidates": [c.as_dict() for c in candidates],
                "chosen": candidates.index(chosen),
                "refinement": refinement,
                "time_scale": time_scale_note(chosen),
            },
            "seconds": round(time.perf_counter() - began, 2),
        }
    )
    return {"report": report, "identifier": identifier, "model": final}


#: candidates (best first) whose weights are refined on simulation error; the best refined one is kept
REFINED_CANDIDATES = 3


def _refine_best(candidates: list[Candidate], record: Record, say: Any) -> tuple[Candidate, dict[str, Any]]:
    """Refine the first REFINED_CANDIDATES usable candidates (iterations chosen on the blocks); keep the best.

    Refinement can reorder candidates (a hinge model that least squares left behind may
    simulate best once refined), so the choice among them is made again on the refined
    block scores with the same rules (:func:`order_candidates`).
    """
    usable = [c for c in candidates if c.model is not None][:REFINED_CANDIDATES]
    for candidate in usable:
        say(f"refining {candidate.spec.label} ({candidate.terms} terms) on simulation error")
        result = cross_validated_refinement(candidate, record)
        candidate.refinement = result.as_dict()
        candidate.rmse_validation = result.rmse_blocks_after
    for candidate in usable:  # the report's list: the refined ones first (the chosen one leading), then the rest
        candidates.remove(candidate)
    candidates[:0] = order_candidates(usable)
    chosen = candidates[0]
    return chosen, {"done": True, **chosen.refinement}


def time_scale_note(candidate: Candidate) -> str:
    """What the report says about lag spans: the issue of records sampled far faster than their dynamics."""
    spec = candidate.spec
    if spec.increment and spec.lags > max(INCREMENT_LAGS):
        return (
            f"multi-scale increments over {spec.lags - 1} samples (spans 1, 2, 4, ...): the record is sampled "
            "far faster than its dynamics; the model runs at the recorded rate"
        )
    if spec.increment:
        return "increment form: y(k+1) = y(k) + f(increments, inputs), the integrator kept exactly"
    return f"lags {spec.lags} samples at the recorded rate"


def _select(record: Record, scaling: Scaling, say: Any) -> tuple[list[Candidate], list[str]]:
    """(candidates, warnings): the strict selection, else the loose one with a warning, else FitError."""

    def tell(candidate: Candidate) -> None:
        shown = (
            f"{candidate.terms} terms, free-run RMSE {candidate.rmse_validation:.5g}"
            if candidate.model is not None
            else f"rejected ({candidate.rejected})"
        )
        say(f"  {candidate.spec.label}: {shown}")

    candidates = select_structure(record.u, record.y, scaling, record.breaks, progress=tell)
    warnings = []
    if not any(c.model is not None for c in candidates):
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


def score(
    identifier: Identifier, u: np.ndarray, y: np.ndarray, start: int, breaks: list[int] | tuple[int, ...] = ()
) -> dict[str, Any]:
    """Test-part figures of the frozen model: one-step and free run from sample ``start``.

    ``breaks`` (samples that start a new run: gaps in a bag) are never crossed: the
    one-step pass and the free run restart from the measured outputs after each
    (:func:`~lenn_ros.core.evaluation.free_run_segments`, as ``evaluate`` does); the samples
    that seed them are not scored.
    """
    cuts = sorted(int(b) for b in breaks if 0 < b < len(y))
    y_hat = np.full(len(y), np.nan)
    window = identifier.structure.warm_up
    for a, b in itertools.pairwise([0, *cuts, len(y)]):
        if b - a > window:
            y_hat[a:b] = identifier.run(u[a:b], y[a:b], learn=False)
    first = start - window  # the regressors that predict samples start..N-1
    x_test, _ = identifier.structure.regressors(u[first:], y[first:])
    test_clipped = int(np.count_nonzero(np.abs(x_test[:-1]) > 1.0))
    if cuts:
        index = np.arange(len(y)) + np.searchsorted(cuts, np.arange(len(y)), side="right")  # one lost per break
        y_free, info = free_run_segments(identifier, index, u, y, start)
    else:
        y_free, info = identifier.free_run(u, y, start), identifier.last_free_run
    y_test = y[start:]
    simulated = np.isfinite(y_free)
    healthy = not info["diverged"] and bool(simulated.any())
    predicted = np.isfinite(y_hat[start:])
    structure = identifier.structure
    outside = Scaling(structure.y_offset, structure.y_scale, structure.u_offset, structure.u_scale).outside(
        u[start:], y_test
    )
    return {
        "samples": len(y_test),
        "rmse": rmse(y_test[predicted], y_hat[start:][predicted]),
        "nmse_db": nmse_db(y_test[predicted], y_hat[start:][predicted]),
        "rmse_free_run": rmse(y_test[simulated], y_free[simulated]) if healthy else math.nan,
        "nmse_free_run_db": nmse_db(y_test[simulated], y_free[simulated]) if healthy else math.nan,
        "free_run": {**info, "starts_from": f"measured outputs before sample {start + 1}"},
        "clipped_inputs_one_step": test_clipped,
        "test_samples_outside_training_range": outside,
        "warnings": free_run_problems(y_test[simulated], y_free[simulated], info),
        "y_test": y_test,
        "y_hat_test": y_hat[start:],
        "y_free_test": y_free,
        "y_hat_train": y_hat[:start],
    }


def fit_intervals(
    report: dict[str, Any], identifier: Identifier, chosen: Candidate, record: Record, held_out: bool
) -> dict[str, Any]:
    """Nominal 95 % bands, one step ahead and in free run, and how much of the test part they cover.

    Both from errors on samples the model was not fitted to: the blocks the structure
    was chosen by, each run by the weights fitted without it (``held_out``), one step
    ahead and in free run. An MLP or SGD model, which the blocks did not run, takes its
    own errors over the training record (in-sample: optimistic, and said). A
    half-width is the 95 % quantile of |e|, not 1.96 sigma: free-run errors drift and
    have heavy tails. The one-step std is also the noise the twin node may add.
    """
    y_train = record.y
    if held_out:
        one_step = out_of_fold_residuals(chosen, record, one_step=True)
        free = out_of_fold_residuals(chosen, record)
        source = "the selection's blocks, each run by the weights fitted without it"
    else:
        warm = identifier.structure.warm_up
        one_step = report["y_hat_train"][warm:] - y_train[warm:]
        free = identifier.free_run(record.u, y_train, warm) - y_train[warm:]
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
    return {
        "network": "lenn",
        "family": chosen.spec.family,
        "structure": {
            "y_lags": model.y_lags,
            "u_lags": model.u_lags,
            "predicts": "y(k) from y(k-1..), u(k-1..)",
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

    s = selected.scaling
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

    s = selected.scaling
    structure = dataclasses.replace(selected.structure, output_offset=s.y_offset)
    features, _ = selected.regression(u[:validation_start], y[:validation_start])
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
    limit = float(10.0 ** math.ceil(math.log10(max(1e3, 10.0 * float(max(np.abs(u).max(), np.abs(y).max()))))))
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
        "known_a": [0.0],
        "known_b": [0.0],
        "y_scale": float(s.y_scale),
        "u_scale": float(s.u_scale),
        "y_offset": float(s.y_offset),
        "u_offset": float(s.u_offset),
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


def write_outputs(
    directory: str | Path,
    result: dict[str, Any],
    u: np.ndarray,
    y: np.ndarray,
    interpretation: dict[str, Any] | None = None,
) -> dict[str, str]:
    """``DIR/params.yaml`` (key ``/**``: any node name or namespace) and ``DIR/weights.npz``.

    ``interpretation``: the node values that say how its topics become samples (a
    bag's types, fields, pairing, sample period: :mod:`lenn_ros.fit.bag`), so the node
    started from the file reads the topics the model was fitted on, the same way.

    ``weights_in`` in the params file is the absolute path of the weights: the node
    opens a relative path from its own working directory (it cannot know where the
    params file was), so only an absolute path makes the params file enough on its own,
    for the node and for ``lenn-ros evaluate`` alike, from any directory.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    identifier, model = result["identifier"], result["model"]
    forgetting = result["report"]["model"]["live"].get("forgetting", 1.0)
    weights = directory / "weights.npz"
    identifier.model.save(weights)
    values = {
        **(interpretation or {}),
        **params_values(identifier, model, forgetting, u, y),
        "weights_in": str(weights.resolve()),
    }
    note = "starts from weights_in below;\n# move the directory and weights_in must follow: it is absolute"
    params = write_params(directory, result["report"], values, note)
    return {"params": str(params), "weights": str(weights), "report": str(write_report(directory, result["report"]))}


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


#: the command line's flags that say how a bag's topics become samples (fit.bag.load_bag)
BAG_FLAGS = ("u_field", "y_field", "u_names", "y_names", "sample_period", "pairing")


def bag_flags(args: Any) -> dict[str, Any]:
    return {key: getattr(args, key, None) for key in BAG_FLAGS}


def test_row(index: np.ndarray | None, given: int | None, recorded: int | None) -> int | None:
    """The 1-based row ``--test-from`` means: a bag's is a sample index, as the node counts (the row it
    starts), a CSV's a row; without it, the bag's recorded test start (a row already)."""
    if given is None:
        return recorded
    return given if index is None else int(np.searchsorted(index, given)) + 1


def load_for(args: Any) -> Any:
    """What ``lenn-ros fit DATA`` reads: a :class:`Data`, or a ``MimoData`` where the bag's identifier read
    several channels (then ``cli`` hands it to :func:`lenn_ros.fit.mimo.run`)."""
    u_columns, y_columns = columns(args.u), columns(args.y)
    return load_data(
        args.data, u_columns[0] if u_columns else None, y_columns[0] if y_columns else None, bag_flags(args)
    )


def main(args: Any, data: Data | None = None) -> int:
    import sys

    data = load_for(args) if data is None else data
    progress = None if args.json else (lambda text: print(text, file=sys.stderr, flush=True))
    network = getattr(args, "network", "lenn") or "lenn"
    test_from = test_row(data.index, args.test_from, data.test_start)
    solver = getattr(args, "solver", "ls") or "ls"
    result = fit(data, test_from, refine=not args.no_refine, network=network, solver=solver, progress=progress)
    report = result["report"]
    if args.output:
        report["files"] = write_outputs(
            args.output, result, data.u[: report["train_samples"]], data.y, data.interpretation
        )
    if args.plot:
        from lenn_ros.plotting import plot_identification

        title = f"{Path(args.data).name}: free-run RMSE {report['rmse_free_run']:.4g} on the test part"
        band = report["intervals"]["free_run"]["half_width"]
        plot_identification(args.plot, report["y_test"], report["y_hat_test"], title, report["y_free_test"], band)
    if args.json:
        print(json.dumps(_jsonable(report), indent=1, allow_nan=False))
        return 0
    print(format_report(report, args.dt))
    return 0


def columns(given: str | list[str] | None) -> list[str]:
    """``--u`` / ``--y`` as a list: the command line repeats them (MIMO), a caller may pass one name."""
    if given is None:
        return []
    return [given] if isinstance(given, str) else list(given)


def is_vector_bag(path: str | Path) -> bool:
    """A bag whose u holds Float64MultiArray samples is a MIMO run (``import-csv`` with several columns)."""
    path = Path(path)
    if not (path.is_dir() or path.suffix == ".mcap") or not path.exists():
        return False
    from lenn_ros.bag.vectors import is_vector_run

    return is_vector_run(path)


def format_report(report: dict[str, Any], dt: float | None = None) -> str:
    m, c = report["model"], report["choices"]
    lines = [
        f"{report['data']}: built on samples 1..{report['train_samples']}, "
        f"tested on {report['samples']} samples from {report['test_from']}",
        f"  scaling from the training samples, margin {c['scaling']['margin']:.0%}: "
        f"y = {c['scaling']['y_offset']:.6g} +- {c['scaling']['y_scale']:.6g}, "
        f"u = {c['scaling']['u_offset']:.6g} +- {c['scaling']['u_scale']:.6g}",
        f"  structure judged by the free runs of {c['blocks']} blocks of the training samples"
        + (f" ({c['gaps']} gaps in the record, not joined)" if c.get("gaps") else "")
        + ":",
    ]
    lines += _candidate_lines(c)
    lines.append(f"  time scale: {c['time_scale']}")
    if m["network"] == "lenn" and "epochs" in m:
        e = m["epochs"]
        lines.append(f"  trained by SGD epochs: {e['epochs']} run, best {e['best_epoch']} ({e['stopped']})")
    if m["network"] == "mlp":
        e = m["epochs"]
        lines.append(f"  model: MLP {m['structure']} hidden {m['expansion']['hidden']}, {m['n_terms']} weights")
        lines.append(f"  trained by epochs: {e['epochs']} run, best {e['best_epoch']} ({e['stopped']})")
    else:
        terms = " + ".join(m["expansion"]["terms"])
        lines.append(f"  model: {m['family']} ({m['expansion']['basis']}), {m['n_terms']} terms: {terms}")
    refinement = c["refinement"]
    if refinement.get("done"):
        lines.append(
            f"  refined on simulation error: {refinement['iterations']} of {refinement['tried']} iterations "
            f"(chosen on the blocks: held-out free-run RMSE {refinement['rmse_blocks_before']:.5g} -> "
            f"{refinement['rmse_blocks_after']:.5g})"
        )
    live = m["live"]
    lines.append(
        f"  live: RLS, forgetting {live['forgetting']:.6g}"
        if live["solver"] == "rls"
        else f"  live: SGD, alpha {live['alpha']:.6g}, beta {live['beta']:.3g}"
    )
    lines += _test_lines(report, dt)
    return "\n".join(lines)


#: candidates listed in the text report (the JSON has them all)
SHOWN_CANDIDATES = 12


def _candidate_lines(choices: dict[str, Any]) -> list[str]:
    lines = []
    listed = choices["candidates"]
    for index, candidate in enumerate(listed[:SHOWN_CANDIDATES]):
        mark = "->" if index == choices["chosen"] else "  "
        value = candidate["rmse_free_run_validation"]
        shown = f"free-run RMSE {value:.5g}" if value is not None else f"rejected: {candidate['rejected']}"
        if candidate.get("note"):
            shown += f" ({candidate['note']})"
        if candidate.get("refinement"):
            shown += f", refined {candidate['refinement']['iterations']}x"
        lines.append(
            f"   {mark} {candidate['family']} degree {candidate['degree']}, lags {candidate['y_lags']}/"
            f"{candidate['u_lags']}: {candidate['terms']} of {candidate['dictionary']} terms, {shown}"
        )
    if len(listed) > SHOWN_CANDIDATES:
        usable = sum(1 for c in listed if c["rmse_free_run_validation"] is not None)
        more = len(listed) - SHOWN_CANDIDATES
        lines.append(f"      ... {more} more ({usable} of {len(listed)} usable; --json lists all)")
    return lines


def _test_lines(report: dict[str, Any], dt: float | None) -> list[str]:
    lines = [f"  test part ({report['samples']} samples):"]
    lines.append(f"    one-step: RMSE {report['rmse']:.5g}, NMSE {report['nmse_db']:.2f} dB")
    free = report["free_run"]
    lines.append(
        f"    free run (from the measured outputs before sample {report['test_from']}): "
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
    lines += [f"  WARNING: {text}" for text in report["warnings"]]
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
