"""lenn_ros.bag against real MCAP files, checked with an independent reader (mcap + mcap_ros2)."""

from __future__ import annotations

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
        ("a,b\n1,2\n3,nan\n", "a", "b", {}, r"line 3, column 'b': 'nan' is not finite"),
        ("a,b\n1,2\n3\n", "a", "b", {}, r"line 3 has 1 cells"),
        ("a,b\n1,2\n", "a", "b", {"test_from": 5}, r"test_from=5 is outside samples 1..1"),
        ("a,b\n1,2\n", "a", "b", {"test_from": 0}, r"test_from=0 is outside samples 1..1 .*1-based"),
        ("a,b\n", "a", "b", {}, r"no data rows"),
        ("1,2\n", 0, 7, {}, r"line 1 has 2 cells, no column 7"),
    ],
)
def test_import_csv_errors(tmp_path: Path, text: str, u: str | int, y: str | int, kwargs: dict, pattern: str) -> None:
    csv = tmp_path / "log.csv"
    csv.write_text(text)
    with pytest.raises(BagError, match=pattern):
        import_csv(csv, u, y, 0.1, tmp_path / "bag", **kwargs)
    assert not (tmp_path / "bag").exists()
