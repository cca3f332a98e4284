"""Reading a recording: the bag (LaserScan + JointState), the tape distances and the nominal values.

Formats: docs/formats.md. Every problem raises :class:`~lrfcal.errors.InputError` with a one-line message
naming the file, the topic or field, and the offending value.

Array shapes: S scans, N beams per scan, J joint-state samples, n markers, P measured pairs.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .errors import InputError
from .kinematics import ANGLE_NAMES, dh_from_mapping, pose_from_mapping
from .types import JointStates, Nominal, Recording, Scans, TapeMeasurements

LASERSCAN_TYPE = "sensor_msgs/msg/LaserScan"
JOINTSTATE_TYPE = "sensor_msgs/msg/JointState"
DISTANCES_HEADER = ("marker_i", "marker_j", "distance_m")
NOMINAL_KEYS = ("dh", "mount", "marker_radius_m", "scan_topic", "joint_topic", "joint_name")
MIN_MARKERS = 4

#: Relative tolerance on angle_min / angle_increment / time_increment across scans.
_ANGLE_TOL_RAD = 1e-6


def _stamp_s(msg: Any) -> float:
    """header.stamp of a ROS 1 or ROS 2 message in seconds (float64)."""
    st = msg.header.stamp
    return float(st.sec) + 1e-9 * float(st.nanosec)


def _open_reader(path: Path) -> Any:
    """An unopened AnyReader for a ROS 1 .bag file, a ROS 2 bag folder, or a single .mcap/.db3 file."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise InputError(f"{path}: bag not found")
    try:
        return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    except Exception as err:  # rosbags raises several unrelated types for unreadable input
        raise InputError(f"{path}: cannot open bag: {_one_line(err)}") from None


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text or type(err).__name__


def _topic_connections(reader: Any, path: Path, topic: str, msgtype: str) -> list[Any]:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        have = sorted({c.topic for c in reader.connections})
        raise InputError(f"{path}: topic {topic}: not in bag (topics: {', '.join(have) or 'none'})")
    wrong = sorted({c.msgtype for c in conns if c.msgtype != msgtype})
    if wrong:
        raise InputError(f"{path}: topic {topic}: type {wrong[0]}, expected {msgtype}")
    return conns


def read_bag(
    path: str | Path,
    scan_topic: str = "/scan",
    joint_topic: str = "/joint_states",
    joint_name: str = "servo",
    check_coverage: bool = True,
) -> tuple[Scans, JointStates]:
    """Read the LaserScan and JointState messages of a bag.

    Args:
        path: a ROS 1 ``.bag`` file, a ROS 2 bag folder (sqlite3 or MCAP) or a single ``.mcap``/``.db3`` file.
        scan_topic, joint_topic: topic names; joint_name: the motor joint in JointState.name.
        check_coverage: require the joint states to cover every beam time (within one joint sample period).
    Returns:
        Scans (S scans sorted by header.stamp; ranges (S, N) with NaN for NaN/inf/outside [range_min,
        range_max]; intensities (S, N), zeros when the driver published none) and JointStates (J samples of
        ``joint_name`` sorted by stamp, duplicate stamps averaged).
    Raises:
        InputError: unreadable bag, missing topic, no messages, inconsistent beam layout, missing joint,
            joint states that do not cover the scans.
    """
    path = Path(path)
    reader = _open_reader(path)
    try:
        with reader:
            scan_conns = _topic_connections(reader, path, scan_topic, LASERSCAN_TYPE)
            joint_conns = _topic_connections(reader, path, joint_topic, JOINTSTATE_TYPE)
            scan_msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(scan_conns)]
            joint_msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(joint_conns)]
    except InputError:
        raise
    except Exception as err:
        raise InputError(f"{path}: cannot read bag: {_one_line(err)}") from None
    scans = _scans_from_msgs(scan_msgs, f"{path}: {scan_topic}")
    joints = _joints_from_msgs(joint_msgs, f"{path}: {joint_topic}", joint_name)
    if check_coverage:
        check_joint_coverage(scans, joints, f"{path}: {joint_topic}")
    return scans, joints


