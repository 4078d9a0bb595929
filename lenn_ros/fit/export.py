"""The model the identifier node runs, and the files ``fit -o`` writes for it.

Each output's selected :class:`~lenn_ros.fit.termmodel.TermModel` becomes the package's
:class:`~lenn_ros.core.structure.Identifier` (one output of one input:
:func:`build_identifier`) or :class:`~lenn_ros.core.mimo.MimoIdentifier` (several: built
by the node's own :func:`lenn_ros.config.build_identifier` from the values written,
:func:`build_mimo_identifier`), RLS-ready, so the model scored is the node's by
construction; the report describes it (:func:`describe_model`, :func:`describe_mimo`).
``fit -o DIR`` writes params.yaml (how the node reads its topics, and the model),
weights.npz and fit.json (:func:`write_outputs`). Apart from the procedure: what the node
is given depends on the model chosen, not on how it was chosen.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lenn_ros import topics
from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.networks import FunctionalLinkNetwork
from lenn_ros.core.structure import Identifier
from lenn_ros.core.threads import cores, side_by_side
from lenn_ros.fit.data import REPORT_FILE, Data
from lenn_ros.fit.record import Record
from lenn_ros.fit.result import FitResult, OutputFit
from lenn_ros.fit.selection import Candidate
from lenn_ros.fit.soundness import level_free, output_rows, widened
from lenn_ros.fit.termmodel import TermModel
from lenn_ros.fit.training import MIN_VALIDATION, VALIDATION_FRACTION, describe_mlp, describe_sgd, fit_lenn_sgd, fit_mlp

#: relative ridge on the live RLS start covariance (see build_identifier): condition number <= 1e7,
#: well inside the ~1/sqrt(machine epsilon) ~ 7e7 at which conventional RLS goes indefinite by round-off
RLS_RIDGE = 1e-7


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


def identifiers(
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
    from lenn_ros.service import building

    models = common_lags([fitted.model for fitted in outputs])
    values = {**_vector_reading(data), **mimo_values(models, data, forgetting)}
    resolved, network = config.resolve(values)
    identifier = building.build_identifier({**values, **resolved}, network)

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
    other output reads (:func:`identifiers` has widened its reading, as :func:`_read_wide` does a single output's)."""
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


def write_outputs(directory: str | Path, result: FitResult, data: Data) -> dict[str, str]:
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
    identifier = result.identifier
    weights = directory / "weights.npz"
    train = result.train_samples
    u, y = data.matrices()
    if isinstance(identifier, MimoIdentifier):
        identifier.save_state(weights)
        forgetting = result.model["live"]["forgetting"]
        values = {**_vector_reading(data), **mimo_values(result.models, data, forgetting)}
        note = (
            "several channels, read as the bag's\n# topics were (or Float64MultiArray samples); weights_in is absolute"
        )
    else:
        identifier.model.save(weights)
        forgetting = result.model["live"].get("forgetting", 1.0)
        model_values = params_values(identifier, result.models[0], forgetting, u[:train, 0], y[:, 0])
        values = {**data.interpretation, **model_values}
        note = "starts from weights_in below;\n# move the directory and weights_in must follow: it is absolute"
    values["weights_in"] = str(weights.resolve())
    # the model was chosen and refined for its free run: learning on from it live keeps only what simulates
    # no worse (without, a robot's 10-minute bag: fit's free run -65.1 dB, after learning on -55.6 dB)
    values["free_run_guard"] = True
    params = write_params(directory, result, values, note)
    return {"params": str(params), "weights": str(weights), "report": str(write_report(directory, result))}


def write_report(directory: Path, result: FitResult) -> Path:
    """DIR/fit.json: the report as ``--json`` prints it, beside the weights.

    :func:`lenn_ros.load_model` and the twin node read it for the residual statistics
    (the bands, the twin's noise) and for what the model is.
    """
    path = directory / REPORT_FILE
    path.write_text(result.to_json())
    return path


def write_params(directory: Path, result: FitResult, values: dict[str, Any], note: str) -> Path:
    """DIR/params.yaml for every node (``/**``), headed by where it came from and how to start from it."""
    params = directory / "params.yaml"
    header = (
        f"# written by lenn-ros fit ({result.data}, test from sample {result.test_from})\n"
        f"# ros2 run lenn_ros identifier --ros-args --params-file {params}   ({note})\n"
    )
    params.write_text(header + yaml.safe_dump({"/**": {"ros__parameters": values}}, sort_keys=False))
    return params
