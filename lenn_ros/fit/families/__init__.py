"""Model families ``lenn-ros fit`` chooses among: the dictionaries of terms it selects from, one module each.

Every family is a functional link (fixed features, weights linear), so each is one
:class:`~lenn_ros.fit.termmodel.TermModel`: the identifier node runs and adapts any of
them by RLS with the same compiled step. What they offer (each module says more):

- ``polynomial``: Legendre polynomials of the lags and their products up to a degree
  (degree 1 is a linear ARX): smooth nonlinearities such as a hardening spring.
- ``hinge``: the linear terms plus hinges relu(x - c) of the most recent output and
  input at knots on their training quantiles: saturation, overflow, dead zones and
  absolute values, which no low-degree polynomial follows.
- ``rff``: the linear terms plus random Fourier features cos(w . x + b) of the recent
  lags: a smooth nonlinearity of several lags at once (a GP-NARX's feature map).
- ``index``: the linear terms plus hinges of one index z = h . (the inputs' lags), a
  filtered input, h found from the record: a static map between two filters
  (Wiener-Hammerstein).
- ``increment``: y(k+1) - y(k) from the increments of the output, the inputs and
  friction-like functions of the velocity: a plant that integrates keeps its integrator
  exactly; multi-scale increments for records sampled far faster than their dynamics.
- ``stick``: the increment form's linear terms and the dead zone of the friction-free
  next increment: the exact sampled form of Coulomb friction with sticking.
- ``legendre``: the paper's LeNN expansion, P_1..P_15 of every lag alone: a static
  nonlinearity with several turns.
- ``fir``: the output from the inputs alone, no output fed back: a model that cannot run
  away, for records where one-step least squares sets the feedback wrong.

The term parameters (knots, velocity scales) come from the training inputs and are
rounded to six significant digits, which is how ``format_terms`` writes them: the
params file holds the very terms the weights were fitted with.

A dictionary is built over one output's view (:class:`~lenn_ros.fit.termmodel.Layout`):
column 0 is the output, the other columns what it reads (one input u, or several). Its
width is columns x lags, so the families serve one input or several alike: what they do
with "the input" they do with every column after the output. With more than one input,
the products of the nonlinear families involve fewer lags of each input
(:func:`~lenn_ros.fit.families.base.recent_inputs`), so a six-input record's dictionary
stays a few hundred terms.

A family is a plug-in: a module with a ``dictionary(spec, x)`` builder (made of the pieces
of :mod:`.base`) and its lags, registered by one :class:`Family` entry in :data:`FAMILIES`,
the one place that names them all; the entries' order is the grid's. The rest of ``fit``
asks the registry (through :class:`Spec`) what it needs of a family: whether it is an
increment form or input-only, whether it is offered again with the other outputs' past,
how far its refinement goes, what the report says of its lags.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lenn_ros.fit.families import fir, hinge, increment, index, legendre, polynomial, rff, stick
from lenn_ros.fit.families.base import Dictionary

#: a candidate needs this many samples per lag of each column of the view
SAMPLES_PER_LAG = 20


@dataclass(frozen=True)
class Spec:
    """One candidate structure: a family at some lags and degree."""

    family: str
    lags: int
    degree: int

    @property
    def label(self) -> str:
        return f"{self.family} degree {self.degree}, lags {self.lags}/{self.lags}"

    @property
    def registered(self) -> Family:
        """Its family's entry in :data:`FAMILIES`."""
        return FAMILIES[self.family]

    @property
    def increment(self) -> bool:
        return self.registered.increment

    @property
    def multi_scale(self) -> bool:
        """An increment form over spans 1, 2, 4, ... (:func:`~lenn_ros.fit.families.increment.multi_scale`)."""
        return self.increment and increment.multi_scale(self.lags)

    @property
    def time_scale(self) -> str:
        """What the report says of its lag spans."""
        return self.registered.time_scale(self)

    def as_dict(self) -> dict:
        return {
            "family": self.family,
            "y_lags": self.lags,
            "u_lags": self.lags,
            "degree": self.degree,
            "form": "increment: y(k+1) = y(k) + f(...)" if self.increment else "y(k+1) = f(...)",
            "multi_scale": self.multi_scale,
        }

    def dictionary(self, x: np.ndarray) -> Dictionary:
        """The terms this candidate offers, their parameters taken from the training inputs ``x``."""
        return self.registered.dictionary(self, np.asarray(x, dtype=np.float64))


