"""``lrfcal inspect BAG``: what a bag holds and how to read it (pure function; the CLI prints the result).

Topics with their types, counts, rates and clocks; the scan geometry as the driver filled it; the servo angle's
range and rate; the clock offset between laser and servo; the problems found (everything the reader skipped,
masked or assumed, plus coverage); and the rig-file snippet (YAML) that reads this bag. Where the rig file or
the options do not say where the data are, the source is guessed (a LaserScan topic or a message holding one;
a JointState, dynamixel JointState, std_msgs number, a number beside the scan, or /tf) and marked as guessed.

Echo choice: where a bag has a MultiEchoLaserScan topic (urg_node's ``echoes`` with ``publish_multiecho``) beside
LaserScan topics, the guess is the MultiEchoLaserScan with ``echo: strongest``, and a note says why: where a
beam's footprint straddles a marker's edge it splits into a marker echo and a wall echo, and the strongest echo
keeps the marker's return, while a LaserScan holds one return per beam fixed by the driver (the simulator's
/scan: the power-weighted mixture of the two, a range between marker and wall; docs/sensor_errors.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lrfcal.errors import InputError
from lrfcal.io.bag import BagData, read_bag
from lrfcal.io.bag_messages import (
    DYNAMIXEL_JOINTSTATE_TYPE,
    JOINTSTATE_TYPE,
    MULTIECHO_TYPE,
    TF_TYPE,
    complete_types,
    decode_message,
    get_field,
    ns_to_s,
    one_line,
    open_reader,
    stamp_s,
)
from lrfcal.io.bag_scans import is_laserscan, is_multiecho
from lrfcal.io.bag_servo import default_field
from lrfcal.io.multiecho import Echoes
from lrfcal.io.recording import check_units
from lrfcal.io.rig import rig_snippet
from lrfcal.model.kinematics import is_placeholder_dh
from lrfcal.stages.timing import covered_scans
from lrfcal.types import ReadReport, ScanSource, ServoSource, TfSource
from lrfcal.types.sources import ServoStamp, Unit

if TYPE_CHECKING:
    from lrfcal.stages.propose import DHProposal

#: messages decoded per topic for the statistics (receive times come from all messages)
MAX_DECODED = 5000
_SERVO_HINTS = ("servo", "tilt", "angle", "joint", "pan", "motor", "dynamixel")


@dataclass(frozen=True)
class TopicInfo:
    """One topic: type, message count, mean rate [Hz] from receive times, whether it has a header and
    median(receive - header.stamp) [s] (None without header)."""

    topic: str
    msgtype: str
    count: int
    rate_hz: float | None
    has_header: bool
    receive_minus_stamp_s: float | None


@dataclass(frozen=True)
class ScanGeometry:
    """The scans as the driver filled them (over all messages, including the ones the reader skips)."""

    n_messages: int
    beam_count: tuple[int, int]
    angle_min_rad: tuple[float, float]
    angle_max_rad: tuple[float, float]
    angle_increment_rad: tuple[float, float]
    time_increment_s: tuple[float, float]
    scan_time_s: tuple[float, float]
    range_min_m: float
    range_max_m: float
    has_intensities: bool


@dataclass(frozen=True)
class ServoInfo:
    """The servo angle as read: samples, range [rad], sample rate [Hz], median |speed| [rad/s]."""

    n_samples: int
    min_rad: float
    max_rad: float
    rate_hz: float | None
    median_speed_rad_s: float


@dataclass(frozen=True)
class BagInspection:
    """What :func:`inspect_bag` found."""

    path: Path
    ros_version: int
    duration_s: float
    topics: tuple[TopicInfo, ...]
    scan_source: ScanSource | None
    servo_source: ServoSource | None
    guessed: tuple[str, ...]
    geometry: ScanGeometry | None
    servo: ServoInfo | None
    report: ReadReport | None
    n_scans_covered: int | None
    problems: tuple[str, ...]
    rig_snippet: str
    dh: dict[str, float] = field(default_factory=dict)
    #: why a source was chosen (e.g. the MultiEchoLaserScan topic with its strongest echo over a LaserScan)
    notes: tuple[str, ...] = ()
    #: the DH proposed from the scene's planes (lrfcal.stages.propose; None: not searched, the dh were given or skipped)
    proposal: DHProposal | None = None


def _rate(times: list[float]) -> float | None:
    if len(times) < 2 or times[-1] <= times[0]:
        return None
    return (len(times) - 1) / (times[-1] - times[0])


def _numeric_fields(msg: Any, prefix: str = "", depth: int = 0) -> list[tuple[str, float]]:
    """(dotted path, value) of the scalar numeric fields of a message (not inside a LaserScan or header)."""
    out: list[tuple[str, float]] = []
    for name in getattr(msg, "__dataclass_fields__", {}):
        if name in ("__msgtype__", "header"):
            continue
        v = getattr(msg, name)
        path = f"{prefix}{name}"
        if isinstance(v, bool):
            continue
        if isinstance(v, (int, float)):
            out.append((path, float(v)))
        elif hasattr(v, "__dataclass_fields__") and not is_laserscan(v) and depth < 3:
            out.extend(_numeric_fields(v, path + ".", depth + 1))
    return out


def _laserscan_field(msg: Any) -> str | None:
    for name in getattr(msg, "__dataclass_fields__", {}):
        if name != "__msgtype__" and is_laserscan(getattr(msg, name)):
            return name
    return None


def guess_unit(values: np.ndarray) -> tuple[Unit, float | None]:
    """rad / deg / counts (+ a counts_per_rev guess) from the recorded values' range."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return "rad", None
    lo, hi = float(v.min()), float(v.max())
    integer = bool(np.all(v == np.round(v)))
    if max(abs(lo), abs(hi)) <= 2 * math.pi + 0.5 and not (integer and hi - lo > 3):
        return "rad", None
    if max(abs(lo), abs(hi)) <= 360.0:
        return "deg", None
    return "counts", 4096.0 if hi <= 4096 else 2.0 ** math.ceil(math.log2(hi + 1))


