"""A robot with two joints, recorded while the identifier ran, fitted from the bag, restarted from the model.

Real processes over DDS: ``bench/mimo_robot.py`` is the robot (at 50 Hz: a controller's
Float64MultiArray command without header (RELIABLE), a driver's stamped JointState listing
``[j2, wrist, j1]`` (BEST_EFFORT), the 2x2 plant ``narendra2x2``, 1 % of the
measurements lost and a 0.2 s stall of the driver); the identifier reads it in
``sample`` mode with ``u_field data[*]`` / ``u_names`` and ``y_field position[*]`` /
``y_names [j1, j2]`` (another order than the driver's), remapped onto the robot's
topics, while the recorder records. ``lenn-ros fit BAG --test-from K -o model`` (a real
subprocess, no flags: the bag's identifier_config says what the topics mean) must fit
the vectors the node's session pairs, never across the gaps, and write a params file
from which a fresh identifier, given the same remaps and nothing else, pairs and
predicts both joints from its first samples on a new run of the robot.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")

from rosutil import REPO, start_node, stop  # noqa: E402
from test_fit_robot_live import StatusWatch  # noqa: E402
from test_robot import finish  # noqa: E402

from lenn_ros.service.params import read_params_file  # noqa: E402

pytestmark = [
    pytest.mark.ros,
    pytest.mark.slow,
    pytest.mark.timeout(420),
    # its robot (bench/mimo_robot.py, one process) skips late steps on a loaded 2-core machine and the
    # recorded pairs stop matching the plant: 2 of 3 full-suite runs passed, one fitted j2 at -25.7 dB
    # against the -28 dB bound. Run it with LENN_ROS_TIMING_TESTS=1 until a multi-joint robot_simulator
    # (a driver that applies only the commands it received) replaces that script.
    pytest.mark.skipif(
        os.environ.get("LENN_ROS_TIMING_TESTS") != "1",
        reason="timing-dependent robot script (set LENN_ROS_TIMING_TESTS=1): see the comment above",
    ),
]

#: 50 Hz: a command is timed when it is received, the measurement by its stamp, so the command must arrive
#: within one period of being sent; at 100 Hz on the shared 2-core machine some arrived later, were paired
#: one sample late, and one run fitted y2 at -21 dB
PERIOD = 0.02
REMAPS = ("-r", "u:=/robot/cmd", "-r", "y_p:=/robot/joint_states")
#: how the identifier reads the robot: what the fitted params file must say again
INTERPRETATION = {
    "u_type": "std_msgs/msg/Float64MultiArray",
    "u_field": "data[*]",
    "u_names": ["u1", "u2"],
    "y_type": "sensor_msgs/msg/JointState",
    "y_field": "position[*]",
    "y_names": ["j1", "j2"],
    "pairing": "sample",
    "sample_period": PERIOD,
}
#: the identifier that runs while the bag is recorded: a MIMO LeNN learning from scratch
RECORDING = {
    **INTERPRETATION,
    "example": 0,
    "network": "lenn",
    "y_scales": [2.0, 1.6],
    "u_scale": 1.0,
    "y_lags": 1,
    "u_lags": 1,
    "order": 4,
    "cross_degree": 3,
    "solver": "rls",
    "forgetting": 1.0,
    "output": "linear",
    "status_period": 0.5,
}
SECONDS, TEST_FROM = 40.0, 1601  # 2000 steps; the stall at 20 s, in the training part
#: live one-step NMSE, per joint, of the restarted identifier 10 s after its first sample: the issue's
#: criterion. Measured (100 Hz, BEST_EFFORT command): -36.8 / -31.8 dB; (50 Hz, RELIABLE command): -36.4 /
#: -31.5 dB; but -21.0 / -21.7 dB in a run where the shared machine made the robot process skip steps:
#: the in-process robot's timing under load, not the fit, is what this bound still depends on
BOUND_DB = {"j1": -25.0, "j2": -25.0}


def robot(seed: int, seconds: float, readers: int, *extra: str) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    command = [sys.executable, str(REPO / "bench" / "mimo_robot.py"), "--seed", str(seed), "--seconds", str(seconds)]
    command += ["--rate", str(1 / PERIOD), "--subscribers", str(readers), *extra]
    return subprocess.Popen(command, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("seed", [1, 2])
def test_fit_a_two_joint_robot_bag_and_restart_the_identifier_from_the_model(
    tmp_path: Path, domain: int, seed: int
) -> None:
    bag, params = tmp_path / "arm_run1", tmp_path / "recording.json"
    params.write_text(json.dumps({"/**": {"ros__parameters": RECORDING}}))
    recorder = start_node(
        "recorder", f"output:={bag}", "mimo:=true", f"u_type:={INTERPRETATION['u_type']}",
        f"y_type:={INTERPRETATION['y_type']}", "flush_period:=0.5", ros_args=REMAPS,
    )  # fmt: skip
    identifier = start_node("identifier", params_file=params, ros_args=REMAPS)
    driver = robot(seed, SECONDS, 2, "--stall-at", "20")  # the identifier and the recorder read it
    try:
        code, driver_err = finish(driver, 180)
    finally:  # the recorder drains what DDS still holds before it closes the bag
        _, recording_err = stop(identifier)
        _, recorder_err = stop(recorder)
    assert code == 0, driver_err
    assert "[ERROR]" not in recorder_err + recording_err, recorder_err + recording_err

    model = tmp_path / "model"
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(bag), "--test-from", str(TEST_FROM), "--json", "-o",
         str(model)],
        capture_output=True, text=True, timeout=600, check=False, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    one_step = {o["name"]: round(o["nmse_db"], 2) for o in report["per_output"]}
    print(f"fit: {report['data']}; lags {report['model']['y_lags']} order {report['model']['order']}; {one_step}")
    print(f"fit, SISO per output: {[round(o['nmse_db'], 2) for o in report['comparison']['per_output']]}")
    assert "/robot/joint_states position[*]" in report["data"] and "paired by sample" in report["data"]
    assert report["inputs"] == ["u1", "u2"] and report["outputs"] == ["j1", "j2"]
    assert report["model"]["gaps"] >= 1  # the stall (and lost measurements): never joined across
    # every measurement the driver published is at most one sample (BEST_EFFORT may lose a few)
    published = int(re.search(r"(\d+) measurements published", driver_err).group(1))
    paired = report["train_samples"] + report["samples"]
    print(f"published {published}, paired {paired}")
    assert 0.99 * published <= paired <= published, (published, driver_err)
    assert all(o["nmse_db"] < -28.0 for o in report["per_output"]), one_step
    siso = report["comparison"]["per_output"]
    assert all(o["nmse_db"] < c["nmse_db"] for o, c in zip(report["per_output"], siso, strict=True))  # coupled
    values = read_params_file(model / "params.yaml")
    assert {key: values[key] for key in INTERPRETATION} == INTERPRETATION

    # a new run of the robot; the identifier knows only the remaps and the fitted params file
    watch = StatusWatch(domain)
    restarted = start_node("identifier", params_file=model / "params.yaml", ros_args=REMAPS)
    driver = robot(seed + 10, 20.0, 1)
    try:
        first = watch.first_paired(timeout=60)
        status = watch.status_after(first, 10.0)
    finally:
        finish(driver, 90)
        stop(restarted)
        watch.close()
    live = {name: channel["phase_nmse_db"] for name, channel in status["channels"].items()}
    print(f"restarted identifier, 10 s after its first sample: {live}, paired {status['counters']['paired']}")
    assert status["counters"]["paired"] >= 0.9 * 10 / PERIOD and status["counters"]["field_errors"] == 0
    assert status["y_channels"] == ["j1", "j2"] and status["u_channels"] == ["u1", "u2"]
    for name, bound in BOUND_DB.items():
        assert live[name] is not None and live[name] <= bound, (name, live)
