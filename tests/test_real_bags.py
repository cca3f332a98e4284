"""The public recordings of real tilting-lidar rigs in ../shared/realbags (see its README.md).

They are not part of the project (a clone alone does not have them): every test skips with the reason when the
folder is absent. Counts are checked against an independent pass over the raw messages with rosbags.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from lrfcal.commands.inspect_bag import inspect_bag
from lrfcal.commands.reproject import reproject_beams
from lrfcal.io.bag import read_bag
from lrfcal.io.rig import ScanSource, ServoSource, parse_rig
from lrfcal.model.kinematics import DH

REALBAGS = Path(__file__).resolve().parents[2] / "shared" / "realbags"
BOX = REALBAGS / "cardboard_box.bag"
ROOM = REALBAGS / "room_240.bag"
RPLIDAR = REALBAGS / "rplidar_servo_3hz"

pytestmark = pytest.mark.skipif(not REALBAGS.is_dir(), reason=f"real recordings not present at {REALBAGS} "
                                "(public bags shared beside the project, not part of a clone)")

URG_SCAN = ScanSource(topic="/slice", field="laserScan")
URG_SERVO = ServoSource(topic=None, field="stepAngle", unit="deg", stamp="scan")
#: The URG-04LX stand of liangfok/tilting_lidar_scanner: the stand tilts about the scanner's y axis and the scan
#: plane sits about 0.08 m from the tilt axis (the authors' model; a nominal only). In eq. (3)
#: (T_M_L = Rz(lambda) Tx(a) Rx(alpha) Tz(b) Rz(beta) Rz(mu)) the motor axis z_M must be the scanner's y axis:
#: alpha = +90 deg turns z into -y, so y_L = z_M (beta = 0 keeps x_L = x_M, forward at lambda = 0), and the
#: laser origin lies b = 0.08 m along z_L from the axis (a = 0: the axis crosses the scanner's z axis).
URG_NOMINAL = DH(a=0.0, alpha=math.pi / 2, b=0.08, beta=0.0)
#: URG-04LX range accuracy: +-10 mm for 60-1000 mm (Hokuyo URG-04LX specification); 1-sigma well below that.
URG_NOISE_M = 0.010


def _raw(path: Path, topic: str):
    """Independent pass: (receive ns, decoded message) of a topic."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        conns = [c for c in r.connections if c.topic == topic]
        return [(t, r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages(connections=conns)]


def _expected_masks(scans) -> dict[str, int]:
    out = {"zero": 0, "nan": 0, "inf": 0, "below_range_min": 0, "above_range_max": 0}
    for ls in scans:
        r = np.asarray(ls.ranges, dtype=np.float64)
        if r.size == 0 or not math.isfinite(ls.angle_increment):
            continue
        fin = np.isfinite(r)
        out["zero"] += int((r == 0).sum())
        out["nan"] += int(np.isnan(r).sum())
        out["inf"] += int(np.isinf(r).sum())
        out["below_range_min"] += int((fin & (r != 0) & (r < ls.range_min)).sum())
        out["above_range_max"] += int((fin & (r > ls.range_max)).sum())
    return {k: v for k, v in out.items() if v}


@pytest.fixture(scope="module")
def box():
    return read_bag(BOX, URG_SCAN, URG_SERVO, warn=lambda _t: None)


@pytest.mark.parametrize("path", [BOX, ROOM], ids=["cardboard_box", "room_240"])
def test_urg_recordings_read_with_counts_of_the_bag(path):
    raw = _raw(path, "/slice")
    data = read_bag(path, URG_SCAN, URG_SERVO, warn=lambda _t: None)
    rep = data.report
    scans = [m.laserScan for _, m in raw]
    assert rep.n_scan_messages == len(raw) and rep.n_scans == len(raw) and not rep.skipped
    assert rep.beam_count_min == rep.beam_count_max == len(scans[0].ranges)
    assert rep.masked == _expected_masks(scans)
    assert rep.n_valid_returns == int(np.isfinite(data.scans.ranges_m).sum())
    assert rep.n_servo_samples == len(raw) and not rep.clock_offset_applied
    # the tilt angle travels with its scan, in degrees (0.075 deg steps)
    by_time = sorted(raw, key=lambda x: (x[1].laserScan.header.stamp.sec, x[1].laserScan.header.stamp.nanosec))
    deg = [m.stepAngle for _, m in by_time]
    np.testing.assert_allclose(np.degrees(data.joints.positions_rad), deg, atol=1e-9)


def test_box_walls_are_planar_within_the_sensor_noise(box):
    """The box's far wall (beams within 15 deg of the scanner's x axis, tilt below 40 deg, where the scanner does
    not see its own stand) reprojected with the authors' nominal geometry is a plane within the URG-04LX's
    noise; the same beams with the tilt misread as radians are not."""
    def plane_rms(p: np.ndarray) -> float:
        q = p - p.mean(0)
        return float(np.linalg.svd(q, full_matrices=False)[1][2] / math.sqrt(len(q)))

    c = reproject_beams(box.scans, box.joints, URG_NOMINAL)
    mu = np.degrees(box.scans.mu_rad[c.scan, c.beam])
    sel = (np.abs(mu) < 15) & (c.lambda_rad < math.radians(40))
    assert sel.sum() > 50_000
    rms = plane_rms(c.points_M[sel])
    assert rms < URG_NOISE_M
    wrong = read_bag(BOX, URG_SCAN, URG_SERVO.model_copy(update={"unit": "rad"}), warn=lambda _t: None)
    cw = reproject_beams(wrong.scans, wrong.joints, URG_NOMINAL)
    np.testing.assert_array_equal(cw.scan, c.scan)  # the same beams
    assert plane_rms(cw.points_M[sel]) > 3 * rms


def test_rplidar_reads_and_names_its_timing_problems():
    raw = _raw(RPLIDAR, "/scan")
    warnings: list[str] = []
    data = read_bag(RPLIDAR, ScanSource(topic="/scan"),
                    ServoSource(topic="/lidar_servo_angle", unit="deg", stamp="receive", offset_rad=-math.pi / 2),
                    warn=warnings.append)
    rep = data.report
    empty = sum(1 for _, m in raw if len(m.ranges) == 0 or not math.isfinite(m.angle_increment))
    assert empty > 0 and rep.skipped == {"empty": empty}
    assert rep.n_scan_messages == len(raw) and rep.n_scans == len(raw) - empty
    assert rep.masked == _expected_masks([m for _, m in raw])
    assert rep.n_servo_messages == len(_raw(RPLIDAR, "/lidar_servo_angle"))
    counts = [len(m.ranges) for _, m in raw if len(m.ranges)]
    assert (rep.beam_count_min, rep.beam_count_max) == (min(counts), max(counts))
    # timing problems named: time_increment 0 (warned), uptime vs wall clock, scan_time vs stamps, irregular servo
    assert rep.n_time_increment_assumed == rep.n_scans and len(warnings) == 1 and "time_increment" in warnings[0]
    assert rep.clock_offset_applied and rep.clock_offset_s < -1e9
    text = "\n".join(rep.lines())
    for phrase in ("time_increment is 0", "clocks:", "scan_time 0.1 s but the stamps", "irregular servo samples"):
        assert phrase in text
    cloud = reproject_beams(data.scans, data.joints, DH(a=0.0, alpha=math.pi / 2, b=0.04, beta=0.0))
    assert len(cloud) > 0.9 * rep.n_valid_returns and np.isfinite(cloud.points_M).all()


@pytest.mark.parametrize("path,n_topics", [(BOX, 1), (RPLIDAR, 3)], ids=["cardboard_box", "rplidar"])
def test_inspect_snippet_reads_the_bag(path, n_topics):
    result = inspect_bag(path, propose=False)  # the DH proposal: tests/test_inspect_dh.py
    assert len(result.topics) == n_topics and result.report is not None
    rig = parse_rig(yaml.safe_load(result.rig_snippet), "snippet")
    data = read_bag(path, rig.scan_source(), rig.servo_source(), warn=lambda _t: None)
    assert data.report.n_scans == result.report.n_scans > 0
    if path == BOX:
        assert rig.servo_source().field == "stepAngle" and rig.servo_source().unit == "deg"
        assert rig.servo_source().stamp == "scan" and result.geometry.beam_count == (512, 512)
        assert rig.servo_source().motion == "step" and "motion: step" in result.rig_snippet
    else:
        assert rig.servo_source().topic == "/lidar_servo_angle" and rig.servo_source().stamp == "receive"
        assert any("time_increment is 0" in p for p in result.problems)


def _eq3_points(r: np.ndarray, lam: np.ndarray, mu: np.ndarray, dh: DH) -> np.ndarray:
    """Eq. (3) written out independently of the model: Rz(lam) Tx(a) Rx(alpha) Tz(b) Rz(beta + mu) [r 0 0]."""
    th = dh.beta + mu
    x_l, y_l = r * np.cos(th), r * np.sin(th)  # in the frame after Tz(b): (x_l, y_l, b)
    ca, sa = math.cos(dh.alpha), math.sin(dh.alpha)
    x1, y1, z1 = x_l + dh.a, ca * y_l - sa * dh.b, sa * y_l + ca * dh.b
    cl, sl = np.cos(lam), np.sin(lam)
    return np.stack([cl * x1 - sl * y1, sl * x1 + cl * y1, z1], axis=1)


@pytest.mark.parametrize("path", [BOX, ROOM], ids=["cardboard_box", "room_240"])
def test_step_and_scan_every_beam_takes_its_own_messages_angle(path):
    """The URG stand steps, stands still and scans: the tilt in a /slice message belongs to every beam of its scan.
    The reprojected cloud matches an independent reprojection that gives each beam its own message's angle within
    0.05 mm; interpolating towards the next message's angle (motion: continuous) does not."""
    raw = sorted(_raw(path, "/slice"), key=lambda x: (x[1].laserScan.header.stamp.sec,
                                                      x[1].laserScan.header.stamp.nanosec))
    data = read_bag(path, URG_SCAN, URG_SERVO, warn=lambda _t: None)
    assert URG_SERVO.steps() and data.scans.angle_per_scan  # stamp: scan means step and scan by default
    c = reproject_beams(data.scans, data.joints, URG_NOMINAL)
    assert c.n_scans_uncovered == 0 and len(c) == data.report.n_valid_returns
    lam_msg = np.radians([m.stepAngle for _, m in raw])[c.scan]
    ls0 = raw[0][1].laserScan
    mu = ls0.angle_min + c.beam * ls0.angle_increment
    r = np.asarray([m.laserScan.ranges for _, m in raw], dtype=float)[c.scan, c.beam]
    expected = _eq3_points(r, lam_msg, mu, URG_NOMINAL)
    assert float(np.abs(c.points_M - expected).max()) < 5e-5
    moving = read_bag(path, URG_SCAN, URG_SERVO.model_copy(update={"motion": "continuous"}), warn=lambda _t: None)
    cm = reproject_beams(moving.scans, moving.joints, URG_NOMINAL)
    common = min(len(cm), len(c))
    # up to 0.0375 deg of the next step: 0.15 mm at the box's walls, about 2 mm at room_240's far wall
    assert float(np.abs(cm.points_M[:common] - c.points_M[:common]).max()) > 2 * 5e-5
