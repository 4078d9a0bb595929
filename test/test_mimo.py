"""MIMO core: one MISO model per output, stepped together; no ROS."""

from __future__ import annotations

import re

import numpy as np
import pytest

from lenn_ros.core.metrics import nmse_db
from lenn_ros.core.mimo import MimoStructure, build_mimo_identifier, parse_couplings
from lenn_ros.core.networks import FunctionalLinkNetwork
from lenn_ros.paper.evaluation import simulate_mimo
from lenn_ros.paper.plants import narendra_mimo_plant


def _identifier(couplings: str = "full", seed: int = 0, scales=(2.0, 1.6)):
    structure = MimoStructure(
        n_u=2, n_y=2, y_scale=scales, u_scale=(1.0, 1.0), couplings=parse_couplings(couplings, 2, 2)
    )

    def make_model(n_inputs: int, _output: int) -> FunctionalLinkNetwork:
        return FunctionalLinkNetwork(
            n_inputs=n_inputs, order=4, cross_degree=3, solver="rls", output="linear", random_state=seed
        )

    return build_mimo_identifier(structure, make_model, names=("y1", "y2"))


def test_couplings_parse_presets_lists_and_refuse_unknown_channels() -> None:
    assert parse_couplings("full", 2, 2) == (("y0", "y1", "u0", "u1"),) * 2
    assert parse_couplings("diagonal", 2, 2) == (("y0", "u0"), ("y1", "u1"))
    assert parse_couplings("y0 u0 u1; y1 y0", 2, 2) == (("y0", "u0", "u1"), ("y1", "y0"))
    with pytest.raises(ValueError, match="no channel 'u2'"):
        parse_couplings("y0 u2; y1", 2, 2)
    with pytest.raises(ValueError, match="lists 1 output"):
        parse_couplings("y0 u0", 2, 2)
    with pytest.raises(ValueError, match="as many inputs"):
        parse_couplings("diagonal", 1, 2)


def test_channel_structure_sees_the_configured_channels_in_order() -> None:
    structure = MimoStructure(n_u=2, n_y=2, y_lags=2, u_lags=1, couplings=parse_couplings("y0 u1; y1 y0 u0", 2, 2))
    assert structure.others(0) == [("u", 1)]
    assert structure.others(1) == [("y", 0), ("u", 0)]
    channel = structure.channel(1)
    assert [c[0] for c in channel.input_channels()] == [2, 2, 1] and (channel.n_inputs, channel.warm_up) == (5, 2)
    u = np.arange(10.0).reshape(5, 2)
    y = 100 + np.arange(10.0).reshape(5, 2)
    x, _ = channel.regressors(structure.other_values(1, u, y), y[:, 1])
    # row for k = 1: y1(1), y1(0), y0(1), y0(0), u0(1)
    assert x[0].tolist() == [103.0, 101.0, 102.0, 100.0, 2.0]


def test_step_equals_run_bit_for_bit_and_a_gap_restarts_every_output() -> None:
    series = simulate_mimo(narendra_mimo_plant(), -30.0, seed=3, train_samples=1500, test_samples=200)
    stepped, batch = _identifier(), _identifier()
    learn = np.arange(len(series.y)) < series.test_start
    y_hat_batch = batch.run(series.u, series.y, learn)
    y_hat_step = np.full_like(series.y, np.nan)
    for k in range(len(series.y)):
        result = stepped.step(k + 1, series.u[k], series.y[k], bool(learn[k]))
        if result.y_hat is not None:
            y_hat_step[k] = result.y_hat
    np.testing.assert_array_equal(y_hat_step, y_hat_batch)
    assert stepped.counters["samples"] == len(series.y)
    assert stepped.counters["learned"] == 2 * (series.test_start - 1)  # every output learnt every training error
    gap = stepped.step(len(series.y) + 5, series.u[0], series.y[0])
    assert gap.event == "gap" and gap.y_hat is None and stepped.counters["gaps"] == 1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mimo_model_beats_one_siso_model_per_output_on_the_coupled_plant(seed: int) -> None:
    """The check of the issue, offline: coupling matters in both outputs of this plant."""
    series = simulate_mimo(narendra_mimo_plant(), None, seed=seed, train_samples=8000, test_samples=600)
    learn = np.arange(len(series.y)) < series.test_start
    scores = {}
    for couplings in ("full", "diagonal"):
        identifier = _identifier(couplings, seed)
        y_hat = identifier.run(series.u, series.y, learn)
        test = slice(series.test_start, None)
        free = identifier.free_run(series.u, series.y, series.test_start)
        assert not identifier.last_free_run["diverged"]
        scores[couplings] = [
            (nmse_db(series.y[test, j], y_hat[test, j]), nmse_db(series.y[test, j], free[:, j])) for j in range(2)
        ]
    for j in range(2):
        assert scores["full"][j][0] < scores["diagonal"][j][0] - 5.0  # one step ahead
        assert scores["full"][j][1] < scores["diagonal"][j][1] - 5.0  # free run


