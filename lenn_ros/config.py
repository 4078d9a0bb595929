"""Identifier configuration: one table of parameters for the node, the CLI and files.

The identifier node declares exactly these parameters (with their descriptions and
ranges), ``lenn-ros evaluate --params FILE`` reads the same ``ros__parameters``
YAML, and both build the model through :func:`build_identifier`: the offline
evaluation of a recording runs the very configuration the live node ran.

Defaults are for "my own plant" (``example: 0``, the default): a LeNN on u(k), u(k-1),
y(k), y(k-1) learnt by RLS with a memory of minutes, its scales and offsets learnt from
the first seconds of data (:mod:`lenn_ros.core.warmup`). A paper example (``example``
1-4) is a preset asked for by name: its known linear part, order and scale factors, read
as plain data from :mod:`lenn_ros.presets` (not from the paper harness, which simulates).
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from lenn_ros.core.change import DEFAULT_THRESHOLD
from lenn_ros.core.expansions import parse_terms, siso_channels
from lenn_ros.core.fields import FieldError, channel_names, compile_path, compile_vector, is_vector
from lenn_ros.core.mimo import MimoIdentifier, MimoStructure, build_mimo_identifier, parse_couplings
from lenn_ros.core.networks import OUTPUTS, SOLVERS
from lenn_ros.core.structure import Identifier, ModelStructure
from lenn_ros.presets import PARAMETER_SETS, example_preset, network_settings


class ConfigError(ValueError):
    """A params file or parameter value the user must fix (the command line prints it as one line)."""


@dataclass(frozen=True)
class Parameter:
    """One ROS parameter: name, default, why it exists, allowed range."""

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    live: bool = False  # may change while the node runs (others are read-only)


#: The identifier node's own parameters (topics, pairing, files, limits, reporting):
#: not the model's business, but known names, so a typo in a params file is caught.
NODE_PARAMETERS = [
    Parameter("learning", True, "learn from each sample (false: frozen weights, the paper's test)", live=True),
    Parameter("follow_test_start", True, "freeze learning from the index on the test_start topic", live=True),
    Parameter("weights_in", "", "weights file (.npz) to start from ('' = fresh weights)"),
    Parameter("weights_out", "", "weights file written on shutdown and every autosave_period s ('' = none)", live=True),
    Parameter(
        "autosave_period", 0.0, "seconds between atomic weight saves (0 = only on shutdown)", 0.0, 86400.0, live=True
    ),
    Parameter("u_limit", 1.0e3, "|u| above this is an absurd value", 0.0, 1e300, live=True),
    Parameter("y_limit", 1.0e3, "|y_p| above this is an absurd value", 0.0, 1e300, live=True),
    Parameter("out_of_range", "reject", "what to do with an absurd value", choices=("reject", "clip"), live=True),
    Parameter(
        "wait_for_y_hat_subscribers",
        0,
        "hold the first pairs until y_hat has this many matched "
        "subscribers (e.g. 2: a recorder and a lockstep simulator), so none misses sample 1",
        0,
        100,
    ),
    Parameter("wait_for_error_subscribers", 0, "the same for error (e.g. 1: a recorder)", 0, 100),
    Parameter("wait_for_samples_subscribers", 0, "the same for samples (e.g. 1: a recorder)", 0, 100),
    Parameter("report_every", 100, "publish the running NMSE every N errors", 1, 10**9, live=True),
    Parameter("status_period", 1.0, "seconds between status messages", 0.05, 3600.0),
    Parameter("health_interval", 1000, "samples per divergence check", 10, 10**7),
    Parameter(
        "divergence_ratio",
        100.0,
        "roll back if block MSE > ratio x var(target) (the larger of the block's and the one learnt while it moved)",
        1.0,
        1e12,
        live=True,
    ),
    Parameter(
        "resume_after",
        10,
        "after a divergence, learning resumes by itself from the healthy state after this many health_interval "
        "blocks of samples, doubled for each divergence that follows (0 = stay off until learning:=true)",
        0,
        10**6,
        live=True,
    ),
    # -- where u and y_p come from (issue 9: a real robot's topics) --
    Parameter("u_type", "std_msgs/msg/Float64", "message type on u (e.g. std_msgs/msg/Float64MultiArray)"),
    Parameter("y_type", "std_msgs/msg/Float64", "message type on y_p (e.g. sensor_msgs/msg/JointState)"),
    Parameter(
        "u_topics",
        [""],
        "MIMO: several topics carrying u's channels (each with u_type, u_field), merged per sample as pairing "
        "says ([''] = the one topic u)",
    ),
    Parameter("y_topics", [""], "MIMO: several topics carrying y_p's channels ([''] = the one topic y_p)"),
    Parameter("u_field", "data", "path to the scalar in a u message, as ros2 topic echo --field writes it: data[0]"),
    Parameter("y_field", "data", "path to the scalar in a y_p message: position[2], position[elbow], twist.linear.x"),
    Parameter(
        "pairing",
        "sequence",
        "how u and y_p become samples: sequence (one lockstep publisher of both), stamp (header stamps "
        "within slop), sample (fixed sample_period, zero-order hold)",
        choices=("sequence", "stamp", "sample"),
    ),
    Parameter("slop", 0.0, "stamp pairing: largest |t_u - t_y| of a pair, seconds (0 = exact)", 0.0, 3600.0),
    Parameter("sample_period", 0.0, "sample pairing: seconds between samples (1 / rate)", 0.0, 3600.0),
    Parameter(
        "max_delay", 0.0, "stamp/sample: seconds to wait for a late message (0 = 2 periods, >= 0.05 s)", 0.0, 3600.0
    ),
    Parameter("y_max_age", 0.0, "sample: reuse a y_p this old when no new one came (0 = never: a gap)", 0.0, 3600.0),
    Parameter(
        "max_skew",
        0.25,
        "sequence: refuse a pair whose halves were published further apart, unless both came after the pair before (s)",
        0.0,
        3600.0,
    ),
    Parameter(
        "max_clock_offset",
        0.0,
        "stamp/sample: say so when the inputs' clocks differ by more, seconds (0 = max(T/2, 50 ms))",
        0.0,
        3600.0,
    ),
    Parameter("use_header_stamp", True, "time a message by its header stamp when it has one (else receive time)"),
    Parameter("lone_timeout", 3.0, "warn when one input arrives alone this many seconds", 0.1, 3600.0),
    Parameter(
        "silence_timeout",
        30.0,
        "warn once when neither input arrived for this many seconds after data flowed (0 = never)",
        0.0,
        86400.0,
        live=True,
    ),
    Parameter(
        "input_timeout",
        5.0,
        "an input topic whose rate is known (>= 5 Hz) and whose publisher is still matched delivers nothing for "
        "this many seconds (at least 20 of its periods): said with the publisher, counted (input_stalls), WARN on "
        "/diagnostics, and the input resubscribed; again after twice as long (0 = no watchdog; core.watchdog)",
        0.0,
        3600.0,
    ),
    Parameter(
        "max_lag",
        0.5,
        "stamp/sample overload: a message that waited longer than this many seconds in its queue is shed "
        "unprocessed (counted shed), so the node keeps up with the newest (0 = never shed; sequence never sheds)",
        0.0,
        3600.0,
        live=True,
    ),
    Parameter(
        "scale_warm_up",
        10.0,
        "y_scale/u_scale 0: seconds of samples (by sample_period, else at 50 Hz) held to learn the scales and "
        "offsets from, then learnt from (the signals must move in them)",
        0.0,
        200.0,
    ),
    Parameter("warn_period", 5.0, "seconds between repeats of one kind of warning", 0.0, 3600.0, live=True),
    Parameter(
        "change_alarm",
        True,
        "watch the one-step errors for a plant change: /diagnostics WARN 'plant changed' while the residual level "
        "stays above the one the model had learnt (single output; core.change)",
        live=True,
    ),
    Parameter(
        "change_threshold",
        DEFAULT_THRESHOLD,
        "change alarm: CUSUM threshold on e^2 / its learnt level (higher: fewer false alarms, later detection; "
        "bench/change_alarm.py measures both)",
        1.0,
        1e6,
        live=True,
    ),
]


def identifier_parameters(example: int, network: str, parameters: str = "calibrated") -> list[Parameter]:
    """The identifier's parameters with defaults from the example preset."""
    if example:
        preset = example_preset(example)
        structure = ModelStructure(**preset["structure"])
        net = network_settings(preset, network, parameters)
    else:
        # my own plant: scales 0 = learnt from the warm-up; RLS (LeNN) with forgetting 0 = a memory of
        # RLS_MEMORY_S seconds; two lags each (a joint is second order: angle and velocity)
        structure = ModelStructure(y_lags=2, u_lags=2, y_scale=UNSET_SCALE, u_scale=UNSET_SCALE)
        net = {"order": 4, "hidden": [20, 10], "output": "tanh", "alpha": 0.01, "beta": 0.5}
        if network == "lenn":
            net.update(output="linear", solver="rls", forgetting=AUTO_FORGETTING)
    return [
        Parameter("y_lags", structure.y_lags, "past plant outputs y(k..k-n+1) fed to the network", 0, 200),
        Parameter("u_lags", structure.u_lags, "past inputs u(k..k-m+1) fed to the network", 0, 200),
        Parameter("known_a", list(structure.known_a) or [0.0], "known linear part on y(k), y(k-1).. ([0.0]: none)"),
        Parameter("known_b", list(structure.known_b) or [0.0], "known linear part on u(k), u(k-1).. ([0.0]: none)"),
        Parameter(
            "y_scale",
            structure.y_scale,
            "scale factor SF: the network sees y / SF, which must be in [-1, 1] (0 = learnt with y_offset from "
            "the first scale_warm_up seconds of data)",
            0.0,
            1e6,
        ),
        Parameter(
            "u_scale",
            structure.u_scale,
            "the network sees u / u_scale, which must be in [-1, 1] (0 = learnt with u_offset from the warm-up)",
            0.0,
            1e6,
        ),
        Parameter(
            "y_offset", structure.y_offset, "centre of y: the network sees (y - y_offset) / y_scale", -1e12, 1e12
        ),
        Parameter(
            "u_offset", structure.u_offset, "centre of u: the network sees (u - u_offset) / u_scale", -1e12, 1e12
        ),
        Parameter(
            "output_offset",
            structure.output_offset,
            "known constant in y^: the network learns y - output_offset (fit sets it for the MLP)",
            -1e12,
            1e12,
        ),
        Parameter(
            "y_abs",
            structure.y_abs,
            "the sensor reads |y| (a pulse counter on a speed that changes sign): the model is of the signed "
            "output, each y_p takes the sign the model gives it (its free run, its prediction near zero; not "
            "learnt while unsure), y^ is published as |y^| (fit sets it; one output)",
        ),
        Parameter("separate", structure.separate, "Model 3 structure: N1[y] + N2[u] instead of one network"),
        Parameter(
            "order", int(net.get("order", 4)), "LeNN: polynomial degree per input (paper's terms / inputs)", 1, 30
        ),
        Parameter(
            "basis", net.get("basis", "legendre"), "LeNN expansion", choices=("legendre", "chebyshev", "trigonometric")
        ),
        Parameter(
            "cross_degree",
            int(net.get("cross_degree", 0)),
            "LeNN: tensor-product terms up to this total degree (0: the paper's per-input expansion)",
            0,
            6,
        ),
        Parameter(
            "terms",
            [""],
            "LeNN: selected terms instead of the full expansion ([''] = full), as lenn-ros fit writes them: "
            "'1' bias, 'y1^3' = degree-3 basis polynomial of scaled y(k-1), 'y1*u2' = P1(y(k-1)) P1(u(k-2)); "
            "with several channels each names its output first and the channel's lag after '_': "
            "'y1: u0_2*y1_1' = a term of output y1, P1(u0(k-2)) P1(y1(k-1))",
        ),
        Parameter("hidden", [int(h) for h in net.get("hidden", [20, 10])], "MLP hidden layer sizes"),
        Parameter("output", net.get("output", "tanh"), "output node", choices=OUTPUTS),
        Parameter("output_scale", float(net.get("output_scale", 1.0)), "tanh output multiplied by this", 1e-6, 1e6),
        Parameter(
            "solver", net.get("solver", "sgd"), "LeNN learning rule (nlms/rls need output: linear)", choices=SOLVERS
        ),
        Parameter("alpha", float(net["alpha"]), "learning rate (eqs. 6-10)", 0.0, 10.0, live=True),
        Parameter("beta", float(net["beta"]), "momentum factor", 0.0, 0.999, live=True),
        Parameter(
            "forgetting",
            float(net.get("forgetting", 1.0)),
            f"RLS forgetting factor lambda in [0.5, 1] (0 = a memory of {RLS_MEMORY_S:g} s: "
            f"1 - sample_period / {RLS_MEMORY_S:g}, or 1 - 1 / {RLS_MEMORY_SAMPLES} without sample_period)",
            0.0,
            1.0,
            live=True,
        ),
        Parameter("nlms_step", float(net.get("nlms_step", 0.5)), "NLMS step size mu", 1e-6, 1.999, live=True),
        Parameter("seed", 0, "seed of the initial weights", 0, 2**31 - 1),
        *MIMO_PARAMETERS,
    ]


