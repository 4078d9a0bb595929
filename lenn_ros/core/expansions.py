"""Functional expansions: the one place that turns network inputs into features.

Every functional-link network in the package (the paper's LeNN, and the Chebyshev and
trigonometric relatives it cites) is a linear combiner over one of these feature maps,
so the map is kept separate from the learning rule and vectorised over samples: the
series-parallel training data is known in advance, and expanding 50 000 samples at once
costs less than expanding one sample in a Python loop 50 000 times.

Layout of a feature row (the paper's Fig. 3): one bias term first, then the terms of
input 1 (degree 1..order), then those of input 2, and so on. The paper counts "terms"
without the bias (Ex. 2: two inputs "expanded to 12 terms" is 2 x 6; Table I adds the
bias separately as N0 = n0 + 1), and so does :func:`feature_count`.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from functools import lru_cache
from itertools import combinations_with_replacement

import numpy as np

from lenn_ros.core import batch_kernels, jit, term_kernels

BASES = ("legendre", "chebyshev", "trigonometric")


def _three_term_recursion(x: np.ndarray, order: int, next_term) -> np.ndarray:
    """P_1..P_order from P_0 = 1, P_1 = x and P_{n+1} = next_term(n, x, P_n, P_{n-1})."""
    x = np.asarray(x, dtype=np.float64)
    out = np.empty((*x.shape, order), dtype=np.float64)
    if order == 0:
        return out
    previous, current = np.ones_like(x), x
    out[..., 0] = current
    for n in range(1, order):
        previous, current = current, next_term(n, x, current, previous)
        out[..., n] = current
    return out


def _legendre_next(n, x, p, q):
    """Bonnet: L_{n+1} = ((2n + 1) x L_n - n L_{n-1}) / (n + 1)."""
    return ((2 * n + 1) * x * p - n * q) / (n + 1)


def _chebyshev_next(n, x, p, q):
    """T_{n+1} = 2 x T_n - T_{n-1}."""
    return 2.0 * x * p - q


def legendre_polynomials(x: np.ndarray, order: int) -> np.ndarray:
    """L_1..L_order of every element of ``x`` by Bonnet's recursion (paper eq. 4).

    The recursion is the paper's, and it is stable on [-1, 1], which is why inputs
    must be scaled into that interval before they get here.
    Returns shape ``x.shape + (order,)``.
    """
    return _three_term_recursion(x, order, _legendre_next)


def chebyshev_polynomials(x: np.ndarray, order: int) -> np.ndarray:
    """T_1..T_order by T_{n+1} = 2 x T_n - T_{n-1} (the ChNN the paper cites)."""
    return _three_term_recursion(x, order, _chebyshev_next)


#: The recursions again, for one sample in plain floats: the live identifier expands
#: one sample per message, where a numpy call per order costs more than the learning.
#: The same IEEE operations in the same order give the same bits as the array path
#: (test_core checks step-by-step == batch), so live and offline results still agree.
_SCALAR_RECURSIONS = {"legendre": _legendre_next, "chebyshev": _chebyshev_next}


def _one_sample_univariate(row: list[float], order: int, next_term) -> list[list[float]]:
    terms = []
    for x in row:
        values = [x]
        previous, current = 1.0, x
        for n in range(1, order):
            previous, current = current, next_term(n, x, current, previous)
            values.append(current)
        terms.append(values[:order])
    return terms


def trigonometric_terms(x: np.ndarray, order: int) -> np.ndarray:
    """FLANN's trigonometric expansion: x, sin(pi x), cos(pi x), sin(2 pi x), ...

    The first term is x itself (Patra's FLANN), then sin/cos pairs of increasing
    frequency until ``order`` terms are filled.
    """
    x = np.asarray(x, dtype=np.float64)
    out = np.empty((*x.shape, order), dtype=np.float64)
    if order == 0:
        return out
    out[..., 0] = x
    for n in range(1, order):
        harmonic = (n + 1) // 2
        out[..., n] = np.sin(harmonic * np.pi * x) if n % 2 else np.cos(harmonic * np.pi * x)
    return out


_UNIVARIATE = {
    "legendre": legendre_polynomials,
    "chebyshev": chebyshev_polynomials,
    "trigonometric": trigonometric_terms,
}


@lru_cache(maxsize=64)
def cross_term_exponents(n_inputs: int, degree: int) -> tuple[tuple[int, ...], ...]:
    """Multi-indices of the tensor-product terms of total degree 2..degree.

    Only mixed terms (two or more inputs involved) are listed: the pure powers are
    already in the per-input part of the expansion.
    """
    terms: list[tuple[int, ...]] = []
    for total in range(2, degree + 1):
        for combo in combinations_with_replacement(range(n_inputs), total):
            exponents = tuple(combo.count(i) for i in range(n_inputs))
            if sum(1 for e in exponents if e) >= 2:
                terms.append(exponents)
    return tuple(terms)


def feature_count(n_inputs: int, order: int, cross_degree: int = 0) -> int:
    """Number of expanded terms, not counting the bias (the paper's way of counting)."""
    return n_inputs * order + len(cross_term_exponents(n_inputs, cross_degree))


def expand(
    x: np.ndarray,
    order: int,
    basis: str = "legendre",
    cross_degree: int = 0,
) -> np.ndarray:
    """Bias + per-input expansion (+ optional tensor-product cross terms).

    ``x`` has shape (n_samples, n_inputs) with every element already in [-1, 1].
    Cross terms are products of the univariate polynomials of different inputs
    (e.g. L1(y1) L1(y2)), so a linear combiner can represent f(y1, y2) = y1 y2 ...,
    which the paper's per-input expansion cannot.
    Returns shape (n_samples, 1 + feature_count(...)).
    """
    if basis not in _UNIVARIATE:
        raise ValueError(f"unknown basis {basis!r}; expected one of {', '.join(BASES)}")
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    n_samples, n_inputs = x.shape
    needed = max(order, cross_degree - 1 if cross_degree else 0)
    crosses = cross_term_exponents(n_inputs, cross_degree)
    if n_samples == 1 and basis in _SCALAR_RECURSIONS and needed:
        return _one_sample_expansion(x[0].tolist(), order, needed, crosses, _SCALAR_RECURSIONS[basis])
    univariate = _UNIVARIATE[basis](x, needed)  # (n_samples, n_inputs, needed)
    features = np.empty((n_samples, 1 + n_inputs * order + len(crosses)))
    features[:, 0] = 1.0
    features[:, 1 : 1 + n_inputs * order] = univariate[:, :, :order].reshape(n_samples, -1)
    column = 1 + n_inputs * order
    for exponents in crosses:
        product = np.ones(n_samples)
        for i, e in enumerate(exponents):
            if e:
                product = product * univariate[:, i, e - 1]
        features[:, column] = product
        column += 1
    return features


def _one_sample_expansion(
    row: list[float], order: int, needed: int, crosses: tuple[tuple[int, ...], ...], next_term
) -> np.ndarray:
    """:func:`expand` of one sample in plain floats: the live identifier's path (a MIMO output's
    model has tens of cross terms, and a numpy call per term cost more than the learning).
    The products are taken in the array path's order, so the bits are the same."""
    univariate = _one_sample_univariate(row, needed, next_term)
    values = [1.0]
    for terms in univariate:
        values += terms[:order]
    for exponents in crosses:
        product = 1.0
        for i, e in enumerate(exponents):
            if e:
                product = product * univariate[i][e - 1]
        values.append(product)
    return np.array([values])


def legendre_features(x: np.ndarray, order: int) -> np.ndarray:
    """The paper's LeNN expansion: bias, then L1..L_order of each input on its own."""
    return expand(x, order, "legendre", 0)


# -- selected terms: any subset of the products of univariate polynomials --------------------
#
# A term is a product prod_i P_{e_i}(x_i) of basis polynomials of the inputs; one row of
# non-negative integers e (an exponent row) names it: all zeros is the bias, a single
# non-zero entry is a per-input term, several are a cross term. Term selection (FROLS)
# keeps a few rows out of a large dictionary, so a selected model is stored as its rows.


def full_exponents(n_inputs: int, order: int, cross_degree: int = 0) -> np.ndarray:
    """Exponent rows of :func:`expand`'s columns, in its order (bias first)."""
    rows = [[0] * n_inputs]
    for i in range(n_inputs):
        for degree in range(1, order + 1):
            row = [0] * n_inputs
            row[i] = degree
            rows.append(row)
    rows += [list(e) for e in cross_term_exponents(n_inputs, cross_degree)]
    return np.array(rows, dtype=np.int64).reshape(len(rows), n_inputs)


def dictionary_exponents(
    n_inputs: int,
    degree: int,
    nonlinear_inputs: list[int] | None = None,
    pure_degree: int = 0,
    pure_inputs: list[int] | None = None,
) -> np.ndarray:
    """Every term of total degree <= ``degree``: the candidate dictionary of term selection.

    Linear terms cover all inputs; terms of degree >= 2 only involve
    ``nonlinear_inputs`` (default: all), which keeps the dictionary small when long
    lags are wanted for the linear dynamics but the nonlinearity sits in a few recent samples.
    ``pure_degree`` adds single-input terms P_d(x_i) of degree ``degree`` < d <= pure_degree
    for the ``pure_inputs`` (default: the nonlinear ones): the paper's high-order per-input
    expansion, for a strongly curved static nonlinearity.
    """
    nonlinear = list(range(n_inputs)) if nonlinear_inputs is None else list(nonlinear_inputs)
    rows = [[0] * n_inputs]
    for i in range(n_inputs):
        row = [0] * n_inputs
        row[i] = 1
        rows.append(row)
    for total in range(2, degree + 1):
        for combo in combinations_with_replacement(nonlinear, total):
            rows.append([combo.count(i) for i in range(n_inputs)])
    for i in nonlinear if pure_inputs is None else pure_inputs:
        for d in range(degree + 1, pure_degree + 1):
            row = [0] * n_inputs
            row[i] = d
            rows.append(row)
    return np.array(rows, dtype=np.int64).reshape(len(rows), n_inputs)


#: bases whose compiled expansion gives the numpy recursion's bits: the same IEEE
#: additions and multiplications in the same order. The trigonometric basis is left to
#: numpy, whose sin/cos may differ from the compiled libm's in the last bit.
COMPILED_BASES = ("legendre", "chebyshev")


def _checked_terms(x: np.ndarray, exponents: np.ndarray, basis: str) -> tuple[np.ndarray, np.ndarray]:
    if basis not in _UNIVARIATE:
        raise ValueError(f"unknown basis {basis!r}; expected one of {', '.join(BASES)}")
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    exponents = np.asarray(exponents, dtype=np.int64)
    if exponents.ndim != 2 or exponents.shape[1] != x.shape[1]:
        raise ValueError(f"exponent rows must have {x.shape[1]} entries (one per input)")
    return x, exponents


# -- factors: a non-polynomial function of a linear form of the inputs ----------------------
#
# A term may carry one factor g(b + w . x) besides its polynomials: hinges, absolute values,
# saturations and cosines (random Fourier features) of any input or of a combination such
# as a velocity y1 - y2. Still a functional link: fixed features, the weights linear, so
# least squares, RLS and the compiled step and free run treat these terms like the others.
# A factor row is [kind, b, w_1 .. w_n]; kind 0 is no factor (the term is its polynomials).

#: factor name -> kind code (shared with the compiled kernels: ``term_kernels.factor_value``)
FACTOR_KINDS = {"lin": 1, "abs": 2, "relu": 3, "tanh": 4, "cos": 5, "sqabs": 6}
_FACTOR_NAMES = {code: name for name, code in FACTOR_KINDS.items()}


def no_factors(n_terms: int, n_inputs: int) -> np.ndarray:
    """Factor rows of terms that are all polynomials (kind 0 everywhere)."""
    return np.zeros((n_terms, n_inputs + 2), dtype=np.float64)


def factor_function(kind: int, z: np.ndarray) -> np.ndarray:
    """g(z) of a factor kind, vectorised (the reference for ``term_kernels.factor_value``)."""
    if kind == 1:
        return z
    if kind == 2:
        return np.abs(z)
    if kind == 3:
        return np.maximum(z, 0.0)
    if kind == 4:
        return np.tanh(z)
    if kind == 5:
        return np.cos(z)
    if kind == 6:
        return z * np.abs(z)
    raise ValueError(f"unknown factor kind {kind}")


def checked_factors(factors: np.ndarray | None, n_terms: int, n_inputs: int) -> np.ndarray:
    """Factor rows as the kernels take them: (n_terms, n_inputs + 2), or (0, n_inputs + 2) when none has a kind."""
    if factors is None:
        return np.zeros((0, n_inputs + 2))
    factors = np.ascontiguousarray(factors, dtype=np.float64)
    if factors.shape[0] == 0:
        return np.zeros((0, n_inputs + 2))
    if factors.shape != (n_terms, n_inputs + 2):
        raise ValueError(f"factor rows must be {n_terms} rows of {n_inputs + 2} entries (kind, b, one w per input)")
    kinds = factors[:, 0]
    known = (kinds >= 0) & (kinds <= max(FACTOR_KINDS.values())) & (kinds == np.floor(kinds))
    if not (known.all() and np.isfinite(factors).all()):
        raise ValueError("factor rows need a known kind code and finite b, w")
    return factors if kinds.any() else np.zeros((0, n_inputs + 2))


def term_features(
    x: np.ndarray,
    exponents: np.ndarray,
    basis: str = "legendre",
    factors: np.ndarray | None = None,
    order: str = "C",
) -> np.ndarray:
    """Columns prod_i P_{e_ti}(x_i) [* g_t(b_t + w_t . x)] for each exponent row (x already in [-1, 1]).

    Compiled (:func:`batch_kernels.term_expansion`) for the polynomial bases when numba
    compiles, bit for bit :func:`term_features_reference` (test_offline_speed checks it): numpy
    makes one pass over the batch per degree and per term, several times the cost of
    the arithmetic, and this expansion is most of an offline run's time. ``order="F"``: the
    columns contiguous, for a caller that picks columns (``fit``'s ranked terms out of hundreds).
    """
    x, exponents = _checked_terms(x, exponents, basis)
    factors = checked_factors(factors, exponents.shape[0], x.shape[1])
    if not (jit.JIT and basis in COMPILED_BASES):
        return np.asarray(term_features_reference(x, exponents, basis, factors), order=order)
    features = np.empty((x.shape[0], exponents.shape[0]), order=order)
    code = term_kernels.BASIS_CODES[basis]
    batch_kernels.term_expansion(np.ascontiguousarray(x), np.ascontiguousarray(exponents), code, factors, features)
    return features


def term_features_reference(
    x: np.ndarray, exponents: np.ndarray, basis: str = "legendre", factors: np.ndarray | None = None
) -> np.ndarray:
    """:func:`term_features` in numpy, one vectorised pass per degree and term (the reference)."""
    x, exponents = _checked_terms(x, exponents, basis)
    factors = checked_factors(factors, exponents.shape[0], x.shape[1])
    top = int(exponents.max(initial=0))
    univariate = _UNIVARIATE[basis](x, top) if top else np.empty((*x.shape, 0))
    features = np.ones((x.shape[0], exponents.shape[0]))
    for t, row in enumerate(exponents):
        for i, e in enumerate(row):
            if e:
                features[:, t] *= univariate[:, i, e - 1]
        if len(factors) and factors[t, 0]:
            z = factors[t, 1] + x @ factors[t, 2:]
            features[:, t] *= factor_function(int(factors[t, 0]), z)
    return features


#: the network inputs' channels in regressor order, (name, lags) each: a term's inputs are named by them
Channels = Sequence[tuple[str, int]]


def siso_channels(y_lags: int, u_lags: int) -> list[tuple[str, int]]:
    """One output of one input: y(k-1..), then u(k-1..), named ``y1``, ``u2``."""
    return [("y", y_lags), ("u", u_lags)]


def _channel_name(name: str, lag: int) -> str:
    """``y`` at lag 2 is ``y2``; a numbered channel ``u3`` at lag 2 is ``u3_2``."""
    return f"{name}_{lag}" if name[-1:].isdigit() else f"{name}{lag}"


def _input_names(channels: Channels) -> list[str]:
    return [_channel_name(name, lag + 1) for name, lags in channels for lag in range(lags)]


def round6(value: float) -> float:
    """Six significant digits, as :func:`format_terms` writes a term's parameters: a term's parameters are kept
    so (by the families that make them, and by any scaling of them after), so that the params file holds the very
    terms the weights were fitted with."""
    return float(f"{value:.6g}")


def _format_linear(factor: np.ndarray, names: list[str]) -> str:
    """b + w . x as ``2.5*y1-2.5*y2+0.1`` (coefficients to 6 significant digits, which fit rounds them to)."""
    parts = [
        ("+" if w > 0 else "-") + ("" if abs(w) == 1.0 else f"{abs(w):.6g}*") + names[i]
        for i, w in enumerate(factor[2:])
        if w
    ]
    if factor[1] or not parts:
        parts.append(f"{factor[1]:+.6g}")
    return "".join(parts).lstrip("+")


def format_terms(exponents: np.ndarray, channels: Channels, factors: np.ndarray | None = None) -> list[str]:
    """Readable names: ``y1^3*u2`` is P3(y(k-1)) P1(u(k-2)) for a model of y(k), ``1`` the bias.

    The network inputs are the lags of each channel in turn (``channels``: (name, lags)
    each; :func:`siso_channels` for y then u): the usual NARX lags of the predicted sample
    (the structure's y(k), u(k) when it predicts y(k+1)). A numbered channel's lag follows
    an underscore: ``y1_2*u0_1`` is P1(y1(k-2)) P1(u0(k-1)). A factor is written
    ``kind(linear form)``: ``u1*tanh(40*y1-40*y2)`` is P1(u(k-1)) tanh(40 (x_y1 - x_y2)), on
    the scaled inputs x the network sees.
    """
    exponents = np.asarray(exponents, dtype=np.int64)
    factors = checked_factors(factors, len(exponents), exponents.shape[1] if exponents.ndim == 2 else 0)
    inputs = _input_names(channels)
    names = []
    for t, row in enumerate(exponents):
        parts = []
        for i, e in enumerate(row):
            if e:
                parts.append(inputs[i] if e == 1 else f"{inputs[i]}^{e}")
        if len(factors) and factors[t, 0]:
            parts.append(f"{_FACTOR_NAMES[int(factors[t, 0])]}({_format_linear(factors[t], inputs)})")
        names.append("*".join(parts) or "1")
    return names


_FACTOR = re.compile(r"([a-z]+)\(([^()]*)\)")
_LINEAR_PART = re.compile(
    r"\s*([+-]?)\s*(\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?)?\s*(\*?)\s*([yu]\d+(?:_\d+)?)?"
)


@lru_cache(maxsize=32)
def _input_indices(channels: tuple[tuple[str, int], ...]) -> dict[str, int]:
    """Each input name's 0-based position: a robot's params file names hundreds of terms over 455 inputs,
    and listing the names again for every one took 0.4 s of building its identifier."""
    return {name: i for i, name in enumerate(_input_names(channels))}


def _lag_index(text: str, name: str, channels: Channels) -> int:
    """0-based network input of ``y3`` / ``u2`` (or ``y1_3`` / ``u0_2``), or an error naming the term."""
    index = _input_indices(tuple((str(c), int(lags)) for c, lags in channels)).get(name)
    if index is not None:
        return index
    shown = ", ".join(f"{_channel_name(c, 1)}..{_channel_name(c, lags)}" for c, lags in channels if lags) or "none"
    raise ValueError(f"term {text!r}: no input {name!r} (the inputs are {shown})")


def _parse_linear(text: str, inner: str, channels: Channels) -> tuple[float, np.ndarray]:
    """(b, w) of ``2.5*y1-2.5*y2+0.1``."""
    w = np.zeros(sum(lags for _, lags in channels))
    b, position, inner = 0.0, 0, inner.replace(" ", "")
    while position < len(inner):
        match = _LINEAR_PART.match(inner, position)
        sign, number, star, name = match.groups() if match else ("", None, "", None)
        if not match or match.end() == position or (star and not (number and name)) or (not number and not name):
            raise ValueError(f"term {text!r}: cannot read {inner[position:]!r} as a linear form like 2*y1-2*y2+0.5")
        value = (-1.0 if sign == "-" else 1.0) * (float(number) if number else 1.0)
        if name:
            w[_lag_index(text, name, channels)] += value
        else:
            b += value
        position = match.end()
    return b, w


def parse_terms(terms: list[str], channels: Channels) -> tuple[np.ndarray, np.ndarray]:
    """(exponent rows, factor rows) from names written by :func:`format_terms`; a bad name is an error naming it."""
    n = sum(lags for _, lags in channels)
    rows, factors = [], []
    for text in terms:
        row, factor = [0] * n, np.zeros(n + 2)
        clean = str(text).replace(" ", "")
        match = _FACTOR.search(clean)
        if match:
            kind = FACTOR_KINDS.get(match.group(1))
            if kind is None:
                raise ValueError(f"term {text!r}: unknown factor {match.group(1)!r}; known: {', '.join(FACTOR_KINDS)}")
            factor[0] = kind
            factor[1], factor[2:] = _parse_linear(text, match.group(2), channels)
            clean = (clean[: match.start()] + clean[match.end() :]).strip("*").replace("**", "*")
        if clean not in ("1", ""):
            for part in clean.split("*"):
                name, _, power = part.partition("^")
                try:
                    degree = int(power or 1)
                except ValueError:
                    raise ValueError(f"term {text!r}: factor {part!r} is not like y1, u2^3") from None
                if degree < 1 or not name[1:].replace("_", "").isdigit():
                    raise ValueError(f"term {text!r}: factor {part!r} is not like y1, u2^3 (degree >= 1)")
                row[_lag_index(text, name, channels)] += degree
        elif clean == "" and not match:
            raise ValueError(f"term {text!r} is empty")
        rows.append(row)
        factors.append(factor)
    exponents = np.array(rows, dtype=np.int64).reshape(len(rows), n)
    return exponents, np.array(factors, dtype=np.float64).reshape(len(rows), n + 2)
