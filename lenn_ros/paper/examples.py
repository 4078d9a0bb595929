"""The paper's four examples: plant, noise, model structure, both networks.

The numbers are the presets of :mod:`lenn_ros.presets` (plain data, which the identifier's
parameters read too); here each becomes one :class:`PaperExample` with what only the paper
harness needs (the plant, the network objects, Table I's counts), so ``reproduce``, the ROS
nodes, the config files and the tests all read the same numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from lenn_ros import presets
from lenn_ros.core.networks import OnlineRegressor, make_network
from lenn_ros.core.structure import ModelStructure
from lenn_ros.paper.complexity import Complexity, lenn_complexity, mlp_complexity
from lenn_ros.paper.plants import Plant, example_plant


@dataclass(frozen=True)
class PaperExample:
    """One example of Section IV with the paper's reported results."""

    number: int
    noise_db: float
    structure: ModelStructure
    lenn: dict[str, Any]
    mlp: dict[str, Any]
    paper_nmse_db: dict[str, float]
    description: str = ""
    #: alpha/beta found by bench/calibrate.py for this implementation (see README)
    calibrated: dict[str, dict[str, float]] = field(default_factory=dict)

    def plant(self, **changes: Any) -> Plant:
        return example_plant(self.number, **changes)

    def network_params(self, network: str, parameters: str = "calibrated") -> dict[str, Any]:
        """Constructor arguments of the network (without the seed).

        ``parameters`` is ``"paper"`` (alpha and beta as printed in the paper) or
        ``"calibrated"`` (as chosen for this implementation by bench/calibrate.py).
        """
        fields = {"lenn": self.lenn, "mlp": self.mlp, "calibrated": self.calibrated}
        base = presets.network_settings(fields, network, parameters)
        return {"n_inputs": self.structure.n_inputs, "branches": self.structure.branches(), **base}

    def make_network(
        self, network: str, seed: int | None = 0, parameters: str = "calibrated", **overrides: Any
    ) -> OnlineRegressor:
        params = {**self.network_params(network, parameters), **overrides, "random_state": seed}
        return make_network(network, **params)

    def complexity(self, network: str) -> Complexity:
        """Table I counts per training iteration (both sub-networks for Ex. 3)."""
        branches = self.structure.branches() or [list(range(self.structure.n_inputs))]
        total = Complexity(0, 0, 0, 0)
        for branch in branches:
            if network == "lenn":
                total = total + lenn_complexity(len(branch) * self.lenn["order"])
            else:
                total = total + mlp_complexity([len(branch), *self.mlp["hidden"], 1])
        return total


EXAMPLES: dict[int, PaperExample] = {
    number: PaperExample(
        number=number,
        noise_db=preset["noise_db"],
        description=preset["description"],
        structure=ModelStructure(**preset["structure"]),
        lenn=dict(preset["lenn"]),
        mlp=dict(preset["mlp"]),
        paper_nmse_db=dict(preset["paper_nmse_db"]),
        calibrated={network: dict(values) for network, values in preset["calibrated"].items()},
    )
    for number, preset in presets.EXAMPLES.items()
}


def get_example(number: int) -> PaperExample:
    """The example by its number, with a clear error for anything else."""
    presets.example_preset(number)  # (the one check of a number, and its message)
    return EXAMPLES[int(number)]
