"""The identifier on a robot's own topics, as a new user connects it: real processes over DDS.

Command and measurement come from *different* nodes, as stamped or vector messages,
BEST_EFFORT or not; each way it can go wrong must be said in one line and counted.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import threading
import time
from pathlib import Path

import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rosutil import REPO, final_status, start_node, stop  # noqa: E402

from lenn_ros import topics  # noqa: E402

pytestmark = pytest.mark.timeout(180)


class Graph:
    """In-test publisher nodes (each its own node, as a controller and a driver are)."""

    def __init__(self, domain_id: int) -> None:
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.nodes = []
        self.status: dict = {}
        self.diagnostics: list = []
        self.stamped: list = []
        self.thread: threading.Thread | None = None

    def node(self, name: str):
        node = rclpy.create_node(name, context=self.ctx)
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def lockstep(self, name: str):
        """(u, y_p) Float64 publishers of one node, as a lockstep plant has them (``sequence`` pairing)."""
        from std_msgs.msg import Float64

        node = self.node(name)
        return tuple(node.create_publisher(Float64, topic, topics.data_qos()) for topic in (topics.U, topics.Y_P))

    def listen(self, namespace: str = "") -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        node = self.node("test_listener")
        prefix = namespace.rstrip("/") + "/" if namespace else ""
        node.create_subscription(
            String, prefix + topics.STATUS, lambda m: self.status.update(json.loads(m.data)), topics.data_qos()
        )
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self.diagnostics.append, 10)
        node.create_subscription(JointState, prefix + topics.Y_HAT_STAMPED, self.stamped.append, topics.data_qos())

    def spin(self) -> None:
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def wait(self, condition, timeout: float = 30.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.status and condition(self.status):
                return self.status
            time.sleep(0.1)
        raise AssertionError(f"status never satisfied the condition; last: {self.status}")

    def ready(self, *publishers, timeout: float = 30.0) -> dict:
        """The identifier is up and each of our ``publishers`` is matched both ways: it counts the
        identifier's subscription, and the identifier's ``status["publishers"]`` counts it. A message
        published before that is lost to discovery, which has nothing to do with what a test checks."""
        deadline = time.monotonic() + timeout
        status = self.wait(
            lambda s: all(s.get("publishers", {}).get(p.topic_name, 0) >= 1 for p in publishers), timeout
        )
        while any(p.get_subscription_count() < 1 for p in publishers):
            assert time.monotonic() < deadline, [(p.topic_name, p.get_subscription_count()) for p in publishers]
            time.sleep(0.05)
        return status

    def close(self) -> None:
        self.executor.shutdown()
        if self.thread is not None:
            self.thread.join(timeout=5)
        for node in self.nodes:
            node.destroy_node()
        self.ctx.try_shutdown()


@pytest.fixture
def graph(domain: int):
    g = Graph(domain)
    yield g
    g.close()


def publish_for(seconds: float, rate: float, publish, at_least: int = 0) -> None:
    """``publish(k)`` about ``rate`` times a second for ``seconds``, and on until ``at_least`` were sent (a loaded
    machine slows the loop: a test that waits for a count must not depend on the time it had)."""
    start = time.monotonic()
    k = 0
    while time.monotonic() - start < seconds or k < at_least:
        publish(k)
        k += 1
        time.sleep(1.0 / rate)


def test_separate_publishers_are_refused_in_sequence_mode(graph: Graph) -> None:
    """u from a controller, y_p from a driver, 0.5 s apart: sequence mode must not pair them."""
    from std_msgs.msg import Float64

    identifier = start_node("identifier", "status_period:=0.2")
    u_pub = graph.node("controller").create_publisher(Float64, topics.U, topics.data_qos())
    y_pub = graph.node("driver").create_publisher(Float64, topics.Y_P, topics.data_qos())
    graph.listen()
    graph.spin()
    try:
        graph.ready(u_pub, y_pub)  # the identifier is up, our publishers matched
        publish_for(0.5, 100, lambda k: u_pub.publish(Float64(data=0.1 * (k % 7))))
        publish_for(3.0, 100, lambda k: (u_pub.publish(Float64(data=0.1)), y_pub.publish(Float64(data=0.2))))
        status = graph.wait(lambda s: s["counters"]["refused"] > 50)
    finally:
        _, err = stop(identifier)
    assert status["counters"]["learned"] == 0 and "different nodes" in status["refused"]
    assert "come from different nodes" in err and "pairing:=sample" in err
    assert final_status(err)["counters"]["learned"] == 0
    from diagnostic_msgs.msg import DiagnosticStatus

    levels = {status.level for array in graph.diagnostics for status in array.status}
    assert DiagnosticStatus.ERROR in levels  # standard tools show the refusal too


def test_best_effort_publisher_is_reported_with_the_fix_then_accepted(graph: Graph) -> None:
    from std_msgs.msg import Float64

    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    identifier = start_node("identifier", "status_period:=0.2")
    publisher = graph.node("sensor").create_publisher(Float64, topics.U, best_effort)
    graph.listen()
    graph.spin()
    try:
        publish_for(2.0, 50, lambda k: publisher.publish(Float64(data=0.1)))
        graph.wait(lambda s: s["counters"]["qos_incompatible"] >= 1, timeout=20)
    finally:
        _, err = stop(identifier)
    assert "qos_overrides./u.subscription.reliability:=best_effort" in err
    # the fix, as the warning words it
    graph.status.clear()
    fixed = start_node("identifier", "status_period:=0.2", "qos_overrides./u.subscription.reliability:=best_effort")
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not graph.status.get("counters", {}).get("u_messages"):
            publisher.publish(Float64(data=0.1))
            time.sleep(0.02)
    finally:
        _, err = stop(fixed)
    assert final_status(err)["counters"]["u_messages"] > 0
    assert final_status(err)["counters"]["qos_incompatible"] == 0


def test_u_without_y_p_is_said_and_counted(graph: Graph) -> None:
    from std_msgs.msg import Float64

    identifier = start_node("identifier", "status_period:=0.2", "lone_timeout:=1.0")
    publisher = graph.node("controller").create_publisher(Float64, topics.U, topics.data_qos())
    graph.listen()
    graph.spin()
    try:
        graph.ready(publisher)  # the identifier is up, our publishers matched
        publish_for(4.0, 50, lambda k: publisher.publish(Float64(data=0.1)))
        graph.wait(lambda s: s["counters"]["lone_u"] > 20, timeout=20)
    finally:
        _, err = stop(identifier)
    assert "/u has been arriving alone" in err and "nothing on /y_p" in err


def test_inputs_that_stop_are_said_and_their_return_too(graph: Graph) -> None:
    """A driver publishing both inputs goes quiet with its publishers still matched: after silence_timeout the
    node says so in one line, counts it, and its status and diagnostics show it until data comes back."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from std_msgs.msg import Float64

    identifier = start_node("identifier", "status_period:=0.2", "silence_timeout:=1.0")
    u, y = graph.lockstep("driver")
    graph.listen()
    graph.spin()

    def both(k: int) -> None:
        u.publish(Float64(data=0.1 * (k % 7)))
        y.publish(Float64(data=0.05 * (k % 5)))

    try:
        graph.ready(u, y)
        publish_for(1.0, 50, both)
        silent = graph.wait(lambda s: s["silent_since"] is not None, timeout=20)
        assert silent["counters"]["silences"] == 1 and silent["counters"]["u_messages"] > 20

        def warned() -> list:  # the diagnostics say it for as long as it lasts
            return [d.status[0] for d in graph.diagnostics if "silence_timeout" in d.status[0].message]

        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not warned():
            time.sleep(0.1)
        warned = warned()
        assert warned and warned[-1].level == DiagnosticStatus.WARN, [d.status[0].message for d in graph.diagnostics]
        publish_for(0.5, 50, both)
        back = graph.wait(lambda s: s["silent_since"] is None, timeout=20)
        assert back["counters"]["silences"] == 1
    finally:
        _, err = stop(identifier)
    assert "nothing on /u or /y_p for 1." in err and "s (silence_timeout 1 s)" in err, err[-2000:]
    assert "/u arrived again after" in err and "without data: learning goes on" in err, err[-2000:]


