"""The "beyond the paper" claims, measured: RLS health, speed, tracking, cross terms.

Every test computes what it checks (no stored results), on seeds 0..2 and, where the
claim allows, on fewer training samples than the 50 000 of the full report, so the
file runs in well under a minute on two cores.
"""

from __future__ import annotations

import io
import json
from contextlib import redirect_stdout

import numpy as np
import pytest

from lenn_ros.core import learning_rules
from lenn_ros.core.expansions import expand
from lenn_ros.core.structure import Identifier
from lenn_ros.paper.evaluation import simulate, train_and_test
from lenn_ros.paper.examples import EXAMPLES
from lenn_ros.paper.experiments import candidates, convergence, tracking
from lenn_ros.paper.plants import example4_f
from lenn_ros.paper.signals import noise_std

CHUNK = 100_000


def _example4_features(x: np.ndarray, cross_degree: int) -> np.ndarray:
    """Ex. 4's network inputs [y(k), y(k-1), y(k-2), u(k), u(k-1)] expanded with cross terms."""
    return expand(x, EXAMPLES[4].lenn["order"], "legendre", cross_degree)


def _example4_data(n: int, seed: int, rest: slice | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Network inputs and targets of Ex. 4's plant driven as in training, for ``n`` samples.

    A plain loop over the plant equation (Plant.step is too slow for 10^6 samples);
    over ``rest`` the plant gets no input at all (u = 0, no noise): it settles at
    y = 0 within three samples and every network input is then exactly zero.
    """
    example = EXAMPLES[4]
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1.0, 1.0, n)
    applied = u + rng.normal(0.0, noise_std(example.noise_db), n)
    if rest is not None:
        u[rest] = applied[rest] = 0.0
    a, y = applied.tolist(), [0.0] * n
    y0 = y1 = y2 = u1 = 0.0
    for k in range(n - 1):
        y[k + 1] = example4_f(y0, y1, y2, a[k], u1)
        y0, y1, y2, u1 = y[k + 1], y0, y1, a[k]
    inputs, targets, _ = example.structure.training_pairs(u, np.array(y))
    return inputs, targets


def _assert_healthy(weights: np.ndarray, covariance: np.ndarray) -> None:
    assert np.all(np.isfinite(weights)) and np.all(np.isfinite(covariance))
    assert np.array_equal(covariance, covariance.T), "covariance lost its symmetry"
    np.linalg.cholesky(covariance)  # raises LinAlgError unless positive definite


def _rls(weights, covariance, x, targets, forgetting, max_trace, cross_degree) -> int:
    """Feed the compiled RLS rule in chunks (the features of 10^6 samples would need 400 MB)."""
    y = np.empty(CHUNK)
    done = 0
    for start in range(0, len(x), CHUNK):
        phi = _example4_features(x[start : start + CHUNK], cross_degree)
        n = learning_rules.functional_link_rls(
            weights,
            covariance,
            phi,
            targets[start : start + CHUNK],
            forgetting,
            max_trace,
            True,
            y[: len(phi)],
            np.empty(0),
        )
        done += n
        if n < len(phi):
            break
    return done


# -- (a) numerical health of RLS ------------------------------------------------------------
def test_rls_million_updates_on_example4_cross_terms_stays_least_squares():
    """10^6 updates on Ex. 4's plant, lambda = 1, 51 weights (cross terms up to degree 3).

    With lambda = 1 the covariance shrinks to ~1e-6 (condition number ~4e5 here) and
    round-off is what could break it. Beyond symmetric and positive definite, the
    weights and covariance must still be the batch least-squares solution of all 10^6
    samples (normal equations accumulated alongside, with the prior of P0 = 1000 I).
    """
    x, targets = _example4_data(1_000_000, 0)
    n = _example4_features(x[:1], 3).shape[1]
    assert n == 51
    weights, covariance = np.zeros(n), np.eye(n) * 1000.0
    gram, moment = np.eye(n) / 1000.0, np.zeros(n)
    y = np.empty(CHUNK)
    for start in range(0, len(x), CHUNK):
        phi, t = _example4_features(x[start : start + CHUNK], 3), targets[start : start + CHUNK]
        assert learning_rules.functional_link_rls(
            weights, covariance, phi, t, 1.0, 1.0e6, True, y[: len(phi)], np.empty(0)
        ) == len(phi)
        gram += phi.T @ phi
        moment += phi.T @ t
    _assert_healthy(weights, covariance)
    batch = np.linalg.solve(gram, moment)
    assert np.max(np.abs(weights - batch)) < 1e-8 * np.max(np.abs(batch))
    inverse = np.linalg.inv(gram)
    assert np.max(np.abs(covariance - inverse)) < 1e-8 * np.max(np.abs(inverse))


def test_rls_bounded_trace_stops_windup_during_zero_excitation():
    """lambda = 0.99 on Ex. 4's plant: 450k excited samples, 100k at rest (u = 0), 450k again.

    At rest the network inputs are all zero: one constant feature vector, so forgetting
    inflates P by 1/0.99 per sample in every other direction. The bounded trace must
    hold trace(P) <= max_trace through the stretch, leave P positive definite, and the
    model must learn again afterwards; the same stretch without the bound winds up
    (the control: it shows that the bound is what stops it).
    """
    cross, forgetting, max_trace = 2, 0.99, 1.0e6  # the old fixed default (the model's is now its prior's trace)
    x, targets = _example4_data(1_000_000, 1, rest=slice(450_000, 550_000))
    assert not np.any(x[450_010:549_990])  # rows are k - 2: all inputs zero once the plant settled
    n = _example4_features(x[:1], cross).shape[1]
    weights, covariance = np.zeros(n), np.eye(n) * 1000.0
    traces = []
    for start in range(0, len(x), 10_000):
        stop = start + 10_000
        assert _rls(weights, covariance, x[start:stop], targets[start:stop], forgetting, max_trace, cross) == len(
            x[start:stop]
        )
        traces.append(np.trace(covariance))
    assert max(traces) <= max_trace * (1 + 1e-9)
    assert max(traces[45:55]) > 1000 * max(traces[10:45])  # the rest did push P up to the bound
    _assert_healthy(weights, covariance)
    # learns again: on the last 10 000 samples, as good as a batch fit of the same features
    phi, t = _example4_features(x[-10_000:], cross), targets[-10_000:]
    batch = np.linalg.lstsq(phi, t, rcond=None)[0]
    assert np.mean((phi @ weights - t) ** 2) < 1.5 * np.mean((phi @ batch - t) ** 2)

    # control: the same rest without the bound winds up (or the rule refuses an update)
    weights, covariance = np.zeros(n), np.eye(n) * 1000.0
    assert _rls(weights, covariance, x[:50_000], targets[:50_000], forgetting, max_trace, cross) == 50_000
    done = _rls(weights, covariance, x[450_000:550_000], targets[450_000:550_000], forgetting, np.inf, cross)
    assert done < 100_000 or not np.isfinite(np.trace(covariance)) or np.trace(covariance) > 1e20


# -- (b) convergence speed --------------------------------------------------------------------
def test_learning_curve_ends_at_train_and_test_nmse():
    """The checkpointed training sees exactly the samples train_and_test learns from."""
    example = EXAMPLES[1]
    series = simulate(example.plant(), example.noise_db, 0, train_samples=3000)
    candidate = candidates.candidates(1)[0]
    evaluation = train_and_test(Identifier(example.structure, candidate.make(example, 0)), series)
    curve = convergence.learning_curve(
        example.structure, candidate.make(example, 0), series, convergence.checkpoints(3000)
    )
    assert convergence.checkpoints(3000) == [250, 500, 1000, 2000, 3000]
    assert curve[-1] == pytest.approx(evaluation.nmse_db, abs=1e-9)
    assert curve[0] > curve[-1]


def test_samples_to_within_counts_from_where_the_curve_stays():
    at = [250, 500, 1000, 2000, 4000]
    assert convergence.samples_to_within(at, [-10.0, -20.0, -20.5, -21.0, -20.8]) == 500
    assert convergence.samples_to_within(at, [-21.0, -10.0, -20.5, -21.0, -20.8]) == 1000  # early luck not credited
    assert convergence.samples_to_within(at, [-5.0, -10.0, -15.0, -18.0, -22.0]) == 4000
    assert convergence.samples_to_within(at, [np.nan, -10.0, -15.0, -18.0, -22.0]) is None


def test_rls_lenn_example1_within_1db_of_final_in_2000_samples():
    """RLS on the paper's LeNN features (Legendre, order 14), full 50 000-sample protocol."""
    example = EXAMPLES[1]
    candidate = candidates.candidates(1)[0]
    assert (candidate.solver, candidate.basis, candidate.order) == ("rls", "legendre", example.lenn["order"])
    at = convergence.checkpoints(50_000)
    for seed in (0, 4):  # 4: the slowest of seeds 0..4 in the report
        series = simulate(example.plant(), example.noise_db, seed)
        curve = convergence.learning_curve(example.structure, candidate.make(example, seed), series, at)
        assert convergence.samples_to_within(at, curve) <= 2000, (seed, curve)


# -- (c) tracking a changing plant --------------------------------------------------------------
def test_recovery_uses_whole_windows_after_the_change():
    squared = np.full(3000, 0.1)
    squared[1001:1301] = 1.0  # 300 bad samples right after the change at 1000
    recovery, level = tracking.recovery_samples(squared, 1000, reference=500)
    assert level == pytest.approx(-10.0)
    # the window ending at 1000 + r holds 500 - r bad samples; within 1 dB of 0.1 allows
    # b of them with 0.9 b / 200 <= 0.1 (10^0.1 - 1), i.e. b <= 5, so r = 495
    assert recovery == 495


def test_rls_with_forgetting_recovers_within_500_samples_after_plant_change():
    """Ex. 1, g changes sign at k = 10 000; RLS (paper features, lambda 0.99) keeps learning.

    lambda 0.99, not 0.995: the old plant's share of the estimate decays as lambda^n,
    and getting its error contribution under the 1 dB band takes n ~ 1.8 / (1 - lambda)
    samples, ~350 at 0.995, plus the 200-sample window; with the window's own seed to
    seed spread (about +-70 samples) 0.995 lands on both sides of 500 (seeds 0-5 at
    this length: 395-539), while 0.99 stays near 300 on every seed.
    """
    example = EXAMPLES[1]
    rls = candidates.candidates(1)[0]
    for seed in (0, 1, 2):
        u, y = tracking.simulate_change(seed, 15_000, 10_000)
        result = tracking.track(lambda s=seed: rls.with_params(forgetting=0.99).make(example, s), u, y, 10_000)
        assert result.frozen_jump_db > 5.0  # the change is large for a model that stops learning
        assert result.recovery is not None and result.recovery <= 500, (seed, result.recovery)
        stuck = tracking.track(lambda s=seed: rls.make(example, s), u, y, 10_000)
        assert stuck.recovery is None or stuck.recovery > 2000  # without forgetting it does not track


# -- (d) cross terms ---------------------------------------------------------------------------
def test_cross_term_rls_beats_paper_lenn_by_5db_on_example2():
    """Mean one-step NMSE over seeds 0-2, 20 000 training samples, against both the
    paper's reported LeNN figure and our calibrated LeNN on the same data."""
    example = EXAMPLES[2]
    best = candidates.winner(2)
    assert best.solver == "rls" and best.cross_degree >= 2
    ours, paper = [], []
    for seed in (0, 1, 2):
        series = simulate(example.plant(), example.noise_db, seed, train_samples=20_000)
        ours.append(train_and_test(Identifier(example.structure, best.make(example, seed)), series).nmse_db)
        lenn = example.make_network("lenn", seed, "calibrated")
        paper.append(train_and_test(Identifier(example.structure, lenn), series).nmse_db)
    assert np.mean(ours) <= example.paper_nmse_db["lenn"] - 5.0
    assert np.mean(ours) <= np.mean(paper) - 5.0


# -- the command ---------------------------------------------------------------------------------
def test_beyond_command_json():
    from lenn_ros import cli

    out = io.StringIO()
    with redirect_stdout(out):
        status = cli.main(["reproduce", "--beyond", "--example", "3", "--seeds", "2", "--iterations", "1000", "--json"])
    assert status == 0
    objects = json.loads(out.getvalue())
    assert [o["row"] for o in objects] == ["paper LeNN", "paper MLP", "RLS, paper features", "beyond"]
    for o in objects:
        assert o["kind"] == "identification" and o["seeds"] == [0, 1] and len(o["nmse_db"]) == 2
        assert o["checkpoints"] == [250, 500, 1000]
