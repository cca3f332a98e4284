"""The ROS 2 files beside rig.urdf (lrfcal.io.ros_launch): rig_tf.launch.py (tf2_ros static_transform_publisher of
the mount, new-style arguments) and rig_joints.urdf (the servo's revolute joint and the scanner's fixed joint)."""

from __future__ import annotations

import ast
import dataclasses
import math
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import console_script
from synthetic import make_result

from lrfcal.commands.calibration_folder import write_calibration
from lrfcal.io.rig import ServoSource
from lrfcal.io.ros_launch import JOINTS_NAME, LAUNCH_NAME, MOTOR_FRAME, WORLD_FRAME, quaternion_xyzw
from lrfcal.model.kinematics import DH, Pose, chain_T_M_L, pose_matrix, rot_z

LAUNCH_ARGS = ("--x", "--y", "--z", "--qx", "--qy", "--qz", "--qw", "--frame-id", "--child-frame-id")


def _static_tf_arguments(text: str) -> dict[str, str]:
    """The static_transform_publisher's arguments of a launch file, flag -> value, read from its syntax tree (the
    file compiles: a syntax error raises here)."""
    tree = ast.parse(compile(text, LAUNCH_NAME, "exec", ast.PyCF_ONLY_AST))
    lists = [n for n in ast.walk(tree) if isinstance(n, ast.List)
             and any(isinstance(e, ast.Constant) and e.value == "--qw" for e in n.elts)]
    assert len(lists) == 1, "one static_transform_publisher argument list"
    items = [ast.literal_eval(e) for e in lists[0].elts]
    assert len(items) == 2 * len(LAUNCH_ARGS)
    return dict(zip(items[::2], items[1::2], strict=True))


def _quaternion_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """The rotation matrix of a unit quaternion (Hamilton, as tf2), written out (not lrfcal's conversion)."""
    return np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]])


def _origin(joint: ET.Element) -> np.ndarray:
    o = joint.find("origin")
    assert o is not None
    return pose_matrix(*map(float, o.get("xyz", "").split()), *map(float, o.get("rpy", "").split()))


def _joint_chain(text: str, q: float) -> tuple[np.ndarray, ET.Element]:
    """T_motor_base_laser of rig_joints.urdf at joint position q (revolute origin, Rz(axis q), fixed origin)."""
    root = ET.fromstring(text)
    joints = root.findall("joint")
    servo = next(j for j in joints if j.get("type") == "revolute")
    fixed = next(j for j in joints if j.get("type") == "fixed")
    axis = np.array([float(v) for v in servo.find("axis").get("xyz").split()])  # type: ignore[union-attr]
    assert np.allclose(np.abs(axis), [0, 0, 1])
    turn = np.eye(4)
    turn[:3, :3] = rot_z(axis[2] * q)
    assert servo.find("child").get("link") == fixed.find("parent").get("link")  # type: ignore[union-attr]
    return _origin(servo) @ turn @ _origin(fixed), servo


def test_quaternion_is_the_mount_rotation() -> None:
    for pose in (Pose(roll=1.5882, pitch=-0.0262, yaw=-1.5533), Pose(roll=-3.0, pitch=1.2, yaw=2.9), Pose()):
        q = quaternion_xyzw(pose)
        assert q[3] >= 0 and math.isclose(float(np.linalg.norm(q)), 1.0, abs_tol=1e-12)
        np.testing.assert_allclose(_quaternion_matrix(*q), pose.matrix()[:3, :3], atol=1e-12)


def test_files_of_a_servo_turned_the_other_way_with_an_offset(tmp_path: Path) -> None:
    """A servo source with sign -1 and an offset, the calibration's direction negated too: the joint's position q
    still gives the chain of eq. (3) at lambda = servo_sign (sign q + offset)."""
    result = make_result(n_scans=40, n_beams=121)
    nominal = dataclasses.replace(result.recording.nominal,
                                  servo=ServoSource(topic="/dxl/joint_states", joint="tilt", sign=-1, offset_rad=0.3))
    result = dataclasses.replace(result, recording=dataclasses.replace(result.recording, nominal=nominal),
                                 servo_sign=-1)
    out = write_calibration(tmp_path / "cal", result)
    text = (out / JOINTS_NAME).read_text()
    dh = result.solution.params.dh
    for q in (-1.1, 0.0, 0.7):
        T, servo = _joint_chain(text, q)
        lam = -1 * (-1 * q + 0.3)
        np.testing.assert_allclose(T, chain_T_M_L(lam, 0.0, dh)[0], atol=1e-8)
    assert servo.get("name") == "tilt"
    launch = (out / LAUNCH_NAME).read_text()
    assert "'/dxl/joint_states'" in launch


