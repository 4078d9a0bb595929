"""A restricted arithmetic-expression parser for user-defined plants.

A params file may define a plant by a formula such as ``y1*y2*(y1+2.5)/(1+y1**2)``.
Such text comes from outside and must never reach ``eval``/``exec``: it is parsed
with :mod:`ast`, and only numbers, the declared variable names, + - * / **, unary
minus and a fixed table of math functions are accepted. Anything else (attribute
access, calls to other names, subscripts, lambdas, comprehensions, strings) is
refused with the offending construct named.

Evaluation fails the same way: a division by zero, an overflow or a math domain
error at some inputs (``u1/y1`` while the plant rests at y1 = 0) is an
:class:`ExpressionError` naming the problem and the inputs, so a node or the command
line can report it as one line instead of a Python exception from deep inside.

:meth:`Expression.source` turns the checked tree into Python source for numba (see
its docstring): the user's text itself is never executed.
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
#: Deepest allowed nesting (a sum of k terms nests k levels). The checker, the evaluator
#: and ast.unparse recurse once or more per level, and 1500 nested minus signs fit in the
#: length limit; real plant formulas nest about 10 levels.
MAX_DEPTH = 300  # ~3 frames a level: well inside Python's default limit of 1000, with room for the caller


class ExpressionError(ValueError):
    """The text is not an allowed expression, or it cannot be evaluated at the given inputs."""


class _Failure(ArithmeticError):
    """An operation cannot give a finite number; the caller adds which formula and inputs."""


def _finite(result: float, symbol: str, *operands: float) -> float:
    """Python's + - * / overflow to inf silently: a finite formula must not, so refuse it here."""
    if not math.isfinite(result) and all(math.isfinite(x) for x in operands):
        raise _Failure(f"overflow in {symbol}")
    return result


def _divide(a: float, b: float) -> float:
    if b == 0.0:
        raise _Failure("division by zero")
    return _finite(a / b, "/", a, b)


def _power(a: float, b: float) -> float:
    """``**`` without its three escapes: ZeroDivisionError, OverflowError and a *complex* result."""
    if a == 0.0 and b < 0.0:
        raise _Failure("zero to a negative power")
    if math.isfinite(a) and a < 0.0 and math.isfinite(b) and b != math.floor(b):
        raise _Failure("negative number to a fractional power")
    try:
        return _finite(a**b, "**", a, b)
    except OverflowError:
        raise _Failure("overflow in **") from None


def _call(name: str, x: float) -> float:
    try:
        return FUNCTIONS[name](x)
    except OverflowError:
        raise _Failure(f"overflow in {name}()") from None
    except ValueError:
        raise _Failure(f"math domain error in {name}()") from None


_BINARY: Mapping[type, Callable[[float, float], float]] = {
    ast.Add: lambda a, b: _finite(a + b, "+", a, b),
    ast.Sub: lambda a, b: _finite(a - b, "-", a, b),
    ast.Mult: lambda a, b: _finite(a * b, "*", a, b),
    ast.Div: _divide,
    ast.Pow: _power,
}
_UNARY = {ast.USub: lambda a: -a, ast.UAdd: lambda a: a}
#: The same operations as source text for :meth:`Expression.source` (fixed strings only).
_SYMBOLS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Pow: "**"}
_SOURCE_FUNCTIONS = {name: "abs" if name == "abs" else f"math.{name}" for name in FUNCTIONS}
#: Leaves of the tree that do not nest (operators, Load): not counted as levels.
_NOT_LEVELS = (ast.expr_context, ast.operator, ast.unaryop, ast.boolop, ast.cmpop)


