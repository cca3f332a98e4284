"""Bags read in bulk (lrfcal.io.wire, bag_arrays, bag_raw) give what rosbags' generic path gives, to the bit.

Every shipped scenario's recording (the shared simulated recordings of tests/conftest.py), every real recording in
../shared/realbags (skipped with the reason when absent) and small bags of every storage (ROS 1, sqlite3, MCAP) with
the layouts the bulk path must not mistake: scans of varying beam counts, frame ids and intensities, several joint
names, empty arrays, big-endian CDR (left to rosbags, message by message). Compared: the serialised messages and
their log times (the MCAP index against rosbags' reader), the arrays of each topic, and read_bag's whole result.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import tiered
from rosbags.typesys import Stores, get_typestore

from lrfcal.io.bag import BagData, Topic, read_bag, read_topic
from lrfcal.io.bag_arrays import joints_of, scans_of
from lrfcal.io.bag_messages import complete_types, open_reader
from lrfcal.io.bag_raw import raw_messages
from lrfcal.io.bag_scans import laser_arrays
from lrfcal.io.recording import read_nominal
from lrfcal.io.rig import ScanSource, ServoSource

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted(p.stem for p in (ROOT / "scenarios").glob("*.yaml"))
#: the shapes read alike in the suite: a marker rig, a targetless room and the URG-04LX replica (the rest: -m slow)
ALIKE_FIRST = ["tunnel_v", "room_box", "urg_box_60"]
REALBAGS = ROOT.parent / "shared" / "realbags"
needs_realbags = pytest.mark.skipif(not REALBAGS.is_dir(), reason=f"real recordings not present at {REALBAGS} "
                                    "(public bags shared beside the project, not part of a clone)")
LASERSCAN, JOINTSTATE = "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/JointState"


def same(a: Any, b: Any, where: str = "") -> None:
    """``a`` and ``b`` equal to the bit: arrays of the same dtype, shape and bytes (NaNs included), dataclasses
    field by field, everything else by ==."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert (a.dtype, a.shape) == (b.dtype, b.shape), where
        assert np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes(), where
    elif dataclasses.is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, float) and math.isnan(a):
        assert isinstance(b, float) and math.isnan(b), where
    elif isinstance(a, (list, tuple)) and any(isinstance(v, (np.ndarray, float)) for v in a):
        assert len(a) == len(b), where
        for k, (u, v) in enumerate(zip(a, b, strict=True)):
            same(u, v, f"{where}[{k}]")
    else:
        assert a == b, where


def both_ways(bag: Path, topic: str, bulk_expected: bool, of: Callable[[list[Any]], Any]) -> None:
    """The topic's messages, log times and arrays, bulk and generic."""
    reader = open_reader(bag)
    with reader:
        complete_types(reader)
        conns = [c for c in reader.connections if c.topic == topic]
        raw_fast, = raw_messages(reader, [conns])
        raw_slow, = raw_messages(reader, [conns], fast=False)
    same(raw_fast.times_ns, raw_slow.times_ns, f"{topic} log times")
    assert len(raw_fast) == len(raw_slow) > 0
    assert all(raw_fast.message(i) == raw_slow.message(i) for i in range(len(raw_fast))), f"{topic}: messages"
    fast, slow = read_topic(bag, topic), read_topic(bag, topic, bulk=False)
    assert isinstance(fast, Topic) and slow.arrays is None and slow.messages is not None
    same(fast.recv_s, slow.recv_s, f"{topic} receive times")
    assert (fast.arrays is not None) == bulk_expected, f"{topic}: bulk path taken"
    if fast.arrays is not None:
        same(fast.arrays, of(slow.messages), topic)


def same_read(bag: Path, scan: ScanSource, servo: ServoSource) -> BagData:
    """read_bag bulk and generic: the same Scans, JointStates and report (warnings included)."""
    warned: tuple[list[str], list[str]] = ([], [])
    fast = read_bag(bag, scan, servo, warn=warned[0].append)
    slow = read_bag(bag, scan, servo, warn=warned[1].append, bulk=False)
    same(fast, slow, "BagData")
    assert warned[0] == warned[1]
    return fast


