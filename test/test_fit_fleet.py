"""``lenn-ros fit-fleet`` on a real Dask cluster: a scheduler and two single-threaded workers as subprocesses.

Twelve logs of a simulated plant and one corrupt file are fitted: each model equals a serial
``lenn-ros fit`` of its log byte for byte; a worker killed once the first models are written
loses no model; the corrupt file fails in one line while the others are done; a rerun skips
every whole model. Manifests are refused in one line naming the entry and the key.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from lenn_ros.core.threads import worker_environment
from lenn_ros.fleet_fit.manifest import ManifestError, entries_from
from lenn_ros.fleet_fit.store import COMPLETE, RelocationError, relocated

distributed = pytest.importorskip(
    "distributed", reason="fit-fleet needs Dask distributed: pip install 'lenn_ros[fleet]'"
)

LOGS = 12
SAMPLES, TEST_FROM = 2500, 2001
FLAGS = ["--u", "input", "--y", "output", "--test-from", str(TEST_FROM)]
#: readiness and the runs: generous bounds on a loaded 2-core machine, never waited out when all goes well
READY, RUN = 60.0, 600.0


def plant(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A damped oscillator with a cubic stiffness, driven by smoothed noise (a small Silverbox)."""
    rng = np.random.default_rng(seed)
    u = np.convolve(rng.uniform(-1, 1, n), np.ones(3) / 3, mode="same") + 0.3
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 1.5 * y[k - 1] - 0.7 * y[k - 2] + 0.35 * u[k - 1] - 0.4 * y[k - 1] ** 3
    return u, y + 0.002 * rng.standard_normal(n)


def write_logs(folder: Path, count: int = LOGS) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for seed in range(count):
        u, y = plant(SAMPLES, seed)
        path = folder / f"joint{seed:02d}.csv"
        np.savetxt(path, np.c_[np.arange(SAMPLES), u, y], delimiter=",", header="t,input,output", comments="")
        paths.append(path)
    return paths


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def dask(*arguments: str, log: Path, prefix: list[str] | None = None) -> subprocess.Popen:
    """A ``dask`` command in a session of its own (killed with its nanny's worker as one group)."""
    env = {**os.environ, **worker_environment(1)}
    command = [*(prefix or []), str(Path(sys.executable).parent / "dask"), *arguments]
    return subprocess.Popen(command, stdout=log.open("w"), stderr=subprocess.STDOUT, env=env, start_new_session=True)


def stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGKILL)
    process.wait(timeout=30)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, list[subprocess.Popen]]]:
    """A scheduler and two ``dask worker --nthreads 1`` on 127.0.0.1, polled until both have joined."""
    logs = tmp_path_factory.mktemp("dask")
    address = f"tcp://127.0.0.1:{free_port()}"
    port = address.rsplit(":", 1)[1]
    scheduler = dask("scheduler", "--host", "127.0.0.1", "--port", port, "--no-dashboard", log=logs / "scheduler.log")
    workers = [
        dask("worker", address, "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1", log=logs / f"w{i}.log")
        for i in range(2)
    ]
    try:
        with distributed.Client(address, timeout=READY) as client:
            client.wait_for_workers(2, timeout=READY)
        yield address, workers
    finally:
        for process in [*workers, scheduler]:
            stop(process)


