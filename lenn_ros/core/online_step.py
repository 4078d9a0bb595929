"""One compiled call per live sample: score, learn, push the history, expand, predict.

The live identifier used to spend about 70 us of Python per sample around a learning
rule that costs well under 1 us compiled: building the regressor as a list, checking
and clipping it with numpy, expanding it in Python, and two kernel calls through
numba's dispatcher. :func:`functional_link_step` does all of it in one call, with the
same arithmetic in the same order as the Python path of
:meth:`lenn_ros.core.structure.Identifier.step` (regressor of
:meth:`~lenn_ros.core.structure.ModelStructure.regressor_row`, the compiled
:func:`~lenn_ros.core.batch_kernels.term_expansion`, the learning rule's own kernel), so
the two paths agree bit for bit and a test holds them to it.

The state the call carries from one sample to the next lives in small arrays owned by
the caller (:class:`StepState`), not in the kernel, so a rollback, a gap or a reload
is plain Python on those arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lenn_ros.core.batch_kernels import term_expansion
from lenn_ros.core.jit import njit
from lenn_ros.core.learning_rules import functional_link_nlms, functional_link_rls, functional_link_sgd, leverage

SOLVER_CODES = {"sgd": 0, "nlms": 1, "rls": 2}
NLMS_EPSILON = 1e-6  # as FunctionalLinkNetwork.update_features passes it

#: ``out`` of :func:`functional_link_step`: what the caller reads back. LEVERAGE: phi' P phi of y^(k+1)'s
#: pattern (RLS; 0 for the other rules), the part of the one-step variance the weights' uncertainty adds
PRIOR, Y_HAT_NEXT, CLIPPED, STATUS, LINEAR_PREVIOUS, LEVERAGE = range(6)
#: STATUS values
OK, DIVERGED, NON_FINITE = 1, 0, -1


@dataclass
class StepState:
    """History (newest first), the pending pattern and the scratch one live sample needs.

    ``counts[0]`` is how many history entries are filled, ``counts[1]`` whether a
    prediction is pending (its pattern in ``phi``, its linear part in ``linear``).
    """

    u_history: np.ndarray
    y_history: np.ndarray
    counts: np.ndarray
    linear: np.ndarray
    x: np.ndarray
    phi: np.ndarray
    scratch: np.ndarray
    out: np.ndarray
    u_now: np.ndarray

    @classmethod
    def empty(cls, window: int, n_inputs: int, n_features: int, channels: int = 1) -> StepState:
        """``channels``: the input channels the output sees (u for a single-channel model; the other
        channels for one output of a several-channel model), one column of the u history each."""
        return cls(
            u_history=np.zeros((window, channels)),
            y_history=np.zeros(window),
            counts=np.zeros(2, dtype=np.int64),
            linear=np.zeros(1),
            x=np.zeros((1, n_inputs)),
            phi=np.zeros((1, n_features)),
            scratch=np.zeros(2),
            out=np.zeros(6),
            u_now=np.zeros(channels),
        )

    def restart(self) -> None:
        """Forget the history and the pending prediction (a gap, a rejected sample)."""
        self.counts[:] = 0


@njit(cache=True, nogil=True, inline="always")
def _rule(
    solver: int,
    weights: np.ndarray,
    momentum: np.ndarray,
    covariance: np.ndarray,
    phi: np.ndarray,
    target: np.ndarray,
    feature_branch: np.ndarray,
    n_branches: int,
    rule: np.ndarray,
    tanh_output: bool,
    learn: bool,
    y_out: np.ndarray,
) -> int:
    """The model's rule on one pattern; ``rule`` = alpha, beta, output_scale, nlms_step, forgetting, trace bound."""
    if solver == 0:
        alpha, beta, scale = rule[0], rule[1], rule[2]
        return functional_link_sgd(
            weights, momentum, phi, target, feature_branch, n_branches, alpha, beta, tanh_output, scale, learn, y_out
        )
    if solver == 1:
        return functional_link_nlms(weights, phi, target, rule[3], NLMS_EPSILON, learn, y_out)
    return functional_link_rls(weights, covariance, phi, target, rule[4], rule[5], learn, y_out, y_out[:0])


