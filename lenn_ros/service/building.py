"""Parameters to an identifier: the one factory, for any number of channels (:func:`build_identifier`),
and the model as the node builds it: from a params file, from the configuration a recording holds, with
the weights learning starts from (``weights_in``).

One place for it: the node, ``evaluate``, ``fit`` (a bag's samples, the several-channel model it
writes), ``replay`` and ``load_model`` all build here, so a params file means the same model
everywhere. The values are those of :mod:`lenn_ros.config` (the one table of parameters, checked by
its :func:`~lenn_ros.config.resolve`); a params file is matched to a node by rcl's own rules
(:mod:`lenn_ros.service.params`); ``weights_in`` is opened as the node opens it (``~`` expanded, a
relative path from the current directory).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

from lenn_ros import topics
from lenn_ros.bag.reader import iter_messages
from lenn_ros.config import (
    NODE_PARAMETERS,
    UNSET_SCALE,
    ConfigError,
    is_mimo,
    resolve,
    rls_forgetting,
    side_channels,
)
from lenn_ros.core.expansions import parse_terms, siso_channels
from lenn_ros.core.fields import FieldError
from lenn_ros.core.mimo import MimoIdentifier, MimoStructure, build_mimo_identifier, parse_couplings
from lenn_ros.core.networks import MLP, FunctionalLinkNetwork, ModelFileError, read_weights_file
from lenn_ros.core.structure import Identifier, ModelStructure
from lenn_ros.service import RecordingError
from lenn_ros.service.params import read_params_file
from lenn_ros.service.reading import READING
from lenn_ros.session import ParameterChange, Session, SessionConfig

#: Every node parameter's default: what a value a params file or a recording leaves out means.
NODE_DEFAULTS = {parameter.name: parameter.default for parameter in NODE_PARAMETERS}


# -- the one factory: checked parameter values -> an identifier of one channel or several ---------------


def build_identifier(values: dict[str, Any], network: str) -> Identifier | MimoIdentifier:
    """The identifier parameter values describe (node, params file or CLI): an :class:`Identifier` for one
    input and one output, a :class:`MimoIdentifier` (one network per output) where the fields or topics
    name several channels (:func:`~lenn_ros.config.is_mimo`). The one factory: every front-end builds here.

    The values are the user's, so what the model's own checks refuse (a term list that
    does not parse, a solver that needs a linear output) is a :class:`ConfigError`.
    """
    try:
        return _build_identifier(values, network)
    except ConfigError:
        raise
    except ValueError as error:
        raise ConfigError(str(error)) from error


def _build_identifier(values: dict[str, Any], network: str) -> Identifier | MimoIdentifier:
    if is_mimo(values):
        return _build_mimo(values, network)
    structure = ModelStructure(
        y_lags=int(values["y_lags"]),
        u_lags=int(values["u_lags"]),
        known_a=_coefficients(values["known_a"]),
        known_b=_coefficients(values["known_b"]),
        y_scale=float(values["y_scale"]),
        u_scale=float(values["u_scale"]),
        separate=bool(values["separate"]),
        y_offset=float(values.get("y_offset", 0.0)),
        u_offset=float(values.get("u_offset", 0.0)),
        output_offset=float(values.get("output_offset", 0.0)),
        y_abs=bool(values.get("y_abs", False)),
    )
    if values.get("weights_in") and not structure.scaled:
        structure = _scaling_of_weights(structure, str(values["weights_in"]))
    terms = [str(t) for t in values.get("terms", [""]) if str(t).strip()]
    selected = terms and network == "lenn"  # the MLP takes every input (terms are the LeNN's)
    exponents = factors = None
    if selected:
        rows, factor_rows = parse_terms(terms, siso_channels(structure.y_lags, structure.u_lags))
        exponents = rows.tolist()
        factors = factor_rows.tolist() if factor_rows[:, 0].any() else None
    if exponents is not None and structure.separate:
        raise ConfigError("terms select one combiner over all inputs: set separate: false")
    model = _make_model(values, network, structure.n_inputs, structure.branches(), exponents, factors)
    return Identifier(structure, model)


def _make_model(
    values: dict[str, Any],
    network: str,
    n_inputs: int,
    branches: list[list[int]] | None,
    exponents: list | None,
    factors: list | None = None,
) -> Any:
    """One network from the parameter values (the SISO model, or one output's of a MIMO model)."""
    common = {
        "n_inputs": n_inputs,
        "branches": branches,
        "output": values["output"],
        "output_scale": float(values["output_scale"]),
        "alpha": float(values["alpha"]),
        "beta": float(values["beta"]),
        "random_state": int(values["seed"]),
    }
    if network == "mlp":
        model = MLP(hidden=[int(h) for h in values["hidden"]], **common)
    elif network == "lenn":
        model = FunctionalLinkNetwork(
            exponents=exponents,
            factors=factors,
            order=int(values["order"]),
            basis=values["basis"],
            cross_degree=int(values["cross_degree"]),
            solver=values["solver"],
            forgetting=rls_forgetting(values),
            nlms_step=float(values["nlms_step"]),
            **common,
        )
    else:
        raise ConfigError(f"unknown network {network!r}; use 'lenn' or 'mlp'")
    return model


def _per_channel(values: dict[str, Any], name: str, count: int) -> tuple[float, ...]:
    """``u_scales`` etc.: one value per channel, or the scalar parameter for all of them."""
    listed = [float(value) for value in values.get(f"{name}s", [0.0])]
    if len(listed) == count:
        return tuple(listed)
    if len(listed) == 1:
        value = float(values.get(name, 1.0 if name.endswith("scale") else 0.0))
        return (value,) * count  # (a scale left at 0: learnt per channel by the session's warm-up)
    raise ConfigError(f"{name}s has {len(listed)} values for {count} channels: give one per channel, or one")


def _pass_through(values: dict[str, Any], n_y: int) -> tuple[bool, ...]:
    """``y_pass_through``: one flag per output, or the single default (none passed through)."""
    flags = [bool(flag) for flag in values.get("y_pass_through", [False])]
    if len(flags) == n_y:
        return tuple(flags)
    if flags == [False]:
        return ()
    raise ConfigError(f"y_pass_through has {len(flags)} values for {n_y} outputs: give one per output")


def unlearnt_mimo_scales(values: dict[str, Any]) -> str | None:
    """Several channels with scales left at 0 and ``weights_in``: what cannot work (None: nothing).

    The warm-up learns such scales per channel, but weights saved on one scaling mean
    something else on another: a MIMO weights file needs its scales given.
    """
    if not is_mimo(values) or not values.get("weights_in"):
        return None
    unset = [
        side
        for side in ("u", "y")
        if float(values.get(f"{side}_scale", 1.0)) == UNSET_SCALE
        and all(float(v) == UNSET_SCALE for v in values.get(f"{side}_scales", [0.0]))
    ]
    if not unset:
        return None
    names = " and ".join(f"{side}_scales" for side in unset)
    return (
        f"weights_in with several channels and {names} not given: the weights mean something only on the scaling "
        f"they were learnt with; give {names} (one per channel; lenn-ros fit writes them)"
    )


def _scaling_of_weights(structure: ModelStructure, weights_in: str) -> ModelStructure:
    """``structure`` with the scales the weights file was saved with, for ``weights_in`` without scales.

    A network's weights mean something only on the scaling their inputs had; a run
    that learnt its scales by the warm-up saves them with the weights (``weights_out``),
    so restarting from that file with the same short command needs no scales either.
    A file without them (an older save) cannot say: then the error names the fix.
    """
    path = os.path.abspath(os.path.expanduser(weights_in))
    try:
        header, _ = read_weights_file(path)
    except (ModelFileError, OSError, ValueError):
        return structure  # a missing or broken file: the load (node, evaluate) says so in its own line
    scaling = header.get("scaling") if isinstance(header, dict) else None
    keys = Identifier.SCALING  # (what a save records of its inputs' scaling)
    if isinstance(scaling, dict) and all(isinstance(scaling.get(k), int | float) for k in keys):
        return dataclasses.replace(structure, **{k: float(scaling[k]) for k in keys})
    raise ConfigError(
        "weights_in with y_scale/u_scale 0 (learnt from the warm-up), and the file holds no scales: weights mean "
        "something only on the scaling they were learnt with; give y_scale, u_scale, y_offset, u_offset (the run "
        "that saved them said its learnt ones in the line 'scales learnt from ...' and in status scaling; "
        "lenn-ros fit writes them; a run of this version saves them with weights_out)"
    )


def _build_mimo(values: dict[str, Any], network: str) -> MimoIdentifier:
    """One network per output over the coupled channels; SISO-only structure options are refused."""
    try:
        u_names = side_channels(values, "u")[0]
        y_names = side_channels(values, "y")[0]
    except FieldError as error:
        raise ConfigError(str(error)) from None
    unsupported = [
        name
        for name, given in (
            ("known_a", any(float(a) for a in values.get("known_a", [0.0]))),
            ("known_b", any(float(b) for b in values.get("known_b", [0.0]))),
        )
        if given
    ]
    if values.get("y_abs", False):
        raise ConfigError("y_abs: a sensor read as |y| is signed by one output's predictions, not supported with "
                          "several channels (set y_abs: false)")  # fmt: skip
    if unsupported:
        raise ConfigError(
            f"{', '.join(unsupported)}: a known linear part is a single-channel option (which of several inputs "
            "would known_b weigh?), not supported with several channels (the paper's examples set them: "
            "example:=0 for a model of your own plant)"
        )
    problem = unlearnt_mimo_scales(values)
    if problem:
        raise ConfigError(problem)
    n_u, n_y = len(u_names), len(y_names)
    separate = bool(values.get("separate", False))
    structure = MimoStructure(
        n_u=n_u,
        n_y=n_y,
        y_lags=int(values["y_lags"]),
        u_lags=int(values["u_lags"]),
        y_scale=_per_channel(values, "y_scale", n_y),
        y_offset=_per_channel(values, "y_offset", n_y),
        u_scale=_per_channel(values, "u_scale", n_u),
        u_offset=_per_channel(values, "u_offset", n_u),
        couplings=parse_couplings(str(values.get("couplings", "full")), n_u, n_y),
        separate=separate,
        y_pass_through=_pass_through(values, n_y),
    )
    selected = mimo_terms(values, structure) if network == "lenn" else [(None, None)] * n_y
    if separate and any(rows is not None for rows, _ in selected):
        raise ConfigError("terms select one combiner over all inputs: set separate: false")
    try:
        channels = [structure.channel(j) for j in range(n_y)]  # (each output's structure checks itself)
    except ValueError as error:
        why = " (separate: every output needs its own past and another channel in couplings)" if separate else ""
        raise ConfigError(f"{error}{why}") from None
    return build_mimo_identifier(
        structure,
        lambda n_inputs, output: _make_model(values, network, n_inputs, channels[output].branches(), *selected[output]),
        y_names,
    )


def mimo_channels(structure: MimoStructure, output: int) -> list[tuple[str, int]]:
    """Output ``output``'s network inputs as terms name them: its own lags (``y1_1``..), then each channel
    it sees (``u0_1``.., ``y0_1``..), in the regressor's order (``MimoStructure.channel``'s input channels)."""
    channel = structure.channel(output)
    lags = [count for count, _, _ in channel.input_channels()[1:]]  # (reading no other channel: one u of no lags)
    others = [(f"{kind}{index}", lags[c]) for c, (kind, index) in enumerate(structure.others(output))]
    return [(f"y{output}", channel.y_lags), *others]


def mimo_terms(values: dict[str, Any], structure: MimoStructure) -> list[tuple[list | None, list | None]]:
    """(exponents, factors) of each output's selected terms, or (None, None) each: the full expansion.

    With several outputs every entry of ``terms`` names its output first, ``y1: u0_2*y1_1``
    (as ``lenn-ros fit`` writes them); every output needs at least one term.
    """
    terms = [str(t) for t in values.get("terms", [""]) if str(t).strip()]
    if not terms:
        return [(None, None)] * structure.n_y
    outputs = [f"y{j}" for j in range(structure.n_y)]
    groups: dict[str, list[str]] = {name: [] for name in outputs}
    for text in terms:
        prefix, colon, term = text.partition(":")
        if not colon or prefix.strip() not in groups:
            raise ConfigError(
                f"terms entry {text!r}: with several outputs each term names its output first, e.g. "
                f"'y0: u1_2*y0_1' (outputs {', '.join(outputs)})"
            )
        groups[prefix.strip()].append(term.strip())
    empty = [name for name in outputs if not groups[name]]
    if empty:
        raise ConfigError(f"terms name no term for {', '.join(empty)}: give each output at least one ('y0: 1')")
    selected = []
    for j, name in enumerate(outputs):
        try:
            rows, factor_rows = parse_terms(groups[name], mimo_channels(structure, j))
        except ValueError as error:
            raise ConfigError(f"terms of {name}: {error}") from None
        selected.append((rows.tolist(), factor_rows.tolist() if factor_rows[:, 0].any() else None))
    return selected


def _coefficients(values: Any) -> tuple[float, ...]:
    coefficients = tuple(float(v) for v in values)
    return () if all(c == 0.0 for c in coefficients) else coefficients


# -- as the node builds it: a params file, a recording's configuration, weights_in, the session ----------


def identifier_from_params(path: str | None, node: str = "/identifier") -> tuple[Identifier | MimoIdentifier, dict]:
    """The identifier a params file describes for the node ``node`` (fully qualified, rcl's matching rules,
    as the node itself is given its parameters), and every node value (defaults filled in)."""
    values = read_params_file(path, node) if path else {}
    return build(values, f"params file {path}")


def build(given: dict[str, Any], source: str, adjust: Any = None) -> tuple[Identifier | MimoIdentifier, dict[str, Any]]:
    """The identifier and every node value (defaults filled in) that ``given`` parameter values describe, built as
    the node builds it (weights_in loaded, named after ``source`` when it is missing). ``adjust(values)`` may change
    the node values first (what is read: topics, fields, pairing), which can change the model's channels."""
    model, network = resolve(given)
    values = {**NODE_DEFAULTS, **given}
    if adjust is not None:
        values = adjust(values)
    # the fields say how many channels (MIMO): node-level values, which resolve() leaves out; what was given or
    # adjusted (the channels' names a bag labels) wins over the preset's defaults
    identifier = build_identifier({**model, **values}, network)
    return as_node_builds_it(identifier, values, source), values


def weights_path(value: str) -> Path:
    """``weights_in`` as the identifier node opens it: ``~`` expanded, a relative path from the cwd.

    The node cannot know which params file a value came from (ROS merges them), so it
    opens the path from its working directory; evaluate does the same, so one params
    file means the same model in both. ``lenn-ros fit -o DIR`` writes an absolute path.
    """
    return Path(os.path.expanduser(value))


def as_node_builds_it(
    identifier: Identifier | MimoIdentifier, values: dict[str, Any], source: str
) -> Identifier | MimoIdentifier:
    """What the node adds to the bare identifier: the divergence guard and the weights learning starts from."""
    identifier.health_interval = int(values["health_interval"])
    identifier.divergence_ratio = float(values["divergence_ratio"])
    identifier.resume_after = int(values["resume_after"])
    identifier.free_run_guard = bool(values["free_run_guard"])
    if values.get("weights_in"):
        path = weights_path(values["weights_in"])
        if not path.is_file():
            raise RecordingError(
                f"weights_in {path} (from the {source}) does not exist (a relative path is taken from the current "
                f"directory {Path.cwd()}, as the identifier node does): run from there, give an absolute path, "
                "or set weights_in to '' for fresh weights"
            )
        identifier.load_state(path)
        identifier.mark_healthy()
    return identifier


def recorded_values(path: str | Path) -> dict[str, Any] | None:
    """The parameter values the identifier recorded in the bag (``identifier_config``: its starting values, with
    ``network`` and the topics its inputs resolved to); None where it recorded none."""
    recorded = list(iter_messages(path, [topics.IDENTIFIER_CONFIG]))
    if not recorded:
        return None
    values = json.loads(recorded[-1].message.data)
    values.pop(topics.PARAMETER_CHANGES, None)  # (recorded_changes reads them: the values are the starting ones)
    values.setdefault("resume_after", 0)  # recorded before learning resumed by itself: it never did live
    return values


def configuration(
    path: str | Path,
    params: str | None,
    node: str = "/identifier",
    model: bool = True,
    adjust: Any = None,
    defaults: bool = False,
) -> tuple[Identifier | MimoIdentifier, dict[str, Any]]:
    """The identifier and node values a recording is read with: the params file given (``node``'s sections of
    it, by rcl's rules), else its identifier_config, else (``defaults``) the node's defaults. ``model=False``: only
    how the topics become samples, with the node's default model of as many channels, no weights (what pairing a
    record needs: fit builds its own model, and the weights file may have stayed on the robot). ``adjust``: see
    :func:`build` (the flags)."""
    if params:
        given, source = read_params_file(params, node), f"params file {params}"
    else:
        given, source = recorded_values(path), f"identifier configuration recorded in {path}"
        if given is None and not defaults:
            raise RecordingError(
                f"{path}: the bag holds no identifier configuration (identifier_config); pass --params FILE, the "
                "params file the identifier ran with (e.g. config/example1_lenn.yaml, or fit -o's params.yaml)"
            )
        if given is None:
            given, source = {}, "node's defaults"
    given = dict(given)
    if not model:
        kept = {*NODE_DEFAULTS, *READING, topics.RESOLVED_TOPICS}  # (the channels' names are the model table's)
        given = {key: value for key, value in given.items() if key in kept}
        given["weights_in"] = ""
    resolved_topics = given.pop(topics.RESOLVED_TOPICS, {})

    def reading(values: dict[str, Any]) -> dict[str, Any]:
        values = {**values, topics.RESOLVED_TOPICS: resolved_topics}
        values.pop("network", None)
        return adjust(values) if adjust is not None else values

    return build(given, source, reading)


def recorded_changes(path: str | Path) -> list[ParameterChange]:
    """The live parameter changes the identifier recorded (``identifier_config``'s change log), in order.

    Each republished config carries the whole log: the last one read has them all (a
    recorder that joined late still got it, the topic being latched).
    """
    recorded = iter_messages(path, [topics.IDENTIFIER_CONFIG])
    logs = [json.loads(message.message.data).get(topics.PARAMETER_CHANGES) for message in recorded]
    logs = [log for log in logs if log]
    return [ParameterChange.from_dict(entry) for entry in logs[-1]] if logs else []


def make_session(identifier: Identifier | MimoIdentifier, values: dict[str, Any]) -> Session:
    """The node's session over a recording: its pairing, learning on (the phases are the recording's)."""
    return Session(identifier, SessionConfig.from_values(values, follow_test_start=False, learning=True))


def loaded_text(identifier: Any, path: str, network: str, values: dict[str, Any]) -> str:
    """One line at start for ``weights_in``: learning resumes from a file, not from fresh weights, and the user must
    be able to see which file and which network (a stale path is otherwise silent)."""
    from lenn_ros.session.values import values_for

    models = identifier.models
    model = models[0]
    structural = {k: v for k, v in model.get_params().items() if k in model._structural_params and v is not None}
    structure = identifier.structure
    lags = f"y_lags {structure.y_lags}, u_lags {structure.u_lags}, " if hasattr(structure, "y_lags") else ""
    outputs = f" for {len(models)} outputs" if len(models) > 1 else ""
    seen = sum(int(getattr(each, "n_samples_seen_", 0)) for each in models)
    # one output's scales left to be learnt: the file's (the run that saved it learnt them)
    from_file = not values_for(identifier).vector and not (float(values["y_scale"]) and float(values["u_scale"]))
    scales = (
        "; scales from the file (the run that saved it learnt them): "
        + ", ".join(f"{key} {getattr(structure, key):.6g}" for key in identifier.SCALING)
        if from_file
        else ""
    )
    return (
        f"weights_in: loaded {sum(each.n_weights for each in models)} weights{outputs} from {path} "
        f"(learnt from {seen} samples): {network}, {lags}"
        + ", ".join(f"{key} {value}" for key, value in structural.items())
        + scales
    )


def compile_ahead(identifier: Any) -> None:
    """Step a throwaway copy of the model through its warm-up, before any input arrives.

    On a machine whose numba cache is cold the first live sample would otherwise wait seconds
    for the compiled step (4 s for an output of several inputs'), while a BEST_EFFORT queue
    overflows; with the cache warm this takes milliseconds.
    """
    import copy

    from lenn_ros.session.values import values_for

    scratch = copy.deepcopy(identifier)
    u, y = values_for(scratch).zeros(scratch)
    window = max(output.structure.warm_up for output in scratch.outputs)
    for k in range(window + 2):
        scratch.step(k + 1, u, y, True)
