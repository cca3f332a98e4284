"""Read the scans and the servo angle from the bags real tilting / rotating 2D lidar rigs record.

One entry point, :func:`read_bag`, and one function per bag shape of the servo angle:

* ``_servo_joint_state``: sensor_msgs/JointState, the joint picked by name;
* ``_servo_field``: a numeric field (dotted path) of any message: std_msgs Float64 / Int32 (``data``),
  dynamixel_msgs/JointState (``current_pos``), custom messages;
* ``_servo_in_scan``: the angle travels inside the scan's own (custom) message (``stamp: scan``);
* ``_servo_tf``: the rotation of one frame relative to another in /tf (or a constant from /tf_static).

Messages are decoded with the definitions the bag carries (rosbags' AnyReader registers them from every
connection's message definition, ROS 1 and ROS 2 alike), so custom types need no ROS installation; types a bag
does not define fall back to the ROS 2 Humble store.

LaserScan as drivers really fill it (sensor_msgs/LaserScan definition; urg_node; docs/formats.md): each scan
keeps its own angle_min / angle_increment / beam count / time_increment; empty scans and non-finite or zero
increments are skipped; 0.0, NaN, +-inf and values outside [range_min, range_max] are masked (NaN);
``time_increment`` = 0 is replaced by scan_time / beams-per-revolution (2 pi / |angle_increment|, i.e. the
mirror turns at a constant rate through a full revolution per scan_time) with a printed warning. Everything
skipped, masked or assumed is counted in the :class:`~lrfcal.types.ReadReport`; nothing aborts the recording
except a missing topic or no usable scan or servo sample at all.

MultiEchoLaserScan (urg_node's ``echoes`` topic: per beam a LaserEcho of up to 3 ranges and one of as many
intensities) is read as a LaserScan with one return per beam, chosen by the rig file's ``scan.echo``: among the
beam's valid echoes (finite, non-zero, within [range_min, range_max]) the nearest (``first``), the farthest
(``last``) or the one with the highest intensity (``strongest``, the default; the first of equals); a beam
without a valid echo is NaN.

Clocks: per topic the median of (bag receive time - stamp); their difference is the coarse laser-minus-servo
offset. When it exceeds :data:`COARSE_OFFSET_MIN_S` (different clocks: microcontroller uptime vs wall clock)
the servo stamps are moved onto the laser clock by it; below, the offset is only reported (what remains is the
fine offset: ``--clock-offset`` or the calibration's estimate). Joint-state coverage is not checked here.

Array shapes: S scans, N beams (the largest beam count), J servo samples.
"""

from __future__ import annotations

import math
import sys
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError
from .rig import ScanSource, ServoSource
from .types import JointStates, ReadReport, Scans

LASERSCAN_TYPES = ("sensor_msgs/msg/LaserScan",)
MULTIECHO_TYPE = "sensor_msgs/msg/MultiEchoLaserScan"
JOINTSTATE_TYPE = "sensor_msgs/msg/JointState"
DYNAMIXEL_JOINTSTATE_TYPE = "dynamixel_msgs/msg/JointState"
TF_TYPE = "tf2_msgs/msg/TFMessage"
#: default numeric field per message type
DEFAULT_FIELDS = {DYNAMIXEL_JOINTSTATE_TYPE: "current_pos"}
STD_NUMERIC = ("Float64", "Float32", "Int8", "Int16", "Int32", "Int64", "UInt8", "UInt16", "UInt32", "UInt64")
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


@dataclass
class _Samples:
    """Raw servo samples: header stamps (None when the message has none), receive times, values (J,)."""

    stamps_s: np.ndarray | None
    recv_s: np.ndarray
    values: np.ndarray
    skipped: Counter[str]
    #: stamps already on the laser clock (the scan's own stamps, a constant from /tf_static): no clock offset
    on_laser_clock: bool = False


def one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text or type(err).__name__