@pytest.mark.parametrize("name", tiered(ALIKE_FIRST + [n for n in SHIPPED if n not in ALIKE_FIRST], keep=3))
def test_shipped_recordings_read_alike(name: str, shipped_recording: Callable[[str], Path]) -> None:
    folder = shipped_recording(name)
    nominal = read_nominal(folder / "nominal.yaml")
    both_ways(folder / "bag", nominal.scan.topic, True, scans_of)
    both_ways(folder / "bag", nominal.servo.topic or "", True, joints_of)
    data = same_read(folder / "bag", nominal.scan, nominal.servo)
    assert data.report.n_scans > 100 and data.joints.stamps_s.size > 100


@needs_realbags
@pytest.mark.parametrize("bag", ["cardboard_box.bag", "room_240.bag"])
def test_real_urg_bags_read_alike(bag: str) -> None:
    path = REALBAGS / bag
    scan = ScanSource(topic="/slice", field="laserScan")
    both_ways(path, "/slice", False, scans_of)  # a custom type: rosbags decodes it whichever way
    lasers = [read_topic(path, "/slice", bulk=b).messages for b in (True, False)]
    same(*(laser_arrays(m or [], scan, "pcg_node/msg/LaserScanAngle", bag) for m in lasers))
    same_read(path, scan, ServoSource(topic=None, field="stepAngle", unit="deg", stamp="scan"))


@needs_realbags
def test_real_rplidar_bag_reads_alike() -> None:
    path = REALBAGS / "rplidar_servo_3hz"  # sqlite3; 0-600 beams a scan, empty scans, inf increments
    both_ways(path, "/scan", True, scans_of)
    both_ways(path, "/lidar_servo_angle", False, scans_of)
    both_ways(path, "/imu", False, scans_of)
    same_read(path, ScanSource(topic="/scan"),
              ServoSource(topic="/lidar_servo_angle", unit="deg", stamp="receive", offset_rad=-math.pi / 2))


# --- small bags of every storage, with the layouts the bulk path must tell apart --------------------------------

T0_NS = 1_700_000_000 * 10**9


