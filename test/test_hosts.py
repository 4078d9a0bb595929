"""Three hosts: simulator, identifier and recorder each in its own Linux network namespace.

Each namespace has only its loopback and one veth into a bridge that lives in a fourth
namespace, so the nodes find each other through ordinary DDS discovery (UDP multicast,
``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET``) and exchange data over UDP across the veths,
as on separate machines (Fast DDS's shared-memory transport, which would take the
short cut through ``/dev/shm`` that the namespaces still share, is switched off with
``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``). No address is added outside the namespaces.

The run must give the same live NMSE and the same recording as the same three nodes on
one host. Skipped, with the reason, where ``ip netns`` is not permitted.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(300)]

rclpy = pytest.importorskip("rclpy")

from rosutil import REPO, final_status  # noqa: E402

from lenn_ros.bag import read_run  # noqa: E402

ROLES = ("sim", "ident", "rec")
TRAIN, TEST, SEED, EXAMPLE = 2000, 300, 4, 1
SUBNET = "10.213.7"  # inside the namespaces only


def _ip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=False)


def netns_refusal() -> str | None:
    """Why ``ip netns`` cannot be used here, or None."""
    if shutil.which("ip") is None:
        return "no `ip` command (Debian's iproute2)"
    if os.geteuid() != 0:
        return "network namespaces need root"
    probe = f"lenn_probe_{os.getpid()}"
    made = _ip("netns", "add", probe)
    if made.returncode:
        return f"`ip netns add` not permitted: {made.stderr.strip()}"
    _ip("netns", "del", probe)
    return None


class Hosts:
    """One namespace per role, each with a veth into a bridge in a namespace of its own."""

    def __init__(self, tag: str, multicast: bool = True) -> None:
        self.tag = tag
        self.multicast = multicast
        self.bridge = f"lr{tag}br"
        self.namespaces = {role: f"lr{tag}{role}" for role in ROLES}
        self.made: list[str] = []

    def _must(self, *args: str) -> None:
        done = _ip(*args)
        if done.returncode:
            raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip()}")

    def __enter__(self) -> Hosts:
        try:
            for name in (self.bridge, *self.namespaces.values()):
                self._must("netns", "add", name)
                self.made.append(name)
                self._must("-n", name, "link", "set", "lo", "up")
            self._must("-n", self.bridge, "link", "add", "br0", "type", "bridge", "mcast_snooping", "0")
            self._must("-n", self.bridge, "link", "set", "br0", "up")
            for number, (role, namespace) in enumerate(self.namespaces.items(), start=1):
                port, host_end = f"port{number}", f"to{role}"
                self._must("-n", self.bridge, "link", "add", port, "type", "veth", "peer", "name", host_end)
                self._must("-n", self.bridge, "link", "set", host_end, "netns", namespace)
                self._must("-n", self.bridge, "link", "set", port, "master", "br0", "up")
                self._must("-n", namespace, "link", "set", host_end, "name", "eth0")
                self._must("-n", namespace, "addr", "add", f"{SUBNET}.{number}/24", "dev", "eth0")
                self._must("-n", namespace, "link", "set", "eth0", "up", "multicast", "on" if self.multicast else "off")
                if self.multicast:
                    self._must("-n", namespace, "route", "add", "224.0.0.0/4", "dev", "eth0")  # discovery's multicast
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *_: object) -> None:
        for name in reversed(self.made):  # deleting a namespace deletes its veth ends
            _ip("netns", "del", name)
        self.made = []

    def addresses(self) -> list[str]:
        return [f"{SUBNET}.{number}" for number in range(1, len(ROLES) + 1)]

    def bytes_through(self, role: str) -> int:
        """Bytes received plus sent on the role's only network interface."""
        stats = json.loads(_ip("-n", self.namespaces[role], "-s", "-j", "link", "show", "eth0").stdout)[0]["stats64"]
        return int(stats["rx"]["bytes"]) + int(stats["tx"]["bytes"])


def node_argv(module: str, *params: str) -> list[str]:
    args = [sys.executable, "-m", f"lenn_ros.nodes.{module}", "--ros-args"]
    for param in params:
        args += ["-p", param]
    return args