def fleet(source: Path, models: Path, address: str, *extra: str) -> subprocess.Popen:
    command = [sys.executable, "-m", "lenn_ros.cli", "fit-fleet", str(source), *FLAGS, "-o", str(models)]
    return subprocess.Popen([*command, "--cluster", address, *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)  # fmt: skip


def summary(models: Path) -> dict[str, dict[str, str]]:
    with (models / "summary.csv").open(newline="") as stream:
        return {row["name"]: row for row in csv.DictReader(stream)}


def whole(models: Path) -> list[str]:
    folders = models.iterdir() if models.is_dir() else []
    return sorted(p.name for p in folders if p.is_dir() and all((p / f).is_file() for f in COMPLETE))


def test_a_fleet_on_a_cluster_is_serial_fit_bit_for_bit_and_survives_a_lost_worker(tmp_path: Path, cluster) -> None:
    address, workers = cluster
    logs = write_logs(tmp_path / "logs")
    (tmp_path / "logs" / "corrupt.csv").write_text("t,input,output\n1,0.5,not-a-number-at-all,7\n\x00\x01\n")
    models = tmp_path / "models"
    run = fleet(tmp_path / "logs", models, address)
    deadline = time.monotonic() + RUN
    while not whole(models) and run.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)  # poll: the first model written
    assert whole(models), f"no model written: {run.poll()} {run.stderr.read() if run.poll() is not None else ''}"
    assert len(whole(models)) < LOGS  # (mid-run: models still to come)
    stop(workers[1])  # a worker lost mid-run, with its nanny: its entries must be fitted by the other
    out, err = run.communicate(timeout=RUN)
    assert run.returncode == 1, err  # the corrupt log failed
    rows = summary(models)
    assert whole(models) == sorted(p.stem for p in logs)
    assert {name: row["status"] for name, row in rows.items()} == {
        **{p.stem: "done" for p in logs},
        "corrupt": "failed",
    }
    assert "corrupt.csv" in rows["corrupt"]["reason"] and "corrupt: failed:" in err
    assert "12 done, 1 failed" in out
    done_by = {row["worker"] for row in rows.values() if row["status"] == "done"}
    assert len(done_by) >= 1 and all(worker.startswith("tcp://127.0.0.1:") for worker in done_by)
    for row in rows.values():
        if row["status"] == "done":
            assert float(row["nmse_free_run_db"]) < -30 and row["samples"] == str(SAMPLES - TEST_FROM + 1)

    # bit for bit what the serial command writes into the same folder (two entries: one per worker if both did some)
    chosen = {row["worker"]: name for name, row in sorted(rows.items()) if row["status"] == "done"}
    for name in list(chosen.values())[:2]:
        folder = models / name
        fleet_params = (folder / "params.yaml").read_bytes()
        with np.load(folder / "weights.npz") as fleet_weights:
            fleet_arrays = {key: fleet_weights[key] for key in fleet_weights.files}
        serial = subprocess.run([sys.executable, "-m", "lenn_ros.cli", "fit", str(tmp_path / "logs" / f"{name}.csv"),
                                 *FLAGS, "-o", str(folder)], capture_output=True, text=True, timeout=RUN)  # fmt: skip
        assert serial.returncode == 0, serial.stderr
        assert (folder / "params.yaml").read_bytes() == fleet_params
        with np.load(folder / "weights.npz") as serial_weights:
            assert sorted(serial_weights.files) == sorted(fleet_arrays)
            for key in serial_weights.files:
                assert np.array_equal(serial_weights[key], fleet_arrays[key]), f"{name}: {key}"

    # a rerun skips every whole model; the corrupt log is tried again and fails again
    rerun = fleet(tmp_path / "logs", models, address)
    out, err = rerun.communicate(timeout=RUN)
    assert rerun.returncode == 1, err
    rows = summary(models)
    assert {name: row["status"] for name, row in rows.items()} == {
        **{p.stem: "skipped" for p in logs},
        "corrupt": "failed",
    }
    assert rows[logs[0].stem]["rmse_free_run"]  # a skipped model's figures are read from its fit.json
    assert "12 skipped, 1 failed" in out


@pytest.mark.parametrize(
    ("manifest", "said"),
    [
        ({"entries": [{"name": "a", "records": ["joint00.csv"]}, {"name": "b", "recrds": ["x"]}]},
         "entry 'b': unknown key 'recrds'"),
        ({"entries": [{"name": "a", "records": ["missing.csv"]}]}, "entry 'a': key 'records': missing.csv does not"),
        ({"entries": [{"name": "a", "record": "joint00.csv", "flags": ["--bogus"]}]},
         "entry 'a': key 'flags': unrecognized arguments: --bogus"),
        ({"entries": [{"name": "a", "record": "joint00.csv", "flags": "-o elsewhere"}]},
         "entry 'a': key 'flags': -o is the fleet's"),
        ({"entries": [{"name": "a/b", "record": "joint00.csv"}]}, "entry 'a/b': key 'name'"),
        ({"entries": [{"name": "a", "record": "joint00.csv"}, {"name": "a", "record": "joint00.csv"}]},
         "entry 'a': key 'name': given to two entries"),
        ({"entries": [{"records": ["joint00.csv"]}]}, "entry 1: key 'name'"),
        ({"entry": []}, "key 'entries'"),
    ],
)  # fmt: skip
def test_a_malformed_manifest_is_refused_in_one_line_naming_the_entry_and_the_key(
    tmp_path: Path, manifest: dict, said: str
) -> None:
    write_logs(tmp_path, count=1)
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(manifest))
    from lenn_ros.cli import build_parser

    with pytest.raises(ManifestError, match=said.replace("(", r"\(")) as refused:
        entries_from(path, FLAGS, build_parser)
    assert "\n" not in str(refused.value)