#: ``y_scale`` / ``u_scale`` left at this: learnt (with the offset) from the first data (core.warmup)
UNSET_SCALE = 0.0
#: ``forgetting`` left at this: lambda from a memory of RLS_MEMORY_S seconds (see :func:`rls_forgetting`)
AUTO_FORGETTING = 0.0
#: RLS memory on robot topics: long enough to average over many motions (a joint's swing is ~1 s),
#: short enough to follow a load or a temperature drift within minutes
RLS_MEMORY_S = 120.0
#: ... in samples, where no sample_period says how long a sample is (sequence/stamp pairing)
RLS_MEMORY_SAMPLES = 12_000


def rls_forgetting(values: dict[str, Any]) -> float:
    """The RLS lambda ``values`` ask for: ``forgetting``, or (0, the robot default) 1 - 1/memory.

    A memory of N samples (1 / (1 - lambda)) is RLS_MEMORY_S of sample time at
    ``sample_period``, else RLS_MEMORY_SAMPLES. Forgetting at rest (no excitation) would
    let the covariance wind up; the RLS rule bounds trace(P) at its prior's (networks.py).
    """
    forgetting = float(values.get("forgetting", 1.0))
    if forgetting != AUTO_FORGETTING:
        if forgetting < 0.5:
            raise ConfigError(f"forgetting must be 0 (auto: a memory of {RLS_MEMORY_S:g} s) or in [0.5, 1]")
        return forgetting
    period = float(values.get("sample_period", 0.0) or 0.0)
    memory = RLS_MEMORY_S / period if period > 0 else RLS_MEMORY_SAMPLES
    return 1.0 - 1.0 / max(memory, 2.0)


