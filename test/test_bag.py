"""lenn_ros.bag against real MCAP files, checked with an independent reader (mcap + mcap_ros2)."""

from __future__ import annotations

import os
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2.metadata import parse_qos

from lenn_ros import topics
from lenn_ros.bag import BagError, BagWriter, bag_info, default_qos, import_csv, read_run, recover

N = 400


def write_run(path: Path, n: int = N, *, chunk: int = 2000, test_start: int | None = 300) -> Path:
    """A run with u(k) = k/10, y_p(k) = -k, y_hat(k) = k + 0.5 at log time k ms; small chunks."""
    with BagWriter(path, flush_period=None, max_chunk_size=chunk) as bag:
        for name in ("/u", "/y_p", "/y_hat", "/test_start"):
            bag.add_topic(name)
        if test_start is not None:
            bag.write_value("/test_start", test_start, 0)
        for k in range(n):
            t = k * 1_000_000
            bag.write_value("/u", k / 10, t)
            bag.write_value("/y_p", -float(k), t)
            bag.write_value("/y_hat", k + 0.5, t + 1)
    return path


def independent_read(mcap_file: Path) -> dict[str, list[tuple[int, float]]]:
    """(log time, value) per topic, decoded by the mcap package (needs a complete file)."""
    out: dict[str, list[tuple[int, float]]] = {}
    with mcap_file.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((message.log_time, getattr(decoded, "data", None)))
    return out


def complete_chunk_counts(mcap_file: Path) -> Counter[str]:
    """Messages per topic in the *whole* chunks of a possibly unfinished file (independent parser)."""
    counts: Counter[str] = Counter()
    channels: dict[int, str] = {}
    with mcap_file.open("rb") as f:
        try:
            for record in StreamReader(f, emit_chunks=True).records:
                if not isinstance(record, Chunk) or len(record.data) != record.uncompressed_size:
                    continue
                for inner in breakup_chunk(record):
                    if isinstance(inner, Channel):
                        channels[inner.id] = inner.topic
                    elif isinstance(inner, Message):
                        counts[channels[inner.channel_id]] += 1
        except Exception:  # the unfinished end of the file
            pass
    return counts


def test_round_trip(tmp_path: Path) -> None:
    run = read_run(write_run(tmp_path / "run"))
    k = np.arange(N)
    np.testing.assert_array_equal(run.u, k / 10)
    np.testing.assert_array_equal(run.y_p, -k.astype(float))
    np.testing.assert_array_equal(run.y_hat, k + 0.5)
    np.testing.assert_array_equal(run.u_t, k * 1_000_000)
    np.testing.assert_array_equal(run.y_hat_t, k * 1_000_000 + 1)
    assert run.error is None and run.error_t is None  # absent, not silently empty
    assert run.test_start == 300
    assert run.topics[topics.U] == "/u"


def test_independent_reader_agrees(tmp_path: Path) -> None:
    bag = write_run(tmp_path / "run")
    ours = read_run(bag)
    theirs = independent_read(bag / "run.mcap")
    assert [v for _, v in theirs["/u"]] == ours.u.tolist()
    assert [v for _, v in theirs["/y_p"]] == ours.y_p.tolist()
    assert [t for t, _ in theirs["/y_hat"]] == ours.y_hat_t.tolist()
    assert theirs["/test_start"] == [(0, 300)]


def test_offered_qos_is_stored(tmp_path: Path) -> None:
    bag = write_run(tmp_path / "run")
    with (bag / "run.mcap").open("rb") as f:
        channels = {c.topic: c for c in make_reader(f).get_summary().channels.values()}
    data = parse_qos(channels["/u"].metadata["offered_qos_profiles"])
    latched = parse_qos(channels["/test_start"].metadata["offered_qos_profiles"])
    assert data == [default_qos(topics.RUN_TOPICS[0])]
    assert data[0].depth == topics.DATA_DEPTH and data[0].reliability.name == "RELIABLE"
    assert latched[0].durability.name == "TRANSIENT_LOCAL" and latched[0].depth == 1
    info = bag_info(bag)
    assert info["topics"]["/u"]["offered_qos"][0]["durability"] == "volatile"


