"""Model families ``lenn-ros fit`` chooses among: the dictionaries of terms it selects from.

Every family is a functional link (fixed features, weights linear), so each is one
:class:`~lenn_ros.fit.selection.TermModel`: the identifier node runs and adapts any of
them by RLS with the same compiled step. What they offer:

- ``polynomial``: Legendre polynomials of the lags and their products up to a degree
  (degree 1 is a linear ARX): smooth nonlinearities such as a hardening spring.
- ``hinge``: the linear terms plus hinges relu(x - c) of the most recent output and
  input at knots on their training quantiles: saturation, overflow, dead zones and
  absolute values (|x - c| is a combination of a hinge and the linear terms) are
  piecewise linear, which no low-degree polynomial follows.
- ``rff``: the linear terms plus random Fourier features cos(w . x + b) of the recent
  lags, w drawn with the spread of the training regressors (the median-distance rule):
  a smooth nonlinearity of several lags at once, the feature map of a GP-NARX's
  squared-exponential kernel, of which FROLS keeps the few that matter.
- ``index``: the linear terms plus hinges relu(z - c) of one index z = h . (the inputs'
  lags), a filtered input, at its three newest lags and at knots on its training
  quantiles. A static map between two filters (Wiener-Hammerstein: an amplifier stage,
  a sensor or an actuator that saturates) acts on the first filter's output, a
  combination of many input lags that no term of a few lags holds; h is found from the
  record (:func:`index_direction`: Gauss-Newton on the one-step residual, the rest
  least squares). The hinges read no output, so the model is as stable in free run as
  its linear part.
- ``increment``: the model predicts the change y(k+1) - y(k) from the increments of the
  output, the inputs and, from degree 2, friction-like functions of the velocity:
  tanh (Coulomb friction), |v| and v|v| (drag), and stiction: tanh(a v + b d), friction
  that opposes the motion when moving and the net drive d at rest (where a tanh of the
  velocity is 0 and the model would creep); degree 3 adds
  polynomials of the position (gravity, a spring) and of the input. A plant that
  integrates (a motor position driven by a torque) keeps its integrator exactly
  instead of a least-squares estimate of it that drifts. For lag spans beyond 10
  samples (a record sampled far faster than its dynamics, such as a 1 kHz robot) the
  increments are taken over spans 1, 2, 4, ... and the input averaged over them
  (multi-scale), so a long memory costs a few terms, not one per sample.
- ``stick``: the increment form's linear terms and the dead zone of the friction-free
  next increment, relu(p - c) and relu(-p - c) at knots c around the Coulomb step: a
  body with Coulomb friction moves on by what drives it beyond the friction and stops
  exactly, within one sample, where that is less. This is the exact sampled form of
  Coulomb friction with sticking, which smooth terms of the velocity only approach (a
  tanh of it creeps where the body sticks). The direction p and the step come from the
  training record (:func:`_dead_zone_terms`). Least squares fits the stick threshold
  badly when the measured velocity at rest is noise (a 1 kHz encoder): its weights are a
  start that the refinement on simulation error takes further than other families'
  (``refinement.FAR_ITERATIONS``).
- ``legendre``: the paper's LeNN expansion, P_1..P_15 of every lag alone (no products):
  a static nonlinearity with several turns (the paper's example 1, sin(5 pi u)), which
  no product of low degrees follows.
- ``fir``: the output from the inputs alone, no output fed back: the newest input lags and
  the inputs averaged over spans 16, 32, 64 up to the lags; degree 2 adds tanh, v|v| and
  dead-zones (relu beyond one spread) of the averages over FIR_SPANS. Where one-step least
  squares sets the feedback of a model's own past wrong (a robot arm's angles, whose
  velocity follows the torque: the fitted poles sit on or outside the unit circle and
  every free run drifts), a model that cannot run away simulates best; the blocks decide.

The term parameters (knots, velocity scales) come from the training inputs and are
rounded to six significant digits, which is how ``format_terms`` writes them: the
params file holds the very terms the weights were fitted with.

A dictionary is built over one output's view (:class:`~lenn_ros.fit.selection.Layout`):
column 0 is the output, the other columns what it reads (one input u, or several). Its
width is columns x lags, so the families serve one input or several alike: what they do
with "the input" they do with every column after the output. With more than one input,
the products of the nonlinear families involve fewer lags of each input
(:func:`_recent`), so a six-input record's dictionary stays a few hundred terms.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lenn_ros.core.expansions import FACTOR_KINDS, dictionary_exponents


class OutputScaling(Protocol):
    """What the increment form's pass-through needs of a view's scaling (a :class:`~lenn_ros.fit.selection.Layout`)."""

    @property
    def y_offset(self) -> float: ...

    @property
    def y_scale(self) -> float: ...


#: lags (equal for y and u) tried per family, and the degrees
POLYNOMIAL_LAGS = (1, 2, 3, 4, 6, 8, 10)
HINGE_LAGS = (1, 2, 4, 8)
RFF_LAGS = (2, 4)
#: random Fourier features offered, and the seed they are drawn with (fixed: a fit is repeatable)
RFF_FEATURES = 60
RFF_SEED = 0
#: the ``index`` family: lags tried, how many newest lags of the index its hinges read, their knots (quantiles
#: of the index over the training rows), and the Gauss-Newton iterations that find its direction
INDEX_LAGS = (17, 33)
INDEX_SHIFTS = 3
INDEX_KNOTS = (0.05, 0.2, 0.35, 0.5, 0.65, 0.8, 0.95)
INDEX_ITERATIONS = 60
#: rows of the view the direction is searched on (evenly spread; a direction needs far fewer than 40 000), and
#: the relative fall in the residual below which the search stops
INDEX_ROWS = 2000
INDEX_TOLERANCE = 1e-5
INCREMENT_LAGS = (2, 3, 4, 6, 10)
#: lags of the ``stick`` family, and the dead zone's knots in units of the Coulomb step it estimates
STICK_LAGS = (3, 4)
STICK_KNOTS = (0.5, 1.0, 2.0)
#: increment-form families: the target is y(k+1) - y(k), y(k) passed through
INCREMENT_FAMILIES = ("increment", "stick")
#: long lag spans (multi-scale increments) for records sampled far faster than their dynamics
LONG_SPANS = (17, 33, 65)
#: input-only models: lags tried (the longer with averages of the inputs over spans up to it)
FIR_LAGS = (10, 65)
#: newest input lags an input-only model reads one by one; spans of the averages its nonlinear terms take
FIR_RECENT = 10
FIR_SPANS = (8, 32, 64)
#: the paper's expansion: Legendre polynomials of each lag alone, up to a high degree (no products)
LEGENDRE_LAGS = (1, 2, 4)
LEGENDRE_DEGREES = (15,)
#: training quantiles at which the hinges' knots sit
KNOT_QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9)
#: sharpness of the tanh velocity terms, in units of the velocity's standard deviation
VELOCITY_SHARPNESS = (3.0, 10.0, 30.0)
#: nonlinear terms involve the 3 most recent lags of each signal (the usual home of a static nonlinearity)
RECENT = 3
#: a candidate needs this many samples per lag of each column of the view
SAMPLES_PER_LAG = 20


def _round6(value: float) -> float:
    return float(f"{value:.6g}")


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
    def increment(self) -> bool:
        return self.family in INCREMENT_FAMILIES

    def as_dict(self) -> dict:
        return {
            "family": self.family,
            "y_lags": self.lags,
            "u_lags": self.lags,
            "degree": self.degree,
            "form": "increment: y(k+1) = y(k) + f(...)" if self.increment else "y(k+1) = f(...)",
            "multi_scale": self.family == "increment" and self.lags > max(INCREMENT_LAGS),
        }

    def dictionary(self, x: np.ndarray) -> Dictionary:
        """The terms this candidate offers, their parameters taken from the training inputs ``x``."""
        builder = {"polynomial": _polynomial, "hinge": _hinge, "rff": _fourier, "increment": _increment,
                   "stick": _stick, "fir": _input_only, "legendre": _legendre,
                   "index": _index}[self.family]  # fmt: skip
        return builder(self, np.asarray(x, dtype=np.float64))


#: the grid: (family, lags tried, degrees at each)
GRID = (
    ("polynomial", POLYNOMIAL_LAGS, (1, 2, 3)),
    ("hinge", HINGE_LAGS, (2,)),
    ("rff", RFF_LAGS, (2,)),
    ("index", INDEX_LAGS, (2,)),
    ("increment", INCREMENT_LAGS, (1, 2, 3)),
    ("increment", LONG_SPANS, (1, 3)),
    ("stick", STICK_LAGS, (2,)),
    ("fir", FIR_LAGS, (1, 2)),
    ("legendre", LEGENDRE_LAGS, LEGENDRE_DEGREES),
)


def candidate_specs(n_samples: int, n_columns: int = 2) -> list[Spec]:
    """The grid, bounded by how much data there is (SAMPLES_PER_LAG samples per lag of each of the view's
    ``n_columns`` columns: the output and what it reads)."""
    return [
        Spec(family, lags, degree)
        for family, lag_set, degrees in GRID
        for lags in lag_set
        if SAMPLES_PER_LAG * n_columns * lags <= n_samples
        for degree in degrees
    ]


@dataclass
class Dictionary:
    """Candidate terms: exponent rows, factor rows, and whether the target is the increment."""

    exponents: np.ndarray
    factors: np.ndarray
    increment: bool = False

    def pass_through(self, x: np.ndarray, scaling: OutputScaling) -> np.ndarray:
        """The part of the target the terms need not explain: y(k) in the increment form, else 0."""
        if not self.increment:
            return np.zeros(len(x))
        return x[:, 0] * scaling.y_scale + scaling.y_offset

    def with_pass_through(
        self, chosen: list[int], weights: np.ndarray, scaling: OutputScaling
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(exponents, factors, weights) of the chosen terms; in the increment form plus y(k) itself.

        y(k) = y_scale * x_1 + y_offset, i.e. weight y_scale on the term ``y1`` and
        y_offset on the bias, added to those terms' weights (appended if not chosen).
        """
        exponents = self.exponents[chosen]
        factors = self.factors[chosen]
        weights = np.array(weights, dtype=np.float64)
        if not self.increment:
            return exponents, factors, weights
        n = exponents.shape[1]
        for row in _pass_through_rows(n):
            if not len(_matching(exponents, factors, row)):
                exponents = np.vstack([exponents, row])
                factors = np.vstack([factors, np.zeros(n + 2)])
                weights = np.append(weights, 0.0)
        return exponents, factors, weights + pass_through_weights(exponents, factors, scaling)


