"""A term model in compiled code, sample by sample: the free runs, and what ``fit`` scores and refines with.

A free run feeds the model its own outputs, so no sample can be computed before the one
before it: the loop cannot be vectorised, and in Python its pass over the terms would cost
microseconds per sample. Here, compiled with numba (``core.jit``):
- the pieces every compiled evaluation of a term model shares: the numbering of the bases
  (``BASIS_CODES``), a factor's g(z) (:func:`factor_value`), the term plan
  (:func:`sparse_terms`, :func:`top_degree`), one sample's polynomials; ``batch_kernels``
  expands whole series from the same plan;
- :func:`free_run`: the package's only simulation loop, any number of outputs;
- :func:`simulate_pieces`: free runs of many pieces and folds in one call (``fit``'s selection);
- :func:`free_run_jacobian`: one output's free run with d y^ / d w by forward sensitivity
  (``fit``'s refinement).
"""

from __future__ import annotations

import math

import numpy as np

from lenn_ros.core.jit import njit

#: basis name -> code understood by the compiled free run (and by ``batch_kernels``' expansions)
BASIS_CODES = {"legendre": 0, "chebyshev": 1, "trigonometric": 2}


@njit(cache=True, nogil=True, inline="always")
def factor_value(kind: int, z: float) -> float:
    """g(z) of a term's factor (``expansions.FACTOR_KINDS``; ``expansions.factor_function`` is the reference)."""
    if kind == 1:
        return z
    if kind == 2:
        return abs(z)
    if kind == 3:
        return z if z > 0.0 else 0.0
    if kind == 4:
        return math.tanh(z)
    if kind == 5:
        return math.cos(z)
    if kind == 6:
        return z * abs(z)
    return 1.0


@njit(cache=True, nogil=True, inline="always")
def _univariate_row(x: float, top: int, basis: int, out: np.ndarray) -> None:
    """out[0..top] = P_0(x)..P_top(x) in the numbered basis (same recursions as expansions)."""
    out[0] = 1.0
    if top == 0:
        return
    out[1] = x
    for n in range(1, top):
        if basis == 0:
            out[n + 1] = ((2 * n + 1) * x * out[n] - n * out[n - 1]) / (n + 1)
        elif basis == 1:
            out[n + 1] = 2.0 * x * out[n] - out[n - 1]
        else:
            harmonic = (n + 1) // 2
            out[n + 1] = math.sin(harmonic * math.pi * x) if n % 2 else math.cos(harmonic * math.pi * x)


@njit(cache=True, nogil=True, inline="always")
def top_degree(exponents: np.ndarray) -> int:
    """Highest degree any term asks of any input, at least 1: how far each input's recursion must go,
    and the depth of the table it fills. At least 1 because a factor reads its inputs x_i as table[i, 1]
    (:func:`sparse_terms`' ``need``): a model of factor terms only (``fit``'s input averages) had a
    table of depth 1 written at depth 2, past its end."""
    top = 1
    for t in range(exponents.shape[0]):
        for i in range(exponents.shape[1]):
            top = max(top, exponents[t, i])
    return top


