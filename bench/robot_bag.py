"""A robot's own recording, written as ``ros2 bag record`` writes one: rosbag2, MCAP or sqlite3.

    python bench/robot_bag.py OUT --seconds 600 --storage mcap     # a 10-minute log
    python bench/robot_bag.py OUT --storage sqlite3                # as Humble / Iron record by default

Not the package's own topics: the driver's ``/joint_states`` (``sensor_msgs/JointState``,
stamped, 500 Hz, three joints named in another order than the command's) and a forward
command controller's ``/arm_controller/commands`` (``std_msgs/Float64MultiArray``,
unstamped, 100 Hz), each logged at its arrival (the stamp plus a jittered latency), written
through rosbags' public ``Writer`` (another library than the package's recorder). No
``identifier_config``, no ``u`` / ``y_p``, no ``samples``, no sequence numbers: to read it,
a user names the topics, fields and sample period (``--u /arm_controller/commands
--u-field 'data[1]' --y /joint_states --y-field 'position[elbow]' --sample-period 0.002``).

The elbow is a position servo: a PD loop on the commanded position drives a joint with
gravity, viscous and Coulomb friction; the command is a sequence of moves to random set
points with rests between them, so the log holds motion and standing still, as a robot's does.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

JOINTS = ("shoulder", "elbow", "wrist")
#: the order the driver publishes them in (not the command's)
DRIVER_ORDER = ("wrist", "shoulder", "elbow")
STATE_RATE = 500.0
COMMAND_RATE = 100.0
U_FLAGS = ("--u", "/arm_controller/commands", "--u-field", "data[1]")
Y_FLAGS = ("--y", "/joint_states", "--y-field", "position[elbow]")
PERIOD = 1.0 / STATE_RATE


def elbow(command: np.ndarray, seed: int, substeps: int = 4) -> np.ndarray:
    """The elbow's angle at each state sample, for the command held at each (zero-order hold)."""
    dt = PERIOD / substeps
    angle, speed = 0.0, 0.0
    out = np.empty(command.size)
    gain, damping, gravity, viscous, coulomb = 60.0, 9.0, 4.0, 1.5, 0.8
    for k, target in enumerate(command):
        for _ in range(substeps):
            torque = gain * (target - angle) - damping * speed
            accel = torque - gravity * math.sin(angle) - viscous * speed - coulomb * math.tanh(speed / 0.02)
            speed += dt * accel
            angle += dt * speed
        out[k] = angle
    return out


def command_profile(seconds: float, seed: int) -> np.ndarray:
    """The elbow's commanded position at 100 Hz: moves to random set points (smooth ramps) and rests."""
    rng = np.random.default_rng(seed)
    n = int(seconds * COMMAND_RATE)
    out = np.zeros(n)
    k, level = 0, 0.0
    while k < n:
        target = rng.uniform(-1.0, 1.0)
        ramp = int(rng.uniform(0.3, 1.5) * COMMAND_RATE)
        rest = int(rng.choice([rng.uniform(0.2, 1.0), rng.uniform(2.0, 5.0)]) * COMMAND_RATE)
        steps = np.linspace(level, target, ramp + 1)[1:]
        out[k : k + ramp] = steps[: max(0, min(ramp, n - k))]
        out[k + ramp : k + ramp + rest] = target
        k, level = k + ramp + rest, target
    return out


def write_robot_bag(path: str | Path, seconds: float = 30.0, storage: str = "mcap", seed: int = 0) -> Path:
    """Write the recording (see the module docstring); returns its directory."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    rng = np.random.default_rng(seed + 1000)
    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    commands = command_profile(seconds, seed)
    n_state = int(seconds * STATE_RATE)
    held = np.repeat(commands, int(STATE_RATE / COMMAND_RATE))[:n_state]
    # the servo acts on the command it has received: a command logged at t acts from the next state sample
    acting = np.r_[0.0, held[:-1]]
    angle = elbow(acting, seed) + rng.normal(0.0, 2e-4, n_state)
    start_ns = 1_800_000_000 * 10**9
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        states = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store)
        cmd = writer.add_connection("/arm_controller/commands", "std_msgs/msg/Float64MultiArray", typestore=store)
        events = []
        for k in range(n_state):
            stamp = start_ns + round(k * PERIOD * 1e9)
            events.append((stamp + int(rng.uniform(0.2e6, 1.5e6)), 0, k, stamp))
        per = int(STATE_RATE / COMMAND_RATE)
        for j in range(commands.size):
            sent = start_ns + round(j * per * PERIOD * 1e9) - int(0.3e6)
            events.append((sent + int(rng.uniform(0.05e6, 0.4e6)), 1, j, sent))
        events.sort()
        joint = types["sensor_msgs/msg/JointState"]
        header = types["std_msgs/msg/Header"]
        time = types["builtin_interfaces/msg/Time"]
        array = types["std_msgs/msg/Float64MultiArray"]
        layout = types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
        order = [JOINTS.index(name) for name in DRIVER_ORDER]
        for logged, kind, k, stamp in events:
            if kind == 0:
                values = np.array([0.3 * math.sin(0.1 * k * PERIOD), angle[k], 0.0])[order]
                message = joint(
                    header=header(stamp=time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=""),
                    name=list(DRIVER_ORDER), position=values, velocity=np.zeros(3), effort=np.zeros(3),
                )  # fmt: skip
                writer.write(states, logged, store.serialize_cdr(message, "sensor_msgs/msg/JointState"))
            else:
                message = array(layout=layout, data=np.array([0.0, commands[k], 0.0]))
                writer.write(cmd, logged, store.serialize_cdr(message, "std_msgs/msg/Float64MultiArray"))
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    write_robot_bag(args.out, args.seconds, args.storage, args.seed)
    print(f"wrote {args.out}: flags {' '.join(U_FLAGS + Y_FLAGS)} --sample-period {PERIOD}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
