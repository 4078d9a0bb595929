"""``lenn-ros fit BAG`` on a robot's own topics: paired as the node pairs them, gaps kept, params that restart it.

The bag is a real MCAP written message by message: a driver's JointState at 200 Hz
(two joints, their order changing; the one of interest behind a name), a controller's
Float64MultiArray at 50 Hz without a header, the plant a joint with friction and
stiction, and 0.2 s of the driver's messages lost in the middle. It is read back with
the identifier's configuration from the bag, and without it with the flags that say the
same; the params file fit writes must make the node read the same topics the same way.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from lenn_ros import topics
from lenn_ros.bag.msgtypes import TYPESTORE
from lenn_ros.bag.writer import BagWriter
from lenn_ros.config import resolve
from lenn_ros.paper.physical import FrictionJoint
from lenn_ros.paper.signals import Excitation
from lenn_ros.service.building import NODE_DEFAULTS, build_identifier, make_session
from lenn_ros.service.params import read_params_file
from lenn_ros.service.recording import pair_raw

PERIOD, COMMAND_EVERY, SAMPLES = 0.005, 4, 8000  # 200 Hz driver, 50 Hz controller, 40 s
LOST = range(3000, 3040)  # driver messages never recorded (0.2 s)
INTERPRETATION = {
    "u_type": "std_msgs/msg/Float64MultiArray",
    "u_field": "data[0]",
    "y_type": "sensor_msgs/msg/JointState",
    "y_field": "position[elbow]",
    "pairing": "sample",
    "sample_period": PERIOD,
}


def message(type_name: str, **fields: object) -> object:
    return TYPESTORE.types[type_name](**fields)


def joint_states(k: int, elbow: float, t_ns: int) -> object:
    names, positions = (["wrist", "elbow"], [0.3, elbow]) if k % 2 else (["elbow", "wrist"], [elbow, 0.3])
    stamp = message("builtin_interfaces/msg/Time", sec=t_ns // 10**9, nanosec=t_ns % 10**9)
    return message(
        "sensor_msgs/msg/JointState",
        header=message("std_msgs/msg/Header", stamp=stamp, frame_id=""),
        name=names,
        position=np.array(positions),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )


def command(value: float) -> object:
    layout = message("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
    return message("std_msgs/msg/Float64MultiArray", layout=layout, data=np.array([value, 0.0]))


def write_robot_bag(path: Path, configured: bool, weights_in: str = "") -> np.ndarray:
    """The bag; returns the angles the driver measured (index k: sample k + 1 of the grid).
    ``weights_in``: the weights the recorded identifier started from (in its identifier_config)."""
    excitation = Excitation(3, "steps")
    torques = np.array([2.0 * excitation.sample(k // COMMAND_EVERY)[0] for k in range(SAMPLES)])
    angles = FrictionJoint(period=PERIOD).run(torques)[:SAMPLES]
    angles = np.round((angles + np.random.default_rng(0).normal(0, 2e-4, SAMPLES)) / 1e-4) * 1e-4
    t0 = 1_700_000_000 * 10**9
    with BagWriter(path) as bag:
        bag.add_topic("/arm/cmd", "std_msgs/msg/Float64MultiArray")
        bag.add_topic("/arm/joint_states", "sensor_msgs/msg/JointState")
        if configured:
            bag.add_topic("/identifier_config", "std_msgs/msg/String")
            resolved = {"u": "/arm/cmd", "y_p": "/arm/joint_states"}
            values = {**INTERPRETATION, "network": "lenn", topics.RESOLVED_TOPICS: resolved, "weights_in": weights_in}
            bag.write_message("/identifier_config", message("std_msgs/msg/String", data=json.dumps(values)), t0)
        for k in range(SAMPLES):
            t_ns = t0 + round(k * PERIOD * 1e9)
            if k % COMMAND_EVERY == 0:  # the command applied from step k on, received just before it
                bag.write_message("/arm/cmd", command(torques[k]), t_ns - 1_000_000)
            if k not in LOST:
                bag.write_message("/arm/joint_states", joint_states(k, angles[k], t_ns), t_ns + 3_000_000)
    return angles


def run_fit(bag: Path, out: Path, *flags: str) -> dict:
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(bag), "--test-from", "6001", "--json", "-o", str(out),
         *flags],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


@pytest.mark.slow
@pytest.mark.parametrize("configured", [True, False], ids=["identifier_config", "flags"])
def test_fit_reads_a_robot_bag_as_the_node_pairs_it_and_writes_params_that_read_it_again(
    tmp_path: Path, configured: bool
) -> None:
    bag = tmp_path / "elbow_run1"
    write_robot_bag(bag, configured)
    flags = () if configured else (
        "--u", "/arm/cmd", "--u-field", "data[0]", "--y", "/arm/joint_states", "--y-field", "position[elbow]",
        "--sample-period", str(PERIOD),
    )  # fmt: skip
    report = run_fit(bag, tmp_path / "model", *flags)
    assert "/arm/joint_states position[elbow]" in report["data"] and "paired by sample" in report["data"]
    assert report["choices"]["gaps"] >= 1  # the lost driver messages: never joined across
    assert report["train_samples"] + report["samples"] >= SAMPLES - len(LOST) - 5  # the grid's two ends
    assert report["nmse_free_run_db"] < -25.0, report["model"]["expansion"]["terms"]
    values = read_params_file(tmp_path / "model" / "params.yaml")
    assert {key: values[key] for key in INTERPRETATION} == INTERPRETATION
    document = yaml.safe_load((tmp_path / "model" / "params.yaml").read_text())
    assert list(document) == ["/**"]  # any node name, any namespace: the user's remaps pick the topics
    # the params file alone makes the session pair the bag's topics into the same samples
    resolved, network = resolve(values)
    identifier = build_identifier({**values, **resolved}, network)
    node_values = {**NODE_DEFAULTS, **values, topics.RESOLVED_TOPICS: {"u": "/arm/cmd", "y_p": "/arm/joint_states"}}
    index = pair_raw(str(bag), make_session(identifier, node_values), node_values).index
    assert len(index) == report["train_samples"] + report["samples"]
    # by the node's numbers: every sample numbered below 6001 built the model, the lost ones among them not counted
    assert report["test_from"] == 6001 and report["train_samples"] == int(np.count_nonzero(index < 6001))
    assert report["sample_numbers"]["train"] == [int(index[0]), int(index[index < 6001][-1])]
    gaps = np.flatnonzero(np.diff(index) != 1)
    assert len(gaps) >= 1 and index[gaps[0] + 1] - index[gaps[0]] >= len(LOST)


def test_a_bag_without_configuration_or_flags_says_what_to_pass(tmp_path: Path) -> None:
    bag = tmp_path / "elbow_run1"
    with BagWriter(bag) as writer:
        writer.add_topic("/arm/cmd", "std_msgs/msg/Float64MultiArray")
        writer.write_message("/arm/cmd", command(1.0), 10**9)
    done = subprocess.run(
        [sys.executable, "-m", "lenn_ros.cli", "fit", str(bag), "--test-from", "100"],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert "--u TOPIC --u-field PATH --y TOPIC --y-field PATH" in done.stderr and "/arm/cmd" in done.stderr


def test_a_bag_whose_start_weights_are_elsewhere_is_fitted_and_evaluate_says_what_it_lacks(tmp_path: Path) -> None:
    """The identifier that was recorded started from a weights file this machine does not have: fit needs
    only the record's meaning (it builds its own model) and pairs it as without one; evaluate, which relearns
    from those weights, refuses in one line naming the file."""
    from lenn_ros.fit.bag import load_bag
    from lenn_ros.service import RecordingError
    from lenn_ros.service.evaluation import evaluate_bag

    elsewhere = str(tmp_path / "on_the_robot" / "weights.npz")  # never written
    with_weights, without = tmp_path / "started_from_weights", tmp_path / "fresh"
    write_robot_bag(with_weights, configured=True, weights_in=elsewhere)
    write_robot_bag(without, configured=True)
    data, reference = load_bag(with_weights, {}), load_bag(without, {})
    assert np.array_equal(data.index, reference.index) and len(data.index) >= SAMPLES - len(LOST) - 5
    assert np.array_equal(data.u, reference.u) and np.array_equal(data.y, reference.y)
    assert data.breaks == reference.breaks and data.interpretation == reference.interpretation
    with pytest.raises(RecordingError, match=r"weights_in .*on_the_robot/weights\.npz.* does not exist"):
        evaluate_bag(str(with_weights))
