"""The free-run guard (``free_run_guard``): live learning keeps a model that simulates, and follows a plant that
changed. Real identifiers on the paper's plants; the batch run and the step judge alike."""

from __future__ import annotations

import numpy as np
import pytest

from lenn_ros.core.free_run_guard import WINDOW_BLOCKS, RecentSamples
from lenn_ros.core.metrics import nmse_db
from lenn_ros.core.structure import Identifier
from lenn_ros.paper.evaluation import simulate
from lenn_ros.paper.examples import EXAMPLES

BLOCK = 200  # health_interval: a window of WINDOW_BLOCKS blocks is 2 000 samples


def _identifier(number: int, guard: bool) -> Identifier:
    example = EXAMPLES[number]
    return Identifier(example.structure, example.make_network("lenn", 0), health_interval=BLOCK, free_run_guard=guard)


def _free_run_db(identifier: Identifier, u: np.ndarray, y: np.ndarray, start: int) -> float:
    return nmse_db(y[start:], identifier.free_run(u, y, start))


def test_recent_samples_keep_the_last_window_and_where_each_history_started() -> None:
    pushed, extended = RecentSamples(), RecentSamples()
    for recent in (pushed, extended):
        recent.restart(100)
    rng = np.random.default_rng(0)
    u, y = rng.standard_normal(250), rng.standard_normal(250)
    for k in range(250):
        if k == 180:
            pushed.restart(100)
        pushed.push(u[k], y[k])
    extended.extend(u[:180], y[:180])
    extended.restart(100)
    extended.extend(u[180:], y[180:])
    for recent in (pushed, extended):
        assert recent.full
        (u1, y1), (u2, y2) = recent.segments()  # a restart splits the window; nothing before it is lost
        assert np.array_equal(y1, y[150:180]) and np.array_equal(y2, y[180:])
        assert np.array_equal(u1[:, 0], u[150:180]) and np.array_equal(u2[:, 0], u[180:])
    assert not RecentSamples().full


@pytest.mark.parametrize("number", [1, 3])
def test_step_and_batch_judge_alike(number: int) -> None:
    """The node's step and evaluate's batch run adopt the same learning models at the same samples: a gap, and
    a frozen stretch in the middle (where learning stops, the network takes the kept state)."""
    example = EXAMPLES[number]
    series = simulate(example.plant(), None, 4, 19000, 500)
    rng = np.random.default_rng(1)
    y = series.y + 0.3 * np.std(series.y) * rng.standard_normal(len(series.y))  # (noise: not every check adopts)
    learn = (np.arange(19500) < 19000) & ~((np.arange(19500) >= 5000) & (np.arange(19500) < 5300))
    batch = _identifier(number, True)
    y_batch = np.concatenate([batch.run(series.u[:3000], y[:3000], learn[:3000]),
                              batch.run(series.u[3001:], y[3001:], learn[3001:])])  # fmt: skip
    online = _identifier(number, True)
    y_online = []
    for k in [*range(3000), *range(3001, 19500)]:  # sample 3001 lost
        y_online.append(online.step(k + 1, series.u[k], y[k], bool(learn[k])).y_hat)
    y_online = np.array([np.nan if v is None else v for v in y_online])
    assert np.array_equal(y_batch, y_online, equal_nan=True)
    indexing = ("gaps", "lost")  # (a batch run is handed runs without gaps: the session counts them)
    assert {k: v for k, v in batch.counters.items() if k not in indexing} == {
        k: v for k, v in online.counters.items() if k not in indexing
    }
    assert np.array_equal(batch.model.weights_, online.model.weights_)
    checks, adopted = online.counters["guard_checks"], online.counters["guard_adopted"]
    assert 0 < adopted < checks, online.counters


@pytest.mark.parametrize(("number", "plain_loss_db"), [(1, 5.0), (3, 1.5)])
def test_learning_on_noisy_outputs_keeps_the_free_run(number: int, plain_loss_db: float) -> None:
    """A model learnt on clean data learns on from outputs measured with noise (30 % of their spread): one-step
    learning drifts where the noise pulls it, and without the guard the free run gets worse (measured: example 1
    -32.3 -> -22.3 dB, example 3 -23.0 -> -20.2 dB); with it the free run is the one it had."""
    example = EXAMPLES[number]
    clean = simulate(example.plant(), None, 1, 20000, 0)
    noisy = simulate(example.plant(), None, 2, 20000, 0)
    y_measured = noisy.y + 0.3 * np.std(noisy.y) * np.random.default_rng(0).standard_normal(len(noisy.y))
    test = simulate(example.plant(), None, 3, 2000, 1000)
    figures = {}
    for guard in (False, True):
        identifier = _identifier(number, guard)
        identifier.run(clean.u, clean.y, np.arange(20000) < 19999)  # (the last sample: learning stops)
        before = _free_run_db(identifier, test.u, test.y, 2000)
        identifier.run(noisy.u, y_measured, np.arange(20000) < 19999)
        figures[guard] = (before, _free_run_db(identifier, test.u, test.y, 2000))
    assert figures[False][1] > figures[False][0] + plain_loss_db, figures
    assert figures[True][1] <= figures[True][0] + 0.5, figures


def test_a_plant_that_changed_is_followed() -> None:
    """After the plant's input gain changes (x1.3), the learning model simulates the new plant better on every
    piece of the window once the window holds only the new plant, and is adopted: the guarded model ends as
    good as unguarded learning, far better than the model of the old plant."""
    example = EXAMPLES[1]
    before = simulate(example.plant(), None, 1, 20000, 0)
    after = simulate(example.plant(), None, 2, 20000, 0)
    y_after = example.plant().run(1.3 * after.u)[:-1]
    test = simulate(example.plant(), None, 3, 2000, 1000)
    y_test = example.plant().run(1.3 * test.u)[:-1]
    figures = {}
    for guard in (False, True):
        identifier = _identifier(1, guard)
        identifier.run(before.u, before.y, np.arange(20000) < 19999)
        old = _free_run_db(identifier, test.u, y_test, 2000)
        identifier.run(after.u, y_after, np.arange(20000) < 19999)
        figures[guard] = (old, _free_run_db(identifier, test.u, y_test, 2000))
    assert figures[True][1] < figures[True][0] - 10.0, figures  # the new plant learnt
    assert abs(figures[True][1] - figures[False][1]) < 1.0, figures
    assert WINDOW_BLOCKS * BLOCK < 20000  # (the window can fill with the new plant)


def test_saved_weights_are_the_kept_model(tmp_path) -> None:
    """While the learning model differs from the kept one, a weights file (weights_out, autosave) holds the kept
    one: a restart starts from what simulates, and the network learns on undisturbed."""
    example = EXAMPLES[1]
    clean = simulate(example.plant(), None, 1, 6000, 0)
    identifier = _identifier(1, True)
    identifier.run(clean.u, clean.y, True)  # learning goes on: the learning model is not the kept one
    learning = identifier.model.weights_.copy()
    kept = identifier._guard.kept["weights_"]
    assert not np.array_equal(learning, kept)
    identifier.save_state(tmp_path / "w.npz")
    assert np.array_equal(identifier.model.weights_, learning)
    restarted = _identifier(1, True)
    restarted.load_state(tmp_path / "w.npz")
    assert np.array_equal(restarted.model.weights_, kept)
