"""Plant formulas fail with one clear ExpressionError, never a Python exception or a traceback."""

from __future__ import annotations

import subprocess
import sys

import pytest

from lenn_ros.paper.expression import ExpressionError, compile_expression
from lenn_ros.paper.plants import plant_from_expressions


def test_division_by_zero_at_rest_names_the_formula_and_its_inputs() -> None:
    """u1/y1 is fine in general but divides by zero while the plant is at rest (y1 = 0)."""
    plant = plant_from_expressions(4, 1, 1, f="u1/y1")
    with pytest.raises(ExpressionError, match=r"^division by zero in f at y1=0\.0, u1=0\.5$"):
        plant.step(0.5)


def test_deep_nesting_is_refused_at_compile_time() -> None:
    """1500 unary minus signs are under the length limit but would exhaust Python's recursion."""
    for text in ("-" * 1500 + "y1", "y1+" * 600 + "y1", "-sin(" * 160 + "y1" + ")" * 160):
        with pytest.raises(ExpressionError, match=r"^expression nested deeper than \d+ levels"):
            compile_expression(text, ("y1",))
    assert compile_expression("-" * 49 + "y1", ("y1",))(2.0) == -2.0  # shallow nesting still compiles
    assert compile_expression("+".join(["y1"] * 250), ("y1",))(1.0) == 250.0  # so does a long sum


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("exp(1000*y1)", "overflow in exp()"),
        ("10**(400*y1)", "overflow in **"),
        ("log(-y1)", "math domain error in log()"),
        ("sqrt(-y1)", "math domain error in sqrt()"),
        ("(-8*y1)**(1/3)", "negative number to a fractional power"),
        ("(y1-1)**-1", "zero to a negative power"),
        ("y1*1e300*1e300", "overflow in *"),
        ("1/(1/(y1-1))", "division by zero"),
    ],
)
def test_overflow_and_domain_errors_are_expression_errors(text: str, problem: str) -> None:
    function = compile_expression(text, ("y1",))
    with pytest.raises(ExpressionError) as raised:
        function(1.0)
    assert str(raised.value) == f"{problem} in expression at y1=1.0"


@pytest.mark.parametrize("text", ["10**400", "1e999", "1" + "0" * 400, "exp(1000)"])
def test_constant_formulas_that_overflow_fail_at_compile_or_first_call(text: str) -> None:
    with pytest.raises(ExpressionError, match=r"overflow|out of range"):
        compile_expression(text, ("y1",))(0.0)


def test_plant_simulator_stops_with_one_line_when_the_formula_fails(domain: int) -> None:
    """The node steps the plant in a timer callback: an ExpressionError there must not become a traceback."""
    pytest.importorskip("rclpy")
    from rosutil import REPO

    command = [sys.executable, "-m", "lenn_ros.nodes.plant_simulator", "--ros-args"]
    for parameter in ("example:=0", "model:=4", "n:=1", "m:=1", "f:=u1/y1", "wait_for_subscribers:=0"):
        command += ["-p", parameter]
    process = subprocess.run(
        command,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )
    assert process.returncode == 2, process.stderr
    assert "Traceback" not in process.stderr
    failure = [line for line in process.stderr.splitlines() if "division by zero" in line]
    assert len(failure) == 1 and failure[0].startswith("plant_simulator: ") and "at step 0" in failure[0]
    assert "y1=0.0" in failure[0]
