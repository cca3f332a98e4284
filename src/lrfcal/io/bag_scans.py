"""LaserScan messages (and MultiEchoLaserScan) stacked into :class:`~lrfcal.types.Scans`, as the bag reader
(lrfcal.io.bag) and the scan-log reader (lrfcal.io.scanlog) need them.

LaserScan as drivers really fill it (sensor_msgs/LaserScan definition; urg_node; docs/formats.md): each scan
keeps its own angle_min / angle_increment / beam count / time_increment; empty scans and non-finite or zero
increments are skipped; 0.0, NaN, +-inf and values outside [range_min, range_max] are masked (NaN);
``time_increment`` = 0 is replaced by scan_time / beams-per-revolution (2 pi / |angle_increment|, i.e. the
mirror turns at a constant rate through a full revolution per scan_time) with a printed warning. Everything
skipped, masked or assumed is counted.

MultiEchoLaserScan (urg_node's ``echoes`` topic: per beam a LaserEcho of up to 3 ranges and one of as many
intensities) is read as a LaserScan with one return per beam, chosen by the rig file's ``scan.echo``: among the
beam's valid echoes (finite, non-zero, within [range_min, range_max]) the nearest (``first``), the farthest
(``last``) or the one with the highest intensity (``strongest``, the default; the first of equals); a beam
without a valid echo is NaN.

Array shapes: S scans, N beams (the largest beam count).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import InputError
from ..rig import ScanSource
from ..types import Scans
from .bag_messages import get_field, stamp_s
from .multiecho import Echoes

#: one usable scan: (stamp [s], receive time [s], the LaserScan, the message that holds it)
Row = tuple[float, float, Any, Any]


def is_laserscan(obj: Any) -> bool:
    """Has the fields of a sensor_msgs/LaserScan (ranges, angle_min, angle_increment, time_increment)."""
    return all(hasattr(obj, f) for f in ("ranges", "angle_min", "angle_increment", "time_increment"))


def is_multiecho(ls: Any) -> bool:
    """A MultiEchoLaserScan: its ranges are LaserEcho messages (a sequence with ``echoes``), or lrfcal.io.multiecho's
    Echoes."""
    return isinstance(ls.ranges, Echoes) or (len(ls.ranges) > 0 and hasattr(ls.ranges[0], "echoes"))


def select_echo(ranges: Any, intensities: Any, range_min: float, range_max: float, echo: str
                ) -> tuple[np.ndarray, np.ndarray]:
    """One return per beam of a MultiEchoLaserScan (module docstring): ranges (N,) [m] (NaN: no valid echo)
    and intensities (N,) (0 there). ``ranges`` / ``intensities``: the message's LaserEcho[] fields, as decoded
    LaserEcho lists or as lrfcal.io.multiecho.Echoes (intensities may be empty or shorter: 0)."""
    rng, ins = Echoes.of(ranges), Echoes.of(intensities)
    lens = rng.counts
    n = lens.size
    E = int(lens.max()) if n else 0
    r = np.full((n, max(E, 1)), np.nan)
    it = np.zeros((n, max(E, 1)))
    if E:  # every beam's echoes in one array, scattered to (beam, echo); a beam's intensities cut to its echoes
        rows, cols = _slots(lens)
        r[rows, cols] = rng.values
        m = min(ins.counts.size, n)
        ilens = ins.counts[:m]
        if ilens.sum():
            irows, icols = _slots(ilens)
            keep = icols < lens[irows]
            it[irows[keep], icols[keep]] = ins.values[:irows.size][keep]
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


def _slots(lens: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) (sum(lens),) of each element of rows of ``lens`` (B,) elements laid end to end."""
    rows = np.repeat(np.arange(lens.size), lens)
    return rows, np.arange(rows.size) - np.repeat(np.cumsum(lens) - lens, lens)


def scans_from(items: list[tuple[float, Any]], scan: ScanSource, msgtype: str, where: str,
               warn: Callable[[str], None]) -> tuple[Scans, dict[str, Any], list[str]]:
    """Stack LaserScans (each with its own layout) into Scans; count what is skipped, masked, assumed.

    ``items``: (receive time [s], message) in bag order. Returns the Scans sorted by stamp, the counts (keys
    skipped, masked, n_assumed, assumed, recv_s and _kept_items: (stamp, message) of the scans kept) and the notes.
    """
    rows, skipped = _usable_rows(items, scan, msgtype, where)
    S = len(rows)
    scans_ls = [r[2] for r in rows]
    counts = np.array([len(ls.ranges) for ls in scans_ls], dtype=np.int64)
    stamps = np.array([r[0] for r in rows])
    recv = np.array([r[1] for r in rows])
    scan_time = np.array([float(ls.scan_time) for ls in scans_ls])
    rmin = np.array([float(ls.range_min) for ls in scans_ls])
    rmax = np.array([float(ls.range_max) for ls in scans_ls])
    span, span_note = _angle_span(scans_ls, counts, scan, where)
    ranges, intens, mu, t_inc, n_intens_bad = _stack(scans_ls, counts, scan.echo, span)
    # time_increment = 0 (or non-finite): the mirror turns 2 pi per scan_time at a constant rate
    bad_ti = ~np.isfinite(t_inc) | (t_inc == 0.0)
    assumed: float | None = None
    notes: list[str] = [span_note] if span_note else []
    if np.any(bad_ti):
        period = np.where(np.isfinite(scan_time) & (scan_time > 0), scan_time, np.nan)
        fallback = float(np.median(np.diff(stamps))) if S > 1 else 0.0
        period = np.where(np.isfinite(period), period, fallback)
        incs = np.array([abs(float(ls.angle_increment)) for ls in scans_ls])
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
    masked = _mask(ranges, intens, counts, rmin, rmax)
    first = scans_ls[0]
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