def open_reader(path: Path) -> Any:
    """An unopened AnyReader for a ROS 1 .bag file, a ROS 2 bag folder, or a single .mcap/.db3 file."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise InputError(f"{path}: bag not found")
    try:
        return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    except Exception as err:  # rosbags raises several unrelated types for unreadable input
        raise InputError(f"{path}: cannot open bag: {one_line(err)}") from None


def complete_types(reader: Any) -> None:
    """Register types a bag does not define (a ROS 2 bag with definitions for only some connections) from the
    ROS 2 Humble store, so every connection can be decoded."""
    from rosbags.typesys import Stores, get_typestore

    have = reader.typestore.fielddefs
    missing = {c.msgtype for c in reader.connections if c.msgtype not in have}
    if not missing:
        return
    store = get_typestore(Stores.ROS2_HUMBLE)
    add = {k: v for k, v in store.fielddefs.items() if k not in have}
    if add:
        reader.typestore.register(add)


def ns_to_s(t_ns: int) -> float:
    """Integer nanoseconds to seconds, rounded exactly as :func:`stamp_s` rounds sec + nanosec (float64 has
    only ~0.2 us resolution at today's epoch times: both clocks must be converted the same way)."""
    return float(t_ns // 1_000_000_000) + 1e-9 * float(t_ns % 1_000_000_000)


def stamp_s(msg: Any) -> float | None:
    """header.stamp [s] of a ROS 1 / ROS 2 message, None when it has no header."""
    h = getattr(msg, "header", None)
    st = getattr(h, "stamp", None)
    if st is None:
        return None
    return float(st.sec) + 1e-9 * float(st.nanosec)


def get_field(msg: Any, dotted: str, where: str) -> Any:
    """``msg.a.b.c`` for ``dotted = "a.b.c"``; a missing field names the fields that exist."""
    cur = msg
    for part in dotted.split("."):
        if not hasattr(cur, part):
            have = [f for f in getattr(cur, "__dataclass_fields__", {}) if f != "__msgtype__"]
            raise InputError(f"{where}: field {dotted}: no {part!r} in {getattr(cur, '__msgtype__', type(cur))} "
                             f"(fields: {', '.join(have) or 'none'})")
        cur = getattr(cur, part)
    return cur


def _connections(reader: Any, path: Path, topic: str) -> list[Any]:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        have = sorted({c.topic for c in reader.connections})
        raise InputError(f"{path}: topic {topic}: not in bag (topics: {', '.join(have) or 'none'})")
    return conns


def _messages(reader: Any, conns: list[Any], progress: Progress | None, done: int, total: int
              ) -> list[tuple[float, Any]]:
    """(receive time [s], decoded message) of the connections, in bag order."""
    out = []
    for k, (c, t_ns, raw) in enumerate(reader.messages(connections=conns)):
        out.append((ns_to_s(t_ns), reader.deserialize(raw, c.msgtype)))
        if progress is not None and k % 256 == 0:
            progress(done + k, total)
    return out


def read_bag(
    path: str | Path,
    scan: ScanSource | None = None,
    servo: ServoSource | None = None,
    *,
    progress: Progress | None = None,
    warn: Callable[[str], None] | None = None,
) -> BagData:
    """Read the scans and the servo angle of a bag (module docstring).

    Args:
        path: a ROS 1 ``.bag`` file, a ROS 2 bag folder (sqlite3 or MCAP) or a single ``.mcap``/``.db3`` file.
        scan, servo: where the data are (lrfcal.rig; defaults: /scan LaserScan, /joint_states joint ``servo``).
        progress: called as progress(messages_done, messages_total) while reading.
        warn: called once with each assumption the reader makes (default: printed to stderr).
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
    warn = warn or (lambda text: print(f"warning: {text}", file=sys.stderr))
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
            scan_items = _messages(reader, scan_conns, progress, 0, total)
            servo_items = [] if not servo_conns else [
                (t, m, c.topic) for c, (t, m) in _tagged(reader, servo_conns, progress, len(scan_items), total)]
            scan_type = scan_conns[0].msgtype
            servo_type = servo_conns[0].msgtype if servo_conns else scan_type
    except InputError:
        raise
    except Exception as err:
        raise InputError(f"{path}: cannot read bag: {one_line(err)}") from None
    if progress is not None:
        progress(total, total)
    where_scan = f"{path}: {scan.topic}"
    if not scan_items:
        raise InputError(f"{where_scan}: no messages")
    scans, srep, notes = _scans_from(scan_items, scan, scan_type, where_scan, warn)
    where_servo = f"{path}: {servo.describe()}"
    if servo.tf is not None:
        samples = _servo_tf(servo_items, servo, where_servo, scans.stamps_s)
    elif servo.stamp == "scan":
        samples = _servo_in_scan(srep.pop("_kept_items"), servo, where_servo)
    elif servo_type == JOINTSTATE_TYPE:
        samples = _servo_joint_state([(t, m) for t, m, _ in servo_items], servo, where_servo)
    else:
        samples = _servo_field([(t, m) for t, m, _ in servo_items], servo, servo_type, where_servo)
    srep.pop("_kept_items", None)
    joints, servo_stamps, servo_recv, n_used = _joints_from(samples, servo, scans, srep["recv_s"], where_servo)
    scan_med = float(np.median(srep["recv_s"] - scans.stamps_s))
    servo_med = float(np.median(servo_recv - servo_stamps))
    offset = 0.0 if samples.on_laser_clock else servo_med - scan_med
    applied = abs(offset) > COARSE_OFFSET_MIN_S
    if applied:
        joints = JointStates(stamps_s=joints.stamps_s + offset, positions_rad=joints.positions_rad, name=joints.name)
        notes.append(f"clocks: laser and servo stamps {offset:+.3f} s apart (median receive-minus-stamp "
                     f"{scan_med:+.3f} s on {scan.topic}, {servo_med:+.3f} s on the servo); servo stamps moved "
                     f"onto the laser clock by it (coarse, from the bag's receive times)")
    notes.extend(_timing_notes(scans, joints, where_scan, where_servo))
    report = ReadReport(
        bag=str(path), scan_source=_describe_scan(scan), servo_source=servo.describe(),
        n_scan_messages=len(scan_items), n_scans=int(scans.stamps_s.size),
        n_beams=int(np.sum(scans.beam_counts)), n_valid_returns=int(np.isfinite(scans.ranges_m).sum()),
        beam_count_min=int(scans.beam_counts.min()), beam_count_max=int(scans.beam_counts.max()),
        skipped=dict(srep["skipped"]), masked=dict(srep["masked"]),
        n_time_increment_assumed=int(srep["n_assumed"]), assumed_time_increment_s=srep["assumed"],
        n_servo_messages=len(servo_items) if servo_items else len(scan_items), n_servo_samples=n_used,
        servo_skipped=dict(samples.skipped), scan_receive_minus_stamp_s=scan_med,
        servo_receive_minus_stamp_s=servo_med, clock_offset_s=offset, clock_offset_applied=applied,
        notes=tuple(notes),
    )
    if servo.steps():  # step and scan: every beam takes the angle of its scan
        scans = replace(scans, angle_per_scan=True)
    return BagData(scans=scans, joints=joints, report=report)


def _timing_notes(scans: Scans, joints: JointStates, where_scan: str, where_servo: str) -> list[str]:
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


def _tagged(reader: Any, conns: list[Any], progress: Progress | None, done: int, total: int
            ) -> Iterable[tuple[Any, tuple[float, Any]]]:
    for k, (c, t_ns, raw) in enumerate(reader.messages(connections=conns)):
        if progress is not None and k % 256 == 0:
            progress(done + k, total)
        yield c, (ns_to_s(t_ns), reader.deserialize(raw, c.msgtype))


def _describe_scan(scan: ScanSource) -> str:
    return f"{scan.topic}{'.' + scan.field if scan.field else ''} (stamp {scan.stamp})"


def _is_laserscan(obj: Any) -> bool:
    return all(hasattr(obj, f) for f in ("ranges", "angle_min", "angle_increment", "time_increment"))


def _is_multiecho(ls: Any) -> bool:
    """A MultiEchoLaserScan: its ranges are LaserEcho messages (a sequence with ``echoes``)."""
    return len(ls.ranges) > 0 and hasattr(ls.ranges[0], "echoes")


def select_echo(ranges: list[Any], intensities: list[Any], range_min: float, range_max: float, echo: str
                ) -> tuple[np.ndarray, np.ndarray]:
    """One return per beam of a MultiEchoLaserScan (module docstring): ranges (N,) [m] (NaN: no valid echo)
    and intensities (N,) (0 there). ``ranges`` / ``intensities``: the message's LaserEcho lists (intensities
    may be empty or shorter: 0)."""
    n = len(ranges)
    E = max((len(e.echoes) for e in ranges), default=0)
    r = np.full((n, max(E, 1)), np.nan)
    it = np.zeros((n, max(E, 1)))
    for b, e in enumerate(ranges):
        k = len(e.echoes)
        if k:
            r[b, :k] = np.asarray(e.echoes, dtype=np.float64)
            if b < len(intensities):
                v = np.asarray(intensities[b].echoes, dtype=np.float64)[:k]
                it[b, :v.size] = v
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r != 0.0) & (r >= range_min) & (r <= range_max)
    if echo == "first":
        key = np.where(ok, -r, -np.inf)
    elif echo == "last":
        key = np.where(ok, r, -np.inf)
    else:
        key = np.where(ok, np.nan_to_num(it, nan=0.0), -np.inf)
    pick = np.argmax(key, axis=1)
    rows = np.arange(n)
    any_ok = ok.any(axis=1)
    return np.where(any_ok, r[rows, pick], np.nan), np.where(any_ok, it[rows, pick], 0.0)


def _scans_from(items: list[tuple[float, Any]], scan: ScanSource, msgtype: str, where: str,
                warn: Callable[[str], None]) -> tuple[Scans, dict[str, Any], list[str]]:
    """Stack LaserScans (each with its own layout) into Scans; count what is skipped, masked, assumed."""
    skipped: Counter[str] = Counter()
    masked: Counter[str] = Counter()
    rows: list[tuple[float, float, Any, Any]] = []  # (stamp, recv, laserscan, container message)
    for recv, msg in items:
        ls = get_field(msg, scan.field, where) if scan.field else msg
        if not _is_laserscan(ls):
            what = f"field {scan.field}" if scan.field else f"type {msgtype}"
            raise InputError(f"{where}: {what}: not a sensor_msgs/LaserScan (set scan.field to the LaserScan "
                             f"inside the message)")
        t = recv if scan.stamp == "receive" else stamp_s(ls)
        if t is None:
            raise InputError(f"{where}: header: the scan has no header.stamp; use scan.stamp: receive")
        n = len(ls.ranges)
        a0, inc = float(ls.angle_min), float(ls.angle_increment)
        if n == 0:
            skipped["empty"] += 1
        elif not (math.isfinite(inc) and inc != 0.0):
            skipped["bad_angle_increment"] += 1
        elif not math.isfinite(a0):
            skipped["bad_angle_min"] += 1
        elif not math.isfinite(t):
            skipped["bad_stamp"] += 1
        else:
            rows.append((t, recv, ls, msg))
    if not rows:
        raise InputError(f"{where}: no usable scan in {len(items)} messages (skipped: "
                         f"{', '.join(f'{k} {v}' for k, v in sorted(skipped.items()))})")
    order = sorted(range(len(rows)), key=lambda k: rows[k][0])
    rows = [rows[k] for k in order]
    S = len(rows)
    counts = np.array([len(r[2].ranges) for r in rows], dtype=np.int64)
    N = int(counts.max())
    stamps = np.array([r[0] for r in rows])
    recv = np.array([r[1] for r in rows])
    ranges = np.full((S, N), np.nan)
    intens = np.zeros((S, N))
    mu = np.empty((S, N))
    t_inc = np.empty(S)
    scan_time = np.array([float(r[2].scan_time) for r in rows])
    rmin = np.array([float(r[2].range_min) for r in rows])
    rmax = np.array([float(r[2].range_max) for r in rows])
    idx = np.arange(N)
    n_intens_bad = 0
    for k, (_, _, ls, _) in enumerate(rows):
        n = counts[k]
        mu[k] = float(ls.angle_min) + idx * float(ls.angle_increment)
        t_inc[k] = float(ls.time_increment)
        if _is_multiecho(ls):
            ranges[k, :n], intens[k, :n] = select_echo(list(ls.ranges), list(ls.intensities),
                                                       float(ls.range_min), float(ls.range_max), scan.echo)
            continue
        ranges[k, :n] = np.asarray(ls.ranges, dtype=np.float64)
        i = np.asarray(ls.intensities, dtype=np.float64)
        if i.size == n:
            intens[k, :n] = i
        elif i.size:
            n_intens_bad += 1
    # time_increment = 0 (or non-finite): the mirror turns 2 pi per scan_time at a constant rate
    bad_ti = ~np.isfinite(t_inc) | (t_inc == 0.0)
    assumed: float | None = None
    notes: list[str] = []
    if np.any(bad_ti):
        period = np.where(np.isfinite(scan_time) & (scan_time > 0), scan_time, np.nan)
        fallback = float(np.median(np.diff(stamps))) if S > 1 else 0.0
        period = np.where(np.isfinite(period), period, fallback)
        incs = np.array([abs(float(r[2].angle_increment)) for r in rows])
        per_rev = 2.0 * math.pi / incs
        t_inc[bad_ti] = (period / per_rev)[bad_ti]
        assumed = float(np.median(t_inc[bad_ti]))
        text = (f"{where}: time_increment is 0 in {int(bad_ti.sum())} of {S} scans; assumed scan_time / "
                f"beams-per-revolution (2 pi / |angle_increment|) = {assumed:.4g} s per beam (the beams of a "
                f"scan are spread over a constant-rate revolution of scan_time)")
        warn(text)
        notes.append(text)
    if n_intens_bad:
        notes.append(f"{where}: intensities: length differs from ranges in {n_intens_bad} scans; set to 0 there")
    pad = idx[None, :] >= counts[:, None]
    with np.errstate(invalid="ignore"):
        zero = (ranges == 0.0) & ~pad
        nan = np.isnan(ranges) & ~pad
        inf = np.isinf(ranges)
        low = np.isfinite(ranges) & ~zero & (ranges < rmin[:, None])
        high = np.isfinite(ranges) & (ranges > rmax[:, None])
    for name, m in (("zero", zero), ("nan", nan), ("inf", inf), ("below_range_min", low),
                    ("above_range_max", high)):
        c = int(m.sum())
        if c:
            masked[name] = c
    ranges[zero | inf | low | high] = np.nan
    intens[~np.isfinite(intens) | pad] = 0.0
    first = rows[0][2]
    scans = Scans(
        stamps_s=stamps, ranges_m=ranges, intensities=intens, mu_rad=mu, time_increment_s=t_inc,
        scan_time_s=float(np.median(scan_time)),
        range_min_m=float(np.nanmax(rmin)) if np.isfinite(rmin).any() else 0.0,
        range_max_m=float(np.nanmin(rmax)) if np.isfinite(rmax).any() else math.inf,
        frame_id=str(first.header.frame_id) if hasattr(first, "header") else "", source=where,
        beam_counts=counts,
    )
    rep = {"skipped": skipped, "masked": masked, "n_assumed": int(bad_ti.sum()), "assumed": assumed,
           "recv_s": recv, "_kept_items": [(r[0], r[3]) for r in rows]}
    return scans, rep, notes


# --- the servo angle, one function per bag shape ------------------------------------------------------------

def _as_float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _servo_joint_state(items: list[tuple[float, Any]], servo: ServoSource, where: str) -> _Samples:
    """sensor_msgs/JointState: position of the joint named servo.joint (the only joint when not given)."""
    names_seen: set[str] = set()
    stamps, recv, vals = [], [], []
    skipped: Counter[str] = Counter()
    for t, m in items:
        names = list(m.name)
        names_seen.update(names)
        joint = servo.joint
        if joint is None:
            if len(names) != 1:
                raise InputError(f"{where}: joint: not given and the JointState has {len(names)} names "
                                 f"({', '.join(names)}); set servo.joint")
            joint = names[0]
        if joint not in names:
            skipped["joint_absent"] += 1
            continue
        j = names.index(joint)
        if j >= len(m.position):
            skipped["no_position"] += 1
            continue
        stamps.append(stamp_s(m))
        recv.append(t)
        vals.append(float(m.position[j]))
    if not vals:
        raise InputError(f"{where}: name: joint {servo.joint!r} not found (available: "
                         f"{', '.join(sorted(names_seen)) or 'none'})")
    return _Samples(np.array(stamps, dtype=float), np.array(recv), np.array(vals), skipped)


def default_field(msgtype: str) -> str | None:
    """The numeric field that holds the angle in well-known message types (None: unknown)."""
    if msgtype in DEFAULT_FIELDS:
        return DEFAULT_FIELDS[msgtype]
    pkg, _, name = msgtype.rpartition("/")
    if pkg.startswith("std_msgs") and name in STD_NUMERIC:
        return "data"
    return None


def _servo_field(items: list[tuple[float, Any]], servo: ServoSource, msgtype: str, where: str) -> _Samples:
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
    return _Samples(stamps, np.array([t for t, _ in items]), vals, Counter())


def _servo_in_scan(items: list[tuple[float, Any]], servo: ServoSource, where: str) -> _Samples:
    """The angle inside the scan's own message; its stamp is the scan's (items: (scan stamp, message))."""
    assert servo.field is not None
    vals = np.array([_as_float(get_field(m, servo.field, where)) for _, m in items])
    stamps = np.array([t for t, _ in items])
    return _Samples(stamps, stamps.copy(), vals, Counter(), True)


def _servo_tf(items: list[tuple[float, Any, str]], servo: ServoSource, where: str, scan_stamps: np.ndarray
              ) -> _Samples:
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
        return _Samples(np.array([lo, hi]), np.array([lo, hi]), np.array([static[-1]] * 2), Counter(), True)
    if not vals:
        raise InputError(f"{where}: no transform {parent} -> {child} in /tf or /tf_static")
    return _Samples(np.array(stamps, dtype=float), np.array(recv), np.unwrap(np.array(vals)), Counter())


def _joints_from(samples: _Samples, servo: ServoSource, scans: Scans, scan_recv: np.ndarray, where: str
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


__all__ = ["BagData", "COARSE_OFFSET_MIN_S", "MULTIECHO_TYPE", "complete_types", "default_field", "get_field",
           "open_reader", "read_bag", "select_echo", "stamp_s"]