def _scans_from_msgs(msgs: list[Any], where: str) -> Scans:
    """Stack LaserScan messages into a :class:`Scans`; ``where`` prefixes error messages."""
    if not msgs:
        raise InputError(f"{where}: no messages")
    stamps = np.array([_stamp_s(m) for m in msgs])
    order = np.argsort(stamps, kind="stable")
    msgs = [msgs[i] for i in order]
    stamps = stamps[order]
    first = msgs[0]
    n_beams = len(first.ranges)
    if n_beams == 0:
        raise InputError(f"{where}: ranges: empty in the first scan (stamp {stamps[0]:.6f} s)")
    angle_min = float(first.angle_min)
    inc = float(first.angle_increment)
    t_inc = float(first.time_increment)
    if not (math.isfinite(angle_min) and math.isfinite(inc) and inc != 0.0):
        raise InputError(f"{where}: angle_min/angle_increment: invalid ({angle_min!r}, {inc!r})")
    if not math.isfinite(t_inc):
        raise InputError(f"{where}: time_increment: invalid ({t_inc!r})")
    S = len(msgs)
    ranges = np.empty((S, n_beams), dtype=np.float64)
    intens = np.zeros((S, n_beams), dtype=np.float64)
    rmin = np.empty(S)
    rmax = np.empty(S)
    for k, m in enumerate(msgs):
        r = np.asarray(m.ranges, dtype=np.float64)
        if r.size != n_beams:
            raise InputError(f"{where}: ranges: {r.size} beams at stamp {stamps[k]:.6f} s, the first scan "
                             f"has {n_beams}")
        if abs(float(m.angle_min) - angle_min) > _ANGLE_TOL_RAD or abs(float(m.angle_increment) - inc) > 1e-9:
            raise InputError(f"{where}: angle_min/angle_increment: ({float(m.angle_min)}, "
                             f"{float(m.angle_increment)}) at stamp {stamps[k]:.6f} s differ from the first "
                             f"scan's ({angle_min}, {inc})")
        if abs(float(m.time_increment) - t_inc) > 1e-6 * max(abs(t_inc), 1e-9):
            raise InputError(f"{where}: time_increment: {float(m.time_increment)} at stamp {stamps[k]:.6f} s "
                             f"differs from the first scan's {t_inc}")
        ranges[k] = r
        rmin[k] = float(m.range_min)
        rmax[k] = float(m.range_max)
        i = np.asarray(m.intensities, dtype=np.float64)
        if i.size == n_beams:
            intens[k] = i
        elif i.size != 0:
            raise InputError(f"{where}: intensities: {i.size} values for {n_beams} beams at stamp "
                             f"{stamps[k]:.6f} s")
    range_min = float(np.nanmax(rmin)) if np.isfinite(rmin).any() else 0.0
    range_max = float(np.nanmin(rmax)) if np.isfinite(rmax).any() else math.inf
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(ranges) | (ranges < rmin[:, None]) | (ranges > rmax[:, None])
    ranges[bad] = np.nan
    intens[~np.isfinite(intens)] = 0.0
    mu = angle_min + np.arange(n_beams) * inc
    return Scans(
        stamps_s=stamps,
        ranges_m=ranges,
        intensities=intens,
        mu_rad=mu,
        time_increment_s=t_inc,
        scan_time_s=float(first.scan_time),
        range_min_m=range_min,
        range_max_m=range_max,
        frame_id=str(first.header.frame_id),
        source=where,
    )


def _joints_from_msgs(msgs: list[Any], where: str, joint_name: str) -> JointStates:
    """Extract one joint's (stamp, position) samples from JointState messages."""
    if not msgs:
        raise InputError(f"{where}: no messages")
    names_seen: set[str] = set()
    stamps: list[float] = []
    pos: list[float] = []
    for m in msgs:
        names = list(m.name)
        names_seen.update(names)
        if joint_name not in names:
            continue
        j = names.index(joint_name)
        p = np.asarray(m.position, dtype=np.float64)
        t = _stamp_s(m)
        if p.size != len(names):
            raise InputError(f"{where}: position: {p.size} values for {len(names)} names at stamp {t:.6f} s")
        if not math.isfinite(p[j]):
            raise InputError(f"{where}: position[{joint_name}]: {p[j]!r} at stamp {t:.6f} s")
        stamps.append(t)
        pos.append(float(p[j]))
    if not stamps:
        raise InputError(f"{where}: name: joint {joint_name!r} not found (available: "
                         f"{', '.join(sorted(names_seen)) or 'none'})")
    t = np.asarray(stamps)
    q = np.asarray(pos)
    order = np.argsort(t, kind="stable")
    t, q = t[order], q[order]
    ut, inv = np.unique(t, return_inverse=True)
    if ut.size != t.size:  # duplicate stamps: average their positions
        q = np.bincount(inv, weights=q) / np.bincount(inv)
        t = ut
    if t.size < 2:
        raise InputError(f"{where}: {joint_name}: only {t.size} sample; need at least 2 to interpolate")
    return JointStates(stamps_s=t, positions_rad=q, name=joint_name)


