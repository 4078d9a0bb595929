"""Series-parallel model structures: what the network sees and what it must learn.

The paper identifies each plant class with a model of the same class: the known
linear part is computed, the network learns only the unknown nonlinear part, and in
training the *plant's* past outputs (not the model's) form the regressor
(series-parallel, Fig. 1). This module turns (u, y_p) series into the network's
inputs and targets, one sample at a time or a whole series at once, with the same
arithmetic either way.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from lenn_ros.core.free_run import FREE_RUN_DIVERGENCE_BOUND, identifier_free_run
from lenn_ros.core.free_run_guard import WINDOW_BLOCKS, BatchGuard, FreeRunGuard
from lenn_ros.core.networks import DivergenceError, OnlineRegressor
from lenn_ros.core.online_step import (
    CLIPPED,
    DIVERGED,
    LEVERAGE,
    LINEAR_PREVIOUS,
    NON_FINITE,
    PRIOR,
    STATUS,
    Y_HAT_NEXT,
    StepPlan,
)
from lenn_ros.core.target_variance import TargetVariance


@dataclass(frozen=True)
class ModelStructure:
    """y^(k+1) = sum a_i y(k-i) + sum b_i u(k-i) + N[y(k..)/SF_y, u(k..)/SF_u].

    - ``y_lags`` / ``u_lags``: how many past plant outputs / inputs feed the network.
    - ``known_a`` / ``known_b``: the known linear part (Model 1's a_i, Model 2's b_i).
    - ``y_scale`` / ``u_scale``: the paper's scale factor SF; the network sees y / SF
      so its inputs lie in [-1, 1] (a Legendre requirement).
    - ``y_offset`` / ``u_offset``: centring, the network sees (y - y_offset) / y_scale;
      real signals rarely sit symmetric about 0 (``lenn-ros fit`` takes both from the data).
    - ``output_offset``: a known constant in y^(k+1), so a gradient-trained network
      learns the deviation from the operating point rather than climbing to it.
    - ``separate``: Model 3's N1[y] + N2[u], two networks summed, rather than one.
    - ``others``: further channels the network reads after u, (lags, offset, scale) each. One
      output of a several-channel model is this structure: it reads the other outputs and
      the inputs its couplings name, the first of them in the ``u_*`` fields, the rest here;
      the ``u`` its methods take is then a matrix, one column per channel after the output.
    - ``history``: samples of history before the first prediction, at least (the outputs of
      a several-channel model all predict from the same sample on).
    - ``y_abs``: the sensor reads the absolute value of the output (a pulse counter on a
      speed that changes sign). The model is of the signed output, whose sign is a hidden
      state no NARX of |y| carries through a free run; each measured y takes the sign the
      model gives it (its free run alongside, or its prediction near zero:
      :class:`SignTracker`), and what is published and scored is |y^|.

    One description for any number of channels: the compiled step and the free run read
    it through :meth:`input_channels` and :meth:`known_parts`.
    """

    y_lags: int = 0
    u_lags: int = 1
    known_a: tuple[float, ...] = ()
    known_b: tuple[float, ...] = ()
    y_scale: float = 1.0
    u_scale: float = 1.0
    separate: bool = False
    y_offset: float = 0.0
    u_offset: float = 0.0
    output_offset: float = 0.0
    others: tuple[tuple[int, float, float], ...] = ()
    history: int = 1
    y_abs: bool = False

    def __post_init__(self) -> None:
        if min(self.y_lags, self.u_lags, *(lags for lags, _, _ in self.others)) < 0 or self.n_inputs == 0:
            raise ValueError("the network needs at least one input: y_lags + u_lags >= 1")
        if min(self.y_scale, self.u_scale, *(scale for _, _, scale in self.others)) < 0:
            raise ValueError("scale factors must be positive (0: not yet known, learnt by a session's warm-up)")
        if self.separate and (self.y_lags == 0 or self.u_lags == 0):
            raise ValueError("separate N1[y] + N2[u] needs both y_lags and u_lags >= 1")

    @property
    def scaled(self) -> bool:
        """Whether every scale factor is known (0: to be learnt from the first data, core.warmup)."""
        return self.y_scale > 0 and self.u_scale > 0 and all(scale > 0 for _, _, scale in self.others)

    @property
    def n_inputs(self) -> int:
        return self.y_lags + self.u_lags + sum(lags for lags, _, _ in self.others)

    @property
    def y_history(self) -> int:
        return max(self.y_lags, len(self.known_a), 1)

    @property
    def u_history(self) -> int:
        return max(self.u_lags, len(self.known_b), 1)

    @property
    def warm_up(self) -> int:
        """Samples needed before the first regressor is complete."""
        return max(self.y_history, self.u_history, self.history, *(lags for lags, _, _ in self.others))

    def input_channels(self) -> list[tuple[int, float, float]]:
        """(lags, offset, scale) of each channel the network reads, in regressor order: the output, then u.

        The description every path shares with one output of a several-channel model
        (the compiled step and the free run), for one input or several."""
        return [(self.y_lags, self.y_offset, self.y_scale), (self.u_lags, self.u_offset, self.u_scale), *self.others]

    def known_parts(self) -> list[tuple[float, ...]]:
        """The known linear weights on each channel's lags, in :meth:`input_channels` order."""
        return [tuple(self.known_a), tuple(self.known_b), *([()] * len(self.others))]

    def branches(self) -> list[list[int]] | None:
        """Network input groups: [[y inputs], [u inputs]] for Model 3, else one group."""
        if not self.separate:
            return None
        return [list(range(self.y_lags)), list(range(self.y_lags, self.n_inputs))]

    def regressors(self, u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Network inputs x(k) and known linear part lin(k) for every complete k.

        Rows are for k = warm_up - 1 .. N - 1 (each predicts y(k+1)); ``u``/``y`` hold
        u(0..N-1) and y(0..N-1), already paired.
        """
        u = np.asarray(u, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        first = self.warm_up - 1
        k = np.arange(first, len(y))
        # a[k - i] as a slice: the same values without gathering a copy per lag; indexing
        # when there is nothing to slice or u is too short (it raises, as it always did)
        sliced = len(k) > 0 and len(u) >= len(y)

        def lag(a: np.ndarray, i: int) -> np.ndarray:
            return a[first - i : len(y) - i] if sliced else a[k - i]

        # one input: u a vector; several (one output of a several-channel model): a column per channel
        channels = [u[:, c] for c in range(u.shape[1])] if u.ndim == 2 else [u]
        columns = [(lag(y, i) - self.y_offset) / self.y_scale for i in range(self.y_lags)]
        for c, (lags, offset, scale) in enumerate(self.input_channels()[1:]):
            columns += [(lag(channels[c], i) - offset) / scale for i in range(lags)]
        x = np.stack(columns, axis=1) if len(k) else np.empty((0, self.n_inputs))
        linear = np.full(len(k), float(self.output_offset))
        for i, a in enumerate(self.known_a):
            linear = linear + a * lag(y, i)
        for i, b in enumerate(self.known_b):
            linear = linear + b * lag(channels[0], i)
        return x, linear

    def regressor_row(self, u_past: list[float], y_past: list[float]) -> tuple[np.ndarray, float]:
        """The last row of :meth:`regressors` from histories kept newest first, for one sample.

        The same arithmetic in the same order as the batch path (so live and offline
        agree bit for bit), without building arrays of the whole history.
        """
        row = [(y_past[i] - self.y_offset) / self.y_scale for i in range(self.y_lags)]
        vector = len(u_past) > 0 and np.ndim(u_past[0]) > 0  # an entry holds every channel after the output
        for c, (lags, offset, scale) in enumerate(self.input_channels()[1:]):
            row += [((u_past[i][c] if vector else u_past[i]) - offset) / scale for i in range(lags)]
        linear = float(self.output_offset)
        for i, a in enumerate(self.known_a):
            linear = linear + a * y_past[i]
        for i, b in enumerate(self.known_b):
            linear = linear + b * (u_past[i][0] if vector else u_past[i])
        return np.array([row], dtype=np.float64), linear

    def training_pairs(self, u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Series-parallel pairs: inputs x(k), targets y(k+1) - lin(k), and lin(k).

        Row r is k = warm_up - 1 + r and predicts y(k+1) = lin(k) + network(x(k)); the
        last regressor row has no y(k+1) yet and is left out. With
        :meth:`pairs_from_regressors`, the one place this one-sample offset is written,
        so batch training, the learning curves and the benchmarks cannot disagree about
        which output a row predicts.
        """
        x, linear = self.regressors(u, y)
        return self.pairs_from_regressors(x, linear, y)

    def pairs_from_regressors(
        self, x: np.ndarray, linear: np.ndarray, y: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`training_pairs` from the output of :meth:`regressors` on the same ``y``.

        For a caller that also needs the last regressor row (which predicts a sample
        not yet measured), so the regressors are not built twice.
        """
        targets = np.asarray(y, dtype=np.float64)[self.warm_up :] - linear[:-1]
        return x[:-1], targets, linear[:-1]


@dataclass(slots=True)
class StepResult:
    """What one paired sample (u(k), y_p(k)) produced."""

    index: int
    y_hat_next: float | None = None  # prediction of y_p(k+1), if the regressor is complete
    error: float | None = None  # e(k) = y_p(k) - y^(k), if y^(k) had been predicted
    y_hat: float | None = None  # y^(k) itself
    learned: bool = False
    event: str = ""  # "", "gap", "duplicate", "rejected", "diverged", "resumed"
    leverage: float = 0.0  # phi' P phi of y_hat_next's pattern (RLS; 0: other rules), for its one-step std
    y_hat_next_std: float | None = None  # one-step std of y_hat_next (the session's core.spread fills it in)
    y_hat_std: float | None = None  # ... of y_hat, the prediction this sample scored
    y_hat_next_band: float | None = None  # half-width of y_hat_next's live 95 % band (core.spread.LiveBand)
    y_hat_band: float | None = None  # ... of y_hat's

    @property
    def outputs(self) -> list[StepResult]:
        """Per output (one): what a model of several outputs gives per output too (``MimoStepResult``)."""
        return [self]

    def gather_stds(self) -> None:
        """The monitors filled the stds in: nothing to gather for one output."""


@dataclass
class Identifier:
    """Online series-parallel identification, one paired sample at a time.

    The live ROS node and the offline evaluation both drive this class, so a
    recording evaluated offline reproduces what the node computed live, bit for bit
    (:meth:`run` is :meth:`step` over a whole series, batched into the compiled
    kernel). Samples carry an index (the publication sequence number of the pair):
    a gap restarts the regressor history (no prediction across missing samples), a
    repeated or older index is ignored, and neither is ever learnt from. An output its sensor
    reads as |y| (``y_abs``) is signed first, by a :class:`SignTracker`.

    Divergence guard: learning proceeds in blocks of ``health_interval`` learnt
    samples. After each block the mean squared a-priori error is compared with the
    variance of the network's target (y_p minus the known linear part), i.e. with what
    predicting its mean would cost; above ``divergence_ratio`` times it (or if an
    update would make a weight non-finite) the model goes back to the state at the
    start of the last block that passed, learning pauses and ``diverged`` is set. Predictions
    go on from the healthy model.

    The variance is the larger of the block's own and the target's *learnt* variance
    (``target_variance``, :class:`~lenn_ros.core.target_variance.TargetVariance`), so that a
    plant at rest does not roll back a healthy model that stands still.

    After a divergence learning resumes by itself, from the healthy state, once
    ``resume_after`` blocks' worth of learnable samples have passed (``resume_in`` counts
    them down; 0 = stay paused until :meth:`mark_healthy`): a transient cause (a burst
    of bad data, an alpha set too high and set back) does not stop learning for good.
    Each divergence doubles the next pause (up to ``MAX_BACKOFF`` times), and
    ``resume_after`` blocks passed in a row bring it back to one.

    Free-run guard (``free_run_guard``, which ``lenn-ros fit`` turns on for the models it writes):
    the network learns on, and a *kept* state is what a frozen phase, a free run and a saved
    weights file use; the learning model is adopted as the kept one where it simulates the samples
    that followed it better (:mod:`~lenn_ros.core.free_run_guard`; counted: ``guard_checks``,
    ``guard_adopted``). When learning stops (a frozen phase, a test part) the network takes the
    kept state.
    """

    structure: ModelStructure
    model: OnlineRegressor
    learning: bool = True
    health_interval: int = 1000
    divergence_ratio: float = 100.0
    resume_after: int = 10
    counters: dict[str, int] = field(default_factory=dict)
    diverged: bool = False
    free_run_guard: bool = False

    #: The pause after a divergence grows at most to this many times ``resume_after`` blocks.
    MAX_BACKOFF: ClassVar[int] = 64
    #: The output's name: a model of one output is the composite of one (``MimoIdentifier`` names several).
    names: ClassVar[tuple[str, ...]] = ("y",)
    #: As a model of its own: one input channel and one output channel, carried as plain floats (``vector`` False;
    #: an output of a ``MimoIdentifier`` reads several channels, which its composite says).
    n_u: ClassVar[int] = 1
    n_y: ClassVar[int] = 1
    vector: ClassVar[bool] = False

    @property
    def outputs(self) -> list[Identifier]:
        """The per-output identifiers: this one (a model of several outputs composes one per output)."""
        return [self]

    @property
    def models(self) -> list[OnlineRegressor]:
        return [self.model]

    #: The structure's scales and offsets a weights file keeps beside the weights.
    SCALING: ClassVar[tuple[str, ...]] = ("y_scale", "u_scale", "y_offset", "u_offset")

    def save_state(self, path: str | os.PathLike[str]) -> None:
        """The network's weights (atomic, ``OnlineRegressor.save``) with the scaling its inputs had: a run that
        learnt its scales restarts from this file alone (a model of several outputs: one file for all)."""
        structure = self.structure
        scaling = {key: getattr(structure, key) for key in self.SCALING} if structure.scaled else None
        with self.serving():
            self.model.save(path, scaling=scaling)

    def load_state(self, path: str | os.PathLike[str]) -> None:
        """Start from a file of :meth:`save_state` (``ModelFileError`` with the reason, the model untouched)."""
        self.model.load_state(path)

    def __post_init__(self) -> None:
        for name in (
            "samples",
            "learned",
            "gaps",
            "lost",
            "duplicates",
            "rejected",
            "diverged",
            "resumed",
            "clipped",
            "clipped_free_run",
        ):
            self.counters.setdefault(name, 0)
        self._y_past: list[float] = []
        self._u_past: list[float] = []
        self._last_index: int | None = None
        self._pending: tuple[np.ndarray, float, np.ndarray | None] | None = None  # x(k-1), lin(k-1), phi(k-1)
        self._block_errors: list[float] = []
        self._block_targets: list[float] = []
        self._plan: StepPlan | None = None  # the compiled per-sample path, where the model has one
        self._plan_model: OnlineRegressor | None = None  # the model the plan was made for
        self.last_free_run: dict = {}
        self.last_leverage = np.zeros(0)  # run(): phi' P phi of each y^(k) (RLS; 0 elsewhere)
        self._target = TargetVariance()  # what the guard measures a block against
        self.hold_off = 0  # learnable samples of the last pause after a divergence
        self.resume_in = 0  # of them still to pass before learning resumes
        self._backoff = 1
        self._passed_since_resume = 0
        self._signs = SignTracker()  # y_abs: the sign of each |y| (unused otherwise)
        self._guard = FreeRunGuard()  # free_run_guard: the kept state and the samples it is judged on
        self.mark_healthy()

    # -- one sample ------------------------------------------------------------------
    def step(self, index: int, u: float, y: float, learn: bool | None = None) -> StepResult:
        """Process the pair (u(k), y_p(k)) with sample index k."""
        if self.structure.y_abs:
            return self._signs.step(self, index, u, y, learn)
        return self._step(index, u, y, learn)

    @property
    def sign_settled(self) -> bool | None:
        """``y_abs``: whether the sign of |y| has settled since the history last started (learning waits for
        it); None for an output read as it is."""
        return self._signs.settled if self.structure.y_abs else None

    def _step(self, index: int, u: float, y: float, learn: bool | None = None) -> StepResult:
        learn = self.learning if learn is None else learn
        result = StepResult(index=index)
        if self._last_index is not None and index <= self._last_index:
            self.counters["duplicates"] += 1
            result.event = "duplicate"
            return result
        if self._last_index is not None and index != self._last_index + 1:
            self.counters["gaps"] += 1
            self.counters["lost"] += index - self._last_index - 1
            self._restart_history()
            result.event = "gap"
        self._last_index = index
        self.counters["samples"] += 1
        if self._plan_model is not self.model:
            self._check_scaled()
            self._plan_model, self._plan = self.model, StepPlan.for_model(self.model, self.structure)
            self._restart_history()
        if self.free_run_guard:
            self._guard.recent.push(u, y)
            scored = self._pending is not None if self._plan is None else bool(self._plan.state.counts[1])
            if not learn and scored and self._guard.learnt:
                self._learning_stops()
        if self._plan is not None:
            self._step_compiled(self._plan, u, y, learn, result)
            return result
        if self._pending is not None:
            self._score_pending(y, learn, result)
        self._push(u, y)
        if len(self._y_past) >= self.structure.warm_up:
            result.y_hat_next = self._predict_next()
            result.leverage = self._leverage
        return result

    def set_structure(self, structure: ModelStructure) -> None:
        """Take learnt scales and offsets (a session's warm-up) before the first sample is stepped.

        Only before: weights learnt on one scaling mean something else on another.
        """
        if self.counters["samples"]:
            raise ValueError("the structure changes only before the first sample (weights depend on the scaling)")
        self.structure = structure
        self._plan_model = self._plan = None

    def _check_scaled(self) -> None:
        if not self.structure.scaled:
            raise ValueError(
                "y_scale / u_scale are 0 (to be learnt): step the identifier through a Session, whose warm-up "
                "learns them, or give them"
            )

    def _step_compiled(self, plan: StepPlan, u: float, y: float, learn: bool, result: StepResult) -> None:
        """:meth:`step`'s scoring, learning and prediction in one compiled call (same numbers)."""
        if learn and self.diverged:  # (the common case costs no call: this runs for every sample)
            learn = self._may_learn(learn, bool(plan.state.counts[1]), result)
        out = plan.run(self.model, u, y, learn, score=True).tolist()  # Python floats: cheaper to read
        if out[STATUS] == DIVERGED:
            self._on_divergence()
            learn = False
            result.event = "diverged"
            self._record_score(result, y, out[LINEAR_PREVIOUS], out[PRIOR], False)
            out = plan.run(self.model, u, y, False, score=False).tolist()
        elif out[PRIOR] == out[PRIOR]:  # (not nan)
            self._record_score(result, y, out[LINEAR_PREVIOUS], out[PRIOR], learn)
        if out[STATUS] == NON_FINITE:
            raise ValueError("non-finite network input")
        if out[CLIPPED]:
            self.counters["clipped"] += int(out[CLIPPED])
            self.model.n_clipped_ = getattr(self.model, "n_clipped_", 0) + int(out[CLIPPED])
        if out[Y_HAT_NEXT] == out[Y_HAT_NEXT]:
            result.y_hat_next = out[Y_HAT_NEXT]
            result.leverage = out[LEVERAGE]

    def _score_pending(self, y: float, learn: bool, result: StepResult) -> None:
        """y_p(k) has arrived: score the prediction made at k-1 and learn from its error.

        The learning step reuses the regressor (and its expansion) stored when the
        prediction was made, so the update is from exactly the pattern that predicted.
        """
        x_previous, linear_previous, phi_previous = self._pending
        learn = self._may_learn(learn, True, result)
        try:
            if phi_previous is None:
                prior = float(self.model.update(x_previous, y - linear_previous, learn=learn)[0])
            else:
                prior = float(self.model.update_features(phi_previous, y - linear_previous, learn=learn)[0])
        except DivergenceError as error:
            prior = float(error.predictions[0])
            self._on_divergence()
            learn = False
            result.event = "diverged"
        self._record_score(result, y, linear_previous, prior, learn)

    def _may_learn(self, learn: bool, scored: bool, result: StepResult) -> bool:
        """Whether this sample is learnt from: not while paused after a divergence, which a scored
        sample that asked to learn counts down; the one that ends the pause resumes learning."""
        if not learn:
            return False
        if not self.diverged:
            return True
        if not scored or self.resume_after <= 0:
            return False
        if self.resume_in > 0:
            self.resume_in -= 1
            return False
        self._resume()
        result.event = "resumed"
        return True

    def _record_score(self, result: StepResult, y: float, linear_previous: float, prior: float, learn: bool) -> None:
        """y^(k), e(k) into ``result``; a learnt error also into the divergence guard's block."""
        result.y_hat = linear_previous + prior
        result.error = y - result.y_hat
        result.learned = learn
        if learn:
            self.counters["learned"] += 1
            self._guard.learnt = True
            self._block_errors.append(result.error)
            self._block_targets.append(y - linear_previous)
            if len(self._block_errors) == self.health_interval and not self._check_block():
                result.event = "diverged"

    def _predict_next(self) -> float:
        """y^(k+1) from the current history; keeps its regressor pending until y_p(k+1) arrives to learn from."""
        x, linear = self.structure.regressor_row(self._u_past, self._y_past)
        self.counters["clipped"] += sum(1 for value in x[0] if abs(value) > 1.0)
        features = getattr(self.model, "features", None)
        if features is None:  # no expansion to reuse (MLP)
            self._pending = (x, linear, None)
            return float(linear + self.model.predict(x)[0])
        if not self.model.is_initialised:
            self.model._initialise()
        phi = features(x)
        self._pending = (x, linear, phi)
        if getattr(self.model, "solver", None) == "rls":  # (the compiled step's LEVERAGE, where numba is missing)
            self._leverage = float(phi[0] @ self.model.covariance_ @ phi[0])
        return float(linear + self.model.update_features(phi, 0.0, learn=False)[0])

    _leverage = 0.0

    def skip(self, index: int | None = None) -> None:
        """Sample ``index`` was rejected (bad value): the history is broken there.

        The index still counts as consumed, so the next sample is not a gap.
        """
        self.counters["rejected"] += 1
        if index is not None:
            self._last_index = index
        self._restart_history()

    def restart_stream(self) -> None:
        """The sample indices start over (a publisher restarted): forget the history."""
        self._last_index = None
        self._restart_history()

    def _restart_history(self) -> None:
        self._signs.restart()
        self._y_past.clear()
        self._u_past.clear()
        self._pending = None
        if self._plan is not None:
            self._plan.state.restart()
        self._guard.recent.restart(WINDOW_BLOCKS * self.health_interval + self.structure.warm_up)

    def _push(self, u: float, y: float) -> None:
        keep = self.structure.warm_up
        self._y_past.insert(0, y)
        self._u_past.insert(0, u)
        del self._y_past[keep:], self._u_past[keep:]

    # -- divergence guard --------------------------------------------------------------
    def _check_block(self, errors: np.ndarray | None = None, targets: np.ndarray | None = None) -> bool:
        """End of a block of learnt samples: keep it (True) or roll back (False).

        ``errors`` and ``targets`` are a whole block learnt in one kernel call (:meth:`run`),
        given as arrays rather than through the lists :meth:`step` fills sample by sample,
        which cost more to fill and convert than the check itself; the numbers are the same.
        """
        if errors is None or targets is None:
            errors = np.asarray(self._block_errors)
            targets = np.asarray(self._block_targets)
        self._block_errors.clear()
        self._block_targets.clear()
        mse = float(np.mean(errors * errors))
        variance = float(np.var(targets))
        reference = self._target.reference(variance, self.structure.y_scale)
        if not np.isfinite(mse) or mse > self.divergence_ratio * reference + 1e-12:
            self._on_divergence()
            return False
        # The block's a-priori errors vouch for the weights it *started* from; the
        # weights now (after its last update) are vouched for by the next block.
        self._healthy_state = self._candidate_state
        self._candidate_state = self.model.state()
        if self.free_run_guard:
            self._guard.block_end(self.structure, self.model, self.health_interval, self.counters)
        self._target.learn(variance, self.structure.y_scale)
        self._passed_since_resume += 1
        if self._passed_since_resume >= self.resume_after:
            self._backoff = 1
        return True

    def _learning_stops(self) -> None:
        """``free_run_guard``: learning stopped (a frozen phase, a test part): the learning model is judged once
        more, and the network takes the kept state, from which the divergence guard's blocks start again."""
        self._guard.learning_stops(self.structure, self.model, self.health_interval, self.counters)
        kept = self._guard.kept
        if kept is not None:
            self.model.set_state(kept)
            self._healthy_state = self._candidate_state = kept
        self._block_errors.clear()
        self._block_targets.clear()

    def serving(self) -> contextlib.AbstractContextManager[None]:
        """The network holds the kept state for the duration (``free_run_guard``: what a weights file saves)."""
        return self._guard.serving(self.model) if self.free_run_guard else contextlib.nullcontext()

    @property
    def target_variance(self) -> float:
        """The target's variance learnt while it moved (0: not yet): what the guard measures blocks against."""
        return self._target.value

    def _on_divergence(self) -> None:
        self.counters["diverged"] += 1
        self.diverged = True
        self.model.set_state(self._healthy_state)
        self._candidate_state = self._healthy_state  # a resumed block starts from (and vouches for) this state
        self._block_errors.clear()
        self._block_targets.clear()
        self.hold_off = self.resume_in = self._backoff * self.resume_after * self.health_interval
        self._backoff = min(2 * self._backoff, self.MAX_BACKOFF)
        self._passed_since_resume = 0

    def _resume(self) -> None:
        """The pause after a divergence is over: learn again from the healthy state (the model is at it)."""
        self.diverged = False
        self.resume_in = 0
        self.counters["resumed"] += 1

    def mark_healthy(self) -> None:
        """Take the current model state as the one to fall back to.

        Also called to resume after a divergence (e.g. once alpha was lowered) and
        after loading weights.
        """
        if not self.model.is_initialised:
            self.model._initialise()
        self._healthy_state = self.model.state()
        self._candidate_state = self._guard.kept = self._healthy_state
        self.diverged = False
        self.resume_in = 0

    # -- whole series (offline) --------------------------------------------------------------
    def run(
        self,
        u: np.ndarray,
        y: np.ndarray,
        learn: np.ndarray | bool = True,
        changes: Sequence[tuple[int, Callable[[], None]]] = (),
    ) -> np.ndarray:
        """Series-parallel pass over paired series; returns y^(k) (nan where none).

        ``learn`` may be an array over k: whether the error at y(k) is learnt from.
        Runs of samples go to the compiled kernel in one call, cut at the same
        health-check boundaries as :meth:`step`, so the result is the same as calling
        :meth:`step` for every sample (a test checks it).
        ``changes``: (position p, apply) pairs, ``apply`` called where :meth:`step` of sample p
        would come next (a live parameter change, e.g. alpha, made before that sample): the
        run is cut there, so the learning from y(p) on uses what ``apply`` set.
        """
        self._check_scaled()
        u = np.asarray(u, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        learn_mask = np.broadcast_to(np.asarray(learn, dtype=bool), y.shape)
        if self.structure.y_abs:
            return self._signs.run(self, u, y, learn_mask, changes)
        return self._run_batch(u, y, learn_mask, changes)

    def _run_batch(
        self, u: np.ndarray, y: np.ndarray, learn_mask: np.ndarray, changes: Sequence[tuple[int, Callable[[], None]]]
    ) -> np.ndarray:
        x, linear = self.structure.regressors(u, y)
        self.counters["clipped"] += int(np.count_nonzero(np.abs(x) > 1.0))  # incl. the last row, as step counts it
        inputs, targets, linear = self.structure.pairs_from_regressors(x, linear, y)
        first = self.structure.warm_up - 1
        mask, outputs = learn_mask[first + 1 :], y[first + 1 :]  # outputs: y(k+1)
        y_hat = np.full(len(y), np.nan)
        leverage = np.zeros(len(targets))  # phi' P phi of each prediction (RLS), for its one-step std
        self.last_leverage = np.zeros(len(y))
        mask_changes = np.append(np.flatnonzero(mask[1:] != mask[:-1]) + 1, len(targets))
        # sample p's step learns from target p - first - 1 (none yet in the warm-up: before the first)
        cuts = sorted(((max(position - first - 1, 0), apply) for position, apply in changes), key=lambda c: c[0])
        start = 0
        guard = BatchGuard(self, u, y, first)  # free_run_guard: samples pushed and judged where step does it
        while start < len(targets) or cuts:
            while cuts and cuts[0][0] <= start:
                cuts.pop(0)[1]()
            if start >= len(targets):
                break
            guard.before(start, bool(mask[start]))
            paused = bool(mask[start]) and self.diverged and self.resume_after > 0
            if paused and self.resume_in == 0:
                self._resume()  # as step(): the first learnable sample after the pause learns
                paused = False
            learning = bool(mask[start]) and not self.diverged
            if learning:
                limit = start + self.health_interval - len(self._block_errors)
            else:
                limit = start + self.resume_in if paused else len(targets)
            next_change = int(mask_changes[np.searchsorted(mask_changes, start, side="right")])
            next_cut = cuts[0][0] if cuts else len(targets)
            stop = max(start + 1, min(limit, len(targets), next_change, next_cut))  # equal flags, cut at the block
            if paused:
                self.resume_in -= stop - start
            try:
                prior = self._update(inputs[start:stop], targets[start:stop], learning, leverage[start:stop])
            except DivergenceError as error:
                stop = start + error.sample_index + 1
                prior = error.predictions
                self.counters["learned"] += error.sample_index  # learnt before the one that diverged, as step counts
                self._on_divergence()
                learning = False
            y_hat[first + 1 + start : first + 1 + stop] = linear[start:stop] + prior
            if learning:
                self.counters["learned"] += stop - start
                guard.learnt(stop)
                self._score_run(outputs[start:stop] - y_hat[first + 1 + start : first + 1 + stop], targets[start:stop])
            start = stop
        guard.to(len(y))
        self.counters["samples"] += len(y)
        self.last_leverage[first + 1 :] = leverage
        return y_hat

    def signed(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``y`` as the model reads it (``y_abs``: each sample signed as the frozen model predicts it, the
        sign the node gives it); ``y`` itself otherwise. What seeds a free run from measured outputs."""
        y = np.asarray(y, dtype=np.float64)
        return self._signs.signed(self, u, y) if self.structure.y_abs else y

    def _update(self, inputs: np.ndarray, targets: np.ndarray, learning: bool, leverage: np.ndarray) -> np.ndarray:
        """The model's batch update; an RLS functional-link model also fills ``leverage``, as the live step has it."""
        if getattr(self.model, "solver", None) == "rls" and hasattr(self.model, "term_exponents"):
            return self.model.update(inputs, targets, learn=learning, leverage_out=leverage)
        return self.model.update(inputs, targets, learn=learning)

    def _score_run(self, errors: np.ndarray, targets: np.ndarray) -> None:
        """Add a learnt run of :meth:`run` to the divergence guard's block, checking it once full."""
        if not self._block_errors and len(errors) == self.health_interval:  # a whole block at once
            self._check_block(errors, targets.copy())
            return
        self._block_errors.extend(errors.tolist())
        self._block_targets.extend(targets.tolist())
        if len(self._block_errors) == self.health_interval:
            self._check_block()

    def free_run(self, u: np.ndarray, y: np.ndarray, start: int, seeds_signed: bool = False) -> np.ndarray:
        """Parallel model from ``start`` on: the network fed its own past outputs.

        Plant outputs y(0..start-1) seed the model's history (a live switch from
        series-parallel to parallel); from then on only u is taken from the data.
        Returns y^(start..N-1) (frozen weights). Network inputs outside [-1, 1] are
        clipped, so an unstable model saturates instead of overflowing, and counted
        in ``counters["clipped_free_run"]``; ``last_free_run`` says how many and
        whether (and where) the run diverged. Functional-link models run compiled.

        ``y_abs``: the measured |y| before ``start`` is signed as the node signs it
        (:meth:`signed`), and the run is returned as |y^|; ``seeds_signed``: y before
        ``start`` is signed already (a run going on from its own outputs, as a twin's),
        and the run is returned signed.
        """
        return identifier_free_run(self, u, y, start, seeds_signed)


# -- |y| outputs -------------------------------------------------------------------------
class SignTracker:
    """The sign of an output whose sensor reads |y| (``ModelStructure.y_abs``), for its :class:`Identifier`.

    Why it exists: the model is of the signed output, and the sensor gives |y|. Each reading is
    signed as the model predicts it, and learnt from only where that sign can be trusted; deciding
    it is a state machine of its own beside the series-parallel step (two free runs alongside, how
    long they have agreed, how many sure signs in a row), which only ``y_abs`` outputs need. Apart,
    the :class:`Identifier` keeps to its step, its divergence guard and its runs, and hands a
    ``y_abs`` sample over; its history restarts call :meth:`restart`. The methods take the
    identifier they sign for rather than holding it (no reference cycle). It lives in this module,
    not one of its own, because it drives the identifier's private step and builds identifiers
    (the free runs alongside): a module of its own would have to import this one back.
    """

    #: the free run alongside decides a sign beyond this fraction of ``y_scale`` from zero
    SIGN_MARGIN: ClassVar[float] = 0.1

    def __init__(self) -> None:
        self.signed_next: float | None = None  # the signed one-step prediction of the next sample
        self.shadows: list[Identifier] = []  # the free runs alongside
        self.shadow_next: float | None = None  # and their predictions of the next sample
        self.mirror_next: float | None = None
        self.settled = False  # the free runs have forgotten the start (its sign)
        self.agreed = 0  # samples in a row the two free runs have agreed
        self.sure_run = 0  # samples in a row whose sign was sure

    def restart(self) -> None:
        """The identifier's history starts over (a gap, a rejected sample, a new stream): so do the signs."""
        self.signed_next = self.shadow_next = self.mirror_next = None
        self.shadows, self.settled, self.sure_run = [], False, 0

    def sign_for(self, identifier: Identifier, index: int) -> tuple[float, bool]:
        """The sign a measured |y(index)| takes, and whether it is sure.

        Where the free run alongside (:meth:`_step_shadows`) is clearly away from zero
        (SIGN_MARGIN of ``y_scale``), its sign; nearer zero, where a crossing's timing is
        uncertain, the sign of the one-step prediction; + with neither (a history that starts
        over). Sure where the two agree. Why the free run: a history signed the
        wrong way round is the mirror image of the plant, and one-step predictions from it stay
        mirrored (a slow output's next value is mostly its last); a stable model's free run
        forgets its start and follows the input.
        """
        if identifier._last_index is None or index != identifier._last_index + 1:
            return 1.0, False
        free, one = self.shadow_next, self.signed_next
        agree = free is not None and one is not None and (free < 0.0) == (one < 0.0)
        if free is not None and abs(free) >= self.SIGN_MARGIN * identifier.structure.y_scale:
            return (-1.0 if free < 0.0 else 1.0), agree
        return (-1.0 if one is not None and one < 0.0 else 1.0), agree

    def step(self, identifier: Identifier, index: int, u: float, y: float, learn: bool | None) -> StepResult:
        """The identifier's step on the signed output, scored and published as the sensor reads it.

        With y signed as its prediction is, y - y^ is +-(|y| - |y^|): the model learns
        exactly the error the sensor shows, and nothing the sensor cannot tell. A sample is
        learnt only once the sign has settled after a start (the free runs from either sign of
        it agree) and when its sign and those of its whole history were sure: a history signed
        the wrong way round would teach the mirror image of the plant, and one wrong sign at a
        crossing a jump it never made (counted: ``sign_unsure``).
        """
        sign, sure = self.sign_for(identifier, index)
        signed = sign * y
        self.sure_run = self.sure_run + 1 if sure else 0
        trusted = self.settled and self.sure_run > identifier.structure.y_history
        learn = identifier.learning if learn is None else learn
        result = identifier._step(index, u, signed, learn and trusted)
        if result.event == "duplicate":
            return result
        if learn and not trusted and result.y_hat is not None:  # a sample it would have learnt from
            identifier.counters["sign_unsure"] = identifier.counters.get("sign_unsure", 0) + 1
        self.signed_next = result.y_hat_next
        self._step_shadows(identifier, index, u, signed)
        if result.y_hat is not None:
            result.y_hat = abs(result.y_hat)
            result.error = y - result.y_hat
        if result.y_hat_next is not None:
            result.y_hat_next = abs(result.y_hat_next)
        return result

    def _step_shadows(self, identifier: Identifier, index: int, u: float, signed: float) -> None:
        """The free runs alongside: the same weights, fed their own predictions, seeded by the
        signed measurements until they predict, and a second one by their mirror image. Their difference
        is twice what is left of the start (exactly, for a linear model); once it stays within SIGN_MARGIN
        over the output's whole history, a sign the free run decides (beyond SIGN_MARGIN from zero) no
        longer depends on the start's: it is settled, and the second one is dropped. (Mirror images
        meet at zero: one sample of agreement there says nothing.)"""
        structure = identifier.structure
        if not self.shadows or self.shadows[0].model is not identifier.model:
            plain = dataclasses.replace(structure, y_abs=False)
            self.shadows = [Identifier(plain, identifier.model, learning=False) for _ in range(2)]
            self.shadow_next, self.mirror_next, self.settled, self.agreed = None, None, False, 0
        bound = FREE_RUN_DIVERGENCE_BOUND * structure.y_scale
        following = []
        feeds = ((self.shadow_next, signed), (self.mirror_next, -signed))
        for shadow, (own, seed) in zip(self.shadows, feeds[: len(self.shadows)], strict=True):
            value = shadow.step(index, u, seed if own is None else own, learn=False).y_hat_next
            inside = value is not None and abs(value - structure.y_offset) <= bound
            following.append(value if inside else None)
        self.shadow_next, self.mirror_next = following[0], (following[1] if len(following) == 2 else None)
        margin = self.SIGN_MARGIN * structure.y_scale
        agree = None not in following and abs(following[0] - following[-1]) < margin
        self.agreed = self.agreed + 1 if agree else 0
        if len(following) == 2 and self.agreed >= structure.y_history:
            self.settled, self.shadows = True, self.shadows[:1]

    def signed(self, identifier: Identifier, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Each |y| sample signed as the identifier's model, frozen, predicts it (:meth:`Identifier.signed`)."""
        observer = Identifier(identifier.structure, identifier.model, learning=False)
        out = np.empty(len(y))
        for k in range(len(y)):
            out[k] = observer._signs.sign_for(observer, k)[0] * y[k]
            observer.step(k, float(u[k]), float(y[k]), learn=False)
        return out

    def run(
        self,
        identifier: Identifier,
        u: np.ndarray,
        y: np.ndarray,
        learn: np.ndarray,
        changes: Sequence[tuple[int, Callable[[], None]]],
    ) -> np.ndarray:
        """:meth:`Identifier.run` as its step over a fresh history, one sample at a time: each
        sample's sign comes from the predictions made before it, so no batch can be formed ahead."""
        identifier.restart_stream()
        cuts = sorted(changes, key=lambda c: c[0])
        y_hat = np.full(len(y), np.nan)
        identifier.last_leverage = np.zeros(len(y))
        leverage = 0.0  # of the prediction made at the sample before
        for k in range(len(y)):
            while cuts and cuts[0][0] <= k:
                cuts.pop(0)[1]()
            result = identifier.step(k, float(u[k]), float(y[k]), bool(learn[k]))
            if result.y_hat is not None:
                y_hat[k] = result.y_hat
                identifier.last_leverage[k] = leverage
            leverage = result.leverage
        for _, apply in cuts:
            apply()
        identifier.restart_stream()
        return y_hat
