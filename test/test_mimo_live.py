"""A two-output plant identified live: the simulator's MIMO plant, two identifier processes over DDS.

One simulator publishes u and y_p as Float64MultiArray; the MIMO identifier (couplings
full) and, in a namespace, one SISO model per output (couplings diagonal) learn from
the same messages (bench/mimo_live.py runs them). Per-channel NMSE over seeds must
show the coupling captured, and equal what the core computes offline from the same seeds.
"""

from __future__ import annotations

from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(300)]

rclpy = pytest.importorskip("rclpy")

from mimo_live import NAMES, run_live, run_offline  # noqa: E402

TRAIN, TEST, NOISE_DB = 3000, 600, -30.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_output_plant_identified_live_beats_one_siso_model_per_output(tmp_path: Path, domain: int, seed: int):
    live = run_live(seed, TRAIN, TEST, NOISE_DB, tmp_path)
    for couplings, status in live.items():
        counters = status["counters"]
        assert counters["paired"] == TRAIN + TEST and counters["lost"] == counters["rejected"] == 0, counters
        assert status["u_channels"] == ["u1", "u2"] and status["y_channels"] == list(NAMES)
        assert status["phase_samples"] == TEST and status["learning"] is False  # frozen at test_start
        offline = run_offline(seed, TRAIN, TEST, NOISE_DB, couplings)
        for name in NAMES:
            assert status["channels"][name]["phase_nmse_db"] == pytest.approx(offline[name], abs=1e-9)
    for name in NAMES:
        mimo = live["full"]["channels"][name]["phase_nmse_db"]
        siso = live["diagonal"]["channels"][name]["phase_nmse_db"]
        assert mimo < siso - 5.0, (name, mimo, siso)


def test_robot_vector_topics_from_two_nodes_are_learnt_per_named_joint(domain: int) -> None:
    """A controller's Float64MultiArray command and a driver's JointState, joints picked by name.

    The driver lists its joints in another order (and one more); the identifier takes the
    named ones (y_names) from ``position[*]``. A command with the wrong number of elements
    is said in one line and counted, never learnt.
    """
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosutil import start_node, stop
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray
    from test_robot_topics import Graph, publish_for

    from lenn_ros import topics

    identifier = start_node(
        "identifier",
        "example:=0",
        "status_period:=0.2",
        "pairing:=sample",
        "sample_period:=0.01",
        "scale_warm_up:=1.0",  # (no scales: each channel's learnt from the first 100 samples)
        "u_type:=std_msgs/msg/Float64MultiArray",
        "u_field:=data[*]",
        "u_names:=[cmd_shoulder, cmd_elbow]",
        "y_type:=sensor_msgs/msg/JointState",
        "y_field:=position[*]",
        "y_names:=[shoulder, elbow]",
        ros_args=("-r", "u:=/robot/cmd", "-r", "y_p:=/robot/joint_states"),
    )
    graph = Graph(domain)
    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    u_pub = graph.node("controller").create_publisher(Float64MultiArray, "/robot/cmd", best_effort)
    y_pub = graph.node("driver").create_publisher(JointState, "/robot/joint_states", topics.data_qos())
    graph.listen()
    graph.spin()

    def send(k: int) -> None:
        a, b = 0.5 * ((k * 7919) % 13 / 13.0 - 0.5), 0.5 * ((k * 104729) % 17 / 17.0 - 0.5)
        u_pub.publish(Float64MultiArray(data=[a, b]))
        state = JointState(name=["elbow", "wrist", "shoulder"], position=[0.3 * a + 0.1 * b, 9.0, 0.5 * a])
        state.header.stamp = graph.nodes[1].get_clock().now().to_msg()  # a driver stamps its measurement
        y_pub.publish(state)

    try:
        graph.ready(u_pub, y_pub)  # the identifier is up, our publishers matched
        publish_for(4.0, 100, send)
        publish_for(0.3, 100, lambda k: u_pub.publish(Float64MultiArray(data=[0.1, 0.2, 0.3])))
        status = graph.wait(lambda s: s["counters"]["learned"] > 400 and s["counters"]["field_errors"] >= 10)
    finally:
        _, err = stop(identifier)
        graph.close()
    assert set(status["channels"]) == {"shoulder", "elbow"} and status["u_channels"] == ["cmd_shoulder", "cmd_elbow"]
    assert graph.stamped and graph.stamped[-1].name == ["shoulder", "elbow"]
    assert "has 3 elements, the model has 2 channels" in err and err.count("has 3 elements") == 1  # said once