#: Several channels (u_field / y_field naming several: a list, or ``name[*]``): README "MIMO"
MIMO_PARAMETERS = [
    Parameter(
        "couplings",
        "full",
        "MIMO: channels that feed each output's network: full, diagonal (output j: y_j and u_j only), "
        "or per output ';'-separated, e.g. 'y0 u0 u1; y1 y0 u1'",
    ),
    Parameter("u_names", [""], "MIMO: names of the input channels (needed with u_field name[*]; [''] = from fields)"),
    Parameter("y_names", [""], "MIMO: names of the output channels (needed with y_field name[*])"),
    Parameter("u_scales", [0.0], "MIMO: u_scale per input channel (one value: u_scale for every channel)"),
    Parameter("u_offsets", [0.0], "MIMO: u_offset per input channel (one value: u_offset for every channel)"),
    Parameter("y_scales", [0.0], "MIMO: y_scale per output channel (one value: y_scale for every channel)"),
    Parameter("y_offsets", [0.0], "MIMO: y_offset per output channel (one value: y_offset for every channel)"),
    Parameter(
        "y_pass_through",
        [False],
        "MIMO: per output, y(k) passed through (y(k+1) = y(k) + the network): an integrating output "
        "(a wheel) that fit found ([false] = none)",
    ),
]