def proposed_dh(data: BagData | None, dh: dict[str, float] | None, propose: bool,
                progress: Callable[[int, int], None] | None = None) -> DHProposal | None:
    """``lrfcal inspect``'s proposal: the DH from the recording's planes when none were given (``dh`` None or the
    placeholder) and ``propose``; None when not searched. Without ``data`` (the recording could not be read) the
    proposal says so."""
    if not propose or (dh and not is_placeholder_dh(dh)):
        return None
    # the search's modules (scipy) once the recording is read: bad input is answered without them
    from lrfcal.pipeline.search import propose_for_recording
    from lrfcal.stages.propose import DHProposal

    if data is None:
        return DHProposal(None, reason="the recording could not be read (see the problems)")
    return propose_for_recording(data.scans, data.joints, progress)  # the stage takes scans and joint states


def inspect_bag(
    path: str | Path,
    scan: ScanSource | None = None,
    servo: ServoSource | None = None,
    dh: dict[str, float] | None = None,
    *,
    propose: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> BagInspection:
    """Inspect a bag (module docstring). ``scan`` / ``servo``: where the data are (from a rig file or options);
    None: guessed. ``dh``: the nominal DH for the snippet; when None (or the placeholder) and ``propose``, the DH
    proposed from the scene's planes (lrfcal.stages.propose; ``progress(done, total)`` over its search), else
    placeholders.

    Raises:
        InputError: the bag cannot be opened or read.
    """
    path = Path(path)
    sv = _survey(path)
    guessed: list[str] = []
    problems: list[str] = []
    multiecho = {tp for tp, msgs in sv.scan_msgs.items() if sv.types.get(tp) == MULTIECHO_TYPE
                 or any(is_multiecho(m) for m in msgs[:50])}
    if scan is None:
        scan = _guess_scan(sv.first, sv.scan_msgs, multiecho)
        if scan is not None:
            guessed.append("scan")
    notes = _echo_notes(scan, sv.scan_msgs, multiecho)
    if servo is None and scan is not None:
        servo = _guess_servo(sv.types, sv.first, scan, sv.tf_pairs, path)
        if servo is not None:
            guessed.append("servo")
    if scan is None:
        problems.append(f"{path}: no sensor_msgs/LaserScan topic and no message holding one")
    elif servo is None:
        problems.append(f"{path}: no servo angle found (JointState, std_msgs number, a number beside the scan, "
                        f"or /tf); give --servo-topic/--servo-field or --tf-parent/--tf-child")

    geometry = None
    if scan is not None and scan.topic in sv.scan_msgs:
        geometry = _geometry(sv.scan_msgs[scan.topic])
    report, servo_info, n_cov, data = None, None, None, None
    if scan is not None and servo is not None:
        report, servo_info, n_cov, data = _read_and_check(path, scan, servo, geometry, problems)
    if guessed:
        problems.append(f"guessed: {', '.join(guessed)} source (check the snippet, especially servo unit, sign "
                        f"and offset_rad)")
    proposal = proposed_dh(data, dh, propose, progress)
    snippet = rig_snippet(scan, servo, dh if proposal is None else proposal.values(),
                          multiecho=scan is not None and scan.topic in multiecho,
                          comment=None if proposal is None else proposal.comment())
    ros = 1 if path.suffix == ".bag" else 2
    return BagInspection(path, ros, float(sv.duration_s), tuple(_topic_infos(sv)), scan, servo, tuple(guessed),
                         geometry, servo_info, report, n_cov, tuple(problems), snippet, dict(dh or {}), tuple(notes),
                         proposal)


@dataclass
class _Survey:
    """One pass over a bag's messages: per topic its type, message count, receive times [s] (all messages), header
    stamps [s], first message and LaserScans (of the first MAX_DECODED messages); per /tf frame pair the rotation
    angle 2 acos(|w|) [rad] of each sample; the bag's duration [s]."""

    types: dict[str, str]
    counts: dict[str, int]
    duration_s: float
    recv: dict[str, list[float]] = field(default_factory=dict)
    stamps: dict[str, list[float]] = field(default_factory=dict)
    first: dict[str, Any] = field(default_factory=dict)
    scan_msgs: dict[str, list[Any]] = field(default_factory=dict)
    tf_pairs: dict[tuple[str, str], list[float]] = field(default_factory=dict)

    def add(self, reader: Any, conn: Any, t_ns: int, raw: bytes) -> None:
        """One message (``raw`` on connection ``conn`` of ``reader``, received at ``t_ns``); decoded while its
        topic has had at most MAX_DECODED messages."""
        tp = conn.topic
        self.recv.setdefault(tp, []).append(ns_to_s(t_ns))
        if len(self.recv[tp]) > MAX_DECODED and tp in self.first:
            return
        msg = decode_message(reader, raw, conn.msgtype)
        self.first.setdefault(tp, msg)
        ls = msg if is_laserscan(msg) else None
        fld = None if ls is not None else _laserscan_field(msg)
        st = stamp_s(msg) if fld is None else stamp_s(getattr(msg, fld))  # a LaserScan's own header
        if st is not None:
            self.stamps.setdefault(tp, []).append(st)
        if ls is not None:
            self.scan_msgs.setdefault(tp, []).append(ls)
        elif fld is not None:
            self.scan_msgs.setdefault(tp, []).append(getattr(msg, fld))
        if conn.msgtype == TF_TYPE and tp == "/tf":
            for tr in msg.transforms:
                key = (tr.header.frame_id, tr.child_frame_id)
                w = min(1.0, abs(float(tr.transform.rotation.w)))
                self.tf_pairs.setdefault(key, []).append(2.0 * math.acos(w))


def _survey(path: Path) -> _Survey:
    """Read every message of the bag once (:class:`_Survey`).

    Raises:
        InputError: the bag cannot be opened or read.
    """
    reader = open_reader(path)
    try:
        with reader:
            complete_types(reader)
            conns = reader.connections
            counts: dict[str, int] = {}
            for c in conns:
                counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
            duration = (reader.end_time - reader.start_time) * 1e-9 if conns else 0.0
            sv = _Survey({c.topic: c.msgtype for c in conns}, counts, duration)
            for c, t_ns, raw in reader.messages():
                sv.add(reader, c, t_ns, raw)
    except InputError:
        raise
    except Exception as err:
        raise InputError(f"{path}: cannot read bag: {one_line(err)}") from None
    return sv


def _topic_infos(sv: _Survey) -> list[TopicInfo]:
    """Every topic, alphabetically, with its rate and median receive - stamp."""
    topics = []
    for tp in sorted(sv.types):
        r = sv.recv.get(tp, [])
        st = sv.stamps.get(tp)
        rms = None
        if st and len(st) == len(r[: len(st)]):
            rms = float(np.median(np.asarray(r[: len(st)]) - np.asarray(st)))
        topics.append(TopicInfo(tp, sv.types[tp], sv.counts.get(tp, 0), _rate(r), tp in sv.stamps, rms))
    return topics


def _read_and_check(path: Path, scan: ScanSource, servo: ServoSource, geometry: ScanGeometry | None,
                    problems: list[str]
                    ) -> tuple[ReadReport | None, ServoInfo | None, int | None, BagData | None]:
    """Read the bag as the calibration will: the reader's report, the servo angle's statistics, the number of
    scans the servo samples cover and what was read (None each when the bag cannot be read); what is wrong
    appended to ``problems``."""
    try:
        data = read_bag(path, scan, servo, warn=lambda _t: None)
    except InputError as err:
        problems.append(str(err))
        return None, None, None, None
    report = data.report
    j = data.joints
    dt = np.diff(j.stamps_s)
    speed = np.abs(np.diff(j.positions_rad)) / np.where(dt > 0, dt, np.nan)
    servo_info = ServoInfo(int(j.stamps_s.size), float(j.positions_rad.min()),
                           float(j.positions_rad.max()), _rate(list(j.stamps_s)),
                           float(np.nanmedian(speed)) if speed.size else 0.0)
    cov = covered_scans(data.scans, j)
    n_cov = int(cov.sum())
    problems.extend(_report_problems(report))
    try:  # ranges in millimetres, joint positions in degrees: what reproject and calibrate refuse
        check_units(data.scans, j, f"{path}: {scan.topic}", f"{path}: {servo.describe()}", servo=servo)
    except InputError as err:
        problems.append(str(err))
    if n_cov < cov.size:
        problems.append(f"{cov.size - n_cov} of {cov.size} scans not covered by the servo samples "
                        f"(within one sample period); reproject and calibrate skip them")
    if geometry is not None and not geometry.has_intensities:
        problems.append(f"{scan.topic}: no intensities: reproject works, marker calibration does not")
    return report, servo_info, n_cov, data


def _report_problems(rep: ReadReport) -> list[str]:
    out = []
    if rep.skipped:
        out.append("skipped scans: " + ", ".join(f"{k} {v}" for k, v in sorted(rep.skipped.items())))
    if rep.masked:
        out.append("masked returns: " + ", ".join(f"{k} {v}" for k, v in sorted(rep.masked.items())))
    if rep.servo_skipped:
        out.append("servo samples skipped: " + ", ".join(f"{k} {v}" for k, v in sorted(rep.servo_skipped.items())))
    out.extend(rep.left_out)
    out.extend(rep.notes)
    return out


#: why the strongest echo of a MultiEchoLaserScan is proposed (module docstring)
STRONGEST_ECHO_REASON = ("where a beam's footprint straddles a marker's edge the beam splits into a marker echo and a "
                         "wall echo: the strongest echo keeps the marker's return, a LaserScan holds one return per "
                         "beam fixed by the driver (the simulator's /scan mixes the two into a range between "
                         "marker and wall; docs/sensor_errors.md)")


def _guess_scan(first: dict[str, Any], scan_msgs: dict[str, list[Any]], multiecho: set[str]
                ) -> ScanSource | None:
    """The scan source: a MultiEchoLaserScan topic first (with its strongest echo), then /scan, then the
    alphabetically first LaserScan topic or message holding one."""
    cands = sorted(scan_msgs, key=lambda t: (t not in multiecho, t != "/scan", t))
    if not cands:
        return None
    tp = cands[0]
    msg = first[tp]
    fld = None if is_laserscan(msg) else _laserscan_field(msg)
    return ScanSource(topic=tp, field=fld)  # echo: strongest, the default (read only for MultiEchoLaserScan)


def _echo_notes(scan: ScanSource | None, scan_msgs: dict[str, list[Any]], multiecho: set[str]) -> list[str]:
    """Why the scan topic holds (or should hold) the MultiEchoLaserScan's strongest echo."""
    if scan is None or not multiecho:
        return []
    single = sorted(set(scan_msgs) - multiecho)
    if scan.topic in multiecho:
        if scan.echo != "strongest":
            return [f"scan: {scan.topic} (MultiEchoLaserScan) read with echo: {scan.echo}, as asked; echo: "
                    f"strongest is the choice for markers: {STRONGEST_ECHO_REASON}"]
        beside = f" rather than {', '.join(single)} (LaserScan)" if single else ""
        return [f"scan: {scan.topic} (MultiEchoLaserScan) with echo: strongest{beside}: {STRONGEST_ECHO_REASON}"]
    return [f"scan: {scan.topic} (LaserScan) as asked; the bag also has {', '.join(sorted(multiecho))} "
            f"(MultiEchoLaserScan), and scan: {{topic: {sorted(multiecho)[0]}, echo: strongest}} is the choice for "
            f"markers: {STRONGEST_ECHO_REASON}"]


def _guess_servo(types: dict[str, str], first: dict[str, Any], scan: ScanSource,
                 tf_pairs: dict[tuple[str, str], list[float]], path: Path) -> ServoSource | None:
    def hinted(t: str) -> bool:
        return any(h in t.lower() for h in _SERVO_HINTS)

    def values_of(tp: str, fld: str | None, joint: str | None = None) -> np.ndarray:
        return _values(path, tp, fld, joint)

    # a number beside the LaserScan in the scan's own message
    if scan.field is not None:
        nums = _numeric_fields(first[scan.topic])
        if nums:
            name = next((n for n, _ in nums if hinted(n) or "step" in n.lower()), nums[0][0])
            unit, cpr = guess_unit(values_of(scan.topic, name))
            # the angle travels with its scan: a step-and-scan rig, said explicitly in the proposed rig file
            return ServoSource(topic=None, field=name, unit=unit, counts_per_rev=cpr, stamp="scan", motion="step")
    order = sorted(types, key=lambda t: (not hinted(t), t))
    for tp in order:
        mt = types[tp]
        if mt == JOINTSTATE_TYPE and tp in first:
            names = list(first[tp].name)
            joint = next((n for n in names if hinted(n)), names[0] if names else None)
            if joint is None:
                continue
            stamp: ServoStamp = "header" if stamp_s(first[tp]) is not None else "receive"
            return ServoSource(topic=tp, joint=joint, stamp=stamp)
    for tp in order:
        mt = types[tp]
        fld = default_field(mt)
        if fld is None or tp not in first:
            continue
        unit, cpr = guess_unit(values_of(tp, fld))
        stamp = "header" if stamp_s(first[tp]) is not None else "receive"
        if mt == DYNAMIXEL_JOINTSTATE_TYPE:
            unit, cpr = "rad", None  # dynamixel_controllers publish radians
        return ServoSource(topic=tp, field=None if fld == default_field(mt) else fld, unit=unit,
                           counts_per_rev=cpr, stamp=stamp)
    if tf_pairs:
        # the pair whose rotation changes most (a joint, not a fixed mount)
        (parent, child), _ = max(tf_pairs.items(), key=lambda kv: max(kv[1]) - min(kv[1]))
        return ServoSource(topic=None, tf=TfSource(parent=parent, child=child))
    return None


def _values(path: Path, topic: str, fld: str | None, joint: str | None = None) -> np.ndarray:
    """The numeric values of a field (first MAX_DECODED messages) for the unit guess."""
    reader = open_reader(path)
    out: list[float] = []
    with reader:
        complete_types(reader)
        conns = [c for c in reader.connections if c.topic == topic]
        for c, _, raw in reader.messages(connections=conns):
            m = decode_message(reader, raw, c.msgtype)
            try:
                out.append(float(get_field(m, fld, topic)) if fld else math.nan)
            except (InputError, TypeError, ValueError):
                return np.zeros(0)
            if len(out) >= MAX_DECODED:
                break
    return np.asarray(out)


def _geometry(msgs: list[Any]) -> ScanGeometry:
    def span(vals: list[float]) -> tuple[float, float]:
        a = np.asarray(vals, dtype=float)
        a = a[np.isfinite(a)]
        return (float(a.min()), float(a.max())) if a.size else (math.nan, math.nan)

    n = [len(m.ranges) for m in msgs]
    return ScanGeometry(
        n_messages=len(msgs), beam_count=(min(n), max(n)),
        angle_min_rad=span([m.angle_min for m in msgs]), angle_max_rad=span([m.angle_max for m in msgs]),
        angle_increment_rad=span([m.angle_increment for m in msgs]),
        time_increment_s=span([m.time_increment for m in msgs]), scan_time_s=span([m.scan_time for m in msgs]),
        range_min_m=float(np.nanmin([m.range_min for m in msgs])),
        range_max_m=float(np.nanmax([m.range_max for m in msgs])),
        has_intensities=any(_has_intensities(m) for m in msgs),
    )


def _has_intensities(msg: Any) -> bool:
    """Any positive intensity in a LaserScan or a MultiEchoLaserScan (per-beam LaserEcho lists)."""
    it = msg.intensities
    if is_multiecho(msg):
        return bool(np.any(Echoes.of(it).values > 0))
    return len(it) > 0 and bool(np.any(np.asarray(it) > 0))


__all__ = ["BagInspection", "ScanGeometry", "ServoInfo", "TopicInfo", "guess_unit", "inspect_bag", "proposed_dh"]