def test_the_command_refuses_a_manifest_before_any_cluster_starts(tmp_path: Path) -> None:
    write_logs(tmp_path, count=1)
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump({"entries": [{"name": "arm", "records": ["joint00.csv"], "flag": []}]}))
    done = subprocess.run([sys.executable, "-m", "lenn_ros.cli", "fit-fleet", str(path), "-o", str(tmp_path / "m")],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"lenn-ros fit-fleet: error: {path}: entry 'arm': unknown key 'flag' (expected name, records, flags)"
    ]
    assert not (tmp_path / "m").exists()


def test_a_manifest_entry_is_the_serial_argv_with_the_common_flags_first(tmp_path: Path) -> None:
    write_logs(tmp_path, count=2)
    path = tmp_path / "fleet.yaml"
    entries = {
        "flags": ["--network", "lenn"],
        "entries": [{"name": "arm", "record": "joint01.csv", "flags": "--no-refine"}],
    }
    path.write_text(yaml.safe_dump(entries))
    from lenn_ros.cli import build_parser

    (entry,) = entries_from(path, FLAGS, build_parser)
    expected = ["fit", str(tmp_path / "joint01.csv"), *FLAGS, "--network", "lenn", "--no-refine", "-o", "OUT"]
    assert entry.argv("OUT") == expected
    folder = entries_from(tmp_path, FLAGS, build_parser)
    assert [e.name for e in folder] == ["joint00", "joint01"] and folder[0].flags == tuple(FLAGS)


def test_relocation_gives_the_files_their_place_or_fails_the_entry() -> None:
    scratch = "/tmp/lenn-ros-fleet-abc/arm"
    text = f"weights_in: {scratch}/weights.npz\n# --params-file {scratch}/params.yaml\n".encode()
    assert relocated(text, scratch, "/m/arm") == b"weights_in: /m/arm/weights.npz\n# --params-file /m/arm/params.yaml\n"
    with pytest.raises(RelocationError):  # a path broken over two lines is not found whole: never half relocated
        relocated(b"weights_in: /tmp/lenn-ros-fleet-abc/\n  arm/weights.npz", scratch, "/m/arm")


@pytest.mark.parametrize("logs_are", ["shared", "sent"])
def test_a_cluster_across_hosts_fits_the_logs_and_sends_the_models_back(tmp_path: Path, logs_are: str) -> None:
    """Scheduler and client in one network namespace, a worker in each of two others (test_hosts' hosts), the
    models coming back over the (virtual) network. ``shared``: the workers read the logs at the manifest's paths;
    ``sent``: the workers' own mounts hide the logs' folder (an empty tmpfs over it) and ``--send-logs`` carries
    them over the network."""
    hosts_module = pytest.importorskip("test_hosts", reason="the hosts of test_hosts (it needs rclpy)")
    refusal = hosts_module.netns_refusal()
    if refusal is not None:
        pytest.skip(f"a cluster across hosts needs network namespaces: {refusal}")
    logs = write_logs(tmp_path / "logs", count=2)
    over = 'mount -t tmpfs none "$0" && exec "$@"'  # (an empty folder over the logs', then the command)
    hidden = ["unshare", "--mount", "--propagation", "private", "sh", "-c", over, str(tmp_path / "logs")]
    hidden = hidden if logs_are == "sent" else []
    with hosts_module.Hosts(f"f{os.getpid() % 10000}", multicast=False) as hosts:
        scheduler_ns, *worker_ns = hosts.namespaces.values()
        scheduler, *workers = hosts.addresses()
        address = f"tcp://{scheduler}:8786"

        def inside(namespace: str, *argv: str, log: str, mounts: list[str] | None = None) -> subprocess.Popen:
            return dask(*argv, log=tmp_path / log, prefix=["ip", "netns", "exec", namespace, *(mounts or [])])

        if hidden:  # (the hiding holds: a worker's view of the logs' folder is empty)
            view = subprocess.run(["ip", "netns", "exec", worker_ns[0], *hidden, "ls", "-A", str(tmp_path / "logs")],
                                  capture_output=True, text=True, timeout=READY)  # fmt: skip
            assert view.returncode == 0 and view.stdout == "", (view.stdout, view.stderr)
        started = [inside(scheduler_ns, "scheduler", "--host", scheduler, "--port", "8786", "--no-dashboard",
                          log="scheduler.log")]  # fmt: skip
        started += [inside(ns, "worker", address, "--host", host, "--nthreads", "1", "--no-dashboard", log=f"{ns}.log",
                           mounts=hidden) for ns, host in zip(worker_ns, workers, strict=True)]  # fmt: skip
        try:
            ready = f"import distributed; distributed.Client({address!r}, timeout=60).wait_for_workers(2, timeout=60)"
            polled = subprocess.run(["ip", "netns", "exec", scheduler_ns, sys.executable, "-c", ready],
                                    capture_output=True, text=True, timeout=READY * 2)  # fmt: skip
            assert polled.returncode == 0, polled.stderr
            before = {role: hosts.bytes_through(role) for role in list(hosts.namespaces)[1:]}
            command = [sys.executable, "-m", "lenn_ros.cli", "fit-fleet", str(tmp_path / "logs"), *FLAGS,
                       "-o", str(tmp_path / "models"), "--cluster", address,
                       *(["--send-logs"] if logs_are == "sent" else [])]  # fmt: skip
            run = subprocess.run(["ip", "netns", "exec", scheduler_ns, *command], capture_output=True, text=True,
                                 timeout=RUN)  # fmt: skip
            assert run.returncode == 0, run.stderr
            carried = {role: hosts.bytes_through(role) - before[role] for role in before}
        finally:
            for process in started:
                stop(process)
    rows = summary(tmp_path / "models")
    assert {row["status"] for row in rows.values()} == {"done"} and len(rows) == len(logs)
    assert {row["worker"].rsplit(":", 1)[0] for row in rows.values()} <= {f"tcp://{host}" for host in workers}
    size = sum(f.stat().st_size for f in (tmp_path / "models" / logs[0].stem).iterdir())
    assert max(carried.values()) > size  # a model's files crossed the network to the client
    if logs_are == "sent":  # and a log's, to the worker
        assert max(carried.values()) > size + logs[0].stat().st_size


