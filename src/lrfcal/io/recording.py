"""Reading a recording: the bag (lrfcal.io.bag), the tape distances and the rig file (lrfcal.io.rig).

Formats: docs/formats.md. Every problem raises :class:`~lrfcal.errors.InputError` with a one-line message
naming the file, the topic or field, and the offending value.

Array shapes: S scans, N beams per scan, J joint-state samples, n markers, P measured pairs.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path

import numpy as np

from lrfcal.errors import InputError
from lrfcal.io.bag import BagReader, Progress, read_bag
from lrfcal.io.bag_messages import one_line
from lrfcal.io.rig import ScanSource, ServoSource, load_rig
from lrfcal.io.scanlog import LOOKED_FOR, is_scan_log, read_scan_log, resolve_recording
from lrfcal.model.kinematics import DH, Pose
from lrfcal.types import JointStates, Nominal, Recording, Scans, SelfBox, TapeMeasurements

DISTANCES_HEADER = ("marker_i", "marker_j", "distance_m")
MIN_MARKERS = 4


def check_joint_coverage(scans: Scans, joints: JointStates, where: str = "joint states",
                         clock_offset_s: float = 0.0) -> None:
    """Raise InputError unless the joint states span every beam time, within one joint sample period.

    Beam times (laser clock) are converted to the servo clock as t - clock_offset_s. For reporting: the
    reader does not call it (the calibration trims uncovered scans, timing.covered_scans).
    """
    from lrfcal.types import joint_period_s, scan_spans

    period = joint_period_s(joints)
    lo, hi = scan_spans(scans)
    first, last = float(np.min(lo)) - clock_offset_s, float(np.max(hi)) - clock_offset_s
    j0, j1 = float(joints.stamps_s[0]), float(joints.stamps_s[-1])
    if first < j0 - period:
        raise InputError(f"{where}: joint states start at {j0:.6f} s, {j0 - first:.6f} s after the first "
                         f"beam at {first:.6f} s (tolerance one sample period {period:.6f} s)")
    if last > j1 + period:
        raise InputError(f"{where}: joint states end at {j1:.6f} s, {last - j1:.6f} s before the last beam "
                         f"at {last:.6f} s (tolerance one sample period {period:.6f} s)")


# --- units of the recorded numbers ----------------------------------------------------------------------------

#: A LaserScan's ranges are metres (REP 103); a median valid range beyond this, or a declared range_max beyond
#: MAX_RANGE_MAX_M with a median beyond MIN_MEDIAN_MM_M, is a recording in millimetres: a 2D scanner on a turning
#: mount sees a room or a tunnel (the UTM-30LX-EW reaches 60 m, a URG-04LX 5.6 m: Hokuyo specifications).
MAX_MEDIAN_RANGE_M = 100.0
MAX_RANGE_MAX_M = 1000.0
MIN_MEDIAN_MM_M = 10.0
#: A sweeping servo turns less than a turn each way; joint states that go more than this far both ways were
#: recorded in degrees (a spinning motor turns on one way and is not judged).
MAX_SWEEP_RAD = 2.0 * math.pi * 1.05


def check_units(scans: Scans, joints: JointStates, where_scan: str, where_servo: str,
                servo: ServoSource | None = None) -> None:
    """Refuse ranges or joint positions whose size is implausible for their unit (metres, radians), naming the field,
    the value and the likely unit: the scans' median valid range and range_max (:data:`MAX_MEDIAN_RANGE_M`,
    :data:`MAX_RANGE_MAX_M`) and the joint positions of a servo that sweeps back and forth by more than
    :data:`MAX_SWEEP_RAD` each way. ``where_scan`` / ``where_servo`` name the file and topic; ``servo``: the rig's
    servo source (its ``unit`` for the advice).

    Raises:
        InputError: ranges in millimetres or joint positions in degrees, in one line.
    """
    rmax = float(scans.range_max_m)
    limit = MIN_MEDIAN_MM_M if math.isfinite(rmax) and rmax > MAX_RANGE_MAX_M else MAX_MEDIAN_RANGE_M
    median = _median_beyond(scans.ranges_m, limit)
    if median > limit:
        raise InputError(
            f"{where_scan}: ranges look like millimetres, not metres: range_max {rmax:g} m, median range {median:g} m "
            f"(as millimetres: {rmax / 1000:g} m and {median / 1000:g} m); LaserScan ranges are in metres (REP 103): "
            "have the driver publish metres, or convert the recording (ranges, range_min, range_max x 0.001)")
    q = np.asarray(joints.positions_rad, dtype=float)
    if q.size < 2:
        return
    rise = float(np.max(q - np.minimum.accumulate(q)))  # the farthest it went up from a low, and down from a high
    fall = float(np.max(np.maximum.accumulate(q) - q))
    if min(rise, fall) <= MAX_SWEEP_RAD:
        return
    lo, hi = float(q.min()), float(q.max())
    unit = servo.unit if servo is not None else "rad"
    fix = ("they look like degrees: set servo.unit: deg in the rig file" if unit == "rad" else
           f"check servo.unit ({unit}) and counts_per_rev in the rig file")
    raise InputError(
        f"{where_servo}: joint positions {lo:.4g} to {hi:.4g} rad, a servo sweeping back and forth by "
        f"{min(rise, fall) / (2 * math.pi):.1f} turns each way (a sweep turns less than one); {fix} "
        f"({lo:.4g} to {hi:.4g} deg is {math.radians(lo):.3f} to {math.radians(hi):.3f} rad)")


def _median_beyond(ranges_m: np.ndarray, limit_m: float) -> float:
    """The median of the valid (finite, positive) ranges of ``ranges_m`` (any shape) when it can exceed ``limit_m``
    (> 0), else 0.0 (not computed: fewer than half of the valid ranges are beyond the limit, so the median is not;
    counting them takes a third of the time of the median); 0.0 for no valid range."""
    valid = np.isfinite(ranges_m)
    valid &= ranges_m > 0
    n = int(np.count_nonzero(valid))
    if 2 * int(np.count_nonzero(valid & (ranges_m > limit_m))) < n or n == 0:
        return 0.0
    return float(np.median(ranges_m[valid]))


# --- distances.csv ------------------------------------------------------------------------------------------

def read_distances(path: str | Path, tolerance_m: float = 1e-6) -> TapeMeasurements:
    """Read the tape measurements (CSV ``marker_i,marker_j,distance_m``, one row per unordered pair).

    Marker ids are taken in order of first appearance. A pair listed twice (in either order) must agree
    within ``tolerance_m`` and is then kept once (averaged); otherwise the file is rejected as asymmetric.
    Blank lines and lines starting with ``#`` are ignored; ids are stripped of surrounding whitespace.
    Returns:
        TapeMeasurements with marker_ids (n,), pairs (P, 2) int indices (i < j), distances_m (P,).
    Raises:
        InputError: missing file, bad header, bad row (line number named), asymmetric pair, fewer than 4
            markers, or a distance graph that is not connected.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: distances file not found")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not a text (UTF-8) file: byte {e.object[e.start]:#04x} at offset {e.start}; the "
                         f"distances file is a CSV with the header {','.join(DISTANCES_HEADER)} (docs/formats.md)"
                         ) from None
    except OSError as err:
        raise InputError(f"{path}: cannot read: {one_line(err)}") from None
    rows = [(n, row) for n, row in enumerate(csv.reader(text.splitlines()), start=1)
            if row and any(c.strip() for c in row) and not row[0].lstrip().startswith("#")]
    if not rows:
        raise InputError(f"{path}: empty (expected header {','.join(DISTANCES_HEADER)})")
    line, header = rows[0]
    if tuple(c.strip() for c in header) != DISTANCES_HEADER:
        raise InputError(f"{path}:{line}: header: expected {','.join(DISTANCES_HEADER)}, "
                         f"got {','.join(header)}")
    ids: dict[str, int] = {}
    seen: dict[tuple[int, int], tuple[int, list[float]]] = {}
    for line, row in rows[1:]:
        if len(row) != 3:
            raise InputError(f"{path}:{line}: expected 3 columns (marker_i,marker_j,distance_m), "
                             f"got {len(row)}: {','.join(row)}")
        a, b, d_text = (c.strip() for c in row)
        if not a or not b:
            raise InputError(f"{path}:{line}: {'marker_i' if not a else 'marker_j'}: empty id")
        if a == b:
            raise InputError(f"{path}:{line}: marker_j: pair of {a!r} with itself")
        try:
            d = float(d_text)
        except ValueError:
            raise InputError(f"{path}:{line}: distance_m: not a number: {d_text!r}") from None
        if not math.isfinite(d) or d <= 0.0:
            raise InputError(f"{path}:{line}: distance_m: must be a finite positive length, got {d_text!r}")
        ia = ids.setdefault(a, len(ids))
        ib = ids.setdefault(b, len(ids))
        key = (min(ia, ib), max(ia, ib))
        if key in seen:
            first_line, values = seen[key]
            if abs(values[0] - d) > tolerance_m:
                raise InputError(f"{path}:{line}: distance_m: {a}-{b} = {d_text} disagrees with line "
                                 f"{first_line} ({values[0]!r}) (asymmetric)")
            values.append(d)
        else:
            seen[key] = (line, [d])
    names = tuple(ids)
    if len(names) < MIN_MARKERS:
        raise InputError(f"{path}: only {len(names)} markers ({', '.join(names) or 'none'}); need at least "
                         f"{MIN_MARKERS}")
    pairs = np.array(list(seen), dtype=np.int64).reshape(-1, 2)
    dist = np.array([float(np.mean(v)) for _, v in seen.values()])
    parts = _components(len(names), pairs)
    if len(parts) > 1:
        groups = "; ".join(",".join(names[i] for i in p) for p in parts)
        raise InputError(f"{path}: markers not connected by distances (groups: {groups})")
    return TapeMeasurements(marker_ids=names, pairs=pairs, distances_m=dist)