def test_calibrate_writes_the_ros_files(tmp_path: Path, shipped_recording) -> None:  # type: ignore[no-untyped-def]
    """`lrfcal calibrate` writes rig_tf.launch.py and rig_joints.urdf beside rig.urdf: the launch file compiles, its
    static transform is the calibrated mount (translation, and the quaternion's rotation against the mount's roll,
    pitch, yaw in calibration.yaml), the URDF parses and its joints compose to the calibrated T_M_L at a test angle."""
    out = tmp_path / "cal"
    proc = subprocess.run([console_script("lrfcal"), "calibrate", str(shipped_recording("plane_30deg")),
                           "-o", str(out), "--no-baseline", "--no-figures"], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert {"rig.urdf", LAUNCH_NAME, JOINTS_NAME} <= {p.name for p in out.iterdir()}
    data = yaml.safe_load((out / "calibration.yaml").read_text())
    mount = Pose(**{k: float(v["value"] if isinstance(v, dict) else v) for k, v in data["mount"].items()})
    dh = DH(**{k: float(v["value"] if isinstance(v, dict) else v) for k, v in data["dh"].items()})

    args = _static_tf_arguments((out / LAUNCH_NAME).read_text())
    assert set(args) == set(LAUNCH_ARGS)
    assert (args["--frame-id"], args["--child-frame-id"]) == (WORLD_FRAME, MOTOR_FRAME)
    np.testing.assert_allclose([float(args[k]) for k in ("--x", "--y", "--z")], [mount.x, mount.y, mount.z],
                               atol=1e-9)
    q = [float(args[k]) for k in ("--qx", "--qy", "--qz", "--qw")]
    np.testing.assert_allclose(_quaternion_matrix(*q), mount.matrix()[:3, :3], atol=1e-8)
    launch = (out / LAUNCH_NAME).read_text()
    for name, value in (("roll", mount.roll), ("pitch", mount.pitch), ("yaw", mount.yaw)):
        assert f"{name} {value:.6g}" in launch or f"{name} {value:.9g}" in launch, name  # the comment

    text = (out / JOINTS_NAME).read_text()
    T, servo = _joint_chain(text, 0.4)
    np.testing.assert_allclose(T, chain_T_M_L(0.4, 0.0, dh)[0], atol=1e-7)
    links = {e.get("name") for e in ET.fromstring(text).findall("link")}
    assert servo.find("parent").get("link") == MOTOR_FRAME and MOTOR_FRAME in links  # type: ignore[union-attr]


@pytest.mark.parametrize("sign", [1, -1])
def test_joint_snippet_matches_rig_urdf(tmp_path: Path, sign: int) -> None:
    """The mount of the launch file then rig_joints.urdf's chain equal rig.urdf's whole chain at any angle."""
    result = dataclasses.replace(make_result(n_scans=40, n_beams=121), servo_sign=sign)
    out = write_calibration(tmp_path / "cal", result)
    rig = ET.fromstring((out / "rig.urdf").read_text())
    joints = {j.get("name"): j for j in rig.findall("joint")}
    args = _static_tf_arguments((out / LAUNCH_NAME).read_text())
    T_W_M = np.eye(4)
    T_W_M[:3, :3] = _quaternion_matrix(*(float(args[k]) for k in ("--qx", "--qy", "--qz", "--qw")))
    T_W_M[:3, 3] = [float(args[k]) for k in ("--x", "--y", "--z")]
    for lam in (-0.9, 0.25):
        turn = np.eye(4)
        turn[:3, :3] = rot_z(lam)
        whole = _origin(joints["world_to_motor_base"]) @ _origin(joints["servo"]) @ turn @ _origin(
            joints["laser_mount"])
        np.testing.assert_allclose(T_W_M @ _joint_chain((out / JOINTS_NAME).read_text(), sign * lam)[0], whole,
                                   atol=1e-8)


def test_targetless_launch_publishes_no_mount() -> None:
    """A targetless calibration estimates no mount: its launch file compiles, starts robot_state_publisher only and
    says why there is no static transform."""
    from lrfcal.io.ros_launch import mount_launch

    text = mount_launch(None)
    compile(text, LAUNCH_NAME, "exec")
    assert "static_transform_publisher" not in text and "robot_state_publisher" in text
    assert "targetless calibration does not estimate it" in text


def test_joint_snippet_cautions_where_a_urdf_joint_cannot_say_it() -> None:
    """A servo angle recorded in degrees, or taken from a tf rather than a JointState, cannot be a URDF joint's
    position as it is: rig_joints.urdf's header says CAUTION and why; a plain JointState in rad needs none."""
    from lrfcal.io.ros_launch import ros_files

    result = make_result(n_scans=40, n_beams=121)
    assert "CAUTION" not in ros_files(result)[JOINTS_NAME]
    for servo, words in ((ServoSource(joint="servo", unit="deg"), "unit deg"),
                         (ServoSource(topic="/imu", field="angle"), "not a sensor_msgs/JointState")):
        nominal = dataclasses.replace(result.recording.nominal, servo=servo)
        other = dataclasses.replace(result, recording=dataclasses.replace(result.recording, nominal=nominal))
        text = ros_files(other)[JOINTS_NAME]
        ET.fromstring(text)  # still XML: no "--" in its comment
        assert "CAUTION" in text and words in text, text


def test_urdf_attribute_quoting_is_xml_saxs() -> None:
    """lrfcal.io.urdf quotes attribute values as xml.sax.saxutils.quoteattr does (without importing it: it loads
    urllib, http and ssl on every calibration)."""
    from xml.sax.saxutils import quoteattr

    from lrfcal.io.urdf import _quoteattr

    for text in ("laser", "", "a&b<c>d", 'say "hi"', "it's", "both ' and \"", "tab\there\nnew\rline", "&amp;"):
        assert _quoteattr(text) == quoteattr(text), text