def _usable_rows(items: list[tuple[float, Any]], scan: ScanSource, msgtype: str, where: str
                 ) -> tuple[list[Row], Counter[str]]:
    """The scans that can be used, sorted by stamp, and the count of those skipped (by reason)."""
    skipped: Counter[str] = Counter()
    rows: list[Row] = []
    for recv, msg in items:
        ls = get_field(msg, scan.field, where) if scan.field else msg
        if not is_laserscan(ls):
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
    return [rows[k] for k in order], skipped


#: a scan whose angle_max lies this many increments or more from angle_min + (N - 1) angle_increment (and that is
#: not a full revolution) has fields that disagree: which of them is right is the rig file's ``scan.angles``
SPAN_TOLERANCE = 0.5


def _span_off(ls: Any, n: int) -> float:
    """(angle_max - angle_min) / angle_increment - (N - 1) of one scan of N beams: 0 when its fields agree, 0 too for
    a full revolution whose last beam lies one increment before angle_max (a 360 deg scanner); NaN without
    angle_max or with fewer than 2 beams."""
    amax = getattr(ls, "angle_max", None)
    a0, inc = float(ls.angle_min), float(ls.angle_increment)
    if amax is None or n < 2 or not math.isfinite(float(amax)):
        return math.nan
    span = float(amax) - a0
    off = span / inc - (n - 1)
    if abs(off - 1.0) < SPAN_TOLERANCE and abs(abs(span) - 2.0 * math.pi) < 1.5 * abs(inc):
        return 0.0
    return off


def _angle_span(scans: list[Any], counts: np.ndarray, scan: ScanSource, where: str) -> tuple[bool, str]:
    """Whether the beams' bearings come from the span (angle_max - angle_min) / (N - 1) rather than the increment,
    and the note saying so ("" when the scans' fields agree).

    Raises:
        InputError: the fields disagree (median over the scans) and the rig file does not say which to use.
    """
    offs = np.array([_span_off(ls, int(n)) for ls, n in zip(scans, counts, strict=True)])
    finite = np.flatnonzero(np.isfinite(offs))
    off = float(np.median(offs[finite])) if finite.size else 0.0
    if abs(off) < SPAN_TOLERANCE:
        return False, ""
    first = scans[int(finite[0])]
    n = len(first.ranges)
    last = float(first.angle_min) + (n - 1) * float(first.angle_increment)
    what = (f"angle_increment {float(first.angle_increment):.7g} rad puts the last of {n} beams at {last:.6g} rad, "
            f"but angle_max is {float(first.angle_max):.6g} rad ({off:+.2f} increments, median over the scans)")
    if scan.angles is None:
        raise InputError(f"{where}: {what}: the scan's fields disagree (a driver's off-by-one?); set scan.angles in "
                         "the rig file: increment (beam i at angle_min + i angle_increment) or span (at angle_min "
                         "+ i (angle_max - angle_min) / (N - 1))")
    return scan.angles == "span", f"{where}: {what}; the bearings from the {scan.angles} (scan.angles)"


def _stack(scans: list[Any], counts: np.ndarray, echo: str, span: bool = False
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Ranges, intensities and bearings (S, N; padded with NaN, 0) and time increments (S,) of the LaserScans
    (one echo per beam of a MultiEchoLaserScan, :func:`select_echo`), and the number of scans whose intensities
    do not match their ranges (left 0). ``span``: beam i at angle_min + i (angle_max - angle_min) / (N - 1)
    instead of angle_min + i angle_increment."""
    S, N = len(scans), int(counts.max())
    ranges = np.full((S, N), np.nan)
    intens = np.zeros((S, N))
    mu = np.empty((S, N))
    t_inc = np.empty(S)
    idx = np.arange(N)
    n_intens_bad = 0
    for k, ls in enumerate(scans):
        n = counts[k]
        step = (float(ls.angle_max) - float(ls.angle_min)) / max(n - 1, 1) if span else float(ls.angle_increment)
        mu[k] = float(ls.angle_min) + idx * step
        t_inc[k] = float(ls.time_increment)
        if is_multiecho(ls):
            ranges[k, :n], intens[k, :n] = select_echo(ls.ranges, ls.intensities,
                                                       float(ls.range_min), float(ls.range_max), echo)
            continue
        ranges[k, :n] = np.asarray(ls.ranges, dtype=np.float64)
        i = np.asarray(ls.intensities, dtype=np.float64)
        if i.size == n:
            intens[k, :n] = i
        elif i.size:
            n_intens_bad += 1
    return ranges, intens, mu, t_inc, n_intens_bad


def _mask(ranges: np.ndarray, intens: np.ndarray, counts: np.ndarray, rmin: np.ndarray, rmax: np.ndarray
          ) -> Counter[str]:
    """Mask (NaN) the ranges that are no return (0, +-inf, outside [range_min, range_max] of their scan) and zero
    the intensities of padding and non-finite ones, in place; the count of masked values by reason."""
    masked: Counter[str] = Counter()
    pad = np.arange(ranges.shape[1])[None, :] >= counts[:, None]
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
    return masked


__all__ = ["is_laserscan", "is_multiecho", "scans_from", "select_echo"]