def test_y_p_whose_field_cannot_be_read_is_said_as_such_not_as_silence(graph: Graph) -> None:
    """JointStates arrive but y_field names a joint they lack: the lone-u line names the field and the error."""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64

    identifier = start_node(
        "identifier", "status_period:=0.2", "lone_timeout:=1.0", "pairing:=sample", "sample_period:=0.02",
        "y_type:=sensor_msgs/msg/JointState", "y_field:=position[joint1]",
    )  # fmt: skip
    u_pub = graph.node("controller").create_publisher(Float64, topics.U, topics.data_qos())
    y_pub = graph.node("driver").create_publisher(JointState, topics.Y_P, topics.data_qos())
    graph.listen()
    graph.spin()
    try:
        graph.ready(u_pub, y_pub)  # the identifier is up, our publishers matched
        publish_for(4.0, 50, lambda k: (u_pub.publish(Float64(data=0.1)),
                                        y_pub.publish(JointState(name=["pendulum"], position=[0.2]))))  # fmt: skip
        status = graph.wait(lambda s: s["counters"]["lone_u"] > 20 and s["counters"]["field_errors"] > 20, timeout=20)
    finally:
        _, err = stop(identifier)
    assert "nothing on /y_p" not in err, err
    assert "messages arrived on /y_p but their field could not be read: y_field position[joint1]" in err, err
    assert "no joint 'joint1'" in err and status["counters"]["learned"] == 0