def _components(n: int, pairs: Iterable[Iterable[int]]) -> list[list[int]]:
    """Connected components of an undirected graph on n nodes (union-find), each sorted."""
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in pairs:
        parent[find(int(i))] = find(int(j))
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values())


# --- nominal.yaml -------------------------------------------------------------------------------------------

#: the rig file's name in a recording folder (what `lrfcal calibrate REC` and `lrfcal reproject REC` read without
#: --nominal)
RIG_FILE = "nominal.yaml"


def read_nominal(path: str | Path) -> Nominal:
    """Read the rig file nominal.yaml (lrfcal.io.rig.RigFile; keys in docs/formats.md).

    Raises:
        InputError: missing file, YAML syntax error, unknown or missing key, bad value (the key is named).
    """
    rig = load_rig(path)
    dh = DH(**rig.dh.model_dump())
    mount = Pose(**rig.mount.model_dump()) if rig.mount is not None else None
    scan, servo = rig.scan_source(), rig.servo_source()
    tol = rig.dh_tolerance
    return Nominal(dh=dh, dh_tolerance=None if tol is None else (tol.a, tol.alpha, tol.b, tol.beta), mount=mount,
                   marker_radius_m=rig.marker_radius_m,
                   beam_divergence_rad=rig.beam_divergence_rad, range_sigma_m=rig.range_sigma_m,
                   range_pattern=rig.range_pattern,
                   self_boxes=tuple(SelfBox(Pose(**b.pose.model_dump()), b.size_m) for b in rig.self_boxes),
                   scan_topic=scan.topic,
                   joint_topic=servo.topic or "", joint_name=servo.joint or "", scan=scan, servo=servo,
                   log=rig.log)