def compile_expression(text: str, variables: tuple[str, ...], name: str = "expression") -> Expression:
    """Parse and check ``text`` once; return it as a function of ``variables`` (positional floats).

    ``name`` (e.g. "f") is how evaluation errors refer to the formula.
    """
    if len(text) > 2000:
        raise ExpressionError("expression longer than 2000 characters")
    try:
        tree = ast.parse(text, mode="eval").body
    except (SyntaxError, ValueError) as error:  # ValueError: a null byte
        raise ExpressionError(f"cannot parse {text!r}: {getattr(error, 'msg', error)}") from None
    if _depth(tree) > MAX_DEPTH:
        raise ExpressionError(f"expression nested deeper than {MAX_DEPTH} levels (a sum of k terms nests k levels)")
    try:
        _check(tree, set(variables))
    except RecursionError:  # not expected below MAX_DEPTH, but never a traceback
        raise ExpressionError("expression nested too deeply") from None
    return Expression(text, tuple(variables), tree, name)


class Expression:
    """A checked formula: callable on floats, and convertible to source text for numba.

    Calling it is the reference evaluation (a tree walk, a few microseconds); the
    compiled whole-run simulation in :mod:`lenn_ros.paper.plants` must equal it.
    """

    def __init__(self, text: str, variables: tuple[str, ...], tree: ast.expr, name: str) -> None:
        self.text, self.variables, self.tree, self.name = text, variables, tree, name
        self._index = {variable: i for i, variable in enumerate(variables)}
        self.__doc__ = f"{name}({', '.join(variables)}) = {text}"

    def __repr__(self) -> str:
        return f"Expression({self.__doc__!r})"

    def __call__(self, *values: float) -> float:
        try:
            return float(self._evaluate(self.tree, values))
        except _Failure as failure:
            pairs = zip(self.variables, values, strict=False)
            where = ", ".join(f"{variable}={float(value)!r}" for variable, value in pairs)
            raise ExpressionError(f"{failure} in {self.name}" + (f" at {where}" if where else "")) from None

    def _evaluate(self, node: ast.AST, values: tuple[float, ...]) -> float:
        if isinstance(node, ast.Constant):
            return float(node.value)
        if isinstance(node, ast.Name):
            return values[self._index[node.id]] if node.id in self._index else CONSTANTS[node.id]
        if isinstance(node, ast.BinOp):
            return _BINARY[type(node.op)](self._evaluate(node.left, values), self._evaluate(node.right, values))
        if isinstance(node, ast.UnaryOp):
            return _UNARY[type(node.op)](self._evaluate(node.operand, values))
        assert isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
        return _call(node.func.id, self._evaluate(node.args[0], values))

    def source(self, function_name: str = "formula") -> tuple[str, tuple[float, ...]]:
        """Python source of the formula for numba, ``def function_name(c, a0, a1, ...)``, and the values of ``c``.

        Why generated code is safe to execute: the text is produced here from the
        *validated* tree only, never copied from the user's string. Variables become
        the positional arguments a0, a1, ... (by position in ``variables``), numbers
        the elements of the array argument ``c``, operators and functions come from
        fixed tables (``math.sin``, ...). Exec-ing this generated text is the intended way to hand
        the formula to numba; the user's text itself is never passed to eval or exec.

        One temporary per operation (a post-order walk with an explicit stack) keeps
        the source flat: no recursion here, no nested parentheses for Python's parser.

        Numbers are read from ``c`` rather than written as literals because LLVM
        rewrites calls with constant operands: pow(x, 2.0) becomes x*x and pow(x, -1.0)
        1/x, which differ from Python's pow in the last bit for about 1 input in 1000.
        With opaque numbers the compiled formula makes the calls Python makes.

        Errors: compiled code cannot raise this module's messages cheaply, so it
        returns NaN as soon as an operand of ``/``, ``**`` or a function is not
        finite, and may return inf/NaN from + - *. Every case in which the reference
        raises yields a non-finite result (x/0 is inf or NaN under numba's
        error_model="numpy"; overflow is inf; a domain error NaN), and + - * keep a
        non-finite value non-finite, so a caller that re-evaluates every non-finite
        result with the reference reports exactly the reference's errors.
        """
        writer = _SourceWriter(self._index)
        stack: list[tuple[ast.AST, bool]] = [(self.tree, False)]
        while stack:
            node, operands_done = stack.pop()
            children = _operands(node)
            if operands_done:
                writer.write(node, children)
            else:
                stack.append((node, True))
                stack.extend((child, False) for child in reversed(children))
        arguments = "".join(f", a{i}" for i in range(len(self.variables)))
        lines = [
            f"def {function_name}(c{arguments}):",
            *writer.lines,
            f"    return float({writer.value[id(self.tree)]})",
        ]
        return "\n".join(lines) + "\n", tuple(writer.constants)


