"""A robot's own recording, written as ``ros2 bag record`` writes one: rosbag2, MCAP or sqlite3.

    python bench/robot_bag.py OUT --seconds 600 --storage mcap     # a 10-minute log
    python bench/robot_bag.py OUT --storage sqlite3                # as Humble / Iron record by default
    python bench/robot_bag.py OUT --seconds 3600 --joints 6 --rate 1000   # an hour of a six-joint robot at 1 kHz

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

``--joints 6`` (a six-joint arm, ``ur_robot_driver``'s joint names and order, the elbow third in
the command: ``--u-field data[2]``) and ``--rate`` (the driver's rate; the commands stay at
100 Hz) make longer, larger logs; :func:`flags` gives the flags that read each. Messages are
merged in arrival order as they are written (nothing per message is held), so an hour at 1 kHz
(3.6 M JointState, 1.1 GB) is written in a few minutes in bounded memory.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

JOINTS = ("shoulder", "elbow", "wrist")
#: the order the driver publishes them in (not the command's)
DRIVER_ORDER = ("wrist", "shoulder", "elbow")
#: a six-joint arm's joints in the command's order, and the order its driver publishes them in
JOINTS_6 = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
DRIVER_ORDER_6 = ("shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3", "shoulder_pan")
STATE_RATE = 500.0
COMMAND_RATE = 100.0
U_FLAGS = ("--u", "/arm_controller/commands", "--u-field", "data[1]")
Y_FLAGS = ("--y", "/joint_states", "--y-field", "position[elbow]")
PERIOD = 1.0 / STATE_RATE
#: the servo's integration step (s), whatever the driver's rate
STEP = PERIOD / 4


def names(joints: int) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(the command's joint order, the driver's) of a 3- or 6-joint robot."""
    if joints not in (3, 6):
        raise ValueError(f"joints must be 3 or 6, not {joints}")
    return (JOINTS, DRIVER_ORDER) if joints == 3 else (JOINTS_6, DRIVER_ORDER_6)


def flags(joints: int = 3, rate: float = STATE_RATE) -> list[str]:
    """The command-line flags that read the elbow's command and position of such a recording, on its grid."""
    order = names(joints)[0]
    u = ["--u", U_FLAGS[1], "--u-field", f"data[{order.index('elbow')}]"]
    return [*u, *Y_FLAGS, "--sample-period", repr(1.0 / rate)]


def elbow(command: np.ndarray, seed: int, substeps: int = 4, period: float = PERIOD) -> np.ndarray:
    """The elbow's angle at each state sample, for the command held at each (zero-order hold)."""
    dt = period / substeps
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


def write_robot_bag(
    path: str | Path,
    seconds: float = 30.0,
    storage: str = "mcap",
    seed: int = 0,
    joints: int = 3,
    rate: float = STATE_RATE,
) -> Path:
    """Write the recording (see the module docstring); returns its directory."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    order_cmd, order_driver = names(joints)
    per = round(rate / COMMAND_RATE)
    if per < 1 or abs(per * COMMAND_RATE - rate) > 1e-9:
        raise ValueError(f"rate must be a multiple of the command rate {COMMAND_RATE:g} Hz, not {rate:g}")
    period = 1.0 / rate
    rng = np.random.default_rng(seed + 1000)
    store = get_typestore(Stores.ROS2_JAZZY)
    commands = command_profile(seconds, seed)
    n_state = int(seconds * rate)
    held = np.repeat(commands, per)[:n_state]
    # the servo acts on the command it has received: a command logged at t acts from the next state sample
    acting = np.r_[0.0, held[:-1]]
    angle = elbow(acting, seed, max(1, round(period / STEP)), period) + rng.normal(0.0, 2e-4, n_state)
    start_ns = 1_800_000_000 * 10**9
    # each message logged at its arrival: the stamp plus a jittered latency (a state's 0.1 to 0.75 of a period, a
    # command's 0.05 to 0.4 ms after it was sent, 0.3 ms before its state sample)
    k_state = np.arange(n_state)
    stamps = start_ns + np.round(k_state * period * 1e9).astype(np.int64)
    state_logged = stamps + rng.uniform(0.1 * period * 1e9, 0.75 * period * 1e9, n_state).astype(np.int64)
    k_cmd = np.arange(commands.size)
    sent = start_ns + np.round(k_cmd * per * period * 1e9).astype(np.int64) - int(0.3e6)
    cmd_logged = sent + rng.uniform(0.05e6, 0.4e6, commands.size).astype(np.int64)
    logged = np.r_[state_logged, cmd_logged]
    kind = np.r_[np.zeros(n_state, np.int8), np.ones(commands.size, np.int8)]
    which = np.r_[k_state, k_cmd]
    arrival = np.lexsort((which, kind, logged))  # arrival order (ties: states first, then by number)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        messages = _Messages(store, order_cmd, order_driver, period, stamps, angle, commands)
        states = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store)
        cmd = writer.add_connection("/arm_controller/commands", "std_msgs/msg/Float64MultiArray", typestore=store)
        for i in arrival.tolist():
            k = int(which[i])
            if kind[i] == 0:
                writer.write(states, int(logged[i]), messages.state(k))
            else:
                writer.write(cmd, int(logged[i]), messages.command(k))
    return path


class _Messages:
    """The CDR bytes of state sample k and command k."""

    def __init__(self, store: Any, order_cmd: tuple[str, ...], order_driver: tuple[str, ...], period: float,
                 stamps: np.ndarray, angle: np.ndarray, commands: np.ndarray) -> None:  # fmt: skip
        types = store.types
        self.store, self.period, self.stamps, self.angle, self.commands = store, period, stamps, angle, commands
        self.joint = types["sensor_msgs/msg/JointState"]
        self.header = types["std_msgs/msg/Header"]
        self.time = types["builtin_interfaces/msg/Time"]
        self.array = types["std_msgs/msg/Float64MultiArray"]
        self.layout = types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
        self.order = [order_cmd.index(name) for name in order_driver]
        self.names = list(order_driver)
        self.elbow_at = order_cmd.index("elbow")
        self.joints = len(order_cmd)
        self.zeros = np.zeros(self.joints)

    def state(self, k: int) -> bytes:
        values = np.zeros(self.joints)
        values[0] = 0.3 * math.sin(0.1 * k * self.period)
        values[self.elbow_at] = self.angle[k]
        if self.joints == 6:  # the other joints drift slowly, as an arm's do
            values[1] = -0.5 + 0.2 * math.sin(0.05 * k * self.period)
            values[3] = 0.1 * math.cos(0.2 * k * self.period)
        stamp = int(self.stamps[k])
        message = self.joint(
            header=self.header(stamp=self.time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=""),
            name=self.names, position=values[self.order], velocity=self.zeros, effort=self.zeros,
        )  # fmt: skip
        return self.store.serialize_cdr(message, "sensor_msgs/msg/JointState")

    def command(self, k: int) -> bytes:
        data = np.zeros(self.joints)
        data[self.elbow_at] = self.commands[k]
        message = self.array(layout=self.layout, data=data)
        return self.store.serialize_cdr(message, "std_msgs/msg/Float64MultiArray")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--joints", type=int, choices=(3, 6), default=3, help="a 3- or 6-joint robot")
    parser.add_argument("--rate", type=float, default=STATE_RATE, help="JointState rate, Hz (a multiple of 100)")
    args = parser.parse_args()
    write_robot_bag(args.out, args.seconds, args.storage, args.seed, args.joints, args.rate)
    print(f"wrote {args.out}: flags {' '.join(flags(args.joints, args.rate))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