def test_a_nan_sample_is_skipped_by_every_output_and_never_learnt() -> None:
    identifier = _identifier()
    rng = np.random.default_rng(0)
    for k in range(1, 50):
        identifier.step(k, rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2))
    weights = [model.weights_.copy() for model in identifier.models]
    identifier.skip(50)
    assert identifier.counters["rejected"] == 1
    result = identifier.step(51, np.zeros(2), np.zeros(2))
    assert result.y_hat is None and not result.learned  # history restarted: nothing to score
    for before, model in zip(weights, identifier.models, strict=True):
        np.testing.assert_array_equal(before, model.weights_)


def test_a_session_pairs_vector_halves_screens_each_channel_and_scores_per_channel() -> None:
    from lenn_ros.core.pairing import U, Y
    from lenn_ros.session import Session, SessionConfig

    series = simulate_mimo(narendra_mimo_plant(), -30.0, seed=1, train_samples=600, test_samples=100)
    session = Session(_identifier(), SessionConfig(pairing="sequence", y_limit=100.0))
    reference = _identifier()
    y = series.y.copy()
    y[300, 1] = np.nan  # one bad channel: the whole sample is skipped
    y[301, 0] = 1e6  # beyond y_limit: skipped too
    samples = []
    for k in range(len(y)):
        samples += session.offer(U, series.u[k], time=k * 0.01, sequence=k + 1)
        samples += session.offer(Y, y[k], time=k * 0.01, sequence=k + 1)
    assert len(samples) == len(y)
    status = session.status()
    assert status["counters"]["nan"] == 1 and status["counters"]["out_of_range"] == 1
    assert status["counters"]["rejected"] == 2
    assert set(status["channels"]) == {"y1", "y2"}
    assert all(channel["phase_nmse_db"] < -10 for channel in status["channels"].values())
    kinds = {notice.kind for notice in session.take_notices()}
    assert {"nan", "out_of_range"} <= kinds
    # the batch path (evaluate) gives the same numbers from the same samples
    index = np.array([sample.index for sample in samples])
    u = np.array([sample.u for sample in samples])
    y_seen = np.array([sample.y for sample in samples])
    offline = Session(reference, SessionConfig(pairing="sequence"))
    y_hat = offline.run_samples(index, u, y_seen, np.ones(len(index), dtype=bool))
    live = np.array(
        [s.result.y_hat if s.result is not None and s.result.y_hat is not None else [np.nan] * 2 for s in samples]
    )
    np.testing.assert_array_equal(live, y_hat)
    offline_db = offline.status()["channels"]["y1"]["phase_nmse_db"]
    assert offline_db == pytest.approx(status["channels"]["y1"]["phase_nmse_db"], rel=1e-12)  # Welford vs Chan


def test_save_state_and_load_state_round_trip_every_output_in_one_file(tmp_path) -> None:
    from lenn_ros.core.networks import ModelFileError

    series = simulate_mimo(narendra_mimo_plant(), -30.0, seed=4, train_samples=1500, test_samples=200)
    learnt = _identifier()
    learnt.run(series.u, series.y, np.arange(len(series.y)) < series.test_start)
    learnt.save_state(tmp_path / "weights.npz")
    fresh = _identifier(seed=9)
    fresh.load_state(tmp_path / "weights.npz")
    for a, b in zip(learnt.models, fresh.models, strict=True):
        np.testing.assert_array_equal(a.weights_, b.weights_)
        np.testing.assert_array_equal(a.covariance_, b.covariance_)
    np.testing.assert_array_equal(
        learnt.free_run(series.u, series.y, series.test_start), fresh.free_run(series.u, series.y, series.test_start)
    )
    with pytest.raises(ModelFileError, match=r"output 0 \(y1\): weights are for a different network.*n_inputs"):
        _identifier("diagonal").load_state(tmp_path / "weights.npz")  # 2 inputs per output, not 4
    learnt.models[0].save(tmp_path / "one.npz")
    with pytest.raises(ModelFileError, match="weights of a single-output model, this model has 2 outputs"):
        fresh.load_state(tmp_path / "one.npz")
    with pytest.raises(ModelFileError, match=r"with 2 outputs \(MIMO\)"):
        learnt.models[0].load_state(tmp_path / "weights.npz")


