"""A robot's whole day for the identifier, with nothing given but what the topics are.

    python bench/robot_day.py                    # the day at full length (about 5 minutes)
    python bench/robot_day.py --solver rls       # the same day with RLS
    python bench/robot_day.py --scale 0.2 --json # a short day (the test runs one)

Real processes over DDS, all started from here:
- the **driver** (this script, ``--driver``): a pendulum joint with viscous and Coulomb
  friction and stiction (:class:`~lenn_ros.paper.physical.FrictionJoint`) stepped at 1 kHz,
  its angle quantised to 1e-4 rad like an encoder, published as stamped BEST_EFFORT
  ``sensor_msgs/JointState`` with the joints in another order (``[wrist, joint1, base]``);
  the latest command is held (zero-order hold);
- the **controller** (this script, ``--controller``): torques as
  ``std_msgs/Float64MultiArray`` at 50 Hz, random steps within +-2 N m;
- the real ``identifier`` with only remaps, types, fields, ``pairing:=sample`` and
  ``sample_period`` (no scales, no example, no solver unless ``--solver``), and the real
  ``recorder``, recording everything.

The day, in order (seconds at ``--scale 1``):

| phase | s | what happens |
|---|---:|---|
| driver alone | 60 | the controller has not started: RSS sampled every 0.5 s |
| moving | 60 | random torque steps |
| standing still | 40 | the command held at 0: the joint hangs at rest, the encoder reads one tick |
| moving, alpha changed | 40 | ``alpha`` set live to half its value at the phase's start |
| burst | 5 | the driver publishes as fast as it can; a parameter call every 0.1 s |
| moving | 30 | |
| test | 30 | ``learning:=false`` set live: a frozen test phase |

Then, once ``status`` says every output is acknowledged (the recorder, which records the
burst too, has caught up), SIGINT to the identifier (its exit time measured), and ``lenn-ros evaluate`` of the
bag, whose test figure must equal the live one. Printed: one table (``--json``: one
JSON object).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from probe import Probe  # noqa: E402  (bench/, this script's folder)

PERIOD = 0.001  # s: the driver's loop and the identifier's grid
COMMAND_PERIOD = 0.02  # s: 50 Hz
TICK = 1e-4  # rad: the encoder's resolution
PHASES = (  # (name, seconds at scale 1)
    ("driver alone", 60.0),
    ("moving", 60.0),
    ("standing still", 40.0),
    ("moving, alpha changed", 40.0),
    ("burst", 5.0),
    ("moving after the burst", 30.0),
    ("test", 30.0),
)
FILLED_S = 12  # s after the driver starts: its queue of 10 000 is full (1 kHz), the RSS compared after this
MIN_ALONE = 25.0  # s: the driver alone at least this long, whatever the scale
REMAPS = ["-r", "u:=/cmd", "-r", "y_p:=/joint_states"]
TOPIC_SETTINGS = [
    "u_type:=std_msgs/msg/Float64MultiArray", "u_field:=data[0]",
    "y_type:=sensor_msgs/msg/JointState", "y_field:=position[joint1]",
    "pairing:=sample", f"sample_period:={PERIOD}",
]  # fmt: skip


def schedule(scale: float, t0: float) -> list[dict]:
    """The phases with absolute monotonic start and end times (one host: one monotonic clock for every process)."""
    phases, start = [], t0
    for name, seconds in PHASES:
        length = seconds if name == "burst" else seconds * scale  # a burst is a burst: its length is not scaled
        if name == "driver alone":  # the pairing queue fills in its first 10 s at 1 kHz: flat is judged after that
            length = max(length, MIN_ALONE)
        phases.append({"name": name, "start": start, "end": start + length})
        start += length
    return phases


def _phase_at(phases: list[dict], now: float) -> str | None:
    for phase in phases:
        if phase["start"] <= now < phase["end"]:
            return phase["name"]
    return None


# -- the driver and the controller (subprocesses) --------------------------------------------------
def run_driver(phases: list[dict]) -> None:
    """JointState at 1 kHz from the friction joint (as fast as it can during the burst), until the day ends."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from lenn_ros.paper.physical import FrictionJoint

    rclpy.init()
    node = rclpy.create_node("robot_day_driver")
    publisher = node.create_publisher(JointState, "/joint_states", qos_profile_sensor_data)
    command = [0.0]
    node.create_subscription(
        Float64MultiArray, "/cmd", lambda m: command.__setitem__(0, float(m.data[0])), qos_profile_sensor_data
    )
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    joint, clock = FrictionJoint(period=PERIOD), node.get_clock()
    message = JointState(name=["wrist", "joint1", "base"], position=[0.0, 0.0, 0.0])
    start, end = phases[0]["start"], phases[-1]["end"]
    while time.monotonic() < start:
        time.sleep(0.01)
    steps, sent = 0, 0
    while (now := time.monotonic()) < end:
        due = int((now - start) / PERIOD) + 1
        burst = _phase_at(phases, now) == "burst"
        if steps >= due and not burst:
            time.sleep(0.0002)
            continue
        while steps < due:  # the plant on its own clock; a late loop catches up
            joint.step(command[0])
            steps += 1
        message.header.stamp = clock.now().to_msg()
        message.position[1] = round(joint.output / TICK) * TICK
        publisher.publish(message)
        sent += 1
    print(json.dumps({"driver_sent": sent, "steps": steps}), flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()


def run_controller(phases: list[dict], seed: int) -> None:
    """Torque steps at 50 Hz from the end of 'driver alone'; 0 while standing still."""
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from std_msgs.msg import Float64MultiArray

    rclpy.init()
    node = rclpy.create_node("robot_day_controller")
    publisher = node.create_publisher(Float64MultiArray, "/cmd", qos_profile_sensor_data)
    rng = random.Random(seed)
    start, end = phases[1]["start"], phases[-1]["end"]
    while time.monotonic() < start:
        time.sleep(0.01)
    message, level, hold_until, k = Float64MultiArray(data=[0.0]), 0.0, 0.0, 0
    while (now := time.monotonic()) < end:
        if now >= hold_until:  # a new step every 0.1-0.5 s
            level, hold_until = rng.uniform(-2.0, 2.0), now + rng.uniform(0.1, 0.5)
        message.data[0] = 0.0 if _phase_at(phases, now) == "standing still" else level
        publisher.publish(message)
        k += 1
        time.sleep(max(0.0, start + k * COMMAND_PERIOD - time.monotonic()))
    node.destroy_node()
    rclpy.try_shutdown()


# -- the measuring side ---------------------------------------------------------------------------
def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _wait_until(moment: float) -> None:
    while (left := moment - time.monotonic()) > 0:
        time.sleep(min(left, 0.05))


def _popen(argv: list[str], env: dict[str, str], output) -> subprocess.Popen[str]:
    """A child whose stdout and stderr go to the file ``output``, never to a pipe.

    A pipe nobody reads until the end fills after 64 KiB, and the child then blocks in
    its next write: a recorder that logs through a burst stopped there, never caught up,
    and the identifier's status said ``acknowledged: false`` for the rest of the day.
    """
    return subprocess.Popen(argv, env=env, cwd=REPO, stdout=output, stderr=subprocess.STDOUT, text=True)


def _tail(output, lines: int) -> list[str]:
    """The last ``lines`` lines written to ``output`` (a child's log file)."""
    output.flush()
    output.seek(0)
    return output.read().strip().splitlines()[-lines:]


def live_day(probe: Probe, phases: list[dict], identifier: subprocess.Popen) -> dict:
    """What this process does to the identifier through the day, and what it measures meanwhile."""
    by_name = {phase["name"]: phase for phase in phases}
    rss: list[int] = []
    while time.monotonic() < by_name["driver alone"]["end"]:
        rss.append(_rss_kib(identifier.pid))
        time.sleep(0.5)
    _wait_until(by_name["moving, alpha changed"]["start"])
    alpha = probe.get("alpha")
    alpha_call = probe.set("alpha", 0.5 * float(alpha)) if alpha is not None else (None, False)
    burst = by_name["burst"]
    _wait_until(burst["start"])
    latencies: list[float | None] = []
    while time.monotonic() < burst["end"]:
        sent = time.monotonic()
        latencies.append(probe.set("warn_period", 5.0 + 0.5 * (len(latencies) % 2))[0])
        time.sleep(max(0.0, 0.1 - (time.monotonic() - sent)))
    _wait_until(by_name["test"]["start"])
    frozen_call = probe.set("learning", False)
    _wait_until(by_name["test"]["end"] + 1.0)
    return {"rss": rss, "latencies": latencies, "alpha_call": alpha_call, "frozen_call": frozen_call,
            "live": probe.last(time.monotonic())}  # fmt: skip


def _wait_acknowledged(probe: Probe, timeout: float = 120.0) -> float | None:
    """Seconds until a status says the recorder has every output message (``acknowledged``), None if never.

    The recorder records the burst too and falls behind; stopping the identifier before
    it caught up would leave the bag short of the test phase."""
    began = time.monotonic()
    while time.monotonic() < began + timeout:
        received, status = probe.statuses[-1] if probe.statuses else (0.0, {})
        if received > began and status.get("acknowledged"):
            return round(time.monotonic() - began, 2)
        time.sleep(0.1)
    return None


def _sigint(process: subprocess.Popen) -> float:
    """Seconds from SIGINT until the process has gone (polled every 10 ms)."""
    sent = time.monotonic()
    process.send_signal(signal.SIGINT)
    while process.poll() is None and time.monotonic() - sent < 30.0:
        time.sleep(0.01)
    return time.monotonic() - sent


def run(scale: float, solver: str | None, bag: Path, seed: int, extra: list[str]) -> dict:
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "PYTHONUNBUFFERED": "1"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    os.environ.update(env)
    settings = TOPIC_SETTINGS + ([f"solver:={solver}"] if solver else []) + extra
    identifier_argv = [sys.executable, "-m", "lenn_ros.nodes.identifier", "--ros-args", *REMAPS]
    identifier_argv += [arg for setting in settings for arg in ("-p", setting)]
    recorder_argv = [sys.executable, "-m", "lenn_ros.nodes.recorder", "--ros-args", *REMAPS, "-p", f"output:={bag}"]
    recorder_argv += ["-p", "u_type:=std_msgs/msg/Float64MultiArray", "-p", "y_type:=sensor_msgs/msg/JointState"]
    with contextlib.ExitStack() as files:
        log, recorder_log, driver_log, controller_log = (
            files.enter_context(tempfile.TemporaryFile(mode="w+")) for _ in range(4)
        )
        recorder = _popen(recorder_argv, env, recorder_log)
        identifier = _popen(identifier_argv, env, log)
        probe = Probe("robot_day_probe")
        others: list[subprocess.Popen] = []
        try:
            if not probe.setter.wait_for_service(timeout_sec=60.0):
                raise SystemExit("robot_day: the identifier's parameter service never appeared")
            phases = schedule(scale, time.monotonic() + 3.0)
            for mode, output in (("--driver", driver_log), ("--controller", controller_log)):
                argv = [sys.executable, __file__, mode, json.dumps(phases), "--seed", str(seed)]
                others.append(_popen(argv, env, output))
            day = live_day(probe, phases, identifier)
            for process in others:
                process.wait(timeout=60)
            day["recorder_caught_up_s"] = _wait_acknowledged(probe)
            day["exit_s"] = _sigint(identifier)
        finally:
            probe.close()
            for process in [identifier, *others]:
                if process.poll() is None:
                    process.kill()
                process.wait(timeout=30)
            recorder.send_signal(signal.SIGINT)
            recorder.wait(timeout=60)
        day["log"] = "\n".join(_tail(log, 10**9))
        day["driver"] = "\n".join(_tail(driver_log, 10**9))
        day["recorder"] = _tail(recorder_log, 5)
    evaluated = subprocess.run([sys.executable, "-m", "lenn_ros.cli", "evaluate", str(bag), "--json"], env=env,
                               cwd=REPO, capture_output=True, text=True, timeout=600, check=False)  # fmt: skip
    day["offline"] = json.loads(evaluated.stdout) if evaluated.returncode == 0 else {"error": evaluated.stderr.strip()}
    return summary(phases, probe, day, identifier.returncode)


def summary(phases: list[dict], probe: Probe, day: dict, exit_code: int | None) -> dict:
    """The figures of the day, per phase and at its end."""
    rows = []
    for phase in phases:
        before, after = probe.last(phase["start"]), probe.last(phase["end"])
        counters_before, counters_after = before.get("counters", {}), after.get("counters", {})
        rows.append({
            "phase": phase["name"],
            "seconds": round(phase["end"] - phase["start"], 1),
            "learned": counters_after.get("learned", 0) - counters_before.get("learned", 0),
            "paired": counters_after.get("paired", 0) - counters_before.get("paired", 0),
            "shed": counters_after.get("shed", 0) - counters_before.get("shed", 0),
            "diverged_end": after.get("diverged"),
            "phase_nmse_db_end": after.get("phase_nmse_db"),
        })  # fmt: skip
    rss = day["rss"][2 * FILLED_S :]  # sampled every 0.5 s; after the pairing queue is full
    half = len(rss) // 2
    answered = [latency for latency in day["latencies"] if latency is not None]
    offline = day["offline"]
    live = _final_status(day["log"]) or day["live"]  # the status it printed at exit: every sample it took
    return {
        "phases": rows,
        "rss_kib_first_half_mean": round(statistics.mean(rss[:half])) if half else None,
        "rss_kib_second_half_mean": round(statistics.mean(rss[half:])) if half else None,
        "rss_kib_max": max(rss, default=None),
        "alpha_call": {"latency_s": day["alpha_call"][0], "accepted": day["alpha_call"][1]},
        "learning_false_call": {"latency_s": day["frozen_call"][0], "accepted": day["frozen_call"][1]},
        "burst_calls": len(day["latencies"]),
        "burst_calls_unanswered": len(day["latencies"]) - len(answered),
        "burst_call_p50_ms": round(1e3 * statistics.median(answered), 1) if answered else None,
        "burst_call_max_ms": round(1e3 * max(answered), 1) if answered else None,
        "live_test_nmse_db": live.get("phase_nmse_db"),
        "live_test_samples": live.get("phase_samples"),
        "live_counters": live.get("counters"),
        "change": live.get("change"),  # the alarm: a healthy day raises none (issue 43)
        "offline_test_nmse_db": offline.get("nmse_db"),
        "offline": {k: v for k, v in offline.items() if k in ("nmse_db", "nmse_free_run_db", "error", "notices")},
        "recorder_caught_up_s": day["recorder_caught_up_s"],
        "recorder": day["recorder"],
        "sigint_exit_s": round(day["exit_s"], 2),
        "exit_code": exit_code,
        "identifier_log": day["log"].splitlines()[:400],
        "driver": day["driver"],
    }


def _final_status(log: str) -> dict:
    """The status the identifier prints on its way out (``identifier: {...}``), or {} if it printed none."""
    for line in reversed(log.splitlines()):
        if line.startswith("identifier: {"):
            return json.loads(line.removeprefix("identifier: "))
    return {}


def print_table(result: dict) -> None:
    print("| phase | s | paired | learned | shed | diverged at its end | phase NMSE at its end (dB) |")
    print("|---|---:|---:|---:|---:|---|---:|")
    for row in result["phases"]:
        print(f"| {row['phase']} | {row['seconds']} | {row['paired']} | {row['learned']} | {row['shed']} "
              f"| {row['diverged_end']} | {row['phase_nmse_db_end']} |")  # fmt: skip
    print(f"RSS while the command is absent: {result['rss_kib_first_half_mean']} kB (first half mean), "
          f"{result['rss_kib_second_half_mean']} kB (second half), max {result['rss_kib_max']} kB")  # fmt: skip
    print(f"parameter calls during the burst: {result['burst_calls']}, unanswered {result['burst_calls_unanswered']}, "
          f"p50 {result['burst_call_p50_ms']} ms, max {result['burst_call_max_ms']} ms")  # fmt: skip
    print(f"test phase one-step NMSE: live {result['live_test_nmse_db']} dB over {result['live_test_samples']} "
          f"samples; evaluate of the bag {result['offline_test_nmse_db']} dB")  # fmt: skip
    print(f"exit {result['sigint_exit_s']} s after SIGINT (code {result['exit_code']})")
    change = result["change"] or {}
    print(f"change alarms: {change.get('count')} (armed {change.get('armed')}, reference "
          f"{change.get('reference_nmse_db')} dB; blocks tested {change.get('blocks_tested')}, novel "
          f"{change.get('blocks_novel')}{'; ' + change['why'] if change.get('why') else ''})")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", type=float, default=1.0, help="phase lengths x this (the burst stays 5 s)")
    parser.add_argument("--solver", default=None, help="the identifier's solver (default: its own default)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bag", type=Path, default=None, help="where to record (default: a temporary directory)")
    parser.add_argument("--param", action="append", default=[], help="an extra identifier parameter, NAME:=VALUE")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--driver", metavar="PHASES", help=argparse.SUPPRESS)
    parser.add_argument("--controller", metavar="PHASES", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.driver:
        run_driver(json.loads(args.driver))
        return 0
    if args.controller:
        run_controller(json.loads(args.controller), args.seed)
        return 0
    with tempfile.TemporaryDirectory() as scratch:
        bag = args.bag or Path(scratch) / "robot_day"
        result = run(args.scale, args.solver, bag, args.seed, args.param)
    if args.json:
        print(json.dumps(result))
    else:
        print_table(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
