"""Several inputs, several outputs: one MISO series-parallel model per output.

A robot arm's joints or a process's tanks are coupled: output j's next value depends
on the other outputs and on every actuator, not only on "its own" input. The MIMO
identifier gives each output j one network over the lags of the channels that are
allowed to feed it (``couplings``: all by default, or a configured subset such as
``y0 u0 u1``) and learns them side by side from the same paired vector samples.

Nothing new is learnt here: output j's model is an ordinary
:class:`~lenn_ros.core.structure.Identifier` whose "input" is the vector of the other
channels it sees (the other outputs at k, k-1, ... are measured like inputs in
series-parallel mode), so gaps, duplicates, rejection, the divergence guard and the
batch :meth:`~lenn_ros.core.structure.Identifier.run` are those of the SISO path,
bit for bit. What only a MIMO model has is the parallel (free-run) model, where every
output is fed the *model's* other outputs: :meth:`MimoIdentifier.free_run`.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from lenn_ros.core.free_run import OutputRun, free_run_outputs
from lenn_ros.core.structure import Identifier, ModelStructure, StepResult
from lenn_ros.core.threads import cores, side_by_side

COUPLING_PRESETS = ("full", "diagonal")
_CHANNEL = re.compile(r"([uy])(\d+)")


def parse_couplings(text: str, n_u: int, n_y: int) -> tuple[tuple[str, ...], ...]:
    """Which channels feed each output: ``full``, ``diagonal`` or ``y0 u0 u1; y1 y0 u1``.

    ``full``: every output and input (the MIMO model); ``diagonal``: output j sees only
    its own past and input j (one SISO model per output, for comparison; needs as many
    inputs as outputs). An explicit list names the channels of output 0, 1, ... in
    order, ``;``-separated. Raises ValueError with the reason in one line.
    """
    text = text.strip()
    names_y = [f"y{j}" for j in range(n_y)]
    names_u = [f"u{i}" for i in range(n_u)]
    if text in ("", "full"):
        return tuple(tuple(names_y + names_u) for _ in range(n_y))
    if text == "diagonal":
        if n_u != n_y:
            raise ValueError(
                f"couplings 'diagonal' pairs output j with input j: needs as many inputs ({n_u}) as outputs ({n_y})"
            )
        return tuple((f"y{j}", f"u{j}") for j in range(n_y))
    groups = [group.split() for group in text.split(";")]
    if len(groups) != n_y:
        raise ValueError(f"couplings {text!r} lists {len(groups)} output(s) (';'-separated), the plant has {n_y}")
    known = set(names_y + names_u)
    result = []
    for j, group in enumerate(groups):
        unknown = [name for name in group if name not in known]
        if unknown:
            raise ValueError(f"couplings of y{j}: no channel {unknown[0]!r} (channels: {', '.join(names_y + names_u)})")
        if not group:
            raise ValueError(f"couplings of y{j}: empty; name at least one of {', '.join(names_y + names_u)}")
        result.append(tuple(dict.fromkeys(group)))
    return tuple(result)


@dataclass(frozen=True)
class MimoStructure:
    """Lags, scales and couplings of a model with ``n_u`` inputs and ``n_y`` outputs.

    Scales/offsets are per channel (the network sees (value - offset) / scale in
    [-1, 1]); ``couplings[j]`` names the channels (``y0``, ``u1``...) output j sees.
    """

    n_u: int
    n_y: int
    y_lags: int = 1
    u_lags: int = 1
    y_scale: tuple[float, ...] = ()
    y_offset: tuple[float, ...] = ()
    u_scale: tuple[float, ...] = ()
    u_offset: tuple[float, ...] = ()
    couplings: tuple[tuple[str, ...], ...] = ()
    separate: bool = False  # each output N1[its own past] + N2[the other channels it sees] (Model 3)
    #: per output: y(k) passed through as the known part y(k+1) = y(k) + ..., the network its increment. An
    #: output that integrates (a wheel, a joint without gravity) goes where its input takes it, beyond the
    #: range its network reads; passed through, its level is exact at any value (``fit`` sets it).
    y_pass_through: tuple[bool, ...] = ()

    def __post_init__(self) -> None:
        if self.n_u < 1 or self.n_y < 1:
            raise ValueError("a MIMO model needs at least one input and one output channel")
        if self.y_lags < 0 or self.u_lags < 0 or self.y_lags + self.u_lags == 0:
            raise ValueError("the networks need inputs: y_lags + u_lags >= 1")
        for name, values, count in (
            ("y_scale", self.y_scale, self.n_y),
            ("y_offset", self.y_offset, self.n_y),
            ("u_scale", self.u_scale, self.n_u),
            ("u_offset", self.u_offset, self.n_u),
        ):
            if values and len(values) != count:
                raise ValueError(f"{name} has {len(values)} value(s), one per channel needs {count}")
        if self.y_pass_through and len(self.y_pass_through) != self.n_y:
            raise ValueError(f"y_pass_through has {len(self.y_pass_through)} value(s), one per output needs {self.n_y}")
        if not self.couplings:
            object.__setattr__(self, "couplings", parse_couplings("full", self.n_u, self.n_y))
        # where each output's other channels sit in the vector [y_0.., u_0..]: picked once per sample
        columns = [[i if kind == "y" else self.n_y + i for kind, i in self.others(j)] for j in range(self.n_y)]
        object.__setattr__(self, "_picks", tuple(np.array(c, dtype=np.intp) for c in columns))

    @property
    def scaled(self) -> bool:
        """Whether every channel's scale is known (0: to be learnt by a session's warm-up, core.warmup)."""
        return all(scale > 0 for scale in (*self.y_scale, *self.u_scale))

    @property
    def warm_up(self) -> int:
        """Samples of history before the first prediction: every output's (their common ``history``).

        So code written for a SISO structure's ``warm_up`` (a free run restarted after each
        break, a regression masked at gaps) reads a MIMO model's the same way.
        """
        return max(self.y_lags, self.u_lags, 1)

    def _scale(self, kind: str, index: int) -> tuple[float, float]:
        """(scale, offset) of a channel; a scale still to be learnt stands in as 1 until the warm-up sets it."""
        scales, offsets = (self.y_scale, self.y_offset) if kind == "y" else (self.u_scale, self.u_offset)
        scale = float(scales[index]) if scales else 1.0
        return (scale if scale > 0 else 1.0), (float(offsets[index]) if offsets else 0.0)

    def others(self, output: int) -> list[tuple[str, int]]:
        """The channels output ``output`` sees besides itself, in regressor order: (kind, index)."""
        seen = [(match.group(1), int(match.group(2))) for match in map(_CHANNEL.fullmatch, self.couplings[output])]
        return [channel for channel in seen if channel != ("y", output)]

    def channel(self, output: int) -> ModelStructure:
        """Output ``output``'s structure: its own lags, then each channel it sees (the first in the u
        fields, the rest in ``others``), all predicting from the model's common warm-up."""
        own = f"y{output}" in self.couplings[output]
        passed = bool(self.y_pass_through[output]) if self.y_pass_through else False
        if passed and not (own and self.y_lags):
            raise ValueError(f"y_pass_through: output y{output} passes y(k) through, so it needs its own past")
        scale, offset = self._scale("y", output)
        channels = []
        for kind, index in self.others(output):
            other_scale, other_offset = self._scale(kind, index)
            channels.append((self.y_lags if kind == "y" else self.u_lags, other_offset, other_scale))
        first = channels[0] if channels else (0, 0.0, 1.0)
        return ModelStructure(
            y_lags=self.y_lags if own else 0,
            u_lags=first[0],
            u_offset=first[1],
            u_scale=first[2],
            y_scale=scale,
            y_offset=offset,
            others=tuple(channels[1:]),
            history=max(self.y_lags, self.u_lags, 1),
            known_a=(1.0,) if passed else (),
            output_offset=0.0 if passed else offset,  # (passed: y(k) carries the level, the network learns increments)
            separate=self.separate,
        )

    def other_values(self, output: int, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The columns (or, for one sample, the vector) of the other channels output ``output`` sees."""
        return np.concatenate((y, u), axis=-1)[..., self.picks(output)]

    def picks(self, output: int) -> np.ndarray:
        """Where output ``output``'s other channels sit in the vector [y_0.., u_0..]."""
        return self._picks[output]


@dataclass
class MimoStepResult:
    """What one paired vector sample produced: per-output arrays (None before the warm-up), and each output's
    own :class:`StepResult` (``outputs``: what the session's monitors watch, output by output)."""

    index: int
    y_hat_next: np.ndarray | None = None
    error: np.ndarray | None = None
    y_hat: np.ndarray | None = None
    learned: bool = False
    event: str = ""  # "diverged" if any output diverged, else the first non-empty one (gap, duplicate)
    outputs: list[StepResult] = field(default_factory=list)
    y_hat_next_std: np.ndarray | None = None  # one-step std of each output's y_hat_next (the monitors' band)
    y_hat_std: np.ndarray | None = None  # ... of each output's y_hat
    y_hat_next_band: np.ndarray | None = None  # half-width of each output's live 95 % band around y_hat_next
    y_hat_band: np.ndarray | None = None  # ... around y_hat

    def gather_stds(self) -> None:
        """The outputs' stds and live half-widths (filled in by the monitors) as vectors, published beside y^."""
        self.y_hat_next_std = _stack([out.y_hat_next_std for out in self.outputs])
        self.y_hat_std = _stack([out.y_hat_std for out in self.outputs])
        self.y_hat_next_band = _stack([out.y_hat_next_band for out in self.outputs])
        self.y_hat_band = _stack([out.y_hat_band for out in self.outputs])


def _stack(values: list[float | None]) -> np.ndarray | None:
    return None if any(value is None for value in values) else np.array(values, dtype=np.float64)


#: a run this long or longer runs its outputs on threads: a bag's many short runs between gaps would
#: pay a thread pool each for work of microseconds
THREADED_RUN_SAMPLES = 1000


@dataclass
class MimoIdentifier:
    """One :class:`Identifier` per output, stepped together on vector samples.

    Offers the interface a :class:`~lenn_ros.session.Session` drives (``step``,
    ``skip``, ``restart_stream``, ``run``, ``counters``, ``diverged``), so the node,
    ``evaluate`` and replay handle a MIMO plant with the session code they use for one
    output. ``counters`` adds up the outputs' counters except ``samples`` and the
    indexing ones, which every output counts alike.
    """

    structure: MimoStructure
    outputs: list[Identifier]
    names: tuple[str, ...] = ()
    _learning: bool = field(default=True, repr=False)

    #: Its samples carry a vector per side (:mod:`lenn_ros.session.values`), even of one channel.
    vector = True

    @property
    def n_u(self) -> int:
        return self.structure.n_u

    @property
    def n_y(self) -> int:
        return self.structure.n_y

    @property
    def SCALING(self) -> tuple[str, ...]:
        return ("y_scale", "u_scale", "y_offset", "u_offset")

    def __post_init__(self) -> None:
        if len(self.outputs) != self.structure.n_y:
            raise ValueError(f"{len(self.outputs)} models for {self.structure.n_y} outputs")
        if not self.names:
            self.names = tuple(f"y{j}" for j in range(self.structure.n_y))
        self.last_free_run: dict = {}  # what the last free_run did (samples, clipped inputs, divergence)

    @property
    def model(self):
        """Output 0's model: what a status reports as the model (weights per output: ``outputs``)."""
        return self.outputs[0].model

    @property
    def models(self) -> list:
        return [identifier.model for identifier in self.outputs]

    #: a |y| sensor is one output's option (``y_abs``): never waited for here
    sign_settled = None

    @property
    def learning(self) -> bool:
        return self._learning

    @learning.setter
    def learning(self, value: bool) -> None:
        self._learning = bool(value)
        for identifier in self.outputs:
            identifier.learning = bool(value)

    @property
    def diverged(self) -> bool:
        return any(identifier.diverged for identifier in self.outputs)

    @property
    def health_interval(self) -> int:
        return self.outputs[0].health_interval

    @health_interval.setter
    def health_interval(self, value: int) -> None:
        for identifier in self.outputs:
            identifier.health_interval = int(value)

    @property
    def divergence_ratio(self) -> float:
        return self.outputs[0].divergence_ratio

    @divergence_ratio.setter
    def divergence_ratio(self, value: float) -> None:
        for identifier in self.outputs:
            identifier.divergence_ratio = float(value)

    @property
    def resume_after(self) -> int:
        return self.outputs[0].resume_after

    @resume_after.setter
    def resume_after(self, value: int) -> None:
        for identifier in self.outputs:
            identifier.resume_after = int(value)

    @property
    def free_run_guard(self) -> bool:
        return self.outputs[0].free_run_guard

    @free_run_guard.setter
    def free_run_guard(self, value: bool) -> None:
        for identifier in self.outputs:
            identifier.free_run_guard = bool(value)

    @property
    def hold_off(self) -> int:
        """The longest pause after a divergence among the outputs (each output pauses on its own)."""
        return max(identifier.hold_off for identifier in self.outputs)

    @property
    def resume_in(self) -> int:
        """Samples until every paused output learns again."""
        return max(identifier.resume_in for identifier in self.outputs if identifier.diverged) if self.diverged else 0

    @property
    def counters(self) -> dict[str, int]:
        shared = ("samples", "gaps", "lost", "duplicates", "rejected")
        totals = dict(self.outputs[0].counters)
        for identifier in self.outputs[1:]:
            for name, value in identifier.counters.items():
                if name not in shared:
                    totals[name] = totals.get(name, 0) + value
        return totals

    def mark_healthy(self) -> None:
        for identifier in self.outputs:
            identifier.mark_healthy()

    def step(self, index: int, u: np.ndarray, y: np.ndarray, learn: bool | None = None) -> MimoStepResult:
        """Process the vector pair (u(k), y_p(k)) with sample index k: every output's model steps."""
        y = np.asarray(y, dtype=np.float64)
        channels = np.concatenate((y, np.asarray(u, dtype=np.float64)))
        results: list[StepResult] = [
            identifier.step(index, channels[self.structure.picks(j)], float(y[j]), learn)
            for j, identifier in enumerate(self.outputs)
        ]
        events = tuple(result.event for result in results)
        event = "diverged" if "diverged" in events else next((e for e in events if e), "")  # (or "resumed")
        return MimoStepResult(
            index=index,
            y_hat_next=_stack([result.y_hat_next for result in results]),
            error=_stack([result.error for result in results]),
            y_hat=_stack([result.y_hat for result in results]),
            learned=any(result.learned for result in results),
            event=event,
            outputs=results,
        )

    def set_structure(self, structure: MimoStructure) -> None:
        """Take learnt scales and offsets (a session's warm-up) before the first sample: every output's channels."""
        for j, identifier in enumerate(self.outputs):
            identifier.set_structure(structure.channel(j))
        self.structure = structure

    def skip(self, index: int | None = None) -> None:
        for identifier in self.outputs:
            identifier.skip(index)

    def restart_stream(self) -> None:
        for identifier in self.outputs:
            identifier.restart_stream()

    def run(
        self,
        u: np.ndarray,
        y: np.ndarray,
        learn: np.ndarray | bool = True,
        changes: Sequence[tuple[int, Callable[[int], None]]] = (),
    ) -> np.ndarray:
        """Series-parallel pass over paired (N, n_u) / (N, n_y) series; returns y^ (N, n_y), nan where none.

        The outputs' identifiers share nothing, so they run side by side on the cores (a six-joint
        robot's 40 000 samples over 455 inputs: 2.0 s on one, 0.7 s on two), each exactly as alone.
        ``changes``: (position, apply) as :meth:`Identifier.run` takes them; ``apply(j)`` is called for
        output j's model at that position, since the outputs do not run in step.
        """
        u = np.asarray(u, dtype=np.float64).reshape(len(y), self.structure.n_u)
        y = np.asarray(y, dtype=np.float64).reshape(len(y), self.structure.n_y)
        workers = cores() if len(y) >= THREADED_RUN_SAMPLES else 1

        def output(j: int) -> np.ndarray:
            cuts = [(position, functools.partial(apply, j)) for position, apply in changes]
            return self.outputs[j].run(self.structure.other_values(j, u, y), y[:, j], learn, cuts)

        columns = list(side_by_side(output, range(len(self.outputs)), workers))
        return np.stack(columns, axis=1) if columns else np.empty((len(y), 0))

    def free_run(self, u: np.ndarray, y: np.ndarray, start: int, seeds_signed: bool = False) -> np.ndarray:
        """Parallel model from ``start`` on: every output fed the model's own outputs (frozen weights).

        Inputs outside [-1, 1] are clipped (counted per output in ``clipped_free_run``);
        an output further than the SISO bound from its offset ends the run there
        (``last_free_run['diverged_at']``), the rest is NaN. ``seeds_signed``: as the single output's (no
        output here is read as |y|, so its seeds are as they are).
        """
        structure = self.structure
        u = np.asarray(u, dtype=np.float64).reshape(-1, structure.n_u)
        y_model = np.array(y, dtype=np.float64, copy=True).reshape(len(u), structure.n_y)
        window = max(identifier.structure.warm_up for identifier in self.outputs)
        if start < window:
            raise ValueError(f"free run needs {window} samples of history before it starts")
        values = np.concatenate((y_model, u), axis=1)
        runs = [
            OutputRun(identifier.structure, identifier.model, j, tuple(int(c) for c in structure.picks(j)))
            for j, identifier in enumerate(self.outputs)
        ]
        clipped, diverged_at = free_run_outputs(runs, values, int(start))
        y_model = values[:, : structure.n_y]
        for identifier, count in zip(self.outputs, clipped, strict=True):
            identifier.counters["clipped_free_run"] += count
        self.last_free_run = {
            "samples": len(u) - start,
            "clipped_inputs": sum(clipped),
            "diverged": diverged_at is not None,
            "diverged_at": diverged_at,
        }
        return y_model[start:]

    def save_state(self, path: str | os.PathLike[str]) -> None:
        """Every output's model in one .npz (atomic, like ``OnlineRegressor.save``).

        One file, not one per output: in free run each output's model feeds the others,
        so the outputs are one model, and a restart must never pair output 0 of one save
        with output 1 of another.
        """
        from lenn_ros.core.networks import FORMAT_VERSION, write_weights_file

        arrays, outputs = {}, []
        for j, identifier in enumerate(self.outputs):
            model = identifier.model
            if not model.is_initialised:
                model._initialise()
            seen = int(getattr(model, "n_samples_seen_", 0))
            outputs.append(
                {"name": self.names[j], "kind": model._kind, "params": model.get_params(), "n_samples_seen": seen}
            )
            with identifier.serving():  # (free_run_guard: the kept state)
                arrays.update({f"y{j}_{name}": value for name, value in model.state().items()})
        header = {"format": FORMAT_VERSION, "kind": "mimo", "n_u": self.structure.n_u, "outputs": outputs}
        write_weights_file(path, header, arrays)

    def load_state(self, path: str | os.PathLike[str]) -> None:
        """Start every output from a file of :meth:`save_state`; all or nothing.

        Every output is checked (the file's output count, each network's configuration
        and array shapes) before any is installed, so a refused file leaves the running
        model whole instead of half replaced. Raises ModelFileError with the reason in one line.
        """
        from lenn_ros.core.networks import ModelFileError, read_weights_file

        header, arrays = read_weights_file(path)
        saved = header.get("outputs", []) if header.get("kind") == "mimo" else None
        if saved is None or len(saved) != len(self.outputs):
            found = "a single-output model" if saved is None else f"{len(saved)} output(s)"
            raise ModelFileError(
                f"{path}: weights of {found}, this model has {len(self.outputs)} outputs; "
                "configure the same channels or start without the file"
            )
        states = []
        for j, (model, entry) in enumerate(zip(self.models, saved, strict=True)):
            where = f"{path}: output {j} ({self.names[j]})"
            structural = {k: v for k, v in model.get_params().items() if k in model._structural_params}
            differing = sorted(k for k, v in structural.items() if entry.get("params", {}).get(k) != v)
            if entry.get("kind") != model._kind or differing:
                raise ModelFileError(
                    f"{where}: weights are for a different network ({entry.get('kind')}, differs in "
                    f"{', '.join(differing) or 'kind'}); configure the same network or start without the file"
                )
            fresh = type(model)(**model.get_params())
            fresh._initialise()
            state = {name: arrays.get(f"y{j}_{name}") for name in model._state_names}
            wrong = [
                name for name, value in state.items() if value is None or value.shape != getattr(fresh, name).shape
            ]
            if wrong:
                raise ModelFileError(
                    f"{where}: array {wrong[0]!r} missing or of shape "
                    f"{getattr(state[wrong[0]], 'shape', None)}, the network needs {getattr(fresh, wrong[0]).shape}"
                )
            states.append(state)
        for model, entry, state in zip(self.models, saved, states, strict=True):
            model._install(state, entry, path)
        self.mark_healthy()


def build_mimo_identifier(
    structure: MimoStructure,
    make_model,
    names: Sequence[str] = (),
) -> MimoIdentifier:
    """A MIMO identifier whose output j's network is ``make_model(n_inputs, j)`` (a fresh OnlineRegressor)."""
    outputs = []
    for j in range(structure.n_y):
        channel = structure.channel(j)
        outputs.append(Identifier(channel, make_model(channel.n_inputs, j)))
    return MimoIdentifier(structure, outputs, tuple(names))