class _SourceWriter:
    """The body of :meth:`Expression.source`, one checked node at a time, operands first."""

    def __init__(self, index: Mapping[str, int]) -> None:
        self.index = index
        self.lines: list[str] = []
        self.value: dict[int, str] = {}  # id(node) -> the argument a<i>, number c[<i>] or temporary t<i>
        self.constants: list[float] = []
        self._checked: set[str] = set()

    def write(self, node: ast.AST, children: list[ast.AST]) -> None:
        operands = [self.value[id(child)] for child in children]
        if isinstance(node, ast.Name) and node.id in self.index:
            self.value[id(node)] = f"a{self.index[node.id]}"
        elif isinstance(node, ast.Constant | ast.Name):  # a number or pi / e: finite, _check refused the rest
            self.value[id(node)] = f"c[{len(self.constants)}]"
            self.constants.append(float(node.value) if isinstance(node, ast.Constant) else CONSTANTS[node.id])
        elif isinstance(node, ast.BinOp):
            if isinstance(node.op, ast.Div | ast.Pow):
                self._require_finite(*operands)
            self._assign(node, f"{operands[0]} {_SYMBOLS[type(node.op)]} {operands[1]}")
        elif isinstance(node, ast.UnaryOp):
            if isinstance(node.op, ast.USub):
                self._assign(node, f"-{operands[0]}")
            else:
                self.value[id(node)] = operands[0]
        else:
            assert isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
            self._require_finite(operands[0])
            self._assign(node, f"{_SOURCE_FUNCTIONS[node.func.id]}({operands[0]})")

    def _require_finite(self, *operands: str) -> None:
        """The NaN exit of Expression.source's docstring, once per value."""
        for operand in operands:
            if not operand.startswith("c[") and operand not in self._checked:
                self.lines += [f"    if not math.isfinite({operand}):", "        return math.nan"]
                self._checked.add(operand)

    def _assign(self, node: ast.AST, expression: str) -> None:
        temporary = f"t{len(self.value)}"
        self.lines.append(f"    {temporary} = {expression}")
        self.value[id(node)] = temporary


def _operands(node: ast.AST) -> list[ast.AST]:
    """Sub-expressions of a checked node, in evaluation order."""
    if isinstance(node, ast.BinOp):
        return [node.left, node.right]
    if isinstance(node, ast.UnaryOp):
        return [node.operand]
    if isinstance(node, ast.Call):
        return [node.args[0]]
    return []


def _depth(tree: ast.AST) -> int:
    """Nesting depth without recursion (the point is to refuse trees too deep to recurse over)."""
    deepest = 0
    stack = [(tree, 1)]
    while stack:
        node, depth = stack.pop()
        deepest = max(deepest, depth)
        if deepest > MAX_DEPTH:
            break
        stack.extend((child, depth + 1) for child in ast.iter_child_nodes(node) if not isinstance(child, _NOT_LEVELS))
    return deepest


def _check_constant(node: ast.Constant) -> None:
    """A number that is a float and finite: 1e999 parses to inf, and 10**400 written out overflows float()."""
    if isinstance(node.value, bool) or not isinstance(node.value, int | float):
        raise ExpressionError(f"only numbers are allowed as constants, not {node.value!r}")
    try:
        finite = math.isfinite(float(node.value))
    except OverflowError:  # an integer literal beyond the float range
        finite = False
    if not finite:
        raise ExpressionError("constant out of range: a float is at most about 1.8e308")


def _check(node: ast.AST, variables: set[str]) -> None:
    if isinstance(node, ast.Constant):
        _check_constant(node)
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
