"""One identification session: raw halves in, samples and what the model made of them out.

The identifier node, ``evaluate``, ``fit`` (a bag's samples) and replay all feed raw halves (a value
of u or y_p with its time, sequence number and source timestamp) into a :class:`Session` and get
back the samples it formed and the model's results. Offline equals live by construction: the same
stages decide what is paired, what is refused, what is learnt from and how the phase NMSE is kept.
The stages, each a class of its own:

- stream (:mod:`~lenn_ros.session.stream`): overload, presence, merging, screening, pairing;
- hold (:mod:`~lenn_ros.session.hold`): the live hold for the outputs' readers (offline: collect);
- learner (:mod:`~lenn_ros.session.learner`): warm-up, phases, the model's step or batch;
- monitors (:mod:`~lenn_ros.session.monitors`): each output's band and change alarm;
- notices (:mod:`~lenn_ros.session.notices`): what to say, in one line each, and the counters.

A model of several channels is the model of one channel composed per output (its outputs step
side by side on vector samples); where the two differ in how a value looks is said in one place
(:mod:`~lenn_ros.session.values`). Nothing here knows ROS.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lenn_ros.core.alignment import Pair
from lenn_ros.core.holding import START_GRACE
from lenn_ros.session.config import (
    GUARD_PARAMETERS,
    MODEL_PARAMETERS,
    ParameterChange,
    SessionConfig,
    json_safe,
)
from lenn_ros.session.hold import Hold
from lenn_ros.session.learner import Learner
from lenn_ros.session.monitors import Monitors
from lenn_ros.session.notices import Notice, Notices
from lenn_ros.session.stream import Stream
from lenn_ros.session.values import values_for


@dataclass(slots=True)
class Sample:
    """A paired sample and what the model did with it (``result`` None: refused/skipped)."""

    index: int
    time: float
    u: Any  # a float, or a vector of the model's input channels
    y: Any
    result: Any


@dataclass
class Session:
    """The stages composed; see the module docstring."""

    identifier: Any
    config: SessionConfig = field(default_factory=SessionConfig)

    def __post_init__(self) -> None:
        self.values = values_for(self.identifier)
        self.notices = Notices()
        self.counters = self.notices.counters
        self.stream = Stream(self.config, self.notices, self.values, self.identifier.restart_stream)
        self.hold = Hold(self.config, self.notices)
        self.learner = Learner(self.identifier, self.config, self.notices, self.values)
        self.monitors = Monitors(self.identifier.names, self.config, self.notices)
        #: offline: every formed pair goes here, unprocessed and unbounded (no reader to wait for, nothing
        #: shed; the caller learns them in one batch): what a recording's pairing collects them with
        self.collect: Callable[[list[Pair]], None] | None = None
        self.changes: list[ParameterChange] = []  # live parameter changes applied, in order
        self.last_y_hat_std = np.zeros(0)  # run_samples(): the std of each y^(k), shaped as y (nan: none)
        self.last_y_hat_band = np.zeros(0)  # ... the live band's half-width around each y^(k)

    # -- live parameters ---------------------------------------------------------------------
    def apply_parameters(self, values: dict[str, Any]) -> ParameterChange:
        """Apply accepted parameter values now, and record them from the next sample on.

        The one place that decides what a parameter change does to the model and the
        session: the node calls it when ``ros2 param set`` is accepted, ``evaluate`` calls
        :meth:`replay_change` (the same code) at the recorded sample, so offline stays
        equal to live across the change. Values that are none of the session's business
        (weights_out, report_every...) are recorded, and left to the caller.
        """
        last = self.learner.last_index
        change = ParameterChange(1 if last is None else last + 1, dict(values))
        self.replay_change(change)
        return change

    def replay_change(self, change: ParameterChange, output: int | None = None) -> None:
        """Apply a (recorded) change: to every output's network and divergence guard (``output``: one of them,
        as a batch of several outputs runs them one after another), or the session's config."""
        outputs = self.identifier.outputs if output is None else [self.identifier.outputs[output]]
        if output in (None, 0):  # (a batch of several outputs replays it once per output)
            self.changes.append(change)
        for name, value in change.values.items():
            if name in MODEL_PARAMETERS and name in outputs[0].model.get_params():
                for each in outputs:
                    each.model.set_params(**{name: value})
            elif name in GUARD_PARAMETERS:
                for each in outputs:
                    setattr(each, name, value)
            elif name == "change_threshold":
                self.config.change_threshold = float(value)
                for monitor in self.monitors.outputs:
                    monitor.change.threshold = float(value)
            elif name in SessionConfig.__dataclass_fields__:
                setattr(self.config, name, value)
                self._learning_again(name, value, outputs, change.from_index)

    def _learning_again(self, name: str, value: Any, outputs: list[Any], index: int) -> None:
        """The user re-enables learning after a divergence: the diverged outputs are healthy again."""
        diverged = [each for each in outputs if each.diverged]
        if name == "learning" and value and diverged:
            for each in diverged:
                each.mark_healthy()
            self.notices.say("parameters", f"sample {index}: learning re-enabled after a divergence")

    # -- input -------------------------------------------------------------------------------
    def admit(self, queue: object, received: float, now: float) -> bool:
        """Whether a message taken from ``queue`` is processed or shed (see :meth:`Stream.admit`)."""
        return self.stream.admit(queue, received, now)

    def offer(
        self,
        channel: str,
        value: Any,
        time: float,
        received: float | None = None,
        sequence: int | None = None,
        source_time: float | None = None,
        part: int = 0,
    ) -> list[Sample]:
        """One half: ``channel`` U or Y, its value and time (stamp or receive time, s).

        ``received`` is the receive time (defaults to ``time``), ``sequence`` the DDS
        publication sequence number, ``source_time`` the publisher's timestamp (s);
        ``part``: which of the side's topics it came on, where it has several
        (``u_parts`` / ``y_parts``: merged into one half first, see :mod:`~lenn_ros.core.merging`).
        """
        received = time if received is None else received
        return self._process(self.stream.offer(channel, value, time, received, sequence, source_time, part))

    def unreadable(self, channel: str, received: float, field: str, error: str) -> None:
        """A message of ``channel`` whose ``field`` could not be read (see :meth:`Stream.unreadable`)."""
        self.stream.unreadable(channel, received, field, error)

    def poll(self, now: float) -> list[Sample]:
        """Time passes (receive clock, s): settle waiting samples, watch for a lone input or none at all."""
        return self._process(self.stream.poll(now))

    def flush(self) -> list[Sample]:
        """End of a recording: settle what can still be settled (a side's incomplete parts are dropped)."""
        return self._process(self.stream.flush())

    def set_test_start(self, index: int) -> None:
        """Sequence index of the first test sample (see :meth:`Learner.set_test_start`)."""
        self.learner.set_test_start(index)

    # -- the hold (live) -----------------------------------------------------------------------
    @property
    def held(self) -> int:
        """Pairs formed while holding, not yet processed."""
        return len(self.hold.pairs)

    @property
    def holding(self) -> bool:
        return self.hold.holding

    def release(self) -> list[Sample]:
        """Stop holding: process the samples formed meanwhile (outputs now have readers)."""
        return self._process(self.hold.release())

    def held_at_stop(self) -> str | None:
        """What to say when the node stops while it holds pairs (None: it holds none)."""
        return self.hold.at_stop()

    def hold_for(self, wanted: dict[str, int], grace: float = START_GRACE) -> None:
        """Live: hold formed pairs until each output in ``wanted`` has that many readers and, in ``sequence``
        pairing, the graph has shown who publishes u and y_p (:mod:`~lenn_ros.core.holding`)."""
        self.hold.hold_for(wanted, grace)

    @property
    def publishers_known(self) -> bool:
        """Whether the graph has shown both inputs' publishers (or the grace for them ran out)."""
        return self.hold.publishers_known

    def graph_publishers(self, seen: dict[str, set[tuple[str, str]]]) -> None:
        """The publishers (namespace, node) of each input the graph shows now; in ``sequence`` pairing, two
        disjoint sets refuse every half from now on (said with the fix, counted) and drop what is held."""
        decided, refusal = self.hold.publishers(seen)
        if not decided:
            return
        self.stream.refusal = refusal
        if refusal is not None:
            self.hold.discard()

    def release_ready(self, readers: dict[str, int], now: float) -> list[Sample]:
        """The held samples, processed, once the outputs have their ``readers`` and the publishers are vouched
        for (monotonic ``now``, s); else nothing, and what they wait for is said after the grace."""
        return self.release() if self.hold.ready(readers, now) else []

    @property
    def refusal(self) -> str | None:
        return self.stream.refusal

    @property
    def silent(self) -> bool:
        """Whether the inputs are silent (said by the presence watch, until a message comes)."""
        return self.stream.presence.silent_since is not None

    @property
    def shedder(self) -> Any:
        return self.stream.shedder

    @property
    def phase_nmse(self) -> Any:
        return self.learner.phase_nmse

    # -- learning ------------------------------------------------------------------------------
    def _process(self, pairs: list[Pair]) -> list[Sample]:
        if self.collect is not None:
            self.collect(pairs)
            return []
        if self.hold.holding:
            self.hold.keep(pairs)
            return []
        return [self._step(pair) for pair in self.learner.warm(pairs)]

    def _step(self, pair: Pair) -> Sample:
        result = self.learner.step(pair)
        if self.learner.references:
            self.monitors.offer(self.learner.take_references())
        if result is not None:
            ys = self.values.split(pair.y)
            # what each output's model reads, for the alarm's reference only (not per sample when it is off)
            inputs = self.values.inputs(self.identifier, pair.u, pair.y) if self.config.change_alarm else ys
            self.monitors.watch(ys, result, pair.index, pair.time, inputs)
        return Sample(pair.index, pair.time, pair.u, pair.y, result)

    def run_samples(
        self,
        index: np.ndarray,
        u: np.ndarray,
        y: np.ndarray,
        learn: np.ndarray,
        changes: Sequence[ParameterChange] = (),
    ) -> np.ndarray:
        """The samples a live session formed, learnt again in one pass; returns y^(k) (nan: none).

        The learner runs them as the node steps them (:meth:`Learner.run`: the warm-up, the gaps,
        the recorded live ``changes`` each at its sample); the monitors then watch every scored
        error in order (:meth:`Monitors.watch_batch`), so ``last_y_hat_std`` (``last_y_hat_band``) is the std
        (the live band's half-width) each y^(k) was published with and the alarm rises where it rose live.
        """
        index = np.asarray(index, dtype=np.int64)
        u = np.asarray(u, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        learn = np.asarray(learn, dtype=bool)
        before = (self.config.change_alarm, self.config.change_threshold)
        y_hat, leverage, stepped = self.learner.run(index, u, y, learn, changes, self.replay_change)
        stds = np.full((len(y), len(self.identifier.names)), np.nan)
        bands = stds.copy()
        if stepped.any():
            rows = np.flatnonzero(stepped)
            inputs = self.values.inputs(self.identifier, u[rows], y[rows])
            references = self.learner.take_references()
            watched = self.monitors.watch_batch(
                index[rows], y[rows], y_hat[rows], leverage[rows], changes, before, inputs, references
            )
            stds[rows], bands[rows] = watched
        self.last_y_hat_std = stds.reshape(np.shape(y))
        self.last_y_hat_band = bands.reshape(np.shape(y))
        return y_hat

    # -- reporting -----------------------------------------------------------------------------
    def take_notices(self) -> list[Notice]:
        return self.notices.take()

    def change_text(self, index: int, time: float | None) -> str:
        """The alarm on (the first output whose alarm is) in one line: when, where, by how much."""
        return (self.monitors.alarm or self.monitors.outputs[0]).text(index, time)

    def all_counters(self) -> dict[str, int]:
        """Every counter of the session, its pairing and the model, in one flat dict."""
        counters = dict(self.counters)
        for name, value in self.stream.counters().items():
            counters[f"pairing_{name}" if name in counters else name] = value
        renamed = {"clipped": "clipped_inputs", "duplicates": "model_duplicates"}  # vs the session's own
        for name, value in self.identifier.counters.items():
            counters[renamed.get(name, name)] = value
        return counters

    def queued(self) -> dict[str, int]:
        """What waits in the session's queues now: halves to pair, parts to merge, pairs held (all bounded)."""
        return {**self.stream.queued(), "held": len(self.hold.pairs), "warm_up": len(self.learner.warming)}

    def status(self) -> dict[str, Any]:
        """Everything a user or a test needs to know about the session so far (JSON-safe)."""
        learner, identifier = self.learner, self.identifier
        return json_safe(
            {
                "pairing": self.config.pairing,
                "learning": learner.learning_now(),
                "diverged": identifier.diverged,
                "resume_in": identifier.resume_in if identifier.diverged else None,
                "test_start": learner.test_start,
                "refused": self.stream.refusal,
                "silent_since": self.stream.presence.silent_since,  # receive time of the last message while silent
                "phase_samples": learner.phase_nmse.count,
                "phase_nmse_db": learner.phase_nmse.nmse_db,
                "phase_rmse": learner.phase_nmse.rmse,
                "counters": self.all_counters(),
                "queued": self.queued(),
                "lag_s": self.stream.shedder.lag,
                "samples_seen": int(getattr(identifier.model, "n_samples_seen_", 0)),
                "scaling": learner.warm_up.status() if learner.warm_up is not None else {"state": "given"},
                "parameter_changes": len(self.changes),  # live changes applied, each in identifier_config
                "change": self.monitors.status(),
                "channels": self._channel_status(),
            }
        )

    def _channel_status(self) -> dict[str, Any]:
        """Per output channel: its phase NMSE and whether its model diverged."""
        phase = self.learner.phase_nmse
        return {
            name: {"phase_nmse_db": channel.nmse_db, "phase_rmse": channel.rmse, "diverged": output.diverged}
            for name, channel, output in zip(phase.names, phase.channels, self.identifier.outputs, strict=True)
        }