@njit(cache=True, nogil=True)
def sparse_terms(exponents: np.ndarray, factors: np.ndarray):
    """The terms as lists of their non-zero entries, and the degree each input needs.

    (e_start, e_input, e_degree, f_start, f_input, f_weight, need): term t's
    polynomials are e_input/e_degree[e_start[t]:e_start[t+1]], its factor's weights
    f_input/f_weight[f_start[t]:f_start[t+1]], both in increasing input order, so a
    product or sum over them takes the same operations in the same order as one over
    the dense rows (the same bits). A free run visits every term every sample: with
    long lag spans most entries of a row are zero.
    """
    n_terms, n_inputs = exponents.shape
    with_factors = factors.shape[0] > 0
    e_start = np.zeros(n_terms + 1, dtype=np.int64)
    f_start = np.zeros(n_terms + 1, dtype=np.int64)
    for t in range(n_terms):
        e_count = 0
        f_count = 0
        for i in range(n_inputs):
            if exponents[t, i]:
                e_count += 1
            if with_factors and factors[t, 0] != 0.0 and factors[t, 2 + i] != 0.0:
                f_count += 1
        e_start[t + 1] = e_start[t] + e_count
        f_start[t + 1] = f_start[t] + f_count
    e_input = np.empty(e_start[n_terms], dtype=np.int64)
    e_degree = np.empty(e_start[n_terms], dtype=np.int64)
    f_input = np.empty(f_start[n_terms], dtype=np.int64)
    f_weight = np.empty(f_start[n_terms])
    need = np.zeros(n_inputs, dtype=np.int64)
    for t in range(n_terms):
        e, f = e_start[t], f_start[t]
        for i in range(n_inputs):
            if exponents[t, i]:
                e_input[e] = i
                e_degree[e] = exponents[t, i]
                need[i] = max(need[i], exponents[t, i])
                e += 1
            if with_factors and factors[t, 0] != 0.0 and factors[t, 2 + i] != 0.0:
                f_input[f] = i
                f_weight[f] = factors[t, 2 + i]
                need[i] = max(need[i], 1)  # the factor reads x_i from table[i, 1]
                f += 1
    return e_start, e_input, e_degree, f_start, f_input, f_weight, need


@njit(cache=True, nogil=True)
def free_run(
    values: np.ndarray,
    start: int,
    n_y: int,
    input_start: np.ndarray,
    input_source: np.ndarray,
    input_lag: np.ndarray,
    input_offset: np.ndarray,
    input_scale: np.ndarray,
    known_start: np.ndarray,
    known_source: np.ndarray,
    known_lag: np.ndarray,
    known_weight: np.ndarray,
    term_start: np.ndarray,
    exponents: np.ndarray,
    factors: np.ndarray,
    weights: np.ndarray,
    feature_branch: np.ndarray,
    n_branches: int,
    tanh_output: np.ndarray,
    output_scale: np.ndarray,
    constant: np.ndarray,
    y_offset: np.ndarray,
    y_scale: np.ndarray,
    basis: int,
    divergence_bound: float,
    clipped: np.ndarray,
) -> int:
    """The free run (simulation) of a functional-link model of any number of outputs: the only one.

    ``values`` (N, n_y + n_u) holds [y, u] per sample; its outputs before ``start`` seed
    the history and the rest are overwritten with the model's, each fed back as the next
    input of every output that reads it. Output j's network inputs are entries
    ``input_start[j]..input_start[j+1]`` (a column of ``values``, a lag, an offset and a
    scale each), its terms rows ``term_start[j]..term_start[j+1]`` of ``exponents`` /
    ``weights`` (``feature_branch``: each term's branch, fewer than ``n_branches``), its
    known linear part entries ``known_start[j]..known_start[j+1]`` (a column, a lag and a
    weight each, added after the network's output). Network inputs outside [-1, 1] are
    clipped (the polynomials are only bounded there) and counted per output in
    ``clipped``. Returns the first diverged sample, or -1: an output that is non-finite
    or further than ``divergence_bound`` scale units from its offset ends the run (every
    output after it is nan), so an unstable model is flagged instead of printed as a
    number. ``factors``: the terms' factor rows, or none (0 rows) when every term is
    polynomials only. Each input's polynomials are computed once per sample and shared by
    all the output's terms, so a sample costs one pass over the terms.
    """
    n = values.shape[0]
    plan = sparse_terms(exponents, factors)
    need = plan[6]
    read_start, read = _inputs_read(input_start, input_source, need, n_y)
    table = np.empty((exponents.shape[1], top_degree(exponents) + 1))
    sums = np.zeros(n_branches)
    for k in range(start - 1, n - 1):
        for j in range(n_y):
            clipped[j] += _input_table(
                values, k, input_start[j], read[read_start[j] : read_start[j + 1]], input_source, input_lag,
                input_offset, input_scale, basis, need, table,
            )  # fmt: skip
            out = constant[j] + _term_network_output(
                table, plan, factors, term_start[j], term_start[j + 1], weights, feature_branch, tanh_output[j],
                output_scale[j], sums,
            )  # fmt: skip
            for entry in range(known_start[j], known_start[j + 1]):
                out += known_weight[entry] * values[k - known_lag[entry], known_source[entry]]
            if not math.isfinite(out) or abs(out - y_offset[j]) > divergence_bound * y_scale[j]:
                for later in range(k + 1, n):
                    for c in range(n_y):
                        values[later, c] = np.nan
                return k + 1
            values[k + 1, j] = out
    return -1


