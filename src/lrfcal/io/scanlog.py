"""Scan logs: the text files hobby and lab rigs write over a serial line, one row per scan (docs/formats.md,
"Scan logs"), read into the same :class:`~lrfcal.io.bag.BagData` as a bag.

A row is a few leading columns (the rig file's ``log.columns``: ``time`` and ``angle`` once each, ``ignore`` for
anything else such as a row number), then one range per beam, then (``log.intensities: true``) as many
intensities. Fields are separated by commas (blanks around them allowed; one trailing comma allowed) or, in a row
without a comma, by blanks or tabs. Blank lines and lines starting with ``#`` are ignored. With
``log.header: angles`` the first row holds, after its leading columns, every beam's angle (the format of the
long-arm lidar of Lin et al., IEEE TIM 70, 4506610, 2021, github.com/SCVision/LongarmLiDAR); otherwise the
scanner's ``angle_min_rad`` and ``angle_increment_rad`` come from the rig file.

The motor angle of a row belongs to its scan: a log rig steps and scans unless ``servo.motion: continuous`` says
it turns while the laser scans. The angle becomes lambda as for a bag (``servo.unit``, ``sign``, ``offset_rad``).
Ranges are masked exactly as the bag reader masks a LaserScan's (0 = no return, NaN, +-inf, below
``log.range_min_m``, above ``log.range_max_m``) and counted; a row with a non-finite time is skipped and counted;
a missing ``log.time_increment_s`` is assumed (scan period / beams per revolution) with a warning. A value that is
not a number, a row with the wrong number of columns, or a header row whose angles are not strictly monotonic is
one :class:`~lrfcal.errors.InputError` naming the file, the line, the column and the value.

Array shapes: R rows (scans), N beams.
"""

from __future__ import annotations

import math
import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.io.bag import BagData, timing_notes
from lrfcal.io.bag_scans import scans_from
from lrfcal.io.bag_servo import Samples, joints_from
from lrfcal.io.rig import LogLayout, ScanSource, ServoSource
from lrfcal.types import ReadReport

FloatArray = NDArray[np.float64]
#: file name endings of a scan log (a ROS 1 bag is ``.bag``; a ROS 2 bag a folder, ``.mcap`` or ``.db3``)
LOG_SUFFIXES = (".txt", ".csv", ".log")
#: a gap between rows longer than this many scan periods is named (dropped scans)
GAP_PERIODS = 1.5


def is_scan_log(path: str | Path) -> bool:
    """True for a file ending in .txt, .csv or .log that is not a ROS 1 bag (``#ROSBAG`` magic)."""
    p = Path(path)
    if p.suffix.lower() not in LOG_SUFFIXES or not p.is_file():
        return False
    with open(p, "rb") as f:
        return not f.read(7).startswith(b"#ROSBAG")


def find_log(folder: Path) -> Path | None:
    """The one recording in a recording folder without ``bag/``: a bag under any name (a ROS 1 ``.bag``, an
    ``.mcap`` or ``.db3`` file, a ROS 2 bag folder with its metadata.yaml) or a scan log (distances.csv is not one);
    None when there is none. Raises InputError naming them when there are several."""
    found = sorted(p for p in folder.iterdir() if (p.name != "distances.csv" and is_scan_log(p)) or _is_bag(p))
    if len(found) > 1:
        logs = all(is_scan_log(p) for p in found)
        what = f"{len(found)} scan logs" if logs else f"{len(found)} bags or scan logs"
        raise InputError(f"{folder}: no bag/ and {what} ({', '.join(p.name for p in found)}); "
                         f"pick one with --bag {'LOG' if logs else 'PATH'}")
    return found[0] if found else None


#: what a recording folder is searched for (:func:`find_log`), in words for the error that finds none
LOOKED_FOR = ("bag/ (a ROS 2 bag folder), or else one bag under any name (a ROS 1 .bag, an .mcap or .db3 file, a "
              "folder with metadata.yaml) or one scan log (.txt, .csv, .log)")


