"""The learner stage of a session: pairs in, the model stepped (or run in one batch), its events said.

- **warm-up**: with scales not given, the first ``scale_warm_up`` seconds of pairs are held, give
  the scales (:mod:`lenn_ros.core.warmup`, said in one line), and are then learnt from; the batch
  path takes the same decision on the same samples;
- **phases**: samples are learnt from until the test start (``test_start``, followed in sequence
  pairing) or while ``learning``; the phase NMSE restarts with each phase;
- **the step**: one pair through the identifier (live), or runs of consecutive valid samples
  through its compiled batch (offline, :meth:`Learner.run`), cut where a recorded live parameter
  change comes, so a recording evaluated offline learns as the node learnt; the model's events
  (a gap, a divergence and its resume, clipped inputs, the sign of a |y| sensor) said in one line;
- **references**: before the first sample stepped in each span of ``REFERENCE_SAMPLES`` sample numbers, a
  frozen copy of every output's served model (:class:`~lenn_ros.core.change.Reference`), for the change
  alarm; the batch takes it at the same samples, inside a run as a recorded change is applied there.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from lenn_ros.core.alignment import Pair
from lenn_ros.core.change import REFERENCE_SAMPLES, Reference
from lenn_ros.core.metrics import ChannelsNMSE
from lenn_ros.core.runs import finite_rows, gap_text, missing, runs
from lenn_ros.core.warmup import MAX_WARM_UP, ScaleWarmUp, warm_up_samples
from lenn_ros.session.config import ParameterChange, SessionConfig
from lenn_ros.session.notices import Notices
from lenn_ros.session.values import Values

#: Replays a recorded change into the model, for every output (``output`` None) or one of them.
Replay = Callable[[ParameterChange, int | None], None]


class Learner:
    """Warm-up, phases and the model's step; see the module docstring."""

    def __init__(self, identifier: Any, config: SessionConfig, notices: Notices, values: type[Values]) -> None:
        self.identifier, self.config, self.notices, self.values = identifier, config, notices, values
        self.test_start: int | None = None
        self.phase_learning: bool | None = None
        self.phase_nmse = ChannelsNMSE(identifier.names)
        self.warm_up: ScaleWarmUp | None = None  # scales to learn from the first samples (None: given)
        if not identifier.structure.scaled:  # (several channels: per channel)
            samples = warm_up_samples(config.scale_warm_up, config.sample_period)
            self.warm_up = ScaleWarmUp.for_structure(identifier.structure, samples)
        self.warming: list[Pair] = []  # pairs held by the warm-up, learnt once it ends
        self.last_index: int | None = None  # of the last sample stepped
        self._last_pair: Pair | None = None
        self._seen_clipped = 0
        self._clipped_said_at = -math.inf
        self._seen_unsure = 0
        self._seen_checks = 0
        self._sign_settled: bool | None = None
        self._span: int | None = None  # REFERENCE_SAMPLES span of the last reference taken
        #: references taken and not yet handed to the monitors: (sample, {output: Reference})
        self.references: list[tuple[int, dict[int, Reference]]] = []

    # -- phases ----------------------------------------------------------------------------------
    def set_test_start(self, index: int) -> None:
        """Sequence index of the first test sample (from the simulator's latched topic).

        It must come before that sample: one that comes after it cannot undo the learning
        from test samples already stepped, so it is said in one line and counted.
        """
        index = int(index)
        late = (
            index != self.test_start
            and self.config.learning
            and self._follows_test_start()
            and self.last_index is not None
            and self.last_index >= index
        )
        self.test_start = index
        if late:
            self.notices.counters["test_start_late"] += 1
            self.notices.say(
                "test_start_late",
                f"test_start {index} came after sample {self.last_index}: samples {index}..{self.last_index} were "
                "learnt from (its publisher did not wait for this reader); the frozen phase is shorter",
            )

    def _follows_test_start(self) -> bool:
        """test_start is a sequence number: followed in sequence pairing only, and when asked to."""
        return self.config.follow_test_start and self.config.pairing == "sequence"

    def learns(self, index: int) -> bool:
        if not self.config.learning:
            return False
        return not (self._follows_test_start() and self.test_start is not None and index >= self.test_start)

    def learning_now(self) -> bool:
        """Whether samples are learnt now: the phase learns and the model is not paused after a divergence."""
        phase = bool(self.phase_learning) if self.phase_learning is not None else self.config.learning
        return phase and not self.identifier.diverged

    # -- warm-up ---------------------------------------------------------------------------------
    def warm(self, pairs: list[Pair]) -> list[Pair]:
        """Hold pairs until the warm-up knows the scales; then every pair held so far, and the rest."""
        warm_up = self.warm_up
        if warm_up is None or warm_up.done:
            return pairs
        for position, pair in enumerate(pairs):
            self.warming.append(pair)
            if warm_up.add(pair.u, pair.y):
                self._end_warm_up()
                held, self.warming = self.warming, []
                return held + pairs[position + 1 :]
            if len(self.warming) >= MAX_WARM_UP:
                self._restart_warm_up(len(self.warming))
                self.warming = []
        return []

    def _end_warm_up(self) -> None:
        assert self.warm_up is not None
        identifier = self.identifier
        identifier.set_structure(self.warm_up.structure(identifier.structure))
        self.notices.say("scales", self.warm_up.text(self.config.u_name, self.config.y_name))

    def _restart_warm_up(self, held: int) -> None:
        assert self.warm_up is not None
        self.warm_up.restart(held)
        self.notices.counters["warm_up_discarded"] += held
        self.notices.say(
            "warm_up_discarded",
            f"{held} samples held for the scale warm-up discarded, never learnt: {self.config.u_name} or "
            f"{self.config.y_name} did not move in them "
            "(a plant at rest shows nothing of its range); the warm-up starts over. Fix: move the plant, or give "
            "y_scale/u_scale",
        )

    def warm_offline(self, u: np.ndarray, y: np.ndarray) -> int | None:
        """:meth:`warm` over a whole series: the first row the identifier is stepped from (None: never)."""
        warm_up = self.warm_up
        assert warm_up is not None
        first = 0
        for row in range(len(y)):
            if warm_up.add(u[row], y[row]):
                self._end_warm_up()
                return first
            if row + 1 - first >= MAX_WARM_UP:
                self._restart_warm_up(row + 1 - first)
                first = row + 1
        return None

    # -- one sample (live) ----------------------------------------------------------------------
    def step(self, pair: Pair) -> Any:
        """One pair through the identifier: its step result (None: refused, skipped)."""
        self.last_index = pair.index
        identifier = self.identifier
        if self.values.refused(pair.u, pair.y):
            identifier.skip(pair.index)
            self._last_pair = pair
            return None
        learn = self.learns(pair.index)
        if learn != self.phase_learning:
            self.phase_learning = learn
            self.phase_nmse.reset()
            self.notices.say("phase", f"sample {pair.index}: {'training' if learn else 'frozen (test)'} phase")
        if self._new_span(pair.index):
            self._take_reference(pair.index, range(len(identifier.outputs)))
        result = identifier.step(pair.index, pair.u, pair.y, learn)
        if learn and identifier.sign_settled is not self._sign_settled:
            self._say_sign(pair.index)
        if result.event == "gap":
            self._say_gap(pair)
        elif result.event in ("diverged", "resumed"):
            self.notices.say(result.event, self.divergence_text(pair.index, result.event))
        self._last_pair = pair
        if identifier.counters["clipped"] > self._seen_clipped:
            self.say_clipped(pair.time)
        if identifier.counters.get("guard_checks", 0) > self._seen_checks:
            self._say_guard(f"sample {pair.index}: ")
        if result.error is not None and result.y_hat is not None:
            self.phase_nmse.add(self.values.split(pair.y), self.values.split(result.y_hat))
        return result

    def _say_sign(self, index: int) -> None:
        """A |y| sensor (``y_abs``): learning waits for the sign to settle after each start, and resumes."""
        self._sign_settled = settled = self.identifier.sign_settled
        if settled:
            self.notices.say("sign", f"sample {index}: the sign of |y| has settled: learning (not where a sign is "
                             "unsure, at a crossing: counted in sign_unsure)")  # fmt: skip
        elif settled is not None:
            self.notices.say("sign", f"sample {index}: not learning until the sign of |y| settles (the model's free "
                             "runs from either sign of the start must agree; counted in sign_unsure)")  # fmt: skip

    def _say_gap(self, pair: Pair) -> None:
        """A gap before ``pair``: how long (samples and seconds), and whether it is a stall or lost messages."""
        last = self._last_pair
        counters = self.identifier.counters
        absent = pair.index - last.index - 1 if last is not None else 0
        seconds = pair.time - last.time if last is not None else None
        self.notices.say(
            "gap",
            f"sample {pair.index}: a gap of {gap_text(self.config.pairing, absent, seconds)}; the model restarts its "
            f"history there ({counters['gaps']} gaps, {counters['lost']} sample indices missing so far)",
        )

    def divergence_text(self, index: int, event: str) -> str:
        """One line for a divergence (what was done, and when learning comes back) or for a resume."""
        identifier = self.identifier
        counters = identifier.counters
        if event == "resumed":
            return (
                f"sample {index}: learning resumes from the healthy state after the pause that followed a "
                f"divergence ({counters['diverged']} divergence(s), {counters['resumed']} resume(s) so far)"
            )
        text = (
            f"sample {index}: the model diverged (its errors grew beyond divergence_ratio x the target's variance, "
            "or a weight would have become non-finite): weights rolled back to the last healthy state"
        )
        if not identifier.resume_after:
            return text + "; learning stays off until learning:=true (resume_after is 0)"
        return (
            f"{text}; pausing learning for {identifier.hold_off} samples, then it resumes by itself (each "
            f"divergence doubles the pause; {counters['diverged']} so far). If it keeps diverging, lower alpha"
        )

    def say_clipped(self, time: float | None) -> None:
        """Network inputs outside [-1, 1]: said at most every ``warn_period`` s of sample time (None: now).

        Throttled here as well as in the node: the condition holds for sample after
        sample, and ``evaluate`` lists every distinct notice it is handed.
        """
        if time is not None and abs(time - self._clipped_said_at) < self.config.warn_period:
            return
        clipped = self.identifier.counters["clipped"]
        learnt_range = (
            f" (the scales were learnt from the first {self.warm_up.valid} samples and the signals have left "
            "that range: a longer scale_warm_up, or scales by hand)"
            if self.warm_up is not None and self.warm_up.done
            else ""
        )
        self.notices.say(
            "clipped_inputs",
            f"{clipped} network inputs outside [-1, 1] clipped so far (+{clipped - self._seen_clipped}): the scaled "
            f"{self.config.u_name} / {self.config.y_name} leave the range the network is built for, and it learns "
            "them flattened. Fix: u_scale/u_offset, y_scale/y_offset that map the signals into [-1, 1] (the network "
            "sees (u - u_offset) / u_scale), or `lenn-ros fit` a recording to take them from the data" + learnt_range,
        )
        self._seen_clipped = clipped
        if time is not None:
            self._clipped_said_at = time

    # -- a whole series (offline) ---------------------------------------------------------------
    def run(
        self,
        index: np.ndarray,
        u: np.ndarray,
        y: np.ndarray,
        learn: np.ndarray,
        changes: Sequence[ParameterChange],
        replay: Replay,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The samples learnt in one pass: (y^, leverage of each prediction per output, the rows stepped).

        Equal to stepping them one by one (the node's path): runs of consecutive valid indices go to
        the identifier's batch, cut at the same boundaries as the step; a missing index or a refused
        sample (NaN) restarts the history there (:mod:`lenn_ros.core.runs`), as live. ``changes``:
        the live parameter changes recorded with the run, each ``replay``-ed where its sample comes,
        as live: before the first sample whose index is at least its ``from_index`` (after the last
        sample, if none is). The warm-up, where the scales are not given, decides on the same samples
        as live; the rows before the first stepped (those it discarded) get no prediction.
        """
        n_y = len(self.identifier.names)
        y_hat = np.full((len(y), n_y), np.nan)
        leverage = np.zeros((len(y), n_y))
        first = 0
        if self.warm_up is not None and not self.warm_up.done:
            first = self.warm_offline(u, y)
            if first is None:
                return y_hat.reshape(np.shape(y)), leverage, np.zeros(len(y), bool)
        stepped = np.arange(len(y)) >= first
        rows = slice(first, None)
        self._run_rows(index[rows], u[rows], y[rows], learn[rows], changes, replay, y_hat[rows], leverage[rows])
        if index.size:
            self.last_index = int(index[-1])
        self._phases(learn[rows], u[rows], y[rows], y_hat[rows])
        self._say_offline()
        return y_hat.reshape(np.shape(y)), leverage, stepped

    def _run_rows(
        self,
        index: np.ndarray,
        u: np.ndarray,
        y: np.ndarray,
        learn: np.ndarray,
        changes: Sequence[ParameterChange],
        replay: Replay,
        y_hat: np.ndarray,
        leverage: np.ndarray,
    ) -> None:
        """Each run of consecutive valid samples through the identifier, each change replayed at its sample."""
        valid = finite_rows(u) & finite_rows(y)
        counters = self.identifier.outputs[0].counters  # the index counters: every output counts them alike
        gaps, lost = missing(index)
        counters["gaps"] += gaps
        counters["lost"] += lost
        counters["rejected"] += int(np.count_nonzero(~valid))
        pending = sorted(changes, key=lambda change: change.from_index)  # (stable: one index, in recorded order)
        where = [int(np.searchsorted(index, change.from_index, side="left")) for change in pending]

        def applier(change: ParameterChange) -> Callable[..., None]:
            return lambda *output: replay(change, *(output or (None,)))

        for start, stop in zip(*runs(index, valid), strict=True):
            while pending and where[0] <= start:  # before this run (or in a break before it)
                where.pop(0)
                replay(pending.pop(0), None)
            inside = []
            while pending and where[0] < stop:
                inside.append((where.pop(0) - start, applier(pending.pop(0))))
            if stop > start and valid[start]:
                inside += self._references_inside(index, start, stop)
                predicted = self.identifier.run(u[start:stop], y[start:stop], learn[start:stop], inside)
                y_hat[start:stop] = np.reshape(predicted, (stop - start, -1))
                for j, output in enumerate(self.identifier.outputs):
                    leverage[start:stop, j] = output.last_leverage
        for change in pending:  # from after the last sample: no sample learns with it, the state has it
            replay(change, None)

    # -- references for the change alarm ------------------------------------------------------------
    def _new_span(self, index: int) -> bool:
        span = index // REFERENCE_SAMPLES
        if span == self._span:
            return False
        self._span = span
        return True

    def _take_reference(self, index: int, outputs: Any) -> None:
        """Frozen copies of the given outputs' served models, before sample ``index`` is stepped."""
        if not self.references or self.references[-1][0] != index:
            self.references.append((index, {}))
        taken = self.references[-1][1]
        for j in outputs:
            output = self.identifier.outputs[j]
            with output.serving():
                taken[j] = Reference(output.structure, output.model, index)

    def _references_inside(self, index: np.ndarray, start: int, stop: int) -> list[tuple[int, Callable[..., None]]]:
        """The run's samples that open a new span: a reference before each, as (position, apply) cuts
        (``apply(j)`` per output of a several-output model, as its run applies a change; ``apply()`` else)."""
        cuts: list[tuple[int, Callable[..., None]]] = []
        every = range(len(self.identifier.outputs))
        spans = index[start:stop] // REFERENCE_SAMPLES
        opening = np.flatnonzero(spans != np.concatenate(([-1 if self._span is None else self._span], spans[:-1])))
        for row in opening.tolist():
            sample = int(index[start + row])
            self._new_span(sample)

            def take(*output: int, sample: int = sample) -> None:
                self._take_reference(sample, output or every)

            cuts.append((row, take))
        return cuts

    def take_references(self) -> list[tuple[int, dict[int, Reference]]]:
        """The references taken since the last call, in order (the monitors offer them to their detectors)."""
        taken, self.references = self.references, []
        return taken

    def _phases(self, learn: np.ndarray, u: np.ndarray, y: np.ndarray, y_hat: np.ndarray) -> None:
        """The phase NMSE follows the learn flags as live (a new phase starts where the flag changes)."""
        valid = finite_rows(u) & finite_rows(y)
        phases = learn[valid]
        if not phases.size:
            return
        changes = np.flatnonzero(phases[1:] != phases[:-1]) + 1
        if phases[0] != self.phase_learning or changes.size:
            self.phase_nmse.reset()
        self.phase_learning = bool(phases[-1])
        last = np.flatnonzero(valid)[changes[-1]] if changes.size else 0
        scored = valid & finite_rows(y_hat) & (np.arange(len(y)) >= last)
        self.phase_nmse.extend(y[scored], y_hat[scored])

    def _say_guard(self, where: str) -> None:
        """``free_run_guard`` judged the learning model: said at the first check, then as their count doubles."""
        counters = self.identifier.counters
        self._seen_checks = checks = counters["guard_checks"]
        self.notices.doubling(
            "guard",
            checks,
            f"{where}the learning model simulated the recent samples better than the model kept in "
            f"{counters.get('guard_adopted', 0)} of {checks} checks and was adopted then; the kept model is what "
            "frozen phases, free runs and saved weights use (free_run_guard; counted in guard_checks, guard_adopted)",
        )

    def _say_offline(self) -> None:
        """What a batch pass says once for all its samples (live: as it happens)."""
        if self.identifier.counters.get("guard_checks", 0) > self._seen_checks:
            self._say_guard("")
        if self.identifier.counters["clipped"] > self._seen_clipped:
            self.say_clipped(None)
        unsure = self.identifier.counters.get("sign_unsure", 0)
        if unsure > self._seen_unsure:  # (live: a line at each start and when it settles)
            self.notices.say(
                "sign",
                f"{unsure - self._seen_unsure} samples not learnt for an unsure sign of |y|: after a start or a gap "
                "until it settled, and at crossings (counted in sign_unsure)",
            )
            self._seen_unsure = unsure