@njit(cache=True, nogil=True)
def _inputs_read(input_start: np.ndarray, source: np.ndarray, need: np.ndarray, simulated: int):
    """(read_start, read): per output, the network inputs (local indices, in order) a sample must read.

    Those some term reads (``need`` > 0), and the fed-back outputs (a column below
    ``simulated``), whose clipping is counted even where no term reads them. A measured
    input that no term reads (a long lag span's middle lags) cannot matter: listing the
    others once, instead of skipping those every sample, is what keeps a model of many
    channels' long lags (hundreds of inputs, a dozen terms) as cheap as its terms.
    """
    n_out = len(input_start) - 1
    read_start = np.zeros(n_out + 1, dtype=np.int64)
    read = np.empty(input_start[n_out] - input_start[0], dtype=np.int64)
    count = 0
    for j in range(n_out):
        for i in range(input_start[j + 1] - input_start[j]):
            if need[i] > 0 or source[input_start[j] + i] < simulated:
                read[count] = i
                count += 1
        read_start[j + 1] = count
    return read_start, read[:count]


@njit(cache=True, nogil=True, inline="always")
def _input_table(
    values: np.ndarray,
    k: int,
    first: int,
    read: np.ndarray,
    source: np.ndarray,
    lag: np.ndarray,
    offset: np.ndarray,
    scale: np.ndarray,
    basis: int,
    need: np.ndarray,
    table: np.ndarray,
) -> int:
    """table[i, n] = P_n(x_i(k)) for n <= need[i] of the network inputs ``first + i``, i in ``read``
    (:func:`_inputs_read`), of sample k; returns how many were clipped.

    Input ``first + i`` is column ``source`` of ``values`` at ``lag`` samples before k, as
    (value - offset) / scale clipped to [-1, 1]. Each input's polynomials are computed once
    per sample and shared by all terms, which is what makes a free run cost one pass over
    the terms per sample. The one place a free run turns a sample into network inputs.
    """
    clipped = 0
    for i in read:
        entry = first + i
        x = (values[k - lag[entry], source[entry]] - offset[entry]) / scale[entry]
        if x > 1.0:
            x = 1.0
            clipped += 1
        elif x < -1.0:
            x = -1.0
            clipped += 1
        _univariate_row(x, need[i], basis, table[i])
    return clipped


@njit(cache=True, nogil=True, inline="always")
def _term_network_output(
    table: np.ndarray,
    plan,
    factors: np.ndarray,
    t0: int,
    t1: int,
    weights: np.ndarray,
    feature_branch: np.ndarray,
    tanh_output: bool,
    output_scale: float,
    sums: np.ndarray,
) -> float:
    """Network part of the output over terms t0..t1: sum over branches of (tanh of) the weighted product terms.

    ``plan`` is :func:`sparse_terms` of the terms; ``sums`` the caller's scratch of one
    entry per branch, so no sample allocates.
    """
    e_start, e_input, e_degree, f_start, f_input, f_weight, _need = plan
    sums[:] = 0.0
    for t in range(t0, t1):
        value = weights[t]
        for e in range(e_start[t], e_start[t + 1]):
            value *= table[e_input[e], e_degree[e]]
        if f_start[t + 1] > f_start[t] or (factors.shape[0] > 0 and factors[t, 0] != 0.0):
            z = factors[t, 1]
            for f in range(f_start[t], f_start[t + 1]):
                z += f_weight[f] * table[f_input[f], 1]
            value *= factor_value(int(factors[t, 0]), z)
        sums[feature_branch[t]] += value
    out = 0.0
    for b in range(len(sums)):
        out += output_scale * math.tanh(sums[b]) if tanh_output else sums[b]
    return out


