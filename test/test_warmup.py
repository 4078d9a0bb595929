"""Defaults for a robot, without DDS: scales learnt by the session's warm-up, live and offline alike."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lenn_ros.config import NODE_PARAMETERS, ConfigError, resolve, rls_forgetting
from lenn_ros.core.pairing import U, Y
from lenn_ros.paper.physical import FrictionJoint
from lenn_ros.paper.signals import Excitation
from lenn_ros.service.building import build_identifier, unlearnt_mimo_scales
from lenn_ros.session import Session, SessionConfig
from lenn_ros.session import learner as learner_module

PERIOD = 0.01


def joint(seconds: float, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A pendulum joint in radians under torque steps of +-2 N m (commands at 50 Hz), sampled at 100 Hz."""
    excitation = Excitation(seed, "steps")
    commands = 2.0 * np.array([excitation.sample(k)[0] for k in range(int(seconds * 50) + 1)])
    u = np.repeat(commands, 2)[: int(seconds / PERIOD)]
    y = FrictionJoint(period=PERIOD).run(u)[:-1] + np.random.default_rng(seed).normal(0.0, 2e-4, len(u))
    return u, y


def defaults_session(**given: float) -> Session:
    """What the node builds from the robot command: types, fields, pairing and period, nothing else."""
    node = {parameter.name: parameter.default for parameter in NODE_PARAMETERS} | {"sample_period": PERIOD}
    resolved, network = resolve(given)
    values = {**node, **given, **resolved}
    return Session(build_identifier(values, network), SessionConfig.from_values(values, pairing="sequence"))


def feed(live: Session, u: np.ndarray, y: np.ndarray, first: int = 0) -> list:
    samples = []
    for k in range(first, len(u)):
        for channel, value in ((U, u[k]), (Y, y[k])):
            samples += live.offer(channel, float(value), k * PERIOD, sequence=k + 1, source_time=k * PERIOD)
    return samples


def test_warm_up_holds_the_first_seconds_then_learns_every_sample_on_the_learnt_scales() -> None:
    u, y = joint(40.0)
    live = defaults_session()
    warming = {"state": "warming_up", "samples": 0, "needed": 1000, "restarts": 0, "discarded": 0}
    assert live.status()["scaling"] == warming
    held = feed(live, u[:999], y[:999])
    assert held == [] and live.queued()["warm_up"] == 999 and live.status()["counters"]["learned"] == 0
    released = feed(live, u[:1000], y[:1000], first=999)
    assert [sample.index for sample in released] == list(range(1, 1001))  # none lost: all learnt now
    notices = [notice.text for notice in live.take_notices() if notice.kind == "scales"]
    assert len(notices) == 1 and notices[0].startswith("scales learnt from the first 1000 samples: u: u_offset")
    scaling = live.status()["scaling"]
    low, high = float(u[:1000].min()), float(u[:1000].max())
    assert scaling["state"] == "learnt" and scaling["u_offset"] == pytest.approx((low + high) / 2)
    assert scaling["u_scale"] == pytest.approx(high - low)  # half-range x (1 + margin 1)
    structure = live.identifier.structure
    assert (structure.y_scale, structure.y_offset) == (scaling["y_scale"], scaling["y_offset"])
    feed(live, u, y, first=1000)
    assert live.status()["counters"]["clipped_inputs"] == 0
    assert live.status()["phase_nmse_db"] < -30.0  # measured -47 dB (training phase, 40 s)


def test_offline_run_reaches_the_same_scales_and_predictions() -> None:
    u, y = joint(20.0)
    u[100] = math.nan  # a refused sample in the warm-up is held, not counted
    live = defaults_session()
    samples = feed(live, u, y)
    live_hat = np.array([s.result.y_hat if s.result and s.result.y_hat is not None else np.nan for s in samples])
    offline = defaults_session()
    offline_hat = offline.run_samples(np.arange(1, len(u) + 1), u, y, np.ones(len(u), dtype=bool))
    assert live.status()["scaling"] == offline.status()["scaling"] and live.status()["scaling"]["samples"] == 1000
    np.testing.assert_array_equal(live_hat, offline_hat)