def build_identifier(values: dict[str, Any], network: str) -> Identifier | MimoIdentifier:
    """An :class:`Identifier` from parameter values (node, params file or CLI).

    The values are the user's, so what the model's own checks refuse (a term list that
    does not parse, a solver that needs a linear output) is a :class:`ConfigError`.
    """
    try:
        return _build_identifier(values, network)
    except ConfigError:
        raise
    except ValueError as error:
        raise ConfigError(str(error)) from error


def is_mimo(values: dict[str, Any]) -> bool:
    """Whether the values name several u or y_p channels (then the model is a MimoIdentifier)."""
    several = any(len(_side_topics(values, side)) > 1 for side in ("u", "y"))
    return several or is_vector(str(values.get("u_field", "data"))) or is_vector(str(values.get("y_field", "data")))


def _side_topics(values: dict[str, Any], side: str) -> list[str]:
    return [str(topic).strip() for topic in values.get(f"{side}_topics", [""]) if str(topic).strip()]


def input_topics(values: dict[str, Any]) -> list[tuple[str, int, str]]:
    """(side ``u``/``y``, part, topic) of every input the node subscribes: ``u`` and ``y_p``, or a side's topics."""
    inputs = []
    for side, default in (("u", "u"), ("y", "y_p")):
        listed = _side_topics(values, side)
        inputs += [(side, part, name) for part, name in enumerate(listed if len(listed) > 1 else [default])]
    return inputs