def test_pairs_held_for_missing_readers_are_said_and_counted(graph: Graph) -> None:
    """wait_for_error_subscribers:=2 with no reader of error: nothing learnt, and the node says why."""
    from std_msgs.msg import Float64

    identifier = start_node("identifier", "status_period:=0.2", "wait_for_error_subscribers:=2")
    u_pub, y_pub = graph.lockstep("plant")
    graph.listen()
    graph.spin()
    try:
        graph.ready(u_pub, y_pub)  # the identifier is up, our publishers matched
        publish_for(7.0, 50, lambda k: (u_pub.publish(Float64(data=0.1)), y_pub.publish(Float64(data=0.2))))
        status = graph.wait(lambda s: s["held"] > 100)
    finally:
        _, err = stop(identifier)
    assert status["counters"]["learned"] == 0 and status["readers"]["error"] == 0
    assert "pairs held, not learnt" in err and "error has 0 of 2 readers" in err, err[-2000:]
    assert "stopping with" in err and "pairs held, not learnt: the outputs' readers" in err, err[-2000:]


@pytest.mark.parametrize("remap", [("-r", "__ns:=/id3"), ("-r", "__node:=ident3")])
def test_params_file_applies_under_any_namespace_or_node_name(tmp_path: Path, domain: int, remap) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"example": 3, "network": "lenn"}}}))
    identifier = start_node("identifier", params_file=params, ros_args=remap)
    try:
        said = _wait_for_output(identifier, "paired by", timeout=60.0)  # its start-up line is all this test reads
    finally:
        _, err = stop(identifier)
    assert "example preset 3" in said + err, said + err


def _wait_for_output(process: subprocess.Popen, text: str, timeout: float) -> str:
    """The process's stderr up to (at least) the first line holding ``text``: a poll, not a guessed sleep."""
    fd, seen = process.stderr.fileno(), b""
    deadline = time.monotonic() + timeout
    while text.encode() not in seen:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"no {text!r} within {timeout} s:\n{seen.decode()[-2000:]}"
        ready, _, _ = select.select([fd], [], [], remaining)
        chunk = os.read(fd, 65536) if ready else b""
        assert chunk or not ready, f"the process ended without {text!r}:\n{seen.decode()[-2000:]}"
        seen += chunk
    return seen.decode()


def test_wrong_type_or_field_is_one_line_at_start(graph: Graph) -> None:
    from sensor_msgs.msg import JointState

    publisher = graph.node("driver").create_publisher(JointState, topics.U, topics.data_qos())
    graph.spin()
    deadline = time.monotonic() + 10
    while not graph.nodes[0].get_publishers_info_by_topic("/u") and time.monotonic() < deadline:
        time.sleep(0.1)
    identifier = start_node("identifier")
    try:
        _, err = identifier.communicate(timeout=30)
    finally:
        if identifier.poll() is None:
            stop(identifier)
    assert identifier.returncode == 2
    assert "/u is published as sensor_msgs/msg/JointState, not u_type std_msgs/msg/Float64" in err
    assert "Traceback" not in err
    del publisher
    bad_field = start_node("identifier", "y_type:=sensor_msgs/msg/JointState", "y_field:=positions[0]")
    _, err = bad_field.communicate(timeout=30)
    assert bad_field.returncode == 2 and "JointState has no field 'positions'" in err
    assert len(err.strip().splitlines()) == 1
    indexed = start_node("identifier", "u_field:=data[1]")  # u_type left at its default, Float64
    _, err = indexed.communicate(timeout=30)
    assert indexed.returncode == 2 and "u_type:=std_msgs/msg/Float64MultiArray" in err, err
    assert len(err.strip().splitlines()) == 1


