"""The servo angle of a bag, one function per bag shape (docs/formats.md "Reading real bags"):

* :func:`servo_joint_state`: sensor_msgs/JointState, the joint picked by name;
* :func:`servo_field`: a numeric field (dotted path) of any message: std_msgs Float64 / Int32 (``data``),
  dynamixel_msgs/JointState (``current_pos``), custom messages;
* :func:`servo_in_scan`: the angle travels inside the scan's own (custom) message (``stamp: scan``);
* :func:`servo_tf`: the rotation of one frame relative to another in /tf (or a constant from /tf_static).

Each gives raw :class:`Samples`; :func:`joints_from` turns them into the motor angle lambda (unit, sign, offset,
the stamp choice). Array shapes: J servo samples.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.io.bag_arrays import JointArrays
from lrfcal.io.bag_messages import DYNAMIXEL_JOINTSTATE_TYPE, get_field, stamp_s
from lrfcal.io.rig import ServoSource
from lrfcal.types import JointStates, Scans

#: default numeric field per message type
DEFAULT_FIELDS = {DYNAMIXEL_JOINTSTATE_TYPE: "current_pos"}
STD_NUMERIC = ("Float64", "Float32", "Int8", "Int16", "Int32", "Int64", "UInt8", "UInt16", "UInt32", "UInt64")


@dataclass
class Samples:
    """Raw servo samples: header stamps (None when the message has none), receive times, values (J,)."""

    stamps_s: np.ndarray | None
    recv_s: np.ndarray
    values: np.ndarray
    skipped: Counter[str]
    #: stamps already on the laser clock (the scan's own stamps, a constant from /tf_static): no clock offset
    on_laser_clock: bool = False


def _as_float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def servo_joint_state(joints: JointArrays, recv_s: NDArray[np.float64], servo: ServoSource, where: str) -> Samples:
    """sensor_msgs/JointState (``joints``, received at ``recv_s`` (M,) [s]): position of the joint named servo.joint
    (the only joint when not given)."""
    kinds = list(dict.fromkeys(joints.names))  # the distinct name lists, in order of appearance
    if servo.joint is None:
        several = next((names for names in kinds if len(names) != 1), None)
        if several is not None:
            raise InputError(f"{where}: joint: not given and the JointState has {len(several)} names "
                             f"({', '.join(several)}); set servo.joint")
    column = {names: (names.index(servo.joint) if servo.joint in names else -1) if servo.joint else 0
              for names in kinds}
    j = np.array([column[names] for names in joints.names], dtype=np.int64)
    absent = j < 0
    no_position = ~absent & (j >= joints.position_counts)
    skipped: Counter[str] = Counter({k: int(v.sum()) for k, v in (("joint_absent", absent),
                                                                   ("no_position", no_position)) if v.any()})
    rows = np.flatnonzero(~absent & ~no_position)
    if not rows.size:
        seen = sorted({n for names in kinds for n in names})
        raise InputError(f"{where}: name: joint {servo.joint!r} not found (available: {', '.join(seen) or 'none'})")
    return Samples(joints.stamps_s()[rows], recv_s[rows], joints.positions[rows, j[rows]], skipped)


def default_field(msgtype: str) -> str | None:
    """The numeric field that holds the angle in well-known message types (None: unknown)."""
    if msgtype in DEFAULT_FIELDS:
        return DEFAULT_FIELDS[msgtype]
    pkg, _, name = msgtype.rpartition("/")
    if pkg.startswith("std_msgs") and name in STD_NUMERIC:
        return "data"
    return None


def servo_field(items: list[tuple[float, Any]], servo: ServoSource, msgtype: str, where: str) -> Samples:
    """A numeric field of any message (std_msgs Float64/Int32: data; dynamixel_msgs/JointState: current_pos)."""
    fld = servo.field or default_field(msgtype)
    if fld is None:
        raise InputError(f"{where}: field: {msgtype} is not a known servo message; set servo.field to the "
                         f"angle's dotted path")
    has_header = stamp_s(items[0][1]) is not None if items else False
    if servo.stamp == "header" and not has_header:
        raise InputError(f"{where}: stamp: {msgtype} has no header; set servo.stamp: receive")
    vals = np.array([_as_float(get_field(m, fld, where)) for _, m in items])
    stamps = np.array([stamp_s(m) for _, m in items], dtype=float) if has_header else None
    return Samples(stamps, np.array([t for t, _ in items]), vals, Counter())


def servo_in_scan(items: list[tuple[float, Any]], servo: ServoSource, where: str) -> Samples:
    """The angle inside the scan's own message; its stamp is the scan's (items: (scan stamp, message))."""
    assert servo.field is not None
    vals = np.array([_as_float(get_field(m, servo.field, where)) for _, m in items])
    stamps = np.array([t for t, _ in items])
    return Samples(stamps, stamps.copy(), vals, Counter(), True)


def servo_tf(items: list[tuple[float, Any, str]], servo: ServoSource, where: str, scan_stamps: np.ndarray
             ) -> Samples:
    """The rotation of tf.child relative to tf.parent about tf.axis (angle = 2 atan2(q_axis, q_w)); a pair
    only in /tf_static gives a constant angle over the scans."""
    assert servo.tf is not None
    parent, child, axis = servo.tf.parent, servo.tf.child, servo.tf.axis
    stamps, recv, vals, static = [], [], [], []
    for t, m, topic in items:
        for tr in m.transforms:
            if tr.header.frame_id.lstrip("/") != parent.lstrip("/") or \
                    tr.child_frame_id.lstrip("/") != child.lstrip("/"):
                continue
            q = tr.transform.rotation
            ang = 2.0 * math.atan2(float(getattr(q, axis)), float(q.w))
            if topic == "/tf_static":
                static.append(ang)
            else:
                stamps.append(stamp_s(tr))
                recv.append(t)
                vals.append(ang)
    if not vals and static:
        lo, hi = float(scan_stamps.min()) - 1.0, float(scan_stamps.max()) + 1.0
        return Samples(np.array([lo, hi]), np.array([lo, hi]), np.array([static[-1]] * 2), Counter(), True)
    if not vals:
        raise InputError(f"{where}: no transform {parent} -> {child} in /tf or /tf_static")
    return Samples(np.array(stamps, dtype=float), np.array(recv), np.unwrap(np.array(vals)), Counter())


def joints_from(samples: Samples, servo: ServoSource, scans: Scans, scan_recv: np.ndarray, where: str
                ) -> tuple[JointStates, np.ndarray, np.ndarray, int]:
    """Apply unit, sign, offset and the stamp choice; drop non-finite values; sort; average equal stamps.

    Returns the JointStates, the chosen stamps and receive times of the used samples (for the clock estimate)
    and the number of samples used."""
    if servo.stamp == "receive":
        stamps = samples.recv_s
    else:
        if samples.stamps_s is None:
            raise InputError(f"{where}: stamp: the servo messages have no header; set servo.stamp: receive")
        stamps = samples.stamps_s
    lam = servo.sign * samples.values * servo.unit_factor() + servo.offset_rad
    ok = np.isfinite(lam) & np.isfinite(stamps)
    if np.any(~ok):
        samples.skipped["non_finite"] += int((~ok).sum())
    t, q, r = stamps[ok], lam[ok], samples.recv_s[ok]
    order = np.argsort(t, kind="stable")
    t, q, r = t[order], q[order], r[order]
    ut, inv = np.unique(t, return_inverse=True)
    if ut.size != t.size:  # duplicate stamps: average their angles
        samples.skipped["duplicate_stamp_averaged"] += int(t.size - ut.size)
        q = np.bincount(inv, weights=q) / np.bincount(inv)
        t = ut
    if t.size < 2:
        raise InputError(f"{where}: only {t.size} usable servo sample(s); need at least 2 to interpolate")
    name = servo.joint or (servo.tf.child if servo.tf else (servo.field or "servo"))
    return JointStates(stamps_s=t, positions_rad=q, name=name), stamps[ok], samples.recv_s[ok], int(ok.sum())


__all__ = ["DEFAULT_FIELDS", "Samples", "default_field", "joints_from", "servo_field", "servo_in_scan",
           "servo_joint_state", "servo_tf"]