@njit(cache=True, nogil=True)
def simulate_pieces(
    values: np.ndarray,
    first: np.ndarray,
    stop: np.ndarray,
    group: np.ndarray,
    warm: int,
    source: np.ndarray,
    lag: np.ndarray,
    offset: np.ndarray,
    scale: np.ndarray,
    exponents: np.ndarray,
    factors: np.ndarray,
    weights: np.ndarray,
    basis: int,
    divergence_bound: float,
    out: np.ndarray,
    clip_limit: np.ndarray,
) -> None:
    """Free runs of column 0 of ``values`` over samples first[p]..stop[p], pooled per group.

    ``values`` is one output's view: column 0 the output the model predicts (simulated,
    from the ``warm`` measured samples before each piece), the other columns what it
    reads besides (measured). Network input i is column ``source[i]`` at ``lag[i]``,
    (value - offset[i]) / scale[i]; input 0 is the output's newest lag, whose offset and
    scale bound the divergence. Piece p is simulated with the weights ``weights[group[p]]``
    (a fold's); ``out[g]`` accumulates [sum of squared errors, samples, sum of squares
    about each piece's mean, clipped inputs, diverged (1.0)]. One call scores a prefix on
    every block, so the selection pays no Python per simulation. The pieces come group by
    group; once a group has diverged or clipped more than ``clip_limit[g]`` inputs, it is
    finished and the call returns: the later groups' rows stay as they were (a prefix
    already refused needs no more simulation).
    """
    longest = 0
    for p in range(len(first)):
        longest = max(longest, stop[p] - first[p])
    scratch = np.empty((longest + warm, values.shape[1]))
    n_terms, n_inputs = exponents.shape[0], len(source)
    branch = np.zeros(n_terms, dtype=np.int64)
    no_index = np.zeros(0, dtype=np.int64)
    input_start = np.array([0, n_inputs])
    known_start = np.zeros(2, dtype=np.int64)
    term_start = np.array([0, n_terms])
    linear_output = np.zeros(1, dtype=np.bool_)
    unit = np.ones(1)
    zero = np.zeros(1)
    y_offset = np.array([offset[0]])
    y_scale = np.array([scale[0]])
    clipped = np.zeros(1, dtype=np.int64)
    for p in range(len(first)):
        a, b, g = first[p], stop[p], group[p]
        buffer = scratch[: b - a + warm]
        buffer[:, :] = values[a - warm : b, :]
        clipped[0] = 0
        diverged_at = free_run(
            buffer, warm, 1, input_start, source, lag, offset, scale, known_start, no_index, no_index, zero[:0],
            term_start, exponents, factors, weights[g], branch, 1, linear_output, unit, zero, y_offset, y_scale,
            basis, divergence_bound, clipped,
        )  # fmt: skip
        mean = 0.0
        for k in range(a, b):
            mean += values[k, 0]
        mean /= b - a
        squared, deviation = 0.0, 0.0
        for k in range(a, b):
            error = buffer[k - a + warm, 0] - values[k, 0]
            squared += error * error
            deviation += (values[k, 0] - mean) * (values[k, 0] - mean)
        out[g, 0] += squared
        out[g, 1] += b - a
        out[g, 2] += deviation
        out[g, 3] += clipped[0]
        if diverged_at >= 0:
            out[g, 4] = 1.0
        group_done = p + 1 == len(first) or group[p + 1] != g
        if group_done and (out[g, 4] != 0.0 or out[g, 3] > clip_limit[g]):
            return