def test_stamped_vector_topics_pair_by_stamp_and_outputs_carry_the_sample_time(graph: Graph) -> None:
    """PointStamped command and JointState measurement from two nodes, paired by header stamp."""
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState

    identifier = start_node(
        "identifier",
        "status_period:=0.2",
        "pairing:=stamp",
        "u_type:=geometry_msgs/msg/PointStamped",
        "u_field:=point.x",
        "y_type:=sensor_msgs/msg/JointState",
        "y_field:=position[elbow]",
        "scale_warm_up:=2.0",  # (no sample_period: 100 samples, then all of them are learnt)
        ros_args=("-r", "u:=/robot/cmd", "-r", "y_p:=/robot/joint_states"),
    )
    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    u_pub = graph.node("controller").create_publisher(PointStamped, "/robot/cmd", best_effort)
    y_pub = graph.node("driver").create_publisher(JointState, "/robot/joint_states", topics.data_qos())
    graph.listen()
    graph.spin()
    sent = []
    try:
        graph.ready(u_pub, y_pub)  # the identifier is up, our publishers matched
        for k in range(300):
            stamp = graph.nodes[0].get_clock().now().to_msg()
            command = PointStamped()
            command.header.stamp = stamp
            command.point.x = 0.5 * ((k * 7919) % 13 / 13.0 - 0.5)
            measurement = JointState(name=["shoulder", "elbow"], position=[9.0, 0.3 * command.point.x])
            measurement.header.stamp = stamp
            y_pub.publish(measurement)
            u_pub.publish(command)
            sent.append(stamp.sec + stamp.nanosec * 1e-9)
            time.sleep(0.01)
        status = graph.wait(lambda s: s["counters"]["paired"] >= 280, timeout=20)
    finally:
        stop(identifier)
    assert status["counters"]["misaligned"] == 0 and status["counters"]["learned"] > 250
    stamps = {m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in graph.stamped}
    assert len(stamps) > 250
    assert all(any(abs(s - t) < 1e-6 for t in sent) for s in stamps)
    assert graph.stamped[0].name == ["/robot/joint_states"]


def test_each_kind_of_warning_has_its_own_throttle(graph: Graph) -> None:
    """NaN on u and u arriving alone, with a 60 s throttle: each said once, neither hides the other."""
    from std_msgs.msg import Float64

    identifier = start_node("identifier", "status_period:=0.2", "lone_timeout:=1.0", "warn_period:=60.0")
    publisher = graph.node("controller").create_publisher(Float64, topics.U, topics.data_qos())
    graph.listen()
    graph.spin()
    try:
        graph.ready(publisher)  # the identifier is up, our publishers matched
        publish_for(3.0, 50, lambda k: publisher.publish(Float64(data=float("nan"))))
        graph.wait(lambda s: s["counters"]["lone_u"] > 10 and s["counters"]["nan"] > 50, timeout=20)
    finally:
        _, err = stop(identifier)
    nan_lines = [line for line in err.splitlines() if "u = nan" in line]
    lone_lines = [line for line in err.splitlines() if "arriving alone" in line]
    assert len(nan_lines) == 1 and len(lone_lines) == 1, err


def test_params_file_for_another_node_name_is_said(graph: Graph) -> None:
    """The shipped files address /**/identifier: under -r __node:=ident3 they apply to nothing (rclpy is silent)."""
    graph.listen()
    graph.spin()
    identifier = start_node(
        "identifier",
        "status_period:=0.2",
        params_file=REPO / "config" / "example3_lenn.yaml",
        ros_args=("-r", "__node:=ident3"),
    )
    try:
        graph.wait(lambda status: status["counters"]["unknown_parameters"] >= 1)
    finally:
        _, err = stop(identifier)
    assert "params file" in err and "has no section for this node (/ident3" in err, err
    assert "'/**/ident3:'" in err
    assert final_status(err)["counters"]["unknown_parameters"] >= 1


def _name(info: object) -> str:
    """The fully qualified name of the node behind a topic endpoint's info."""
    namespace = info.node_namespace.rstrip("/")
    return f"{namespace}/{info.node_name}"