def test_default_qos_mirrors_topics_module() -> None:
    pytest.importorskip("rclpy")
    from lenn_ros.bag import qos_from_profile

    for spec in topics.RUN_TOPICS:
        assert qos_from_profile(topics.qos_for(spec)) == default_qos(spec), spec.name


def test_raw_cdr_from_rclpy(tmp_path: Path) -> None:
    """What a raw=True subscription hands the recorder is written unchanged and reads back."""
    pytest.importorskip("rclpy")
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64

    with BagWriter(tmp_path / "raw") as bag:
        bag.add_topic("/u")
        bag.add_topic("/y_p")
        for k in range(5):
            bag.write_raw("/u", serialize_message(Float64(data=k * 1.5)), k)
            bag.write_raw("/y_p", serialize_message(Float64(data=-k * 1.5)), k)
    assert read_run(tmp_path / "raw").u.tolist() == [0.0, 1.5, 3.0, 4.5, 6.0]


def test_bag_info(tmp_path: Path) -> None:
    info = bag_info(write_run(tmp_path / "run"))
    assert info["storage"] == "mcap"
    assert info["message_count"] == 3 * N + 1
    assert info["topics"]["/y_p"] == {**info["topics"]["/y_p"], "type": topics.FLOAT64, "count": N}
    assert info["topics"]["/test_start"]["type"] == topics.INT64
    assert info["duration_s"] == pytest.approx((N - 1) * 1e-3, abs=1e-8)


# ---------------------------------------------------------------- crash bound and recovery


def test_unclosed_writer_has_every_flushed_message_on_disk(tmp_path: Path) -> None:
    """The SIGKILL bound: what ``flushed_counts`` reports is already in whole chunks on disk."""
    bag = BagWriter(tmp_path / "live", flush_period=0.05, max_chunk_size=10**9).open()
    try:
        bag.add_topic("/u")
        for k in range(50):
            bag.write_value("/u", float(k), k)
        assert complete_chunk_counts(bag.mcap_path)["/u"] == 0  # nothing flushed yet: still in memory
        assert bag.maybe_flush(now=1e12)  # the flush period has passed
        for k in range(50, 60):
            bag.write_value("/u", float(k), k)
        assert bag.flushed_counts["/u"] == 50
        assert complete_chunk_counts(bag.mcap_path)["/u"] == 50
        # A "killed" copy of the open file recovers exactly the flushed messages.
        killed = tmp_path / "killed"
        killed.mkdir()
        shutil.copy(bag.mcap_path, killed / "killed.mcap")
        report = recover(killed)
        assert report.messages == {"/u": 50} and not report.was_complete
        assert read_run(killed, require=("u",)).u.tolist() == [float(k) for k in range(50)]
    finally:
        bag.close()
    assert read_run(tmp_path / "live", require=("u",)).u.size == 60


def test_chunk_size_bound(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "b", flush_period=None, max_chunk_size=1024) as bag:
        bag.add_topic("/u")
        for k in range(100):
            bag.write_value("/u", float(k), k)
            # A Float64 message record is 43 bytes: the unflushed tail stays within ~1024 bytes of them.
            assert bag.counts["/u"] - bag.flushed_counts["/u"] <= 1024 // 43 + 1


def cut_copy(bag: Path, dest: Path, fraction: float) -> Path:
    dest.mkdir()
    data = (bag / f"{bag.name}.mcap").read_bytes()
    (dest / f"{dest.name}.mcap").write_bytes(data[: int(len(data) * fraction)])
    return dest


def test_recover_truncated_file(tmp_path: Path) -> None:
    original = read_run(write_run(tmp_path / "run"))
    cut = cut_copy(tmp_path / "run", tmp_path / "cut", 0.6)
    with pytest.raises(BagError, match=r"bag-repair .*cut"):
        read_run(cut)
    report = recover(cut)
    assert 0 < report.messages["/u"] < N and 0 < report.messages["/y_p"] < N
    assert report.messages["/test_start"] == 1 and not report.was_complete
    assert report.source.name == "cut.mcap.damaged" and report.source.exists()
    repaired = read_run(cut)
    # A prefix, in order, values untouched.
    np.testing.assert_array_equal(repaired.u, original.u[: repaired.u.size])
    np.testing.assert_array_equal(repaired.y_p, original.y_p[: repaired.y_p.size])
    np.testing.assert_array_equal(repaired.u_t, original.u_t[: repaired.u.size])
    assert repaired.test_start == 300
    theirs = independent_read(cut / "cut.mcap")  # needs the summary and footer we rewrote
    assert len(theirs["/u"]) == report.messages["/u"]
    assert bag_info(cut)["topics"]["/u"]["offered_qos"][0]["depth"] == topics.DATA_DEPTH