def test_a_side_on_several_topics_merges_by_sequence_stamp_or_hold() -> None:
    from lenn_ros.core.merging import TopicMerger

    by_sequence = TopicMerger((1, 2), "sequence", window=5)
    assert by_sequence.add(1, [2.0, 3.0], 0.1, 0.1, sequence=7) == []
    half = by_sequence.add(0, [1.0], 0.1, 0.1, sequence=7)[0]
    assert half.value.tolist() == [1.0, 2.0, 3.0] and half.sequence == 7
    by_sequence.add(0, [1.0], 0.2, 0.2, sequence=8)  # its partner never comes
    by_sequence.add(0, [1.0], 0.3, 0.3, sequence=20)
    assert by_sequence.counters["merge_dropped"] == 1  # 8 fell out of the window at 20

    by_stamp = TopicMerger((1, 1), "stamp", slop=0.001)
    assert by_stamp.add(0, [1.0], 5.0, 5.01) == []
    assert by_stamp.add(1, [2.0], 5.2, 5.21) == []  # another reading
    assert by_stamp.add(1, [3.0], 5.0004, 5.22)[0].value.tolist() == [1.0, 3.0]

    held = TopicMerger((1, 1), "sample", max_age=0.05)
    assert held.add(0, [1.0], 0.00, 0.00) == []  # part 1 never seen yet
    assert held.add(1, [2.0], 0.01, 0.01)[0].value.tolist() == [1.0, 2.0]
    assert held.add(0, [4.0], 0.02, 0.02)[0].value.tolist() == [4.0, 2.0]  # part 1 held
    assert held.add(0, [5.0], 0.20, 0.20) == [] and held.stale_part == 1  # part 1 silent: no half
    assert held.counters["merge_stale"] == 1


def test_a_session_learns_from_a_side_split_over_topics_and_says_a_silent_one() -> None:
    from lenn_ros.core.pairing import U, Y
    from lenn_ros.session import Session, SessionConfig

    series = simulate_mimo(narendra_mimo_plant(), -30.0, seed=2, train_samples=400, test_samples=0)
    config = SessionConfig(pairing="sequence", u_parts=(1, 1), u_parts_names=("/cmd0", "/cmd1"))
    session, reference = Session(_identifier(), config), _identifier()
    for k in range(len(series.y)):
        session.offer(U, [series.u[k, 1]], k * 0.01, sequence=k + 1, part=1)
        session.offer(U, [series.u[k, 0]], k * 0.01, sequence=k + 1, part=0)
        session.offer(Y, series.y[k], k * 0.01, sequence=k + 1)
    reference.run(series.u, series.y)
    assert session.all_counters()["u_merged"] == len(series.y)
    for merged, whole in zip(session.identifier.models, reference.models, strict=True):
        np.testing.assert_array_equal(merged.weights_, whole.weights_)  # as if u had come on one topic

    held = Session(_identifier(), SessionConfig(pairing="sample", sample_period=0.01, y_parts=(1, 1),
                                                y_parts_names=("/left", "/right")))  # fmt: skip
    for k in range(50):
        held.offer(U, [0.1, 0.2], k * 0.01)
        held.offer(Y, [0.3], k * 0.01, part=0)
        if k < 10:
            held.offer(Y, [0.4], k * 0.01, part=1)
    notices = [notice.text for notice in held.take_notices() if notice.kind == "merge_stale"]
    assert notices and notices[0].startswith("/right is older than 0.050 s")


@pytest.mark.parametrize("basis", ["legendre", "chebyshev"])
def test_the_one_sample_expansion_with_cross_terms_equals_the_batch_bit_for_bit(basis: str) -> None:
    """The live path (plain floats per sample) must give the offline path's bits, or live != offline."""
    from lenn_ros.core.expansions import expand

    x = np.random.default_rng(0).uniform(-1, 1, (200, 4))
    batch = expand(x, 4, basis, 3)
    one_by_one = np.vstack([expand(x[i : i + 1], 4, basis, 3) for i in range(len(x))])
    assert one_by_one.shape == batch.shape == (200, 39)  # bias, 4 x 4 univariate, 22 cross terms
    np.testing.assert_array_equal(one_by_one, batch)