# --- the whole folder ---------------------------------------------------------------------------------------

def read_recording(
    folder: str | Path | None,
    bag: str | Path | None = None,
    distances: str | Path | None = None,
    nominal: str | Path | None = None,
    scan_topic: str | None = None,
    joint_topic: str | None = None,
    joint_name: str | None = None,
    *,
    scan: ScanSource | None = None,
    servo: ServoSource | None = None,
    require_distances: bool = True,
    progress: Progress | None = None,
    warn: Callable[[str], None] | None = None,
    bag_reader: BagReader | None = None,
    give_bag: str = "give the bag with --bag PATH",
) -> Recording:
    """Read a recording: the bag (lrfcal.io.bag.read_bag) or scan log (lrfcal.io.scanlog.read_scan_log, for a .txt,
    .csv or .log file), ``distances.csv`` and the rig file ``nominal.yaml``.

    ``folder`` may be a scan log itself (the folder is then the log's), and a folder without ``bag/`` is read
    from its one scan log (lrfcal.io.scanlog.resolve_recording).

    Each path can be overridden (then ``folder`` may be None if all needed paths are given). Where the data
    are in the bag comes from the rig file, replaced by ``scan`` / ``servo`` when given, with ``scan_topic``,
    ``joint_topic``, ``joint_name`` overriding single keys. ``require_distances=False`` skips the tape
    distances (Recording.tape is then None unless a distances file is given). The reader does not check that
    the joint states cover the scans (see :func:`check_joint_coverage`, timing.covered_scans). ``bag_reader(scan,
    servo, warn)``: the bag's data from elsewhere than a file (a simulation's messages: lrfsim.recording).
    ``give_bag``: how the command that reads takes a bag, for the message when a folder holds none.
    """
    if bag_reader is None:
        base, bag = resolve_recording(folder, bag)  # a scan log as the recording, or a folder holding one
    else:
        base = None if folder is None else Path(folder)
    if base is not None and not base.is_dir():
        raise InputError(f"{base}: recording folder not found")
    if bag_reader is None and bag is None and base is not None and not (base / "bag").exists():
        raise InputError(f"{base}: no bag found in the recording folder: looked for {LOOKED_FOR}; {give_bag} (a ROS 1 "
                         ".bag file, a ROS 2 bag folder or its .mcap/.db3 file, a scan log)")

    def pick(given: str | Path | None, default: str, what: str) -> Path:
        if given is not None:
            return Path(given)
        if base is None:
            raise InputError(f"{what}: no path given and no recording folder")
        return base / default

    nom = read_nominal(pick(nominal, RIG_FILE, "nominal"))
    tape = None
    if require_distances or distances is not None:
        tape = read_distances(pick(distances, "distances.csv", "distances"))
    scan_src, servo_src = scan or nom.scan, servo or nom.servo
    assert scan_src is not None and servo_src is not None  # read_nominal sets both from the rig file
    if scan_topic:
        scan_src = scan_src.model_copy(update={"topic": scan_topic})
    if joint_topic or joint_name:
        upd = {k: v for k, v in (("topic", joint_topic), ("joint", joint_name)) if v}
        servo_src = ServoSource.model_validate({**servo_src.model_dump(), **upd})
    if bag_reader is not None:
        data = bag_reader(scan_src, servo_src, warn)
        where = f"{base or 'the recording'}: {scan_src.topic}", f"{base or 'the recording'}: {servo_src.describe()}"
    elif is_scan_log(bag_path := pick(bag, "bag", "bag")):  # a text log (lrfcal.io.scanlog; the rig's log: section)
        data = read_scan_log(bag_path, nom.log, servo_src, warn=warn)
        where = f"{bag_path}: the range columns", f"{bag_path}: the angle column ({servo_src.unit})"
    else:
        data = read_bag(bag_path, scan_src, servo_src, progress=progress, warn=warn)
        where = f"{bag_path}: {scan_src.topic}", f"{bag_path}: {servo_src.describe()}"
    check_units(data.scans, data.joints, *where, servo=servo_src)
    nom = replace(nom, scan=scan_src, servo=servo_src, scan_topic=scan_src.topic,
                  joint_topic=servo_src.topic or "", joint_name=servo_src.joint or "")
    return Recording(scans=data.scans, joints=data.joints, tape=tape, nominal=nom, source=base,
                     report=data.report)


__all__ = [
    "MAX_MEDIAN_RANGE_M", "MAX_RANGE_MAX_M", "MAX_SWEEP_RAD", "MIN_MEDIAN_MM_M", "check_joint_coverage", "check_units",
    "RIG_FILE", "read_distances", "read_nominal", "read_recording",
]