def run_graph(bag: Path, env: dict[str, str], prefix: dict[str, list[str]]) -> tuple[dict, str]:
    """Recorder, identifier, lockstep simulator; returns the identifier's final status and its log."""

    def start(role: str, argv: list[str]) -> subprocess.Popen[str]:
        return subprocess.Popen(
            prefix[role] + argv, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )

    recorder = start("rec", node_argv("recorder", f"output:={bag}"))
    identifier = start(
        "ident",
        node_argv(
            "identifier",
            f"example:={EXAMPLE}",
            f"seed:={SEED}",
            "wait_for_y_hat_subscribers:=2",  # the simulator (lockstep) and the recorder
            "wait_for_error_subscribers:=1",
            "wait_for_samples_subscribers:=1",
        ),
    )
    simulator = start(
        "sim",
        node_argv(
            "plant_simulator",
            f"example:={EXAMPLE}",
            f"seed:={SEED}",
            f"train_samples:={TRAIN}",
            f"test_samples:={TEST}",
            # paced: at full speed the static-peers recording once held 1 550 of 2 298 error messages (a local CI
            # run, 2026-12-07; not reproduced in 2 reruns, cause not established); the test is about equality
            "rate_hz:=500.0",
            "wait_for_subscribers:=2",
            "exit_when_done:=true",
        ),
    )
    processes = (simulator, identifier, recorder)
    try:
        _, sim_err = simulator.communicate(timeout=180)
        assert simulator.returncode == 0, sim_err[-2000:]
        identifier.send_signal(signal.SIGINT)
        _, ident_err = identifier.communicate(timeout=30)
        recorder.send_signal(signal.SIGINT)
        _, rec_err = recorder.communicate(timeout=30)
        assert recorder.returncode == 0, rec_err[-2000:]
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.communicate()
    return final_status(ident_err), ident_err


@pytest.fixture
def netns() -> None:
    refusal = netns_refusal()
    if refusal is not None:
        pytest.skip(f"three-host test needs network namespaces: {refusal}")


def across_hosts(hosts: Hosts, bag: Path, env: dict[str, str]) -> tuple[dict, str, dict[str, int]]:
    """:func:`run_graph` with each role in its namespace; also the bytes each one's interface carried."""
    before = {role: hosts.bytes_through(role) for role in ROLES}
    prefix = {role: ["ip", "netns", "exec", namespace] for role, namespace in hosts.namespaces.items()}
    status, log = run_graph(bag, env, prefix)
    return status, log, {role: hosts.bytes_through(role) - before[role] for role in ROLES}


def test_three_hosts_give_the_one_host_result(tmp_path: Path, domain: int, netns: None) -> None:
    """Same live NMSE, same recording, with every sample crossing a (virtual) network.

    Twice: discovery by multicast (the default on a LAN), and with multicast off on
    every interface, by unicast to ``ROS_STATIC_PEERS`` (a network without multicast).
    """
    base = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    base["PYTHONUNBUFFERED"] = "1"
    local = {**base, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    one_host, _ = run_graph(tmp_path / "one_host", local, {role: [] for role in ROLES})
    # across the namespaces: discovery on the subnet, data over UDP only
    remote = {**base, "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
    tag = str(os.getpid() % 100000)
    runs = {}
    with Hosts(tag) as hosts:
        runs["multicast"] = across_hosts(hosts, tmp_path / "multicast", remote)
    with Hosts(tag, multicast=False) as hosts:
        peers = {**remote, "ROS_STATIC_PEERS": ";".join(hosts.addresses())}
        runs["static_peers"] = across_hosts(hosts, tmp_path / "static_peers", peers)
    total = TRAIN + TEST
    for status in (one_host, *(run[0] for run in runs.values())):
        counters = status["counters"]
        assert counters["paired"] == counters["samples"] == total, counters
        assert counters["lost"] == counters["unpaired"] == counters["stale"] == 0, counters
    recorded = read_run(tmp_path / "one_host")
    for name, (status, log, crossed) in runs.items():
        assert status["phase_samples"] == one_host["phase_samples"] == TEST, name
        assert status["phase_nmse_db"] == one_host["phase_nmse_db"], (name, log[-2000:])
        # every message went over the wire: each host sends or receives u, y_p and y_hat of every sample, and
        # an RTPS message carrying one Float64 is over 60 bytes (measured: about 900 bytes per sample per host)
        assert all(count > 3 * total * 60 for count in crossed.values()), (name, crossed)
        run = read_run(tmp_path / name)
        for topic in ("u", "y_p", "y_hat", "error"):
            here, there = getattr(recorded, topic), getattr(run, topic)
            assert here.size >= TEST and np.array_equal(here, there), (name, topic)
        assert run.test_start == recorded.test_start == TRAIN + 1, name