def side_channels(values: dict[str, Any], side: str) -> tuple[list[str], tuple[int, ...], tuple[str, ...]]:
    """A side's (``u`` or ``y``) channel names, channels per topic and topic names (both empty: one topic).

    Several topics share the side's type and field; each contributes the channels its
    field names, named by the topic (one channel each) or ``topic.channel``, unless
    ``u_names`` / ``y_names`` name them all. Raises FieldError with the reason.
    """
    field = str(values[f"{side}_field"])
    names = [str(name) for name in values.get(f"{side}_names", [""]) if str(name)]
    listed = _side_topics(values, side)
    if len(listed) <= 1:
        return channel_names(field, names), (), ()
    if "[*]" in field:
        raise FieldError(f"{side}_field {field!r} with several {side}_topics: list the fields instead of [*]")
    per_topic = channel_names(field)
    default = [topic if len(per_topic) == 1 else f"{topic}.{name}" for topic in listed for name in per_topic]
    if names and len(names) != len(default):
        raise FieldError(f"{side}_names has {len(names)} names for {len(default)} channels of {', '.join(listed)}")
    return names or default, (len(per_topic),) * len(listed), tuple(listed)


def field_extractor(values: dict[str, Any], side: str) -> Callable[[Any], Any]:
    """message -> what the node takes from a ``side`` (``u``/``y``) message: one number, or (MIMO) the vector
    of channels its field names; with several topics on the side, that topic's channels only."""
    field = str(values[f"{side}_field"])
    if not is_mimo(values):
        return compile_path(field)
    names, parts, _ = side_channels(values, side)
    return compile_vector(field) if parts else compile_vector(field, names)


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
        from lenn_ros.core.networks import MLP

        model = MLP(hidden=[int(h) for h in values["hidden"]], **common)
    elif network == "lenn":
        from lenn_ros.core.networks import FunctionalLinkNetwork

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
    import os

    from lenn_ros.core.networks import ModelFileError, read_weights_file

    path = os.path.abspath(os.path.expanduser(weights_in))
    try:
        header, _ = read_weights_file(path)
    except (ModelFileError, OSError, ValueError):
        return structure  # a missing or broken file: the load (node, evaluate) says so in its own line
    scaling = header.get("scaling") if isinstance(header, dict) else None
    if isinstance(scaling, dict) and all(isinstance(scaling.get(k), int | float) for k in SCALING_KEYS):
        return dataclasses.replace(structure, **{k: float(scaling[k]) for k in SCALING_KEYS})
    raise ConfigError(
        "weights_in with y_scale/u_scale 0 (learnt from the warm-up), and the file holds no scales: weights mean "
        "something only on the scaling they were learnt with; give y_scale, u_scale, y_offset, u_offset (the run "
        "that saved them said its learnt ones in the line 'scales learnt from ...' and in status scaling; "
        "lenn-ros fit writes them; a run of this version saves them with weights_out)"
    )


