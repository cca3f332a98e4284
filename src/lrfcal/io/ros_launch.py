"""The ROS 2 files beside rig.urdf: rig_tf.launch.py and rig_joints.urdf.

rig_tf.launch.py, a Python launch file, starts tf2_ros' static_transform_publisher with the calibrated mount T_W_M
(parent frame ``world`` = W, the frame of the marker map, child ``motor_base`` = M, the motor frame at servo angle
0) in its new-style arguments ``--x --y --z --qx --qy --qz --qw --frame-id --child-frame-id`` (ros2/geometry2,
tf2_ros/src/static_transform_broadcaster_program.cpp: the transform from frame-id to child-frame-id, i.e. the child's
pose in the parent, translation in m, a unit quaternion; the old positional order x y z yaw pitch roll is
deprecated), the rotation also as roll, pitch, yaw in a comment (REP 103; URDF's R = Rz(yaw) Ry(pitch) Rx(roll)),
and robot_state_publisher with rig_joints.urdf (lrfcal.io.urdf.joints_urdf: the servo's revolute joint and the
scanner's fixed joint at the calibrated DH), which turns the recording's sensor_msgs/JointState into the motor's and
the laser's frames.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from lrfcal.io.urdf import joints_urdf
from lrfcal.model.kinematics import ESTIMATE_NAMES, Pose
from lrfcal.result import CalibrationResult, MarkerEvidence
from lrfcal.types import ServoSource

#: the file names in a calibration's output folder
LAUNCH_NAME = "rig_tf.launch.py"
JOINTS_NAME = "rig_joints.urdf"
#: the frames of the static transform: W and M (the motor frame at servo angle 0)
WORLD_FRAME = "world"
MOTOR_FRAME = "motor_base"


def quaternion_xyzw(mount: Pose) -> tuple[float, float, float, float]:
    """The rotation of ``mount`` as a unit quaternion (qx, qy, qz, qw), ROS's order, with qw >= 0."""
    q = Rotation.from_matrix(mount.matrix()[:3, :3]).as_quat()  # scalar last
    q = -q if q[3] < 0 else q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def _static_tf(mount: Pose, sigma: dict[str, float] | None) -> tuple[str, str]:
    """The header comment (the mount in words: roll, pitch, yaw and the 1-sigmas) and the static_transform_publisher
    node of rig_tf.launch.py."""
    qx, qy, qz, qw = quaternion_xyzw(mount)
    deg = ", ".join(f"{n} {v:.9g} rad ({math.degrees(v):.6g} deg)" for n, v in
                    (("roll", mount.roll), ("pitch", mount.pitch), ("yaw", mount.yaw)))
    sig = "" if not sigma else "\n# 1-sigma: " + ", ".join(
        f"{n} {sigma[n] * 1000:.3g} mm" if n in ("x", "y", "z") else f"{n} {math.degrees(sigma[n]):.3g} deg"
        for n in ESTIMATE_NAMES[:6] if n in sigma and math.isfinite(sigma[n])) + " (rx, ry, rz: a rotation vector in M)"
    comment = (f"# mount T_W_M: x {mount.x:.9g} m, y {mount.y:.9g} m, z {mount.z:.9g} m;\n# {deg}\n"
               f"# R = Rz(yaw) Ry(pitch) Rx(roll) (URDF, REP 103){sig}")
    args = [("--x", mount.x), ("--y", mount.y), ("--z", mount.z),
            ("--qx", qx), ("--qy", qy), ("--qz", qz), ("--qw", qw)]
    arg_lines = "\n".join(f'                "{k}", "{float(v)!r}",' for k, v in args)
    node = f'''        Node(package="tf2_ros", executable="static_transform_publisher", name="lrf_mount_tf",
             arguments=[
{arg_lines}
                "--frame-id", "{WORLD_FRAME}", "--child-frame-id", "{MOTOR_FRAME}",
             ]),
'''
    return comment, node


