"""Issue 18, item 3: a flood of JointState does not starve the identifier's services or its exit.

The real identifier (README robot settings, ``pairing:=sample``) and a publisher
process sending JointState at 10 kHz (``bench/overload.py --publisher``: its own
process, so that the calls made from here are not slowed by its work). Figures
(latency p50/max at 2x and 10x capacity, recovery) are the benchmark's
(``bench/overload.py``, bench/RESULTS.md). A flood as fast as one publisher can (about
30 k/s here) is not tested: there the middleware delays the service requests
themselves, by up to 2.3 s, while the node's loop stays on time (bench/RESULTS.md).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(180)]

ROBOT = (
    "u_type:=std_msgs/msg/Float64MultiArray", "u_field:=data[0]",
    "y_type:=sensor_msgs/msg/JointState", "y_field:=position[joint1]",
    "pairing:=sample", "sample_period:=0.001", "status_period:=0.2",
    "example:=0", "y_lags:=10", "u_lags:=10", "order:=3", "cross_degree:=3", "solver:=rls", "output:=linear",
    "y_scale:=3.2", "u_scale:=3.2",
)  # fmt: skip


#: the flood: ten times the 1 kHz the node is set up for. With the README's two-lag model an idle
#: machine took in all 10 kHz without shedding (the test then failed 2 full runs of 3 on its own
#: precondition), so the model above is heavy on purpose: 1 771 terms by RLS at the 1 kHz grid, a few
#: ms a step, behind on any machine, so it must shed (parameter calls then 28-110 ms over 4 runs)
FLOOD_HZ = 10_000.0


def test_parameter_calls_are_answered_and_sigint_ends_the_node_during_a_flood(domain: int) -> None:
    from rosutil import REPO, Listener, ParameterClient, start_node

    identifier = start_node("identifier", *ROBOT, ros_args=("-r", "u:=/cmd", "-r", "y_p:=/joint_states"))
    listener = Listener(domain)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    flood = subprocess.Popen(
        [sys.executable, str(REPO / "bench" / "overload.py"), "--publisher", json.dumps([[60.0, FLOOD_HZ]])],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    try:
        with ParameterClient(domain) as parameters:
            assert flood.stdout is not None and "start" in json.loads(flood.stdout.readline())
            listener.wait_status(lambda s: s["counters"]["shed"] > 1000, timeout=60)  # overloaded: it sheds
            latencies = []
            for value in (2.0, 3.0, 2.5, 4.0, 5.0):  # a live parameter, set to a new value each time
                sent = time.monotonic()
                assert parameters.set("warn_period", value).successful
                latencies.append(time.monotonic() - sent)
            print(f"parameter calls during the flood: {[round(1e3 * t, 1) for t in latencies]} ms")
            # answered within a few of the loop's 0.1 s turns: 28-110 ms idle; 254 ms once in CI with two benchmarks
            # beside it on the two cores. Starved calls would take seconds; their speed is overload.py's to measure.
            assert max(latencies) < 0.5, latencies
        status = listener.wait_status(lambda s: s["counters"]["shed"] > 2000, timeout=30)
        assert status["counters"]["y_messages"] > 0  # it still takes the newest and learns from them
        assert identifier.poll() is None  # (setting warn_period live once stopped it at its next warning)
        sent = time.monotonic()
        identifier.send_signal(signal.SIGINT)
        while identifier.poll() is None and time.monotonic() - sent < 10.0:
            time.sleep(0.01)  # a poll of the exit, 10 ms apart
        exit_s = time.monotonic() - sent
        assert identifier.returncode == 0 and exit_s < 2.0, exit_s
    finally:
        flood.kill()
        flood.communicate()
        if identifier.poll() is None:
            identifier.kill()
        _, err = identifier.communicate()
        listener.close()
    assert "messages shed unprocessed so far" in err