def check_joint_coverage(scans: Scans, joints: JointStates, where: str = "joint states",
                         clock_offset_s: float = 0.0) -> None:
    """Raise InputError unless the joint states span every beam time, within one joint sample period.

    Beam times (laser clock) are converted to the servo clock as t - clock_offset_s.
    """
    from .timing import joint_period_s

    period = joint_period_s(joints)
    bt = scans.beam_times_s - clock_offset_s
    first, last = float(np.min(bt)), float(np.max(bt))
    j0, j1 = float(joints.stamps_s[0]), float(joints.stamps_s[-1])
    if first < j0 - period:
        raise InputError(f"{where}: joint states start at {j0:.6f} s, {j0 - first:.6f} s after the first "
                         f"beam at {first:.6f} s (tolerance one sample period {period:.6f} s)")
    if last > j1 + period:
        raise InputError(f"{where}: joint states end at {j1:.6f} s, {last - j1:.6f} s before the last beam "
                         f"at {last:.6f} s (tolerance one sample period {period:.6f} s)")


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
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: cannot read: {_one_line(err)}") from None
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

def read_nominal(path: str | Path) -> Nominal:
    """Read nominal.yaml (keys: dh (required), mount, marker_radius_m, scan_topic, joint_topic, joint_name).

    Raises:
        InputError: missing file, YAML syntax error, unknown or missing key, bad value (the field is named).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: nominal file not found")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
        problem = getattr(err, "problem", None) or _one_line(err)
        raise InputError(f"{where}: YAML syntax error: {problem}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: cannot read: {_one_line(err)}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping with keys {', '.join(NOMINAL_KEYS)}, got {data!r}")
    unknown = sorted(str(k) for k in data if k not in NOMINAL_KEYS)
    if unknown:
        raise InputError(f"{path}: {unknown[0]}: unknown key (expected {', '.join(NOMINAL_KEYS)})")
    if "dh" not in data:
        raise InputError(f"{path}: dh: missing")
    dh = dh_from_mapping(data["dh"], f"{path}: dh")
    mount = pose_from_mapping(data["mount"], f"{path}: mount") if data.get("mount") is not None else None
    for section, values in (("dh", dh.as_dict()), ("mount", mount.as_dict() if mount is not None else {})):
        for name, v in values.items():
            if name in ANGLE_NAMES and abs(v) > 2 * math.pi:  # an angle in degrees: 90 instead of 1.5708
                raise InputError(f"{path}: {section}.{name}: {v:g} rad is beyond 2 pi: it looks like degrees; "
                                 f"angles are in radians ({v:g} deg = {math.radians(v):.6g} rad)")
    kw: dict[str, Any] = {}
    if "marker_radius_m" in data:
        r = data["marker_radius_m"]
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r) or r < 0:
            raise InputError(f"{path}: marker_radius_m: expected a finite length >= 0, got {r!r}")
        kw["marker_radius_m"] = float(r)
    for key in ("scan_topic", "joint_topic", "joint_name"):
        if key in data:
            v = data[key]
            if not isinstance(v, str) or not v.strip():
                raise InputError(f"{path}: {key}: expected a non-empty string, got {v!r}")
            kw[key] = v.strip()
    return Nominal(dh=dh, mount=mount, **kw)


# --- the whole folder ---------------------------------------------------------------------------------------

def read_recording(
    folder: str | Path | None,
    bag: str | Path | None = None,
    distances: str | Path | None = None,
    nominal: str | Path | None = None,
    scan_topic: str | None = None,
    joint_topic: str | None = None,
    joint_name: str | None = None,
) -> Recording:
    """Read a recording folder (docs/formats.md): ``bag/``, ``distances.csv``, ``nominal.yaml``.

    Each path can be overridden (then ``folder`` may be None if all three are given); topic and joint names
    come from nominal.yaml unless overridden here.
    """
    base = Path(folder) if folder is not None else None
    if base is not None and not base.is_dir():
        raise InputError(f"{base}: recording folder not found")

    def pick(given: str | Path | None, default: str, what: str) -> Path:
        if given is not None:
            return Path(given)
        if base is None:
            raise InputError(f"{what}: no path given and no recording folder")
        return base / default

    nom = read_nominal(pick(nominal, "nominal.yaml", "nominal"))
    tape = read_distances(pick(distances, "distances.csv", "distances"))
    scans, joints = read_bag(
        pick(bag, "bag", "bag"),
        scan_topic=scan_topic or nom.scan_topic,
        joint_topic=joint_topic or nom.joint_topic,
        joint_name=joint_name or nom.joint_name,
    )
    return Recording(scans=scans, joints=joints, tape=tape, nominal=nom, source=base)


__all__ = [
    "check_joint_coverage", "read_bag", "read_distances", "read_nominal", "read_recording",
]