def at_recorded_rate(spec: Spec) -> str:
    """What the report says of most families' lag spans."""
    return f"lags {spec.lags} samples at the recorded rate"


@dataclass(frozen=True)
class Family:
    """A family as ``fit`` uses it: its builder, its part of the grid, and the ways the procedure treats it apart.

    ``grid``: (lags tried, degrees at each) rows, in the order they are tried. ``increment``:
    the target is y(k+1) - y(k), y(k) passed through. ``input_only``: it reads no output fed
    back, so its least squares already minimise its free-run error and it is never refined.
    ``coupled``: offered again (at its shorter lags) to an output's view with the other
    outputs' past, where a coupling such as y1 / (1 + y2^2) is expressed. ``iterations``:
    most refinement iterations where its least-squares start lies far from its
    simulation-error fit (None: ``refinement.ITERATIONS``). ``time_scale``: what the report
    says of its lag spans.
    """

    dictionary: Callable[[Spec, np.ndarray], Dictionary]
    grid: tuple[tuple[tuple[int, ...], tuple[int, ...]], ...]
    increment: bool = False
    input_only: bool = False
    coupled: bool = False
    iterations: int | None = None
    time_scale: Callable[[Spec], str] = at_recorded_rate


#: every family by name, in the grid's order: a new family is a module with a ``dictionary`` builder and one entry here
FAMILIES: dict[str, Family] = {
    "polynomial": Family(polynomial.dictionary, ((polynomial.POLYNOMIAL_LAGS, (1, 2, 3)),), coupled=True),
    "hinge": Family(hinge.dictionary, ((hinge.HINGE_LAGS, (2,)),)),
    "rff": Family(rff.dictionary, ((rff.RFF_LAGS, (2,)),)),
    "index": Family(index.dictionary, ((index.INDEX_LAGS, (2,)),), time_scale=index.time_scale),
    "increment": Family(
        increment.dictionary,
        ((increment.INCREMENT_LAGS, (1, 2, 3)), (increment.LONG_SPANS, (1, 3))),
        increment=True,
        time_scale=increment.time_scale,
    ),
    "stick": Family(
        stick.dictionary,
        ((stick.STICK_LAGS, (2,)),),
        increment=True,
        iterations=stick.FAR_ITERATIONS,
        time_scale=increment.time_scale,
    ),
    "fir": Family(fir.dictionary, ((fir.FIR_LAGS, (1, 2)),), input_only=True),
    "legendre": Family(legendre.dictionary, ((legendre.LEGENDRE_LAGS, legendre.LEGENDRE_DEGREES),)),
}

#: the longest lag span a candidate reads (the widest view's: what the memory and rest rules plan for)
LONGEST_LAGS = max(lags for family in FAMILIES.values() for lag_set, _ in family.grid for lags in lag_set)


def candidate_specs(n_samples: int, n_columns: int = 2) -> list[Spec]:
    """The grid, bounded by how much data there is (SAMPLES_PER_LAG samples per lag of each of the view's
    ``n_columns`` columns: the output and what it reads)."""
    return [
        Spec(name, lags, degree)
        for name, family in FAMILIES.items()
        for lag_set, degrees in family.grid
        for lags in lag_set
        if SAMPLES_PER_LAG * n_columns * lags <= n_samples
        for degree in degrees
    ]