def test_a_recorded_mimo_run_evaluates_offline_to_the_live_figures(tmp_path: Path, domain: int) -> None:
    """simulator + MIMO identifier + recorder; ``evaluate`` of the bag gives the live per-channel NMSE."""
    import json as json_module

    from mimo_live import MIMO_VALUES
    from rosutil import final_status, start_node, stop
    from test_bag import independent_read

    from lenn_ros.service.evaluation import evaluate_bag

    values = {**MIMO_VALUES, "seed": 5, "wait_for_y_hat_subscribers": 2, "wait_for_error_subscribers": 1}
    params = tmp_path / "mimo.json"
    params.write_text(json_module.dumps({"/**": {"ros__parameters": values}}))
    bag = tmp_path / "bag"
    recorder = start_node(
        "recorder",
        f"output:={bag}",
        "mimo:=true",
        "u_type:=std_msgs/msg/Float64MultiArray",
        "y_type:=std_msgs/msg/Float64MultiArray",
    )
    identifier = start_node("identifier", params_file=params)
    simulator = start_node(
        "plant_simulator",
        "mimo_plant:=narendra2x2",
        "seed:=5",
        f"train_samples:={TRAIN}",
        f"test_samples:={TEST}",
        f"noise_db:={NOISE_DB}",
        "rate_hz:=0.0",
        "wait_for_subscribers:=2",
        "exit_when_done:=true",
    )
    try:
        _, sim_err = simulator.communicate(timeout=180)
        assert simulator.returncode == 0, sim_err
    finally:
        _, id_err = stop(identifier)
        _, rec_err = stop(recorder)
    live = final_status(id_err)
    assert "[ERROR]" not in rec_err, rec_err
    theirs = independent_read(bag / "bag.mcap")
    assert {t: len(v) for t, v in theirs.items() if t in ("/u", "/y_p", "/y_hat", "/error")} == {
        "/u": TRAIN + TEST, "/y_p": TRAIN + TEST, "/y_hat": TRAIN + TEST, "/error": TRAIN + TEST - 1
    }  # fmt: skip
    offline = evaluate_bag(str(bag))  # the configuration the identifier recorded; its own samples
    assert (
        offline.source == "samples"
        and offline.pairs == TRAIN + TEST
        and all(e.samples == TEST for e in offline.evaluations.values())
    )
    for name in NAMES:
        assert offline.channels[name]["nmse_db"] == pytest.approx(live["channels"][name]["phase_nmse_db"], abs=1e-9)
        assert offline.channels[name]["nmse_free_run_db"] < -15.0  # the joint model runs stably on its own
    # raw messages lost by the recorder change nothing: the samples are what the identifier learnt from
    from test_nodes import copy_bag

    damaged = tmp_path / "damaged"
    copy_bag(bag, damaged, lambda m: not (m.topic == "/u" and m.sequence in (500, 3300)))
    again = evaluate_bag(str(damaged))
    assert again.source == "samples" and again.channels == offline.channels
    # without the samples topic the raw u / y_p are paired by sequence number, as live: the two lost u
    # messages are two lost samples, each restarting the history
    raw = tmp_path / "raw"
    copy_bag(damaged, raw, lambda m: m.topic != "/samples")
    paired = evaluate_bag(str(raw))
    assert paired.source == "u/y_p by sequence" and paired.pairs == TRAIN + TEST - 2 and paired.missing == 2
    # replayed from its samples into a fresh identifier: the live run again, whatever the recorder lost
    from test_replay_pairs import run_replay

    params.write_text(json_module.dumps({"/**": {"ros__parameters": {**values, "wait_for_error_subscribers": 0}}}))
    again_live = start_node("identifier", params_file=params, ros_args=("-p", "wait_for_y_hat_subscribers:=1"))
    try:
        code, _, err = run_replay(damaged)
        said = "replaying the identifier's samples (0 refused live, as NaN): 2 input(s) and 2 output(s), 3600 samples"
        assert code == 0 and said in err, err
    finally:
        _, again_err = stop(again_live)
    replayed = final_status(again_err)
    for name in NAMES:
        assert replayed["channels"][name]["phase_nmse_db"] == live["channels"][name]["phase_nmse_db"]


