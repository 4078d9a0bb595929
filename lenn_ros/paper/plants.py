"""Plants: the four model classes of Narendra & Parthasarathy and the paper's examples.

A plant is a difference equation y(k+1) = F(y(k..k-n+1), u(k..k-m+1)). The four
classes differ in which part is nonlinear and which is a known linear combination:

- Model 1: y(k+1) = sum a_i y(k-i) + g[u(k..k-m+1)]
- Model 2: y(k+1) = f[y(k..k-n+1)] + sum b_i u(k-i)
- Model 3: y(k+1) = f[y(k..k-n+1)] + g[u(k..k-m+1)]
- Model 4: y(k+1) = f[y(k..k-n+1), u(k..k-m+1)]

The nonlinear parts are Python callables; user-defined ones come from
:mod:`lenn_ros.paper.expression` (never ``eval``). Time convention used everywhere in
the package: at step k the plant *shows* y(k), then the input u(k) is applied (plus
noise) and the plant moves to y(k+1).

Two ways to simulate, equal to the last bit: :meth:`Plant.step` in Python, one sample
at a time (the live plant simulator node; the reference), and :meth:`Plant.run` over
a whole input series, which hands the loop to a numba kernel when the plant has one
(the four examples: cached kernels below; user formulas: compiled from the checked
tree on first use). Issue 12: the Python loop, ~20-40 us a step, was most of the
time of ``lenn-ros reproduce``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import numpy as np

from lenn_ros.core.jit import COMPILED, njit
from lenn_ros.paper.expression import Expression, compile_expression

Function = Callable[..., float]


class Kernel(Protocol):
    """A compiled whole-run simulation of one plant (see :meth:`Plant.run`)."""

    def stands_for(self, plant: Plant) -> bool:
        """False if the plant's f/g were replaced after the kernel was made: then Python runs."""
        ...

    def __call__(
        self, plant: Plant, y_past: np.ndarray, u_past: np.ndarray, u_applied: np.ndarray, y_out: np.ndarray
    ) -> int:
        """Fill y_out[0..count], advance y_past/u_past in place; return count (stopped before a non-finite y)."""
        ...


@dataclass
class Plant:
    """A SISO discrete-time plant with its past outputs and inputs as state.

    ``model`` is the class (1-4); ``a`` / ``b`` the known linear coefficients
    (Model 1 / Model 2); ``f`` takes the n past outputs, ``g`` the m past inputs
    (Model 4's ``f`` takes the outputs then the inputs).
    """

    #: one input, one output (a :class:`MimoPlant` says how many it has)
    n_u: ClassVar[int] = 1
    n_y: ClassVar[int] = 1

    model: int
    n: int
    m: int
    f: Function | None = None
    g: Function | None = None
    a: Sequence[float] = ()
    b: Sequence[float] = ()
    name: str = "plant"
    kernel: Kernel | None = field(default=None, repr=False, compare=False)
    y_past: np.ndarray = field(init=False, repr=False)
    u_past: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.model not in (1, 2, 3, 4):
            raise ValueError(f"model class must be 1, 2, 3 or 4, not {self.model}")
        if self.n < 1 or self.m < 1 or self.m > self.n:
            raise ValueError(f"need 1 <= m <= n (the paper's m <= n), got n={self.n}, m={self.m}")
        needs = {1: ("g", "a"), 2: ("f", "b"), 3: ("f", "g"), 4: ("f",)}[self.model]
        for part in needs:
            if getattr(self, part) is None or (part in "ab" and len(getattr(self, part)) == 0):
                raise ValueError(f"Model {self.model} needs {part!r}")
        if self.model == 1 and len(self.a) != self.n:
            raise ValueError(f"Model 1 needs n={self.n} coefficients a, got {len(self.a)}")
        if self.model == 2 and len(self.b) != self.m:
            raise ValueError(f"Model 2 needs m={self.m} coefficients b, got {len(self.b)}")
        self.reset()

    def reset(self) -> None:
        """Back to rest: all past outputs and inputs zero."""
        self.y_past = np.zeros(self.n)
        self.u_past = np.zeros(self.m)

    @property
    def output(self) -> float:
        """y(k), the output the plant shows now."""
        return float(self.y_past[0])

    def next_output(self, y_past: Sequence[float], u_past: Sequence[float]) -> float:
        """F of the class: y(k+1) from y(k..k-n+1) and u(k..k-m+1)."""
        if self.model == 1:
            return sum(a * y for a, y in zip(self.a, y_past, strict=True)) + self.g(*u_past)
        if self.model == 2:
            return self.f(*y_past) + sum(b * u for b, u in zip(self.b, u_past, strict=True))
        if self.model == 3:
            return self.f(*y_past) + self.g(*u_past)
        return self.f(*y_past, *u_past)

    def step(self, u_applied: float) -> float:
        """Apply u(k) (noise included) and advance; returns y(k+1)."""
        self.u_past = np.roll(self.u_past, 1)
        self.u_past[0] = u_applied
        y_next = self.next_output(self.y_past.tolist(), self.u_past.tolist())
        self.y_past = np.roll(self.y_past, 1)
        self.y_past[0] = y_next
        return y_next

    def run(self, u_applied: np.ndarray, compiled: bool = True) -> np.ndarray:
        """Outputs y(0..N) for inputs u(0..N-1): y[k] is shown before u[k] acts.

        With a kernel (and ``compiled``) the loop runs in numba; ``compiled=False``
        is the reference, :meth:`step` after step. The kernel stops before any step
        whose output is not finite and the reference takes over from there, so a
        formula error is the reference's ExpressionError (same message, same state)
        and a plant that legitimately reaches inf/NaN gives the reference's values.
        """
        u = np.ascontiguousarray(u_applied, dtype=np.float64)
        y = np.empty(len(u) + 1)
        done = 0
        if compiled and COMPILED and self.kernel is not None and self.kernel.stands_for(self):
            # copies: step() never writes state in place, and callers share these arrays between plants
            y_past = np.array(self.y_past, dtype=np.float64)
            u_past = np.array(self.u_past, dtype=np.float64)
            done = self.kernel(self, y_past, u_past, u, y)
            self.y_past, self.u_past = y_past, u_past
        y[done] = self.output
        for k, value in enumerate(u[done:].tolist(), start=done):
            y[k + 1] = self.step(value)
        return y