def test_a_plant_at_rest_is_not_taken_for_its_range(monkeypatch: pytest.MonkeyPatch) -> None:
    """Signals that do not move give no range: held up to MAX_WARM_UP, discarded (counted, said), started over."""
    monkeypatch.setattr(learner_module, "MAX_WARM_UP", 800)
    u, y = joint(30.0)
    u[:1000], y[:1000] = 0.0, 0.0  # the robot stands still for its first 10 s
    live, offline = defaults_session(scale_warm_up=5.0), defaults_session(scale_warm_up=5.0)  # 500 samples
    samples = feed(live, u, y)
    assert live.status()["counters"]["warm_up_discarded"] == 800 and live.status()["scaling"]["restarts"] == 1
    assert samples[0].index == 801 and live.status()["scaling"]["samples"] == 500  # 200 at rest, 300 moving
    assert any(notice.kind == "warm_up_discarded" for notice in live.take_notices())
    y_hat = offline.run_samples(np.arange(1, len(u) + 1), u, y, np.ones(len(u), dtype=bool))
    assert offline.status()["scaling"] == live.status()["scaling"] and np.isnan(y_hat[:800]).all()
    assert np.isfinite(y_hat[802:]).all()


def test_given_scales_skip_the_warm_up() -> None:
    u, y = joint(3.0)
    live = defaults_session(y_scale=2.0, u_scale=2.0)
    assert live.status()["scaling"] == {"state": "given"}
    assert len(feed(live, u[:10], y[:10])) == 10
    assert resolve({"example": 1})[0]["y_scale"] > 0  # a paper preset gives its own


def test_a_sensor_read_as_its_absolute_value_learns_a_range_about_zero() -> None:
    """``y_abs`` with the scales to learn: the model reads the signed output, which spans -max|y|..max|y|; a range
    centred on |y|'s own middle would clip every negative value."""
    from lenn_ros.core.structure import ModelStructure
    from lenn_ros.core.warmup import ScaleWarmUp

    warm = ScaleWarmUp.for_structure(ModelStructure(y_lags=2, u_lags=2, y_scale=0.0, u_scale=0.0, y_abs=True), 50)
    rng = np.random.default_rng(0)
    for _ in range(50):
        warm.add(float(rng.uniform(-1.0, 1.0)), float(rng.uniform(0.5, 3.0)))
    learnt = warm.structure(ModelStructure(y_lags=2, u_lags=2, y_scale=0.0, u_scale=0.0, y_abs=True))
    assert learnt.y_offset == 0.0 and learnt.y_scale == pytest.approx(warm.result["y"]["high"] * (1.0 + warm.margin))
    assert learnt.u_offset != 0.0  # the input's range is its own


def test_rls_forgetting_is_a_memory_of_minutes() -> None:
    values, _ = resolve({})
    assert values["solver"] == "rls" and values["forgetting"] == 0.0
    assert 1.0 / (1.0 - rls_forgetting({**values, "sample_period": 0.01})) == pytest.approx(12_000)
    assert 1.0 / (1.0 - rls_forgetting({**values, "sample_period": 0.0})) == pytest.approx(12_000)
    assert rls_forgetting({"forgetting": 0.999}) == 0.999
    with pytest.raises(ConfigError, match="forgetting must be 0"):
        resolve({"forgetting": 0.3})
    assert resolve({"example": 1})[0]["forgetting"] == 1.0  # the paper's examples as the paper has them


def test_weights_need_the_scaling_they_were_learnt_with(tmp_path) -> None:
    """A weights file saved without its scales cannot be started from with scales to learn; a missing file
    is not taken for one without scales (the load says it is missing, in its own line)."""
    values, network = resolve({})
    saved = tmp_path / "model.npz"
    given, _ = resolve({"y_scale": 2.0, "u_scale": 1.0})
    build_identifier(given, network).model.save(saved)  # (no scaling= : an older save)
    with pytest.raises(ConfigError, match="weights_in with y_scale/u_scale 0"):
        build_identifier({**values, "weights_in": str(saved)}, network)
    build_identifier({**values, "weights_in": str(tmp_path / "missing.npz")}, network)


