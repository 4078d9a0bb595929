"""Defaults for a robot (issue 18 item 6), offline: test one-step NMSE on a friction joint.

    python bench/robot_defaults.py                  # 100 Hz
    python bench/robot_defaults.py --period 0.005   # 200 Hz

A pendulum joint in radians (``paper.physical.FrictionJoint``) under torque steps of
+-2 N m (commands at 50 Hz, levels held 0.2-1.2 s), measured with 0.2 mrad noise, fed
through the Session the node runs (sequence pairing here: the model and the warm-up
are what is measured, not the transport). 120 s of learning, then 30 s frozen (the test
phase). Configurations: the old default (the paper's example-1 preset), the new
defaults (nothing but the sample period), the new defaults with scales set by hand.
Then a slow change: the joint's load m g l 4 -> 5 N m at 120 s of 330, tested over
the last 30 s: forgetting 1.0 against the default (a memory of 120 s), and scales 1.0
(no warm-up) for comparison.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from lenn_ros.config import NODE_PARAMETERS, resolve
from lenn_ros.paper.physical import FrictionJoint
from lenn_ros.paper.signals import Excitation
from lenn_ros.service.building import build_identifier
from lenn_ros.session import Session, SessionConfig


def joint(period: float, seconds: float, seed: int = 1, change_at: float | None = None) -> tuple[np.ndarray, ...]:
    """(u, y): torque steps and the joint's angle; ``change_at``: seconds after which the load is 5 N m."""
    excitation = Excitation(seed, "steps")
    commands = 2.0 * np.array([excitation.sample(k)[0] for k in range(int(seconds * 50) + 1)])
    u = np.repeat(commands, round(1 / (50 * period)))[: int(seconds / period)]
    split = len(u) if change_at is None else int(change_at / period)
    first = FrictionJoint(period=period)
    y = first.run(u[:split])[:-1]
    if split < len(u):
        second = FrictionJoint(period=period, gravity=5.0)
        second.state = first.state.copy()
        y = np.r_[y, second.run(u[split:])[:-1]]
    return u, y + np.random.default_rng(seed).normal(0.0, 2e-4, len(u))


def test_nmse(values: dict[str, Any], u: np.ndarray, y: np.ndarray, period: float, test_s: float) -> dict[str, Any]:
    """The frozen last ``test_s`` seconds' one-step NMSE, the clipped inputs and the scaling."""
    node = {parameter.name: parameter.default for parameter in NODE_PARAMETERS} | {"sample_period": period}
    resolved, network = resolve(values)
    merged = {**node, **values, **resolved}
    session = Session(build_identifier(merged, network), SessionConfig.from_values(merged, pairing="sequence"))
    session.set_test_start(len(u) - int(test_s / period) + 1)
    for k in range(len(u)):
        session.offer("u", float(u[k]), k * period, sequence=k + 1)
        session.offer("y", float(y[k]), k * period, sequence=k + 1)
    status = session.status()
    return {"nmse_db": status["phase_nmse_db"], "clipped": status["counters"]["clipped_inputs"], **status["scaling"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--period", type=float, default=0.01, help="sample period, s")
    period = parser.parse_args().period
    u, y = joint(period, 150.0)
    for name, values in (
        ("old default: example 1 preset", {"example": 1}),
        ("new defaults", {}),
        ("new defaults, scales by hand", {"y_scale": 2.0, "u_scale": 2.0}),
    ):
        print(f"{name}: {test_nmse(values, u, y, period, 30.0)}")
    u, y = joint(period, 330.0, change_at=120.0)
    for name, values in (
        ("load change, forgetting 1.0", {"forgetting": 1.0}),
        ("load change, default forgetting (120 s)", {}),
        ("load change, scales 1.0 (no warm-up)", {"y_scale": 1.0, "u_scale": 1.0}),
    ):
        result = test_nmse(values, u, y, period, 30.0)
        print(f"{name}: {result['nmse_db']:.1f} dB, {result['clipped']} inputs clipped")


if __name__ == "__main__":
    main()