def test_each_channel_on_its_own_topic_from_its_own_node_is_merged_and_a_silent_one_said(domain: int) -> None:
    """Two command topics from two controllers, two measurement topics from two drivers (BEST_EFFORT)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosutil import final_status, start_node, stop
    from std_msgs.msg import Float64
    from test_robot_topics import Graph, publish_for

    identifier = start_node(
        "identifier",
        "example:=0",
        "status_period:=0.2",
        "pairing:=sample",
        "sample_period:=0.01",
        "scale_warm_up:=1.0",  # (no scales: each channel's learnt from the first 100 samples)
        "u_topics:=[/robot/cmd0, /robot/cmd1]",
        "y_topics:=[/robot/left, /robot/right]",
    )
    graph = Graph(domain)
    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    publishers = {
        topic: graph.node(node).create_publisher(Float64, topic, best_effort)
        for node, topic in (("controller0", "/robot/cmd0"), ("controller1", "/robot/cmd1"),
                            ("driver_left", "/robot/left"), ("driver_right", "/robot/right"))
    }  # fmt: skip
    graph.listen()
    graph.spin()

    def send(k: int, right: bool = True) -> None:
        a, b = 0.5 * ((k * 7919) % 13 / 13.0 - 0.5), 0.5 * ((k * 104729) % 17 / 17.0 - 0.5)
        publishers["/robot/cmd0"].publish(Float64(data=a))
        publishers["/robot/cmd1"].publish(Float64(data=b))
        publishers["/robot/left"].publish(Float64(data=0.5 * a + 0.2 * b))
        if right:
            publishers["/robot/right"].publish(Float64(data=0.3 * b))

    try:
        graph.ready(*publishers.values())  # the identifier is up, our publishers matched
        publish_for(3.0, 100, send, at_least=300)  # (CI, loaded: 243 in 3 s, learned 288 of the 300 waited for)
        learned = graph.wait(lambda s: s["counters"]["learned"] > 300)["counters"]["learned"]
        publish_for(1.0, 100, lambda k: send(k, right=False))  # the right driver has stopped
        status = graph.wait(lambda s: s["counters"]["y_merge_stale"] > 20)
    finally:
        _, err = stop(identifier)
        graph.close()
    final = final_status(err)
    assert final["u_channels"] == ["/robot/cmd0", "/robot/cmd1"] and set(status["channels"]) == {
        "/robot/left",
        "/robot/right",
    }
    assert final["counters"]["u_merged"] > 300 and final["counters"]["y_merged"] > 300
    assert final["counters"]["learned"] < learned + 2 * 60  # the silent topic stops learning (2 outputs)
    assert "/robot/right is older than" in err and "no sample formed" in err, err


def test_the_node_refuses_a_mimo_setting_that_cannot_work_in_one_line(domain: int) -> None:
    from rosutil import start_node

    array = "std_msgs/msg/Float64MultiArray"
    fields = ("u_field:=data[0], data[1]", "y_field:=data[0], data[1]", f"u_type:={array}", f"y_type:={array}")
    node = start_node("identifier", "example:=0", *fields, "couplings:=y0 u9; y1")
    _, err = node.communicate(timeout=60)
    lines = [line for line in err.splitlines() if line.strip()]
    assert node.returncode == 2 and lines[-1].startswith("identifier: couplings of y0: no channel 'u9'"), err


def test_replay_of_a_vector_bag_feeds_a_mimo_identifier_the_recorded_samples(tmp_path: Path, domain: int) -> None:
    """import-csv of several columns, replayed into the MIMO identifier: it learns what evaluate learns."""
    import json as json_module

    from mimo_live import MIMO_VALUES
    from rosutil import final_status, start_node, stop
    from test_replay_pairs import run_replay

    from lenn_ros.bag.csv_import import import_csv
    from lenn_ros.paper.evaluation import simulate_mimo
    from lenn_ros.paper.plants import narendra_mimo_plant
    from lenn_ros.service.evaluation import evaluate_bag

    series = simulate_mimo(narendra_mimo_plant(), -20.0, 6, 1500, 300)
    csv = tmp_path / "log.csv"
    rows = "".join(",".join(repr(float(v)) for v in (*u, *y)) + "\n" for u, y in zip(series.u, series.y, strict=True))
    csv.write_text("u1,u2,y1,y2\n" + rows)
    bag = import_csv(csv, ["u1", "u2"], ["y1", "y2"], 0.01, tmp_path / "bag", test_from=1501)
    params = tmp_path / "mimo.json"
    params.write_text(json_module.dumps({"/**": {"ros__parameters": {**MIMO_VALUES, "wait_for_y_hat_subscribers": 1}}}))
    identifier = start_node("identifier", params_file=params)
    try:
        code, _, err = run_replay(bag)
        assert code == 0, err
        assert (
            "replaying /u, /y_p by order (no sequence numbers recorded): "
            "2 input(s) and 2 output(s), 1800 samples in 1 stream(s)" in err
        )
    finally:
        _, id_err = stop(identifier)
    live = final_status(id_err)
    assert live["counters"]["paired"] == 1800 and live["phase_samples"] == 300
    offline = evaluate_bag(str(bag), str(params))
    for name in NAMES:
        assert live["channels"][name]["phase_nmse_db"] == pytest.approx(offline.channels[name]["nmse_db"], abs=1e-9)
