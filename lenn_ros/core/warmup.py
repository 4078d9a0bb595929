"""Scales and offsets learnt from the first data, for a user who gave none (a robot's raw units).

The LeNN's Legendre inputs must lie in [-1, 1]; a pendulum joint in radians driven by
+-2 N m does not, and a user connecting a robot does not know its range beforehand.
When ``y_scale`` / ``u_scale`` are left at 0 the session holds the first paired
samples (a *scale warm-up*), takes each unscaled signal's centre and half-range
from them, widens the half-range by ``margin`` (as ``lenn-ros fit`` does,
:class:`~lenn_ros.core.scaling.Scaling`), sets the structure, and only then steps the
identifier through the held samples: none is lost, every one is learnt on the scaling
the model keeps.

The decision depends on the paired samples alone (their count and values, never a
clock), so ``lenn-ros evaluate`` re-running a recording through the same Session
reaches the same scales at the same sample.

Why the scale is not widened later, when a signal leaves the learnt range: a weight
learnt on one scaling means something else on another, so re-scaling would corrupt
what the network has learnt. Inputs beyond the range are clipped, counted
(``clipped_inputs``) and said, as with scales given by hand; the margin (the range seen
may be exceeded by its own half-width on either side) makes that rare.

Ten seconds by default: on a simulated pendulum joint under random torque steps (levels held
0.2-1.2 s), 5 s missed the swing's range in 1 run of 8 (-28 dB, 1 550 inputs clipped); 10 s
in none of 24 (-46.6 to -55.9 dB test one-step NMSE; a margin of 1.5 instead of 1 cost 1-3 dB).

The warm-up ends at the first sample by which ``samples`` valid pairs were held *and*
every learnt signal has moved (a range above zero): a robot standing still at start
shows nothing of its range. Held pairs are bounded: beyond ``MAX_WARM_UP`` of them the
warm-up starts over from the next pair (the held ones, a plant at rest, are discarded and
counted).

Several channels (a MIMO model) are the same warm-up with one range per channel: a side
(all ``u`` or all ``y`` channels) whose scales were left unset is learnt channel by
channel, and the warm-up ends once every channel of a learnt side has moved.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from lenn_ros.core.scaling import DEFAULT_MARGIN

#: Pairs held at most while waiting for the signals to move (then they are discarded and it starts over).
MAX_WARM_UP = 20_000
#: Fewest samples a warm-up takes, whatever its duration says (a range from a handful is noise).
MIN_WARM_UP = 20
#: Samples per second assumed where no sample_period says how long a sample is (sequence/stamp
#: pairing): 10 s are 500 samples, within the 1 000 steps a lockstep plant_simulator runs ahead
#: of the identifier's y_hat (more would stall it until the warm-up's outputs came).
ASSUMED_RATE_HZ = 50.0


def warm_up_samples(seconds: float, sample_period: float) -> int:
    """How many samples a warm-up of ``seconds`` holds: by ``sample_period``, else at ASSUMED_RATE_HZ."""
    rate = 1.0 / sample_period if sample_period > 0 else ASSUMED_RATE_HZ
    return int(min(max(math.ceil(seconds * rate), MIN_WARM_UP), MAX_WARM_UP // 2))  # (room for refused pairs)


@dataclass
class _Range:
    """Running extent and moments of one signal over the held samples."""

    low: float = math.inf
    high: float = -math.inf
    total: float = 0.0
    squares: float = 0.0

    def add(self, value: float) -> None:
        self.low = min(self.low, value)
        self.high = max(self.high, value)
        self.total += value
        self.squares += value * value

    @property
    def moved(self) -> bool:
        return self.high > self.low


@dataclass
class ScaleWarmUp:
    """Decides, pair by pair, when the held samples give the scales; see the module docstring.

    ``learn_y`` / ``learn_u``: which signals' scale (and offset) are learnt; a given
    (non-zero) offset of a learnt signal is kept and the half-range taken about it.
    ``y_offset`` / ``u_offset`` as tuples (one per channel): a MIMO model's warm-up, whose
    pairs carry vectors and whose result gives tuples.
    """

    samples: int
    learn_y: bool = True
    learn_u: bool = True
    y_offset: float | tuple[float, ...] = 0.0
    u_offset: float | tuple[float, ...] = 0.0
    margin: float = DEFAULT_MARGIN
    y_abs: bool = False  # y is read as |y| of a signed output (ModelStructure.y_abs): its range is +-max|y|
    valid: int = 0
    restarts: int = 0
    discarded: int = 0
    result: dict[str, Any] | None = None
    _ranges: dict[str, list[_Range]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vector = isinstance(self.y_offset, tuple)
        self._restart_ranges()

    def _offsets(self, name: str) -> tuple[float, ...]:
        given = self.y_offset if name == "y" else self.u_offset
        return tuple(given) if isinstance(given, tuple) else (float(given),)

    def _restart_ranges(self) -> None:
        self._ranges = {name: [_Range() for _ in self._offsets(name)] for name in ("y", "u")}

    @classmethod
    def for_structure(cls, structure: Any, samples: int, margin: float = DEFAULT_MARGIN) -> ScaleWarmUp:
        """For a :class:`ModelStructure`, or a MIMO ``MimoStructure`` (scales and offsets per channel)."""
        if isinstance(structure.y_scale, tuple):
            return cls(
                samples,
                learn_y=not all(scale > 0 for scale in structure.y_scale),
                learn_u=not all(scale > 0 for scale in structure.u_scale),
                y_offset=tuple(structure.y_offset) or (0.0,) * structure.n_y,
                u_offset=tuple(structure.u_offset) or (0.0,) * structure.n_u,
                margin=margin,
            )
        return cls(
            samples,
            learn_y=structure.y_scale <= 0,
            learn_u=structure.u_scale <= 0,
            y_offset=structure.y_offset,
            u_offset=structure.u_offset,
            margin=margin,
            y_abs=structure.y_abs,
        )

    @property
    def done(self) -> bool:
        return self.result is not None

    def add(self, u: Any, y: Any) -> bool:
        """One paired sample (NaN: refused, held but not counted); True once the scales are known."""
        if self.vector:
            us, ys = [float(v) for v in u], [float(v) for v in y]
            if any(math.isnan(v) for v in us) or any(math.isnan(v) for v in ys):
                return False
        else:
            if math.isnan(u) or math.isnan(y):
                return False
            us, ys = [u], [y]
        self.valid += 1
        for extent, value in zip(self._ranges["u"], us, strict=True):
            extent.add(value)
        for extent, value in zip(self._ranges["y"], ys, strict=True):
            extent.add(value)
        learnt = [name for name, learn in (("y", self.learn_y), ("u", self.learn_u)) if learn]
        if self.valid >= self.samples and all(e.moved for name in learnt for e in self._ranges[name]):
            self.result = self._scales()
            return True
        return False

    def restart(self, held: int) -> None:
        """``held`` pairs are discarded unlearnt (the signals did not move in MAX_WARM_UP): start over."""
        self.restarts += 1
        self.discarded += held
        self.valid = 0
        self._restart_ranges()

    def _scales(self) -> dict[str, Any]:
        """Per side: one entry (a dict) per channel; a single channel's side is its one dict."""
        values: dict[str, Any] = {"samples": self.valid}
        for name, learn in (("y", self.learn_y), ("u", self.learn_u)):
            entries = []
            for extent, given in zip(self._ranges[name], self._offsets(name), strict=True):
                mean = extent.total / self.valid
                spread = math.sqrt(max(extent.squares / self.valid - mean * mean, 0.0))
                entry = {"low": extent.low, "high": extent.high, "mean": mean, "std": spread, "learnt": learn}
                if learn:
                    centre = 0.0 if name == "y" and self.y_abs else (extent.high + extent.low) / 2.0
                    offset = given if given else centre
                    half = max(extent.high - offset, offset - extent.low)
                    entry.update(offset=offset, scale=half * (1.0 + self.margin))
                entries.append(entry)
            values[name] = entries if self.vector else entries[0]
        return values

    def _entries(self, name: str) -> list[dict[str, Any]]:
        assert self.result is not None
        found = self.result[name]
        return found if self.vector else [found]

    def structure(self, structure: Any) -> Any:
        """``structure`` with the learnt scales and offsets (the given ones kept); tuples for a MIMO one."""
        changes = {}
        for name in ("y", "u"):
            entries = self._entries(name)
            if entries[0]["learnt"]:
                offsets = [entry["offset"] for entry in entries]
                scales = [entry["scale"] for entry in entries]
                changes[f"{name}_offset"] = tuple(offsets) if self.vector else offsets[0]
                changes[f"{name}_scale"] = tuple(scales) if self.vector else scales[0]
        return replace(structure, **changes)

    def text(self, u_name: str, y_name: str) -> str:
        """The one line that says what was learnt."""
        assert self.result is not None
        parts = []
        for name, topic in (("u", u_name), ("y", y_name)):
            entries = self._entries(name)
            for channel, entry in enumerate(entries):
                if entry["learnt"]:
                    label = f"{topic}[{channel}]" if self.vector else topic
                    parts.append(
                        f"{label}: {name}_offset {entry['offset']:.6g}, {name}_scale {entry['scale']:.6g} (seen "
                        f"[{entry['low']:.6g}, {entry['high']:.6g}], mean {entry['mean']:.6g}, std {entry['std']:.3g})"
                    )
        return (
            f"scales learnt from the first {self.result['samples']} samples: {'; '.join(parts)}. Margin "
            f"{self.margin:g}: a signal may leave the range seen by {self.margin:g} x its half-width before its "
            "network inputs are clipped (counted clipped_inputs); set the scales to fix them"
        )

    def status(self) -> dict[str, Any]:
        """For the session's status: warming up (how far) or the learnt values (lists for several channels)."""
        state = {"samples": self.valid, "needed": self.samples, "restarts": self.restarts, "discarded": self.discarded}
        if self.result is None:
            return {"state": "warming_up", **state}
        learnt: dict[str, Any] = {}
        for name in ("u", "y"):
            entries = self._entries(name)
            if entries[0]["learnt"]:
                for what in ("offset", "scale"):
                    values = [entry[what] for entry in entries]
                    if self.vector:
                        learnt[f"{name}_{what}s"] = values
                    else:
                        learnt[f"{name}_{what}"] = values[0]
        return {"state": "learnt", **state, **learnt}
