"""Defaults for a robot, over DDS: the README's short command alone identifies a pendulum joint.

Real processes: ``robot_controller`` (torque steps of +-2 N m, Float64MultiArray, 50 Hz)
drives ``robot_simulator`` (a friction joint in radians, JointState at 100 Hz); the
identifier is given the remaps, types, fields, pairing and sample period and nothing
else. Its scales are learnt from the first 10 s (one log line, ``status["scaling"]``)
and its one-step error in a test phase (learning:=false after 30 s) must be good: with
the old default (the paper's preset, raw units) the same command clipped thousands of
network inputs.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")

from rosutil import REPO, Listener, ParameterClient, final_status, start_node, stop  # noqa: E402
from test_robot import finish  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.timeout(240)]

REMAPS = ("-r", "u:=cmd", "-r", "y_p:=joint_states")
README_COMMAND = [
    "u_type:=std_msgs/msg/Float64MultiArray",
    "u_field:=data[0]",
    "y_type:=sensor_msgs/msg/JointState",
    "y_field:=position[joint1]",
    "pairing:=sample",
    "sample_period:=0.01",
]


def test_the_defaults_alone_identify_a_joint(tmp_path: Path, domain: int) -> None:
    bag = tmp_path / "joint_run"
    recorder = start_node(
        "recorder", f"output:={bag}", "u_type:=std_msgs/msg/Float64MultiArray",
        "y_type:=sensor_msgs/msg/JointState", "flush_period:=0.5", ros_args=REMAPS,
    )  # fmt: skip
    identifier = start_node("identifier", *README_COMMAND, "status_period:=0.5", ros_args=REMAPS)
    listener = Listener(domain)
    controller = start_node(
        "robot_controller", "seed:=7", "rate_hz:=50.0", "signal:=steps", "amplitude:=2.0", "duration:=80.0"
    )
    driver = start_node(
        "robot_simulator", "seed:=7", "plant:=friction_joint", "rate_hz:=100.0", "start_delay:=2.0",
        "duration:=60.0", "loss:=0.01", "noise_db:=-300.0", "measurement_noise:=0.0002",
    )  # fmt: skip
    try:
        learnt = listener.wait_status(lambda s: s["scaling"]["state"] == "learnt", timeout=90)
        listener.wait_status(lambda s: s["counters"]["learned"] >= 3000, timeout=90)  # 30 s of training
        with ParameterClient(domain) as client:
            assert client.set("learning", False).successful  # the test phase: frozen weights, one-step
        driver_code, driver_err = finish(driver, 120)
    finally:
        listener.close()
        stop(controller)
        _, err = stop(identifier)
        stop(recorder)
    assert driver_code == 0, driver_err
    scaling = learnt["scaling"]
    assert scaling["samples"] == 1000 and 0.5 < scaling["y_scale"] < 5.0 and 2.0 < scaling["u_scale"] < 6.0
    lines = [line for line in err.splitlines() if "scales learnt from the first 1000 samples" in line]
    assert len(lines) == 1 and "y_scale" in lines[0] and "u_scale" in lines[0], err[-3000:]
    status = final_status(err)
    print(f"defaults on a joint: test {status['phase_nmse_db']:.1f} dB over {status['phase_samples']} samples, "
          f"scaling {status['scaling']}, clipped {status['counters']['clipped_inputs']}")  # fmt: skip
    assert status["scaling"] == scaling
    assert not status["learning"] and status["phase_samples"] > 500 and status["phase_nmse_db"] < -30.0
    assert status["counters"]["clipped_inputs"] < 100 and status["counters"]["diverged"] == 0

    # offline, from the recording alone (its identifier_config and samples): the same decision, the same scales
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "evaluate", str(bag), "--test-from", "3001", "--json"],
        capture_output=True, text=True, timeout=300, check=False, cwd=REPO,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    said = [notice for notice in json.loads(done.stdout)["notices"] if notice.startswith("scales: ")]
    assert len(said) == 1 and numbers(said[0]) == numbers(lines[0].split("]: ", 1)[1]), (said, lines)


def numbers(text: str) -> list[str]:
    """The figures of a line (the topics are named as each side knows them: /cmd live, u offline)."""
    return re.findall(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?", text)