def test_recover_to_new_path_leaves_source(tmp_path: Path) -> None:
    write_run(tmp_path / "run")
    cut = cut_copy(tmp_path / "run", tmp_path / "cut", 0.5)
    before = (cut / "cut.mcap").read_bytes()
    report = recover(cut / "cut.mcap", out=tmp_path / "fixed")
    assert (cut / "cut.mcap").read_bytes() == before
    assert read_run(tmp_path / "fixed").u.size == report.messages["/u"] > 0


def test_recover_complete_file_keeps_everything(tmp_path: Path) -> None:
    write_run(tmp_path / "run")
    (tmp_path / "run" / "metadata.yaml").unlink()
    report = recover(tmp_path / "run")
    assert report.was_complete and report.messages["/u"] == N
    assert read_run(tmp_path / "run").u.size == N


def test_recover_nothing_flushed(tmp_path: Path) -> None:
    write_run(tmp_path / "run")
    cut = cut_copy(tmp_path / "run", tmp_path / "cut", 0.001)
    with pytest.raises(BagError, match="no complete chunk"):
        recover(cut)


# ---------------------------------------------------------------- malformed inputs


def make_bag(path: Path, spec: dict[str, tuple[str, list]]) -> Path:
    with BagWriter(path) as bag:
        for name, (type_name, _values) in spec.items():
            bag.add_topic(name, type_name)
        for name, (type_name, values) in spec.items():
            for k, value in enumerate(values):
                if type_name == "std_msgs/msg/Float32":
                    from rosbags.typesys import Stores, get_typestore

                    store = get_typestore(Stores.ROS2_JAZZY)
                    raw = store.serialize_cdr(store.types[type_name](data=value), type_name)
                    bag.write_raw(name, raw, k)
                else:
                    bag.write_value(name, value, k)
    return path


def corrupt_footer(tmp_path: Path) -> Path:
    bag = write_run(tmp_path / "bad")
    file = bag / "bad.mcap"
    data = bytearray(file.read_bytes())
    data[-37 + 9 : -37 + 17] = (10**12).to_bytes(8, "little")  # summary offset far past the end
    file.write_bytes(bytes(data))
    return bag


def truncated_with_metadata(tmp_path: Path) -> Path:
    bag = write_run(tmp_path / "trunc")
    file = bag / "trunc.mcap"
    file.write_bytes(file.read_bytes()[:-100])
    return bag


CASES = {
    "missing path": (lambda p: p / "nope", r"no such file or directory"),
    "empty directory": (lambda p: (p / "empty").mkdir() or p / "empty", r"not a rosbag2 bag"),
    "not mcap suffix": (lambda p: (p / "x.csv").write_text("a,b\n") and p / "x.csv", r"not a rosbag2 bag"),
    "not mcap content": (lambda p: (p / "x.mcap").write_text("hello" * 20) and p / "x.mcap", r"not an MCAP file"),
    "truncated": (truncated_with_metadata, r"truncated MCAP file .* bag-repair"),
    "corrupt": (corrupt_footer, r"corrupt or unreadable bag .* bag-repair"),
    "missing topic": (
        lambda p: make_bag(p / "b", {"/u": (topics.FLOAT64, [1.0])}),
        r"required topic 'y_p' is missing \(topics in bag: /u\)",
    ),
    "wrong type": (
        lambda p: make_bag(p / "b", {"/u": (topics.FLOAT64, [1.0]), "/y_p": ("std_msgs/msg/Float32", [1.0])}),
        r"topic '/y_p' has type std_msgs/msg/Float32, expected std_msgs/msg/Float64",
    ),
    "no messages": (
        lambda p: make_bag(p / "b", {"/u": (topics.FLOAT64, [1.0]), "/y_p": (topics.FLOAT64, [])}),
        r"topic '/y_p' has no messages",
    ),
}