@njit(cache=True, nogil=True, inline="always")
def _factor_slope(kind: int, z: float) -> float:
    """g'(z) of a factor kind (0 where g is not differentiable: |z| and relu at 0)."""
    if kind == 1:
        return 1.0
    if kind == 2:
        return 1.0 if z > 0.0 else (-1.0 if z < 0.0 else 0.0)
    if kind == 3:
        return 1.0 if z > 0.0 else 0.0
    if kind == 4:
        t = math.tanh(z)
        return 1.0 - t * t
    if kind == 5:
        return -math.sin(z)
    if kind == 6:
        return 2.0 * abs(z)
    return 0.0


@njit(cache=True, nogil=True, inline="always")
def _slope_row(x: float, top: int, basis: int, values: np.ndarray, out: np.ndarray) -> None:
    """out[n] = P_n'(x) for n <= top, from the recursion differentiated (``values`` holds P_0..P_top)."""
    out[0] = 0.0
    if top == 0:
        return
    out[1] = 1.0
    for n in range(1, top):
        if basis == 0:
            out[n + 1] = ((2 * n + 1) * (values[n] + x * out[n]) - n * out[n - 1]) / (n + 1)
        else:
            out[n + 1] = 2.0 * values[n] + 2.0 * x * out[n] - out[n - 1]


@njit(cache=True, nogil=True, inline="always")
def _polynomial_gradient(
    table: np.ndarray, slopes: np.ndarray, alive: np.ndarray, plan, t: int, weight: float, gradient: np.ndarray
) -> None:
    """gradient[i] += weight * d(prod of term t's polynomials) / dx_i for its live fed-back inputs."""
    e_start, e_input, e_degree = plan[0], plan[1], plan[2]
    for e in range(e_start[t], e_start[t + 1]):
        i = e_input[e]
        if i < len(alive) and alive[i]:
            others = 1.0
            for o in range(e_start[t], e_start[t + 1]):
                if o != e:
                    others *= table[e_input[o], e_degree[o]]
            gradient[i] += weight * others * slopes[i, e_degree[e]]


@njit(cache=True, nogil=True, inline="always")
def _features_and_gradient(
    table: np.ndarray,
    slopes: np.ndarray,
    alive: np.ndarray,
    plan,
    factors: np.ndarray,
    weights: np.ndarray,
    phi: np.ndarray,
    gradient: np.ndarray,
) -> None:
    """phi[t] = term t's feature; gradient[i] = dN/dx_i for every live fed-back input i (< len(alive))."""
    e_start, e_input, e_degree, f_start, f_input, f_weight, _need = plan
    y_lags = len(alive)
    gradient[:] = 0.0
    for t in range(len(phi)):
        product = 1.0
        for e in range(e_start[t], e_start[t + 1]):
            product *= table[e_input[e], e_degree[e]]
        g, slope, kind = 1.0, 0.0, 0
        if factors.shape[0] > 0 and factors[t, 0] != 0.0:
            kind = int(factors[t, 0])
            z = factors[t, 1]
            for f in range(f_start[t], f_start[t + 1]):
                z += f_weight[f] * table[f_input[f], 1]
            g, slope = factor_value(kind, z), _factor_slope(kind, z)
        phi[t] = product * g
        w = weights[t]
        _polynomial_gradient(table, slopes, alive, plan, t, w * g, gradient)
        if kind:
            for f in range(f_start[t], f_start[t + 1]):
                i = f_input[f]
                if i < y_lags and alive[i]:
                    gradient[i] += w * product * slope * f_weight[f]


