"""Parameters to an identifier, as the node builds one: from a params file, from the configuration a
recording holds, with the weights learning starts from (``weights_in``).

One place for it: the node, ``evaluate``, ``fit`` (a bag's samples), ``replay`` and ``load_model`` all
build here, so a params file means the same model everywhere. The node's values come from
:mod:`lenn_ros.config` (the one table of parameters); a params file is matched to a node by rcl's
own rules (:func:`lenn_ros.config.read_params_file`); ``weights_in`` is opened as the node opens it
(``~`` expanded, a relative path from the current directory).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from lenn_ros import topics
from lenn_ros.bag.reader import iter_messages
from lenn_ros.config import NODE_PARAMETERS, build_identifier, read_params_file, resolve
from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.structure import Identifier
from lenn_ros.service import RecordingError
from lenn_ros.service.reading import READING
from lenn_ros.session import ParameterChange, Session, SessionConfig

#: Every node parameter's default: what a value a params file or a recording leaves out means.
NODE_DEFAULTS = {parameter.name: parameter.default for parameter in NODE_PARAMETERS}


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
