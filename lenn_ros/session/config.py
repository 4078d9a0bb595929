"""How halves become samples and samples become learning: the session's configuration and its live changes."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from lenn_ros.core.change import DEFAULT_THRESHOLD

PAIRING_MODES = ("sequence", "stamp", "sample")
#: Live parameters that go to every network of the identifier (``set_params``), where it has them.
MODEL_PARAMETERS = ("alpha", "beta", "forgetting", "nlms_step")
#: Live parameters of the identifier's divergence guard.
GUARD_PARAMETERS = ("divergence_ratio", "resume_after", "free_run_guard")


@dataclass
class SessionConfig:
    """How halves become samples and samples become learning; see :mod:`lenn_ros.session`."""

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
    change_alarm: bool = True  # watch the one-step errors for a plant change (core.change; every output)
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

    @property
    def max_delay_s(self) -> float:
        """How long (receive time) a half waits for its partner: ``max_delay``, else two periods (>= 50 ms)."""
        return self.max_delay or (max(2 * self.sample_period, 0.05) if self.sample_period else 0.5)


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


def json_safe(value: Any) -> Any:
    """NaN and infinities become None (JSON has no NaN: strict parsers reject it)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(item) for item in value]
    return value
