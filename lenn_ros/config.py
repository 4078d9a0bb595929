"""Identifier configuration: one table of parameters for the node, the CLI and files.

The identifier node declares exactly these parameters (with their descriptions and
ranges), ``lenn-ros evaluate --params FILE`` reads the same ``ros__parameters``
YAML (matched to the node by :mod:`lenn_ros.service.params`), and both build the model
from the values checked here through :func:`lenn_ros.service.building.build_identifier`:
the offline evaluation of a recording runs the very configuration the live node ran.
This module is the table only (names, defaults, ranges, the checks of one value, which
channels the values name), below the service layer that builds from it.

Defaults are for "my own plant" (``example: 0``, the default): a LeNN on u(k), u(k-1),
y(k), y(k-1) learnt by RLS with a memory of minutes, its scales and offsets learnt from
the first seconds of data (:mod:`lenn_ros.core.warmup`). A paper example (``example``
1-4) is a preset asked for by name: its known linear part, order and scale factors, read
as plain data from :mod:`lenn_ros.presets` (not from the paper harness, which simulates).
"""

from __future__ import annotations

import difflib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from lenn_ros.core.change import DEFAULT_THRESHOLD
from lenn_ros.core.fields import FieldError, channel_names, compile_path, compile_vector, is_vector
from lenn_ros.core.networks import OUTPUTS, SOLVERS
from lenn_ros.core.structure import ModelStructure
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
    Parameter(
        "free_run_guard",
        False,
        "the network learns on, but the model that is served (frozen phases, free runs, saved weights) takes "
        "its weights of a block's end only once they simulate the 10 blocks of health_interval samples after "
        "it better, and no stretch of them more than 10 % worse: learning on from a model fitted for its free "
        "run (lenn-ros fit -o turns it on) does not trade the free run for the one-step error "
        "(core.free_run_guard)",
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
        "watch for a plant change: a frozen reference of the served model simulates each block of samples; "
        "/diagnostics WARN 'plant changed' when its free-run errors rise above their learnt level where it knows "
        "the motion (every output; armed only by a reference that simulates; core.change)",
        live=True,
    ),
    Parameter(
        "change_threshold",
        DEFAULT_THRESHOLD,
        "change alarm: CUSUM threshold on the blocks' standardised log free-run errors (higher: fewer false "
        "alarms, later detection; bench/change_alarm.py sweeps it)",
        0.1,
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