def _is_bag(path: Path) -> bool:
    """A ROS 1 bag or a single-file ROS 2 bag (.bag, .mcap, .db3), or a ROS 2 bag folder (its metadata.yaml)."""
    if path.is_file():
        return path.suffix.lower() in (".bag", ".mcap", ".db3")
    return path.is_dir() and (path / "metadata.yaml").is_file()


def resolve_recording(folder: str | Path | None, bag: str | Path | None) -> tuple[Path | None, Path | None]:
    """(recording folder, bag or log path) for what a user gave: a recording folder (its ``bag/``, else its one bag
    under any name or scan log: :func:`find_log`), a bag or a scan log itself as the recording (the folder is then
    the file's), or explicit paths."""
    base = Path(folder) if folder is not None else None
    given = Path(bag) if bag is not None else None
    if base is not None and given is None and _is_bag(base):  # a bag itself as the recording: its folder
        return base.parent, base
    if base is not None and is_scan_log(base):
        if given is not None and given.resolve() != base.resolve():
            raise InputError(f"{base}: a scan log given as the recording and --bag {given} as well; give one")
        return base.parent, base
    if base is not None and given is None and base.is_dir() and not (base / "bag").exists():
        return base, find_log(base)
    return base, given


# --- parsing ------------------------------------------------------------------------------------------------

def _fields(text: str) -> list[str]:
    if "," in text:
        parts = [c.strip() for c in text.split(",")]
        return parts[:-1] if len(parts) > 1 and parts[-1] == "" else parts
    return text.split()