def _threads_seen() -> tuple[int, list[int]]:
    """What a fit on this worker would use: its threads (lenn_ros.core.threads.cores) and BLAS's."""
    from threadpoolctl import threadpool_info

    from lenn_ros.core.threads import cores
    from lenn_ros.fleet_fit.task import _the_workers_threads

    with _the_workers_threads():
        return cores(), [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


def test_a_plain_dask_worker_fits_on_its_own_threads_not_every_core(monkeypatch: pytest.MonkeyPatch) -> None:
    """``dask worker ADDRESS --nthreads 1`` started without lenn_ros's variables: its fits take its one thread (and BLAS
    one), not the host's every core; the variables, when set, win; outside a worker nothing changes."""
    monkeypatch.delenv("LENN_ROS_THREADS", raising=False)
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one core: a fit takes one thread anyway")
    with (
        distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as local,
        distributed.Client(local) as client,
    ):
        assert client.submit(_threads_seen, pure=False).result() == (1, [1] * len(_threads_seen()[1]))
        assert "LENN_ROS_THREADS" not in os.environ  # (the worker shares this process: its setting is undone)
        monkeypatch.setenv("LENN_ROS_THREADS", "2")
        assert client.submit(_threads_seen, pure=False).result()[0] == 2
    monkeypatch.delenv("LENN_ROS_THREADS")
    assert _threads_seen()[0] == len(os.sched_getaffinity(0))


def test_a_scheduler_with_no_worker_or_an_odd_one_is_refused_in_one_line() -> None:
    """Nothing is submitted to a cluster no worker joined (it would wait in silence) or where a worker runs another
    lenn_ros or none (each entry would fail on it): one line, naming the address and a worker."""
    from lenn_ros.fleet_fit.run import ClusterError, ready_workers, version_refusal

    with (
        distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as empty,
        distributed.Client(empty) as client,
    ):
        with pytest.raises(ClusterError, match=r"^--cluster \S+: no worker joined the scheduler within 0.5 s"):
            ready_workers(client, timeout=0.5)
        empty.scale(1)
        assert ready_workers(client, timeout=READY) == 1  # (a worker of this process: this lenn_ros)

    def versions(*found):
        workers = {f"tcp://10.0.0.{i}:4000": {"packages": {"lenn_ros": v}} for i, v in enumerate(found)}
        return {"client": {"packages": {"lenn_ros": "0.1.0"}}, "workers": workers}

    assert version_refusal(versions("0.1.0", "0.1.0")) == ""
    assert version_refusal(versions("0.1.0", None, "0.0.9")) == (
        "2 of 3 workers do not run this lenn_ros (0.1.0): tcp://10.0.0.1:4000 has no lenn_ros; install the same "
        "version on every worker"
    )


def serial_fit(argv: list[str], cwd: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "lenn_ros.cli", *argv], capture_output=True, text=True, cwd=cwd,
                          timeout=RUN)  # fmt: skip
    assert done.returncode == 0, done.stderr