@pytest.mark.parametrize("case", CASES)
def test_read_run_errors(tmp_path: Path, case: str) -> None:
    build, pattern = CASES[case]
    path = build(tmp_path)
    with pytest.raises(BagError, match=pattern) as err:
        read_run(path)
    assert "\n" not in str(err.value)


def test_writer_refuses_to_overwrite(tmp_path: Path) -> None:
    write_run(tmp_path / "run")
    with pytest.raises(BagError, match="already exists"):
        BagWriter(tmp_path / "run").open()


# ---------------------------------------------------------------- import_csv


def test_import_csv_by_name_with_test_start(tmp_path: Path) -> None:
    csv = tmp_path / "log.csv"
    csv.write_text("time,input,output\n" + "".join(f"{k * 0.01},{k},{2 * k}\n" for k in range(20)))
    bag = import_csv(csv, "input", "output", 0.01, tmp_path / "bag", test_from=15)
    run = read_run(bag)
    assert run.u.tolist() == [float(k) for k in range(20)]
    assert run.y_p.tolist() == [2.0 * k for k in range(20)]
    assert run.u_t[:3].tolist() == [0, 10_000_000, 20_000_000]
    assert run.test_start == 15


def test_import_csv_by_index_without_header(tmp_path: Path) -> None:
    csv = tmp_path / "log.csv"
    csv.write_text("".join(f"{k};{-k}\n" for k in range(5)))
    run = read_run(import_csv(csv, 1, "0", 0.5, tmp_path / "bag"))
    assert run.u.tolist() == [0.0, -1.0, -2.0, -3.0, -4.0]
    assert run.y_p.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert run.test_start is None


@pytest.mark.parametrize(
    ("text", "u", "y", "kwargs", "pattern"),
    [
        ("a,b\n1,2\n", "a", "c", {}, r"no column 'c' \(columns: a, b\)"),
        ("a,b\n1,2\n3,x\n", "a", "b", {}, r"line 3, column 'b': 'x' is not a number"),
        ("a,b\n1,2\n3,nan\n", "a", "b", {}, r"line 3 has no number in a column asked for .*a run bag has no gaps"),
        ("a,b\n1,2\n3\n", "a", "b", {}, r"line 3 has no number in a column asked for \(empty, NaN, inf or short\)"),
        ("a,b\n1,2\n", "a", "b", {"test_from": 5}, r"test_from=5 is outside samples 1..1"),
        ("a,b\n1,2\n", "a", "b", {"test_from": 0}, r"test_from=0 is outside samples 1..1 .*1-based"),
        ("a,b\n", "a", "b", {}, r"no data rows"),
        ("1,2\n", 0, 7, {}, r"no column '7' \(columns: no header row, indices 0..1\)"),
    ],
)
def test_import_csv_errors(tmp_path: Path, text: str, u: str | int, y: str | int, kwargs: dict, pattern: str) -> None:
    csv = tmp_path / "log.csv"
    csv.write_text(text)
    with pytest.raises(BagError, match=pattern):
        import_csv(csv, u, y, 0.1, tmp_path / "bag", **kwargs)
    assert not (tmp_path / "bag").exists()


# ---------------------------------------------------------------- any message type, sequence numbers, fast path


def typestore_message(type_name: str, **fields: object) -> object:
    from lenn_ros.bag.msgtypes import TYPESTORE

    return TYPESTORE.types[type_name](**fields)


def stamp(sec: int) -> object:
    time_msg = typestore_message("builtin_interfaces/msg/Time", sec=sec, nanosec=7)
    return typestore_message("std_msgs/msg/Header", stamp=time_msg, frame_id="base")


def vector(x: float) -> object:
    return typestore_message("geometry_msgs/msg/Vector3", x=x, y=0.0, z=-x)