def plant_from_expressions(
    model: int,
    n: int,
    m: int,
    f: str | None = None,
    g: str | None = None,
    a: Sequence[float] = (),
    b: Sequence[float] = (),
) -> Plant:
    """A user-defined plant: f over y1..yn (Model 4: then u1..um), g over u1..um.

    y1 is y(k), y2 is y(k-1), ...; u1 is u(k). Formulas go through the restricted
    parser, so a params file cannot run code.
    """
    ys = tuple(f"y{i + 1}" for i in range(n))
    us = tuple(f"u{i + 1}" for i in range(m))
    f_fn = compile_expression(f, ys + us if model == 4 else ys, name="f") if f else None
    g_fn = compile_expression(g, us, name="g") if g else None
    kernel = FormulaKernel(f_fn, g_fn)
    return Plant(model=model, n=n, m=m, f=f_fn, g=g_fn, a=tuple(a), b=tuple(b), name="user-defined", kernel=kernel)


# -- compiled whole-run simulation ----------------------------------------------------
@njit(cache=True, nogil=True, inline="always")
def _push(past: np.ndarray, value: float) -> None:
    """past <- (value, past[0], ..., past[-2]): what step()'s np.roll and assignment do."""
    for i in range(len(past) - 1, 0, -1):
        past[i] = past[i - 1]
    past[0] = value


class FormulaKernel:
    """Whole-run kernel of a user-defined plant, compiled on first use.

    Lazily, so that the plant simulator node (which only steps) never pays numba's
    compile time (~0.1-1 s). The source comes from :meth:`Expression.source` (the
    validated tree, never the user's text) plus the loop below, made here from
    fixed strings; exec-ing that generated text and handing it to numba is the
    intended way to compile a formula. Nothing can be cached on disk: numba caches
    only functions that live in a file.
    """

    def __init__(self, f: Expression | None, g: Expression | None) -> None:
        self.f, self.g = f, g
        self._compiled: dict[tuple[int, int, int], Callable[..., int]] = {}
        self._f_constants = self._g_constants = np.zeros(1)  # the c of Expression.source, set by _compile

    def stands_for(self, plant: Plant) -> bool:
        return plant.f is self.f and plant.g is self.g

    def __call__(
        self, plant: Plant, y_past: np.ndarray, u_past: np.ndarray, u_applied: np.ndarray, y_out: np.ndarray
    ) -> int:
        key = (plant.model, plant.n, plant.m)
        if key not in self._compiled:
            self._compiled[key] = self._compile(*key)
        linear = np.asarray(plant.a if plant.model == 1 else plant.b if plant.model == 2 else (0.0,), dtype=np.float64)
        return self._compiled[key](y_past, u_past, u_applied, linear, self._f_constants, self._g_constants, y_out)

    def run_source(self, model: int, n: int, m: int) -> str:
        """The loop: y(k+1) of the model class from y_past[0..n-1] and u(k) = u0, u_past[0..m-2]."""
        ys = [f"y_past[{i}]" for i in range(n)]
        us = ["u0", *(f"u_past[{i}]" for i in range(m - 1))]

        def linear(values: list[str]) -> str:  # sum() of the Python path: 0 + c0 v0 + c1 v1 ..., in that order
            return "(" * len(values) + "0.0" + "".join(f" + linear[{i}] * {v})" for i, v in enumerate(values))

        f = f"_f(f_constants, {', '.join(ys + us if model == 4 else ys)})"
        g = f"_g(g_constants, {', '.join(us)})"
        next_output = {1: f"{linear(ys)} + {g}", 2: f"{f} + {linear(us)}", 3: f"{f} + {g}", 4: f}[model]
        return (
            "def run(y_past, u_past, u_applied, linear, f_constants, g_constants, y_out):\n"
            "    y_out[0] = y_past[0]\n"
            "    for k in range(u_applied.shape[0]):\n"
            "        u0 = u_applied[k]\n"
            f"        y_next = {next_output}\n"
            "        if not math.isfinite(y_next):\n"
            "            return k\n"
            "        _push(u_past, u0)\n"
            "        _push(y_past, y_next)\n"
            "        y_out[k + 1] = y_next\n"
            "    return u_applied.shape[0]\n"
        )

    def _compile(self, model: int, n: int, m: int) -> Callable[..., int]:
        namespace: dict[str, object] = {"math": math, "_push": _push}
        for part, expression in (("_f", self.f), ("_g", self.g)):
            if expression is not None:
                source, constants = expression.source(part)
                exec(source, namespace)  # generated from the checked tree, see Expression.source
                namespace[part] = njit(nogil=True, error_model="numpy")(namespace[part])
                setattr(self, f"{part}_constants", np.array(constants or (0.0,), dtype=np.float64))
        exec(self.run_source(model, n, m), namespace)
        return njit(nogil=True, error_model="numpy")(namespace["run"])


