"""The free-run guard: live learning changes the model only where it simulates better on samples it never saw.

Why it exists: an identifier learns one step ahead (series-parallel), and a model that
``lenn-ros fit`` chose and refined by its *free run* sits where the one-step error is not
smallest. Learning on from it, live, pulls the weights back towards the one-step optimum:
the one-step error falls and the free run gets worse (a robot's 10-minute bag: fit's free
run -65.1 dB, after learning on over the same training samples -55.6 dB; with forgetting 1,
-50.8 dB). Outputs measured with noise pull the same way (the noise is in the regressors).

With the guard (``free_run_guard``) the network learns on as ever, and a *kept* state is
what a frozen phase, a free run and a saved weights file use. At a block's end the learning
model is taken as a *candidate*; once WINDOW_BLOCKS more blocks have been learnt, the
candidate and the kept model each simulate those later samples, which the candidate never
learnt from, in pieces seeded by the measured outputs before each (as fit's blocks are), and
the candidate is adopted if it simulates them better (:func:`simulates_better`). Judged on
samples it learnt, a candidate would win by fitting their noise; judged on later ones, it
wins only by knowing the plant better, which is what a plant that changed makes it do.

This module holds what the judgement needs beside the identifier's step: the last samples
(:class:`RecentSamples`, fed by the step and the batch run alike, so both judge the same
samples) and the judgement; :class:`~lenn_ros.core.structure.Identifier` calls
:class:`FreeRunGuard` at a block's end and where learning stops.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
from collections.abc import Iterator
from typing import Any

import numpy as np

from lenn_ros.core.free_run import OutputRun, free_run_outputs

#: a candidate is judged on the samples of this many blocks of ``health_interval`` learnt after it was taken.
#: Long enough to hold what the plant does (rest and motion, each speed), so that learning that teaches one of
#: them at the cost of another is seen doing so
WINDOW_BLOCKS = 10
#: a candidate is adopted only if no piece of the window simulates more than this much worse (in mean
#: squared error) with it: learning that mends one kind of motion and spoils another is not (fit's model of a
#: robot that rang at rest, after a block of rest learnt: rest 30x better, motion 1.2 to 5.8x worse)
PIECE_TOLERANCE = 0.1
#: a piece with fewer samples than this after its seed is not judged: a free run of a few samples says nothing
#: of how the model simulates
MIN_JUDGED = 50


class RecentSamples:
    """The last ``capacity`` samples (u's columns and y as the model reads them), with where each history started.

    A gap (or a rejected sample, a new run) starts a new *segment*: a free run never crosses one,
    but the window keeps the samples before it, so a plant that pauses often is still judged on
    the last ``capacity`` samples. A linear buffer of twice the capacity, moved down when full: a
    push costs three stores, and the window is always one slice (no wrap-around to join).
    """

    def __init__(self) -> None:
        self._u: np.ndarray | None = None
        self._y = np.empty(0)
        self._segment = np.empty(0, dtype=np.int64)
        self._n = 0
        self._current = 0  # the current segment's number
        self.capacity = 0
        self.total = 0  # samples ever pushed: where a candidate was taken is a number of these

    def restart(self, capacity: int) -> None:
        """The history starts over: later samples are a new segment (``capacity`` changed: the window empties)."""
        self._current += 1
        if capacity != self.capacity:
            self.capacity = int(capacity)
            self._u = None

    def _room(self, columns: int, count: int) -> None:
        if self._u is None or self._u.shape[1] != columns:
            self._u = np.empty((2 * self.capacity, columns))
            self._y = np.empty(2 * self.capacity)
            self._segment = np.empty(2 * self.capacity, dtype=np.int64)
            self._n = 0
        if self._n + count > 2 * self.capacity:
            keep = min(self._n, self.capacity)
            for array in (self._u, self._y, self._segment):
                array[:keep] = array[self._n - keep : self._n]
            self._n = keep

    def push(self, u: Any, y: float) -> None:
        """One sample (the step): u a float or the row of channels a several-output model gives each output."""
        if self.capacity <= 0:
            return
        self._room(np.size(u), 1)
        self._u[self._n] = u
        self._y[self._n] = y
        self._segment[self._n] = self._current
        self._n += 1
        self.total += 1

    def extend(self, u: np.ndarray, y: np.ndarray) -> None:
        """Consecutive samples (the batch run), oldest first."""
        if self.capacity <= 0 or not len(y):
            return
        u = np.asarray(u, dtype=np.float64).reshape(len(y), -1)[-self.capacity :]
        y = np.asarray(y, dtype=np.float64)[-self.capacity :]
        self._room(u.shape[1], len(y))
        self._u[self._n : self._n + len(y)] = u
        self._y[self._n : self._n + len(y)] = y
        self._segment[self._n : self._n + len(y)] = self._current
        self._n += len(y)
        self.total += len(y)

    @property
    def full(self) -> bool:
        """The window holds ``capacity`` samples."""
        return self._u is not None and self._n >= self.capacity > 0

    def segments(self, since: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
        """(u (N, columns), y (N,)) of each history in the window, oldest first; ``since``: only the samples pushed
        after the first ``since`` (a :attr:`total` taken earlier)."""
        if self._u is None:
            return []
        first = max(self._n - self.capacity, self._n - (self.total - since), 0)
        segment = self._segment[first : self._n]
        cuts = [0, *(np.flatnonzero(segment[1:] != segment[:-1]) + 1).tolist(), len(segment)]
        return [(self._u[first + a : first + b], self._y[first + a : first + b]) for a, b in itertools.pairwise(cuts)]


def free_run_mse(structure: Any, model: Any, u: np.ndarray, y: np.ndarray) -> float:
    """Mean squared error of ``model``'s free run over ``y`` after its first ``warm_up`` samples (which seed it);
    infinite where the run diverges. ``u``: the other channels the structure reads, measured."""
    start = structure.warm_up
    values = np.column_stack([y, u])
    run = OutputRun(structure, model, 0, tuple(range(1, values.shape[1])))
    _, diverged_at = free_run_outputs([run], values, start)
    if diverged_at is not None:
        return float("inf")
    errors = values[start:, 0] - y[start:]
    return float(np.mean(errors * errors))


def pieces_errors(structure: Any, model: Any, pieces: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """(squared-error sum, samples) of ``model``'s free run of each piece after its seed: pieces, not one long run,
    since one run would be judged by where it happened to start (a model that rings at rest, started at rest,
    swamps everything else)."""
    seed = structure.warm_up
    rows = [(free_run_mse(structure, model, u, y) * (len(y) - seed), len(y) - seed) for u, y in pieces]
    return np.array(rows, dtype=np.float64).reshape(-1, 2)


def simulates_better(
    structure: Any, model: Any, candidate: dict[str, np.ndarray], kept: dict[str, np.ndarray], pieces: list
) -> bool | None:
    """Whether the ``candidate`` state simulates the pieces better than the ``kept`` one: better pooled over them,
    and in no piece worse than PIECE_TOLERANCE allows. None: no piece long enough to judge. ``model`` is the
    network whose state is borrowed for the runs (it is left as it was)."""
    now = model.state()
    try:
        model.set_state(candidate)
        learnt = pieces_errors(structure, model, pieces)
        if not len(learnt):
            return None
        model.set_state(kept)
        held = pieces_errors(structure, model, pieces)
    finally:
        model.set_state(now)
    with np.errstate(invalid="ignore", divide="ignore"):
        learnt_mse, held_mse = learnt[:, 0] / learnt[:, 1], held[:, 0] / held[:, 1]
        pooled_better = learnt[:, 0].sum() < held[:, 0].sum()
        none_worse = np.all((learnt_mse <= (1.0 + PIECE_TOLERANCE) * held_mse) | (learnt_mse == held_mse))
    return bool(pooled_better and none_worse)


class FreeRunGuard:
    """One identifier's kept model (``free_run_guard``), its candidates and the recent samples they are judged on.

    The identifier calls :meth:`block_end` after each block of learning that passed the divergence
    guard, and :meth:`learning_stops` where learning stops (then the network takes :attr:`kept`).
    A candidate is taken at every block's end and judged WINDOW_BLOCKS blocks later, so the kept
    model follows a plant that changed a window behind the learning one, not two.
    """

    def __init__(self) -> None:
        self.recent = RecentSamples()
        self.kept: dict[str, np.ndarray] | None = None
        # (state, recent.total then), one per block's end: the oldest is as many blocks old as there are candidates
        self.candidates: collections.deque[tuple[dict, int]] = collections.deque()
        self.learnt = False  # the network has learnt since learning last stopped

    def block_end(self, structure: Any, model: Any, piece: int, counters: dict[str, int]) -> None:
        """A block was learnt: judge the candidate WINDOW_BLOCKS blocks old, and take this one."""
        if len(self.candidates) >= WINDOW_BLOCKS:
            self._judge(structure, model, piece, counters, *self.candidates.popleft())
        self.candidates.append((model.state(), self.recent.total))

    @contextlib.contextmanager
    def serving(self, model: Any) -> Iterator[None]:
        """``model`` holds the kept state for the duration (what a weights file saves), and its own after."""
        if self.kept is None:
            yield
            return
        now = model.state()
        model.set_state(self.kept)
        try:
            yield
        finally:
            model.set_state(now)

    def learning_stops(self, structure: Any, model: Any, piece: int, counters: dict[str, int]) -> None:
        """Learning stopped: each candidate followed by a block's worth of samples or more is judged on them,
        the oldest first (a later one must beat what an earlier one left kept)."""
        while self.candidates:
            state, taken_at = self.candidates.popleft()
            if self.recent.total - taken_at >= piece:
                self._judge(structure, model, piece, counters, state, taken_at)
        self.learnt = False

    def _judge(
        self, structure: Any, model: Any, piece: int, counters: dict[str, int], state: dict, taken_at: int
    ) -> None:
        pieces = self.pieces(structure, piece, taken_at)
        verdict = simulates_better(structure, model, state, self.kept, pieces) if self.kept else None
        if verdict is None:
            return
        counters["guard_checks"] = counters.get("guard_checks", 0) + 1
        if verdict:
            counters["guard_adopted"] = counters.get("guard_adopted", 0) + 1
            self.kept = state

    def pieces(self, structure: Any, piece: int, taken_at: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """The pieces of the samples pushed after ``taken_at``: ``piece`` samples each, with the ``warm_up``
        measured samples before each as its seed, within one history."""
        seed = structure.warm_up
        out = []
        for u, y in self.recent.segments(taken_at - seed):
            for first in range(0, len(y) - seed - MIN_JUDGED + 1, piece):
                stop = min(first + seed + piece, len(y))
                out.append((u[first:stop], y[first:stop]))
        return out


class BatchGuard:
    """A batch run's part in the free-run guard (``free_run_guard``): its samples fed to the guard's window and
    learning judged where it stops, at the same samples as :meth:`Identifier.step` does both.

    The run starts a history of its own (its first samples seed it), so the window starts a segment with it.
    Target ``t`` of the run predicts sample ``first + 1 + t``.
    """

    def __init__(self, identifier: Any, u: np.ndarray, y: np.ndarray, first: int) -> None:
        self.identifier, self.u, self.y, self.first, self.done = identifier, u, y, first, 0
        identifier._guard.recent.restart(WINDOW_BLOCKS * identifier.health_interval + identifier.structure.warm_up)

    def to(self, end: int) -> None:
        """Feed samples up to ``end`` (exclusive)."""
        if self.identifier.free_run_guard and end > self.done:
            self.identifier._guard.recent.extend(self.u[self.done : end], self.y[self.done : end])
            self.done = end

    def before(self, start: int, learn: bool) -> None:
        """Before the chunk from target ``start``: a chunk not learnt after learning stops learning (step pushes
        the sample before it judges)."""
        identifier = self.identifier
        if identifier.free_run_guard and not learn and identifier._guard.learnt:
            self.to(self.first + 2 + start)
            identifier._learning_stops()

    def learnt(self, stop: int) -> None:
        """Targets up to ``stop`` were learnt: their samples go to the window before the block is checked."""
        self.identifier._guard.learnt = True
        self.to(self.first + 1 + stop)
