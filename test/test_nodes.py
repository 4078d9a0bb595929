"""The real nodes as processes over DDS: pairing, recording, live vs offline, parameters."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(180)]

rclpy = pytest.importorskip("rclpy")

from rosutil import Listener, final_status, start_node, stop  # noqa: E402
from test_bag import independent_read  # noqa: E402

from lenn_ros.bag import read_run  # noqa: E402
from lenn_ros.paper.examples import EXAMPLES  # noqa: E402
from lenn_ros.service.evaluation import evaluate_bag  # noqa: E402


def write_params(path: Path, **values) -> Path:
    path.write_text(json.dumps({"identifier": {"ros__parameters": values}}))
    return path


@pytest.mark.parametrize(("example", "network"), [(3, "lenn"), (4, "mlp")])
def test_online_run_is_paired_recorded_and_equals_offline(tmp_path: Path, domain: int, example: int, network: str):
    train, test = 3000, 400
    total = train + test
    params = write_params(
        tmp_path / "identifier.yaml",
        example=example,
        network=network,
        seed=3,
        wait_for_y_hat_subscribers=3,
        wait_for_error_subscribers=2,  # simulator, recorder, listener
    )
    bag = tmp_path / "bag"
    listener = Listener(domain)
    recorder = start_node("recorder", f"output:={bag}")
    identifier = start_node("identifier", params_file=params)
    simulator = start_node(
        "plant_simulator",
        f"example:={example}",
        "seed:=3",
        f"train_samples:={train}",
        f"test_samples:={test}",
        "rate_hz:=0.0",
        "wait_for_subscribers:=3",
        "exit_when_done:=true",
    )
    try:
        _, sim_err = simulator.communicate(timeout=120)
        assert simulator.returncode == 0, sim_err
        listener.wait_status(lambda s: s["counters"]["paired"] == total, timeout=30)
    finally:
        _, id_err = stop(identifier)
        _, rec_err = stop(recorder)
        listener.close()
    live = final_status(id_err)
    counters = live["counters"]
    assert counters["paired"] == total and counters["samples"] == total
    assert counters["lost"] == counters["duplicates"] == counters["stale"] == counters["unpaired"] == 0
    warm_up = EXAMPLES[example].structure.warm_up
    got = {name: len(values) for name, values in listener.values.items()}
    assert got == {"u": total, "y_p": total, "y_hat": total - warm_up + 1, "error": total - warm_up}
    # the bag holds exactly what was published, read by two independent readers
    run = read_run(bag)
    assert np.array_equal(run.u, listener.values["u"]) and np.array_equal(run.y_p, listener.values["y_p"])
    assert np.array_equal(run.y_hat, listener.values["y_hat"]) and np.array_equal(run.error, listener.values["error"])
    theirs = independent_read(bag / "bag.mcap")
    assert {t: len(v) for t, v in theirs.items() if t in ("/u", "/y_p", "/y_hat", "/error")} == {
        "/" + name: count for name, count in got.items()
    }
    assert run.test_start == train + 1
    # the same computation offline, from the recording
    offline = evaluate_bag(str(bag), str(params))
    assert live["phase_samples"] == offline.evaluation.samples == test
    assert abs(live["phase_nmse_db"] - offline.evaluation.nmse_db) < 1e-9
    assert "Traceback" not in rec_err and "[ERROR]" not in rec_err
    if example == 3:
        check_lost_and_reordered_messages(bag, tmp_path, params, live)


def copy_bag(source: Path, target: Path, keep, swap: tuple[int, int] | None = None) -> None:
    """Copy a bag message by message, dropping what ``keep`` refuses; ``swap`` two y_p arrivals."""
    import dataclasses

    from lenn_ros.bag import BagWriter, iter_messages, topic_types

    messages = [m for m in iter_messages(source) if keep(m)]
    if swap is not None:
        y_p = [i for i, m in enumerate(messages) if m.topic == "/y_p"]
        a, b = y_p[swap[0]], y_p[swap[1]]
        messages[a], messages[b] = (
            dataclasses.replace(messages[a], log_time_ns=messages[b].log_time_ns),
            dataclasses.replace(messages[b], log_time_ns=messages[a].log_time_ns),
        )
    with BagWriter(target) as writer:
        for topic, type_name in topic_types(source).items():
            writer.add_topic(topic, type_name)
        for m in messages:
            writer.write_message(
                m.topic, m.message, m.log_time_ns, publish_time_ns=m.publish_time_ns, sequence=m.sequence
            )


def check_lost_and_reordered_messages(bag: Path, tmp_path: Path, params: Path, live: dict) -> None:
    """Raw messages lost or reordered in the recording: the figure is still the live one."""
    dropped = {100, 101, 102, 2000, 3100}
    from lenn_ros.bag import iter_messages

    u_count = {"n": 0}

    def keep(message) -> bool:
        if message.topic == "/u":
            u_count["n"] += 1
            return u_count["n"] not in dropped
        return True

    damaged = tmp_path / "damaged"
    copy_bag(bag, damaged, keep, swap=(500, 503))
    sequences = [m.sequence for m in iter_messages(damaged, ["/y_p"])]
    assert sequences[500:504] == [504, 502, 503, 501]  # arrived out of order, indices recorded
    offline = evaluate_bag(str(damaged), str(params))
    assert abs(live["phase_nmse_db"] - offline.evaluation.nmse_db) < 1e-9
    assert any("5 /u messages missing" in note for note in offline.notices), offline.notices
    # without the identifier's samples the raw topics are paired by their recorded indices
    raw = tmp_path / "raw"
    u_count["n"] = 0
    copy_bag(bag, raw, lambda m: m.topic != "/samples" and keep(m), swap=(500, 503))
    repaired = evaluate_bag(str(raw), str(params))
    assert repaired.source == "u/y_p by sequence" and repaired.missing == len(dropped)
    assert repaired.counters["unpaired"] == len(dropped)  # their y_p halves, never mispaired
    assert abs(repaired.evaluation.nmse_db - live["phase_nmse_db"]) < 1.0
    print(
        f"live {live['phase_nmse_db']:.4f} dB, damaged bag {offline.evaluation.nmse_db:.4f} dB from samples, "
        f"{repaired.evaluation.nmse_db:.4f} dB re-paired from raw topics ({repaired.missing} missing)"
    )


def test_lockstep_waits_for_the_first_y_hat_while_the_identifier_holds_its_pairs(domain: int) -> None:
    """An identifier holds every pair until its error topic has a reader, which joins after the simulator
    has sent its last sample and ``stall_timeout`` (2 s) has passed: the simulator waits for the first y_hat
    (as an identifier under load holds its first pairs for the graph's names, up to 5 s), and every pair is
    learnt. It used to exit after 2 s, and the run ended with every pair held, unlearnt."""
    from std_msgs.msg import Float64, String

    from lenn_ros import topics

    samples = 300
    identifier = start_node("identifier", "example:=1", "status_period:=0.1", "wait_for_error_subscribers:=1")
    simulator = start_node(
        "plant_simulator", "example:=1", f"train_samples:={samples}", "test_samples:=0", "rate_hz:=0.0",
        "exit_when_done:=true",
    )  # fmt: skip
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("late_reader", context=context)
    statuses: list[dict] = []
    node.create_subscription(String, topics.STATUS, lambda m: statuses.append(json.loads(m.data)), topics.data_qos())
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 60
        while not statuses or statuses[-1]["held"] < samples:  # everything sent, and held
            assert time.monotonic() < deadline and simulator.poll() is None, (statuses[-1:], simulator.poll())
            executor.spin_once(timeout_sec=0.1)
        held_at = time.monotonic()
        while time.monotonic() - held_at < 3.0:  # the reader is late by more than stall_timeout: the scenario
            executor.spin_once(timeout_sec=0.1)
        assert simulator.poll() is None, "the simulator left while the identifier still held every pair"
        node.create_subscription(Float64, topics.ERROR, lambda _: None, topics.data_qos())
        _, sim_err = simulator.communicate(timeout=60)
    finally:
        if simulator.poll() is None:
            stop(simulator)
        _, id_err = stop(identifier)
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()
    assert simulator.returncode == 0 and "none of" not in sim_err and "no y_hat for" not in sim_err, sim_err[-2000:]
    counters = final_status(id_err)["counters"]
    assert counters["paired"] == samples and counters["learned"] == samples - EXAMPLES[1].structure.warm_up, counters


def test_live_parameters_are_validated_and_applied(tmp_path: Path, domain: int) -> None:
    from rosutil import ParameterClient

    identifier = start_node("identifier", "example:=1")
    try:
        with ParameterClient(domain) as client:
            set_parameter = client.set
            refused = set_parameter("alpha", -0.5)
            assert not refused.successful and "alpha" in refused.reason
            refused = set_parameter("network", "svm")
            assert not refused.successful and "read-only" in refused.reason
            refused = set_parameter("out_of_range", "ignore")
            assert not refused.successful and "reject" in refused.reason
            assert set_parameter("alpha", 0.02).successful
            assert set_parameter("alpha", 1).successful  # an integer for a double, as `ros2 param set` sends it
            refused = set_parameter("alpha", 100)
            assert not refused.successful and "alpha must be <=" in refused.reason
            refused = set_parameter("alpha", "fast")
            assert not refused.successful and "number" in refused.reason
            assert set_parameter("learning", False).successful
    finally:
        _, err = stop(identifier)
    assert identifier.returncode == 0, err


def run_to_failure(*ros_args: str) -> tuple[int, str]:
    import sys

    from rosutil import REPO

    process = subprocess.run(
        [sys.executable, "-m", "lenn_ros.nodes.identifier", "--ros-args", *ros_args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )
    return process.returncode, process.stderr


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["-p", "example:=7"], "example out of range"),
        (["-p", "network:=svm"], "network must be 'lenn' or 'mlp'"),
        (["-p", "example:=1", "-p", "weights_in:=/nonexistent/w.npz"], "does not exist"),
        (["-p", "weights_in:=w.npz"], "w.npz (from the identifier's parameters) does not exist"),  # (missing)
        (["-p", "y_lags:=0", "-p", "u_lags:=0"], "at least one input"),
    ],
)
def test_startup_errors_are_one_clear_line(domain: int, arguments: list[str], message: str) -> None:
    code, stderr = run_to_failure(*arguments)
    assert code == 2
    assert message in stderr
    assert "Traceback" not in stderr


def test_malformed_params_file_and_foreign_weights(tmp_path: Path, domain: int) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("identifier:\n  ros__parameters:\n    alpha: [1, 2\n")
    code, stderr = run_to_failure("--params-file", str(bad))
    assert code == 2 and "params file" in stderr and "Traceback" not in stderr
    EXAMPLES[1].make_network("mlp").save(tmp_path / "mlp.npz")
    foreign = f"weights_in:={tmp_path / 'mlp.npz'}"
    code, stderr = run_to_failure("-p", "example:=1", "-p", "network:=lenn", "-p", foreign)
    assert code == 2 and "different network" in stderr and "Traceback" not in stderr


def test_weights_in_is_said_at_start_with_file_count_and_structure(tmp_path: Path, domain: int) -> None:
    weights = tmp_path / "start.npz"
    EXAMPLES[1].make_network("lenn").save(weights)
    identifier = start_node("identifier", "example:=1", "network:=lenn", f"weights_in:={weights}")
    listener = Listener(domain)
    try:
        listener.wait_status(lambda s: True, timeout=30)
    finally:
        listener.close()
        _, err = stop(identifier)
    line = next((line for line in err.splitlines() if "weights_in: loaded" in line), "")
    assert f"loaded 15 weights from {weights}" in line, err
    assert "lenn, y_lags 0, u_lags 1" in line and "order 14" in line and "basis legendre" in line, line


def test_sigterm_saves_weights_atomically(tmp_path: Path, domain: int) -> None:
    weights = tmp_path / "weights.npz"
    identifier = start_node("identifier", "example:=1", f"weights_out:={weights}")
    listener = Listener(domain)
    try:
        listener.wait_status(lambda s: True, timeout=30)
    finally:
        listener.close()
        _, err = stop(identifier, signal.SIGTERM)
    assert identifier.returncode == 0, err
    from lenn_ros.core.networks import OnlineRegressor

    assert OnlineRegressor.load(weights).n_weights == 15
    assert not list(tmp_path.glob(".weights.npz.*"))  # no temporary left behind


def test_status_is_strict_json_and_autosave_runs_on_its_own_period(tmp_path: Path, domain: int) -> None:
    """Autosave every 0.3 s with a status every 5 s; NaN (no errors yet) must not reach the JSON."""
    import time

    weights = tmp_path / "auto.npz"
    identifier = start_node("identifier", f"weights_out:={weights}", "autosave_period:=0.3", "status_period:=5.0")
    try:
        deadline = time.monotonic() + 30
        while not weights.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        first_seen = time.monotonic()
        assert weights.exists(), "no autosave within 30 s"
        stamps = set()
        while time.monotonic() - first_seen < 2.0:
            stamps.add(weights.stat().st_mtime_ns)
            time.sleep(0.05)
    finally:
        _, err = stop(identifier)
    assert len(stamps) >= 3  # saved again and again within 2 s, though status comes every 5 s

    def refuse(constant: str):
        raise AssertionError(f"non-JSON constant {constant} in the status line")

    line = next(line for line in err.splitlines() if line.startswith("identifier: {"))
    status = json.loads(line.split(": ", 1)[1], parse_constant=refuse)
    assert status["phase_nmse_db"] is None and status["counters"]["samples"] == 0


def test_learnt_scales_are_saved_with_the_weights_and_a_restart_needs_no_scales(tmp_path: Path, domain: int) -> None:
    """weights_out of a run that learnt its scales by the warm-up holds them; weights_in alone restarts on them."""
    from rosutil import Talker

    from lenn_ros.core.networks import read_weights_file

    weights = tmp_path / "learnt.npz"
    identifier = start_node("identifier", "scale_warm_up:=0.5", "sample_period:=0.01", f"weights_out:={weights}")
    talker = Talker(domain)
    listener = Listener(domain)
    try:
        deadline = time.monotonic() + 30  # the listener's and the identifier's subscriptions
        while min(publisher.get_subscription_count() for publisher in talker.pubs) < 2:
            assert time.monotonic() < deadline, "the identifier never subscribed"
            time.sleep(0.05)
        talker.publish(400)
        learnt = listener.wait_status(lambda s: s.get("scaling", {}).get("state") == "learnt", timeout=30)["scaling"]
    finally:
        listener.close()
        talker.close()
        _, err = stop(identifier)
    header, _ = read_weights_file(weights)
    assert header["scaling"]["y_scale"] == pytest.approx(learnt["y_scale"], rel=1e-12)
    assert header["scaling"]["u_offset"] == pytest.approx(learnt["u_offset"], rel=1e-12)
    restarted = start_node("identifier", f"weights_in:={weights}")
    listener = Listener(domain)
    try:
        status = listener.wait_status(lambda s: True, timeout=30)
    finally:
        listener.close()
        _, err = stop(restarted)
    assert status["scaling"]["state"] == "given", status["scaling"]
    line = next((line for line in err.splitlines() if "weights_in: loaded" in line), "")
    assert "scales from the file" in line and f"y_scale {header['scaling']['y_scale']:.6g}" in line, err
