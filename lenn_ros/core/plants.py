"""Plants: the four model classes of Narendra & Parthasarathy and the paper's examples.

A plant is a difference equation y(k+1) = F(y(k..k-n+1), u(k..k-m+1)). The four
classes differ in which part is nonlinear and which is a known linear combination:

- Model 1: y(k+1) = sum a_i y(k-i) + g[u(k..k-m+1)]
- Model 2: y(k+1) = f[y(k..k-n+1)] + sum b_i u(k-i)
- Model 3: y(k+1) = f[y(k..k-n+1)] + g[u(k..k-m+1)]
- Model 4: y(k+1) = f[y(k..k-n+1), u(k..k-m+1)]

The nonlinear parts are Python callables; user-defined ones come from
:mod:`lenn_ros.core.expression` (never ``eval``). Time convention used everywhere in
the package: at step k the plant *shows* y(k), then the input u(k) is applied (plus
noise) and the plant moves to y(k+1).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from lenn_ros.core.expression import compile_expression

Function = Callable[..., float]


@dataclass
class Plant:
    """A SISO discrete-time plant with its past outputs and inputs as state.

    ``model`` is the class (1-4); ``a`` / ``b`` the known linear coefficients
    (Model 1 / Model 2); ``f`` takes the n past outputs, ``g`` the m past inputs
    (Model 4's ``f`` takes the outputs then the inputs).
    """

    model: int
    n: int
    m: int
    f: Function | None = None
    g: Function | None = None
    a: Sequence[float] = ()
    b: Sequence[float] = ()
    name: str = "plant"
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

    def run(self, u_applied: np.ndarray) -> np.ndarray:
        """Outputs y(0..N) for inputs u(0..N-1): y[k] is shown before u[k] acts."""
        y = np.empty(len(u_applied) + 1)
        y[0] = self.output
        for k, u in enumerate(np.asarray(u_applied, dtype=np.float64).tolist()):
            y[k + 1] = self.step(u)
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
    f_fn = compile_expression(f, ys + us if model == 4 else ys) if f else None
    g_fn = compile_expression(g, us) if g else None
    return Plant(model=model, n=n, m=m, f=f_fn, g=g_fn, a=tuple(a), b=tuple(b), name="user-defined")


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


def example_plant(example: int, gain: float = 1.0, linear: Sequence[float] | None = None) -> Plant:
    """Plant of the paper's Example 1-4.

    ``gain`` multiplies the unknown nonlinear part and ``linear`` replaces the known
    coefficients (Ex. 1's 0.3 / 0.6): both exist to make a plant *change* mid-run,
    the tracking scenario; the defaults are the paper's plants.
    """
    if example == 1:
        return Plant(1, 2, 1, g=lambda u: gain * example1_g(u), a=tuple(linear or (0.3, 0.6)), name="example 1")
    if example == 2:
        return Plant(2, 2, 1, f=lambda y1, y2: gain * example2_f(y1, y2), b=tuple(linear or (1.0,)), name="example 2")
    if example == 3:
        return Plant(3, 1, 1, f=example3_f, g=lambda u: gain * example3_g(u), name="example 3")
    if example == 4:
        return Plant(4, 3, 2, f=lambda *a: gain * example4_f(*a), name="example 4")
    raise ValueError(f"unknown example {example}; the paper has examples 1-4")