def _pass_through_rows(n: int) -> list[np.ndarray]:
    """Exponent rows of the bias and of ``y1`` (P1 of the scaled y(k): x_1 itself)."""
    bias, first = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    first[0] = 1
    return [bias, first]


def _matching(exponents: np.ndarray, factors: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Indices of the terms that are exactly ``row`` with no factor."""
    plain = factors[:, 0] == 0 if len(factors) else np.ones(len(exponents), dtype=bool)
    return np.flatnonzero((exponents == row).all(axis=1) & plain)


def pass_through_weights(
    exponents: np.ndarray, factors: np.ndarray, scaling: OutputScaling, with_offset: bool = True
) -> np.ndarray:
    """Weights that make the terms compute y(k) = y_scale x_1 + y_offset (the bias part only ``with_offset``).

    The increment form's given part, in the basis the node runs: the terms must hold
    ``y1`` (and the bias, for the offset) without factors.
    """
    weights = np.zeros(len(exponents))
    bias, first = _pass_through_rows(exponents.shape[1])
    for row, value in ((first, scaling.y_scale), (bias, scaling.y_offset if with_offset else 0.0)):
        match = _matching(exponents, factors, row)
        if not len(match):
            raise ValueError("the increment form needs the terms y1 and 1")
        weights[match[0]] += value
    return weights


class _Builder:
    """Rows of a dictionary under construction, over ``n`` network inputs."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.exponents: list[list[int]] = []
        self.factors: list[np.ndarray] = []

    def add(self, exponents: list[int] | np.ndarray | None = None, kind: str = "", w=None, b: float = 0.0) -> None:
        row = np.zeros(self.n, dtype=np.int64) if exponents is None else np.asarray(exponents, dtype=np.int64)
        factor = np.zeros(self.n + 2)
        if kind:
            factor[0] = FACTOR_KINDS[kind]
            factor[1] = _round6(b)
            used = np.flatnonzero(w)  # a long view's weight rows are mostly zeros
            factor[2 + used] = [_round6(float(w[i])) for i in used]
        self.exponents.append(row.tolist())
        self.factors.append(factor)

    def power(self, i: int, degree: int) -> list[int]:
        row = [0] * self.n
        row[i] = degree
        return row

    def unit(self, i: int) -> np.ndarray:
        return np.eye(self.n)[i]

    def build(self, increment: bool = False) -> Dictionary:
        exponents = np.array(self.exponents, dtype=np.int64).reshape(len(self.exponents), self.n)
        return Dictionary(exponents, np.array(self.factors).reshape(len(self.factors), self.n + 2), increment)


def _columns(spec: Spec, x: np.ndarray) -> int:
    """Columns of the view the dictionary is built over: the output and what it reads."""
    return x.shape[1] // spec.lags


def _recent(spec: Spec, columns: int) -> list[int]:
    """Network inputs the nonlinear terms involve: the RECENT most recent lags of the output, then of each
    column it reads (fewer of each when it reads several: RECENT shared among them, at least one)."""
    own = min(spec.lags, RECENT)
    each = own if columns <= 2 else min(spec.lags, max(1, RECENT // (columns - 1)))
    return list(range(own)) + [c * spec.lags + i for c in range(1, columns) for i in range(each)]


def _polynomial(spec: Spec, x: np.ndarray) -> Dictionary:
    n = x.shape[1]
    rows = dictionary_exponents(n, spec.degree, _recent(spec, _columns(spec, x)))
    return Dictionary(rows, np.zeros((len(rows), n + 2)))


def _legendre(spec: Spec, x: np.ndarray) -> Dictionary:
    """The bias and P_1..P_degree of every lag of every column, each alone: the paper's LeNN expansion. A
    static nonlinearity with several turns (sin(5 pi u)) needs a degree no product of low degrees reaches."""
    built = _Builder(x.shape[1])
    built.add()
    for degree in range(1, spec.degree + 1):
        for i in range(x.shape[1]):
            built.add(built.power(i, degree))
    return built.build()


def _hinge(spec: Spec, x: np.ndarray) -> Dictionary:
    """Linear terms, the recent lags' squares and products (degree 2), and hinges of each column's newest
    sample (and the lag before)."""
    columns, lags = _columns(spec, x), spec.lags
    built = _Builder(x.shape[1])
    for row in dictionary_exponents(x.shape[1], spec.degree, _recent(spec, columns)):
        built.add(row)
    newest = [c * lags for c in range(columns)]
    for i in newest + ([i + 1 for i in newest] if lags > 1 else []):
        for knot in np.unique([_round6(q) for q in np.quantile(x[:, i], KNOT_QUANTILES)]):
            built.add(None, "relu", built.unit(i), -knot)
    return built.build()


def _fourier(spec: Spec, x: np.ndarray) -> Dictionary:
    """Linear terms and RFF_FEATURES cos(w . x_recent + b), w ~ N(0, 1 / l^2), l the regressors' median distance."""
    n = x.shape[1]
    built = _Builder(n)
    for row in dictionary_exponents(n, 1):
        built.add(row)
    recent = _recent(spec, _columns(spec, x))
    rng = np.random.default_rng(RFF_SEED)
    sample = x[rng.choice(len(x), min(len(x), 400), replace=False)][:, recent]
    distances = np.sqrt(((sample[:, None, :] - sample[None, :, :]) ** 2).sum(axis=-1))
    length = float(np.median(distances[distances > 0])) if np.any(distances > 0) else 1.0
    for _ in range(RFF_FEATURES):
        w = np.zeros(n)
        w[recent] = rng.normal(0.0, 1.0 / length, len(recent))
        built.add(None, "cos", w, float(rng.uniform(0.0, 2.0 * np.pi)))
    return built.build()


def _index(spec: Spec, x: np.ndarray) -> Dictionary:
    """Linear terms of every lag and hinges relu(z_j - c) of one index z, a filtered input (:func:`index_direction`),
    at its INDEX_SHIFTS newest lags j and INDEX_KNOTS quantiles c."""
    n = x.shape[1]
    built = _Builder(n)
    for row in dictionary_exponents(n, 1):
        built.add(row)
    found = index_direction(x, spec.lags)
    if found is None:
        return built.build()
    columns, h, middle, spread, knots = found
    for j in range(INDEX_SHIFTS):
        w = np.zeros(n)
        w[columns + j] = h / spread
        for knot in knots:
            built.add(None, "relu", w, -(middle / spread + knot))
    return built.build()


def index_direction(x: np.ndarray, lags: int) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray] | None:
    """The filtered input a static map acts on: z(k) = h . (the inputs' lags), h found from the record.

    A static map between two filters (Wiener-Hammerstein: an amplifier stage, a sensor with a
    saturation) acts on the first filter's output, a combination of many input lags that no
    term of a few lags holds. Within each row of the view, the newest output lag is regressed
    on the older ones (the model's own problem one sample earlier): on the output's RECENT + 1
    lags before it, the inputs' as many, and hinges of z at its INDEX_SHIFTS lags. The hinges'
    knots sit at quantiles of z, so for a given h the rest is least squares, and h follows by
    Gauss-Newton on that residual (variable projection), from the least-squares FIR of the
    inputs' window. Returns (the window's columns at shift 0, h, z's middle and spread over the
    rows, the knots in units of the spread), or None where the view is too short or flat.
    """
    n = x.shape[1]
    columns_read, taps = n // lags, lags - INDEX_SHIFTS
    if columns_read < 2 or taps < 2 or len(x) < 10 * n:
        return None
    problem = _IndexProblem(x[:: -(-len(x) // INDEX_ROWS)], lags, taps)  # at most INDEX_ROWS rows, evenly spread
    start = np.column_stack([np.ones(len(problem.target)), problem.shifted[0]])
    found = problem.solve(np.linalg.lstsq(start, problem.target, rcond=None)[0][1:])
    if found is None:
        return None
    found = _gauss_newton(problem, found)
    # the model's own z reads the window one sample later than the sub-problem: columns `window`, not `window + 1`
    return problem.window, found.h, found.middle, found.spread, np.array([_round6(k) for k in found.knots])


@dataclass
class _IndexFit:
    """One direction h and what least squares makes of it."""

    h: np.ndarray
    cost: float
    theta: np.ndarray
    residual: np.ndarray
    zs: list[np.ndarray]
    knots: np.ndarray
    middle: float
    spread: float


class _IndexProblem:
    """The sub-problem :func:`index_direction` solves over the rows of a view."""

    def __init__(self, x: np.ndarray, lags: int, taps: int) -> None:
        columns_read = x.shape[1] // lags
        self.window = np.array([c * lags + i for c in range(1, columns_read) for i in range(taps)])
        own = min(RECENT + 1, lags - 1)
        read = [x[:, c * lags + 1 : c * lags + 1 + own] for c in range(1, columns_read)]
        self.fixed = np.column_stack([np.ones(len(x)), x[:, 1 : 1 + own], *read])
        self.target = x[:, 0]
        self.shifted = [x[:, self.window + 1 + j] for j in range(INDEX_SHIFTS)]  # z at lag j, one sample back

    def solve(self, h: np.ndarray) -> _IndexFit | None:
        """Knots at z's quantiles, the rest by least squares; None where z is flat."""
        z0 = self.shifted[0] @ h
        middle, spread = float(np.mean(z0)), float(np.std(z0))
        if not spread > 0.0:
            return None
        knots = np.quantile((z0 - middle) / spread, INDEX_KNOTS)
        zs = [(block @ h - middle) / spread for block in self.shifted]
        features = np.column_stack([self.fixed, *(np.maximum(z[:, None] - knots[None, :], 0.0) for z in zs)])
        theta = np.linalg.lstsq(features, self.target, rcond=None)[0]
        residual = features @ theta - self.target
        return _IndexFit(h, float(residual @ residual), theta, residual, zs, knots, middle, spread)

    def slope(self, found: _IndexFit) -> np.ndarray:
        """d residual / d h, the knots and the least-squares weights held."""
        slope = np.zeros((len(self.target), len(found.h)))
        first, width = self.fixed.shape[1], len(found.knots)
        for j, z in enumerate(found.zs):
            weights = found.theta[first + j * width : first + (j + 1) * width]
            dz = (z[:, None] > found.knots[None, :]) @ weights
            slope += (dz / found.spread)[:, None] * self.shifted[j]
        return slope


def _gauss_newton(problem: _IndexProblem, found: _IndexFit) -> _IndexFit:
    """Damped Gauss-Newton steps on h while they lower the residual (INDEX_ITERATIONS at most)."""
    damping = 1e-3
    slope = problem.slope(found)
    gram, gradient = slope.T @ slope, slope.T @ found.residual  # of the current h: a refused step keeps them
    for _ in range(INDEX_ITERATIONS):
        ridge = damping * (np.trace(gram) / len(found.h)) * np.eye(len(found.h))
        trial = problem.solve(found.h + np.linalg.solve(gram + ridge, -gradient))
        if trial is None or trial.cost >= found.cost:
            damping *= 4.0
            if damping > 1e6:
                break
            continue
        converged = found.cost - trial.cost < INDEX_TOLERANCE * found.cost
        found, damping = trial, damping * 0.5
        if converged:
            break
        slope = problem.slope(found)
        gram, gradient = slope.T @ slope, slope.T @ found.residual
    return found


def _velocity_terms(built: _Builder, x: np.ndarray, span: int) -> None:
    """tanh at three sharpnesses, |v| and v|v| of v = (x_1 - x_{1+span}) / span, scaled to unit spread."""
    difference = (x[:, 0] - x[:, span]) / span
    spread = float(np.std(difference)) or 1.0
    direction = (built.unit(0) - built.unit(span)) / span / spread
    for sharpness in VELOCITY_SHARPNESS:
        built.add(None, "tanh", direction * sharpness)
    built.add(None, "abs", direction)
    built.add(None, "sqabs", direction)


#: how sharply the stiction terms saturate in the net drive, in units of its spread
DRIVE_SHARPNESS = (1.0, 3.0, 10.0)


def _stiction_terms(built: _Builder, x: np.ndarray, read: list[int], span: int) -> None:
    """tanh(a v + b d): friction that opposes the motion v when moving and the net drive d at rest.

    At rest a joint's friction cancels the net drive up to the stiction, which a tanh of
    the velocity alone cannot (it is 0 at rest: the model creeps where the joint sticks).
    The net drive's direction, d = c0 + c . (the inputs' newest samples, the output), comes
    from the training record's own lags: the acceleration over ``span`` samples,
    (y1 - y_{1+s}) - (y_{1+s} - y_{1+2s}), regressed on what drove it (each input's sample
    s lags back, y_{1+s}) and the velocity before it. v is the velocity over the span.
    """
    acceleration = x[:, 0] - 2.0 * x[:, span] + x[:, 2 * span]
    before = x[:, span] - x[:, 2 * span]
    drivers = np.column_stack([np.ones(len(x)), *(x[:, start + span] for start in read), x[:, span], before])
    coefficients = np.linalg.lstsq(drivers, acceleration, rcond=None)[0]
    w = np.zeros(built.n)
    for start, c in zip(read, coefficients[1:-2], strict=True):
        w[start] = c
    w[0] = coefficients[-2]
    drive_spread = float(np.std(x @ w + coefficients[0])) or 1.0
    velocity_spread = float(np.std(x[:, 0] - x[:, span])) or 1.0
    direction = (built.unit(0) - built.unit(span)) / velocity_spread
    for sharpness in VELOCITY_SHARPNESS:
        for drive_sharpness in DRIVE_SHARPNESS:
            built.add(None, "tanh", direction * sharpness + w * drive_sharpness / drive_spread,
                      coefficients[0] * drive_sharpness / drive_spread)  # fmt: skip


def _linear_increments(spec: Spec, x: np.ndarray) -> tuple[_Builder, list[int], list[int]]:
    """The increment form's linear part: the bias, the output's increments and every column read (multi-scale
    beyond INCREMENT_LAGS). Returns (the terms so far, where each column read starts, the increments' spans)."""
    lags = spec.lags
    read = [c * lags for c in range(1, _columns(spec, x))]  # where each column read besides the output starts
    built = _Builder(x.shape[1])
    built.add()  # the bias: a constant force (gravity at rest, an offset)
    multi_scale = lags > max(INCREMENT_LAGS)
    spans = [s for s in (1, 2, 4, 8, 16, 32, 64, 128) if s < lags] if multi_scale else list(range(1, lags))
    for s in spans:
        # multi-scale: y(k) - y(k-s); else consecutive increments y(k-j+1) - y(k-j)
        first = 0 if multi_scale else s - 1
        built.add(None, "lin", built.unit(first) - built.unit(s))
    for start in read:
        _input_terms(built, start, lags, multi_scale)
    return built, read, spans


def _increment(spec: Spec, x: np.ndarray) -> Dictionary:
    """y(k+1) - y(k) from output increments, inputs, and (degree >= 2) velocity and position nonlinearities."""
    lags = spec.lags
    built, read, spans = _linear_increments(spec, x)
    if spec.degree >= 2 and lags >= 2:
        velocity_spans = sorted({1, spans[len(spans) // 2], spans[-1]})
        for span in velocity_spans:
            _velocity_terms(built, x, span)
            if 2 * span < lags:
                _stiction_terms(built, x, read, span)
        for start in read:
            built.add(built.power(start, 2))
    if spec.degree >= 3:
        for degree in (1, 2, 3):
            built.add(built.power(0, degree))
        for start in read:
            built.add(built.power(start, 3))
    return built.build(increment=True)


def _stick(spec: Spec, x: np.ndarray) -> Dictionary:
    """y(k+1) - y(k) from the bias, the output increments, the inputs, and the dead zone of the friction-free
    next increment (:func:`_dead_zone_terms`)."""
    built, read, _ = _linear_increments(spec, x)
    _dead_zone_terms(built, x, read)
    return built.build(increment=True)


#: samples whose increment is beyond this share of the increments' spread count as moving
MOVING = 0.1


def _dead_zone_terms(built: _Builder, x: np.ndarray, read: list[int]) -> None:
    """relu(p - c), relu(-p - c): the dead zone of p, the next increment as it would be without Coulomb friction.

    From the training record's own lags: the increment v = y(k) - y(k-1) is regressed,
    over the samples moving before it, on the increment before it, each input one lag
    back, a sign of that increment (tanh, sharp: the Coulomb friction) and a bias. The
    friction-free next increment is p = a v + sum b_i u_i(k) + bias, and the sign's
    weight is the Coulomb step c. Sampled Coulomb friction is then exactly: the body
    moves on by p less c beyond the dead zone [-c, c] and stands still within it. The
    knots are STICK_KNOTS times c (the estimate is rough; the refinement sets the weights).
    """
    now, before = x[:, 0] - x[:, 1], x[:, 1] - x[:, 2]
    spread = float(np.std(before))
    moving = np.abs(before) > MOVING * spread
    regressors = np.column_stack(
        [before, *(x[:, start + 1] for start in read), np.tanh(before / (0.05 * spread or 1.0)), np.ones(len(x))]
    )
    if spread == 0.0 or np.count_nonzero(moving) < 10 * regressors.shape[1]:
        return
    c = np.linalg.lstsq(regressors[moving], now[moving], rcond=None)[0]
    step = abs(float(c[-2]))
    if not step > 0.0:
        return
    w = np.zeros(built.n)
    w[0], w[1] = c[0], -c[0]
    for start, b in zip(read, c[1:-2], strict=True):
        w[start] = b
    for knot in STICK_KNOTS:
        built.add(None, "relu", w, float(c[-1]) - knot * step)
        built.add(None, "relu", -w, -float(c[-1]) - knot * step)


def _input_terms(built: _Builder, start: int, lags: int, multi_scale: bool) -> None:
    """The linear terms of one column read (its lags at ``start``..): every lag, or multi-scale averages
    over spans 1, 2, 4, ... and the RECENT newest lags after the first."""
    if not multi_scale:
        for j in range(lags):
            built.add(built.power(start + j, 1))
        return
    for s in [1] + [s for s in (2, 4, 8, 16, 32, 64, 128) if s <= lags]:
        w = np.zeros(built.n)
        w[start : start + s] = 1.0 / s
        built.add(None, "lin", w)
    for j in range(1, min(lags, RECENT)):
        built.add(built.power(start + j, 1))


def _input_only(spec: Spec, x: np.ndarray) -> Dictionary:
    """The output from the columns read alone (none of its own lags): their FIR_RECENT newest lags, their
    averages over longer spans, and (degree 2) tanh, v|v| and dead-zones of their averages over FIR_SPANS."""
    lags = spec.lags
    built = _Builder(x.shape[1])
    built.add()  # the bias
    read = [c * lags for c in range(1, _columns(spec, x))]
    for start in read:
        for j in range(min(lags, FIR_RECENT)):
            built.add(built.power(start + j, 1))
        for s in (16, 32, 64, 128):
            if FIR_RECENT < s <= lags:
                w = np.zeros(x.shape[1])
                w[start : start + s] = 1.0 / s
                built.add(None, "lin", w)
    if spec.degree >= 2:
        for start in read:
            for s in FIR_SPANS:
                if s <= lags:
                    _average_terms(built, x, start, s)
    return built.build()


def _average_terms(built: _Builder, x: np.ndarray, start: int, span: int) -> None:
    """tanh(z), z|z| and the dead-zones relu(z - 1), relu(-z - 1) of z, the average of one column over its
    ``span`` newest lags scaled to unit spread."""
    w = np.zeros(x.shape[1])
    w[start : start + span] = 1.0 / span
    # over the span's own columns: the whole row of a 65-lag view is 455 inputs, a pass over all of them each time
    spread = float(np.std(x[:, start : start + span] @ w[start : start + span])) or 1.0
    w /= spread
    built.add(None, "tanh", w)
    built.add(None, "sqabs", w)
    built.add(None, "relu", w, -1.0)
    built.add(None, "relu", -w, -1.0)
