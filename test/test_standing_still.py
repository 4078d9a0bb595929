"""Issue 18, item 1: a robot that stands still is normal, and a real divergence is not the end.

The README's robot settings (``solver:=rls``, ``output:=linear``, two lags each, scales
3.2) on paper example 1's plant (the robot simulator's), without ROS: the core alone
decides what is learnt.
"""

from __future__ import annotations

import numpy as np
import pytest

from lenn_ros.config import resolve
from lenn_ros.core import jit
from lenn_ros.core.pairing import U, Y
from lenn_ros.core.structure import Identifier
from lenn_ros.paper.evaluation import simulate
from lenn_ros.paper.examples import EXAMPLES, get_example
from lenn_ros.service.building import build_identifier
from lenn_ros.session import Session, SessionConfig

README_ROBOT = {
    "example": 0, "y_lags": 2, "u_lags": 2, "solver": "rls", "output": "linear", "y_scale": 3.2, "u_scale": 3.2,
}  # fmt: skip
QUANTUM = 1e-4  # the encoder's resolution


def robot_identifier(**changes) -> Identifier:
    values, network = resolve({**README_ROBOT, **changes})
    identifier = build_identifier(values, network)
    assert isinstance(identifier, Identifier)
    return identifier


def moving_resting_moving(rest: int, moving: int = 5000, command: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Uniform commands, then a constant one (the plant settles and the encoder reads a constant), then again."""
    rng = np.random.default_rng(0)
    u = np.concatenate([rng.uniform(-1, 1, moving), np.full(rest, command), rng.uniform(-1, 1, moving)])
    y = np.round(get_example(1).plant().run(u) / QUANTUM) * QUANTUM
    return u, y


def test_standing_still_keeps_learning() -> None:
    """5 000 samples moving, 5 000 at rest, 5 000 moving: every sample is learnt, nothing rolls back.

    On main (325f0e8) the first block at rest diverged (its target variance is 0) and
    learning stopped for good at 7 000 learnt samples of 15 000.
    """
    identifier = robot_identifier()
    u, y = moving_resting_moving(rest=5000)
    assert np.var(y[6000:10000]) == 0.0  # the quantised plant really stands still
    learned, errors = [], np.full(len(u), np.nan)
    for k in range(len(u)):
        result = identifier.step(k + 1, u[k], y[k])
        errors[k] = np.nan if result.error is None else result.error
        if k + 1 in (5000, 10000, 15000):
            learned.append(identifier.counters["learned"])
    assert identifier.counters["diverged"] == 0 and not identifier.diverged
    assert learned == [4998, 9998, 14998]  # all but the two warm-up samples
    before, after = np.mean(errors[1000:5000] ** 2), np.mean(errors[11000:15000] ** 2)
    assert after < 1.05 * before  # measured 0.0418 after, 0.0419 before: the rest did the model no harm
    moving = float(np.var(y[:5000]))
    assert 0.85 * moving < identifier.target_variance < 1.15 * moving  # measured 0.772 of 0.878: kept through the rest


@pytest.mark.parametrize("forgetting", [1.0, 0.9995])
def test_rls_covariance_stays_bounded_over_minutes_at_rest(forgetting: float) -> None:
    """200 Hz x 5 min at rest between two moving stretches: trace(P) measured every 1 000 samples.

    Without forgetting P cannot grow (it only shrinks with data). With forgetting it grows
    in every direction the constant regressor does not excite, until the trace bound:
    the prior's trace, 17 weights x 1000 (the old fixed bound let it reach 999 655, 59
    times that, and the first moving samples after the rest paid for it).
    """
    rest = 200 * 300
    identifier = robot_identifier(forgetting=forgetting)
    model = identifier.model
    bound = model.n_weights * model.initial_covariance
    assert model.trace_bound == bound == 17_000.0
    u, y = moving_resting_moving(rest=rest)
    traces, errors = [], np.full(len(u), np.nan)
    for k in range(len(u)):
        result = identifier.step(k + 1, u[k], y[k])
        errors[k] = np.nan if result.error is None else result.error
        if (k + 1) % 1000 == 0:
            traces.append(float(np.trace(model.covariance_)))
    at_rest = traces[5 : 5 + rest // 1000]
    assert identifier.counters["diverged"] == 0 and identifier.counters["learned"] == len(u) - 2
    if forgetting == 1.0:
        assert max(at_rest) <= traces[4]  # measured: 240.6 when the rest began, 239.0 through it
    else:
        assert max(at_rest) <= bound * (1 + 1e-12)
        assert max(at_rest) > 0.999 * bound  # measured 16 994.5: the bound is what holds it
    assert traces[-1] < 0.1 * bound  # moving again, P shrinks back (measured 745 / 128)
    before, after = np.mean(errors[1000:5000] ** 2), np.mean(errors[-4000:] ** 2)
    assert after < 1.05 * before


def paused_session(health_interval: int = 200, resume_after: int = 2) -> tuple[Session, Identifier]:
    example = EXAMPLES[1]
    model = example.make_network("lenn", 0, output="linear")  # a tanh output saturates instead of exploding
    identifier = Identifier(example.structure, model, health_interval=health_interval, resume_after=resume_after)
    return Session(identifier, SessionConfig(pairing="sequence")), identifier


def offer(session: Session, k: int, u: float, y: float) -> None:
    session.offer(U, u, k * 0.01, sequence=k)
    session.offer(Y, y, k * 0.01, sequence=k)


def test_a_real_divergence_pauses_then_resumes_by_itself_with_a_back_off() -> None:
    """alpha set absurdly high live: roll back, pause, resume, roll back again, pause twice as long.

    Then alpha is set back while paused: learning resumes from the healthy state and stays.
    Each step is said in one line, counted, and ``status`` never says learning while diverged.
    """
    example = EXAMPLES[1]
    series = simulate(example.plant(), example.noise_db, 0, 12_000, 0)
    session, identifier = paused_session()
    healthy_alpha = identifier.model.alpha
    statuses, texts = [], []

    def run(first: int, last: int) -> None:
        for k in range(first, last):
            offer(session, k + 1, series.u[k], series.y[k])
            status = session.status()
            statuses.append((status["learning"], status["diverged"], status["resume_in"]))
            texts.extend(n.text for n in session.take_notices() if n.kind in ("diverged", "resumed"))

    run(0, 2000)
    assert identifier.counters["diverged"] == 0 and identifier.target_variance > 0
    identifier.model.set_params(alpha=50.0, beta=0.9)
    run(2000, 3200)
    assert identifier.counters["diverged"] == 2 and identifier.counters["resumed"] == 1
    assert identifier.diverged and identifier.hold_off == 2 * 2 * 200  # the second pause: twice the first
    assert np.all(np.isfinite(identifier.model.weights_))
    identifier.model.set_params(alpha=healthy_alpha, beta=0.5)  # the user sets it back, while paused
    run(3200, 12_000)
    assert identifier.counters["diverged"] == 2 and identifier.counters["resumed"] == 2
    assert not identifier.diverged and statuses[-1] == (True, False, None)
    assert not any(learning and diverged for learning, diverged, _ in statuses)
    paused = [resume_in for _, diverged, resume_in in statuses if diverged]
    assert max(paused) == 2 * 2 * 200 and min(paused) == 0  # the samples still to pass, shown as they pass
    assert [text.split(":")[1].split()[0:3] for text in texts] == [
        ["the", "model", "diverged"], ["learning", "resumes", "from"],
        ["the", "model", "diverged"], ["learning", "resumes", "from"],
    ]  # fmt: skip
    assert "pausing learning for 400 samples" in texts[0] and "800 samples" in texts[2]
    learnt_after = identifier.counters["learned"]
    assert learnt_after > 11_000 - 2000  # it learnt again after the second pause


@pytest.mark.parametrize("compiled", [True, False])
def test_pauses_and_resumes_are_the_same_stepped_and_batched(monkeypatch, compiled: bool) -> None:
    """A rule that diverges on every update (alpha 1e308): pause, resume, diverge, ... in run() as in step()."""
    if compiled and not jit.JIT:
        pytest.skip("the compiled step exists only where numba compiles")
    from lenn_ros.core import structure

    if not compiled:
        monkeypatch.setattr(structure.StepPlan, "for_model", classmethod(lambda cls, model, shape: None))
    example = EXAMPLES[2]
    series = simulate(example.plant(), example.noise_db, 3, 3000, 200)
    learn = (np.arange(3200) < 3000) & ~((np.arange(3200) > 700) & (np.arange(3200) < 900))  # a frozen stretch

    def make() -> Identifier:
        model = example.make_network("lenn", 5, solver="sgd", alpha=1e308)
        return Identifier(example.structure, model, health_interval=50, resume_after=1)

    stepped, batched = make(), make()
    y_step = np.full(3200, np.nan)
    for k in range(3200):
        result = stepped.step(k + 1, series.u[k], series.y[k], bool(learn[k]))
        if result.y_hat is not None:
            y_step[k] = result.y_hat
    y_batch = batched.run(series.u, series.y, learn)
    assert stepped.counters["resumed"] >= 4  # 50, 100, 200, 400, 800 ... samples of pause
    assert stepped.counters == batched.counters
    assert (stepped.hold_off, stepped.resume_in) == (batched.hold_off, batched.resume_in)
    assert np.array_equal(y_step, y_batch, equal_nan=True)
    assert np.array_equal(stepped.model.weights_, batched.model.weights_)


def test_a_plant_at_rest_from_the_start_is_not_taken_for_a_diverged_one() -> None:
    """Switched on at rest: nothing moved yet, so the declared range stands in for the learnt variance."""
    identifier = robot_identifier()
    u, y = moving_resting_moving(rest=7000, moving=0)
    u, y = u[1000:], y[1000:]  # the plant has settled: its output is one constant
    assert np.ptp(y) == 0.0
    for k in range(len(u)):
        identifier.step(k + 1, u[k], y[k])
    assert identifier.counters["diverged"] == 0 and identifier.counters["learned"] == len(u) - 2
    assert identifier.target_variance == 0.0  # nothing moved: nothing learnt about its scale


@pytest.mark.parametrize("rest", [4_000, 40_000])
def test_standing_still_then_moving_is_not_a_plant_change(rest: int) -> None:  # (+300: the plant settles in 211)
    """The change alarm holds while the plant stands still: resuming motion is not a change.

    Without the rest gate the learnt residual level sank to the quantisation level at rest
    and the first seconds of motion afterwards raised "plant changed" (as in the robot day).
    Stepped and batched alike.
    """
    u, y = moving_resting_moving(rest=rest, moving=12_000)
    y = y[: len(u)]
    stepped = Session(robot_identifier(), SessionConfig(pairing="sequence"))
    for k in range(len(u)):
        offer(stepped, k, u[k], y[k])
    batched = Session(robot_identifier(), SessionConfig(pairing="sequence"))
    batched.run_samples(np.arange(1, len(u) + 1), u, y, np.ones(len(u), dtype=bool))
    for session in (stepped, batched):
        assert session.counters["change_alarms"] == 0, [n.text for n in session.take_notices() if n.kind == "change"]
        change = session.monitors.outputs[0].change
        assert change.gate.moving_samples < len(u) - rest + 300
