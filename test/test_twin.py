"""A fitted model to use: lenn_ros.load_model and the twin node (issue 20, items 1 and 4).

The model is fitted on a real record (the DaISy flexible robot arm, first 2/3) by
``fit`` as ``lenn-ros fit -o DIR`` runs it; the checks compare with what ``fit``
reported for the test part, never with numbers written here.
"""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

import lenn_ros
from lenn_ros.core.fields import FieldError, compile_path, compile_vector, compose
from lenn_ros.fit.data import Data
from lenn_ros.fit.export import write_outputs
from lenn_ros.fit.procedure import fit
from lenn_ros.model import ModelError

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "daisy_robot-arm.csv"


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> dict:
    if not DATA.is_file():
        pytest.skip(f"{DATA} not found (the shared data sets sit beside the repository)")
    table = np.genfromtxt(DATA, delimiter=",", names=True)
    u, y = np.asarray(table["u"], float), np.asarray(table["y"], float)
    test_from = len(y) * 2 // 3 + 1
    result = fit(Data(u, y, "robot-arm"), test_from)
    directory = tmp_path_factory.mktemp("model")
    start = result.train_samples
    files = write_outputs(directory, result, Data(u, y, "fitted"))
    assert json.loads(Path(files["report"]).read_text())["intervals"] == result.intervals
    return {"dir": directory, "u": u, "y": y, "start": start, "result": result}


def test_load_model_simulates_what_fit_reported(fitted: dict) -> None:
    model = lenn_ros.load_model(fitted["dir"])
    u, y, start, w = fitted["u"], fitted["y"], fitted["start"], model.history
    free = model.simulate(u[start:], y_initial=y[start - w : start], u_initial=u[start - w : start])
    np.testing.assert_array_equal(free, fitted["result"].y_free_test)
    # one sample at a time: the same run, bit for bit
    stepper = model.stepper(y_initial=y[start - w : start], u_initial=u[start - w : start])
    stepped = np.array([stepper.step(value)[0] for value in u[start:]])
    np.testing.assert_array_equal(stepped, free)
    # predict: the next outputs after a measured history, the later inputs given
    k, steps = start + 50, 20
    ahead = model.predict(u[:k], y[:k], steps, u_future=u[k : k + steps - 1])
    again = model.simulate(u[k : k + steps], y_initial=y[k - w : k], u_initial=u[k - w : k])
    np.testing.assert_array_equal(ahead, again)
    assert model.intervals()["free_run"]["half_width"] > 0


def test_load_model_says_what_is_wrong(fitted: dict, tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="no params file"):
        lenn_ros.load_model(tmp_path)
    model = lenn_ros.load_model(fitted["dir"])
    with pytest.raises(ModelError, match="needs the last"):
        model.simulate(np.zeros(10), y_initial=np.zeros(max(model.history - 1, 0)))
    with pytest.raises(ModelError, match="NaN"):
        model.simulate(np.array([0.0, np.nan]))
    with pytest.raises(ModelError, match="u_future has"):
        model.predict(fitted["u"][:50], fitted["y"][:50], 5, u_future=np.zeros(2))


def test_compose_reads_back_through_the_same_field() -> None:
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    message = compose(JointState(), "position[elbow]", 0.25)
    assert list(message.name) == ["elbow"] and compile_path("position[elbow]")(message) == 0.25
    message = compose(Float64MultiArray(), "data[2]", 1.5)
    assert list(message.data) == [0.0, 0.0, 1.5]
    message = compose(JointState(), "effort[*]", [1.0, 2.0], ["a", "b"])
    np.testing.assert_array_equal(compile_vector("effort[*]", ["b", "a"])(message), [2.0, 1.0])
    with pytest.raises(FieldError, match="no field"):
        compose(JointState(), "torque[0]", 1.0)


def _robot_model(fitted: dict, directory: Path) -> Path:
    """The fitted model as a bag-fitted one reads a robot: command Float64MultiArray data[0], joint in JointState."""
    from lenn_ros import topics

    directory.mkdir()
    for name in ("weights.npz", "fit.json"):
        (directory / name).write_bytes((fitted["dir"] / name).read_bytes())
    params = yaml.safe_load((fitted["dir"] / "params.yaml").read_text())
    values = params["/**"]["ros__parameters"]
    values.update(u_type=topics.FLOAT64_ARRAY, u_field="data[0]", y_type=topics.JOINT_STATE, y_field="position[elbow]")
    values["weights_in"] = str(directory / "weights.npz")
    (directory / "params.yaml").write_text(yaml.safe_dump(params))
    return directory


