"""A robot with two joints on its own topics: a controller's command and a driver's JointState.

    python bench/mimo_robot.py --seed 0 --seconds 40 --rate 100 [--stall-at 20]

What an identifier meets on a robot with several channels, as a real process over DDS
(the robot simulator node drives one joint only: ``joint_name`` and ``command_index``):

- node ``controller`` publishes ``/robot/cmd`` (``std_msgs/msg/Float64MultiArray``,
  ``data`` = [u1, u2], no header, BEST_EFFORT): u(k) is i.i.d. uniform on
  [-amplitude, amplitude] per channel (:class:`~lenn_ros.core.signals.Excitation` channel i,
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
stops after ``--seconds``. The schedule is absolute (t_k = t_0 + k T), so a late wake-up
is caught up, not accumulated.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lenn_ros.core.plants import MIMO_PLANTS
from lenn_ros.core.signals import Excitation

CMD, JOINT_STATES = "/robot/cmd", "/robot/joint_states"
#: The driver's joint order: not the identifier's, and one joint it does not model
DRIVER_JOINTS = ("j2", "wrist", "j1")


def run(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    rclpy.init()
    controller, driver = rclpy.create_node("controller"), rclpy.create_node("driver")
    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    cmd = controller.create_publisher(Float64MultiArray, CMD, best_effort)
    states = driver.create_publisher(JointState, JOINT_STATES, best_effort)
    executor = SingleThreadedExecutor()
    executor.add_node(controller)
    executor.add_node(driver)
    deadline = time.monotonic() + args.wait
    while min(cmd.get_subscription_count(), states.get_subscription_count()) < args.subscribers:
        if time.monotonic() > deadline:
            print(f"mimo_robot: fewer than {args.subscribers} readers on {CMD} / {JOINT_STATES}", file=sys.stderr)
            return 1
        executor.spin_once(timeout_sec=0.05)
    plant = MIMO_PLANTS[args.plant]()
    excitations = [Excitation(args.seed, "uniform", noise_db=args.noise_db, channel=i) for i in range(plant.n_u)]
    loss = np.random.default_rng([args.seed, 7])
    period, steps = 1.0 / args.rate, round(args.seconds * args.rate)
    stall = (args.stall_at, args.stall_at + args.stall) if args.stall_at is not None else None
    held = args.amplitude * np.array([excitation.sample(0)[0] for excitation in excitations])
    cmd.publish(Float64MultiArray(data=held.tolist()))
    t0 = time.monotonic() + 2 * period
    published = lost = 0
    for k in range(steps):
        wait = t0 + k * period - time.monotonic()
        if wait > 0:
            time.sleep(wait)
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
    print(f"mimo_robot: {steps} steps, {published} measurements published, {lost} not", file=sys.stderr)
    controller.destroy_node()
    driver.destroy_node()
    rclpy.try_shutdown()
    return 0


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
