"""One identification session: screen, pair/align, step, phase and NMSE.

The identifier node, ``lenn-ros evaluate`` and replay all feed raw halves (a value of
u or y_p with its time, sequence number and source timestamp) into a :class:`Session`
and get back the samples it formed and what the model made of them. Offline equals
live by construction: the same object decides what is paired, what is refused, what
is learnt from and how the phase NMSE is kept.

Nothing here knows ROS. The session *says* what goes wrong as :class:`Notice`
(kind + one line); the node logs them (throttled per kind), ``evaluate`` prints a
summary; every notice kind also has a counter in :meth:`Session.status`.

Times are stamps where a message has one, else receive times. When one input is
timed by stamps whose clock is off the receive clock the other input is timed by (or
both by stamps of two clocks), the pairs are shifted by that offset and nothing in
the pairing itself can tell: the session compares each input's least
(receive - time) over its last messages and says ``clock_offset`` once the two differ by more than
``max_clock_offset`` (default max(T/2, 50 ms): above a driver's own latency, and
the shift from which the held command starts to be the wrong one).

Pairing modes (``SessionConfig.pairing``):
- ``sequence``: u(k) and y_p(k) carry the same DDS publication sequence number
  because one node publishes both in lockstep (our simulator, replay). Refused, with
  the fix named, when the middleware gives no sequence numbers or the two halves of a
  pair were published more than ``max_skew`` seconds apart *and* not in turn after the
  pair before (not one lockstep publisher): garbage is never paired. A lockstep
  publisher descheduled between u(k) and y_p(k) on a loaded machine publishes them far
  apart, yet both after every half of sample k-1: that pair is one sample and is learnt.
  Two streams that merely share indices fall out of turn within a few samples.
- ``stamp``: header stamps within ``slop`` (:class:`~lenn_ros.core.alignment.StampAligner`).
- ``sample``: a grid of ``sample_period`` with zero-order hold
  (:class:`~lenn_ros.core.alignment.GridSampler`).

Scales not given (``y_scale`` / ``u_scale`` 0): the first ``scale_warm_up`` seconds of
samples are held, give the scales (:mod:`~lenn_ros.core.warmup`, said in one line and
shown in ``status["scaling"]``), and are then learnt from; :meth:`Session.run_samples`
takes the same decision on the same samples.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lenn_ros.core.alignment import GridSampler, Pair, StampAligner
from lenn_ros.core.change import ACCEPTED, DEFAULT_THRESHOLD, RAISED, ChangeDetector
from lenn_ros.core.holding import START_GRACE, HoldGate
from lenn_ros.core.merging import TopicMerger, default_max_age
from lenn_ros.core.metrics import ChannelsNMSE, RunningNMSE
from lenn_ros.core.mimo import MimoIdentifier, MimoStepResult
from lenn_ros.core.overload import Shedder
from lenn_ros.core.pairing import Pairer, U, Y, screen, screen_values
from lenn_ros.core.runs import finite_rows, missing, runs
from lenn_ros.core.spread import OneStepSpread
from lenn_ros.core.structure import Identifier, StepResult
from lenn_ros.core.warmup import MAX_WARM_UP, ScaleWarmUp, warm_up_samples

PAIRING_MODES = ("sequence", "stamp", "sample")
SESSION_COUNTERS = (
    "u_messages", "y_messages", "nan", "out_of_range", "clipped",
    "no_sequence", "misaligned", "refused", "lone_u", "lone_y", "clock_offset", "held_overflow", "shed",
    "field_errors", "warm_up_discarded", "change_alarms", "test_start_late", "silences",
)  # fmt: skip
#: Pairs held (not yet learnt) while the outputs wait for readers: beyond this the oldest are dropped.
MAX_HELD = 10_000
#: What rmw reports when it has no publication sequence numbers (rmw_cyclonedds: 2**64-1).
SEQUENCE_UNSUPPORTED = (0, 2**64 - 1)
#: Halves per input whose (receive - time) make the clock-offset estimate: their least, since an offset
#: shifts every message and a delay (load, a stall's burst) only some; at 200 Hz 1.3 s, at 50 Hz 5 s.
CLOCK_WINDOW = 256


#: What missing sample indices mean in each pairing mode: only in ``sequence`` are they lost messages
#: (publication numbers skipped); on a grid they are time in which no new y_p came, a stall.
GAP_CAUSES = {
    "sequence": "lost: their messages never arrived (publication sequence numbers skipped) or found no partner",
    "stamp": "a stall or lost halves: no u / y_p pair within slop formed in that time",
    "sample": "a stall, not a loss: no new measurement arrived in that time (its publisher paused, unless over "
    "BEST_EFFORT every message of that time was lost)",
}


def gap_text(pairing: str, missing: int, seconds: float | None = None) -> str:
    """One gap (or the longest of several) in words: its length in samples and seconds, and what it is."""
    length = f"{missing} sample{'s' if missing != 1 else ''}"
    if seconds is not None and math.isfinite(seconds):
        length += f", {seconds:.3f} s without a sample"
    return f"{length}: {GAP_CAUSES.get(pairing, GAP_CAUSES['sequence'])}"


def describe_gaps(index: np.ndarray, pairing: str, sample_period: float = 0.0) -> list[str]:
    """The missing sample indices of a run (``evaluate``), in lines: how many, in how many gaps, the
    longest (in seconds too on a grid) and what they are in this pairing mode, a stall or lost messages."""
    index = np.asarray(index, dtype=np.int64)
    if index.size == 0:
        return []
    lines = []
    if index[0] > 1:
        lines.append(f"the samples start at index {index[0]}: the {index[0] - 1} before it are not in the recording")
    steps = np.diff(index)
    gaps = steps[steps > 1] - 1
    if gaps.size:
        longest = int(gaps.max())
        seconds = (longest + 1) * sample_period if pairing == "sample" and sample_period > 0 else None
        lines.append(
            f"{int(gaps.sum())} sample indices missing in {gaps.size} gap{'s' if gaps.size != 1 else ''}, "
            f"the longest {gap_text(pairing, longest, seconds)}"
        )
    return lines


@dataclass
class SessionConfig:
    """How halves become samples and samples become learning; see the module docstring."""

    pairing: str = "sequence"
    slop: float = 0.0
    sample_period: float = 0.0
    max_delay: float = 0.0  # stamp/sample: wait this long (receive time) for a late partner; 0 = auto
    y_max_age: float = 0.0  # sample: reuse an old y_p this long (0 = never: a lost y_p is a gap)
    max_skew: float = 0.25  # sequence: the two halves of a pair published further apart are refused
    lone_timeout: float = 3.0  # say so when one input arrives alone this long
    silence_timeout: float = 30.0  # say so when neither input has arrived this long after data flowed (0 = never)
    max_clock_offset: float = 0.0  # stamp/sample: say so when the inputs' clocks differ more (0 = max(T/2, 50 ms))
    warn_period: float = 5.0  # s of sample time between repeats of a notice said per sample (clipped_inputs)
    max_lag: float = 0.5  # live: a message that waited longer in its queue is shed (0 = never; see core.overload)
    queue_depth: int = 0  # live: the subscription queues' depth (0: unknown, max_lag alone)
    u_limit: float = 1.0e3
    y_limit: float = 1.0e3
    out_of_range: str = "reject"
    learning: bool = True
    follow_test_start: bool = True
    scale_warm_up: float = 10.0  # s of samples (by sample_period) the scales not given are learnt from
    change_alarm: bool = True  # watch the one-step errors for a plant change (core.change; single output)
    change_threshold: float = DEFAULT_THRESHOLD  # its CUSUM threshold
    u_name: str = "u"  # topic names, for the messages a user reads
    y_name: str = "y_p"
    u_parts: tuple[int, ...] = ()  # several u topics: channels per topic (merged into one half)
    y_parts: tuple[int, ...] = ()
    u_parts_names: tuple[str, ...] = ()  # their names, for the messages
    y_parts_names: tuple[str, ...] = ()

    @classmethod
    def from_values(cls, values: dict[str, Any], **overrides: Any) -> SessionConfig:
        """The config from parameter values (a node's, or a params file's), ignoring the rest."""
        names = set(cls.__dataclass_fields__)
        return cls(**{**{key: value for key, value in values.items() if key in names}, **overrides})

    def __post_init__(self) -> None:
        if self.pairing not in PAIRING_MODES:
            raise ValueError(f"pairing must be one of {', '.join(PAIRING_MODES)}, not {self.pairing!r}")
        if self.pairing == "sample" and not self.sample_period > 0:
            raise ValueError("pairing 'sample' needs sample_period > 0 (seconds between samples)")


#: Live parameters that go to every network of the identifier (``set_params``), where it has them.
MODEL_PARAMETERS = ("alpha", "beta", "forgetting", "nlms_step")
#: Live parameters of the identifier's divergence guard.
GUARD_PARAMETERS = ("divergence_ratio", "resume_after")


@dataclass(frozen=True)
class ParameterChange:
    """Live parameter values accepted while the session ran, in effect from sample ``from_index`` on.

    ``from_index`` is the index of the first sample the session steps after the change
    (the last one stepped before it, plus one): pairs still waiting to be paired or held
    are stepped after it, so they learn with the new values, live and offline alike.
    """

    from_index: int
    values: dict[str, Any]

    def as_dict(self) -> dict[str, Any]:
        return {"from_sample": self.from_index, "values": dict(self.values)}

    @classmethod
    def from_dict(cls, entry: dict[str, Any]) -> ParameterChange:
        return cls(int(entry["from_sample"]), dict(entry["values"]))


@dataclass(frozen=True)
class Notice:
    """Something the user must hear about, in one line; ``kind`` (and ``subject``) select its throttle.

    ``subject``: what the notice is about where one kind concerns several things (a topic):
    a stale /robot/cmd1 at start-up must not silence a stale /robot/right seconds later.
    """

    kind: str
    text: str
    subject: str = ""


@dataclass(slots=True)
class Sample:
    """A paired sample and what the model did with it (``result`` None: refused/skipped)."""

    index: int
    time: float
    u: float | np.ndarray  # a vector for a MIMO identifier, one element per channel
    y: float | np.ndarray
    result: StepResult | MimoStepResult | None


@dataclass
class Session:
    """Raw halves in, samples and model results out; see the module docstring."""

    identifier: Identifier | MimoIdentifier
    config: SessionConfig = field(default_factory=SessionConfig)

    def __post_init__(self) -> None:
        config = self.config
        self.counters: dict[str, int] = dict.fromkeys(SESSION_COUNTERS, 0)
        self.pairer = Pairer(window=10_000) if config.pairing == "sequence" else None
        delay = config.max_delay or (max(2 * config.sample_period, 0.05) if config.sample_period else 0.5)
        self.aligner: StampAligner | GridSampler | None = None
        if config.pairing == "stamp":
            self.aligner = StampAligner(slop=config.slop, max_delay=delay)
        elif config.pairing == "sample":
            self.aligner = GridSampler(config.sample_period, max_delay=delay, y_max_age=config.y_max_age)
        self.test_start: int | None = None
        self.phase_learning: bool | None = None
        self.mimo = isinstance(self.identifier, MimoIdentifier)
        self.mergers = {
            channel: TopicMerger(
                tuple(parts),
                config.pairing,
                slop=config.slop,
                max_delay=delay,
                max_age=default_max_age(config.sample_period),
            )
            for channel, parts in ((U, config.u_parts), (Y, config.y_parts))
            if len(parts) > 1
        }
        self._seen_merge: dict[str, dict[str, int]] = {}
        self.phase_nmse = ChannelsNMSE(self.identifier.names) if self.mimo else RunningNMSE()
        self.refusal: str | None = None  # set by the caller when it knows pairing cannot work
        self.holding = False  # hold formed samples (unprocessed) until release()
        #: offline: every formed pair goes here, unprocessed and unbounded (no reader to wait for, nothing
        #: shed; the caller learns them in one batch): what a recording's pairing collects them with
        self.collect: Callable[[list[Pair]], None] | None = None
        self.gate: HoldGate | None = None  # live: what the hold waits for (hold_for)
        self._held: list[Pair] = []
        self._notices: list[Notice] = []
        self._last_seen: dict[str, float] = {}
        self._unreadable: dict[str, tuple[int, float, str]] = {}  # channel: (count, last receive time, why)
        self._first_seen: dict[str, float] = {}
        self._seen_dropped = 0
        self._seen_faults = 0  # sequence mode: stale + duplicate halves already said
        self._last_sources: tuple[float, float] | None = None  # sequence mode: the last pair's (u, y) publish times
        self._silent_since: float | None = None  # receive time of the last message, while the silence is said
        self._seen_clipped = 0
        self._said_at_count: dict[str, int] = {}  # kinds said when their count doubles: the count then
        self._clipped_said_at = -math.inf
        self._lags: dict[str, deque[float]] = {U: deque(maxlen=CLOCK_WINDOW), Y: deque(maxlen=CLOCK_WINDOW)}
        self._stamped = {U: False, Y: False}
        self._offset_checks = 0
        self.clock_offset: float | None = None  # least lag of y_p minus that of u while it stands, s
        self.shedder = Shedder(config.max_lag, config.queue_depth)
        self.warm_up: ScaleWarmUp | None = None  # scales to learn from the first samples (None: given)
        if not self.identifier.structure.scaled:  # (a MIMO model's: per channel)
            samples = warm_up_samples(config.scale_warm_up, config.sample_period)
            self.warm_up = ScaleWarmUp.for_structure(self.identifier.structure, samples)
        self._warming: list[Pair] = []  # pairs held by the warm-up, learnt once it ends
        self.last_index: int | None = None  # of the last sample stepped
        self.changes: list[ParameterChange] = []  # live parameter changes applied, in order
        # the change alarm (one output: a MIMO model's channels are not watched), fed every scored error
        self.change = None if self.mimo else ChangeDetector(threshold=config.change_threshold)
        self.change_time: float | None = None  # time of the sample the alarm rose at (live; offline None)
        self.change_started: int | None = None  # the sample the last alarm rose at
        self.spread = None if self.mimo else OneStepSpread()  # the one-step std of each y^ (core.spread)
        self._next_std: float | None = None  # of the pending prediction
        self.last_y_hat_std = np.zeros(0)  # run_samples(): the one-step std of each y^(k) (nan: none)

    # -- live parameters ---------------------------------------------------------------------
    def apply_parameters(self, values: dict[str, Any]) -> ParameterChange:
        """Apply accepted parameter values now, and record them from the next sample on.

        The one place that decides what a parameter change does to the model and the
        session: the node calls it when ``ros2 param set`` is accepted, ``evaluate`` calls
        :meth:`replay_change` (the same code) at the recorded sample, so offline stays
        equal to live across the change. Values that are none of the session's business
        (weights_out, report_every...) are recorded, and left to the caller.
        """
        change = ParameterChange(1 if self.last_index is None else self.last_index + 1, dict(values))
        self.replay_change(change)
        return change

    def replay_change(self, change: ParameterChange) -> None:
        """Apply a (recorded) change: to every network, the divergence guard or the session's config."""
        identifier = self.identifier
        models = identifier.models if isinstance(identifier, MimoIdentifier) else [identifier.model]
        for name, value in change.values.items():
            if name in MODEL_PARAMETERS and name in models[0].get_params():
                for model in models:
                    model.set_params(**{name: value})
            elif name in GUARD_PARAMETERS:
                setattr(identifier, name, value)
            elif name == "change_threshold" and self.change is not None:
                self.change.threshold = float(value)
                self.config.change_threshold = float(value)
            elif name in SessionConfig.__dataclass_fields__:
                setattr(self.config, name, value)
                if name == "learning" and value and identifier.diverged:
                    identifier.mark_healthy()  # the user re-enables learning after a divergence
                    self._say("parameters", f"sample {change.from_index}: learning re-enabled after a divergence")
        self.changes.append(change)

    # -- input -------------------------------------------------------------------------------
    def admit(self, queue: object, received: float, now: float) -> bool:
        """Whether a message taken from ``queue`` (received at ``received``, taken at ``now``, system clock, s)
        is processed, or shed because the node is behind (:mod:`~lenn_ros.core.overload`); shed ones are
        counted and said at the first and each time their count doubles.

        Never in ``sequence`` mode: its one lockstep publisher waits for the identifier (it
        cannot flood it), and a sample shed there would be a gap where offline has none.
        """
        if self.pairer is not None:
            self.shedder.lag = now - received  # (still shown in status)
            return True
        shedder = self.shedder
        shedder.max_lag, shedder.depth = self.config.max_lag, self.config.queue_depth
        if shedder.admit(queue, received, now):
            return True
        self.counters["shed"] = shedder.shed
        self._say_doubling(
            "shed",
            shedder.shed,
            f"overloaded: {shedder.shed} messages shed unprocessed so far (this one waited {shedder.lag:.3f} s in its "
            f"queue, more than max_lag {self.config.max_lag:g} s or half the time its queue of "
            f"{self.config.queue_depth or 'unknown depth'} takes to fill at this rate): messages arrive faster than "
            "the node can learn from them, so it keeps up with the newest",
        )
        return False

    def offer(
        self,
        channel: str,
        value: float,
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
        self.counters["u_messages" if channel == U else "y_messages"] += 1
        self._first_seen.setdefault(channel, received)
        self._last_seen[channel] = received
        if self._silent_since is not None:
            self._say("inputs_resumed", f"{self.config.u_name if channel == U else self.config.y_name} arrived "
                      f"again after {received - self._silent_since:.1f} s without data: learning goes on")  # fmt: skip
            self._silent_since = None
        if self.pairer is None:
            self._watch_clocks(channel, time, received)
        if self._alone_for(channel, received) > 0.0:
            self.counters[f"lone_{channel}"] += 1
        merger = self.mergers.get(channel)
        if merger is None:
            return self._offer_half(channel, value, time, received, sequence, source_time)
        samples = []
        for half in merger.add(part, value, time, received, sequence, source_time):
            samples += self._offer_half(channel, half.value, half.time, half.received, half.sequence, half.source_time)
        self._after_merge(channel, merger)
        return samples

    def unreadable(self, channel: str, received: float, field: str, error: str) -> None:
        """A message of ``channel`` arrived (receive time ``received``) but its ``field`` could not be read.

        Counted (``field_errors``) and kept for the lone-input notice of the other channel:
        its messages did arrive, so "nothing on" it would send the user to check the topic
        name and QoS, when the fix is the field path (a joint name, an index).
        """
        self.counters["field_errors"] += 1
        count = self._unreadable.get(channel, (0, 0.0, ""))[0] + 1
        self._unreadable[channel] = (count, received, f"{field} ({error})")

    def _offer_half(
        self, channel: str, value: Any, time: float, received: float, sequence: int | None, source_time: float | None
    ) -> list[Sample]:
        """A whole half (one topic's message, or the side's topics merged): screened, then paired."""
        config = self.config
        name = config.u_name if channel == U else config.y_name
        limit = config.u_limit if channel == U else config.y_limit
        raw = value
        if self.mimo:
            value, verdict = screen_values(value, limit, config.out_of_range)
        else:
            value, verdict = screen(float(value), limit, config.out_of_range)
        if verdict != "ok":
            self.counters[verdict] += 1
            consequence = "clipped to the limit" if verdict == "clipped" else "its sample is skipped, never learnt"
            shown = np.asarray(raw).tolist() if self.mimo else value
            self._say(verdict, f"{name} = {shown!r} at t={time:.6f}: {verdict.replace('_', ' ')}; {consequence}")
        if self.refusal is not None:
            self.counters["refused"] += 1
            self._say("refused", self.refusal)
            return []
        if self.pairer is not None:
            pairs = self._pair_by_sequence(channel, value, time, sequence, source_time)
        else:
            assert self.aligner is not None
            pairs = self.aligner.add(channel, value, time, received)
            self._after_alignment()
        return self._process(pairs)

    def poll(self, now: float) -> list[Sample]:
        """Time passes (receive clock, s): settle waiting samples, watch for a lone input or none at all."""
        self._check_lone(now)
        self._check_silence(now)
        if self.aligner is None:
            return []
        pairs = self.aligner.poll(now)
        self._after_alignment()
        return self._process(pairs)

    def flush(self) -> list[Sample]:
        """End of a recording: settle what can still be settled (a side's incomplete parts are dropped)."""
        for channel, merger in self.mergers.items():
            merger.flush()
            self._after_merge(channel, merger)
        if isinstance(self.aligner, GridSampler):
            return self._process(self.aligner.flush())
        if isinstance(self.aligner, StampAligner):
            return self._process(self.aligner.poll(math.inf))
        return []

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
            self.counters["test_start_late"] += 1
            self._say(
                "test_start_late",
                f"test_start {index} came after sample {self.last_index}: samples {index}..{self.last_index} were "
                "learnt from (its publisher did not wait for this reader); the frozen phase is shorter",
            )

    @property
    def held(self) -> int:
        """Pairs formed while holding, not yet processed."""
        return len(self._held)

    def release(self) -> list[Sample]:
        """Stop holding: process the samples formed meanwhile (outputs now have readers)."""
        self.holding = False
        held, self._held = self._held, []
        return self._process(held)

    def held_at_stop(self) -> str | None:
        """The line to say when the node stops while it holds pairs (None: it holds none). They are not
        learnt: what they waited for (readers, or who publishes u and y_p) was never confirmed, and a stop
        within the grace would otherwise lose them without a word."""
        if not self._held:
            return None
        return (
            f"stopping with {len(self._held)} pairs held, not learnt: the outputs' readers or the publishers "
            "of u and y_p were not confirmed yet"
        )

    def discard_held(self) -> int:
        """Drop the pairs held so far as refused (the caller found they are not samples)."""
        dropped = len(self._held)
        self.counters["refused"] += dropped
        self._held = []
        return dropped

    # -- the graph (live): hold until the outputs have readers and the publishers are known ---------
    def hold_for(self, wanted: dict[str, int], grace: float = START_GRACE) -> None:
        """Live: hold formed pairs until each output in ``wanted`` has that many readers and, in
        ``sequence`` pairing, the graph has shown who publishes u and y_p (:mod:`~lenn_ros.core.holding`).

        Offline there is no graph: a recording's session never calls this.
        """
        self.gate = HoldGate(self.config.pairing, dict(wanted), self.config.u_name, self.config.y_name, grace)
        self.holding = self.gate.needed

    @property
    def publishers_known(self) -> bool:
        """Whether the graph has shown both inputs' publishers (or the grace for them ran out)."""
        return self.gate is None or self.gate.publishers_known

    def graph_publishers(self, seen: dict[str, set[tuple[str, str]]]) -> None:
        """The publishers (namespace, node) of each input ('u', 'y') the graph shows now.

        In ``sequence`` pairing, two disjoint sets refuse every half from now on (said with
        the fix, counted in ``refused``) and drop what is held; one node of both lifts it.
        """
        if self.gate is None:
            return
        decided, refusal = self.gate.publishers(seen)
        if not decided:
            return
        self.refusal = refusal
        if refusal is not None:
            self.discard_held()

    def release_ready(self, readers: dict[str, int], now: float) -> list[Sample]:
        """The held samples, processed, once the outputs have their ``readers`` and the publishers are
        vouched for (monotonic ``now``, s); else nothing, and what they wait for is said after the grace."""
        gate = self.gate
        if gate is None or not (self.holding and self._held):
            return []
        if not gate.readers_missing(readers):
            vouched, unverified = gate.vouched(now)
            if unverified is not None:
                self._say("unverified", unverified)
            if vouched:
                return self.release()
        waiting = gate.waiting_text(len(self._held), readers, now)
        if waiting is not None:
            self._say("holding", waiting)
        return []

    def release_pairs(self) -> list[Pair]:
        """Stop holding and hand the formed pairs over unprocessed (offline: learnt in one batch)."""
        self.holding = False
        held, self._held = self._held, []
        return held

    # -- pairing -------------------------------------------------------------------------------
    def _pair_by_sequence(
        self, channel: str, value: float, time: float, sequence: int | None, source_time: float | None
    ) -> list[Pair]:
        assert self.pairer is not None
        if sequence is None or sequence in SEQUENCE_UNSUPPORTED:
            self.counters["no_sequence"] += 1
            self._say(
                "no_sequence",
                "pairing 'sequence' needs DDS publication sequence numbers and this middleware gives none "
                "(e.g. rmw_cyclonedds): nothing is paired; use pairing:=sample sample_period:=T (or pairing:=stamp)",
            )
            return []
        restarts = self.pairer.counters["restarts"]
        released = self.pairer.add(channel, int(sequence), (value, time, source_time))
        if self.pairer.counters["restarts"] != restarts:
            self.identifier.restart_stream()
            self._last_sources = None
            self._say("restart", "sample indices started over (publisher restart): history reset")
        faults = self.pairer.counters["stale"] + self.pairer.counters["duplicates"]
        if released and faults > self._seen_faults:
            self._say_stale(faults)
        self._seen_faults = min(self._seen_faults, faults)  # a restart reclaimed halves counted stale
        if self.pairer.counters["unpaired"] > self._seen_dropped:
            dropped = self.pairer.counters["unpaired"] - self._seen_dropped
            self._seen_dropped = self.pairer.counters["unpaired"]
            self._say("dropped", f"{dropped} half(s) found no partner with the same index and were dropped")
        pairs = []
        for index, (u, _u_time, u_source), (y, y_time, y_source) in released:
            if u_source is None or y_source is None:
                pairs.append(Pair(index, y_time, u, y))
                continue
            skew = abs(u_source - y_source)
            previous, self._last_sources = self._last_sources, (u_source, y_source)
            in_turn = previous is not None and min(u_source, y_source) >= max(previous)
            if skew > self.config.max_skew and not in_turn:
                self.counters["misaligned"] += 1
                self._say(
                    "misaligned",
                    f"{self.config.u_name}[{index}] and {self.config.y_name}[{index}] were published {skew:.3f} s "
                    "apart and not both after the pair before: not one lockstep publisher, so equal indices are "
                    "not one sample; refused, never learnt. "
                    "Use pairing:=sample sample_period:=T (or pairing:=stamp)",
                )
                pairs.append(Pair(index, y_time, math.nan, math.nan))
                continue
            pairs.append(Pair(index, y_time, u, y))
        return pairs

    def _after_merge(self, channel: str, merger: TopicMerger) -> None:
        """A side's topics that do not come together: say which, and what became of the parts."""
        names = self.config.u_parts_names if channel == U else self.config.y_parts_names
        if merger.counters["overflow"]:
            self._say_doubling(
                f"{channel}_overflow",
                merger.counters["overflow"],
                f"{merger.counters['overflow']} incomplete {'u' if channel == U else 'y_p'} groups dropped so far: "
                f"more than {merger.window} wait for the side's other topics ({', '.join(names)})",
            )
        seen = self._seen_merge.setdefault(channel, {"merge_dropped": 0, "merge_stale": 0})
        for kind in ("merge_dropped", "merge_stale"):
            count = merger.counters[kind]
            if count <= seen[kind]:
                continue
            topic = ""
            if kind == "merge_stale" and merger.stale_part is not None:
                topic = names[merger.stale_part] if merger.stale_part < len(names) else f"part {merger.stale_part}"
                text = (f"{topic} is older than {merger.max_age:.3f} s when the other topics of its side arrive: "
                        f"no sample formed ({count} so far); is it still published?")  # fmt: skip
            else:
                text = (f"{count - seen[kind]} {'u' if channel == U else 'y_p'} message(s) found no partner on the "
                        f"side's other topics ({', '.join(names)}) and were dropped ({count} so far)")  # fmt: skip
            self._say(kind, text, topic)
            seen[kind] = count

    def _say_stale(self, faults: int) -> None:
        """Repeated or outdated halves, said when a pair is released.

        Not at once: the first halves of a restarted publisher count as stale until
        both halves of its sample 1 are in, and then the Pairer takes them back.
        """
        assert self.pairer is not None
        counters = self.pairer.counters
        self._say(
            "stale",
            f"{faults - self._seen_faults} {self.config.u_name}/{self.config.y_name} half(s) ignored, never learnt "
            f"(so far {counters['stale']} stale: index already paired or passed; {counters['duplicates']} duplicate: "
            "index repeated): a second publisher on one topic, one publisher restarted alone, or messages reordered "
            "on the way (a RELIABLE QoS with KEEP_ALL history keeps them in order)",
        )
        self._seen_faults = faults

    def _after_alignment(self) -> None:
        aligner = self.aligner
        assert aligner is not None
        if aligner.restarted:
            aligner.restarted = False
            self.identifier.restart_stream()
            text = "time went backwards (clock reset, bag looped): history reset"
            if self.clock_offset is not None:
                text += f"; the inputs' clocks also differ by {abs(self.clock_offset):.3f} s (see clock_offset)"
            self._say("clock_jump", text)
        overflow = aligner.counters["overflow"]
        if overflow and aligner.overflowed is not None:
            config = self.config
            name, other = (config.u_name, config.y_name)[:: 1 if aligner.overflowed == U else -1]
            self._say_doubling(
                "overflow",
                overflow,
                f"{overflow} messages dropped unpaired so far: {other} is silent, so {name}'s queue is full "
                f"({aligner.max_queue} waiting for a partner; the newest are kept). Is {other} published?",
            )
        dropped = sum(v for k, v in aligner.counters.items() if k.startswith("dropped") or k == "grid_gaps")
        if dropped > self._seen_dropped:
            what = "grid points without a new y_p (gaps)" if isinstance(aligner, GridSampler) else "unpaired halves"
            self._say("dropped", f"{dropped - self._seen_dropped} {what}: {dict(aligner.counters)}")
            self._seen_dropped = dropped

    def _watch_clocks(self, channel: str, time: float, received: float) -> None:
        """Compare the inputs' (receive - time): see the module docstring.

        A message timed by its arrival has time == received (the node and evaluate
        pass the same number), so its lag is 0 and the other input's least lag is
        the offset of its stamps. The least, not the median: on one host with one clock a
        loaded machine delays most messages by tens of ms, yet some still arrive at once,
        while a clock offset delays every one of them (a median above 50 ms under load was
        said as a clock offset). Taken every 16 halves once each
        input has half a window (the first messages after discovery can come late):
        cheap at kilohertz rates, and a burst delayed by a stall moves neither.
        """
        self._lags[channel].append(received - time)
        self._stamped[channel] = time != received
        if self.clock_offset is not None:
            self.counters["clock_offset"] += 1
        self._offset_checks += 1
        if self._offset_checks % 16 or min(len(lags) for lags in self._lags.values()) < CLOCK_WINDOW // 2:
            return
        lag = {name: min(lags) for name, lags in self._lags.items()}
        offset = lag[Y] - lag[U]
        limit = self.config.max_clock_offset or max(0.5 * self.config.sample_period, 0.05)
        if self.clock_offset is None and abs(offset) > limit:
            self.clock_offset = offset
            self.counters["clock_offset"] += 1
            self._say("clock_offset", self._clock_offset_text(lag, limit))
        elif self.clock_offset is not None and abs(offset) <= 0.5 * limit:
            self.clock_offset = None  # the clocks agree again (hysteresis: no notice per wobble)

    def _clock_offset_text(self, lag: dict[str, float], limit: float) -> str:
        config = self.config
        names = {U: config.u_name, Y: config.y_name}
        offset = abs(lag[Y] - lag[U])
        if all(self._stamped.values()):
            what = (
                f"the header stamps of {names[U]} and {names[Y]} lag their arrival by {lag[U]:.3f} and {lag[Y]:.3f} s "
                f"(at least, over their last {CLOCK_WINDOW} messages): two clocks"
            )
        else:
            stamped = Y if self._stamped[Y] else U
            side = "behind" if lag[stamped] > 0 else "ahead of"
            what = (
                f"{names[stamped]} is timed by its header stamps and {names[U if stamped == Y else Y]} by arrival, "
                f"and {names[stamped]}'s stamps are {abs(lag[stamped]):.3f} s {side} its arrival (every one of its "
                f"last {CLOCK_WINDOW} messages)"
            )
        return (
            f"{what}: each {names[U]} is paired with a {names[Y]} {offset:.3f} s away from it (more than "
            f"{limit * 1e3:.0f} ms: a clock offset, not a delay under load, which leaves some messages on time). "
            "Fix: -p use_header_stamp:=false (time "
            "both inputs by arrival), or synchronise the clocks (chrony/PTP; use_sim_time on every node or none). "
            "If the measurement really is taken that long before it arrives, the stamps are right: ignore this"
        )

    def _alone_for(self, channel: str, now: float) -> float:
        """How long ``channel`` has been arriving while the other input is silent (0: not alone)."""
        seen = self._last_seen.get(channel)
        if seen is None or now - seen > self.config.lone_timeout:
            return 0.0
        other_seen = self._last_seen.get(Y if channel == U else U)
        if other_seen is not None and now - other_seen <= self.config.lone_timeout:
            return 0.0
        return now - max(self._first_seen[channel], other_seen if other_seen is not None else -math.inf)

    def _check_silence(self, now: float) -> None:
        """Neither input for ``silence_timeout`` s after data flowed: said once, counted, shown in the status
        until a message comes (said again then, with how long it lasted).

        A driver that died with its publisher still matched, or one that publishes only on change
        while the robot stands still, looks the same from here: nothing to learn from. Without
        this line a status that still reads "identifying" would hide it.
        """
        timeout = self.config.silence_timeout
        if not timeout or not self._last_seen or self._silent_since is not None:
            return
        last = max(self._last_seen.values())
        if now - last < timeout:
            return
        self._silent_since = last
        self.counters["silences"] += 1
        self._say("silence", f"nothing on {self.config.u_name} or {self.config.y_name} for {now - last:.1f} s "
                  f"(silence_timeout {timeout:g} s): no sample to learn from; a stopped driver, or one that "
                  "publishes only on change while the robot stands still?")  # fmt: skip

    @property
    def silent(self) -> bool:
        """Whether the inputs are silent (said by :meth:`_check_silence`, until a message comes)."""
        return self._silent_since is not None

    def _check_lone(self, now: float) -> None:
        for channel in (U, Y):
            alone = self._alone_for(channel, now)
            if alone >= self.config.lone_timeout:
                topic, missing = (self.config.u_name, self.config.y_name)[:: 1 if channel == U else -1]
                lone = self.counters[f"lone_{channel}"]
                head = f"{topic} has been arriving alone for {alone:.1f} s ({lone} messages)"
                count, last, why = self._unreadable.get(Y if channel == U else U, (0, -math.inf, ""))
                if now - last <= self.config.lone_timeout:
                    text = (f"{head}: {count} messages arrived on {missing} but their field could not be read: {why}; "
                            "so no pairs form (fix the field path, or the type, to fit these messages)")  # fmt: skip
                else:
                    text = (f"{head}: nothing on {missing}, so no pairs form (check {missing}'s topic name/remap, "
                            "type and QoS)")  # fmt: skip
                self._say(f"lone_{channel}", text)

    # -- learning ------------------------------------------------------------------------------
    def _process(self, pairs: list[Pair]) -> list[Sample]:
        if self.collect is not None:
            self.collect(pairs)
            return []
        if self.holding:
            self._held.extend(pairs)
            excess = len(self._held) - MAX_HELD
            if excess > 0:  # the readers never came: keep the newest
                del self._held[:excess]
                self.counters["held_overflow"] += excess
                self._say_doubling(
                    "held_overflow",
                    self.counters["held_overflow"],
                    f"{self.counters['held_overflow']} held pairs dropped, never learnt: {MAX_HELD} wait for the "
                    "outputs' readers (wait_for_*_subscribers) and no more are kept (the newest are)",
                )
            return []
        if self.warm_up is not None and not self.warm_up.done:
            pairs = self._warm(pairs)
        return [self._step(pair) for pair in pairs]

    def _warm(self, pairs: list[Pair]) -> list[Pair]:
        """Hold pairs until the warm-up knows the scales; then every pair held so far, and the rest."""
        warm_up = self.warm_up
        assert warm_up is not None
        for position, pair in enumerate(pairs):
            self._warming.append(pair)
            if warm_up.add(pair.u, pair.y):
                self._end_warm_up()
                held, self._warming = self._warming, []
                return held + pairs[position + 1 :]
            if len(self._warming) >= MAX_WARM_UP:
                self._restart_warm_up(len(self._warming))
                self._warming = []
        return []

    def _end_warm_up(self) -> None:
        assert self.warm_up is not None
        identifier = self.identifier
        identifier.set_structure(self.warm_up.structure(identifier.structure))
        self._say("scales", self.warm_up.text(self.config.u_name, self.config.y_name))

    def _restart_warm_up(self, held: int) -> None:
        assert self.warm_up is not None
        self.warm_up.restart(held)
        self.counters["warm_up_discarded"] += held
        self._say(
            "warm_up_discarded",
            f"{held} samples held for the scale warm-up discarded, never learnt: {self.config.u_name} or "
            f"{self.config.y_name} did not move in them "
            "(a plant at rest shows nothing of its range); the warm-up starts over. Fix: move the plant, or give "
            "y_scale/u_scale",
        )

    def _warm_offline(self, u: np.ndarray, y: np.ndarray) -> int | None:
        """:meth:`_warm` over a whole series: the first row the identifier is stepped from (None: never)."""
        warm_up = self.warm_up
        assert warm_up is not None
        first = 0
        for row in range(len(y)):
            if warm_up.add(u[row], y[row]) if self.mimo else warm_up.add(float(u[row]), float(y[row])):
                self._end_warm_up()
                return first
            if row + 1 - first >= MAX_WARM_UP:
                self._restart_warm_up(row + 1 - first)
                first = row + 1
        return None

    def _say_doubling(self, kind: str, count: int, text: str) -> None:
        """Say a drop that may go on for hours at its first occurrence, then each time its count doubles.

        Rate-limited without a clock (the offline path has none worth trusting): a handful of
        lines per run, each with the count, which ``status`` carries anyway.
        """
        said = self._said_at_count.get(kind)
        if said is None or count >= 2 * said:
            self._said_at_count[kind] = count
            self._say(kind, text)

    def queued(self) -> dict[str, int]:
        """What waits in the session's queues now: halves to pair, parts to merge, pairs held (all bounded)."""
        source = self.pairer if self.pairer is not None else self.aligner
        return {
            "pairing": source.queued if source is not None else 0,
            "merging": sum(merger.queued for merger in self.mergers.values()),
            "held": len(self._held),
            "warm_up": len(self._warming),
        }

    def _follows_test_start(self) -> bool:
        """test_start is a sequence number: followed in sequence pairing only, and when asked to."""
        return self.config.follow_test_start and self.config.pairing == "sequence"

    def _learns(self, index: int) -> bool:
        if not self.config.learning:
            return False
        return not (self._follows_test_start() and self.test_start is not None and index >= self.test_start)

    def _step(self, pair: Pair) -> Sample:
        self.last_index = pair.index
        if self.mimo:
            refused = bool(np.isnan(pair.u).any() or np.isnan(pair.y).any())
        else:
            refused = math.isnan(pair.u) or math.isnan(pair.y)  # (no numpy call per sample for one channel)
        if refused:
            self.identifier.skip(pair.index)
            self._last_pair = pair
            return Sample(pair.index, pair.time, pair.u, pair.y, None)
        learn = self._learns(pair.index)
        if learn != self.phase_learning:
            self.phase_learning = learn
            self.phase_nmse.reset()
            self._say("phase", f"sample {pair.index}: {'training' if learn else 'frozen (test)'} phase")
        result = self.identifier.step(pair.index, pair.u, pair.y, learn)
        if learn and self.identifier.sign_settled is not self._sign_settled:
            self._say_sign(pair.index)
        if result.event == "gap":
            self._say_gap(pair)
        elif result.event in ("diverged", "resumed"):
            self._say(result.event, self._divergence_text(pair.index, result.event))
        self._last_pair = pair
        if self.identifier.counters["clipped"] > self._seen_clipped:
            self._say_clipped(pair.time)
        if result.error is not None and result.y_hat is not None:
            self.phase_nmse.add(pair.y, result.y_hat)
        if self.spread is not None:
            self._watch(pair, result)
        return Sample(pair.index, pair.time, pair.u, pair.y, result)

    def _say_sign(self, index: int) -> None:
        """A |y| sensor (``y_abs``): learning waits for the sign to settle after each start, and resumes."""
        self._sign_settled = settled = self.identifier.sign_settled
        if settled:
            self._say("sign", f"sample {index}: the sign of |y| has settled: learning (not where a sign is unsure, "
                      "at a crossing: counted in sign_unsure)")  # fmt: skip
        elif settled is not None:
            self._say("sign", f"sample {index}: not learning until the sign of |y| settles (the model's free runs "
                      "from either sign of the start must agree; counted in sign_unsure)")  # fmt: skip

    _sign_settled: bool | None = None

    def _watch(self, pair: Pair, result: StepResult) -> None:
        """One output: the one-step std of each prediction (core.spread) and the change alarm (core.change)."""
        spread = self.spread
        assert spread is not None
        error = result.error
        if error is not None:
            result.y_hat_std = self._next_std
            spread.update(error)
            if self.config.change_alarm and self.change is not None:
                event = self.change.update(error, pair.index, pair.y)  # (one output: a float already)
                if event:
                    self._say_change(event, pair.index, pair.time)
        if result.y_hat_next is not None:
            result.y_hat_next_std = self._next_std = spread.std(result.leverage)

    def _spread_offline(self, y: np.ndarray, y_hat: np.ndarray, leverage: np.ndarray) -> np.ndarray:
        """:meth:`_watch`'s one-step std over a batch (``run_samples``): the std each y^(k) was published with.

        The same :class:`~lenn_ros.core.spread.OneStepSpread` calls in the same order as
        live: each scored error updates it, then the next prediction asks for its std
        with its pattern's leverage (the batch RLS reports the same phi' P phi the step
        does), so a recording evaluated offline has the band the node published.
        """
        spread = self.spread
        out = np.full(len(y), np.nan)
        if spread is None:
            return out
        errors = (y - y_hat).tolist()
        predicted = np.isfinite(y_hat).tolist()
        levers = leverage.tolist()
        next_std = self._next_std
        update, std = spread.update, spread.std
        for k, error in enumerate(errors):
            if error == error:  # finite where predicted (y is finite in a valid row)
                out[k] = math.nan if next_std is None else next_std
                update(error)
            if k + 1 < len(errors) and predicted[k + 1]:
                next_std = std(levers[k + 1])
        self._next_std = next_std
        return out

    def _watch_change(
        self,
        index: np.ndarray,
        y: np.ndarray,
        y_hat: np.ndarray,
        before: tuple[bool, float],
        changes: Sequence[ParameterChange],
    ) -> None:
        """:meth:`_step`'s change alarm over a batch (``run_samples``): every scored error, in order, as live.

        ``before``: (change_alarm, change_threshold) when the batch started; recorded live
        changes of either take effect at their sample, as they did live.
        """
        detector = self.change
        if detector is None:
            return
        watched, detector.threshold = before
        pending = sorted(
            (change for change in changes if {"change_alarm", "change_threshold"} & set(change.values)),
            key=lambda change: change.from_index,
        )
        errors = y - y_hat
        scored = np.flatnonzero(np.isfinite(errors))
        update = detector.update
        measured = y.tolist()
        for row, error in zip(scored.tolist(), errors[scored].tolist(), strict=True):
            sample = int(index[row])
            while pending and pending[0].from_index <= sample:
                values = pending.pop(0).values
                watched = bool(values.get("change_alarm", watched))
                detector.threshold = float(values.get("change_threshold", detector.threshold))
            if watched:
                event = update(error, sample, measured[row])
                if event:
                    self._say_change(event, sample, None)
        detector.threshold = self.config.change_threshold

    def _say_change(self, event: str, index: int, time: float | None) -> None:
        """The alarm rose (one WARN line: when, by how much) or cleared (one info line: how long it was on)."""
        detector = self.change
        assert detector is not None
        when = f"sample {index}" + (f" (t={time:.3f} s)" if time is not None else "")
        if event == RAISED:
            self.counters["change_alarms"] += 1
            self.change_time, self.change_started = time, index
            self._say("change", self.change_text(index, time))
            return
        started, self.change_time = self.change_started, None
        how = (
            "the model has re-learnt: residual level back within "
            f"{detector.clear_ratio:g}x its learnt level for {detector.hold_samples} samples"
            if event != ACCEPTED
            else f"the model did not get back to the old level in {detector.accept_samples} samples: its level now "
            "is taken as the learnt one"
        )
        self._say(
            "change_cleared",
            f"{when}: plant change alarm (raised at sample {started}, peak {detector.peak:.1f}x) cleared: {how}",
        )

    def change_text(self, index: int, time: float | None) -> str:
        """The alarm in one line: when, and by how much the residual level rose."""
        detector = self.change
        assert detector is not None
        when = f"sample {index}" + (f" (t={time:.3f} s)" if time is not None else "")
        return (
            f"plant changed at {when}: residual level {detector.magnitude:.1f} times its learnt level "
            f"(RMS one-step error; CUSUM over change_threshold {detector.threshold:g}; alarm {detector.count})"
        )

    _last_pair: Pair | None = None

    def _say_gap(self, pair: Pair) -> None:
        """A gap before ``pair``: how long (samples and seconds), and whether it is a stall or lost messages."""
        last = self._last_pair
        counters = self.identifier.outputs[0].counters if self.mimo else self.identifier.counters
        missing = pair.index - last.index - 1 if last is not None else 0
        seconds = pair.time - last.time if last is not None else None
        self._say(
            "gap",
            f"sample {pair.index}: a gap of {gap_text(self.config.pairing, missing, seconds)}; the model restarts its "
            f"history there ({counters['gaps']} gaps, {counters['lost']} sample indices missing so far)",
        )

    def _divergence_text(self, index: int, event: str) -> str:
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

    # -- whole series (offline) --------------------------------------------------------------------
    def run_samples(
        self,
        index: np.ndarray,
        u: np.ndarray,
        y: np.ndarray,
        learn: np.ndarray,
        changes: Sequence[ParameterChange] = (),
    ) -> np.ndarray:
        """The samples a live session formed, learnt again in one pass; returns y^(k) (nan: none).

        ``changes``: the live parameter changes recorded with the run, each applied
        (:meth:`replay_change`) where its sample comes, as live: before the first sample
        whose index is at least its ``from_index`` (after the last sample, if none is).

        Equal to stepping them one by one (the node's path): runs of consecutive valid
        indices go to :meth:`Identifier.run <lenn_ros.core.structure.Identifier.run>`,
        which batches the compiled kernel at the same boundaries as ``step``; a
        missing index or a refused sample (NaN) restarts the history there, as live.
        The phase NMSE follows the learn flags as live (a new phase starts where the
        flag changes).
        """
        if self.mimo and changes:
            raise NotImplementedError("live parameter changes are not replayed into a MIMO model's batch pass")
        index = np.asarray(index, dtype=np.int64)
        u = np.asarray(u, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        learn = np.asarray(learn, dtype=bool)
        if self.warm_up is not None and not self.warm_up.done:
            first = self._warm_offline(u, y)  # live, the rows before it were discarded by the warm-up
            y_hat = np.full(y.shape, np.nan)
            std = np.full(len(y), np.nan)
            if first is not None:
                y_hat[first:] = self.run_samples(index[first:], u[first:], y[first:], learn[first:], changes)
                if not self.mimo:  # (one output's band only)
                    std[first:] = self.last_y_hat_std
            self.last_y_hat_std = std
            return y_hat
        y_hat = np.full(y.shape, np.nan)
        valid = finite_rows(u) & finite_rows(y)
        # a MIMO identifier's index counters are its outputs' (they count alike): output 0's hold them
        counters = self.identifier.outputs[0].counters if self.mimo else self.identifier.counters
        gaps, lost = missing(index)
        counters["gaps"] += gaps
        counters["lost"] += lost
        counters["rejected"] += int(np.count_nonzero(~valid))
        before = (self.config.change_alarm, self.config.change_threshold)
        leverage = np.zeros(len(y))
        self._run_segments(index, u, y, learn, *runs(index, valid), valid, changes, y_hat, leverage)
        if not self.mimo:
            self.last_y_hat_std = self._spread_offline(y, y_hat, leverage)
            self._watch_change(index, y, y_hat, before, changes)
        if index.size:
            self.last_index = int(index[-1])
        phases = learn[valid]
        if phases.size:
            changes = np.flatnonzero(phases[1:] != phases[:-1]) + 1
            if phases[0] != self.phase_learning or changes.size:
                self.phase_nmse.reset()
            self.phase_learning = bool(phases[-1])
            last = np.flatnonzero(valid)[changes[-1]] if changes.size else 0
            scored = valid & finite_rows(y_hat) & (np.arange(len(y)) >= last)
            self.phase_nmse.extend(y[scored], y_hat[scored])
        self._say_offline()
        return y_hat

    def _say_offline(self) -> None:
        """What a batch pass says once for all its samples (live: as it happens)."""
        if self.identifier.counters["clipped"] > self._seen_clipped:
            self._say_clipped(None)
        unsure = self.identifier.counters.get("sign_unsure", 0)
        if unsure > self._seen_unsure:  # (live: a line at each start and when it settles)
            self._say("sign", f"{unsure - self._seen_unsure} samples not learnt for an unsure sign of |y|: after a "
                      "start or a gap until it settled, and at crossings (counted in sign_unsure)")  # fmt: skip
            self._seen_unsure = unsure

    _seen_unsure = 0

    def _run_segments(
        self,
        index: np.ndarray,
        u: np.ndarray,
        y: np.ndarray,
        learn: np.ndarray,
        starts: np.ndarray,
        stops: np.ndarray,
        valid: np.ndarray,
        changes: Sequence[ParameterChange],
        y_hat: np.ndarray,
        leverage: np.ndarray,
    ) -> None:
        """Each run of consecutive valid samples through the identifier, with each change applied at its sample;
        ``leverage`` gets each prediction's phi' P phi (SISO RLS), for :meth:`_spread_offline`."""
        pending = sorted(changes, key=lambda change: change.from_index)  # (stable: one index, in recorded order)
        where = [int(np.searchsorted(index, change.from_index, side="left")) for change in pending]

        def applier(change: ParameterChange) -> Callable[[], None]:
            return lambda: self.replay_change(change)

        for start, stop in zip(starts, stops, strict=True):
            while pending and where[0] <= start:  # before this run (or in a break before it)
                where.pop(0)
                self.replay_change(pending.pop(0))
            inside = []
            while pending and where[0] < stop:
                inside.append((where.pop(0) - start, applier(pending.pop(0))))
            if stop > start and valid[start]:
                cuts = (inside,) if inside else ()  # (a MIMO identifier's run takes none: refused above)
                y_hat[start:stop] = self.identifier.run(u[start:stop], y[start:stop], learn[start:stop], *cuts)
                if not self.mimo:
                    leverage[start:stop] = self.identifier.last_leverage
        for change in pending:  # from after the last sample: no sample learns with it, the state has it
            self.replay_change(change)

    def _say_clipped(self, time: float | None) -> None:
        """Network inputs outside [-1, 1]: said at most every ``warn_period`` s of sample time (None: now).

        Throttled here as well as in the node: the condition holds for sample after
        sample, and ``evaluate`` lists every distinct notice it is handed.
        """
        if time is not None and abs(time - self._clipped_said_at) < self.config.warn_period:
            return
        clipped = self.identifier.counters["clipped"]
        self._say(
            "clipped_inputs",
            f"{clipped} network inputs outside [-1, 1] clipped so far (+{clipped - self._seen_clipped}): the scaled "
            f"{self.config.u_name} / {self.config.y_name} leave the range the network is built for, and it learns "
            "them flattened. Fix: u_scale/u_offset, y_scale/y_offset that map the signals into [-1, 1] (the network "
            "sees (u - u_offset) / u_scale), or `lenn-ros fit` a recording to take them from the data"
            + (
                f" (the scales were learnt from the first {self.warm_up.valid} samples and the signals have left "
                "that range: a longer scale_warm_up, or scales by hand)"
                if self.warm_up is not None and self.warm_up.done
                else ""
            ),
        )
        self._seen_clipped = clipped
        if time is not None:
            self._clipped_said_at = time

    # -- reporting -----------------------------------------------------------------------------
    def _say(self, kind: str, text: str, subject: str = "") -> None:
        self._notices.append(Notice(kind, text, subject))
        if len(self._notices) > 1000:  # nobody is reading: keep the newest
            del self._notices[:500]

    def take_notices(self) -> list[Notice]:
        notices, self._notices = self._notices, []
        return notices

    def all_counters(self) -> dict[str, int]:
        """Every counter of the session, its pairing and the model, in one flat dict."""
        counters = dict(self.counters)
        source = self.pairer.counters if self.pairer is not None else self.aligner.counters  # type: ignore[union-attr]
        for name, value in source.items():
            counters[f"pairing_{name}" if name in counters else name] = value
        for channel, merger in self.mergers.items():
            for name, value in merger.counters.items():
                counters[f"{channel}_{name}"] = value
        renamed = {"clipped": "clipped_inputs", "duplicates": "model_duplicates"}  # vs the session's own
        for name, value in self.identifier.counters.items():
            counters[renamed.get(name, name)] = value
        return counters

    def status(self) -> dict[str, Any]:
        """Everything a user or a test needs to know about the session so far (JSON-safe)."""
        return json_safe(
            {
                "pairing": self.config.pairing,
                "learning": self._learning_now(),
                "diverged": self.identifier.diverged,
                "resume_in": self.identifier.resume_in if self.identifier.diverged else None,
                "test_start": self.test_start,
                "refused": self.refusal,
                "silent_since": self._silent_since,  # receive time of the last message while silent, else None
                "phase_samples": self.phase_nmse.count,
                "phase_nmse_db": self.phase_nmse.nmse_db,
                "phase_rmse": self.phase_nmse.rmse,
                "counters": self.all_counters(),
                "queued": self.queued(),
                "lag_s": self.shedder.lag,
                "samples_seen": int(getattr(self.identifier.model, "n_samples_seen_", 0)),
                "scaling": self.warm_up.status() if self.warm_up is not None else {"state": "given"},
                "parameter_changes": len(self.changes),  # live changes applied, each in identifier_config
                "change": self._change_status(),
                **({"channels": self._channel_status()} if self.mimo else {}),
            }
        )

    def _change_status(self) -> dict[str, Any]:
        """``status['change']``: the alarm (on, how many, since when, by how much) or why it is not watched."""
        if self.change is None:
            return {"alarm": False, "watched": False, "why": "one output only (a MIMO model is not watched)"}
        watched = {"watched": True} if self.config.change_alarm else {"watched": False, "why": "change_alarm is false"}
        return {**self.change.status(), **watched, "since_time": self.change_time}

    def _learning_now(self) -> bool:
        """Whether samples are learnt now: the phase learns and the model is not paused after a divergence."""
        phase = bool(self.phase_learning) if self.phase_learning is not None else self.config.learning
        return phase and not self.identifier.diverged

    def _channel_status(self) -> dict[str, Any]:
        """Per output channel of a MIMO model: its phase NMSE and whether its model diverged."""
        assert isinstance(self.phase_nmse, ChannelsNMSE) and isinstance(self.identifier, MimoIdentifier)
        return {
            name: {"phase_nmse_db": channel.nmse_db, "phase_rmse": channel.rmse, "diverged": output.diverged}
            for name, channel, output in zip(
                self.phase_nmse.names, self.phase_nmse.channels, self.identifier.outputs, strict=True
            )
        }


def json_safe(value: Any) -> Any:
    """NaN and infinities become None (JSON has no NaN: strict parsers reject it)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(item) for item in value]
    return value