def _drive(domain: int, inputs: np.ndarray, twin) -> list[tuple[list[str], float]]:
    """Publish each input as the controller would, once the twin is matched; the JointStates it published."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray, String

    from lenn_ros import topics

    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("test_twin_driver", context=ctx)
    received: list[tuple[list[str], float]] = []
    done = threading.Event()

    def on_output(message: JointState) -> None:
        received.append((list(message.name), message.position[0]))
        if len(received) >= len(inputs):
            done.set()

    statuses: list[dict] = []
    node.create_subscription(JointState, topics.Y_P, on_output, topics.data_qos())
    node.create_subscription(
        String, "/twin/status", lambda m: statuses.append(json.loads(m.data)), topics.latched_qos()
    )
    publisher = node.create_publisher(Float64MultiArray, topics.U, topics.data_qos())
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        deadline = time.monotonic() + 30
        while publisher.get_subscription_count() < 1 or node.count_publishers(topics.Y_P) < 1:
            assert twin.poll() is None, f"the twin stopped: {twin.communicate()}"
            assert time.monotonic() < deadline, "the twin never matched the driver's topics"
            time.sleep(0.05)
        for value in inputs:
            publisher.publish(Float64MultiArray(data=[float(value)]))
        assert done.wait(30), f"{len(received)} of {len(inputs)} outputs arrived"
        publisher.publish(Float64MultiArray(data=[math.nan]))  # refused, said and counted, never stepped
        while not (statuses and statuses[-1]["refused"] == 1):
            assert time.monotonic() < deadline + 60, f"the twin never counted the NaN command: {statuses[-1:]}"
            time.sleep(0.05)
        assert statuses[-1]["published"] == len(inputs) and statuses[-1]["steps"] == len(inputs)
    finally:
        executor.shutdown()
        spinner.join(timeout=5)
        node.destroy_node()
        ctx.try_shutdown()
    return received


def _run_twin(fitted: dict, domain: int, tmp_path: Path, *params: str) -> tuple[list, str]:
    """The twin of the robot model from the measured history before the test part, driven by its inputs."""
    from rosutil import start_node, stop

    directory = _robot_model(fitted, tmp_path / "robot_model")
    u, y, start = fitted["u"], fitted["y"], fitted["start"]
    w = lenn_ros.load_model(directory).history
    history = [
        f"y_initial:={list(map(float, y[start - w : start]))}",
        f"u_initial:={list(map(float, u[start - w : start]))}",
    ]
    twin = start_node("twin", f"model:={directory}", *params, *history)
    try:
        received = _drive(domain, u[start:], twin)
    finally:
        _, err = stop(twin)
    return received, err


@pytest.mark.ros
def test_twin_publishes_fits_free_run_over_dds(fitted: dict, domain: int, tmp_path: Path) -> None:
    """Driven by the test part's inputs, the twin publishes fit's free run (1e-9), as the robot's messages."""
    received, err = _run_twin(fitted, domain, tmp_path)
    assert all(names == ["elbow"] for names, _ in received)
    published = np.array([value for _, value in received])
    assert np.max(np.abs(published - fitted["result"].y_free_test)) <= 1e-9
    assert "twin of" in err and "stepping on each command" in err and "is not finite: refused" in err


@pytest.mark.ros
def test_twin_noise_has_the_fits_residual_std(fitted: dict, domain: int, tmp_path: Path) -> None:
    """noise:=true adds Gaussian noise of fit.json's one-step std to what is published, not to the model's state."""
    received, err = _run_twin(fitted, domain, tmp_path, "noise:=true", "seed:=3")
    noise = np.array([value for _, value in received]) - fitted["result"].y_free_test
    std = fitted["result"].intervals["one_step"]["std"]
    # 341 draws: the sample std within 4 standard errors of the std, and no drift (the state is noise-free)
    assert abs(np.std(noise) - std) <= 4 * std / np.sqrt(2 * len(noise)), (np.std(noise), std)
    assert abs(np.mean(noise)) <= 4 * std / np.sqrt(len(noise))
    assert f"noise std {std:.4g}" in err
