"""``lenn-ros evaluate BAG`` for a model with several channels: the same session, scored per output.

:func:`lenn_ros.evaluate.evaluate_bag` hands over here when the configuration names
several u or y_p channels, once the recorded u and y_p messages (vector messages, a
side's several topics, or an ``import-csv`` with several columns) are paired by the
session exactly as the node pairs them. The samples are learnt in one batched pass
(:meth:`~lenn_ros.core.session.Session.run_samples`) and scored per output channel:
one-step, and the free run of the joint model (every output fed the model's own
outputs) over the test part up to its first break.

A bag recorded with the identifier running holds its ``samples`` (each sample's index,
time, channels and learn flag, as the node formed them): those are learnt again, so
the figures equal the live ones by construction, whatever the recorder lost of the raw
u / y_p; other bags are paired from their raw u / y_p.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lenn_ros.core.evaluation import free_run_segments
from lenn_ros.core.metrics import nmse_db, rmse
from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.session import Session, describe_gaps, json_safe


@dataclass
class MimoBagEvaluation:
    """Per output channel: NMSE (dB) and RMSE one-step and in free run on the test part."""

    channels: dict[str, dict[str, float]]
    pairs: int
    test_start: int
    source: str
    samples: int  # test samples scored one-step
    missing: int = 0
    free_run: dict[str, Any] = field(default_factory=dict)
    counters: dict[str, int] = field(default_factory=dict)
    notices: list[str] = field(default_factory=list)
    y_test: np.ndarray | None = field(default=None, repr=False)  # (test samples, outputs), for the plot
    y_hat_test: np.ndarray | None = field(default=None, repr=False)
    y_free_test: np.ndarray | None = field(default=None, repr=False)
    gaps: list[str] = field(default_factory=list)  # the missing indices in words (session.describe_gaps)

    def as_dict(self) -> dict[str, Any]:
        return json_safe(
            {
                "channels": self.channels,
                "pairs": self.pairs,
                "test_start": self.test_start,
                "source": self.source,
                "samples": self.samples,
                "missing": self.missing,
                "gaps": self.gaps,
                "free_run": self.free_run,
                "counters": self.counters,
                "notices": self.notices,
            }
        )


def score_mimo(
    session: Session, index: np.ndarray, u: np.ndarray, y: np.ndarray, learn: np.ndarray, start: int, source: str
) -> MimoBagEvaluation:
    """Learn the samples flagged ``learn`` in one pass (as live), then score every output from ``start`` on."""
    identifier = session.identifier
    assert isinstance(identifier, MimoIdentifier)
    u = u.reshape(len(index), -1)
    y = y.reshape(len(index), -1)
    y_hat = session.run_samples(index, u, y, learn)
    test = index >= start
    first = int(np.argmax(test))
    y_free = np.full(y.shape, np.nan)  # restarted from the measured outputs after every break, as one channel's
    y_free[first:], free_run = free_run_segments(identifier, index, u, y, first)
    scored = test & np.isfinite(y_hat).all(axis=1)
    channels = {
        name: _channel_scores(y[:, j], y_hat[:, j], y_free[:, j], scored, test)
        for j, name in enumerate(identifier.names)
    }
    notices = sorted({f"{n.kind}: {n.text}" for n in session.take_notices() if n.kind != "phase"})
    missing = int(np.sum(np.clip(np.diff(index) - 1, 0, None))) + int(index[0] - 1)
    return MimoBagEvaluation(
        channels,
        len(index),
        int(start),
        source,
        int(scored.sum()),
        missing,
        free_run,
        session.all_counters(),
        notices,
        y[test],
        y_hat[test],
        y_free[test],
        describe_gaps(index, session.config.pairing, session.config.sample_period),
    )


def _channel_scores(
    y: np.ndarray, y_hat: np.ndarray, y_free: np.ndarray, scored: np.ndarray, test: np.ndarray
) -> dict[str, float]:
    simulated = test & np.isfinite(y_free)
    return {
        "nmse_db": nmse_db(y[scored], y_hat[scored]) if scored.any() else math.nan,
        "rmse": rmse(y[scored], y_hat[scored]) if scored.any() else math.nan,
        "nmse_free_run_db": nmse_db(y[simulated], y_free[simulated]) if simulated.any() else math.nan,
        "rmse_free_run": rmse(y[simulated], y_free[simulated]) if simulated.any() else math.nan,
    }


def report(args: Any, result: MimoBagEvaluation) -> int:
    """Print the per-channel table (or JSON); ``--plot`` writes one panel per output channel."""
    d = result.as_dict()
    if args.json:
        print(json.dumps(d, indent=1))
        return 0
    print(f"bag {args.bag}: {d['pairs']} samples from {d['source']}, test from sample {d['test_start']}")
    for line in d["gaps"]:
        print(f"  {line}")
    print(f"  scored {d['samples']} test samples per output channel")
    print("  channel        NMSE one-step   NMSE free run   RMSE one-step   RMSE free run")
    for name, scores in result.channels.items():
        cells = [scores[key] for key in ("nmse_db", "nmse_free_run_db", "rmse", "rmse_free_run")]
        shown = [f"{value:13.3f}" if math.isfinite(value) else f"{'nan':>13s}" for value in cells]
        print(f"  {name:12s} " + "   ".join(shown))
    if result.free_run.get("diverged"):
        print(f"  WARNING: the free run diverged at sample {result.free_run.get('diverged_at')}")
    if result.free_run.get("not_simulated"):
        print(f"  note: {result.free_run['not_simulated']} test samples after a break not simulated, not scored")
    if args.plot:
        from lenn_ros.plotting import plot_channels

        names = list(result.channels)
        shown = ", ".join(f"{name} {scores['nmse_db']:.2f}" for name, scores in result.channels.items())
        title = f"{args.bag}: one-step NMSE {shown} dB"
        print(f"  wrote {plot_channels(args.plot, names, result.y_test, result.y_hat_test, title, result.y_free_test)}")
    for notice in d["notices"]:
        print(f"  note: {notice}")
    return 0