#: what a saved model records of its inputs' scaling (``OnlineRegressor.save(scaling=...)``)
SCALING_KEYS = ("y_scale", "u_scale", "y_offset", "u_offset")


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


def read_params_file(path: str | Path, node: str = "/identifier") -> dict[str, Any]:
    """The ``ros__parameters`` a ROS 2 params file gives the node ``node``, by rcl's rules.

    ``node`` is the fully qualified name (``/robot1/identifier``; a bare name is in the
    root namespace). See :func:`read_params_files`: one file is the case of one.
    """
    return read_params_files([path], node)


def read_params_files(paths: list[str | Path] | tuple[str | Path, ...], node: str = "/identifier") -> dict[str, Any]:
    """The parameters rcl gives ``node`` from these files (``--params-file`` after ``--params-file``).

    rcl's rules, as rclpy applies them (checked against rclpy in test_params_keys.py):
    every section whose key matches the node (:func:`node_key_matches`: ``/**``,
    ``/**/identifier``, ``/robot1/*``, ``identifier`` = the root namespace's) applies, in
    the order the keys first appear over the files, a later one overriding an earlier one
    name by name; a key repeated (in the file or a later file) is merged into its first
    place. No "most specific wins": ``/**/identifier`` above ``/**`` is overridden by it.
    ``/robot1/identifier`` and ``/robot2/identifier`` are two nodes, never merged.
    """
    name = "/" + str(node).strip().lstrip("/")
    sections: dict[str, dict[str, Any]] = {}  # key as written -> its parameters, in first-appearance order
    for path in paths:
        for key, parameters in _params_sections(Path(path)).items():
            sections.setdefault(key, {}).update(parameters)
    matched = [key for key in sections if node_key_matches(key, name)]
    if not matched:
        shown = ", ".join(sections) or "none"
        files = ", ".join(str(path) for path in paths)
        raise ConfigError(
            f"params file {files} has no section for the node {name} (its keys: {shown}): name a section '/**:' "
            f"(any node), '/**/{name.rsplit('/', 1)[-1]}:' or '{name}:', each with 'ros__parameters:'"
        )
    merged: dict[str, Any] = {}
    for key in matched:
        merged.update(sections[key])
    return merged


def _params_sections(path: Path) -> dict[str, dict[str, Any]]:
    """A params file's sections: key -> its flattened ``ros__parameters`` (a file ROS would refuse is an error)."""
    try:
        document = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"params file {path} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"params file {path} is a directory; pass the .yaml file in it") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"params file {path} is not valid YAML: {str(error).splitlines()[0]}") from None
    if not isinstance(document, dict):
        raise ConfigError(f"params file {path} must map node names to {{ros__parameters: ...}}")
    sections = {}
    for key, section in document.items():
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            sections[str(key).strip()] = _flatten(section["ros__parameters"])
    return sections


def node_key_matches(key: str, fully_qualified_name: str) -> bool:
    """Whether a params-file key addresses a node, by rcl's rules: the one matcher of the package.

    ``*`` stands for one name token, ``**`` for any number of them (none included); a
    key without a leading ``/`` is taken from the root namespace.
    """
    pattern = [token for token in str(key).strip().split("/") if token]
    name = [token for token in fully_qualified_name.split("/") if token]

    def match(p: int, n: int) -> bool:
        if p == len(pattern):
            return n == len(name)
        if pattern[p] == "**":
            return any(match(p + 1, rest) for rest in range(n, len(name) + 1))
        return n < len(name) and pattern[p] in ("*", name[n]) and match(p + 1, n + 1)

    return match(0, 0)


def params_files(argv: list[str]) -> list[str]:
    """The ``--params-file`` paths in a command line, in order."""
    return [argv[i + 1] for i, argument in enumerate(argv[:-1]) if argument == "--params-file"]


