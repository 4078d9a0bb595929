"""set_params on a fitted network: shape-changing parameters are refused, changes are all or nothing.

Before this was enforced, ``set_params(order=12)`` on a fitted LeNN was accepted and the
next ``predict`` let the compiled kernel index past the weights (a segfault with numba).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from lenn_ros.core.networks import MLP, FunctionalLinkNetwork, LeNN


def _fitted(network: LeNN | MLP | FunctionalLinkNetwork) -> LeNN | MLP | FunctionalLinkNetwork:
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (50, network.n_inputs))
    network.partial_fit(x, np.sin(x[:, 0]))
    return network


@pytest.mark.parametrize(
    ("network", "change"),
    [
        (LeNN(n_inputs=2, order=4), {"order": 12}),
        (LeNN(n_inputs=2, order=4), {"n_inputs": 3}),
        (LeNN(n_inputs=2, order=2), {"cross_degree": 2}),
        (LeNN(n_inputs=2, order=4, output="linear"), {"solver": "rls"}),
        (MLP(n_inputs=1, hidden=(5, 3)), {"hidden": [7, 3]}),
    ],
)
def test_structural_change_of_a_fitted_network_is_refused(network: LeNN | MLP, change: dict) -> None:
    fitted = _fitted(network)
    state = fitted.state()
    params = fitted.get_params()
    name = next(iter(change))
    with pytest.raises(ValueError, match=f"cannot change {name} of a fitted"):
        fitted.set_params(**change)
    assert fitted.get_params() == params
    for key, array in fitted.state().items():
        assert np.array_equal(array, state[key])
    assert np.isfinite(fitted.predict(np.zeros((3, fitted.n_inputs)))).all()


def test_structural_change_before_fitting_is_allowed() -> None:
    network = LeNN(n_inputs=1, order=4).set_params(order=6)
    _fitted(network)
    assert network.weights_.size == 7


def test_same_structural_value_and_learning_rates_are_accepted_on_a_fitted_network() -> None:
    network = _fitted(MLP(n_inputs=1, hidden=(5, 3)))
    network.set_params(hidden=(5, 3), alpha=0.01, beta=0.2)  # tuple equals the stored list
    assert network.alpha == 0.01 and network.beta == 0.2


def test_a_refused_change_changes_nothing() -> None:
    """All or nothing: an invalid value next to a valid one leaves both as they were."""
    network = _fitted(LeNN(n_inputs=1, order=4, alpha=0.5))
    with pytest.raises(ValueError, match="alpha must be"):
        network.set_params(beta=0.1, alpha=-1.0)
    assert (network.alpha, network.beta) == (0.5, 0.5)
    with pytest.raises(ValueError, match="cannot change order"):
        network.set_params(alpha=0.1, order=12)
    assert network.alpha == 0.5


def test_set_params_order_12_then_predict_does_not_crash_the_process() -> None:
    """The reported crash, in a child process so a segfault fails this test instead of killing pytest."""
    code = (
        "import numpy as np\n"
        "from lenn_ros.core.networks import LeNN\n"
        "n = LeNN(n_inputs=1, order=4)\n"
        "n.partial_fit(np.linspace(-1, 1, 20)[:, None], np.zeros(20))\n"
        "try:\n"
        "    n.set_params(order=12)\n"
        "except ValueError as e:\n"
        "    print('refused:', e)\n"
        "print(n.predict(np.linspace(-1, 1, 5)[:, None]).shape)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "refused: cannot change order" in result.stdout