# -- the paper's four examples ------------------------------------------------------
def example1_g(u: float) -> float:
    return 0.6 * math.sin(math.pi * u) + 0.3 * math.sin(3 * math.pi * u) + 0.1 * math.sin(5 * math.pi * u)


def example2_f(y1: float, y2: float) -> float:
    return y1 * y2 * (y1 + 2.5) * (y1 - 1.0) / (1.0 + y1 * y1 + y2 * y2)


def example3_f(y: float) -> float:
    return y * (y + 0.3) / (1.0 + y * y)


def example3_g(u: float) -> float:
    return u * (u + 0.8) * (u - 0.5)


def example4_f(a1: float, a2: float, a3: float, a4: float, a5: float) -> float:
    return (a1 * a2 * a3 * a5 * (a3 - 1.0) + a4) / (1.0 + a2 * a2 + a3 * a3)


_example1_g = njit(cache=True, nogil=True, inline="always")(example1_g)
_example2_f = njit(cache=True, nogil=True, inline="always")(example2_f)
_example3_f = njit(cache=True, nogil=True, inline="always")(example3_f)
_example3_g = njit(cache=True, nogil=True, inline="always")(example3_g)
_example4_f = njit(cache=True, nogil=True, inline="always")(example4_f)


@njit(cache=True, nogil=True)
def _run_example(
    example: int,
    gain: float,
    linear: np.ndarray,
    y_past: np.ndarray,
    u_past: np.ndarray,
    u_applied: np.ndarray,
    y_out: np.ndarray,
) -> int:
    """The examples' plants over a whole series, the same operations in the same order as step().

    One kernel for all four (the branch on ``example`` costs nothing next to the
    sines) so that a single cached compilation serves ``reproduce``; the nonlinear
    parts are the Python functions above compiled as they are, so there is no
    second copy of a formula to keep in sync.
    """
    y_out[0] = y_past[0]
    for k in range(u_applied.shape[0]):
        u0 = u_applied[k]
        if example == 1:
            y_next = (0.0 + linear[0] * y_past[0] + linear[1] * y_past[1]) + gain * _example1_g(u0)
        elif example == 2:
            y_next = gain * _example2_f(y_past[0], y_past[1]) + (0.0 + linear[0] * u0)
        elif example == 3:
            y_next = _example3_f(y_past[0]) + gain * _example3_g(u0)
        else:
            y_next = gain * _example4_f(y_past[0], y_past[1], y_past[2], u0, u_past[0])
        if not math.isfinite(y_next):
            return k
        _push(u_past, u0)
        _push(y_past, y_next)
        y_out[k + 1] = y_next
    return u_applied.shape[0]


@dataclass(frozen=True, eq=False)
class ExampleKernel:
    """Binds :func:`_run_example` to one example plant; the known coefficients are read from the plant."""

    example: int
    gain: float
    f: Function | None
    g: Function | None

    def stands_for(self, plant: Plant) -> bool:
        return plant.f is self.f and plant.g is self.g and (plant.model, plant.n, plant.m) == _SHAPES[self.example]

    def __call__(
        self, plant: Plant, y_past: np.ndarray, u_past: np.ndarray, u_applied: np.ndarray, y_out: np.ndarray
    ) -> int:
        linear = np.asarray(plant.a if plant.model == 1 else plant.b if plant.model == 2 else (0.0,), dtype=np.float64)
        return _run_example(self.example, self.gain, linear, y_past, u_past, u_applied, y_out)