@njit(cache=True, nogil=True, inline="always")
def _push(u_history: np.ndarray, y_history: np.ndarray, counts: np.ndarray, u: np.ndarray, y: float) -> bool:
    """Newest first, as ``Identifier._push``; the channels' history is a matrix, one column each. True once full."""
    window = len(y_history)
    channels = len(u)
    for i in range(window - 1, 0, -1):
        y_history[i] = y_history[i - 1]
        for c in range(channels):
            u_history[i, c] = u_history[i - 1, c]
    y_history[0] = y
    for c in range(channels):
        u_history[0, c] = u[c]
    if counts[0] < window:
        counts[0] += 1
    return counts[0] >= window


@njit(cache=True, nogil=True, inline="always")
def _regressor(
    x: np.ndarray,
    u_history: np.ndarray,
    y_history: np.ndarray,
    geometry: np.ndarray,
    lags: np.ndarray,
    known_a: np.ndarray,
    known_b: np.ndarray,
) -> tuple[float, int]:
    """x(k) clipped into [-1, 1] and lin(k), as the structure's ``regressor_row``; (lin, clipped or -1 if non-finite).

    ``geometry`` = y_offset, y_scale, output_offset, then offset and scale of each input
    channel; ``lags`` = the output's own lags, then each channel's. The known linear part is
    output_offset + sum_i a_i y(k - i) + sum_c sum_i b_ci u_c(k - i) (``known_b``: one row per channel).
    """
    column = 0
    for i in range(lags[0]):
        x[0, column] = (y_history[i] - geometry[0]) / geometry[1]
        column += 1
    for c in range(len(lags) - 1):
        offset, scale = geometry[3 + 2 * c], geometry[4 + 2 * c]
        for i in range(lags[c + 1]):
            x[0, column] = (u_history[i, c] - offset) / scale
            column += 1
    linear = geometry[2]
    for i in range(len(known_a)):
        linear = linear + known_a[i] * y_history[i]
    for c in range(known_b.shape[0]):
        for i in range(known_b.shape[1]):
            linear = linear + known_b[c, i] * u_history[i, c]
    clipped = 0
    for i in range(column):
        value = x[0, i]
        if not math.isfinite(value):
            return linear, -1
        if value > 1.0 or value < -1.0:
            x[0, i] = min(1.0, max(-1.0, value))
            clipped += 1
    return linear, clipped


@njit(cache=True, nogil=True)
def functional_link_step(
    u: np.ndarray,
    y: float,
    learn: bool,
    score: bool,
    u_history: np.ndarray,
    y_history: np.ndarray,
    counts: np.ndarray,
    linear_pending: np.ndarray,
    x: np.ndarray,
    phi: np.ndarray,
    scratch: np.ndarray,
    geometry: np.ndarray,
    lags: np.ndarray,
    known_a: np.ndarray,
    known_b: np.ndarray,
    exponents: np.ndarray,
    factors: np.ndarray,
    basis: int,
    solver: int,
    weights: np.ndarray,
    momentum: np.ndarray,
    covariance: np.ndarray,
    feature_branch: np.ndarray,
    n_branches: int,
    rule: np.ndarray,
    tanh_output: bool,
    out: np.ndarray,
) -> None:
    """The pair (u(k), y_p(k)): learn from y^(k)'s error, then predict y^(k+1): the only compiled step.

    ``u`` holds the input channels the output sees (one for a single-channel model, the
    other channels for one output of a several-channel model); ``geometry``, ``lags`` and
    the known parts are :func:`_regressor`'s. With ``score`` the pending prediction is
    scored (and learnt from if ``learn``); a learning step that would make the model
    non-finite stops the call there with STATUS DIVERGED and nothing pushed, so the
    caller can roll the model back and call again without ``score``. ``out`` gets PRIOR
    (the network's part of y^(k), nan if none), Y_HAT_NEXT (nan until the history is
    full), CLIPPED (network inputs outside [-1, 1]), STATUS and LINEAR_PREVIOUS.
    """
    if not _score(y, learn, score, counts, linear_pending, phi, scratch, solver, weights, momentum, covariance,
                  feature_branch, n_branches, rule, tanh_output, out):  # fmt: skip
        return
    if not _push(u_history, y_history, counts, u, y):
        return
    linear, clipped = _regressor(x, u_history, y_history, geometry, lags, known_a, known_b)
    _predict(linear, clipped, x, exponents, factors, basis, counts, linear_pending, phi, scratch, solver, weights,
             momentum, covariance, feature_branch, n_branches, rule, tanh_output, out)  # fmt: skip