@pytest.mark.parametrize(
    ("change", "said"),
    [
        ({"couplings": "y0 u7; y1"}, "no channel 'u7'"),
        ({"y_scales": [1.0, 2.0, 3.0]}, "y_scales has 3 values for 2 channels"),
        ({"y_names": ["only"]}, "1 names for 2 fields"),
        ({"u_field": "data[*]", "u_names": [""]}, "give the channels' names"),
        ({"terms": ["y1"]}, "each term names its output first, e.g. 'y0: u1_2*y0_1' (outputs y0, y1)"),
        ({"terms": ["y0: 1"]}, "terms name no term for y1"),
        ({"terms": ["y0: 1", "y1: u5_1"]}, "terms of y1: term 'u5_1': no input 'u5_1'"),
        ({"known_a": [0.3, 0.6]}, "known_a: a known linear part is a single-channel option"),
        ({"y_abs": True}, "y_abs: a sensor read as |y| is signed by one output's predictions"),
        ({"separate": True, "terms": ["y0: u0_1", "y1: u1_1"]}, "terms select one combiner over all inputs"),
        ({"separate": True, "couplings": "y0 u0; u1"}, "separate N1[y] + N2[u] needs both y_lags and u_lags >= 1"),
        ({"u_topics": ["/a", "/b"], "u_field": "data[*]"}, "list the fields instead of [*]"),
    ],
)
def test_a_mimo_configuration_that_cannot_work_is_one_clear_error(change: dict, said: str) -> None:
    from lenn_ros.config import ConfigError, identifier_parameters
    from lenn_ros.service.building import build_identifier

    values = {p.name: p.default for p in identifier_parameters(0, "lenn")}
    values.update({"u_field": "data[0], data[1]", "y_field": "position[a], position[b]", "u_topics": [""]})
    values.update(change)
    with pytest.raises(ConfigError, match=re.escape(said)):
        build_identifier(values, "lenn")


@pytest.mark.parametrize(
    "settings",
    [
        {"solver": "rls", "output": "linear"},
        {"solver": "nlms", "output": "linear"},
        {"solver": "sgd", "output": "tanh", "alpha": 0.05},
    ],
)
def test_the_compiled_mimo_step_equals_the_python_step(monkeypatch, settings: dict) -> None:
    """The one compiled step with several channels: each output gives the Python step's numbers bit for bit."""
    from lenn_ros.core import jit, structure

    if not jit.JIT:
        pytest.skip("numba is not installed: there is no compiled step")
    series = simulate_mimo(narendra_mimo_plant(), -20.0, seed=4, train_samples=1200, test_samples=200)
    u = 1.5 * series.u  # beyond u_scale 1: inputs get clipped
    learn = np.arange(len(u)) < 1200
    runs = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(structure.StepPlan, "for_model", classmethod(lambda cls, model, shape: None))
        mimo = MimoStructure(2, 2, y_lags=2, u_lags=1, y_scale=(2.0, 1.6), couplings=parse_couplings("full", 2, 2))
        identifier = build_mimo_identifier(
            mimo, lambda n, _j: FunctionalLinkNetwork(n_inputs=n, order=3, cross_degree=2, **settings)
        )
        results = [identifier.step(k + 1 + (k >= 700), u[k], series.y[k], bool(learn[k])) for k in range(len(u))]
        assert all((output._plan is not None) == compiled for output in identifier.outputs)
        runs.append((results, identifier))
    (fast, fast_id), (slow, slow_id) = runs
    for a, b in zip(fast, slow, strict=True):
        for name in ("y_hat", "y_hat_next", "error"):
            first, second = getattr(a, name), getattr(b, name)
            assert (first is None and second is None) or np.array_equal(first, second)
        assert (a.learned, a.event) == (b.learned, b.event)
    assert fast_id.counters == slow_id.counters and fast_id.counters["clipped"] > 0
    for quick, reference in zip(fast_id.models, slow_id.models, strict=True):
        np.testing.assert_array_equal(quick.weights_, reference.weights_)
        assert quick.n_samples_seen_ == reference.n_samples_seen_
        assert getattr(quick, "n_clipped_", 0) == getattr(reference, "n_clipped_", 0)


