"""Reading recordings: bags of all three kinds, range/angle conventions, and every bad-input case."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from lrfcal.errors import InputError
from lrfcal.io.bag import read_bag as _read_bag
from lrfcal.io.recording import check_joint_coverage, read_distances, read_nominal, read_recording
from lrfcal.io.rig import ScanSource, ServoSource


def read_bag(path, scan_topic="/scan"):
    """(scans, joints) of a bag with a LaserScan topic and JointState joint 'servo'."""
    data = _read_bag(path, ScanSource(topic=scan_topic), ServoSource(joint="servo"))
    return data.scans, data.joints

N_BEAMS = 11
T0 = 1_700_000_000.0


def _time(ts, t: float):
    sec = int(np.floor(t))
    return ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))


def _header(ts, t: float, frame: str, ros1: bool):
    H = ts.types["std_msgs/msg/Header"]
    return H(seq=0, stamp=_time(ts, t), frame_id=frame) if ros1 else H(stamp=_time(ts, t), frame_id=frame)


def _scan(ts, t, ranges, intens, ros1, angle_min=-0.5, inc=0.1, t_inc=1e-3):
    LS = ts.types["sensor_msgs/msg/LaserScan"]
    return LS(header=_header(ts, t, "laser", ros1), angle_min=angle_min,
              angle_max=angle_min + inc * (len(ranges) - 1), angle_increment=inc, time_increment=t_inc,
              scan_time=0.025, range_min=0.023, range_max=60.0,
              ranges=np.asarray(ranges, dtype=np.float32), intensities=np.asarray(intens, dtype=np.float32))


def _joint(ts, t, names, pos, ros1):
    JS = ts.types["sensor_msgs/msg/JointState"]
    n = len(names)
    return JS(header=_header(ts, t, "", ros1), name=list(names), position=np.asarray(pos, dtype=np.float64),
              velocity=np.zeros(n), effort=np.zeros(0))


def default_scans(n=5):
    """(stamp, ranges, intensities) with stamps deliberately out of order."""
    out = []
    for k in range(n):
        r = np.full(N_BEAMS, 2.0 + 0.1 * k)
        out.append((T0 + 0.025 * k, r, np.full(N_BEAMS, 100.0 + k)))
    return [out[i] for i in [2, 0, 4, 1, 3][:n]] if n == 5 else out


def default_joints(t_start=T0 - 0.02, t_end=T0 + 0.2, dt=0.01, names=("servo",)):
    ts = np.arange(t_start, t_end + 1e-9, dt)
    return [(t, names, [0.5 * (t - T0)] + [0.0] * (len(names) - 1)) for t in ts]


def write_bag(path: Path, kind: str, scans=None, joints=None, scan_topic="/scan", joint_topic="/joint_states",
              scan_kw=None) -> Path:
    """Write a tiny bag: kind in {'mcap', 'sqlite3', 'ros1'}."""
    scans = default_scans() if scans is None else scans
    joints = default_joints() if joints is None else joints
    scan_kw = scan_kw or {}
    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer as W1

        writer = W1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as W2

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = W2(path, version=9, storage_plugin=plugin)
    lt, jt = "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/JointState"
    with writer:
        cs = writer.add_connection(scan_topic, lt, typestore=ts)
        cj = writer.add_connection(joint_topic, jt, typestore=ts)
        recv = 0
        for t, r, i in scans:
            recv += 1
            writer.write(cs, int(T0 * 1e9) + recv, ser(_scan(ts, t, r, i, ros1, **scan_kw), lt))
        for t, names, pos in joints:
            recv += 1
            writer.write(cj, int(T0 * 1e9) + recv, ser(_joint(ts, t, names, pos, ros1), jt))
    return path


@pytest.mark.parametrize("kind,name", [("mcap", "bag"), ("sqlite3", "bag"), ("ros1", "rec.bag")])
def test_read_all_bag_kinds(tmp_path, kind, name):
    path = write_bag(tmp_path / name, kind)
    scans, joints = read_bag(path)
    assert scans.ranges_m.shape == (5, N_BEAMS)
    assert np.all(np.diff(scans.stamps_s) > 0)  # sorted by header.stamp
    np.testing.assert_allclose(scans.stamps_s - T0, 0.025 * np.arange(5), atol=1e-6)
    np.testing.assert_allclose(scans.ranges_m[:, 0], 2.0 + 0.1 * np.arange(5), atol=1e-6)
    np.testing.assert_allclose(scans.intensities[:, 3], 100.0 + np.arange(5))
    np.testing.assert_allclose(scans.mu_rad, np.tile(-0.5 + 0.1 * np.arange(N_BEAMS), (5, 1)), atol=1e-6)
    np.testing.assert_allclose(scans.time_increment_s, 1e-3)
    assert scans.frame_id == "laser"
    assert joints.name == "servo" and joints.stamps_s.size == 23
    np.testing.assert_allclose(joints.positions_rad, 0.5 * (joints.stamps_s - T0), atol=1e-9)


def test_read_single_mcap_file(tmp_path):
    path = write_bag(tmp_path / "bag", "mcap")
    (mcap,) = path.glob("*.mcap")
    scans, _ = read_bag(mcap)
    assert scans.ranges_m.shape == (5, N_BEAMS)


def test_invalid_ranges_become_nan(tmp_path):
    r = np.full(N_BEAMS, 3.0)
    r[1], r[2], r[3], r[4], r[5], r[6] = np.nan, np.inf, -np.inf, 0.001, 75.0, 0.0
    scans = [(T0 + 0.025 * k, r, np.ones(N_BEAMS)) for k in range(3)]
    s, _ = read_bag(write_bag(tmp_path / "bag", "mcap", scans=scans))
    assert np.isnan(s.ranges_m[:, 1:7]).all()
    assert np.isfinite(s.ranges_m[:, [0, 7, 8, 9, 10]]).all()
    assert s.range_min_m == pytest.approx(0.023) and s.range_max_m == pytest.approx(60.0)


def test_negative_angle_increment(tmp_path):
    path = write_bag(tmp_path / "bag", "mcap", scan_kw={"angle_min": 0.5, "inc": -0.1})
    s, _ = read_bag(path)
    np.testing.assert_allclose(s.mu_rad[2], 0.5 - 0.1 * np.arange(N_BEAMS), atol=1e-6)


def test_missing_intensities_allowed_until_detection(tmp_path):
    from lrfcal.stages.detection import detect

    scans = [(T0 + 0.025 * k, np.full(N_BEAMS, 2.0), np.zeros(0)) for k in range(3)]
    s, _ = read_bag(write_bag(tmp_path / "bag", "mcap", scans=scans))
    assert np.all(s.intensities == 0)
    with pytest.raises(InputError, match=r"/scan: intensities: none in the scans \(enable .*publish_intensity\)"):
        detect(s)


def test_all_nan_ranges_are_not_called_missing_intensities(tmp_path):
    from lrfcal.stages.detection import detect

    scans = [(T0 + 0.025 * k, np.full(N_BEAMS, np.nan), np.full(N_BEAMS, 500.0)) for k in range(3)]
    s, _ = read_bag(write_bag(tmp_path / "bag", "mcap", scans=scans))
    with pytest.raises(InputError, match=r"/scan: ranges: no valid range") as info:
        detect(s)
    assert "intensit" not in str(info.value)


def test_joint_picked_by_name_among_several(tmp_path):
    joints = [(t, ("pan", "servo"), [9.0, 0.5 * (t - T0)]) for t in np.arange(T0 - 0.02, T0 + 0.2, 0.01)]
    _, j = read_bag(write_bag(tmp_path / "bag", "mcap", joints=joints))
    np.testing.assert_allclose(j.positions_rad, 0.5 * (j.stamps_s - T0), atol=1e-9)


# --- bad bags -----------------------------------------------------------------------------------------------

def test_missing_topic_names_available(tmp_path):
    path = write_bag(tmp_path / "bag", "mcap", scan_topic="/laser/scan")
    with pytest.raises(InputError, match=r"topic /scan: not in bag \(topics: /joint_states, /laser/scan\)"):
        read_bag(path)
    s, _ = read_bag(path, scan_topic="/laser/scan")
    assert s.ranges_m.shape[0] == 5


def test_empty_scan_topic(tmp_path):
    path = write_bag(tmp_path / "bag", "mcap", scans=[])
    with pytest.raises(InputError, match=r"/scan: no messages"):
        read_bag(path)


def test_missing_bag(tmp_path):
    with pytest.raises(InputError, match="bag not found"):
        read_bag(tmp_path / "nope")


def test_recording_folder_given_as_the_bag_names_its_bag(tmp_path):
    """A recording folder (bag/, distances.csv, nominal.yaml) where a bag is expected: one line naming its bag."""
    write_bag(tmp_path / "rec" / "bag", "mcap")
    with pytest.raises(InputError, match=r"a recording folder, not a bag: pass its bag, .*rec/bag"):
        read_bag(tmp_path / "rec")


def test_missing_joint_lists_names(tmp_path):
    joints = [(t, ("pan", "tilt"), [0.0, 0.0]) for t in np.arange(T0 - 0.02, T0 + 0.2, 0.01)]
    path = write_bag(tmp_path / "bag", "mcap", joints=joints)
    with pytest.raises(InputError, match=r"joint 'servo' not found \(available: pan, tilt\)"):
        read_bag(path)


@pytest.mark.parametrize("span,which", [((T0 + 0.05, T0 + 0.3), "start"), ((T0 - 0.1, T0 + 0.05), "end")])
def test_joint_states_not_covering_scans(tmp_path, span, which):
    path = write_bag(tmp_path / "bag", "mcap", joints=default_joints(*span))
    scans, joints = read_bag(path)  # the reader no longer refuses it: the calibration trims the scans
    with pytest.raises(InputError, match=rf"/joint_states: joint states {which} at"):
        check_joint_coverage(scans, joints, "/joint_states")
    # with a clock offset that moves the beams into the joint span the check passes
    shift = (T0 + 0.06 - scans.stamps_s[0]) if which == "start" else (T0 + 0.04 - scans.stamps_s[-1] - 0.011)
    check_joint_coverage(scans, joints, "/joint_states", clock_offset_s=-shift)


def test_joint_states_within_one_period_are_accepted(tmp_path):
    # last beam at T0 + 0.1 + 10 ms; joints end 5 ms earlier, with a 10 ms period
    path = write_bag(tmp_path / "bag", "mcap", joints=default_joints(T0 - 0.005, T0 + 0.105))
    scans, joints = read_bag(path)
    check_joint_coverage(scans, joints)
    assert joints.stamps_s.size == 12


def test_variable_beam_count(tmp_path):
    scans = default_scans()
    scans[3] = (scans[3][0], np.full(N_BEAMS + 1, 2.0), np.ones(N_BEAMS + 1))
    s, _ = read_bag(write_bag(tmp_path / "bag", "mcap", scans=scans))
    assert s.ranges_m.shape == (5, N_BEAMS + 1)
    k = int(np.argmax(s.beam_counts))  # the 12-beam scan; the others are padded with NaN
    assert s.beam_counts[k] == N_BEAMS + 1 and int(np.isnan(s.ranges_m[:, -1]).sum()) == 4


def test_per_scan_angles(tmp_path):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = tmp_path / "bag"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        cs = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        cj = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        for k, amin in enumerate([-0.5, -0.5, -0.6]):
            m = _scan(ts, T0 + 0.025 * k, np.full(N_BEAMS, 2.0), np.ones(N_BEAMS), False, angle_min=amin)
            w.write(cs, k + 1, ts.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
        for k, (t, n, p) in enumerate(default_joints()):
            w.write(cj, 100 + k, ts.serialize_cdr(_joint(ts, t, n, p, False), "sensor_msgs/msg/JointState"))
    s, _ = read_bag(path)  # each scan keeps its own angle_min
    np.testing.assert_allclose(s.mu_rad[:, 0], [-0.5, -0.5, -0.6], atol=1e-6)


# --- distances.csv ------------------------------------------------------------------------------------------

GOOD_CSV = "marker_i,marker_j,distance_m\nm0,m1,1.0\nm1,m2,1.0\nm2,m3,1.0\nm3,m0,1.0\nm0,m2,1.4142\n"


def _csv(tmp_path, text, name="distances.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_read_distances_good(tmp_path):
    t = read_distances(_csv(tmp_path, GOOD_CSV + "m2,m0,1.4142\n\n# comment\n"))
    assert t.marker_ids == ("m0", "m1", "m2", "m3")
    assert t.pairs.shape == (5, 2) and t.pairs.dtype == np.int64
    assert (t.pairs[:, 0] < t.pairs[:, 1]).all()
    np.testing.assert_allclose(sorted(t.distances_m), [1, 1, 1, 1, 1.4142])


@pytest.mark.parametrize("text,pattern", [
    ("a,b,c\nm0,m1,1\n", r"distances.csv:1: header: expected marker_i,marker_j,distance_m, got a,b,c"),
    (GOOD_CSV + "m0,m4,abc\n", r"distances.csv:7: distance_m: not a number: 'abc'"),
    (GOOD_CSV + "m0,m4,?\n", r"distances.csv:7: distance_m: not a number: '\?'"),
    (GOOD_CSV + "m0,m4,-0.5\n", r"distances.csv:7: distance_m: must be a finite positive length, got '-0.5'"),
    (GOOD_CSV + "m0,m4,0\n", r"distances.csv:7: distance_m: must be a finite positive length, got '0'"),
    (GOOD_CSV + "m0,m4,nan\n", r"distances.csv:7: distance_m: must be a finite positive length"),
    (GOOD_CSV + "m4,m4,1.0\n", r"distances.csv:7: marker_j: pair of 'm4' with itself"),
    (GOOD_CSV + "m1,m0,1.2\n", r"csv:7: distance_m: m1-m0 = 1.2 disagrees with line 2 .*asymmetric"),
    (GOOD_CSV + "m0,m1,1.05\n", r"distances.csv:7: distance_m: m0-m1 = 1.05 disagrees with line 2"),
    (GOOD_CSV + "m0,m4\n", r"distances.csv:7: expected 3 columns"),
    (GOOD_CSV + ",m4,1\n", r"distances.csv:7: marker_i: empty id"),
    ("marker_i,marker_j,distance_m\nm0,m1,1\nm1,m2,1\nm0,m2,1\n",
     r"only 3 markers \(m0, m1, m2\); need at least 4"),
    ("marker_i,marker_j,distance_m\nm0,m1,1\nm2,m3,1\n",
     r"not connected by distances \(groups: m0,m1; m2,m3\)"),
    ("", r"distances.csv: empty"),
])
def test_read_distances_bad(tmp_path, text, pattern):
    with pytest.raises(InputError, match=pattern):
        read_distances(_csv(tmp_path, text))


def test_read_distances_missing(tmp_path):
    with pytest.raises(InputError, match=r"nope.csv: distances file not found"):
        read_distances(tmp_path / "nope.csv")


# --- nominal.yaml -------------------------------------------------------------------------------------------

NOMINAL = """dh: {a: 0.01, alpha: 1.5708, b: 0.02, beta: 1.5708}
mount: {x: 0, y: 0, z: 0.3, roll: 0, pitch: 0, yaw: 0}
marker_radius_m: 0.005
scan_topic: /scan
joint_topic: /joint_states
joint_name: servo
"""


def test_read_nominal(tmp_path):
    n = read_nominal(_csv(tmp_path, NOMINAL, "nominal.yaml"))
    assert n.dh.a == 0.01 and n.mount is not None and n.mount.z == 0.3 and n.joint_name == "servo"
    n2 = read_nominal(_csv(tmp_path, "dh: {a: 0, alpha: 0, b: 0, beta: 0}\n", "n2.yaml"))
    assert n2.mount is None and n2.scan_topic == "/scan"


def test_read_nominal_rig_blocks(tmp_path):
    text = ("dh: {a: 0, alpha: 0, b: 0, beta: 0}\nscan: {topic: /slice, field: laserScan}\n"
            "servo: {field: stepAngle, unit: deg, stamp: scan, sign: -1, offset_rad: 0.1}\n")
    n = read_nominal(_csv(tmp_path, text, "rig.yaml"))
    assert (n.scan.topic, n.scan.field, n.scan.stamp) == ("/slice", "laserScan", "header")
    assert (n.servo.field, n.servo.unit, n.servo.stamp, n.servo.sign) == ("stepAngle", "deg", "scan", -1)
    assert n.servo.unit_factor() == pytest.approx(np.pi / 180) and n.servo.offset_rad == 0.1
    legacy = read_nominal(_csv(tmp_path, NOMINAL, "nominal.yaml"))
    assert (legacy.servo.topic, legacy.servo.joint, legacy.scan.topic) == ("/joint_states", "servo", "/scan")


@pytest.mark.parametrize("text,pattern", [
    (NOMINAL + "extra: 1\n", r"nominal.yaml: extra: unknown key"),
    ("mount: {x: 0, y: 0, z: 0, roll: 0, pitch: 0, yaw: 0}\n", r"nominal.yaml: dh: missing"),
    (NOMINAL.replace("b: 0.02", "b: x"), r"nominal.yaml: dh.b: Input should be a valid number.*, got 'x'"),
    (NOMINAL.replace("beta: 1.5708", "gamma: 1"), r"nominal.yaml: dh.gamma: unknown key"),
    (NOMINAL.replace("0.005", "-1"),
     r"nominal.yaml: marker_radius_m: -1 m is no sphere: the markers' radius in metres must be > 0 .*, got -1"),
    (NOMINAL.replace("0.005", "0"), r"nominal.yaml: marker_radius_m: 0 m is no sphere: .*e\.g\. 0\.005.*, got 0"),
    (NOMINAL.replace("joint_name: servo", "joint_name: 3"),
     r"nominal.yaml: joint_name: Input should be a valid string, got 3"),
    ("dh: {a: 0\n", r"nominal.yaml:\d+:\d+: YAML syntax error"),
    ("- 1\n", r"nominal.yaml: expected a mapping"),
    (NOMINAL + "scan: {topic: /x}\n", r"nominal.yaml: scan_topic and scan: both given"),
    ("dh: {a: 0, alpha: 0, b: 0, beta: 0}\nservo: {topic: /s, unit: counts}\n",
     r"nominal.yaml: servo: unit counts needs counts_per_rev"),
    ("dh: {a: 0, alpha: 0, b: 0, beta: 0}\nservo: {topic: /s, unit: degree}\n",
     r"nominal.yaml: servo.unit: Input should be 'rad', 'deg' or 'counts', got 'degree'"),
    ("dh: {a: 0, alpha: 0, b: 0, beta: 0}\nservo: {topic: /s, sign: 2}\n", r"nominal.yaml: servo.sign: .*got 2"),
    ("dh: {a: 0, alpha: 0, b: 0, beta: 0}\nscan: {topic: /s, stamp: now}\n", r"nominal.yaml: scan.stamp: "),
    ("dh: {a: 0, alpha: 0, b: 0, beta: 0}\nservo: {tf: {parent: a}}\n", r"nominal.yaml: servo.tf.child: missing"),
])
def test_read_nominal_bad(tmp_path, text, pattern):
    with pytest.raises(InputError, match=pattern):
        read_nominal(_csv(tmp_path, text, "nominal.yaml"))


# --- the whole folder ---------------------------------------------------------------------------------------

def test_read_recording_defaults_and_overrides(tmp_path):
    rec_dir = tmp_path / "rec"
    rec_dir.mkdir()
    write_bag(rec_dir / "bag", "mcap", scan_topic="/laser/scan")
    _csv(rec_dir, NOMINAL.replace("scan_topic: /scan", "scan_topic: /laser/scan"), "nominal.yaml")
    _csv(rec_dir, GOOD_CSV)
    rec = read_recording(rec_dir)
    assert rec.scans.ranges_m.shape == (5, N_BEAMS) and rec.tape.marker_ids[0] == "m0"
    assert rec.source == rec_dir
    # overrides: a ROS 1 bag elsewhere, topic given explicitly
    other = write_bag(tmp_path / "other.bag", "ros1", scan_topic="/hokuyo")
    rec2 = read_recording(rec_dir, bag=other, scan_topic="/hokuyo")
    assert rec2.scans.ranges_m.shape == (5, N_BEAMS)
    with pytest.raises(InputError, match=r"other.bag: topic /laser/scan: not in bag"):
        read_recording(rec_dir, bag=other)


def test_read_recording_missing_folder(tmp_path):
    with pytest.raises(InputError, match="recording folder not found"):
        read_recording(tmp_path / "nope")