def parse_rows(path: Path) -> tuple[list[int], list[list[str]], int]:
    """The data lines of a log: (line numbers, their fields, number of blank and comment lines).

    Raises InputError: unreadable file, no data line."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: cannot read the scan log: {' '.join(str(err).split())}") from None
    lines, rows, ignored = [], [], 0
    for k, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            ignored += 1
            continue
        lines.append(k)
        rows.append(_fields(s))
    if not rows:
        raise InputError(f"{path}: no data rows (a scan log has one row per scan: time, motor angle, ranges; "
                         f"docs/formats.md \"Scan logs\")")
    return lines, rows, ignored


def numbers(path: Path, line: int, fields: list[str], name: Callable[[int], str]) -> FloatArray:
    """The fields of one line as float64; a field that is not a number is one InputError naming it."""
    try:
        return np.array(fields, dtype=np.float64)
    except ValueError:
        for k, f in enumerate(fields):
            try:
                float(f)
            except ValueError:
                raise InputError(f"{path}:{line}: column {k + 1} ({name(k)}): not a number: {f!r} (fix or delete "
                                 f"the line; comment lines start with #)") from None
        raise


@dataclass(frozen=True)
class LogRows:
    """A scan log as numbers, before masking: times_s (R,) [s], angles (R,) (the motor column as written),
    ranges_m (R, N) [m] (as written: 0, error codes, NaN kept), intensities (R, N) (0 when the log has none),
    mu_rad (N,) every beam's angle, lines (R,) the file's line numbers, header_line (None without header),
    n_ignored_lines (blank and comment lines)."""

    path: Path
    times_s: FloatArray
    angles: FloatArray
    ranges_m: FloatArray
    intensities: FloatArray
    mu_rad: FloatArray
    lines: NDArray[np.int64]
    header_line: int | None
    n_ignored_lines: int

    def evenly_spaced(self) -> tuple[float, float, float]:
        """(angle_min, angle_increment, largest deviation of a beam's angle from that grid) [rad]."""
        n = self.mu_rad.size
        inc = float((self.mu_rad[-1] - self.mu_rad[0]) / (n - 1)) if n > 1 else 0.0
        grid = self.mu_rad[0] + inc * np.arange(n)
        return float(self.mu_rad[0]), inc, float(np.max(np.abs(self.mu_rad - grid)))


def _column_name(layout: LogLayout, n_beams: int | None) -> Callable[[int], str]:
    lead = len(layout.columns)

    def name(k: int) -> str:
        if k < lead:
            return layout.columns[k]
        j = k - lead
        if n_beams is not None and j >= n_beams:
            return f"intensity {j - n_beams + 1}"
        return f"range {j + 1}"

    return name


def load_log(path: str | Path, layout: LogLayout) -> LogRows:
    """Parse a scan log laid out as ``layout`` (module docstring) into :class:`LogRows`.

    Raises:
        InputError: unreadable file, no data row, a value that is not a number, a row with the wrong number of
            columns, a header row whose angles are not finite and strictly monotonic, ranges that look like mm.
    """
    path = Path(path)
    lines, rows, ignored = parse_rows(path)
    lead = len(layout.columns)
    per_beam = 2 if layout.intensities else 1
    header_line = None
    if layout.header == "angles":
        header_line, head = lines[0], rows[0]
        lines, rows = lines[1:], rows[1:]
        n = len(head) - lead
        if n < 2:
            raise InputError(f"{path}:{header_line}: header row has {len(head)} columns: expected {lead} leading "
                             f"({', '.join(layout.columns)}) and then one angle per beam (check log.columns)")
        vals = numbers(path, header_line, head,
                       lambda k: layout.columns[k] if k < lead else f"beam angle {k - lead + 1}")
        mu = vals[lead:] * (math.pi / 180.0 if layout.beam_angle_unit == "deg" else 1.0)
        step = np.diff(mu)
        with np.errstate(invalid="ignore"):
            off = (np.sign(step) != np.sign(mu[-1] - mu[0])) | (step == 0)  # against the overall direction
        bad = np.flatnonzero(~np.isfinite(mu) | np.r_[False, off])
        if bad.size:
            k = int(bad[0])
            raise InputError(f"{path}:{header_line}: column {lead + k + 1} (beam angle {k + 1}): {head[lead + k]!r} "
                             f"breaks the strictly monotonic beam angles of the header row (log.header: angles); "
                             f"fix the row, or use log.header: none with angle_min_rad / angle_increment_rad")
        if not rows:
            raise InputError(f"{path}: only the header row, no scan rows")
    else:
        width = len(rows[0]) - lead
        if width < per_beam or width % per_beam:
            raise InputError(f"{path}:{lines[0]}: {len(rows[0])} columns: expected {lead} leading "
                             f"({', '.join(layout.columns)}) then the ranges"
                             + (" and as many intensities" if layout.intensities else "")
                             + " (check log.columns and log.intensities)")
        n = width // per_beam
        assert layout.angle_min_rad is not None and layout.angle_increment_rad is not None
        mu = layout.angle_min_rad + layout.angle_increment_rad * np.arange(n, dtype=np.float64)
    want = lead + per_beam * n
    name = _column_name(layout, n)
    data = np.empty((len(rows), want))
    for r, (line, fields) in enumerate(zip(lines, rows, strict=True)):
        if len(fields) != want:
            what = f"{lead} leading ({', '.join(layout.columns)}) + {n} ranges" + (
                f" + {n} intensities" if layout.intensities else "")
            first = f"the header row (line {header_line})" if header_line is not None else f"line {lines[0]}"
            raise InputError(f"{path}:{line}: {len(fields)} columns, expected {want} ({what}, as {first}): a cut or "
                             f"merged line? (delete it, or check log.columns / log.intensities)")
        data[r] = numbers(path, line, fields, name)
    ranges = data[:, lead:lead + n] / layout.range_units_per_m()
    pos = ranges[np.isfinite(ranges) & (ranges > 0)]
    if layout.range_unit == "m" and pos.size and float(np.median(pos)) > 100.0:
        raise InputError(f"{path}: log.range_unit: m, but the median range is {float(np.median(pos)):g} m: the log "
                         f"looks like it is in millimetres; set log.range_unit: mm")
    return LogRows(
        path=path, times_s=data[:, layout.columns.index("time")] / layout.time_units_per_s(),
        angles=data[:, layout.columns.index("angle")], ranges_m=ranges,
        intensities=data[:, lead + n:] if layout.intensities else np.zeros_like(ranges), mu_rad=np.asarray(mu),
        lines=np.asarray(lines, dtype=np.int64), header_line=header_line, n_ignored_lines=ignored)


# --- reading ------------------------------------------------------------------------------------------------

def scan_period_s(times_s: FloatArray) -> float:
    """Median time between consecutive rows [s] (0 for fewer than two finite times)."""
    t = np.sort(times_s[np.isfinite(times_s)])
    return float(np.median(np.diff(t))) if t.size > 1 else 0.0


def beam_time_increment_s(rows: LogRows, layout: LogLayout) -> tuple[float, bool]:
    """(time between beams [s], assumed): the rig file's log.time_increment_s, else the scan period over the
    beams per revolution (2 pi / |mean angle step|), the bag reader's rule for time_increment = 0."""
    if layout.time_increment_s is not None:
        return float(layout.time_increment_s), False
    _, inc, _ = rows.evenly_spaced()
    return scan_period_s(rows.times_s) * abs(inc) / (2.0 * math.pi), True


def log_servo(servo: ServoSource | None) -> ServoSource:
    """The rig file's servo keys that apply to a log's angle column (unit, counts_per_rev, sign, offset_rad,
    motion; step unless motion says continuous)."""
    s = servo or ServoSource()
    return ServoSource(topic=None, unit=s.unit, counts_per_rev=s.counts_per_rev, sign=s.sign,
                       offset_rad=s.offset_rad, motion=s.motion or "step")


def describe_layout(layout: LogLayout, n_beams: int) -> str:
    """One line: the columns, the beams and where their angles come from."""
    extra = f" + {n_beams} intensities" if layout.intensities else ""
    where = "header row" if layout.header == "angles" else "rig file"
    return (f"scan log: {', '.join(layout.columns)} ({layout.time_unit}) + {n_beams} ranges ({layout.range_unit})"
            f"{extra}, beam angles from the {where}")


def read_scan_log(
    path: str | Path,
    layout: LogLayout | None,
    servo: ServoSource | None = None,
    *,
    warn: Callable[[str], None] | None = None,
) -> BagData:
    """Read a scan log (module docstring) as a bag is read (lrfcal.io.bag.read_bag).

    Args:
        path: the log; layout: the rig file's ``log:``; servo: the rig file's ``servo:`` (unit, sign, offset_rad,
            motion apply; default rad, step and scan).
        warn: called once with each assumption (default: printed to stderr).
    Returns:
        BagData: Scans (R, N) sorted by time, one JointStates sample per row (the same clock), the ReadReport.
    Raises:
        InputError: no layout, a bad row (named by line and column), no usable row, fewer than two angles.
    """
    path = Path(path)
    if layout is None:
        raise InputError(f"{path}: a scan log needs the rig file's log: section (columns, time_unit, header or "
                         f"angle_min_rad / angle_increment_rad; docs/formats.md \"Scan logs\"); "
                         f"`lrfcal inspect {path}` proposes one")
    warn = warn or (lambda text: print(f"warning: {text}", file=sys.stderr))
    rows = load_log(path, layout)
    a0, inc, _ = rows.evenly_spaced()
    ti, assumed = beam_time_increment_s(rows, layout)
    period = scan_period_s(rows.times_s)
    notes: list[str] = []
    if assumed:
        text = (f"{path}: log.time_increment_s not given: assumed the scan period {period:.4g} s over "
                f"{2 * math.pi / abs(inc):.4g} beams per revolution = {ti:.4g} s per beam (a constant-rate mirror; "
                f"give the scanner's value as log.time_increment_s)")
        warn(text)
        notes.append(text)
    rmax = layout.range_max_m if layout.range_max_m is not None else math.inf
    items = []
    for k in range(rows.times_s.size):
        msg = SimpleNamespace(ranges=rows.ranges_m[k], intensities=rows.intensities[k], angle_min=a0,
                              angle_increment=inc, time_increment=ti, scan_time=period,
                              range_min=layout.range_min_m, range_max=rmax, header=SimpleNamespace(frame_id="laser"))
        items.append((float(rows.times_s[k]), msg))
    where = str(path)
    scans, srep, more = scans_from(items, ScanSource(stamp="receive"), "scan log", where, warn)
    notes.extend(more)
    R, n = rows.ranges_m.shape
    scans = replace(scans, mu_rad=np.broadcast_to(rows.mu_rad, (scans.stamps_s.size, n)).copy(),
                    time_increment_s=np.full(scans.stamps_s.size, ti), source=where)
    src = log_servo(servo)
    ok = np.isfinite(rows.times_s)
    samples = Samples(rows.times_s[ok], rows.times_s[ok], rows.angles[ok], Counter(), True)
    where_servo = f"{path}: column angle"
    joints, _, _, n_used = joints_from(samples, src, scans, srep["recv_s"], where_servo)
    notes.extend(_gap_notes(rows, period))
    notes.extend(timing_notes(scans, joints, where, where_servo))
    if rows.n_ignored_lines:
        notes.append(f"{path}: {rows.n_ignored_lines} blank or comment lines ignored")
    scans = replace(scans, angle_per_scan=src.steps())
    report = ReadReport(
        bag=where, scan_source=describe_layout(layout, n),
        servo_source=f"column angle ({src.unit}, sign {src.sign:+d}, offset {src.offset_rad:g} rad, "
                     f"{'step and scan' if src.steps() else 'continuous motion'})",
        n_scan_messages=R, n_scans=int(scans.stamps_s.size), n_beams=int(np.sum(scans.beam_counts)),
        n_valid_returns=int(np.isfinite(scans.ranges_m).sum()), beam_count_min=n, beam_count_max=n,
        skipped=dict(srep["skipped"]), masked=dict(srep["masked"]), n_time_increment_assumed=R if assumed else 0,
        assumed_time_increment_s=ti if assumed else None, n_servo_messages=R, n_servo_samples=n_used,
        servo_skipped=dict(samples.skipped), clock_offset_s=0.0, clock_offset_applied=False, notes=tuple(notes))
    return BagData(scans=scans, joints=joints, report=report)


def _gap_notes(rows: LogRows, period: float) -> list[str]:
    """Gaps between consecutive rows longer than GAP_PERIODS scan periods (dropped scans), named."""
    t = rows.times_s
    ok = np.flatnonzero(np.isfinite(t))
    if ok.size < 3 or period <= 0:
        return []
    order = ok[np.argsort(t[ok], kind="stable")]
    dt = np.diff(t[order])
    gaps = np.flatnonzero(dt > GAP_PERIODS * period)
    if not gaps.size:
        return []
    big = int(gaps[np.argmax(dt[gaps])])
    return [f"{rows.path}: {gaps.size} gaps longer than {GAP_PERIODS:g} scan periods ({period:.4g} s) between rows "
            f"(dropped scans?); the longest {dt[big]:.4g} s between lines {rows.lines[order[big]]} and "
            f"{rows.lines[order[big + 1]]}"]


__all__ = ["LOOKED_FOR", "LOG_SUFFIXES", "LogRows", "beam_time_increment_s", "describe_layout", "find_log",
           "is_scan_log", "load_log", "log_servo", "numbers", "parse_rows", "read_scan_log", "resolve_recording",
           "scan_period_s"]