def model_bytes(folder: Path) -> dict[str, bytes]:
    """params.yaml, every weights array and fit.json as bytes, fit.json's own timing taken out."""
    with np.load(folder / "weights.npz") as weights:
        arrays = {key: weights[key].tobytes() for key in weights.files}
    report = json.loads((folder / "fit.json").read_text())
    report.pop("seconds")
    return {"params.yaml": (folder / "params.yaml").read_bytes(), **arrays, "fit.json": json.dumps(report).encode()}


def test_sent_logs_are_fitted_from_the_workers_copy_into_the_serial_fits_very_bytes(tmp_path: Path) -> None:
    """``--send-logs``: a worker that cannot read the client's logs fits copies sent with the task (two records of
    the same file name in two folders, and a --test record given relative to the client's folder); the files come
    back naming the logs as the entry gave them: the very bytes a serial fit of the entry writes."""
    from lenn_ros.cli import build_parser
    from lenn_ros.fleet_fit.manifest import Entry
    from lenn_ros.fleet_fit.shipping import pack
    from lenn_ros.fleet_fit.store import Models
    from lenn_ros.fleet_fit.task import fit_entry

    for folder, seed in (("a", 0), ("b", 1), ("c", 2)):
        (tmp_path / "logs" / folder).mkdir(parents=True)
        (tmp_path / "logs" / folder / "joint00.csv").write_bytes(_log_text(seed))
    records = (str(tmp_path / "logs" / "a" / "joint00.csv"), str(tmp_path / "logs" / "b" / "joint00.csv"))
    flags = ("--u", "input", "--y", "output", "--test", "logs/c/joint00.csv")
    entry = Entry("arm", records, flags)
    with contextlib.chdir(tmp_path):  # the client's folder: the --test record is relative to it
        logs = pack(entry)
    assert sorted(logs) == ["0/joint00.csv", "1/joint00.csv", "2/joint00.csv"]
    (tmp_path / "logs").rename(tmp_path / "away")  # the worker's host has none of them, where the entry says
    outcome = fit_entry(entry, build_parser, logs)
    assert outcome.status == "done", outcome.reason
    assert Models(tmp_path / "models").install(outcome).status == "done"
    fleet = model_bytes(tmp_path / "models" / "arm")
    (tmp_path / "away").rename(tmp_path / "logs")
    serial_fit(list(entry.argv(str(tmp_path / "models" / "arm"))), cwd=tmp_path)
    assert model_bytes(tmp_path / "models" / "arm") == fleet
    assert b"logs/c/joint00.csv" in fleet["fit.json"] and b"lenn-ros-fleet-" not in fleet["fit.json"]


def _log_text(seed: int) -> bytes:
    u, y = plant(SAMPLES, seed)
    lines = ["t,input,output", *(f"{k},{float(a)!r},{float(b)!r}" for k, (a, b) in enumerate(zip(u, y, strict=True)))]
    return ("\n".join(lines) + "\n").encode()


def test_the_command_sends_the_logs_a_few_at_a_time_and_writes_the_serial_models(tmp_path: Path) -> None:
    """``fit-fleet DIR --send-logs`` end to end on an embedded cluster (one worker: the logs of two entries in flight):
    every model done, each one's files the serial fit's."""
    logs = write_logs(tmp_path / "logs", 3)
    models = tmp_path / "models"
    run = fleet(tmp_path / "logs", models, "local:1", "--send-logs")
    out, err = run.communicate(timeout=RUN)
    assert run.returncode == 0 and "3 done" in out, err
    assert {name: row["status"] for name, row in summary(models).items()} == {p.stem: "done" for p in logs}
    fleet_made = model_bytes(models / logs[2].stem)
    serial_fit(["fit", str(logs[2]), *FLAGS, "-o", str(models / logs[2].stem)], cwd=tmp_path)
    assert model_bytes(models / logs[2].stem) == fleet_made
