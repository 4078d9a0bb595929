"""The paper's four examples as presets: plain numbers, in one place.

``example: 1``-``4`` asks the identifier for a preset by name (:mod:`lenn_ros.config` reads
its defaults from here), and the paper harness builds its
:class:`~lenn_ros.paper.examples.PaperExample` from the same entries: one source of the
numbers, so a node started on a preset runs the model ``reproduce`` measures.

Plain data on purpose: the table of parameters (and with it every node and command) needs
these numbers, not the simulators, networks and complexity counts of :mod:`lenn_ros.paper`;
this module imports nothing of the package (``test/test_layout.py`` checks it).

Where the paper is silent the choice made here is named in a comment and in the README
("Choices where the paper is ambiguous").
"""

from __future__ import annotations

from typing import Any

#: Section IV's protocol: training samples (``reproduce --iterations``) and test samples per run
TRAIN_SAMPLES = 50_000
TEST_SAMPLES = 600
#: which alpha/beta a preset runs with: bench/calibrate.py's for this implementation, or the paper's
PARAMETER_SETS = ("calibrated", "paper")
NETWORKS = ("lenn", "mlp")

#: Each example: its noise, its model structure (:class:`~lenn_ros.core.structure.ModelStructure`'s
#: arguments), each network's settings with the paper's alpha/beta, the NMSE the paper reports and the
#: alpha/beta bench/calibrate.py found for this implementation (seeds 100-104, README: "Calibrated
#: alpha and beta").
EXAMPLES: dict[int, dict[str, Any]] = {
    1: {
        "noise_db": -10.0,
        "description": "Model 1: y(k+1) = 0.3 y(k) + 0.6 y(k-1) + g[u(k)]",
        "structure": {"y_lags": 0, "u_lags": 1, "known_a": (0.3, 0.6)},
        # "u expanded to 14 terms": one input, L1..L14, plus the bias weight (N0 = 15).
        "lenn": {"order": 14, "output": "tanh", "alpha": 0.5, "beta": 0.5},
        "mlp": {"hidden": [20, 10], "output": "tanh", "alpha": 0.5, "beta": 0.5},
        "paper_nmse_db": {"mlp": -16.69, "lenn": -25.04},
        "calibrated": {"lenn": {"alpha": 0.0078125, "beta": 0.5}, "mlp": {"alpha": 0.015625, "beta": 0.5}},
    },
    2: {
        "noise_db": -20.0,
        "description": "Model 2: y(k+1) = f[y(k), y(k-1)] + u(k)",
        # No SF is given for Ex. 2, but y reaches about +-2.7: SF 3 keeps y/SF in [-1, 1].
        "structure": {"y_lags": 2, "u_lags": 0, "known_b": (1.0,), "y_scale": 3.0},
        # "2 inputs expanded to 12 terms": L1..L6 of each input, plus the bias.
        # f reaches about -2.1, outside tanh's range: the tanh output is scaled by 3.
        "lenn": {"order": 6, "output": "tanh", "output_scale": 3.0, "alpha": 0.009, "beta": 0.01},
        "mlp": {"hidden": [20, 10], "output": "tanh", "output_scale": 3.0, "alpha": 0.05, "beta": 0.10},
        "paper_nmse_db": {"mlp": -18.95, "lenn": -18.80},
        "calibrated": {"lenn": {"alpha": 0.00028125, "beta": 0.5}, "mlp": {"alpha": 0.0125, "beta": 0.1}},
    },
    3: {
        "noise_db": -20.0,
        "description": "Model 3: y(k+1) = f[y(k)] + g[u(k)], model N1[y(k)] + N2[u(k)]",
        "structure": {"y_lags": 1, "u_lags": 1, "y_scale": 2.0, "separate": True},
        "lenn": {"order": 14, "output": "tanh", "alpha": 0.25, "beta": 0.95},
        "mlp": {"hidden": [20, 10], "output": "tanh", "alpha": 0.50, "beta": 0.2},
        "paper_nmse_db": {"mlp": -19.45, "lenn": -19.87},
        "calibrated": {"lenn": {"alpha": 0.00390625, "beta": 0.95}, "mlp": {"alpha": 0.015625, "beta": 0.5}},
    },
    4: {
        "noise_db": -20.0,
        "description": "Model 4: y(k+1) = f[y(k), y(k-1), y(k-2), u(k), u(k-1)]",
        # "SF = 0.7": y reaches about +-1.1, so the network sees 0.7 y (divisor 1/0.7).
        "structure": {"y_lags": 3, "u_lags": 2, "y_scale": 1.0 / 0.7},
        # "5 inputs expanded to 10 terms": L1, L2 of each input, plus the bias.
        "lenn": {"order": 2, "output": "tanh", "alpha": 0.02, "beta": 0.10},
        "mlp": {"hidden": [20, 10], "output": "tanh", "alpha": 0.01, "beta": 0.10},
        "paper_nmse_db": {"mlp": -15.56, "lenn": -15.53},
        "calibrated": {"lenn": {"alpha": 0.005, "beta": 0.5}, "mlp": {"alpha": 0.000625, "beta": 0.5}},
    },
}


def example_preset(number: Any) -> dict[str, Any]:
    """The example's entry by its number, with a clear error for anything else (the one check of a number)."""
    try:
        return EXAMPLES[int(number)]
    except (KeyError, ValueError):
        raise ValueError(f"unknown example {number!r}; the paper has examples 1, 2, 3 and 4") from None


def network_settings(preset: dict[str, Any], network: str, parameters: str = "calibrated") -> dict[str, Any]:
    """One network's settings (a fresh dict): ``preset[network]``, with alpha/beta from
    ``preset["calibrated"]`` unless ``parameters`` is ``"paper"`` (alpha and beta as printed in the paper).

    ``preset`` is an entry of :data:`EXAMPLES` or the same fields of a
    :class:`~lenn_ros.paper.examples.PaperExample`: the node's defaults and the paper harness's
    networks are merged by this one rule.
    """
    if network not in NETWORKS:
        raise ValueError(f"unknown network {network!r}; expected 'lenn' or 'mlp'")
    if parameters not in PARAMETER_SETS:
        raise ValueError(f"unknown parameter set {parameters!r}; expected one of {PARAMETER_SETS}")
    merged = dict(preset[network])
    if parameters == "calibrated":
        merged.update(preset.get("calibrated", {}).get(network, {}))
    return merged
