"""The compiled learning rules: every learning rule of the package, once.

A LeNN update touches ~15 weights; done as numpy calls per sample, interpreter
overhead (microseconds per call) costs 100x the arithmetic. So each rule is written
as a plain loop over samples and compiled with numba (``core.jit``). There is no second, vectorised
copy to keep in sync: the numpy-level models call these functions for one sample
online and for 50 000 samples offline, which is also why a live identifier and an
offline evaluation of its recording agree to the last bit.

Conventions shared by all rules:
- ``y_out[k]`` receives the prediction made *before* the update of sample k
  (the a-priori output), from which the caller computes e(k) = d(k) - y_out[k].
- ``learn`` False runs the forward pass only (frozen weights, the paper's test).
- The return value is the number of samples processed; a smaller value means the
  update of sample ``returned`` would have produced a non-finite weight, and the
  kernel stopped *before* applying it, so the weights are still finite. The caller
  (the divergence guard) decides what to do.
"""

from __future__ import annotations

import math

import numpy as np

from lenn_ros.core.jit import njit


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