def test_the_compiled_joint_free_run_equals_the_python_one_and_flags_the_same_divergence(monkeypatch) -> None:
    from free_run_check import assert_same_divergence, assert_same_free_run

    from lenn_ros.core import jit

    if not jit.JIT:
        pytest.skip("numba is not installed: there is no compiled free run")
    series = simulate_mimo(narendra_mimo_plant(), -20.0, seed=5, train_samples=3000, test_samples=600)
    identifier = _identifier(seed=5, scales=(1.6, 1.4))  # tight scales: some inputs get clipped
    identifier.run(series.u, series.y, np.arange(len(series.y)) < 3000)
    _fast, info = assert_same_free_run(identifier, series.u, series.y, 3000, monkeypatch)
    assert info["clipped_inputs"] > 0
    for model in identifier.models:
        model.weights_ *= 40.0  # an unstable model: both runs must stop at the same sample
    assert_same_divergence(identifier, series.u, series.y, 3000, monkeypatch)


# -- name[*] picks joints by name only (issue 18, item 4) ---------------------------------------
def test_all_joints_are_picked_by_name_never_by_position() -> None:
    from types import SimpleNamespace

    from lenn_ros.core.fields import FieldError, compile_vector

    extract = compile_vector("position[*]", ["shoulder", "elbow"])
    reordered = SimpleNamespace(name=["elbow", "wrist", "shoulder"], position=[0.3, 9.0, 0.5])
    assert extract(reordered).tolist() == [0.5, 0.3]
    renamed = SimpleNamespace(name=["shoulder", "elbow_joint"], position=[0.5, 0.3])  # the counts agree
    with pytest.raises(FieldError, match=r"no joint 'elbow' in name \['shoulder', 'elbow_joint'\].*never by position"):
        extract(renamed)  # on main: taken by position, elbow_joint's value learnt as elbow's
    with pytest.raises(FieldError, match="no joint 'shoulder', 'elbow'"):
        extract(SimpleNamespace(name=[], position=[0.5, 0.3]))  # a driver that names nothing
    with pytest.raises(FieldError, match="1 values for the 2 names"):
        extract(SimpleNamespace(name=["elbow", "shoulder"], position=[0.3]))
    array = compile_vector("data[*]", ["a", "b"])  # no name list: the array as it is
    assert array(SimpleNamespace(data=[1.0, 2.0])).tolist() == [1.0, 2.0]


def test_separate_networks_work_with_several_channels(monkeypatch) -> None:
    """Model 3 per output (N1[own past] + N2[the channels it sees]): built from the parameters, two
    branches each, the compiled step and free run equal to the Python ones, and it learns the plant."""
    from lenn_ros.config import identifier_parameters
    from lenn_ros.core import free_run, jit, structure
    from lenn_ros.service.building import build_identifier

    if not jit.JIT:
        pytest.skip("numba is not installed: there is no compiled step")
    values = {p.name: p.default for p in identifier_parameters(0, "lenn")}
    values.update({"u_field": "data[0], data[1]", "y_field": "position[a], position[b]", "u_topics": [""],
                   "separate": True, "solver": "sgd", "output": "linear", "alpha": 0.05, "y_scales": [2.0, 1.6],
                   "u_scales": [1.0, 1.0]})  # fmt: skip
    series = simulate_mimo(narendra_mimo_plant(), -30.0, seed=2, train_samples=3000, test_samples=400)
    learn = np.arange(len(series.u)) < 3000
    runs = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(structure.StepPlan, "for_model", classmethod(lambda cls, model, shape: None))
            monkeypatch.setattr(free_run, "_compiled", free_run._python)
        identifier = build_identifier(values, "lenn")
        assert [len(model.branch_inputs_) for model in identifier.models] == [2, 2]
        results = [identifier.step(k + 1, series.u[k], series.y[k], bool(learn[k])) for k in range(len(learn))]
        y_hat = np.array([r.y_hat if r.y_hat is not None else np.full(2, np.nan) for r in results])
        free = identifier.free_run(series.u, series.y, 3000)
        runs.append((y_hat, free, [m.weights_.copy() for m in identifier.models]))
    (fast_hat, fast_free, fast_w), (slow_hat, slow_free, slow_w) = runs
    np.testing.assert_array_equal(fast_hat, slow_hat)
    np.testing.assert_allclose(fast_free, slow_free, rtol=0, atol=1e-12)
    for a, b in zip(fast_w, slow_w, strict=True):
        np.testing.assert_array_equal(a, b)
    test = slice(3001, None)
    nmse = [10 * np.log10(np.mean((series.y[test, j] - fast_hat[test, j]) ** 2) / np.var(series.y[test, j]))
            for j in range(2)]  # fmt: skip
    # measured -16.3 / -10.6 dB (seeds 0, 1, 3: -14.4 to -15.0 / -9.0 to -9.6): one-step, learning off
    assert nmse[0] < -14.0 and nmse[1] < -9.0, nmse