ROBOT_MESSAGES = {
    "/robot/joint_states": lambda k: typestore_message(
        "sensor_msgs/msg/JointState",
        header=stamp(k),
        name=["shoulder", "elbow"],
        position=np.array([k, -k], dtype=float),
        velocity=np.array([], dtype=float),
        effort=np.array([], dtype=float),
    ),
    "/robot/cmd": lambda k: typestore_message(
        "std_msgs/msg/Float64MultiArray",
        layout=typestore_message("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0),
        data=np.array([k, 0.5 * k]),
    ),
    "/robot/twist": lambda k: typestore_message(
        "geometry_msgs/msg/TwistStamped",
        header=stamp(k),
        twist=typestore_message("geometry_msgs/msg/Twist", linear=vector(k), angular=vector(0.0)),
    ),
    "/robot/wrench": lambda k: typestore_message(
        "geometry_msgs/msg/WrenchStamped",
        header=stamp(k),
        wrench=typestore_message("geometry_msgs/msg/Wrench", force=vector(k), torque=vector(1.0)),
    ),
}


def write_robot_bag(path: Path, n: int = 20) -> Path:
    with BagWriter(path) as bag:
        for topic, make in ROBOT_MESSAGES.items():
            bag.add_topic(topic, make(0).__msgtype__)
        for k in range(n):
            for j, (topic, make) in enumerate(ROBOT_MESSAGES.items()):
                t = k * 10_000_000 + j
                bag.write_message(topic, make(k), t, publish_time_ns=t - 1 if t else 0, sequence=k + 1)
    return path


def test_any_type_read_back_by_three_readers(tmp_path: Path) -> None:
    """Stamped and vector messages: ours, rosbags' AnyReader and mcap_ros2 all decode the same values."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from lenn_ros.bag import iter_messages, topic_types

    bag = write_robot_bag(tmp_path / "robot")
    assert topic_types(bag)["/robot/wrench"] == "geometry_msgs/msg/WrenchStamped"
    ours = list(iter_messages(bag))
    assert [m.log_time_ns for m in ours] == sorted(m.log_time_ns for m in ours)
    joints = [m for m in ours if m.topic == "/robot/joint_states"]
    assert [m.message.position[1] for m in joints] == [-float(k) for k in range(20)]
    assert joints[3].message.header.stamp.sec == 3 and joints[3].message.name == ["shoulder", "elbow"]
    assert [m.sequence for m in joints] == list(range(1, 21))
    assert joints[2].publish_time_ns == joints[2].log_time_ns - 1
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        forces = [reader.deserialize(raw, c.msgtype).wrench.force.x for c, _t, raw in reader.messages()
                  if c.topic == "/robot/wrench"]  # fmt: skip
    assert forces == [float(k) for k in range(20)]
    with (bag / "robot.mcap").open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = [(c.topic, m, d) for s, c, m, d in reader.iter_decoded_messages(log_time_order=True)]
    assert [d.twist.linear.z for t, _m, d in decoded if t == "/robot/twist"] == [-float(k) for k in range(20)]
    assert [m.sequence for t, m, _d in decoded if t == "/robot/cmd"] == list(range(1, 21))
    assert [list(d.data) for t, _m, d in decoded if t == "/robot/cmd"][5] == [5.0, 2.5]


def test_type_from_an_installed_msg_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A type rosbags does not know is taken from <prefix>/share/<pkg>/msg; the stored msgdef decodes."""
    from lenn_ros.bag import iter_messages
    from lenn_ros.bag.msgtypes import TYPESTORE, ensure_type

    share = tmp_path / "prefix" / "share" / "lenn_test_msgs" / "msg"
    share.mkdir(parents=True)
    (share / "Inner.msg").write_text("float64 gain\nstring label\n")
    (share / "Reading.msg").write_text("# a custom sensor\nstd_msgs/Header header\nfloat64[] values\nInner inner\n"
                                       "int32 LIMIT=3\n")  # fmt: skip
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "prefix"))
    ensure_type("lenn_test_msgs/msg/Reading")
    inner = TYPESTORE.types["lenn_test_msgs/msg/Inner"](gain=2.5, label="x")
    reading = TYPESTORE.types["lenn_test_msgs/msg/Reading"](header=stamp(1), values=np.array([1.0, 2.0]), inner=inner)
    with BagWriter(tmp_path / "custom") as bag:
        bag.add_topic("/reading", "lenn_test_msgs/msg/Reading")
        bag.write_message("/reading", reading, 5)
    with (tmp_path / "custom" / "custom.mcap").open("rb") as f:
        decoded = [d for *_rest, d in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    assert decoded[0].inner.gain == 2.5 and list(decoded[0].values) == [1.0, 2.0]
    assert next(iter_messages(tmp_path / "custom")).message.inner.label == "x"
    # A fresh process without the package: the type comes from the bag's own schema text.
    import subprocess
    import sys

    code = "import sys; from lenn_ros.bag import iter_messages; m = next(iter_messages(sys.argv[1])).message; "
    code += "print(m.inner.label, m.values.tolist(), m.header.stamp.sec)"
    env = {k: v for k, v in os.environ.items() if k != "AMENT_PREFIX_PATH"}
    command = [sys.executable, "-c", code, str(tmp_path / "custom")]
    out = subprocess.run(command, capture_output=True, text=True, env=env, cwd=Path(__file__).parents[1])
    assert out.stdout.split() == ["x", "[1.0,", "2.0]", "1"], out.stderr
    with pytest.raises(BagError, match=r"'lenn_test_msgs/msg/Nope' is unknown.*install its message package"):
        BagWriter(tmp_path / "other").open().add_topic("/x", "lenn_test_msgs/msg/Nope")


def test_lost_and_reordered_messages_are_counted(tmp_path: Path) -> None:
    """A bag whose u lost sequence numbers 4 and 7 and got 9 before 8: read in order, reported."""
    from lenn_ros.bag import sequence_gaps

    sent = [1, 2, 3, 5, 6, 9, 8, 10]
    with BagWriter(tmp_path / "lossy") as bag:
        bag.add_topic("/u")
        bag.add_topic("/y_p")
        for k, seq in enumerate(sent):
            bag.write_value("/u", float(seq), 1000 * k, publish_time_ns=1000 * k, sequence=seq)
        for seq in range(1, 11):
            bag.write_value("/y_p", -float(seq), 1000 * seq, sequence=seq)
    run = read_run(tmp_path / "lossy")
    assert run.u_sequence.tolist() == sent and run.u.tolist() == [float(s) for s in sent]
    assert run.y_p_sequence.tolist() == list(range(1, 11))
    info = bag_info(tmp_path / "lossy")
    assert info["topics"]["/u"]["missing"] == 3 - 1  # 4 and 7 (8 arrived late, not lost)
    assert info["topics"]["/u"]["reordered"] == 1
    assert info["topics"]["/y_p"]["missing"] == 0 and info["missing"] == 2
    assert info["topics"]["/u"]["first_ns"] == 0 and info["topics"]["/u"]["last_ns"] == 7000
    # a restarted publisher starts a new run; a late-started recorder is no loss; no numbers: unknown
    assert sequence_gaps(np.array([5, 6, 8, 1, 2, 4]))["missing"] == 2
    assert sequence_gaps(np.array([5, 6, 8, 1, 2, 4]))["restarts"] == 1
    assert sequence_gaps(np.zeros(4, np.int64))["missing"] is None


def test_fast_path_equals_general_reader(tmp_path: Path) -> None:
    """The numpy decoding gives what per-message deserialisation gives, for every scalar type."""
    from lenn_ros.bag.reader import read_summary
    from lenn_ros.bag.scalars import SCALAR_TYPES, _bulk, _slow

    values = [0, 1, 127, 3, 42]
    with BagWriter(tmp_path / "types", max_chunk_size=200) as bag:  # several chunks
        for type_name in SCALAR_TYPES:
            bag.add_topic("/" + type_name.rsplit("/", 1)[-1].lower(), type_name)
        for k, value in enumerate(values):
            for type_name in SCALAR_TYPES:
                topic = "/" + type_name.rsplit("/", 1)[-1].lower()
                data = bool(value) if type_name.endswith("Bool") else value
                if type_name.endswith(("Byte", "Char")):
                    data = value
                bag.write_message(topic, typestore_message(type_name, data=data), k, sequence=k + 1)
    file, summary = read_summary(tmp_path / "types")
    assert len(summary.chunk_indexes) > 1
    for channel in summary.channels.values():
        type_name = summary.schemas[channel.schema_id].name
        fast = _bulk(file, summary, channel.id, type_name)
        slow = _slow(tmp_path / "types", channel.topic, True)
        np.testing.assert_array_equal(fast.values, slow.values.astype(float), err_msg=channel.topic)
        np.testing.assert_array_equal(fast.sequence, slow.sequence)
        np.testing.assert_array_equal(fast.log_time_ns, slow.log_time_ns)


def test_samples_and_varying_arrays(tmp_path: Path) -> None:
    """read_samples decodes the identifier's rows; arrays whose layout varies take the general path."""
    from lenn_ros.bag import read_samples

    def row(k: int, labelled: bool) -> object:
        dims = [typestore_message("std_msgs/msg/MultiArrayDimension", label="index" * labelled, size=5, stride=5)]
        layout = typestore_message("std_msgs/msg/MultiArrayLayout", dim=dims, data_offset=0)
        return typestore_message(
            "std_msgs/msg/Float64MultiArray", layout=layout, data=np.array([k + 1, k / 100, k, -k, k % 2])
        )

    for name, labelled in (("same", lambda k: True), ("varying", lambda k: k % 3 == 0)):
        with BagWriter(tmp_path / name) as bag:
            bag.add_topic("/id3/samples")
            for k in range(30):
                bag.write_message("/id3/samples", row(k, labelled(k)), 1000 + k)
        samples = read_samples(tmp_path / name)
        assert samples is not None and samples.topic == "/id3/samples"
        assert samples.index.tolist() == list(range(1, 31)) and samples.index.dtype == np.int64
        assert samples.y_p.tolist() == [-float(k) for k in range(30)]
        assert samples.learn.tolist() == [bool(k % 2) for k in range(30)]
        assert samples.log_time_ns.tolist() == list(range(1000, 1030))
    assert read_samples(write_run(tmp_path / "run")) is None


def test_namespaced_run(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "ns") as bag:
        for ns in ("/id3", "/id4"):
            bag.add_topic(f"{ns}/u")
            bag.add_topic(f"{ns}/y_p")
            for k in range(3):
                bag.write_value(f"{ns}/u", float(k) + (ns == "/id4"), k)
                bag.write_value(f"{ns}/y_p", -float(k), k)
    with pytest.raises(BagError, match=r"several topics end in 'u'.*namespace="):
        read_run(tmp_path / "ns")
    run = read_run(tmp_path / "ns", namespace="/id4")
    assert run.u.tolist() == [1.0, 2.0, 3.0] and run.topics[topics.U] == "/id4/u"


def test_repair_keeps_sequence_and_publish_time(tmp_path: Path) -> None:
    """A cut-off uncompressed chunk gives up its whole messages, with their record fields."""
    from lenn_ros.bag import iter_messages

    with BagWriter(tmp_path / "big", flush_period=None) as bag:  # one big chunk
        bag.add_topic("/u")
        for k in range(500):
            bag.write_value("/u", float(k), 10 * k, publish_time_ns=10 * k + 3, sequence=k + 1)
    cut = cut_copy(tmp_path / "big", tmp_path / "cut", 0.5)
    report = recover(cut)
    assert 100 < report.messages["/u"] < 500 and "cut off" in report.stop_reason
    messages = list(iter_messages(cut))
    assert [m.sequence for m in messages] == list(range(1, len(messages) + 1))
    assert all(m.publish_time_ns == m.log_time_ns + 3 for m in messages)


@pytest.mark.parametrize("compression", ["ZSTD", "LZ4", "NONE"])
def test_bag_from_another_writer(tmp_path: Path, compression: str) -> None:
    """An .mcap written by mcap_ros2's writer (compressed chunks): same series through the fast path."""
    from mcap.writer import CompressionType
    from mcap_ros2.writer import Writer as Ros2Writer

    from lenn_ros.bag.reader import read_summary
    from lenn_ros.bag.scalars import _bulk

    bag = tmp_path / "other"
    bag.mkdir()
    with (bag / "other.mcap").open("wb") as f:
        writer = Ros2Writer(f, chunk_size=512, compression=CompressionType[compression])
        schema = writer.register_msgdef("std_msgs/msg/Float64", "float64 data\n")
        for k in range(100):
            writer.write_message("/u", schema, {"data": k / 4}, log_time=k, publish_time=k, sequence=k + 1)
            writer.write_message("/y_p", schema, {"data": -k / 4}, log_time=k, publish_time=k, sequence=k + 1)
        writer.finish()
    run = read_run(bag)  # no metadata.yaml: the single .mcap is read
    assert run.u.tolist() == [k / 4 for k in range(100)] and run.y_p_sequence.tolist() == list(range(1, 101))
    file, summary = read_summary(bag)
    channel = next(c for c in summary.channels.values() if c.topic == "/u")
    fast = _bulk(file, summary, channel.id, "std_msgs/msg/Float64")  # raises rather than taking the slow path
    assert fast.values.tolist() == run.u.tolist()
    assert bag_info(bag)["topics"]["/y_p"]["missing"] == 0


def test_unchunked_file_takes_the_general_path(tmp_path: Path) -> None:
    from mcap.writer import Writer

    bag = tmp_path / "flat"
    bag.mkdir()
    with (bag / "flat.mcap").open("wb") as f:
        writer = Writer(f, use_chunking=False)
        writer.start(profile="ros2")
        schema = writer.register_schema("std_msgs/msg/Float64", "ros2msg", b"float64 data\n")
        channels = {name: writer.register_channel(name, "cdr", schema) for name in ("/u", "/y_p")}
        for k in range(10):
            for name, sign in (("/u", 1), ("/y_p", -1)):
                writer.add_message(channels[name], k, b"\x00\x01\x00\x00" + np.float64(sign * k).tobytes(), k, k + 1)
        writer.finish()
    run = read_run(bag)
    assert run.y_p.tolist() == [-float(k) for k in range(10)] and run.u_sequence.tolist() == list(range(1, 11))


def test_a_damaged_sqlite_bag_is_one_line_with_the_reason(tmp_path: Path) -> None:
    """A sqlite3 bag is read (rosbags' reader); one that is not a database says so in one line, no traceback."""
    bag = tmp_path / "old"
    bag.mkdir()
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: sqlite3\n"
        "  relative_file_paths: [old_0.db3]\n  duration: {nanoseconds: 0}\n"
        "  starting_time: {nanoseconds_since_epoch: 0}\n  message_count: 0\n  topics_with_message_count: []\n"
        "  compression_format: ''\n  compression_mode: ''\n"
    )
    (bag / "old_0.db3").write_bytes(b"SQLite format 3\x00 not really")
    with pytest.raises(BagError) as raised:
        read_run(bag)
    assert str(raised.value).startswith(f"{bag}: ") and "\n" not in str(raised.value)


