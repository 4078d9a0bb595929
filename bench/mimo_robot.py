"""A robot with two joints on its own topics: a controller's command and a driver's JointState.

    python bench/mimo_robot.py --seed 0 --seconds 40 --rate 100 [--stall-at 20]

What an identifier meets on a robot with several channels, as a real process over DDS
(the robot simulator node drives one joint only: ``joint_name`` and ``command_index``):

- node ``controller`` publishes ``/robot/cmd`` (``std_msgs/msg/Float64MultiArray``,
  ``data`` = [u1, u2], no header, RELIABLE: the plant here takes every command at once,
  so one lost on its way to the identifier would pair a measurement with the command
  before; over BEST_EFFORT 0.4-2 % of the samples were so): u(k) is i.i.d. uniform on
  [-amplitude, amplitude] per channel (:class:`~lenn_ros.paper.signals.Excitation` channel i,
  signal ``uniform``, scaled);
- node ``driver`` publishes ``/robot/joint_states`` (``sensor_msgs/msg/JointState``,
  BEST_EFFORT, ``header.stamp`` = the step's time) with the joints listed as
  ``[j2, wrist, j1]``: another order than the identifier's ``y_names [j1, j2]``, and one
  joint more; ``position`` of j1, j2 is the 2x2 plant's (y1, y2), ``MIMO_PLANTS[plant]``;
- every period T the driver publishes y(k) stamped t_k, steps the plant with the
  command it holds (``u(k)`` plus plant-input noise at ``noise_db``), then the
  controller publishes the next command, received before t_(k+1): the grid pairs
  (u(k), y(k)), with y(k+1) = F(y(k), u(k)), the plants' convention;
- ``loss`` of the measurements are never published (seeded), and ``--stall-at S`` stops
  the driver's publications for ``--stall`` seconds from S s on (the plant runs on):
  gaps in the samples that no fit may join across.

It starts once both topics have ``--subscribers`` matched readers each (polled) and
stops after ``--seconds``. The schedule is absolute (t_k = t_0 + k T). A step that wakes
more than ``LATE`` T after its t_k (a loaded machine) is skipped whole: no measurement,
no plant step, no new command, so the grid sees a gap there. Catching up instead
published a burst of measurements into one grid cell, each with its stamp of that
moment: the grid keeps one and joins samples that were not adjacent, and the command
of the burst arrives after the measurement it belongs to (the first version did that:
10 % of the samples missing, the fitted y2 at -8.5 dB).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lenn_ros.paper.plants import MIMO_PLANTS
from lenn_ros.paper.signals import Excitation

CMD, JOINT_STATES = "/robot/cmd", "/robot/joint_states"
#: The driver's joint order: not the identifier's, and one joint it does not model
DRIVER_JOINTS = ("j2", "wrist", "j1")
#: share of a period after its t_k past which a step is skipped (inside the grid cell's half-width)
LATE = 0.3


def run(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    rclpy.init()
    controller, driver = rclpy.create_node("controller"), rclpy.create_node("driver")
    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    cmd = controller.create_publisher(Float64MultiArray, CMD, QoSProfile(depth=100))
    states = driver.create_publisher(JointState, JOINT_STATES, best_effort)
    executor = SingleThreadedExecutor()
    executor.add_node(controller)
    executor.add_node(driver)
    if not _readers(executor, (cmd, states), args.subscribers, args.wait):
        print(f"mimo_robot: fewer than {args.subscribers} readers on {CMD} / {JOINT_STATES}", file=sys.stderr)
        return 1
    plant = MIMO_PLANTS[args.plant]()
    excitations = [Excitation(args.seed, "uniform", noise_db=args.noise_db, channel=i) for i in range(plant.n_u)]
    loss = np.random.default_rng([args.seed, 7])
    period, steps = 1.0 / args.rate, round(args.seconds * args.rate)
    stall = (args.stall_at, args.stall_at + args.stall) if args.stall_at is not None else None
    held = args.amplitude * np.array([excitation.sample(0)[0] for excitation in excitations])
    cmd.publish(Float64MultiArray(data=held.tolist()))
    t0 = time.monotonic() + 2 * period
    published = lost = late = 0
    for k in range(steps):
        wait = t0 + k * period - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        elif -wait > LATE * period:
            late += 1
            continue
        state = JointState(name=list(DRIVER_JOINTS))
        y = plant.output
        state.position = [float(y[1]), 0.25, float(y[0])]
        state.header.stamp = driver.get_clock().now().to_msg()
        stalled = stall is not None and stall[0] <= k * period < stall[1]
        if stalled or loss.random() < args.loss:
            lost += 1
        else:
            states.publish(state)
            published += 1
        drawn = [excitation.sample(k) for excitation in excitations]
        plant.step(held + np.array([noise for _, noise in drawn]))
        held = args.amplitude * np.array([excitation.sample(k + 1)[0] for excitation in excitations])
        cmd.publish(Float64MultiArray(data=held.tolist()))
    print(
        f"mimo_robot: {steps} steps, {published} measurements published, {lost} not (lost or stalled), "
        f"{late} steps skipped late",
        file=sys.stderr,
    )
    controller.destroy_node()
    driver.destroy_node()
    rclpy.try_shutdown()
    return 0


def _readers(executor, publishers, count: int, wait: float) -> bool:
    """Whether every publisher has ``count`` matched readers within ``wait`` s (polled)."""
    deadline = time.monotonic() + wait
    while min(publisher.get_subscription_count() for publisher in publishers) < count:
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.05)
    return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument("--rate", type=float, default=100.0, help="steps per second (1 / sample_period)")
    parser.add_argument("--plant", choices=sorted(MIMO_PLANTS), default="narendra2x2")
    # 0.7 and -40 dB: the fitted model's one-step NMSE is then about -36 / -32 dB (y1 / y2); at amplitude 1
    # the order-3 expansion of y1 y2 / (1 + y2^2) over the wider range stops y2 at about -27 dB
    parser.add_argument("--amplitude", type=float, default=0.7, help="command range, +-")
    parser.add_argument("--noise-db", type=float, default=-40.0, help="plant-input noise vs. U[-1,1] power")
    parser.add_argument("--loss", type=float, default=0.01, help="share of measurements never published")
    parser.add_argument("--stall-at", type=float, help="seconds after the start at which the driver stalls")
    parser.add_argument("--stall", type=float, default=0.2, help="how long the stall lasts, s")
    parser.add_argument("--subscribers", type=int, default=1, help="readers per topic to wait for")
    parser.add_argument("--wait", type=float, default=60.0, help="seconds to wait for them")
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
