"""Unit mistakes in a recording are named at reading time (issue 46, case 4): ranges written in millimetres and joint
positions written in degrees are refused (exit 2) naming the file, the field, the value and the likely unit, through
the programs' entry points (``main(argv)`` in this process, tests/test_cli_usage.py's ``_call``); the public
recordings of real rigs (../shared/realbags) still read.

The faulty bags are a short simulated plane_30deg recording (tests/test_cli_faults.py's) rewritten message by
message with rosbags: every range, range_min and range_max times 1000, or every joint position in degrees.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from test_cli_faults import _scenario_data
from test_cli_usage import _call, _one_error_line
from test_scanlog import LONGARM_LOG_KEYS

from lrfsim.scenario.file import Scenario, parse_scenario

REALBAGS = Path(__file__).resolve().parents[2] / "shared" / "realbags"
ABSENT = f"real recordings not present at {REALBAGS} (public recordings shared beside the project, not part of a clone)"
SCAN, JOINTS = "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/JointState"


@pytest.fixture(scope="module")
def clean(recording_of: Callable[[Scenario], Path]) -> Path:
    """The short plane_30deg recording without faults (shared, read-only)."""
    return recording_of(parse_scenario(_scenario_data("units", {}), "units.yaml"))


def _rewritten(src: Path, dst: Path, change: Callable[[str, Any], Any]) -> Path:
    """A copy of the recording folder ``src`` whose bag's messages are ``change(msgtype, message)``."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    dst.mkdir()
    for name in ("nominal.yaml", "distances.csv"):
        shutil.copy(src / name, dst / name)
    with AnyReader([src / "bag"], default_typestore=ts) as reader, \
            Writer(dst / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=ts) for c in reader.connections}
        for c, t_ns, raw in reader.messages():
            msg = change(c.msgtype, reader.deserialize(raw, c.msgtype))
            writer.write(conns[c.topic], t_ns, ts.serialize_cdr(msg, c.msgtype))
    return dst


def _millimetres(msgtype: str, msg: Any) -> Any:
    if msgtype != SCAN:
        return msg
    return dataclasses.replace(msg, ranges=(msg.ranges * 1000).astype(np.float32), range_min=msg.range_min * 1000,
                               range_max=msg.range_max * 1000)


def _degrees(msgtype: str, msg: Any) -> Any:
    if msgtype != JOINTS:
        return msg
    return dataclasses.replace(msg, position=np.degrees(msg.position), velocity=np.degrees(msg.velocity))


def test_ranges_in_millimetres_are_refused_naming_the_field_and_unit(clean: Path, tmp_path: Path) -> None:
    rec = _rewritten(clean, tmp_path / "mm", _millimetres)
    out = tmp_path / "cal"
    line = _one_error_line(_call("lrfcal", "calibrate", rec, "-o", out, "--no-baseline"))
    assert str(rec / "bag") in line and "/scan" in line and "ranges look like millimetres" in line, line
    assert "range_max 60000 m" in line and "(as millimetres: 60 m" in line, line
    assert not out.exists()


def test_joint_positions_in_degrees_are_refused_naming_the_field_and_unit(clean: Path, tmp_path: Path) -> None:
    rec = _rewritten(clean, tmp_path / "deg", _degrees)
    out = tmp_path / "cal"
    line = _one_error_line(_call("lrfcal", "calibrate", rec, "-o", out, "--no-baseline"))
    assert str(rec / "bag") in line and "/joint_states" in line and "joint positions" in line, line
    assert "look like degrees: set servo.unit: deg" in line and "-90" in line and "90" in line, line
    assert not out.exists()
    # the fix the message gives works: with servo.unit: deg the same recording reads (and reprojects)
    rig = yaml.safe_load((rec / "nominal.yaml").read_text())
    rig.setdefault("servo", {})["unit"] = "deg"
    fixed = tmp_path / "deg.yaml"
    fixed.write_text(yaml.safe_dump(rig))
    proc = _call("lrfcal", "reproject", rec / "bag", "--nominal", fixed, "-o", tmp_path / "cloud.ply")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr


#: the real rigs' rig files (tests/test_real_bags.py, tests/test_scanlog.py): the URG-04LX stand's tilt in degrees
#: inside its custom message, the RPLIDAR's ranges beyond range_max and its servo in degrees, the long-arm log
REAL: dict[str, tuple[str, dict[str, object]]] = {
    "cardboard_box": ("cardboard_box.bag", {
        "scan": {"topic": "/slice", "field": "laserScan"},
        "servo": {"topic": None, "field": "stepAngle", "unit": "deg", "stamp": "scan"}}),
    "room_240": ("room_240.bag", {
        "scan": {"topic": "/slice", "field": "laserScan"},
        "servo": {"topic": None, "field": "stepAngle", "unit": "deg", "stamp": "scan"}}),
    "rplidar_servo_3hz": ("rplidar_servo_3hz", {
        "scan": {"topic": "/scan"},
        "servo": {"topic": "/lidar_servo_angle", "unit": "deg", "stamp": "receive", "offset_rad": -math.pi / 2}}),
    "longarm": ("longarm/batchScanned20191114103039.txt", {
        "servo": {"unit": "deg", "sign": -1},
        "log": LONGARM_LOG_KEYS}),
}


@pytest.mark.skipif(not REALBAGS.is_dir(), reason=ABSENT)
@pytest.mark.parametrize("name", list(REAL))
def test_real_recordings_are_not_taken_for_unit_mistakes(name: str, tmp_path: Path) -> None:
    path, sources = REAL[name]
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump({"dh": {"a": 0.0, "alpha": math.pi / 2, "b": 0.05, "beta": 0.0}, **sources}))
    proc = _call("lrfcal", "reproject", REALBAGS / path, "--nominal", rig, "-o", tmp_path / "cloud.ply")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert (tmp_path / "cloud.ply").stat().st_size > 100_000
