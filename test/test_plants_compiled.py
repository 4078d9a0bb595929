"""The compiled whole-run simulation (Plant.run) equals the Python reference, Plant.step after step."""

from __future__ import annotations

import numpy as np
import pytest

from lenn_ros.core.jit import COMPILED
from lenn_ros.paper import plants
from lenn_ros.paper.examples import EXAMPLES
from lenn_ros.paper.expression import ExpressionError
from lenn_ros.paper.plants import Plant, example_plant, plant_from_expressions
from lenn_ros.paper.signals import Excitation

pytestmark = pytest.mark.skipif(not COMPILED, reason="numba is not installed: Plant.run is the reference itself")

#: Example 4 of the paper written as a formula, with ** and functions so the generated code covers them.
USER_F = (
    "(y1*y2*y3*u2*(y3-1.0) + u1)/(1.0 + y2**2 + y3*y3) + 0.01*tanh(exp(-abs(y1))) - sqrt(abs(u1))/10 + (1+y1*y1)**-1.5"
)


def _applied(number: int, samples: int = 20_000) -> np.ndarray:
    """The paper's plant input (uniform u plus the example's noise, then eq. 11): the data reproduce simulates."""
    u, noise = Excitation(7, "paper", samples, 600, EXAMPLES[number].noise_db).series()
    return u + noise


def _count_steps(plant: Plant) -> list[float]:
    """Record every Plant.step of this plant: the compiled path must not take the Python loop."""
    calls: list[float] = []
    step = plant.step

    def counting(u: float) -> float:
        calls.append(u)
        return step(u)

    plant.step = counting  # type: ignore[method-assign]
    return calls


def _assert_compiled_equals_reference(make, u: np.ndarray) -> None:
    compiled, reference = make(), make()
    calls = _count_steps(compiled)
    y = compiled.run(u)
    assert calls == []  # the kernel ran every step
    y_reference = reference.run(u, compiled=False)
    np.testing.assert_array_equal(y, y_reference)  # bit for bit
    np.testing.assert_array_equal(compiled.y_past, reference.y_past)
    np.testing.assert_array_equal(compiled.u_past, reference.u_past)


@pytest.mark.parametrize("number", [1, 2, 3, 4])
def test_each_example_compiled_equals_step_by_step(number: int) -> None:
    _assert_compiled_equals_reference(lambda: example_plant(number), _applied(number))


def test_a_changed_example_plant_and_a_carried_over_state() -> None:
    """The tracking scenario: gain and linear part changed, the run continued from another plant's state."""
    u = _applied(1)
    first = example_plant(1)
    first.run(u[:5000])

    def make() -> Plant:
        changed = example_plant(1, gain=0.7, linear=(0.2, 0.5))
        changed.y_past, changed.u_past = first.y_past.copy(), first.u_past.copy()
        return changed

    _assert_compiled_equals_reference(make, u[5000:])


@pytest.mark.parametrize(
    ("model", "n", "m", "formulas"),
    [
        (4, 3, 2, {"f": USER_F}),
        (1, 2, 1, {"g": "0.6*sin(pi*u1) + 0.3*sin(3*pi*u1) + 0.1*sin(5*pi*u1)", "a": (0.3, 0.6)}),
        (2, 2, 2, {"f": "y1*y2*(y1+2.5)*(y1-1)/(1+y1**2+y2**2)", "b": (1.0, -0.25)}),
        (3, 1, 1, {"f": "y1*(y1+0.3)/(1+y1**2)", "g": "u1*(u1+0.8)*(u1-0.5) + e**(-u1*u1)"}),
    ],
)
def test_user_formula_compiled_equals_step_by_step(model: int, n: int, m: int, formulas: dict) -> None:
    _assert_compiled_equals_reference(lambda: plant_from_expressions(model, n, m, **formulas), _applied(4))


def test_division_by_zero_in_a_compiled_formula_is_the_references_expression_error() -> None:
    """y counts 0, 1, 2, ... exactly, so u1/(y1-100) divides by zero at step 100, after 100 compiled steps."""
    u = np.full(300, 0.5)
    plant = plant_from_expressions(4, 1, 1, f="y1 + 1 + 0*u1/(y1 - 100)")
    calls = _count_steps(plant)
    with pytest.raises(ExpressionError, match=r"^division by zero in f at y1=100\.0, u1=0\.5$"):
        plant.run(u)
    assert calls == [0.5]  # only the failing step went to Python
    reference = plant_from_expressions(4, 1, 1, f="y1 + 1 + 0*u1/(y1 - 100)")
    with pytest.raises(ExpressionError):
        reference.run(u, compiled=False)
    np.testing.assert_array_equal(plant.y_past, reference.y_past)  # the same state left behind
    np.testing.assert_array_equal(plant.u_past, reference.u_past)


def test_non_finite_values_are_handed_to_the_reference() -> None:
    """NaN in the input is no formula error: the reference's NaNs come out, and finite steps stay compiled."""
    u = np.array([0.5, 0.25, np.nan, 0.1, 0.2])
    for make in (lambda: example_plant(3), lambda: plant_from_expressions(4, 1, 1, f="0.5*y1 + tanh(u1)")):
        compiled, reference = make(), make()
        calls = _count_steps(compiled)
        np.testing.assert_array_equal(compiled.run(u), reference.run(u, compiled=False))
        assert len(calls) == 3  # steps 0 and 1 compiled, from the NaN on Python


def test_replaced_nonlinear_part_is_not_run_by_the_stale_kernel() -> None:
    plant = example_plant(3)
    plant.g = lambda u: 2.0 * u
    assert plant.run(np.array([0.5]))[1] == pytest.approx(1.0)


def test_generated_source_holds_no_user_text() -> None:
    """Names become a0, a1, ..., numbers c[i], functions math.*: nothing of the user's spelling reaches exec."""
    plant = plant_from_expressions(4, 2, 1, f="sin(y2)*1.5 + y1**2/u1")
    source, constants = plant.f.source("_f")
    assert source.startswith("def _f(c, a0, a1, a2):")
    assert "y1" not in source and "u1" not in source and "1.5" not in source and "math.sin(" in source
    assert constants == (1.5, 2.0)
    assert isinstance(plant.kernel, plants.FormulaKernel)