def test_an_output_passed_through_needs_its_own_past_and_one_flag_per_output() -> None:
    from lenn_ros.config import ConfigError, resolve
    from lenn_ros.service.building import build_identifier

    own = parse_couplings("y0 u0; y1 u0", 1, 2)
    structure = MimoStructure(n_u=1, n_y=2, couplings=own, y_pass_through=(True, False))
    passed, plain = structure.channel(0), structure.channel(1)
    assert (passed.known_a, passed.output_offset) == ((1.0,), 0.0) and plain.known_a == ()
    with pytest.raises(ValueError, match="needs its own past"):
        blind = parse_couplings("u0; y1 u0", 1, 2)  # output 0 does not read its own past
        MimoStructure(n_u=1, n_y=2, couplings=blind, y_pass_through=(True, False)).channel(0)
    values = {"u_field": "data[*]", "y_field": "data[*]", "u_names": ["a"], "y_names": ["b", "c"],
              "y_scales": [1.0, 1.0], "u_scales": [1.0], "y_pass_through": [True, False, True]}  # fmt: skip
    resolved, network = resolve(values)
    with pytest.raises(ConfigError, match="y_pass_through has 3 values for 2 outputs"):
        build_identifier({**values, **resolved}, network)


def test_live_parameter_changes_of_a_several_output_model_are_replayed_offline_at_their_sample() -> None:
    """forgetting and learning changed live on a 2x2 model: recorded from the next sample, and the batch pass
    over the recorded samples equals the live run per channel, as for one output (test_session's twin)."""
    from lenn_ros.core.pairing import U, Y
    from lenn_ros.session import Session, SessionConfig

    series = simulate_mimo(narendra_mimo_plant(), -30.0, seed=2, train_samples=1500, test_samples=300)
    changes = {500: {"forgetting": 0.995}, 900: {"learning": False}, 1100: {"learning": True}}
    live = Session(_identifier(), SessionConfig(pairing="sequence"))
    rows = []
    for k in range(1, len(series.u) + 1):
        live.offer(U, series.u[k - 1], time=k * 0.01, sequence=k)
        if k in changes:
            assert live.apply_parameters(changes[k]).from_index == k
        if k == 1501:
            live.apply_parameters({"learning": False})  # the test phase
        for sample in live.offer(Y, series.y[k - 1], time=k * 0.01, sequence=k):
            rows.append((sample.index, sample.u, sample.y, sample.result is not None and sample.result.learned))
    index = np.array([row[0] for row in rows])
    u, y = np.array([row[1] for row in rows]), np.array([row[2] for row in rows])
    learn = np.array([row[3] for row in rows])
    assert not learn[(index >= 900) & (index < 1100)].any() and learn[(index >= 1200) & (index < 1500)].all()
    offline = Session(_identifier(), SessionConfig(pairing="sequence"))
    offline.run_samples(index, u, y, learn, live.changes)
    for name in ("y1", "y2"):
        said = live.status()["channels"][name]["phase_nmse_db"]
        assert offline.status()["channels"][name]["phase_nmse_db"] == pytest.approx(said, abs=1e-9)
    for mine, theirs in zip(offline.identifier.models, live.identifier.models, strict=True):
        np.testing.assert_allclose(mine.weights_, theirs.weights_, rtol=0, atol=1e-12)
        assert mine.forgetting == theirs.forgetting == 0.995
    ignored = Session(_identifier(), SessionConfig(pairing="sequence"))
    ignored.run_samples(index, u, y, learn)  # the change matters: without it another model
    assert not np.allclose(ignored.identifier.models[0].weights_, live.identifier.models[0].weights_, atol=1e-9)
