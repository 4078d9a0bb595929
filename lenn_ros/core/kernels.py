"""The compiled inner loops: every learning rule of the package, once.

A LeNN update touches ~15 weights; done as numpy calls per sample, interpreter
overhead (microseconds per call) costs 100x the arithmetic. So each rule is written
as a plain loop over samples and compiled with numba. There is no second, vectorised
copy to keep in sync: the numpy-level models call these functions for one sample
online and for 50 000 samples offline, which is also why a live identifier and an
offline evaluation of its recording agree to the last bit.

Without numba the same functions run as plain Python (``COMPILED`` is then False);
``test_kernels`` checks that both paths give the same numbers.

Conventions shared by all kernels:
- ``y_out[k]`` receives the prediction made *before* the update of sample k
  (the a-priori output), from which the caller computes e(k) = d(k) - y_out[k].
- ``learn`` False runs the forward pass only (frozen weights, the paper's test).
- The return value is the number of samples processed; a smaller value means the
  update of sample ``returned`` would have produced a non-finite weight, and the
  kernel stopped *before* applying it, so the weights are still finite. The caller
  (the divergence guard) decides what to do.
- The ``_`` helpers a kernel is split into are ``inline="always"``: numba copies
  them into the kernel, within a few percent of one long loop (a plain call cost up
  to 25% on small networks). A kernel's ``.py_func`` still calls their compiled versions.
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is a declared dependency; the fallback keeps the core importable anyway
    from numba import njit

    COMPILED = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    COMPILED = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        def wrap(function):
            function.py_func = function
            return function

        return wrap(args[0]) if args and callable(args[0]) else wrap


@njit(cache=True, nogil=True)
def functional_link_sgd(
    weights: np.ndarray,
    momentum: np.ndarray,
    features: np.ndarray,
    targets: np.ndarray,
    feature_branch: np.ndarray,
    n_branches: int,
    alpha: float,
    beta: float,
    tanh_output: bool,
    output_scale: float,
    learn: bool,
    y_out: np.ndarray,
) -> int:
    """Paper eqs. 6-10: gradient step on e^2/2 with momentum, one sample at a time.

    ``feature_branch[f]`` names the output node feature f feeds; the model output is
    the sum of the branch outputs (one branch for the paper's LeNN, two for Ex. 3's
    N1[y] + N2[u], which must learn from the error of their sum).
    """
    n_samples, n_features = features.shape
    sums = np.zeros(n_branches)
    slopes = np.zeros(n_branches)
    for k in range(n_samples):
        sums[:] = 0.0
        for f in range(n_features):
            sums[feature_branch[f]] += weights[f] * features[k, f]
        y = 0.0
        for b in range(n_branches):
            if tanh_output:
                t = math.tanh(sums[b])
                y += output_scale * t
                slopes[b] = output_scale * (1.0 - t * t)
            else:
                y += sums[b]
                slopes[b] = 1.0
        y_out[k] = y
        if not learn:
            continue
        error = targets[k] - y
        step_size = 0.0
        for f in range(n_features):
            step = alpha * error * slopes[feature_branch[f]] * features[k, f] + beta * momentum[f]
            step_size += abs(step)
        if not math.isfinite(step_size):
            return k
        for f in range(n_features):
            momentum[f] = alpha * error * slopes[feature_branch[f]] * features[k, f] + beta * momentum[f]
            weights[f] += momentum[f]
    return n_samples


@njit(cache=True, nogil=True)
def functional_link_nlms(
    weights: np.ndarray,
    features: np.ndarray,
    targets: np.ndarray,
    step_size: float,
    epsilon: float,
    learn: bool,
    y_out: np.ndarray,
) -> int:
    """Normalised LMS for a linear output: w += mu e phi / (eps + |phi|^2).

    The normalisation makes the step independent of the feature scale, so one
    mu (0 < mu < 2) works across expansions without the paper's per-example tuning.
    """
    n_samples, n_features = features.shape
    for k in range(n_samples):
        y = 0.0
        energy = epsilon
        for f in range(n_features):
            y += weights[f] * features[k, f]
            energy += features[k, f] * features[k, f]
        y_out[k] = y
        if not learn:
            continue
        gain = step_size * (targets[k] - y) / energy
        if not math.isfinite(gain):
            return k
        for f in range(n_features):
            weights[f] += gain * features[k, f]
    return n_samples


@njit(cache=True, nogil=True)
def functional_link_rls(
    weights: np.ndarray,
    covariance: np.ndarray,
    features: np.ndarray,
    targets: np.ndarray,
    forgetting: float,
    max_trace: float,
    learn: bool,
    y_out: np.ndarray,
    leverage_out: np.ndarray,
) -> int:
    """Exponentially weighted recursive least squares for a linear output.

    ``leverage_out`` (length 0: not wanted) receives phi(k)' P phi(k) of each sample's
    pattern with the P its a-priori output was predicted with (:func:`leverage`), the
    share of the one-step variance the weights' uncertainty adds (``core.spread``): the
    same values, in the same arithmetic, as the live step reports for each prediction.

    Two safeguards keep it healthy over millions of updates:
    - the covariance is re-symmetrised after every update (round-off otherwise
      makes it drift asymmetric and eventually indefinite);
    - the division by the forgetting factor is skipped while trace(P) exceeds
      ``max_trace``: with no excitation (a plant at rest) plain forgetting RLS
      inflates P exponentially ("covariance wind-up") and then explodes at the
      next excitation. Bounding the trace is the standard fix.
    """
    n_samples, n_features = features.shape
    p_phi = np.empty(n_features)
    wanted = len(leverage_out) > 0
    for k in range(n_samples):
        if wanted:
            leverage_out[k] = leverage(covariance, features, k)
        y = 0.0
        for f in range(n_features):
            y += weights[f] * features[k, f]
        y_out[k] = y
        if not learn:
            continue
        denominator = _rls_gain(covariance, features, k, forgetting, p_phi)
        error = targets[k] - y
        if not (math.isfinite(error) and math.isfinite(denominator)) or denominator <= 0.0:
            return k
        for i in range(n_features):
            weights[i] += p_phi[i] / denominator * error
        _rls_covariance_update(covariance, p_phi, denominator, forgetting, max_trace)
    return n_samples


@njit(cache=True, nogil=True, inline="always")
def leverage(covariance: np.ndarray, features: np.ndarray, k: int) -> float:
    """phi' P phi of row ``k`` over the upper triangle (P is symmetric): half the multiplications of the full form.

    The one formula the live step (``online_step``) and the batch RLS use, so the one-step
    std of a recording evaluated offline equals the one published live.
    """
    n = features.shape[1]
    total = 0.0
    for i in range(n):
        row = 0.0
        for j in range(i + 1, n):
            row += covariance[i, j] * features[k, j]
        total += features[k, i] * (covariance[i, i] * features[k, i] + 2.0 * row)
    return total


@njit(cache=True, nogil=True, inline="always")
def _rls_gain(covariance: np.ndarray, features: np.ndarray, k: int, forgetting: float, p_phi: np.ndarray) -> float:
    """p_phi = P phi(k); returns lambda + phi' P phi, the gain's denominator.

    Kept apart from the covariance update because the caller must test the
    denominator for a non-finite or non-positive value *before* touching any state.
    """
    n_features = features.shape[1]
    denominator = forgetting
    for i in range(n_features):
        acc = 0.0
        for j in range(n_features):
            acc += covariance[i, j] * features[k, j]
        p_phi[i] = acc
        denominator += features[k, i] * acc
    return denominator


@njit(cache=True, nogil=True, inline="always")
def _rls_covariance_update(
    covariance: np.ndarray, p_phi: np.ndarray, denominator: float, forgetting: float, max_trace: float
) -> None:
    """P -= P phi phi' P / denominator, written symmetric, then P /= lambda unless trace(P) is bounded.

    Only the upper triangle is computed and mirrored: that is the re-symmetrisation
    the docstring of :func:`functional_link_rls` relies on.
    """
    n_features = len(p_phi)
    trace = 0.0
    for i in range(n_features):
        for j in range(i, n_features):
            value = covariance[i, j] - p_phi[i] * p_phi[j] / denominator
            covariance[i, j] = value
            covariance[j, i] = value
        trace += covariance[i, i]
    if trace / forgetting <= max_trace:
        for i in range(n_features):
            for j in range(n_features):
                covariance[i, j] /= forgetting


@njit(cache=True, nogil=True)
def mlp_sgd(
    params: np.ndarray,
    momentum: np.ndarray,
    inputs: np.ndarray,
    targets: np.ndarray,
    layout: np.ndarray,
    n_activations: int,
    alpha: float,
    beta: float,
    tanh_output: bool,
    output_scale: float,
    learn: bool,
    y_out: np.ndarray,
) -> int:
    """Backpropagation with momentum for one or more MLPs whose outputs are summed.

    All weights live in one flat vector. ``layout`` has one row per layer, branch by
    branch, each row: [weight offset, fan-in, fan-out, input activation offset,
    output activation offset, is-output-layer]. A layer's weights are a
    (fan-out, fan-in + 1) row-major matrix whose last column is the bias. The first
    ``inputs.shape[1]`` activations are the network inputs themselves.
    """
    n_samples, n_inputs = inputs.shape
    act = np.zeros(n_activations)
    delta = np.zeros(n_activations)
    for k in range(n_samples):
        for i in range(n_inputs):
            act[i] = inputs[k, i]
        y = _mlp_forward(params, layout, tanh_output, output_scale, act)
        y_out[k] = y
        if not learn:
            continue
        _mlp_deltas(params, layout, tanh_output, output_scale, targets[k] - y, act, delta)
        if not math.isfinite(_mlp_step_size(momentum, layout, alpha, beta, act, delta)):
            return k
        _mlp_apply_step(params, momentum, layout, alpha, beta, act, delta)
    return n_samples


@njit(cache=True, nogil=True, inline="always")
def _mlp_forward(
    params: np.ndarray, layout: np.ndarray, tanh_output: bool, output_scale: float, act: np.ndarray
) -> float:
    """Fill every activation from the inputs already in ``act``; returns the summed output.

    The activations are kept (not just the output) because backpropagation needs them.
    """
    y = 0.0
    for layer in range(layout.shape[0]):
        w0, fan_in, fan_out, a_in, a_out, is_last = layout[layer]
        for j in range(fan_out):
            row = w0 + j * (fan_in + 1)
            s = params[row + fan_in]
            for i in range(fan_in):
                s += params[row + i] * act[a_in + i]
            if is_last:
                if tanh_output:
                    t = math.tanh(s)
                    act[a_out + j] = t
                    y += output_scale * t
                else:
                    act[a_out + j] = s
                    y += s
            else:
                act[a_out + j] = math.tanh(s)
    return y


@njit(cache=True, nogil=True, inline="always")
def _mlp_deltas(
    params: np.ndarray,
    layout: np.ndarray,
    tanh_output: bool,
    output_scale: float,
    error: float,
    act: np.ndarray,
    delta: np.ndarray,
) -> None:
    """Local gradients (deltas) of every unit, computed with the old weights before any update."""
    for layer in range(layout.shape[0] - 1, -1, -1):
        w0, fan_in, fan_out, a_in, a_out, is_last = layout[layer]
        if is_last:
            for j in range(fan_out):
                if tanh_output:
                    t = act[a_out + j]
                    delta[a_out + j] = error * output_scale * (1.0 - t * t)
                else:
                    delta[a_out + j] = error
        if layer > 0 and layout[layer - 1, 4] == a_in:  # hidden input layer of same branch
            for i in range(fan_in):
                acc = 0.0
                for j in range(fan_out):
                    acc += params[w0 + j * (fan_in + 1) + i] * delta[a_out + j]
                a = act[a_in + i]
                delta[a_in + i] = acc * (1.0 - a * a)


@njit(cache=True, nogil=True, inline="always")
def _mlp_step_size(
    momentum: np.ndarray, layout: np.ndarray, alpha: float, beta: float, act: np.ndarray, delta: np.ndarray
) -> float:
    """Sum of |step| over all weights, so a non-finite step is caught before any weight changes."""
    step_size = 0.0
    for layer in range(layout.shape[0]):
        w0, fan_in, fan_out, a_in, a_out, _is_last = layout[layer]
        for j in range(fan_out):
            row = w0 + j * (fan_in + 1)
            g = alpha * delta[a_out + j]
            for i in range(fan_in):
                step_size += abs(g * act[a_in + i] + beta * momentum[row + i])
            step_size += abs(g + beta * momentum[row + fan_in])
    return step_size


@njit(cache=True, nogil=True, inline="always")
def _mlp_apply_step(
    params: np.ndarray,
    momentum: np.ndarray,
    layout: np.ndarray,
    alpha: float,
    beta: float,
    act: np.ndarray,
    delta: np.ndarray,
) -> None:
    """The momentum step of eq. 10 on every weight and bias, once :func:`_mlp_step_size` found it finite."""
    for layer in range(layout.shape[0]):
        w0, fan_in, fan_out, a_in, a_out, _is_last = layout[layer]
        for j in range(fan_out):
            row = w0 + j * (fan_in + 1)
            g = alpha * delta[a_out + j]
            for i in range(fan_in):
                momentum[row + i] = g * act[a_in + i] + beta * momentum[row + i]
                params[row + i] += momentum[row + i]
            momentum[row + fan_in] = g + beta * momentum[row + fan_in]
            params[row + fan_in] += momentum[row + fan_in]


#: basis name -> code understood by the compiled free run
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
    plan = _sparse_terms(exponents, factors)
    need = plan[6]
    read_start, read = _inputs_read(input_start, input_source, need, n_y)
    table = np.empty((exponents.shape[1], _top_degree(exponents) + 1))
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


@njit(cache=True, nogil=True)
def _sparse_terms(exponents: np.ndarray, factors: np.ndarray):
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

    ``plan`` is :func:`_sparse_terms` of the terms; ``sums`` the caller's scratch of one
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
    plan = _sparse_terms(exponents, factors)
    need = plan[6]
    top = _top_degree(exponents)
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


# -- batch expansion and least squares ---------------------------------------------------

#: numba is importable *and* compiling (``NUMBA_DISABLE_JIT=1`` runs every kernel as
#: Python): callers pick a vectorised numpy path over a kernel only when it is not.
try:
    from numba import config as _numba_config

    JIT = COMPILED and not _numba_config.DISABLE_JIT
except ImportError:  # pragma: no cover - exercised only where numba is missing
    JIT = False

#: samples expanded side by side. One sample's recursion is a chain of dependent
#: divisions, bound by their latency; across a block the same step of every sample is
#: independent and runs in SIMD lanes, with unchanged arithmetic per element (the same
#: bits). Ex. 1's 15 terms of 550 000 samples took 35 ms in blocks of 4, 18 ms of 16,
#: 14 ms of 32 and about the same of 64 (one run each, a busy 2-core machine).
EXPANSION_BLOCK = 32
#: the same for a column-major ``out`` (``fit``'s designs): each term's run of samples is written to its
#: own column, and runs of 32 spread a block's writes over as many pages as there are terms (a 281-term
#: design of 40 000 samples: 41 ms in blocks of 32, 31 ms of 256, 26 ms row-major)
COLUMN_MAJOR_BLOCK = 256


@njit(cache=True, nogil=True, inline="always")
def _top_degree(exponents: np.ndarray) -> int:
    """Highest degree any term asks of any input, at least 1: how far each input's recursion must go,
    and the depth of the table it fills. At least 1 because a factor reads its inputs x_i as table[i, 1]
    (:func:`_sparse_terms`' ``need``): a model of factor terms only (``fit``'s input averages) had a
    table of depth 1 written at depth 2, past its end."""
    top = 1
    for t in range(exponents.shape[0]):
        for i in range(exponents.shape[1]):
            top = max(top, exponents[t, i])
    return top


@njit(cache=True, nogil=True, inline="always")
def _univariate_block(x: np.ndarray, k0: int, count: int, i: int, top: int, basis: int, table: np.ndarray) -> None:
    """table[n, b] = P_n(x[k0 + b, i]) for n <= top, b < count: :func:`_univariate_row` for a block.

    The recursions are written exactly as in ``expansions`` ((2n+1) x P_n - n P_{n-1},
    then / (n+1)), so each element gets the numpy path's bits.
    """
    for b in range(count):
        table[0, b] = 1.0
    if top == 0:
        return
    for b in range(count):
        table[1, b] = x[k0 + b, i]
    for n in range(1, top):
        if basis == 0:
            for b in range(count):
                table[n + 1, b] = ((2 * n + 1) * table[1, b] * table[n, b] - n * table[n - 1, b]) / (n + 1)
        elif basis == 1:
            for b in range(count):
                table[n + 1, b] = 2.0 * table[1, b] * table[n, b] - table[n - 1, b]
        else:
            harmonic = (n + 1) // 2
            for b in range(count):
                angle = harmonic * math.pi * table[1, b]
                table[n + 1, b] = math.sin(angle) if n % 2 else math.cos(angle)


@njit(cache=True, nogil=True, inline="always")
def _expand_block(
    x: np.ndarray,
    k0: int,
    count: int,
    plan,
    factors: np.ndarray,
    basis: int,
    table: np.ndarray,
    phi: np.ndarray,
) -> None:
    """phi[t, b] = prod_i P_{e_ti}(x[k0 + b, i]), multiplied from 1.0 in input order.

    1.0 first and the inputs in order is what ``expansions.term_features_reference``
    does (and ``expand``, whose single-input columns are 1.0 * P exactly), so the bits agree.
    ``plan`` is :func:`_sparse_terms` of the terms: only the inputs some term reads get
    polynomials, and each term visits only its own entries. A long lag span's dictionary
    (hundreds of inputs, averages over dozens of them) costs what its terms read.
    """
    e_start, e_input, e_degree, f_start, f_input, f_weight, need = plan
    for i in range(x.shape[1]):
        if need[i] > 0:
            _univariate_block(x, k0, count, i, need[i], basis, table[i])
    for t in range(e_start.shape[0] - 1):
        for b in range(count):
            phi[t, b] = 1.0
        for e in range(e_start[t], e_start[t + 1]):
            row = table[e_input[e], e_degree[e]]
            for b in range(count):
                phi[t, b] *= row[b]
    _factor_block(x, k0, count, f_start, f_input, f_weight, factors, phi)


@njit(cache=True, nogil=True, inline="always")
def _factor_block(
    x: np.ndarray,
    k0: int,
    count: int,
    f_start: np.ndarray,
    f_input: np.ndarray,
    f_weight: np.ndarray,
    factors: np.ndarray,
    phi: np.ndarray,
) -> None:
    """phi[t, b] *= g_t(b_t + w_t . x(k0 + b)) for every term with a factor, over its non-zero weights in order."""
    for t in range(factors.shape[0]):
        if factors[t, 0] != 0.0:
            kind = int(factors[t, 0])
            for b in range(count):
                z = factors[t, 1]
                for f in range(f_start[t], f_start[t + 1]):
                    z += f_weight[f] * x[k0 + b, f_input[f]]
                phi[t, b] *= factor_value(kind, z)


@njit(cache=True, nogil=True)
def term_expansion(x: np.ndarray, exponents: np.ndarray, basis: int, factors: np.ndarray, out: np.ndarray) -> None:
    """out[k, t] = prod_i P_{e_ti}(x[k, i]): ``expansions.term_features`` in one compiled pass.

    Each sample's polynomials are computed once and shared by all its terms; numpy
    instead makes a pass over the whole batch per degree and per term, several times
    the arithmetic in memory traffic.
    """
    n_samples = x.shape[0]
    block = EXPANSION_BLOCK if out.strides[1] <= out.strides[0] else COLUMN_MAJOR_BLOCK
    table = np.empty((x.shape[1], _top_degree(exponents) + 1, block))
    phi = np.empty((exponents.shape[0], block))
    plan = _sparse_terms(exponents, factors)
    for k0 in range(0, n_samples, block):
        count = min(block, n_samples - k0)
        _expand_block(x, k0, count, plan, factors, basis, table, phi)
        for t in range(exponents.shape[0]):  # term by term: contiguous runs in a column-major ``out`` too
            for b in range(count):
                out[k0 + b, t] = phi[t, b]


@njit(cache=True, nogil=True, inline="always")
def _augmented_rows(
    x: np.ndarray,
    targets: np.ndarray,
    k0: int,
    plan,
    factors: np.ndarray,
    basis: int,
    table: np.ndarray,
    phi: np.ndarray,
    rows: np.ndarray,
) -> int:
    """rows[b] = [phi(x[k0 + b]) | d(k0 + b)] for one block; returns how many rows it filled.

    The one place both least-squares kernels (normal equations and Givens QR) form the
    augmented rows they consume.
    """
    n_terms = phi.shape[0]
    count = min(EXPANSION_BLOCK, x.shape[0] - k0)
    _expand_block(x, k0, count, plan, factors, basis, table, phi)
    for b in range(count):
        for t in range(n_terms):
            rows[b, t] = phi[t, b]
        rows[b, n_terms] = targets[k0 + b]
    return count


@njit(cache=True, nogil=True)
def normal_equations(
    x: np.ndarray, targets: np.ndarray, exponents: np.ndarray, factors: np.ndarray, basis: int, gram: np.ndarray
) -> None:
    """gram += [Phi | d]' [Phi | d], each sample's features expanded on the fly.

    The batch least-squares fit needs only Phi' Phi (gram[:p, :p]), Phi' d
    (gram[:p, p]) and d' d, so the N x p feature matrix (70 MB at 550 000 samples and
    16 terms) is never built. Full rows rather than the upper triangle: the fixed
    length vectorises, and costs less than half the work it saves.
    """
    n_samples, n_terms = x.shape[0], exponents.shape[0]
    table = np.empty((x.shape[1], _top_degree(exponents) + 1, EXPANSION_BLOCK))
    rows = np.empty((EXPANSION_BLOCK, n_terms + 1))
    phi = np.empty((n_terms, EXPANSION_BLOCK))
    plan = _sparse_terms(exponents, factors)
    for k0 in range(0, n_samples, EXPANSION_BLOCK):
        count = _augmented_rows(x, targets, k0, plan, factors, basis, table, phi, rows)
        for b in range(count):
            for i in range(n_terms + 1):
                v = rows[b, i]
                for j in range(n_terms + 1):
                    gram[i, j] += v * rows[b, j]


@njit(cache=True, nogil=True)
def qr_rows(
    x: np.ndarray, targets: np.ndarray, exponents: np.ndarray, factors: np.ndarray, basis: int, r: np.ndarray
) -> None:
    """Update the triangular R of [Phi | d] (p + 1 columns) with every sample, by Givens rotations.

    R' R = [Phi | d]' [Phi | d] as with :func:`normal_equations`, but R is formed from
    the rows by orthogonal transformations, so its conditioning is that of Phi, not
    its square: what an ill-conditioned expansion needs. Compiled and single-threaded
    on purpose: numpy's QR of tall blocks of rows runs on OpenBLAS's threads, and on a
    busy 2-core machine took 1.5-50 s for 550 000 rows of 16-42 columns, where this
    loop takes about 0.45 us a row at 16 columns and 1 us at 31.
    """
    n_samples, n_terms = x.shape[0], exponents.shape[0]
    table = np.empty((x.shape[1], _top_degree(exponents) + 1, EXPANSION_BLOCK))
    rows = np.empty((EXPANSION_BLOCK, n_terms + 1))
    phi = np.empty((n_terms, EXPANSION_BLOCK))
    plan = _sparse_terms(exponents, factors)
    for k0 in range(0, n_samples, EXPANSION_BLOCK):
        count = _augmented_rows(x, targets, k0, plan, factors, basis, table, phi, rows)
        for b in range(count):
            _givens_row(r, rows[b])


@njit(cache=True, nogil=True, inline="always")
def _givens_row(r: np.ndarray, row: np.ndarray) -> None:
    """Rotate ``row`` into the upper triangular ``r``, zeroing it entry by entry."""
    n = len(row)
    for j in range(n):
        b = row[j]
        if b == 0.0:
            continue
        a = r[j, j]
        h = math.hypot(a, b)
        c, s = a / h, b / h
        r[j, j] = h
        for col in range(j + 1, n):
            upper, lower = r[j, col], row[col]
            r[j, col] = c * upper + s * lower
            row[col] = c * lower - s * upper