@njit(cache=True, nogil=True, inline="always")
def _score(
    y: float,
    learn: bool,
    score: bool,
    counts: np.ndarray,
    linear_pending: np.ndarray,
    phi: np.ndarray,
    scratch: np.ndarray,
    solver: int,
    weights: np.ndarray,
    momentum: np.ndarray,
    covariance: np.ndarray,
    feature_branch: np.ndarray,
    n_branches: int,
    rule: np.ndarray,
    tanh_output: bool,
    out: np.ndarray,
) -> bool:
    """y_p(k) scores (and, if ``learn``, teaches) the pending y^(k); False: the step diverged, stop there."""
    out[PRIOR] = math.nan
    out[Y_HAT_NEXT] = math.nan
    out[CLIPPED] = 0.0
    out[STATUS] = OK
    out[LINEAR_PREVIOUS] = linear_pending[0]
    out[LEVERAGE] = 0.0
    target, y_out = scratch[0:1], scratch[1:2]
    if score and counts[1]:
        target[0] = y - linear_pending[0]
        done = _rule(
            solver,
            weights,
            momentum,
            covariance,
            phi,
            target,
            feature_branch,
            n_branches,
            rule,
            tanh_output,
            learn,
            y_out,
        )
        out[PRIOR] = y_out[0]
        if done < 1:
            out[STATUS] = DIVERGED
            return False
    counts[1] = 0
    return True


@njit(cache=True, nogil=True, inline="always")
def _predict(
    linear: float,
    clipped: int,
    x: np.ndarray,
    exponents: np.ndarray,
    factors: np.ndarray,
    basis: int,
    counts: np.ndarray,
    linear_pending: np.ndarray,
    phi: np.ndarray,
    scratch: np.ndarray,
    solver: int,
    weights: np.ndarray,
    momentum: np.ndarray,
    covariance: np.ndarray,
    feature_branch: np.ndarray,
    n_branches: int,
    rule: np.ndarray,
    tanh_output: bool,
    out: np.ndarray,
) -> None:
    """y^(k+1) from the regressor x(k) (expanded into ``phi``, kept pending for y_p(k+1) to teach)."""
    if clipped < 0:
        out[STATUS] = NON_FINITE
        return
    out[CLIPPED] = clipped
    target, y_out = scratch[0:1], scratch[1:2]
    term_expansion(x, exponents, basis, factors, phi)
    _rule(
        solver, weights, momentum, covariance, phi, target, feature_branch, n_branches, rule, tanh_output, False, y_out
    )
    out[Y_HAT_NEXT] = linear + y_out[0]
    if solver == 2:
        out[LEVERAGE] = leverage(covariance, phi, 0)
    linear_pending[0] = linear
    counts[1] = 1


