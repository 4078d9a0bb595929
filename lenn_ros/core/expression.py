"""A restricted arithmetic-expression parser for user-defined plants.

A params file may define a plant by a formula such as ``y1*y2*(y1+2.5)/(1+y1**2)``.
Such text comes from outside and must never reach ``eval``/``exec``: it is parsed
with :mod:`ast`, and only numbers, the declared variable names, + - * / **, unary
minus and a fixed table of math functions are accepted. Anything else (attribute
access, calls to other names, subscripts, lambdas, comprehensions, strings) is
refused with the offending construct named.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Mapping

FUNCTIONS: Mapping[str, Callable[..., float]] = {
    "sin": math.sin,
    "cos": math.cos,
    "tan": math.tan,
    "tanh": math.tanh,
    "exp": math.exp,
    "log": math.log,
    "sqrt": math.sqrt,
    "abs": abs,
    "atan": math.atan,
}
CONSTANTS: Mapping[str, float] = {"pi": math.pi, "e": math.e}

_BINARY = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
    ast.Pow: lambda a, b: a**b,
}
_UNARY = {ast.USub: lambda a: -a, ast.UAdd: lambda a: a}


class ExpressionError(ValueError):
    """The text is not an allowed expression."""


def compile_expression(text: str, variables: tuple[str, ...]) -> Callable[..., float]:
    """Parse ``text`` once; return a function of ``variables`` (positional floats)."""
    if len(text) > 2000:
        raise ExpressionError("expression longer than 2000 characters")
    try:
        tree = ast.parse(text, mode="eval").body
    except SyntaxError as error:
        raise ExpressionError(f"cannot parse {text!r}: {error.msg}") from None
    _check(tree, set(variables))
    index = {name: i for i, name in enumerate(variables)}

    def evaluate(node: ast.AST, values: tuple[float, ...]) -> float:
        if isinstance(node, ast.Constant):
            return float(node.value)
        if isinstance(node, ast.Name):
            return values[index[node.id]] if node.id in index else CONSTANTS[node.id]
        if isinstance(node, ast.BinOp):
            return _BINARY[type(node.op)](evaluate(node.left, values), evaluate(node.right, values))
        if isinstance(node, ast.UnaryOp):
            return _UNARY[type(node.op)](evaluate(node.operand, values))
        assert isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
        return FUNCTIONS[node.func.id](*(evaluate(a, values) for a in node.args))

    def function(*values: float) -> float:
        return float(evaluate(tree, values))

    function.__doc__ = f"f({', '.join(variables)}) = {text}"
    return function


def _check(node: ast.AST, variables: set[str]) -> None:
    if isinstance(node, ast.Constant):
        if isinstance(node.value, bool) or not isinstance(node.value, int | float):
            raise ExpressionError(f"only numbers are allowed as constants, not {node.value!r}")
    elif isinstance(node, ast.Name):
        if node.id not in variables and node.id not in CONSTANTS:
            allowed = ", ".join(sorted(variables | set(CONSTANTS)))
            raise ExpressionError(f"unknown name {node.id!r}; allowed: {allowed}")
    elif isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
        _check(node.left, variables)
        _check(node.right, variables)
    elif isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
        _check(node.operand, variables)
    elif isinstance(node, ast.Call):
        if not isinstance(node.func, ast.Name) or node.func.id not in FUNCTIONS:
            raise ExpressionError(
                f"call of {ast.unparse(node.func)!r} is not allowed; functions: {', '.join(FUNCTIONS)}"
            )
        if node.keywords or len(node.args) != 1:
            raise ExpressionError(f"{node.func.id}() takes exactly one positional argument")
        _check(node.args[0], variables)
    else:
        raise ExpressionError(f"{type(node).__name__} is not allowed in an expression: {ast.unparse(node)!r}")