@njit(cache=True, nogil=True, inline="always")
def _sensitivity_row(
    row: np.ndarray,
    phi: np.ndarray,
    gradient: np.ndarray,
    alive: np.ndarray,
    history: np.ndarray,
    y_scale: float,
    head: int,
) -> int:
    """row = d y^(k+1) / d w = phi + sum_i dN/dx_i d x_i / d w; then pushed into ``history``; returns its head.

    ``history`` is a ring: d y^(k-i) / d w is its row (head + i) mod y_lags, so a sample
    writes one row instead of shifting them all (ten lags of 67 weights: 600 copies).
    """
    row[:] = phi
    y_lags = len(alive)
    for i in range(y_lags):
        if alive[i]:
            scale = gradient[i] / y_scale
            past = history[(head + i) % y_lags]
            for j in range(len(row)):
                row[j] += scale * past[j]
    if y_lags:
        head = (head + y_lags - 1) % y_lags
        history[head, :] = row
    return head


@njit(cache=True, nogil=True)
def free_run_jacobian(
    values: np.ndarray,
    start: int,
    y_lags: int,
    source: np.ndarray,
    lag: np.ndarray,
    offset: np.ndarray,
    scale: np.ndarray,
    exponents: np.ndarray,
    factors: np.ndarray,
    weights: np.ndarray,
    basis: int,
    divergence_bound: float,
    jacobian: np.ndarray,
) -> tuple[int, int]:
    """:func:`simulate_pieces`' free run of one piece of a linear-output term model, with d y^(k) / d w.

    ``values`` and the inputs as in :func:`simulate_pieces`; the first ``y_lags`` inputs
    are column 0 (the simulated output) at lags 0, 1, ...; column 0 from ``start`` on is
    overwritten with the model's outputs, computed as :func:`free_run` computes them (the
    same bits). ``jacobian[k - start, j]`` gets d y^(k) / d w_j by forward sensitivity:
    d y^(k+1) = phi(x(k)) + sum_i dN/dx_i (k) dx_i(k), where x_i is a fed-back output
    y^(k-i) scaled (zero when it is clipped or still measured). One pass replaces a
    free run per nudged weight, and it is exact. Legendre and Chebyshev bases only.
    Returns (clipped inputs, first diverged sample or -1).
    """
    n, n_terms = values.shape[0], exponents.shape[0]
    plan = sparse_terms(exponents, factors)
    need = plan[6]
    top = top_degree(exponents)
    table = np.empty((len(source), top + 1))
    slopes = np.zeros((y_lags, top + 1))
    sums = np.zeros(1)
    branch = np.zeros(n_terms, dtype=np.int64)
    history = np.zeros((max(y_lags, 1), n_terms))  # d y^(k-i) / d w, a ring (:func:`_sensitivity_row`)
    phi = np.empty(n_terms)
    gradient = np.zeros(y_lags)
    alive = np.zeros(y_lags, dtype=np.bool_)
    y_offset, y_scale = offset[0], scale[0]
    clipped = 0
    read = _inputs_read(np.array([0, len(source)]), source, need, 1)[1]
    head = 0
    for k in range(start - 1, n - 1):
        clipped += _input_table(values, k, 0, read, source, lag, offset, scale, basis, need, table)
        out = _term_network_output(table, plan, factors, 0, n_terms, weights, branch, False, 1.0, sums)
        for i in range(y_lags):
            value = (values[k - i, 0] - y_offset) / y_scale
            alive[i] = k - i >= start and -1.0 < value < 1.0  # a clipped or measured input has no slope
            if alive[i]:
                _slope_row(table[i, 1], need[i], basis, table[i], slopes[i])
        _features_and_gradient(table, slopes, alive, plan, factors, weights, phi, gradient)
        if not math.isfinite(out) or abs(out - y_offset) > divergence_bound * y_scale:
            for j in range(k + 1, n):
                values[j, 0] = np.nan
            return clipped, k + 1
        values[k + 1, 0] = out
        head = _sensitivity_row(jacobian[k + 1 - start], phi, gradient, alive, history, y_scale, head)
    return clipped, -1
