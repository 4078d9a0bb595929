"""A robot's whole loop: identify live, record, ``lenn-ros fit BAG``, restart the identifier from the model.

Real processes over DDS: ``robot_controller`` (Float64MultiArray torques, 50 Hz,
BEST_EFFORT, no header) drives ``robot_simulator`` (a joint with friction and stiction,
JointState at 200 Hz, stamped, some measurements lost); the identifier reads them in
``sample`` mode with the remaps and fields a user gives, and the recorder records
everything. ``fit`` then builds a model from the bag alone (no flags: the bag's
identifier_config says what the topics mean), and a fresh identifier started with the
same remaps and nothing but the fitted params file must pair and predict well from
its first samples, on a new run of the robot.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rosutil import start_node, stop  # noqa: E402
from test_robot import finish  # noqa: E402

from lenn_ros import topics  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(400)]

PERIOD = 0.005
REMAPS = ("-r", "u:=cmd", "-r", "y_p:=joint_states")
ON_THE_ROBOT = [
    "pairing:=sample",
    f"sample_period:={PERIOD}",
    "u_type:=std_msgs/msg/Float64MultiArray",
    "u_field:=data[0]",
    "y_type:=sensor_msgs/msg/JointState",
    "y_field:=position[joint1]",
    "status_period:=0.5",
]


def robot(seed: int, seconds: float) -> tuple[subprocess.Popen, subprocess.Popen]:
    controller = start_node(
        "robot_controller", f"seed:={seed}", "rate_hz:=50.0", "signal:=steps", "amplitude:=2.0",
        f"duration:={seconds + 10}",
    )  # fmt: skip
    driver = start_node(
        "robot_simulator", f"seed:={seed}", "plant:=friction_joint", f"rate_hz:={1 / PERIOD}", "start_delay:=2.0",
        f"duration:={seconds}", "loss:=0.01", "noise_db:=-300.0", "measurement_noise:=0.0002",
    )  # fmt: skip
    return controller, driver


class StatusWatch:
    """The identifier's status messages, with the time each arrived."""

    def __init__(self, domain_id: int) -> None:
        from std_msgs.msg import String

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("status_watch", context=self.ctx)
        self.seen: list[tuple[float, dict]] = []
        self.node.create_subscription(
            String, topics.STATUS, lambda m: self.seen.append((time.monotonic(), json.loads(m.data))), topics.data_qos()
        )
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def first_paired(self, timeout: float) -> float:
        """When the first status with a paired sample came."""
        deadline = time.monotonic() + timeout
        tick = threading.Event()
        while time.monotonic() < deadline:
            for when, status in self.seen:
                if status["counters"].get("paired", 0) > 0:
                    return when
            tick.wait(0.1)
        raise AssertionError(f"no paired sample within {timeout} s: {self.seen[-1:] or 'no status'}")

    def status_after(self, since: float, seconds: float) -> dict:
        deadline = since + seconds
        tick = threading.Event()
        while time.monotonic() < deadline + 5 and not any(when >= deadline for when, _ in self.seen):
            tick.wait(0.1)
        return next(status for when, status in self.seen if when >= deadline)

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(timeout=5)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def test_record_fit_the_bag_and_restart_the_identifier_from_the_model(tmp_path: Path, domain: int) -> None:
    bag = tmp_path / "elbow_run1"
    recorder = start_node(
        "recorder", f"output:={bag}", "u_type:=std_msgs/msg/Float64MultiArray",
        "y_type:=sensor_msgs/msg/JointState", "flush_period:=0.5", ros_args=REMAPS,
    )  # fmt: skip
    identifier = start_node("identifier", *ON_THE_ROBOT, ros_args=REMAPS)
    controller, driver = robot(seed=4, seconds=45.0)
    try:
        driver_code, driver_err = finish(driver, 120)
    finally:  # the recorder drains what DDS still holds before it closes the bag
        stop(identifier)
        stop(controller)
        stop(recorder)
    assert driver_code == 0, driver_err
    model = tmp_path / "model"
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(bag), "--test-from", "7001", "--json", "-o", str(model)],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    print(
        f"fit from the bag: {report['data']}; {report['model']['family']} {report['model']['n_terms']} terms; "
        f"test one-step {report['nmse_db']:.2f} dB, free run {report['nmse_free_run_db']:.2f} dB"
    )
    assert report["nmse_free_run_db"] < -20.0
    # a new run of the robot; the identifier knows only the remaps and the fitted params file
    watch = StatusWatch(domain)
    restarted = start_node("identifier", params_file=model / "params.yaml", ros_args=REMAPS)
    controller, driver = robot(seed=5, seconds=20.0)
    try:
        first = watch.first_paired(timeout=60)
        status = watch.status_after(first, 10.0)
    finally:
        finish(driver, 60)
        stop(restarted)
        stop(controller)
        watch.close()
    print(f"restarted identifier, 10 s after its first sample: {status['phase_nmse_db']} dB, {status['counters']}")
    assert status["counters"]["paired"] >= 0.9 * 10 / PERIOD
    assert status["phase_nmse_db"] is not None and status["phase_nmse_db"] <= -25.0