_SHAPES = {1: (1, 2, 1), 2: (2, 2, 1), 3: (3, 1, 1), 4: (4, 3, 2)}  # (model, n, m) of each example


def example_plant(example: int, gain: float = 1.0, linear: Sequence[float] | None = None) -> Plant:
    """Plant of the paper's Example 1-4.

    ``gain`` multiplies the unknown nonlinear part and ``linear`` replaces the known
    coefficients (Ex. 1's 0.3 / 0.6): both exist to make a plant *change* mid-run,
    the tracking scenario; the defaults are the paper's plants.
    """
    gain = float(gain)
    if example == 1:
        plant = Plant(1, 2, 1, g=lambda u: gain * example1_g(u), a=tuple(linear or (0.3, 0.6)), name="example 1")
    elif example == 2:
        plant = Plant(2, 2, 1, f=lambda y1, y2: gain * example2_f(y1, y2), b=tuple(linear or (1.0,)), name="example 2")
    elif example == 3:
        plant = Plant(3, 1, 1, f=example3_f, g=lambda u: gain * example3_g(u), name="example 3")
    elif example == 4:
        plant = Plant(4, 3, 2, f=lambda *a: gain * example4_f(*a), name="example 4")
    else:
        raise ValueError(f"unknown example {example}; the paper has examples 1-4")
    plant.kernel = ExampleKernel(example, gain, plant.f, plant.g)
    return plant


@dataclass
class MimoPlant:
    """A plant with several inputs and outputs: y(k+1) = F(y(k), u(k)), vectors.

    Same time convention as :class:`Plant` (y(k) is shown, then u(k) acts). One past
    sample of each is the state: the MIMO examples are first order, like their source.
    """

    n_u: int
    n_y: int
    next_output: Callable[[np.ndarray, np.ndarray], np.ndarray]
    name: str = "mimo plant"
    y_past: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.y_past = np.zeros(self.n_y)

    @property
    def output(self) -> np.ndarray:
        """y(k), a copy (the caller may keep it while the plant moves on)."""
        return self.y_past.copy()

    def step(self, u_applied: Sequence[float]) -> np.ndarray:
        """Apply u(k) (noise included) and advance; returns y(k+1)."""
        u = np.asarray(u_applied, dtype=np.float64)
        if u.shape != (self.n_u,):
            raise ValueError(f"{self.name} takes {self.n_u} inputs, got shape {u.shape}")
        self.y_past = np.asarray(self.next_output(self.y_past, u), dtype=np.float64)
        return self.output

    def run(self, u_applied: np.ndarray) -> np.ndarray:
        """Outputs y(0..N) (rows) for inputs u(0..N-1) (rows)."""
        u = np.asarray(u_applied, dtype=np.float64).reshape(-1, self.n_u)
        y = np.empty((len(u) + 1, self.n_y))
        y[0] = self.y_past
        for k in range(len(u)):
            y[k + 1] = self.step(u[k])
        return y


#: The two-input two-output plant of Narendra & Parthasarathy (1990), with its y1
#: feedback damped from 1 to this gain: at 1, y1 follows a random walk while y2 is near 0
#: (it wandered over [-9, 4.6] in 20 000 samples of U[-1, 1]); at 0.5 the eq. 11 test
#: input keeps both outputs about inside the range the uniform training input covers
#: (|y1| <= 2.0 against 1.8, |y2| <= 1.1 against 1.5), and each output still depends
#: strongly on the other (README: MIMO)
NARENDRA_MIMO_GAIN = 0.5


def narendra_mimo_plant(gain: float = NARENDRA_MIMO_GAIN) -> MimoPlant:
    """y1(k+1) = g y1/(1 + y2^2) + u1, y2(k+1) = g y1 y2/(1 + y2^2) + u2 (all at k).

    Each output depends on the other output: a model per output that sees only its
    own past and input cannot capture that, the MIMO model (every output's lags) can.
    """
    gain = float(gain)

    def next_output(y: np.ndarray, u: np.ndarray) -> np.ndarray:
        y1, y2 = float(y[0]), float(y[1])
        shared = y1 / (1.0 + y2 * y2)
        return np.array([gain * shared + float(u[0]), gain * shared * y2 + float(u[1])])

    return MimoPlant(2, 2, next_output, name=f"narendra 2x2 (gain {gain:g})")


MIMO_PLANTS = {"narendra2x2": narendra_mimo_plant}