def unmatched_params_files(argv: list[str], fully_qualified_name: str) -> list[tuple[str, list[str]]]:
    """The ``--params-file`` files in ``argv`` with no section for this node, and their keys.

    rclpy applies such a file to no node and says nothing: the node would run on its
    defaults while the user believes their file is in force.
    """
    unmatched = []
    for path in params_files(argv):
        try:
            keys = list(_params_sections(Path(path)))
        except ConfigError:
            continue  # rclpy itself refuses a file it cannot read, with its own message
        if not any(node_key_matches(key, fully_qualified_name) for key in keys):
            unmatched.append((path, keys))
    return unmatched


def _flatten(parameters: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested YAML maps are dotted names in ROS 2 (``qos_overrides: {/u: ...}``)."""
    flat: dict[str, Any] = {}
    for name, value in parameters.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{name}."))
        else:
            flat[f"{prefix}{name}"] = value
    return flat


#: names ROS 2 itself gives every node, and prefixes of its per-topic settings
FOREIGN_PARAMETERS = ("use_sim_time", "start_type_description_service", "qos_overrides.")
PRESET_PARAMETERS = ("example", "network", "parameters")


def check_known(names: Any, known: Any, where: str = "params file") -> None:
    """Stop at the first unknown parameter name, naming the closest known one."""
    known = sorted(set(known) | set(PRESET_PARAMETERS))
    for name in names:
        if name in known or str(name).startswith(FOREIGN_PARAMETERS):
            continue
        close = difflib.get_close_matches(str(name), known, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else f"; known: {', '.join(known)}"
        raise ConfigError(f"unknown parameter {name!r} in the {where}{hint}")


def resolve(values: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """Complete user-given values with the example preset's defaults; check them.

    Returns (all values, network). Unknown names and out-of-range values are errors
    that name the parameter, so a typo in a params file is not silently ignored.
    """
    example = int(values.get("example", 0))
    network = str(values.get("network", "lenn"))
    parameter_set = str(values.get("parameters", "calibrated"))
    if network not in ("lenn", "mlp"):
        raise ConfigError(f"network must be 'lenn' or 'mlp', not {network!r}")
    if parameter_set not in PARAMETER_SETS:
        raise ConfigError(f"parameters must be one of {PARAMETER_SETS}, not {parameter_set!r}")
    if example:
        example_preset(example)
    table = {p.name: p for p in identifier_parameters(example, network, parameter_set)}
    check_known(values, set(table) | {p.name for p in NODE_PARAMETERS})
    result = {name: p.default for name, p in table.items()}
    for name, value in values.items():
        if name in ("example", "network", "parameters"):
            continue
        if name not in table:
            continue  # node-level parameters (topics, files...) are not the model's business
        problem = check_value(table[name], value)
        if problem:
            raise ConfigError(problem)
        result[name] = value
    return result, network


def check_value(parameter: Parameter, value: Any) -> str | None:
    """Why ``value`` is not acceptable for ``parameter`` (None if it is)."""
    if parameter.choices and value not in parameter.choices:
        return f"{parameter.name} must be one of {', '.join(parameter.choices)}, not {value!r}"
    if isinstance(parameter.default, bool):
        return None if isinstance(value, bool) else f"{parameter.name} must be true or false, not {value!r}"
    if isinstance(parameter.default, int | float) and not isinstance(value, int | float):
        return f"{parameter.name} must be a number, not {value!r}"
    if isinstance(value, int | float) and not isinstance(value, bool):
        if parameter.low is not None and value < parameter.low:
            return f"{parameter.name} must be >= {parameter.low}, got {value}"
        if parameter.high is not None and value > parameter.high:
            return f"{parameter.name} must be <= {parameter.high}, got {value}"
        if value != value:  # NaN
            return f"{parameter.name} must be a number, not NaN"
        if parameter.name == "forgetting" and 0.0 < value < 0.5:
            return f"forgetting must be 0 (auto: a memory of {RLS_MEMORY_S:g} s) or in [0.5, 1], got {value}"
    return None
