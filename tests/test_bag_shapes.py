"""Every supported bag shape of the same small simulation reprojects to the canonical recording's cloud.

The simulation: S scans of N beams from a 2D scanner on a servo that steps in whole degrees (a hobby servo /
stepper), so that a degree-valued Int32, 0.1-degree encoder counts, radians and a quaternion all carry exactly
the same angle. The canonical recording is what lrfsim writes (sensor_msgs/LaserScan + sensor_msgs/JointState,
header stamps, ROS 2 MCAP). Each shape writes the same information differently; its cloud must equal the
canonical one to 1e-6 m (the only differences are float rounding: float32 time_increment, quaternions).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from lrfcal.commands.reproject import BeamCloud, reproject_beams
from lrfcal.io.bag import read_bag
from lrfcal.io.rig import ScanSource, ServoSource, TfSource
from lrfcal.model.kinematics import DH

T0 = 1_700_000_000.0
S, N = 40, 61
SCAN_TIME = 0.025
ANGLE_MIN, INC = -1.0, 1.0 / 30.0
#: time_increment = scan_time / beams-per-revolution, so that writing 0 loses nothing
T_INC = float(np.float32(SCAN_TIME * INC / (2 * math.pi)))
JOINT_DT = 0.01
DH_TEST = DH(a=0.05, alpha=0.3, b=0.02, beta=0.1)
TOL_M = 1e-6

SCAN_WITH_ANGLE = "lrf_test_msgs/msg/ScanWithAngle"
SCAN_WITH_ANGLE_DEF = "sensor_msgs/LaserScan scan\nfloat64 angle_deg\n"
#: dynamixel_msgs/JointState as in arebgun/dynamixel_motor (dynamixel_msgs/msg/JointState.msg)
DXL = "dynamixel_msgs/msg/JointState"
DXL_DEF = ("std_msgs/Header header\nstring name\nint32[] motor_ids\nint32[] motor_temps\nfloat64 goal_pos\n"
           "float64 current_pos\nfloat64 error\nfloat64 velocity\nfloat64 load\nbool is_moving\n")


def _sim():
    rng = np.random.default_rng(7)
    stamps = T0 + SCAN_TIME * np.arange(S)
    ranges = rng.uniform(0.5, 5.0, (S, N)).astype(np.float32)
    ranges[rng.random((S, N)) < 0.05] = np.nan
    intens = rng.uniform(100, 5000, (S, N)).astype(np.float32)
    jt = np.arange(T0 - 0.05, T0 + S * SCAN_TIME + 0.05, JOINT_DT)
    deg = np.round(40.0 * np.sin(2 * np.pi * 1.0 * (jt - T0)))  # whole degrees
    return stamps, ranges, intens, jt, deg


STAMPS, RANGES, INTENS, JT, JDEG = _sim()


def _store(ros1: bool):
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(SCAN_WITH_ANGLE_DEF, SCAN_WITH_ANGLE))
    ts.register(get_types_from_msg(DXL_DEF, DXL))
    if ros1 and "tf2_msgs/msg/TFMessage" not in ts.types:
        ts2 = get_typestore(Stores.ROS2_HUMBLE)
        ts.register({k: ts2.fielddefs[k] for k in ("tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped")})
    return ts


def _time(ts, t):
    ns = int(round(t * 1e9))
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(ts, t, frame, ros1):
    H = ts.types["std_msgs/msg/Header"]
    return H(seq=0, stamp=_time(ts, t), frame_id=frame) if ros1 else H(stamp=_time(ts, t), frame_id=frame)


def _scan_msg(ts, k, ros1, t_inc=T_INC, n=N):
    LS = ts.types["sensor_msgs/msg/LaserScan"]
    return LS(header=_header(ts, STAMPS[k], "laser", ros1), angle_min=ANGLE_MIN,
              angle_max=ANGLE_MIN + INC * (n - 1), angle_increment=INC, time_increment=t_inc, scan_time=SCAN_TIME,
              range_min=0.05, range_max=30.0, ranges=RANGES[k, :n].copy(), intensities=INTENS[k, :n].copy())


def _ns(t):
    return int(round(t * 1e9))


def write(path: Path, kind: str = "mcap", shape: str = "canonical") -> Path:
    """Write the simulation as one bag shape. kind: mcap | sqlite3 | ros1."""
    ros1 = kind == "ros1"
    ts = _store(ros1)
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer as W1

        writer = W1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as W2

        writer = W2(path, version=9, storage_plugin=StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3)
    LT, JT_ = "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/JointState"
    lam = np.radians(JDEG)
    events = []  # (log ns, connection key, message, type)
    servo_shift = 100.0 if shape == "clocks_100s" else 0.0
    scan_log = 0.0 if shape == "clocks_100s" else SCAN_TIME  # logged at the end of the scan (lrfsim)
    for k in range(S):
        if shape == "in_scan":
            deg = float(np.interp(STAMPS[k], JT, JDEG))
            msg = ts.types[SCAN_WITH_ANGLE](scan=_scan_msg(ts, k, ros1), angle_deg=deg)
            events.append((_ns(STAMPS[k] + scan_log), "scan", msg, SCAN_WITH_ANGLE))
            continue
        t_inc = 0.0 if shape == "time_increment_0" else T_INC
        n = N - (k % 5) * 7 if shape == "variable_beams" else N
        events.append((_ns(STAMPS[k] + scan_log), "scan", _scan_msg(ts, k, ros1, t_inc, n), LT))
    if shape != "in_scan":
        for t, q, d in zip(JT, lam, JDEG, strict=True):
            log = _ns(t)
            if shape in ("canonical", "time_increment_0", "variable_beams", "clocks_100s", "by_name"):
                names = ["pan", "servo", "tilt"] if shape == "by_name" else ["servo"]
                pos = [1.0, q, 2.0] if shape == "by_name" else [q]
                msg = ts.types[JT_](header=_header(ts, t - servo_shift, "", ros1), name=names,
                                    position=np.array(pos), velocity=np.zeros(0), effort=np.zeros(0))
                events.append((log, "servo", msg, JT_))
            elif shape == "int32_deg":
                events.append((log, "servo", ts.types["std_msgs/msg/Int32"](data=int(d)), "std_msgs/msg/Int32"))
            elif shape == "counts":
                events.append((log, "servo", ts.types["std_msgs/msg/Int32"](data=int(d * 10)), "std_msgs/msg/Int32"))
            elif shape == "float64_rad":
                events.append((log, "servo", ts.types["std_msgs/msg/Float64"](data=float(q)), "std_msgs/msg/Float64"))
            elif shape == "sign_minus":
                events.append((log, "servo", ts.types["std_msgs/msg/Float64"](data=float(-q) + 0.25),
                               "std_msgs/msg/Float64"))
            elif shape == "dynamixel":
                msg = ts.types[DXL](header=_header(ts, t, "", ros1), name="tilt", motor_ids=np.array([1], np.int32),
                                    motor_temps=np.array([40], np.int32), goal_pos=0.0, current_pos=float(q),
                                    error=0.0, velocity=0.0, load=0.0, is_moving=True)
                events.append((log, "servo", msg, DXL))
            elif shape == "tf":
                Q = ts.types["geometry_msgs/msg/Quaternion"]
                V = ts.types["geometry_msgs/msg/Vector3"]
                TS = ts.types["geometry_msgs/msg/TransformStamped"]
                Tr = ts.types["geometry_msgs/msg/Transform"]
                tr = TS(header=_header(ts, t, "base", ros1), child_frame_id="tilt",
                        transform=Tr(translation=V(x=0.0, y=0.0, z=0.1),
                                     rotation=Q(x=0.0, y=0.0, z=math.sin(q / 2), w=math.cos(q / 2))))
                other = TS(header=_header(ts, t, "map", ros1), child_frame_id="base",
                           transform=Tr(translation=V(x=1.0, y=0.0, z=0.0), rotation=Q(x=0.0, y=0.0, z=0.0, w=1.0)))
                events.append((log, "tf", ts.types["tf2_msgs/msg/TFMessage"](transforms=[other, tr]),
                               "tf2_msgs/msg/TFMessage"))
            else:
                raise ValueError(shape)
    events.sort(key=lambda e: e[0])
    topics = {"scan": "/scan", "servo": "/servo", "tf": "/tf"}
    if shape in ("canonical", "time_increment_0", "variable_beams", "clocks_100s", "by_name"):
        topics["servo"] = "/joint_states"
    with writer:
        conns = {}
        for _, key, _, typ in events:
            if key not in conns:
                conns[key] = writer.add_connection(topics[key], typ, typestore=ts)
        for log, key, msg, typ in events:
            writer.write(conns[key], log, ser(msg, typ))
    return path


SHAPES = {
    # shape: (scan source, servo source)
    "by_name": (ScanSource(), ServoSource(joint="servo")),
    "int32_deg": (ScanSource(), ServoSource(topic="/servo", unit="deg", stamp="receive")),
    "float64_rad": (ScanSource(), ServoSource(topic="/servo", stamp="receive")),
    "counts": (ScanSource(), ServoSource(topic="/servo", unit="counts", counts_per_rev=3600, stamp="receive")),
    "sign_minus": (ScanSource(), ServoSource(topic="/servo", sign=-1, offset_rad=0.25, stamp="receive")),
    "dynamixel": (ScanSource(), ServoSource(topic="/servo")),
    "tf": (ScanSource(), ServoSource(topic=None, tf=TfSource(parent="base", child="tilt"))),
    "time_increment_0": (ScanSource(), ServoSource(joint="servo")),
    "variable_beams": (ScanSource(), ServoSource(joint="servo")),
    "clocks_100s": (ScanSource(), ServoSource(joint="servo")),
    # this synthetic servo turns while the laser scans: motion continuous (stamp: scan alone means step and scan)
    "in_scan": (ScanSource(field="scan"), ServoSource(topic=None, field="angle_deg", unit="deg", stamp="scan",
                                                      motion="continuous")),
}


def cloud_of(path: Path, scan: ScanSource, servo: ServoSource, **kw) -> tuple[BeamCloud, object]:
    data = read_bag(path, scan, servo, warn=lambda _t: None, **kw)
    return reproject_beams(data.scans, data.joints, DH_TEST), data


@pytest.fixture(scope="module")
def canonical(tmp_path_factory) -> BeamCloud:
    path = write(tmp_path_factory.mktemp("canon") / "bag", "mcap", "canonical")
    cloud, data = cloud_of(path, ScanSource(), ServoSource(joint="servo"))
    assert data.report.n_scans == S and len(cloud) == int(np.isfinite(RANGES).sum())
    return cloud


@pytest.fixture(scope="module")
def canonical_in_scan(tmp_path_factory) -> BeamCloud:
    """The canonical shape whose joint samples are exactly the angle at each scan stamp (what an angle carried
    in the scan's message says)."""
    path = write(tmp_path_factory.mktemp("canon2") / "bag", "mcap", "canonical")
    data = read_bag(path, ScanSource(), ServoSource(joint="servo"), warn=lambda _t: None)
    from lrfcal.types import JointStates

    j = JointStates(STAMPS.copy(), np.radians(np.interp(STAMPS, JT, JDEG)), "servo")
    return reproject_beams(data.scans, j, DH_TEST)


def _same(a: BeamCloud, b: BeamCloud) -> float:
    """Max point distance over the (scan, beam) pairs of b (which must all be in a)."""
    key_a = a.scan * 10_000 + a.beam
    key_b = b.scan * 10_000 + b.beam
    idx = np.searchsorted(key_a, key_b)
    assert np.all(key_a[np.minimum(idx, key_a.size - 1)] == key_b), "returns missing from the canonical cloud"
    return float(np.max(np.linalg.norm(a.points_M[idx] - b.points_M, axis=1)))


@pytest.mark.parametrize("shape", [s for s in SHAPES if s != "in_scan"])
def test_shape_reprojects_like_canonical(tmp_path, canonical, shape):
    scan, servo = SHAPES[shape]
    cloud, data = cloud_of(write(tmp_path / "bag", "mcap", shape), scan, servo)
    n_expected = len(canonical) if shape != "variable_beams" else int(sum(
        np.isfinite(RANGES[k, : N - (k % 5) * 7]).sum() for k in range(S)))
    assert len(cloud) == n_expected
    assert _same(canonical, cloud) < TOL_M
    rep = data.report
    if shape == "time_increment_0":
        assert rep.n_time_increment_assumed == S
        assert rep.assumed_time_increment_s == pytest.approx(T_INC, rel=1e-6)
        assert any("time_increment is 0" in n for n in rep.notes)
    if shape == "variable_beams":
        assert (rep.beam_count_min, rep.beam_count_max) == (N - 28, N)
    if shape == "clocks_100s":
        assert rep.clock_offset_applied and rep.clock_offset_s == pytest.approx(100.0, abs=1e-6)
    else:
        assert not rep.clock_offset_applied


def test_angle_inside_the_scan_message(tmp_path, canonical_in_scan):
    scan, servo = SHAPES["in_scan"]
    cloud, data = cloud_of(write(tmp_path / "bag", "mcap", "in_scan"), scan, servo)
    assert data.report.n_servo_samples == S and data.report.clock_offset_s == 0.0
    assert len(cloud) == len(canonical_in_scan)
    assert _same(canonical_in_scan, cloud) < TOL_M


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_ros1_and_ros2_storages_give_the_same_cloud(tmp_path, canonical, kind):
    path = write(tmp_path / ("rec.bag" if kind == "ros1" else "bag"), kind, "canonical")
    cloud, _ = cloud_of(path, ScanSource(), ServoSource(joint="servo"))
    np.testing.assert_array_equal(cloud.scan, canonical.scan)
    np.testing.assert_array_equal(cloud.points_M, canonical.points_M)


def test_custom_type_in_ros1_bag(tmp_path, canonical_in_scan):
    """A ROS 1 bag whose custom scan message is defined only inside the bag."""
    scan, servo = SHAPES["in_scan"]
    cloud, _ = cloud_of(write(tmp_path / "rec.bag", "ros1", "in_scan"), scan, servo)
    assert _same(canonical_in_scan, cloud) < TOL_M


def test_wrong_sign_is_not_the_same_cloud(tmp_path, canonical):
    """The comparison can fail: reading the sign -1 bag with sign +1 gives another cloud."""
    cloud, _ = cloud_of(write(tmp_path / "bag", "mcap", "sign_minus"), ScanSource(),
                        ServoSource(topic="/servo", offset_rad=0.25, stamp="receive"))
    assert _same(canonical, cloud) > 0.1


def test_inspect_guesses_the_moving_tf_joint(tmp_path):
    from lrfcal.commands.inspect_bag import inspect_bag

    result = inspect_bag(write(tmp_path / "bag", "mcap", "tf"), propose=False)
    assert result.servo_source is not None and result.servo_source.tf == TfSource(parent="base", child="tilt")
    assert result.report is not None and result.report.n_servo_samples == JT.size


def test_bad_servo_sources_name_the_fix(tmp_path):
    from lrfcal.errors import InputError

    path = write(tmp_path / "bag", "mcap", "int32_deg")
    with pytest.raises(InputError, match=r"/servo.*stamp: std_msgs/msg/Int32 has no header; set servo.stamp: rec"):
        read_bag(path, ScanSource(), ServoSource(topic="/servo", unit="deg"))
    with pytest.raises(InputError, match=r"field angle: no 'angle' in std_msgs/msg/Int32 \(fields: data\)"):
        read_bag(path, ScanSource(), ServoSource(topic="/servo", field="angle", stamp="receive"))
    with pytest.raises(InputError, match=r"bag: /scan: field laserScan: no 'laserScan' in sensor_msgs/msg/LaserS"):
        read_bag(path, ScanSource(field="laserScan"), ServoSource(topic="/servo", stamp="receive"))