@pytest.mark.parametrize("labelled", [False, True])
def test_fast_path_ignores_cdr_padding_bytes(tmp_path: Path, labelled: bool) -> None:
    """rclpy leaves CDR alignment padding unzeroed: arrays that differ only there are one layout.

    Comparing those bytes sent every real ``samples`` topic down the general reader
    (about 50 k instead of 1 M samples/s for a 10^6-sample evaluate).
    """
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64MultiArray, MultiArrayDimension

    from lenn_ros.bag import scalars
    from lenn_ros.bag.reader import read_summary

    message = Float64MultiArray()
    if labelled:
        message.layout.dim = [MultiArrayDimension(label="index,time,u,y_p,learn", size=5, stride=5)]
    rng = np.random.default_rng(0)
    rows = rng.normal(size=(200, 5))
    with BagWriter(tmp_path / "b") as bag:
        bag.add_topic("/samples")
        for k, row in enumerate(rows):
            message.data = [float(v) for v in row]
            payload = bytearray(serialize_message(message))
            _data_at, count, meaningful = scalars._array_layout(bytes(payload))
            assert count == 5
            for position in np.flatnonzero(~meaningful):
                payload[position] = k % 251  # what unzeroed memory may hold
            bag.write_raw("/samples", bytes(payload), 10 + k, sequence=k + 1)
    file, summary = read_summary(tmp_path / "b")
    channel = next(c for c in summary.channels.values() if c.topic == "/samples")
    fast = scalars._bulk(file, summary, channel.id, "std_msgs/msg/Float64MultiArray")  # raises _SlowPath if refused
    np.testing.assert_array_equal(fast.values, rows)