@pytest.mark.parametrize("apart", [False, True], ids=["one participant", "inputs apart"])
def test_qos_overrides_take_durability_and_name_typos(graph: Graph, apart: bool, monkeypatch) -> None:
    from rclpy.qos import DurabilityPolicy

    monkeypatch.setenv("LENN_ROS_INPUTS_PARTICIPANT", "1" if apart else "0")  # apart: declared by us, used there
    identifier = start_node(
        "identifier",
        "pairing:=sample",
        "sample_period:=0.01",
        "qos_overrides./u.subscription.durability:=transient_local",
        "qos_overrides./uu.subscription.reliability:=best_effort",
    )
    probe = graph.node("probe")
    graph.listen()
    graph.spin()
    try:
        owner = graph.wait(lambda s: True)["inputs_node"]  # the node that holds the inputs, as the identifier says
        assert owner == ("/identifier_inputs" if apart else "/identifier")
        deadline = time.monotonic() + 20
        infos: list = []
        while not infos and time.monotonic() < deadline:
            infos = [i for i in probe.get_subscriptions_info_by_topic("/u") if _name(i) == owner]
            time.sleep(0.1)
        assert infos, "the identifier's /u subscription never showed up"
        assert infos[0].qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
    finally:
        _, err = stop(identifier)
    assert "unknown QoS override 'qos_overrides./uu.subscription.reliability' is ignored" in err, err
    assert final_status(err)["counters"]["unknown_parameters"] == 1


@pytest.mark.parametrize("apart", [False, True], ids=["one participant", "inputs apart"])
def test_qos_overrides_by_the_name_before_remapping_apply_to_the_remapped_topic(
    graph: Graph, apart: bool, monkeypatch
) -> None:
    """-r u:=/robot/cmd with the README's qos_overrides./u...: applied to /robot/cmd, not refused as unknown."""
    from rclpy.qos import DurabilityPolicy

    monkeypatch.setenv("LENN_ROS_INPUTS_PARTICIPANT", "1" if apart else "0")  # apart: declared by us, used there
    identifier = start_node(
        "identifier",
        "pairing:=sample",
        "sample_period:=0.01",
        "qos_overrides./u.subscription.durability:=transient_local",
        ros_args=("-r", "u:=/robot/cmd"),
    )
    probe = graph.node("probe")
    graph.listen()
    graph.spin()
    try:
        owner = graph.wait(lambda s: True)["inputs_node"]  # the node that holds the inputs, as the identifier says
        assert owner == ("/identifier_inputs" if apart else "/identifier")
        deadline = time.monotonic() + 20
        infos: list = []
        while not infos and time.monotonic() < deadline:
            infos = [i for i in probe.get_subscriptions_info_by_topic("/robot/cmd") if _name(i) == owner]
            time.sleep(0.1)
        assert infos, "the identifier's /robot/cmd subscription never showed up"
        assert infos[0].qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
    finally:
        _, err = stop(identifier)
    assert "unknown QoS override" not in err, err
    assert "qos_overrides./u.subscription.durability applies to /robot/cmd" in err, err
    assert final_status(err)["counters"]["unknown_parameters"] == 0


def test_a_stalled_driver_is_said_as_a_stall_with_its_length(graph: Graph) -> None:
    """The driver (y_p, 100 Hz) publishes nothing for 0.5 s while the controller goes on: a gap said
    as a stall of about 0.5 s, not as lost messages (none were lost)."""
    import re

    from std_msgs.msg import Float64

    identifier = start_node(
        "identifier", "status_period:=0.2", "pairing:=sample", "sample_period:=0.02", "warn_period:=0.05",
        "y_scale:=1.0", "u_scale:=1.0",  # given: no scale warm-up holding the first 10 s
    )  # fmt: skip
    u_pub = graph.node("controller").create_publisher(Float64, topics.U, topics.data_qos())
    y_pub = graph.node("driver").create_publisher(Float64, topics.Y_P, topics.data_qos())
    graph.listen()
    graph.spin()

    def both(k: int) -> None:
        y_pub.publish(Float64(data=0.01 * (k % 50)))
        if k % 2 == 0:
            u_pub.publish(Float64(data=0.02 * (k % 25)))

    try:
        graph.ready(u_pub, y_pub)  # the identifier is up, our publishers matched
        publish_for(2.0, 100, both)
        publish_for(0.5, 100, lambda k: u_pub.publish(Float64(data=0.1)) if k % 2 == 0 else None)  # the stall
        publish_for(2.0, 100, both)
        graph.wait(lambda s: s["counters"]["gaps"] >= 1, timeout=20)
    finally:
        _, err = stop(identifier)
    stalls = [(int(n), float(t)) for n, t in re.findall(r"a gap of (\d+) samples?, (\d+\.\d+) s without a sample: a "
                                                        r"stall, not a loss", err)]  # fmt: skip
    assert stalls, err
    longest = max(stalls, key=lambda stall: stall[1])
    assert 0.45 < longest[1] < 0.9 and 20 <= longest[0] <= 45, stalls
