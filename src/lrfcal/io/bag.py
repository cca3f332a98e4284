"""Read the scans and the servo angle from the bags real tilting / rotating 2D lidar rigs record.

One entry point, :func:`read_bag`. Its parts: opening the bag and reading messages' fields
(lrfcal.io.bag_messages), the LaserScans stacked into Scans (lrfcal.io.bag_scans: what is skipped, masked and
assumed), and one function per bag shape of the servo angle (lrfcal.io.bag_servo: JointState, a numeric field of
any message, the angle inside the scan's message, /tf). Everything skipped, masked or assumed is counted in the
:class:`~lrfcal.types.ReadReport`; nothing aborts the recording except a missing topic or no usable scan or servo
sample at all.

Clocks: per topic the median of (bag receive time - stamp); their difference is the coarse laser-minus-servo
offset. When it exceeds :data:`COARSE_OFFSET_MIN_S` (different clocks: microcontroller uptime vs wall clock)
the servo stamps are moved onto the laser clock by it; below, the offset is only reported (what remains is the
fine offset: ``--clock-offset`` or the calibration's estimate). Joint-state coverage is not checked here.

Array shapes: S scans, N beams (the largest beam count), J servo samples.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.io.bag_arrays import JointArrays, ScanArrays, decode_joints, decode_scans, joints_of
from lrfcal.io.bag_messages import (
    JOINTSTATE_TYPE,
    bulk_kind,
    complete_types,
    decode_message,
    ns_to_s_array,
    one_line,
    open_reader,
)
from lrfcal.io.bag_raw import RawTopic, raw_messages
from lrfcal.io.bag_recover import recovered_notes
from lrfcal.io.bag_scans import laser_arrays, scans_from_arrays
from lrfcal.io.bag_servo import Samples, joints_from, servo_field, servo_in_scan, servo_joint_state, servo_tf
from lrfcal.io.clocksteps import clock_cut
from lrfcal.io.rig import ScanSource, ServoSource
from lrfcal.types import JointStates, ReadReport, Scans

#: a coarse clock offset above this is applied (clocks differ); below it is reported only [s]
COARSE_OFFSET_MIN_S = 1.0

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class BagData:
    """What :func:`read_bag` returns: scans (laser clock), joints (laser clock when the coarse offset was
    applied), and the report."""

    scans: Scans
    joints: JointStates
    report: ReadReport


#: the bag's data where the rig file says they are, from elsewhere than a file: (scan, servo, warn) -> BagData
#: (lrfcal.io.recording.read_recording's ``bag_reader``; a simulation's messages: lrfsim.recording.in_memory_bag)
BagReader = Callable[[ScanSource, ServoSource, "Callable[[str], None] | None"], BagData]


@dataclass(frozen=True)
class Topic:
    """One topic's messages in bag order: receive times ``recv_s`` (M,) [s] and the messages, as objects
    (``messages``, M; with ``topics``, each one's topic, for /tf and /tf_static) or as arrays (``arrays``: LaserScans
    or JointStates, lrfcal.io.bag_arrays), or both."""

    recv_s: NDArray[np.float64]
    messages: list[Any] | None = None
    arrays: ScanArrays | JointArrays | None = None
    topics: list[str] | None = None

    def __len__(self) -> int:
        return int(self.recv_s.size)


def _connections(reader: Any, path: Path, topic: str) -> list[Any]:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        have = sorted({c.topic for c in reader.connections})
        raise InputError(f"{path}: topic {topic}: not in bag (topics: {', '.join(have) or 'none'})")
    return conns


def read_bag(
    path: str | Path,
    scan: ScanSource | None = None,
    servo: ServoSource | None = None,
    *,
    progress: Progress | None = None,
    warn: Callable[[str], None] | None = None,
    bulk: bool = True,
) -> BagData:
    """Read the scans and the servo angle of a bag (module docstring).

    LaserScans and JointStates of the standard definitions are decoded in bulk (lrfcal.io.bag_arrays), every other
    message by rosbags (lrfcal.io.bag_messages.decode_message); the serialised messages are read by
    lrfcal.io.bag_raw. Both give the same arrays, to the bit (tests/test_bulk_bags.py).

    Args:
        path: a ROS 1 ``.bag`` file, a ROS 2 bag folder (sqlite3 or MCAP) or a single ``.mcap``/``.db3`` file.
        scan, servo: where the data are (lrfcal.io.rig; defaults: /scan LaserScan, /joint_states joint ``servo``).
        progress: called as progress(messages_done, messages_total) while reading.
        warn: called once with each assumption the reader makes (default: printed to stderr).
        bulk: False: rosbags reads and decodes every message (the reference the bulk path is tested against).
    Returns:
        BagData: Scans sorted by stamp (S, N); JointStates (J,) lambda [rad] sorted by stamp, duplicate stamps
        averaged; the ReadReport.
    Raises:
        InputError: unreadable bag, missing topic or field, wrong message type, no usable scan, fewer than two
            usable servo samples.
    """
    path = Path(path)
    scan = scan or ScanSource()
    servo = servo or ServoSource(joint="servo")
    reader = open_reader(path)
    try:
        with reader:
            complete_types(reader)
            scan_conns = _connections(reader, path, scan.topic)
            servo_conns: list[Any] = []
            if servo.tf is not None:
                servo_conns = [c for c in reader.connections if c.topic in ("/tf", "/tf_static")]
                if not servo_conns:
                    raise InputError(f"{path}: servo.tf: no /tf or /tf_static topic in bag")
            elif servo.stamp != "scan":
                if servo.topic is None:
                    raise InputError(f"{path}: servo.topic: missing (or use servo.tf / stamp: scan)")
                servo_conns = _connections(reader, path, servo.topic)
            total = sum(c.msgcount for c in scan_conns + servo_conns)
            if progress is not None:
                progress(0, total)
            raw = raw_messages(reader, [scan_conns, servo_conns], fast=bulk,
                               progress=None if progress is None else lambda k: progress(k, total))
            scan_type = scan_conns[0].msgtype
            servo_type = servo_conns[0].msgtype if servo_conns else scan_type
            scans = _topic(reader, scan_conns, raw[0], bulk and scan.field is None and servo.stamp != "scan")
            servo_topic = _topic(reader, servo_conns, raw[1], bulk and servo.tf is None) if servo_conns else \
                Topic(np.zeros(0))
            recovered = recovered_notes(reader)
    except InputError:
        raise
    except Exception as err:
        raise InputError(f"{path}: cannot read bag: {one_line(err)}") from None
    if progress is not None:
        progress(total, total)
    for line in recovered:
        (warn or (lambda text: print(f"warning: {text}", file=sys.stderr)))(line)
    data = bag_data(str(path), scans, servo_topic, scan_type, servo_type, scan, servo, warn)
    if not recovered:
        return data
    return replace(data, report=replace(data.report, left_out=(*recovered, *data.report.left_out)))


def read_topic(path: str | Path, topic: str, *, bulk: bool = True) -> Topic:
    """All messages of one topic of a bag, as :func:`read_bag` decodes them (``bulk``: LaserScans and JointStates
    as arrays) or as rosbags decodes every message (``bulk`` False): what tests and benchmarks compare.

    Raises:
        InputError: unreadable bag, missing topic.
    """
    path = Path(path)
    reader = open_reader(path)
    try:
        with reader:
            complete_types(reader)
            conns = _connections(reader, path, topic)
            return _topic(reader, conns, raw_messages(reader, [conns], fast=bulk)[0], bulk)
    except InputError:
        raise
    except Exception as err:
        raise InputError(f"{path}: cannot read bag: {one_line(err)}") from None


def _topic(reader: Any, conns: list[Any], raw: RawTopic, bulk: bool) -> Topic:
    """The messages ``raw`` of connections ``conns``: LaserScans and JointStates of the standard definitions as
    arrays when ``bulk``, everything else as objects."""
    recv = ns_to_s_array(raw.times_ns)
    types = {c.msgtype for c in conns}
    msgtype = next(iter(types))
    kind = bulk_kind(reader, msgtype) if bulk and len(types) == 1 and len(raw) else None
    if kind is not None:
        decode = decode_scans if kind == "scan" else decode_joints
        return Topic(recv, arrays=decode(raw, reader.is2, lambda i: decode_message(reader, bytes(raw.message(i)),
                                                                                    msgtype)))
    if len(types) == 1:
        return Topic(recv, [decode_message(reader, bytes(raw.message(i)), msgtype) for i in range(len(raw))],
                     topics=[conns[0].topic] * len(raw))
    items = [(c.topic, decode_message(reader, r, c.msgtype)) for c, _, r in reader.messages(connections=conns)]
    return Topic(recv, [m for _, m in items], topics=[t for t, _ in items])


def bag_data(label: str, scan_topic: Topic, servo_topic: Topic, scan_type: str, servo_type: str, scan: ScanSource,
             servo: ServoSource, warn: Callable[[str], None] | None = None) -> BagData:
    """What :func:`read_bag` makes of a bag's messages: those of the scan topic and of the servo's (empty when the
    angle travels in the scan's message); ``label`` names the bag in messages. A simulation's messages, never
    serialised, give what its bag file would (lrfsim.recording.in_memory_bag). ``warn``: as in :func:`read_bag`."""
    warn = warn or (lambda text: print(f"warning: {text}", file=sys.stderr))
    where_scan = f"{label}: {scan.topic}"
    if not len(scan_topic):
        raise InputError(f"{where_scan}: no messages")
    arrays = scan_topic.arrays
    if not isinstance(arrays, ScanArrays):
        assert scan_topic.messages is not None
        arrays = laser_arrays(scan_topic.messages, scan, scan_type, where_scan)
    scans, srep, notes = scans_from_arrays(arrays, scan_topic.recv_s, scan, where_scan, warn)
    where_servo = f"{label}: {servo.describe()}"
    servo_items = [] if servo_topic.messages is None else list(zip(servo_topic.recv_s.tolist(), servo_topic.messages,
                                                                   strict=True))
    if servo.tf is not None:
        samples = servo_tf([(t, m, c) for (t, m), c in zip(servo_items, servo_topic.topics or [], strict=True)],
                           servo, where_servo, scans.stamps_s)
    elif servo.stamp == "scan":
        assert scan_topic.messages is not None
        kept = zip(scans.stamps_s.tolist(), srep["_kept_rows"].tolist(), strict=True)
        samples = servo_in_scan([(t, scan_topic.messages[k]) for t, k in kept], servo, where_servo)
    elif servo_type == JOINTSTATE_TYPE:
        joints_arrays = servo_topic.arrays
        if not isinstance(joints_arrays, JointArrays):
            joints_arrays = joints_of(servo_topic.messages or [])
        samples = servo_joint_state(joints_arrays, servo_topic.recv_s, servo, where_servo)
    else:
        samples = servo_field(servo_items, servo, servo_type, where_servo)
    srep.pop("_kept_rows", None)
    scans, samples, left_out = _one_clock(scans, srep, samples, scan, servo, where_scan, where_servo)
    for line in left_out:
        warn(line)
    joints, servo_stamps, servo_recv, n_used = joints_from(samples, servo, scans, srep["recv_s"], where_servo)
    scan_med = float(np.median(srep["recv_s"] - scans.stamps_s))
    servo_med = float(np.median(servo_recv - servo_stamps))
    offset = 0.0 if samples.on_laser_clock else servo_med - scan_med
    applied = abs(offset) > COARSE_OFFSET_MIN_S
    if applied:
        joints = JointStates(stamps_s=joints.stamps_s + offset, positions_rad=joints.positions_rad, name=joints.name)
        notes.append(f"clocks: laser and servo stamps {offset:+.3f} s apart (median receive-minus-stamp "
                     f"{scan_med:+.3f} s on {scan.topic}, {servo_med:+.3f} s on the servo); servo stamps moved "
                     f"onto the laser clock by it (coarse, from the bag's receive times)")
    notes.extend(timing_notes(scans, joints, where_scan, where_servo))
    report = ReadReport(
        bag=label, scan_source=_describe_scan(scan), servo_source=servo.describe(),
        n_scan_messages=len(scan_topic), n_scans=int(scans.stamps_s.size),
        n_beams=int(np.sum(scans.beam_counts)), n_valid_returns=int(np.isfinite(scans.ranges_m).sum()),
        beam_count_min=int(scans.beam_counts.min()), beam_count_max=int(scans.beam_counts.max()),
        skipped=dict(srep["skipped"]), masked=dict(srep["masked"]),
        n_time_increment_assumed=int(srep["n_assumed"]), assumed_time_increment_s=srep["assumed"],
        n_servo_messages=len(servo_topic) if len(servo_topic) else len(scan_topic), n_servo_samples=n_used,
        servo_skipped=dict(samples.skipped), scan_receive_minus_stamp_s=scan_med,
        servo_receive_minus_stamp_s=servo_med, clock_offset_s=offset, clock_offset_applied=applied,
        notes=tuple(notes), left_out=left_out,
    )
    if servo.steps():  # step and scan: every beam takes the angle of its scan
        scans = replace(scans, angle_per_scan=True)
    return BagData(scans=scans, joints=joints, report=report)


def _one_clock(scans: Scans, srep: dict[str, Any], samples: Samples, scan: ScanSource, servo: ServoSource,
               where_scan: str, where_servo: str) -> tuple[Scans, Samples, tuple[str, ...]]:
    """The scans and servo samples that share one laser-minus-servo clock offset (lrfcal.io.clocksteps.clock_cut:
    a clock step's shorter side left out, named), ``srep["recv_s"]`` cut alike. Nothing to cut where the servo's
    angle has no clock of its own (its stamps the scans' or the receive times).

    Raises:
        CalibrationError: too little of the recording has one clock offset."""
    if samples.on_laser_clock or (servo.stamp == "receive" and scan.stamp == "receive"):
        return scans, samples, ()
    servo_stamps = samples.recv_s if servo.stamp == "receive" else samples.stamps_s
    if servo_stamps is None:
        return scans, samples, ()
    ok = np.isfinite(servo_stamps) & np.isfinite(samples.values)
    cut = clock_cut(srep["recv_s"], scans.stamps_s, samples.recv_s[ok], servo_stamps[ok], where_scan, where_servo)
    if cut.keep_scans.all() and cut.keep_servo.all():
        return scans, samples, cut.notes
    keep_servo = np.zeros(ok.size, dtype=bool)
    keep_servo[np.flatnonzero(ok)[cut.keep_servo]] = True
    keep_servo |= ~ok  # the non-finite ones are counted where they are dropped
    scans = scans.subset(cut.keep_scans)
    srep["recv_s"] = srep["recv_s"][cut.keep_scans]
    stamps = None if samples.stamps_s is None else samples.stamps_s[keep_servo]
    samples = replace(samples, stamps_s=stamps, recv_s=samples.recv_s[keep_servo],
                      values=samples.values[keep_servo])
    return scans, samples, cut.notes


def timing_notes(scans: Scans, joints: JointStates, where_scan: str, where_servo: str) -> list[str]:
    """Timing problems worth naming: scan_time disagreeing with the stamps' period, irregular servo samples,
    servo samples sparser than the scans."""
    out = []
    if scans.stamps_s.size > 2:
        period = float(np.median(np.diff(scans.stamps_s)))
        if scans.scan_time_s > 0 and abs(period - scans.scan_time_s) > 0.2 * scans.scan_time_s:
            out.append(f"{where_scan}: scan_time {scans.scan_time_s:.4g} s but the stamps are {period:.4g} s apart "
                       f"(median): the driver's scan_time (and a time_increment derived from it) is doubtful")
    dt = np.diff(joints.stamps_s)
    if dt.size > 2:
        med = float(np.median(dt))
        spread = float(np.percentile(dt, 90) - np.percentile(dt, 10))
        if med > 0 and spread > 0.5 * med:
            out.append(f"{where_servo}: irregular servo samples: intervals {np.percentile(dt, 10):.4g}-"
                       f"{np.percentile(dt, 90):.4g} s (10-90 %), median {med:.4g} s")
        if scans.stamps_s.size > 2 and med > float(np.median(np.diff(scans.stamps_s))):
            out.append(f"{where_servo}: fewer servo samples ({1 / med:.3g} Hz) than scans "
                       f"({1 / float(np.median(np.diff(scans.stamps_s))):.3g} Hz): the angle within a scan is "
                       f"interpolated over more than a scan period")
    return out


def _describe_scan(scan: ScanSource) -> str:
    return f"{scan.topic}{'.' + scan.field if scan.field else ''} (stamp {scan.stamp})"


__all__ = ["COARSE_OFFSET_MIN_S", "BagData", "BagReader", "Progress", "Topic", "bag_data", "read_bag", "read_topic",
           "timing_notes"]
