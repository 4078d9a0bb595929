"""Offline equals live across live parameter changes (issue 18, item 5).

The real identifier, simulator and recorder as processes over DDS; alpha, forgetting and
learning are set through the identifier's parameter service mid-run, as ``ros2 param set``
does. ``evaluate`` of the bag must give the live test figure to 1e-6 dB: before the changes
were recorded (identifier_config published once), alpha halved live gave -15.79 dB live and
-15.37 dB offline.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(180)]

rclpy = pytest.importorskip("rclpy")

from rosutil import Listener, ParameterClient, final_status, start_node, stop  # noqa: E402

from lenn_ros.service.building import recorded_changes  # noqa: E402
from lenn_ros.service.evaluation import evaluate_bag  # noqa: E402

TRAIN, TEST = 3000, 400


@pytest.mark.parametrize(
    ("solver", "first_change"),
    [("sgd", ("alpha", None)), ("rls", ("forgetting", 0.99))],  # None: alpha halved
)
def test_live_changes_are_recorded_and_evaluate_equals_live(
    tmp_path: Path, domain: int, solver: str, first_change: tuple[str, float | None], monkeypatch: pytest.MonkeyPatch
) -> None:
    values = {"example": 1, "seed": 3, "solver": solver, "status_period": 0.1}
    values |= {"wait_for_y_hat_subscribers": 3, "wait_for_samples_subscribers": 1}  # simulator, recorder, listener
    if solver == "rls":
        values["output"] = "linear"
    params = tmp_path / "identifier.yaml"
    params.write_text(json.dumps({"identifier": {"ros__parameters": values}}))
    bag = tmp_path / "bag"
    listener = Listener(domain)
    recorder = start_node("recorder", f"output:={bag}")
    identifier = start_node("identifier", params_file=params)
    simulator = start_node(
        "plant_simulator", "example:=1", "seed:=3", f"train_samples:={TRAIN}", f"test_samples:={TEST}",
        "rate_hz:=250.0", "wait_for_subscribers:=3", "exit_when_done:=true",
    )  # fmt: skip
    name, value = first_change
    # (at least these many samples learnt when each change is made: well inside the training phase)
    plan = [(600, name, value), (1400, "learning", False), (2000, "learning", True)]
    try:
        with ParameterClient(domain) as client:
            for after, parameter, setting in plan:
                status = listener.wait_status(lambda s, n=after: s["counters"]["samples"] >= n, timeout=60)
                assert status["counters"]["samples"] < TRAIN, "the run outpaced the test: changes not mid-training"
                if setting is None:
                    setting = _alpha(params) / 2
                result = client.set(parameter, setting)
                assert result.successful, result.reason
        _, sim_err = simulator.communicate(timeout=120)
        assert simulator.returncode == 0, sim_err
        listener.wait_status(lambda s: s["counters"]["paired"] == TRAIN + TEST, timeout=30)
    finally:
        _, id_err = stop(identifier)
        rec_out, rec_err = stop(recorder)
        listener.close()
    live = final_status(id_err)
    assert live["parameter_changes"] == 3 and live["phase_samples"] > TEST - 20  # (a loaded core can cost a pair)
    changes = recorded_changes(str(bag))
    assert [list(change.values) for change in changes] == [[name], ["learning"], ["learning"]]
    assert all(after < change.from_index < TRAIN for (after, *_), change in zip(plan, changes, strict=True))
    assert "in effect from sample" in id_err
    summary = [line for line in rec_err.splitlines() + rec_out.splitlines() if "samples" in line]
    print("recorder:", summary[-1:] if summary else rec_err[-500:])
    offline = evaluate_bag(str(bag))  # the configuration recorded in the bag, changes included
    assert offline.evaluation.samples == live["phase_samples"]
    print(f"{solver}: live {live['phase_nmse_db']:.6f} dB, evaluate {offline.evaluation.nmse_db:.6f} dB")
    assert abs(live["phase_nmse_db"] - offline.evaluation.nmse_db) < 1e-6
    applied = [note for note in offline.notices if note.startswith("parameter change")]
    assert len(applied) == 3 and all("applied offline at that sample" in note for note in applied), offline.notices
    assert "Traceback" not in rec_err
    if solver == "sgd":
        check_replay_sets_the_changes(tmp_path, values, bag, live, changes)
    check_the_changes_matter(monkeypatch, bag, live, solver)


def _alpha(params: Path) -> float:
    """The alpha the identifier starts with (the example's preset, as the node resolves it)."""
    from lenn_ros.service.building import identifier_from_params

    identifier, _ = identifier_from_params(str(params))
    return float(identifier.model.alpha)


def check_replay_sets_the_changes(tmp_path: Path, values: dict, bag: Path, live: dict, changes: list) -> None:
    """``replay`` of the bag into a fresh identifier sets each change before the same sample as live."""
    values = {**values, "wait_for_y_hat_subscribers": 1}  # the replay alone
    params = tmp_path / "replayed.yaml"
    params.write_text(json.dumps({"identifier": {"ros__parameters": values}}))
    identifier = start_node("identifier", params_file=params)
    replay = start_node("replay", f"bag:={bag}", "rate:=0.0", "wait_for_subscribers:=1")
    try:
        _, replay_err = replay.communicate(timeout=120)
        assert replay.returncode == 0, replay_err
    finally:
        _, id_err = stop(identifier)
    again = final_status(id_err)
    for change in changes:
        assert f"in effect from sample {change.from_index} (recorded)" in id_err, id_err[-3000:]
    assert again["parameter_changes"] == len(changes)
    gap = abs(again["phase_nmse_db"] - live["phase_nmse_db"])
    print(f"replayed: {again['phase_nmse_db']:.6f} dB ({gap:.2e} dB from live)")
    # A replay descheduled between u(k) and y_p(k) on two loaded cores publishes them over max_skew
    # apart (seen: 0.3 s), yet in turn: the pair is still one sample, learnt as live learnt it.
    assert again["counters"]["misaligned"] == 0, again["counters"]
    assert again["phase_samples"] == live["phase_samples"] and gap < 1e-6


def check_the_changes_matter(monkeypatch: pytest.MonkeyPatch, bag: Path, live: dict, solver: str) -> None:
    """Evaluate without the recorded changes (as before they were recorded) misses the live figure."""
    import lenn_ros.service.evaluation

    monkeypatch.setattr(lenn_ros.service.evaluation, "recorded_changes", lambda path: [])
    unchanged = evaluate_bag(str(bag)).evaluation.nmse_db
    print(f"{solver}: evaluate without the changes {unchanged:.6f} dB")
    assert abs(unchanged - live["phase_nmse_db"]) > 1e-3