def mimo_values(**given) -> dict:
    node = {parameter.name: parameter.default for parameter in NODE_PARAMETERS}
    mimo = {"u_field": "data[*]", "y_field": "data[*]", "u_names": ["u1", "u2"], "y_names": ["y1", "y2"], **given}
    return {**node, **mimo, **resolve(mimo)[0]}


def test_several_channels_learn_their_scales_channel_by_channel() -> None:
    """A MIMO model without scales: each channel's range from the warm-up, stepped and batched alike.

    The plant in raw units (outputs x 40 and x 0.05, inputs x 3): with the placeholder
    scale 1 of old, most network inputs were clipped.
    """
    from lenn_ros.paper.evaluation import simulate_mimo
    from lenn_ros.paper.plants import narendra_mimo_plant

    series = simulate_mimo(narendra_mimo_plant(), -30.0, seed=2, train_samples=3000, test_samples=0)
    u = series.u * 3.0
    y = series.y * np.array([40.0, 0.05])
    n = len(u)
    config = SessionConfig(pairing="sequence", sample_period=0.01, scale_warm_up=5.0)
    stepped = Session(build_identifier(mimo_values(), "lenn"), config)
    assert stepped.status()["scaling"]["state"] == "warming_up"
    outputs = []
    for k in range(n):
        stepped.offer(U, u[k], k * 0.01, sequence=k + 1)
        outputs += stepped.offer(Y, y[k], k * 0.01, sequence=k + 1)
    scaling = stepped.status()["scaling"]
    assert scaling["state"] == "learnt" and scaling["samples"] == 500
    for name, values in (("y", y[:500]), ("u", u[:500])):
        low, high = values.min(axis=0), values.max(axis=0)
        np.testing.assert_allclose(scaling[f"{name}_offsets"], (high + low) / 2, rtol=1e-12)
        np.testing.assert_allclose(scaling[f"{name}_scales"], (high - low) / 2 * 2.0, rtol=1e-12)  # margin 1
    assert len(outputs) == n  # every sample held by the warm-up was learnt afterwards
    clipped = stepped.identifier.counters["clipped"]
    assert clipped < 0.01 * n * 4  # inputs about within the learnt ranges (placeholder 1: most were clipped)
    batched = Session(build_identifier(mimo_values(), "lenn"), config)
    y_hat = batched.run_samples(np.arange(1, n + 1), u, y, np.ones(n, dtype=bool))
    live = np.array([s.result.y_hat if s.result is not None and s.result.y_hat is not None else [np.nan] * 2
                     for s in outputs])  # fmt: skip
    np.testing.assert_array_equal(y_hat, live)
    assert batched.status()["scaling"] == scaling


def test_several_channels_with_weights_need_their_scales() -> None:
    """weights_in with MIMO scales unset: refused with the fix (weights mean something on one scaling only)."""
    values = mimo_values(weights_in="model.npz")
    assert unlearnt_mimo_scales(values).startswith("weights_in with several channels and u_scales and y_scales")
    assert unlearnt_mimo_scales({**values, "y_scales": [2.0, 1.6]}).endswith("give u_scales (one per channel; "
                                                                             "lenn-ros fit writes them)")  # fmt: skip
    assert unlearnt_mimo_scales({**values, "u_scale": 1.0, "y_scales": [2.0, 1.6]}) is None
    assert unlearnt_mimo_scales(mimo_values()) is None  # no weights: the warm-up learns them
    with pytest.raises(ConfigError, match="weights_in with several channels"):
        build_identifier(values, "lenn")


def test_leaving_the_learnt_range_is_clipped_counted_and_said() -> None:
    """Not re-scaled (the weights mean something on one scaling only): clipped, counted, said with the cause."""
    u, y = joint(20.0)
    u[:1000] *= 0.2  # the warm-up sees a tenth of the later torque range
    live = defaults_session()
    feed(live, u, y)
    clipped = live.status()["counters"]["clipped_inputs"]
    said = [notice.text for notice in live.take_notices() if notice.kind == "clipped_inputs"]
    assert clipped > 100 and said and "learnt from the first 1000 samples" in said[0]
    assert live.status()["scaling"]["u_scale"] == live.identifier.structure.u_scale  # kept