def mount_launch(mount: Pose | None, sigma: dict[str, float] | None = None, joint_topic: str = "/joint_states") -> str:
    """rig_tf.launch.py (module docstring) for the mount T_W_M (None: not estimated, a targetless calibration: no
    static transform, said in a comment); ``sigma``: name -> 1-sigma (ESTIMATE_NAMES, SI units) for the header
    comment; ``joint_topic``: where robot_state_publisher reads the joint states."""
    if mount is None:
        comment, node = ("# NO mount: a targetless calibration does not estimate it (no world frame); publish "
                         f"{MOTOR_FRAME}'s pose\n# yourself (measured, or from a calibration with markers)."), ""
    else:
        comment, node = _static_tf(mount, sigma)
    return f'''"""ROS 2 launch file written by lrfcal calibrate: the calibrated mount as a static transform and the
servo's joints (rig_joints.urdf, beside this file) by robot_state_publisher.

Frames (REP 103: SI units, right-handed): {WORLD_FRAME} = W, the frame of the marker map (tape distances);
{MOTOR_FRAME} = M, the motor frame at servo angle 0, z along the motor axis. Change "--frame-id" to re-parent the rig
onto your robot (when the markers were measured in its frame).
"""

import os

from launch import LaunchDescription
from launch_ros.actions import Node

{comment}


def generate_launch_description() -> LaunchDescription:
    here = os.path.dirname(os.path.realpath(__file__))
    with open(os.path.join(here, "{JOINTS_NAME}"), encoding="utf-8") as f:
        joints_urdf = f.read()
    return LaunchDescription([
{node}        Node(package="robot_state_publisher", executable="robot_state_publisher", name="lrf_joints",
             parameters=[{{"robot_description": joints_urdf}}],
             remappings=[("joint_states", {joint_topic!r})]),
    ])
'''


def servo_joint(result: CalibrationResult) -> tuple[int, float, tuple[str, ...]]:
    """How the recording's joint position q gives the motor angle, lambda = zero + sign q (lrfcal.types.ServoSource:
    its sign and offset, the direction the calibration chose, result.servo_sign), as rig_joints.urdf's axis sign and
    zero [rad], and the notes its header needs where lambda is not that (a unit other than rad, an estimated motor
    scale, a servo angle not in a JointState)."""
    nominal = result.recording.nominal
    src = nominal.servo or ServoSource(topic=nominal.joint_topic, joint=nominal.joint_name)
    turn = result.servo_sign
    notes = [f"motor angle lambda = {turn * src.offset_rad:.9g} rad + ({turn * src.sign:+d}) q, q the joint's "
             "position (the origin's yaw and the axis' sign)"]
    scale = result.solution.intrinsics.get("motor_scale", (1.0, float("nan")))[0]
    if src.unit != "rad" or not math.isclose(scale, 1.0, rel_tol=0.0, abs_tol=1e-9):
        notes.append(f"CAUTION: lambda is {scale * src.unit_factor():.9g} x the recorded value (unit {src.unit}, motor "
                     "scale): the joint's position must be that many rad")
    if src.joint is None or src.tf is not None:
        notes.append("CAUTION: the recording's servo angle is not a sensor_msgs/JointState joint: publish one for "
                     "robot_state_publisher")
    return (1 if turn * src.sign > 0 else -1), turn * src.offset_rad, tuple(notes)


def ros_files(result: CalibrationResult) -> dict[str, str]:
    """File name -> text of the ROS 2 files of a calibration (module docstring)."""
    nominal = result.recording.nominal
    src = nominal.servo or ServoSource(topic=nominal.joint_topic, joint=nominal.joint_name)
    sign, zero, notes = servo_joint(result)
    sol = result.solution
    sigma = {n: float(s) for n, s in zip(ESTIMATE_NAMES, np.asarray(sol.sigma, dtype=float), strict=True)}
    return {
        LAUNCH_NAME: mount_launch(sol.params.mount if isinstance(result.evidence, MarkerEvidence) else None, sigma,
                                  src.topic or "/joint_states"),
        JOINTS_NAME: joints_urdf(sol.params.dh, joint=src.joint or "servo",
                                 laser_frame=result.recording.scans.frame_id.lstrip("/") or "laser",
                                 axis_sign=sign, zero_rad=zero, notes=notes),
    }


__all__ = ["JOINTS_NAME", "LAUNCH_NAME", "MOTOR_FRAME", "WORLD_FRAME", "mount_launch", "quaternion_xyzw", "ros_files",
           "servo_joint"]