@dataclass
class StepPlan:
    """What :func:`functional_link_step` needs of one model and structure, fixed while the model lives.

    The learned arrays and the rule's hyper-parameters are read from the model on every
    call: a rollback replaces the arrays, and alpha or the forgetting factor may be
    changed live. One plan for any ``ModelStructure``, read through its ``input_channels()``
    and ``known_parts()``: one input channel, or (one output of a several-channel model)
    the other channels its couplings name.
    """

    state: StepState
    geometry: np.ndarray
    lags: np.ndarray
    known_a: np.ndarray
    known_b: np.ndarray
    exponents: np.ndarray
    factors: np.ndarray
    basis: int
    solver: int
    tanh_output: bool
    n_branches: int
    rule: np.ndarray = field(default_factory=lambda: np.zeros(6))  # the rule's hyper-parameters (see run)
    rule_key: tuple = ()  # the model's values they were filled from

    @classmethod
    def for_model(cls, model: object, structure: object) -> StepPlan | None:
        """The plan, or None where the model has no compiled step (MLP, trigonometric basis, or no numba)."""
        from lenn_ros.core import jit, term_kernels
        from lenn_ros.core.expansions import COMPILED_BASES

        term_exponents = getattr(model, "term_exponents", None)
        if not (
            jit.JIT
            and term_exponents is not None
            and getattr(model, "basis", None) in COMPILED_BASES
            and getattr(model, "solver", None) in SOLVER_CODES
            and getattr(model, "out_of_range", None) == "clip"  # "error" raises from Python, with its text
        ):
            return None
        if not model.is_initialised:
            model._initialise()
        exponents, _branch_of = term_exponents()
        # the output's channel, then those it reads (u; or the other channels of a several-channel model)
        (y_lags, y_offset, y_scale), *others = structure.input_channels()
        known_a, *known_others = structure.known_parts()
        lags = [channel[0] for channel in others]
        known_b = np.zeros((len(others), max((len(k) for k in known_others), default=0)))
        for c, weights in enumerate(known_others):
            known_b[c, : len(weights)] = weights
        geometry = [y_offset, y_scale, structure.output_offset]
        for _lags, offset, scale in others:
            geometry += [offset, scale]
        return cls(
            state=StepState.empty(structure.warm_up, structure.n_inputs, exponents.shape[0], channels=len(lags)),
            geometry=np.array(geometry, dtype=np.float64),
            lags=np.array([y_lags, *lags], dtype=np.int64),
            known_a=np.asarray(known_a, dtype=np.float64),
            known_b=np.ascontiguousarray(known_b, dtype=np.float64),
            exponents=np.ascontiguousarray(exponents, dtype=np.int64),
            factors=model.term_factors(),
            basis=term_kernels.BASIS_CODES[model.basis],
            solver=SOLVER_CODES[model.solver],
            tanh_output=model.output == "tanh",
            n_branches=int(model.feature_branch_.max(initial=0)) + 1,
        )

    def run(self, model: object, u: float | np.ndarray, y: float, learn: bool, score: bool) -> np.ndarray:
        """One :func:`functional_link_step`; returns its ``out`` (read it at once).

        ``u``: the one input of a single-channel model, or the channels one output of a
        several-channel model sees (an array).
        """
        state = self.state
        # the hyper-parameters are read on every call (alpha, forgetting may change live); the
        # array the kernel reads is refilled only when one of them changed (a tuple compare is
        # a third of the refill, which needs the trace bound's arithmetic)
        key = (model.alpha, model.beta, model.output_scale, model.nlms_step, model.forgetting,
               model.max_trace, model.initial_covariance)  # fmt: skip
        if key != self.rule_key:
            self.rule[:] = (key[0], key[1], key[2], key[3], key[4], model.trace_bound)
            self.rule_key = key
        if type(u) is float or np.ndim(u) == 0:
            state.u_now[0] = u  # (one channel: an item store, not a slice assignment)
        else:  # the channels one output of a several-channel model reads (none: its u slot has no lags)
            state.u_now[: len(u)] = u
        functional_link_step(
            state.u_now,
            float(y),
            bool(learn),
            bool(score),
            state.u_history,
            state.y_history,
            state.counts,
            state.linear,
            state.x,
            state.phi,
            state.scratch,
            self.geometry,
            self.lags,
            self.known_a,
            self.known_b,
            self.exponents,
            self.factors,
            self.basis,
            self.solver,
            model.weights_,
            model.momentum_,
            model.covariance_,
            model.feature_branch_,
            self.n_branches,
            self.rule,
            self.tanh_output,
            state.out,
        )
        if learn and score and state.out[STATUS] != DIVERGED and not math.isnan(state.out[PRIOR]):
            model.n_samples_seen_ += 1
        return state.out