def _messages(ts: Any, ros1: bool) -> tuple[list[Any], list[Any]]:
    """LaserScans of varying beam counts, frame ids, intensities (none, matching, too few), NaN / inf / 0 ranges;
    JointStates of one and of several joints, with empty arrays."""
    Time, Header = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    rng = np.random.default_rng(7)

    def header(k: int, frame: str) -> Any:
        stamp = Time(sec=1_700_000_000 + k // 40, nanosec=(k % 40) * 25_000_000)
        return Header(seq=k, stamp=stamp, frame_id=frame) if ros1 else Header(stamp=stamp, frame_id=frame)

    scans = []
    for k in range(60):
        n = (181, 181, 181, 90, 0)[k % 5] if k >= 20 else 181
        r = rng.uniform(0.1, 8.0, n).astype(np.float32)
        r[rng.random(n) < 0.1] = np.nan
        r[rng.random(n) < 0.05] = np.inf
        r[rng.random(n) < 0.05] = 0.0
        i = (rng.uniform(0, 4000, n) if k % 3 else rng.uniform(0, 1, n // 2 if k % 7 == 0 else 0)).astype(np.float32)
        scans.append(ts.types[LASERSCAN](
            header=header(k, "laser" if k % 11 else "laser_frame_b"), angle_min=-1.5, angle_max=-1.5 + (n - 1) * 0.01,
            angle_increment=0.01, time_increment=1e-4 if k % 13 else 0.0, scan_time=0.025, range_min=0.05,
            range_max=6.0 + (k % 2), ranges=r, intensities=i))
    joints = []
    for k in range(150):
        names = ["servo"] if k % 17 else ["pan", "servo"]
        pos = rng.normal(size=len(names))
        joints.append(ts.types[JOINTSTATE](
            header=header(k, ""), name=names, position=pos, velocity=pos[:1] if k % 2 else np.zeros(0),
            effort=np.zeros(0)))
    return scans, joints


def _write(path: Path, kind: str) -> Path:
    """A small bag of :func:`_messages`: ``kind`` ros1, sqlite3, mcap or mcap+MODE (zstd compression of the MCAP
    chunks: storage; of the whole file: file; of every message: message)."""
    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer: Any = Writer1(path)
    else:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        plugin = StoragePlugin.MCAP if kind.startswith("mcap") else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
        if "+" in kind:
            writer.set_compression(CompressionMode[kind.partition("+")[2].upper()], CompressionFormat.ZSTD)
    scans, joints = _messages(ts, ros1)
    with writer:
        cs = writer.add_connection("/scan", LASERSCAN, typestore=ts)
        cj = writer.add_connection("/joint_states", JOINTSTATE, typestore=ts)
        events = [(T0_NS + k * 25_000_000, 0, m) for k, m in enumerate(scans)]
        events += [(T0_NS + k * 10_000_000, 1, m) for k, m in enumerate(joints)]
        events += [(T0_NS + 5 * 25_000_000, 0, scans[5]), (T0_NS + 5 * 25_000_000, 1, joints[3])]  # equal log times
        for k, (t, which, msg) in enumerate(sorted(events, key=lambda e: (e[0], e[1]))):
            typ = (LASERSCAN, JOINTSTATE)[which]
            # every ninth ROS 2 message big-endian CDR: the bulk path leaves it to rosbags
            raw = ts.serialize_ros1(msg, typ) if ros1 else ts.serialize_cdr(msg, typ, little_endian=k % 9 != 4)
            writer.write((cs, cj)[which], t, raw)
    return path


@pytest.mark.parametrize("kind,name", [("mcap", "bag"), ("sqlite3", "bag"), ("ros1", "rec.bag"),
                                       ("mcap+storage", "bag"), ("mcap+file", "bag"), ("mcap+message", "bag")])
def test_every_storage_and_odd_layouts_read_alike(tmp_path: Path, kind: str, name: str) -> None:
    path = _write(tmp_path / name, kind)
    both_ways(path, "/scan", True, scans_of)
    both_ways(path, "/joint_states", True, joints_of)
    fast = read_topic(path, "/scan").arrays
    assert fast is not None and set(fast.counts.tolist()) == {0, 90, 181} and len(set(fast.frame_ids)) == 2
    for stamp in ("header", "receive"):
        same_read(path, ScanSource(stamp=stamp), ServoSource(topic="/joint_states", joint="servo"))


# --- the simulator's bag, written in bulk -----------------------------------------------------------------------

def _records(result: Any, scenario: Any) -> tuple[list[tuple[str, str]], list[tuple[int, str, memoryview]]]:
    """lrfsim.simulation.recording.bag_columns message by message: [(log time ns, topic, CDR bytes)] in file order."""
    from lrfsim.simulation.recording import bag_columns

    topics, messages, log_ns, channel, index = bag_columns(result, scenario)
    return topics, [(t, topics[c][0], memoryview(messages[c][k]))
                    for t, c, k in zip(log_ns.tolist(), channel.tolist(), index.tolist(), strict=True)]


@pytest.mark.parametrize("sections", [
    {},
    {"sensor": {"echoes": {"enabled": True, "separation_m": 0.004}, "divergence_rad": 0.01},
     "faults": {"angle_increment_off_by_one": True}, "servo": {"clock_offset_s": 0.137}},
    {"faults": {"dropped_scans_fraction": 0.3, "stamp_jitter_s": 0.02, "inverted_servo": True, "joint_gap_s": 0.2,
                "encoder_spikes": 5}},
], ids=["plain", "echoes_fault_offset", "dropped_jittered_gap"])
def test_simulated_bag_is_the_file_rosbags_writes(tmp_path: Path, sections: dict[str, Any]) -> None:
    """write_bag in bulk (messages serialised as arrays, the MCAP file assembled from them, lrfcal.io.mcap_write)
    writes the bag.mcap and metadata.yaml that rosbags' serialiser and Writer write, one call per message."""
    from test_lidar import small_scenario

    from lrfsim.simulation.recording import bag_messages, write_bag
    from lrfsim.simulation.simulate import simulate

    scenario = small_scenario(**sections)
    result = simulate(scenario)
    topics, records = _records(result, scenario)
    ref_topics, events = bag_messages(result, scenario)
    assert topics == ref_topics and len(topics) == (3 if "sensor" in sections else 2)
    assert [(t, topic) for t, topic, _ in records] == [(t, topic) for t, topic, _, _ in events]
    ts = get_typestore(Stores.ROS2_HUMBLE)
    for (_, _, raw), (_, _, typ, msg) in zip(records, events, strict=True):
        if typ in (LASERSCAN, JOINTSTATE):
            assert bytes(raw) == bytes(ts.serialize_cdr(msg, typ)), typ
    write_bag(result, scenario, tmp_path / "bulk" / "bag")
    write_bag(result, scenario, tmp_path / "rosbags" / "bag", bulk=False)  # rosbags' serialiser and Writer
    for name in ("bag.mcap", "metadata.yaml"):
        assert (tmp_path / "bulk" / "bag" / name).read_bytes() == (tmp_path / "rosbags" / "bag" / name).read_bytes()
    if "dropped_scans_fraction" in sections.get("faults", {}):  # the faults changed what the bag holds
        assert result.faults["dropped_scans"] and result.faults["joint_gap"]["n_removed"] > 0
        assert len(result.faults["encoder_spikes"]) == 5 and result.faults["receive_stamps"]["max_delay_s"] > 0


def _rosbags_file(path: Path, topics: list[tuple[str, str]], order: list[tuple[int, int, bytes]]) -> Path:
    """The bag rosbags' Writer writes: ``topics`` added in order, then (log time, topic index, bytes) each."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = [writer.add_connection(topic, typ, typestore=ts) for topic, typ in topics]
        for t, c, raw in order:
            writer.write(conns[c], t, raw)
    return path


@pytest.mark.parametrize("n_messages", [0, 1, 700])
def test_bulk_mcap_writer_is_rosbags_writer_byte_for_byte(tmp_path: Path, n_messages: int) -> None:
    """lrfcal.io.mcap_write against rosbags' Writer on records the simulator never writes: 700 messages of 3 MB
    (3 chunks; the first reaches CHUNK_BYTES exactly after one message, which does not close it, and is closed by
    the next), two topics of one type (one schema), a topic without messages, empty messages, log times out of
    order and equal; messages as rows of an array and as bytes; no message at all (one chunk of schemas and
    channels only) and a single one."""
    from lrfcal.io.mcap_write import CHUNK_BYTES, BagTopic, write_rosbag2_mcap

    ts = get_typestore(Stores.ROS2_HUMBLE)
    topics = [BagTopic.of(topic, typ, ts) for topic, typ in
              (("/scan", LASERSCAN), ("/joint_states", JOINTSTATE), ("/scan_b", LASERSCAN), ("/idle", JOINTSTATE))]
    rng = np.random.default_rng(3)
    channel = rng.choice([0, 1, 2], size=n_messages, p=[0.5, 0.3, 0.2]).astype(np.int64)
    index = np.zeros(n_messages, dtype=np.int64)
    for c in range(3):
        index[channel == c] = np.arange(int(np.sum(channel == c)))
    rows = rng.integers(0, 256, (int(np.sum(channel == 0)), 5000), dtype=np.uint8)  # topic 0: of one length
    varied = [rng.bytes(int(n)) for n in rng.choice([0, 17, 60, 9000], size=int(np.sum(channel == 1)))]
    small = rng.integers(0, 256, (int(np.sum(channel == 2)), 8), dtype=np.uint8)
    messages: list[Any] = [rows, varied, small, np.zeros((0, 8), dtype=np.uint8)]
    log_ns = T0_NS + np.cumsum(rng.integers(0, 3_000_000, n_messages)) - rng.integers(0, 10_000_000, n_messages)
    if n_messages:
        log_ns[n_messages // 2:][:2] = log_ns[n_messages // 2]  # two equal log times

    def raw(j: int) -> bytes:
        return bytes(memoryview(messages[int(channel[j])][int(index[j])]))

    if n_messages > 600:  # a topic-1 message resized to take the first chunk to CHUNK_BYTES exactly
        content = 0  # the first chunk: schemas and channels, then message records (31 bytes + the message)
        for t in topics:
            content += 9 + 2 + sum(4 + len(x.encode()) for x in (t.topic, "cdr", "offered_qos_profiles", "[]")) + 6
        content += sum(9 + 2 + 12 + len(t.msgtype) + len("ros2msg") + len(t.msgdef.encode()) for t in topics[:2])
        j = 0
        while not (channel[j] == 1 and content >= CHUNK_BYTES - 31 - 60_000):
            content += 31 + len(raw(j))
            j += 1
        assert content <= CHUNK_BYTES - 31, "the first chunk closed before a topic-1 message could fill it"
        varied[int(index[j])] = rng.bytes(CHUNK_BYTES - 31 - content)
    order = [(int(log_ns[j]), int(channel[j]), raw(j)) for j in range(n_messages)]
    ref = _rosbags_file(tmp_path / "rosbags" / "bag", [(t.topic, t.msgtype) for t in topics], order)
    write_rosbag2_mcap(tmp_path / "bulk" / "bag", topics, messages, log_ns, channel, index)
    for name in ("bag.mcap", "metadata.yaml"):
        assert (tmp_path / "bulk" / "bag" / name).read_bytes() == (ref / name).read_bytes(), name
    if n_messages > 600:  # the edge was there: the first chunk went on past CHUNK_BYTES by message j + 1
        from rosbags.rosbag2.storage_mcap import McapReader

        reader = McapReader(ref / "bag.mcap")
        reader.open()
        sizes = [c.uncompressed_size for c in reader.chunks]
        reader.close()
        assert len(sizes) == 3 and sizes[0] == CHUNK_BYTES + 31 + len(raw(j + 1))


def test_bag_topics_are_humbles_without_loading_its_store() -> None:
    """BagTopic.humble names the simulator's types (definition, hash) as rosbags' Writer does with ROS 2 Humble's
    store, from lrfcal.io's copies of the definitions: writing the simulator's bag does not load that store; another
    type is taken from the store."""
    import subprocess
    import sys

    from lrfcal.io.mcap_write import BagTopic

    humble = get_typestore(Stores.ROS2_HUMBLE)
    for typ in (LASERSCAN, JOINTSTATE, "sensor_msgs/msg/MultiEchoLaserScan", "std_msgs/msg/String"):
        assert BagTopic.humble("/t", typ) == BagTopic.of("/t", typ, humble), typ
    probe = ("import sys; from lrfcal.io.mcap_write import BagTopic; "
             "t = [BagTopic.humble('/t', 'sensor_msgs/msg/' + n) for n in ('LaserScan', 'JointState', "
             "'MultiEchoLaserScan')]; print(len(t), 'rosbags.typesys.stores.ros2_humble' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["3", "False"]


def test_bulk_mcap_writer_refuses_what_it_would_misread(tmp_path: Path) -> None:
    """A topic twice, messages of another dtype, a negative log time, an index past its topic's messages (which
    would silently take another topic's), an existing folder: refused, nothing written."""
    from lrfcal.io.mcap_write import BagTopic, write_rosbag2_mcap

    ts = get_typestore(Stores.ROS2_HUMBLE)
    scan, joint = BagTopic.of("/scan", LASERSCAN, ts), BagTopic.of("/joint_states", JOINTSTATE, ts)
    rows, raws = np.zeros((2, 8), dtype=np.uint8), [b"ab", b"cde"]
    good = (np.array([T0_NS, T0_NS + 1, T0_NS + 2]), np.array([0, 1, 1]), np.array([0, 0, 1]))
    bad = [([scan, scan], [rows, raws], good), ([scan, joint], [rows.astype(np.float32), raws], good),
           ([scan, joint], [rows, raws], (np.array([-1, 0, 1]), *good[1:])),
           ([scan, joint], [rows, raws], (good[0], good[1], np.array([0, 0, 2]))),
           ([scan, joint], [rows, raws], (good[0], np.array([0, 1, 2]), good[2]))]
    for k, (topics, messages, order) in enumerate(bad):
        with pytest.raises(ValueError):
            write_rosbag2_mcap(tmp_path / f"bad{k}" / "bag", topics, messages, *order)
        assert not (tmp_path / f"bad{k}").exists()
    write_rosbag2_mcap(tmp_path / "good" / "bag", [scan, joint], [rows, raws], *good)
    with pytest.raises(FileExistsError):
        write_rosbag2_mcap(tmp_path / "good" / "bag", [scan, joint], [rows, raws], *good)
    raw_topics = raw_messages_of(tmp_path / "good" / "bag", ["/scan", "/joint_states"])
    assert [[bytes(t.message(i)) for i in range(len(t))] for t in raw_topics] == [[bytes(8)] * 1, [b"ab", b"cde"]]


def raw_messages_of(bag: Path, topics: list[str]) -> list[Any]:
    """Each topic's messages as lrfcal.io.bag_raw reads them from the MCAP index."""
    reader = open_reader(bag)
    with reader:
        complete_types(reader)
        return raw_messages(reader, [[c for c in reader.connections if c.topic == t] for t in topics])


def test_a_bag_defining_laserscan_otherwise_is_left_to_rosbags(tmp_path: Path) -> None:
    """A LaserScan whose definition in the bag is not ROS's (a field more) is decoded by rosbags, never by the
    layout reader, which would take the extra field for the beam count."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_types_from_msg

    humble = get_typestore(Stores.ROS2_HUMBLE)
    ts = get_typestore(Stores.EMPTY)
    ts.register({k: humble.fielddefs[k] for k in ("std_msgs/msg/Header", "builtin_interfaces/msg/Time")})
    text = "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n" \
           "float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\nuint32 quality\n" \
           "float32[] ranges\nfloat32[] intensities\n"
    ts.register(get_types_from_msg(text, LASERSCAN))
    Time, Header = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    with Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/scan", LASERSCAN, typestore=ts)
        for k in range(5):
            msg = ts.types[LASERSCAN](
                header=Header(stamp=Time(sec=1_700_000_000, nanosec=k * 25_000_000), frame_id="laser"),
                angle_min=-1.0, angle_max=1.0, angle_increment=0.5, time_increment=1e-4, scan_time=0.025,
                range_min=0.1, range_max=10.0, quality=2, ranges=np.full(5, 2.0, dtype=np.float32),
                intensities=np.zeros(0, dtype=np.float32))
            writer.write(conn, T0_NS + k, ts.serialize_cdr(msg, LASERSCAN))
    both_ways(tmp_path / "bag", "/scan", False, scans_of)
    arrays = laser_arrays(read_topic(tmp_path / "bag", "/scan").messages or [], ScanSource(), LASERSCAN, "bag")
    assert arrays.counts.tolist() == [5] * 5 and np.all(arrays.ranges == 2.0)


def test_a_frame_id_new_in_every_message_is_left_to_rosbags_past_the_layout_cap() -> None:
    """Messages of one length whose layout bytes all differ (a frame id with a counter): MAX_LAYOUTS of them read in
    bulk, the rest by the fallback, the same arrays as rosbags' (and no work quadratic in the messages)."""
    from lrfcal.io.bag_arrays import MAX_LAYOUTS, decode_scans
    from lrfcal.io.bag_raw import RawTopic

    ts = get_typestore(Stores.ROS2_HUMBLE)
    Time, Header = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    n = MAX_LAYOUTS + 16
    msgs = [ts.types[LASERSCAN](
        header=Header(stamp=Time(sec=1_700_000_000, nanosec=k), frame_id=f"laser{k:04d}"), angle_min=-1.0,
        angle_max=1.0, angle_increment=0.5, time_increment=1e-4, scan_time=0.025, range_min=0.1, range_max=10.0,
        ranges=np.full(5, 0.5 * k, dtype=np.float32), intensities=np.zeros(5, dtype=np.float32)) for k in range(n)]
    raw = RawTopic.of(list(range(n)), [bytes(ts.serialize_cdr(m, LASERSCAN)) for m in msgs])
    fell_back: list[int] = []

    def fallback(i: int) -> Any:
        fell_back.append(i)
        return ts.deserialize_cdr(bytes(raw.message(i)), LASERSCAN)

    arrays = decode_scans(raw, True, fallback)
    assert sorted(fell_back) == list(range(MAX_LAYOUTS, n))
    same(arrays, scans_of([ts.deserialize_cdr(bytes(raw.message(i)), LASERSCAN) for i in range(n)]))
    assert arrays.frame_ids == [f"laser{k:04d}" for k in range(n)]


def test_the_bulk_types_definitions_are_humbles_and_a_read_does_not_load_its_store(
        shipped_recording: Callable[[str], Path]) -> None:
    """lrfcal.io.bag_messages.BULK_FIELDDEFS are the definitions ROS 2 Humble's store holds (the layout reader's
    reference), so that reading a bag that defines its types never loads that store (~900 message classes)."""
    import subprocess
    import sys

    from lrfcal.io.bag_messages import BULK_FIELDDEFS

    humble = get_typestore(Stores.ROS2_HUMBLE).fielddefs
    for name, defs in BULK_FIELDDEFS.items():
        assert defs == humble[name], name
    bag = shipped_recording("tunnel_v") / "bag"
    probe = ("import sys; from lrfcal.io.bag import read_bag; d = read_bag(sys.argv[1]); "
             "print(len(d.scans.stamps_s), 'rosbags.typesys.stores.ros2_humble' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe, str(bag)], capture_output=True, text=True, check=True)
    count, loaded = out.stdout.split()
    assert int(count) > 100 and loaded == "False"
