"""``lrfcal convert LOG -o BAG``: a scan log (lrfcal.io.scanlog) as a ROS 2 bag (MCAP, as lrfsim writes its bags):
one sensor_msgs/msg/LaserScan per row on /scan and one sensor_msgs/msg/JointState per row on /joint_states.

What is written is what the log says, so that lrfcal.io.bag.read_bag reads the bag back to the scans and angles
lrfcal.io.scanlog.read_scan_log reads from the log:

* LaserScan: header.stamp = the row's time, frame_id ``laser``; angle_min / angle_increment / angle_max of the
  beams (a header row's angles must lie on a grid within GRID_TOLERANCE_RAD: a LaserScan has nothing else);
  time_increment = the rig file's log.time_increment_s, else 0 (the reader then assumes scan_time / beams per
  revolution, as the log reader does); scan_time = the rows' median spacing; range_min / range_max = the rig
  file's (0 and +inf when absent); ranges [m] as logged (0, error codes and NaN kept: the reader masks and counts
  them), intensities when the log has them.
* JointState: name ``servo``, position = lambda [rad] = sign * angle * unit + offset_rad, stamped with the row's
  time; rows with a non-finite time or angle are left out (and counted).
* Messages are logged at their stamps (which must not be negative); the bag folder is written beside and renamed
  into place. The rig file that reads it (``servo: {joint: servo, motion: step}`` for a step-and-scan log) is
  returned with the summary.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lrfcal.commands.inspect_log import guess_layout
from lrfcal.errors import InputError
from lrfcal.io.files import check_outputs, swapped_folder
from lrfcal.io.rig import load_rig
from lrfcal.io.scanlog import beam_time_increment_s, is_scan_log, load_log, log_servo, scan_period_s
from lrfcal.types import LogLayout, ServoSource

LASERSCAN_TYPE = "sensor_msgs/msg/LaserScan"
JOINTSTATE_TYPE = "sensor_msgs/msg/JointState"
SCAN_TOPIC, JOINT_TOPIC, JOINT_NAME, LASER_FRAME = "/scan", "/joint_states", "servo", "laser"
#: a header row's beam angles must lie this close to an even grid to become a LaserScan [rad]
GRID_TOLERANCE_RAD = 1e-5


def _ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


def log_layout(log: Path, nominal: Path | None) -> tuple[LogLayout, ServoSource, list[str]]:
    """The layout and servo keys from the rig file, else guessed (lrfcal.commands.inspect_log.guess_layout); notes say
    which. Raises InputError: no log: section in the rig file, or a layout that cannot be guessed."""
    if nominal is not None:
        rig = load_rig(nominal)
        if rig.log is None:
            raise InputError(f"{nominal}: log: missing: the rig file must describe the scan log (docs/formats.md "
                             f"\"Scan logs\"; `lrfcal inspect {log}` proposes it)")
        return rig.log, log_servo(rig.servo_source()), [f"layout from {nominal}"]
    g = guess_layout(log)
    if g.layout is None:
        raise InputError(f"{log}: layout not guessable ({'; '.join(g.problems)}); describe it in a rig file's log: "
                         f"section and give --nominal")
    return g.layout, ServoSource(topic=None, unit=g.servo["unit"], motion="step"), [
        "layout guessed (as lrfcal inspect does): " + "; ".join(g.notes)]


def convert_log(log: str | Path, out: str | Path, *, nominal: str | Path | None = None, overwrite: bool = False,
                warn: Callable[[str], None] | None = None) -> list[str]:
    """Write the ROS 2 bag of a scan log (module docstring); returns summary lines, the last ones the rig file
    (YAML) that reads the bag.

    Raises:
        InputError: not a scan log, a bad log, an output that overlaps the input or exists (without
            ``overwrite``, or is not a bag folder), a header whose angles are off a grid, negative times.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    log, out = Path(log), Path(out)
    nom = Path(nominal) if nominal is not None else None
    if not is_scan_log(log):
        raise InputError(f"{log}: not a scan log (a .txt, .csv or .log file; docs/formats.md \"Scan logs\")")
    check_outputs([p for p in (log, nom) if p is not None], [out])
    if out.exists():
        if not overwrite:
            raise InputError(f"{out}: exists; choose another path or pass --overwrite to replace it")
        if not (out.is_dir() and (out / "metadata.yaml").is_file()):
            raise InputError(f"{out}: exists and is not a ROS 2 bag folder (no metadata.yaml): not replaced, even "
                             f"with --overwrite")
    layout, servo, lines = log_layout(log, nom)
    rows = load_log(log, layout)
    a0, inc, dev = rows.evenly_spaced()
    if dev > GRID_TOLERANCE_RAD:
        raise InputError(f"{log}:{rows.header_line}: the header's beam angles are up to {math.degrees(dev):.4g} deg "
                         f"off an even grid; a LaserScan has angle_min + i * angle_increment only, so it cannot be "
                         f"converted (lrfcal reads the log itself)")
    t = rows.times_s
    if np.any(t[np.isfinite(t)] < 0):
        k = int(np.flatnonzero(np.isfinite(t) & (t < 0))[0])
        raise InputError(f"{log}:{rows.lines[k]}: time {t[k]:g} s is negative; a bag's times cannot be (shift the "
                         f"log's clock)")
    ti, assumed = beam_time_increment_s(rows, layout)
    lam = servo.sign * rows.angles * servo.unit_factor() + servo.offset_rad
    ts = get_typestore(Stores.ROS2_HUMBLE)
    LaserScan, JointState = ts.types[LASERSCAN_TYPE], ts.types[JOINTSTATE_TYPE]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    rmax = layout.range_max_m if layout.range_max_m is not None else math.inf
    n = rows.mu_rad.size
    period = scan_period_s(t)
    empty = np.zeros(0, dtype=np.float64)
    ok_scan = np.isfinite(t)
    ok_joint = ok_scan & np.isfinite(lam)
    events = sorted([(_ns(float(t[k])), 0, int(k)) for k in np.flatnonzero(ok_scan)]
                    + [(_ns(float(t[k])), 1, int(k)) for k in np.flatnonzero(ok_joint)])

    def header(ns: int, frame: str) -> Any:
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    # rosbags' Writer makes the bag folder and names its data file after it: swapped_folder names it out's name
    with swapped_folder(out, make=False) as tmp, Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c_scan = w.add_connection(SCAN_TOPIC, LASERSCAN_TYPE, typestore=ts)
        c_joint = w.add_connection(JOINT_TOPIC, JOINTSTATE_TYPE, typestore=ts)
        for ns, kind, k in events:
            if kind == 0:
                msg = LaserScan(header=header(ns, LASER_FRAME), angle_min=a0, angle_max=a0 + (n - 1) * inc,
                                angle_increment=inc, time_increment=0.0 if assumed else ti, scan_time=period,
                                range_min=layout.range_min_m, range_max=rmax,
                                ranges=rows.ranges_m[k].astype(np.float32),
                                intensities=(rows.intensities[k].astype(np.float32) if layout.intensities
                                             else np.zeros(0, dtype=np.float32)))
                w.write(c_scan, ns, ts.serialize_cdr(msg, LASERSCAN_TYPE))
            else:
                msg = JointState(header=header(ns, ""), name=[JOINT_NAME], position=np.array([lam[k]]),
                                 velocity=empty, effort=empty)
                w.write(c_joint, ns, ts.serialize_cdr(msg, JOINTSTATE_TYPE))
    n_scan, n_joint = int(ok_scan.sum()), int(ok_joint.sum())
    lines.append(f"read {rows.times_s.size} rows of {n} beams from {log}"
                 + (f"; {rows.times_s.size - n_scan} rows without a finite time left out" if n_scan < t.size else "")
                 + (f"; {n_scan - n_joint} angles not finite, left out of /joint_states" if n_joint < n_scan else ""))
    if assumed and warn is not None:
        warn(f"{log}: log.time_increment_s not given: the LaserScans carry time_increment 0 and scan_time "
             f"{period:.4g} s, from which readers assume {ti:.4g} s per beam")
    lines.append(f"wrote {out} ({n_scan} {LASERSCAN_TYPE} on {SCAN_TOPIC}, {n_joint} {JOINTSTATE_TYPE} on "
                 f"{JOINT_TOPIC}, joint {JOINT_NAME}, lambda [rad])")
    rig: dict[str, Any] = {"dh": load_rig(nom).dh.model_dump()} if nom is not None else {}
    rig["servo"] = {"topic": JOINT_TOPIC, "joint": JOINT_NAME, "motion": servo.motion}
    lines.append("rig file (nominal.yaml) that reads the bag" + ("" if nom is not None else " (add dh)") + ":")
    lines.extend(yaml.safe_dump(rig, sort_keys=False, default_flow_style=None).splitlines())
    return lines


__all__ = ["GRID_TOLERANCE_RAD", "convert_log", "log_layout"]
