"""The package through the real ``ros2`` command line: run, param set/get, topic echo, launch.

The tools are ROS 2 Jazzy's own ros2cli / launch / launch_ros, installed into the venv by
``bash ../shared/ros-tools/install.sh .venv`` (``.ci/run`` does it when that folder is there);
the package is a real ``colcon build`` found through the ament index, as on a full install.
Every test skips, saying why, where the tools are absent (they exist for Python 3.11 only).
Each run uses a private ROS domain and ``--no-daemon``; the daemon is stopped at the end anyway.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(240)]

REPO = Path(__file__).resolve().parents[1]
TOOLS_ENV = Path(sys.prefix) / "ros-tools.env"


def _skip_reason() -> str | None:
    if sys.version_info[:2] != (3, 11):
        return f"the ros2 CLI wheels of ../shared/ros-tools are built for Python 3.11, this is {sys.version.split()[0]}"
    if not TOOLS_ENV.is_file():
        return f"the ros2 CLI is not installed in this venv (no {TOOLS_ENV}): bash ../shared/ros-tools/install.sh .venv"
    if not Path(sys.executable).with_name("colcon").exists() and shutil.which("colcon") is None:
        return "colcon is not installed (pip install '.[test]')"
    return None


def _sourced(env_file: Path) -> dict[str, str]:
    """The environment after ``source env_file``, as a shell user would have it."""
    dump = subprocess.run(
        ["bash", "-c", f'source "{env_file}" && env -0'], capture_output=True, check=True, env=dict(os.environ)
    ).stdout.decode()
    return dict(item.split("=", 1) for item in dump.split("\0") if "=" in item)


def _copy_package(source: Path) -> None:
    """The package's files into a workspace: git's tracked files, or (no git, e.g. under
    ``colcon test`` of a copied tree) the tree without build products and the bags."""
    listed = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True)
    if listed.returncode != 0:
        skip = shutil.ignore_patterns(".git", ".venv", "build", "install", "log", "bags", "__pycache__", "*.egg-info")
        shutil.copytree(REPO, source, ignore=skip)
        return
    for name in listed.stdout.split():
        if not name.startswith("bags/") and (REPO / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, source / name)


@pytest.fixture(scope="module")
def ros2_env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    """ros-tools sourced, the package colcon-built into a workspace, a private domain."""
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    import domain_coordinator

    workspace = tmp_path_factory.mktemp("ws")
    _copy_package(workspace / "src" / "lenn_ros")
    colcon = shutil.which("colcon") or str(Path(sys.executable).with_name("colcon"))
    build = subprocess.run(
        [colcon, "build", "--packages-select", "lenn_ros"], cwd=workspace, capture_output=True, text=True, timeout=200
    )
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    prefix = workspace / "install" / "lenn_ros"
    env = _sourced(TOOLS_ENV)
    site = next(prefix.glob("lib/python3*/site-packages"))
    env["AMENT_PREFIX_PATH"] = f"{prefix}{os.pathsep}{env.get('AMENT_PREFIX_PATH', '')}"
    env["PYTHONPATH"] = f"{site}{os.pathsep}{env.get('PYTHONPATH', '')}"
    env["PYTHONUNBUFFERED"] = "1"
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["LENN_ROS_PREFIX"] = str(prefix)
    with domain_coordinator.domain_id() as domain_id:
        env["ROS_DOMAIN_ID"] = str(domain_id)
        yield env
        subprocess.run(["ros2", "daemon", "stop"], env=env, capture_output=True, timeout=30)


def ros2(env: dict[str, str], *arguments: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ros2", *arguments], env=env, capture_output=True, text=True, timeout=timeout)


def start(env: dict[str, str], *arguments: str, cwd: Path | None = None) -> subprocess.Popen[str]:
    """``ros2 ARGUMENTS`` in its own process group (ros2 run does not pass a signal on to the node)."""
    return subprocess.Popen(
        ["ros2", *arguments],
        env=env,
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )


def stop(process: subprocess.Popen[str], timeout: float = 30) -> str:
    """SIGINT to the whole group (what Ctrl-C does), then the output."""
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGINT)
    try:
        output, _ = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        output, _ = process.communicate()
    return output


def param_get(env: dict[str, str], node: str, name: str, timeout: float = 45) -> str:
    """``ros2 param get``, retried until the node is discovered (it takes a few seconds to start)."""
    deadline = time.monotonic() + timeout
    while True:
        result = ros2(env, "param", "get", "--no-daemon", "--spin-time", "2", node, name)
        if result.returncode == 0 or time.monotonic() > deadline:
            assert result.returncode == 0, result.stdout + result.stderr
            return result.stdout.strip()
        time.sleep(0.5)


def test_ros2_run_applies_the_shipped_params_file_in_a_namespace(ros2_env: dict[str, str]) -> None:
    """The installed config (keys ``/**/identifier``) reaches the node pushed into /id3."""
    params = Path(ros2_env["LENN_ROS_PREFIX"]) / "share" / "lenn_ros" / "config" / "example3_lenn.yaml"
    node = start(
        ros2_env, "run", "lenn_ros", "identifier", "--ros-args", "-r", "__ns:=/id3", "--params-file", str(params)
    )
    try:
        assert param_get(ros2_env, "/id3/identifier", "example") == "Integer value is: 3"
        assert param_get(ros2_env, "/id3/identifier", "network") == "String value is: lenn"
    finally:
        output = stop(node)
    assert "Traceback" not in output, output


def test_ros2_run_renamed_node_reads_an_any_node_params_file(ros2_env: dict[str, str], tmp_path: Path) -> None:
    """``-r __node:=ident3``: a ``/**`` section applies to the node whatever its name."""
    params = tmp_path / "all_nodes.yaml"
    params.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"example": 2, "network": "mlp"}}}))
    node = start(
        ros2_env, "run", "lenn_ros", "identifier", "--ros-args", "-r", "__node:=ident3", "--params-file", str(params)
    )
    try:
        assert param_get(ros2_env, "/ident3", "example") == "Integer value is: 2"
        assert param_get(ros2_env, "/ident3", "network") == "String value is: mlp"
    finally:
        stop(node)


def test_ros2_param_set_then_get_and_topic_echo(ros2_env: dict[str, str]) -> None:
    """alpha changed live through ``ros2 param set``; the model's outputs seen by ``ros2 topic echo``."""
    identifier = start(ros2_env, "run", "lenn_ros", "identifier", "--ros-args", "-p", "example:=1")
    simulator = start(
        ros2_env,
        "run",
        "lenn_ros",
        "plant_simulator",
        "--ros-args",
        "-p",
        "example:=1",
        "-p",
        "rate_hz:=200.0",
        "-p",
        "train_samples:=100000",
    )
    try:
        assert param_get(ros2_env, "/identifier", "alpha").startswith("Double value is:")
        result = ros2(ros2_env, "param", "set", "--no-daemon", "--spin-time", "3", "/identifier", "alpha", "0.01")
        assert result.returncode == 0 and "Set parameter successful" in result.stdout, result.stdout + result.stderr
        assert param_get(ros2_env, "/identifier", "alpha") == "Double value is: 0.01"
        echo = ros2(ros2_env, "topic", "echo", "--no-daemon", "--once", "/y_hat", "std_msgs/msg/Float64", timeout=60)
        assert echo.returncode == 0, echo.stdout + echo.stderr
        value = yaml.safe_load(echo.stdout.split("---")[0])["data"]
        assert isinstance(value, float) and abs(value) < 1e3
    finally:
        stop(simulator)
        output = stop(identifier)
    assert "Traceback" not in output, output


def test_status_echoes_whole_as_the_readme_says(ros2_env: dict[str, str]) -> None:
    """The README's ``ros2 topic echo`` of /status gives JSON that parses (plain echo cuts it at 128 characters)."""
    readme = (REPO / "README.md").read_text()
    command = next(line.split("#")[0].split() for line in readme.splitlines() if line.startswith("ros2 topic echo")
                   and "/status" in line)  # fmt: skip
    assert "--full-length" in command, command
    identifier = start(ros2_env, "run", "lenn_ros", "identifier", "--ros-args", "-p", "status_period:=0.5")
    try:
        echo = ros2(ros2_env, *command[1:3], "--no-daemon", "--once", *command[3:], "std_msgs/msg/String", timeout=60)
        assert echo.returncode == 0, echo.stdout + echo.stderr
        status = json.loads(yaml.safe_load(echo.stdout.split("---")[0])["data"])
        assert "counters" in status and status["pairing"] == "sequence"
        cut = ros2(ros2_env, "topic", "echo", "--no-daemon", "--once", "/status", "std_msgs/msg/String", timeout=60)
        assert "..." in cut.stdout and len(cut.stdout) < len(echo.stdout)  # why the README says --full-length
    finally:
        output = stop(identifier)
    assert "Traceback" not in output, output


def test_ros2_launch_runs_simulator_identifier_and_recorder(ros2_env: dict[str, str], tmp_path: Path) -> None:
    """A short launch: it ends by itself when the simulator is done, and the bag holds every sample."""
    from mcap.reader import make_reader

    bag = tmp_path / "launched_bag"
    launch = start(
        ros2_env,
        "launch",
        "lenn_ros",
        "identification.launch.py",
        "example:=4",
        "network:=lenn",
        "train_samples:=400",
        "test_samples:=100",
        f"bag:={bag}",
        cwd=tmp_path,
    )
    try:
        output, _ = launch.communicate(timeout=150)
    finally:
        if launch.poll() is None:
            output = stop(launch)
    assert launch.returncode == 0, output[-4000:]
    assert "Traceback" not in output, output[-4000:]
    (mcap_file,) = bag.glob("*.mcap")
    with mcap_file.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    counts = {
        summary.channels[channel].topic: count for channel, count in summary.statistics.channel_message_counts.items()
    }
    assert counts["/u"] == counts["/y_p"] == 500, counts
    # everything the identifier published reached the bag: its configuration, one sample record per
    # paired sample, and its outputs (y_hat from the first complete regressor on)
    recorded = f"{sorted(counts.items())}\n{output[-4000:]}"
    assert counts.get("/identifier_config") == 1 and counts.get("/samples") == 500, recorded
    assert counts.get("/y_hat", 0) >= 490, sorted(counts.items())
    # the identifier's exit line (launch prefixes it with "[identifier-N] "): every sample paired
    final = [line.split("identifier: ", 1)[1] for line in output.splitlines() if "identifier: {" in line]
    assert final, output[-4000:]
    assert json.loads(final[-1])["counters"]["paired"] == 500, final[-1]


def test_the_command_line_is_reachable_through_ros2_run(ros2_env: dict[str, str]) -> None:
    """After colcon, ``lenn-ros`` is in lib/lenn_ros (not on PATH): ``ros2 run lenn_ros lenn-ros`` reaches it."""
    result = ros2(ros2_env, "run", "lenn_ros", "lenn-ros", "--help")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "reproduce" in result.stdout and "evaluate" in result.stdout
