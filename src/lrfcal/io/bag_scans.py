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
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.io.bag_arrays import ScanArrays, scans_of
from lrfcal.io.bag_messages import get_field, stamp_s
from lrfcal.io.multiecho import Echoes
from lrfcal.io.rig import ScanSource
from lrfcal.types import Scans


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
    """:func:`scans_from_arrays` of decoded messages ``items`` (receive time [s], message) in bag order."""
    recv = np.array([t for t, _ in items], dtype=np.float64)
    return scans_from_arrays(laser_arrays([m for _, m in items], scan, msgtype, where), recv, scan, where, warn)


def laser_arrays(messages: list[Any], scan: ScanSource, msgtype: str, where: str) -> ScanArrays:
    """The LaserScans of decoded messages (the message itself, or its field ``scan.field``) as arrays.

    Raises:
        InputError: not a LaserScan (or no ``scan.field``), or no header.stamp when the scans' stamps are wanted.
    """
    lasers = []
    for msg in messages:
        ls = get_field(msg, scan.field, where) if scan.field else msg
        if not is_laserscan(ls):
            what = f"field {scan.field}" if scan.field else f"type {msgtype}"
            raise InputError(f"{where}: {what}: not a sensor_msgs/LaserScan (set scan.field to the LaserScan "
                             f"inside the message)")
        if scan.stamp != "receive" and stamp_s(ls) is None:
            raise InputError(f"{where}: header: the scan has no header.stamp; use scan.stamp: receive")
        lasers.append(ls)

    def pick(ls: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        if not is_multiecho(ls):
            return None
        return select_echo(ls.ranges, ls.intensities, float(ls.range_min), float(ls.range_max), scan.echo)

    return scans_of(lasers, pick)


def scans_from_arrays(arrays: ScanArrays, recv_s: NDArray[np.float64], scan: ScanSource, where: str,
                      warn: Callable[[str], None]) -> tuple[Scans, dict[str, Any], list[str]]:
    """Stack a topic's LaserScans (each with its own layout; ``arrays``, received at ``recv_s`` (M,) [s], in bag
    order) into Scans; count what is skipped, masked, assumed. ``arrays``' ranges may be reused.

    Returns the Scans sorted by stamp, the counts (keys skipped, masked, n_assumed, assumed, recv_s and _kept_rows:
    the rows of ``arrays`` kept, in the Scans' order) and the notes.
    """
    rows, skipped = _usable_rows(arrays, recv_s, scan, where)
    S = rows.size
    every = arrays.counts.size == S and bool(np.all(rows == np.arange(S)))

    def kept(a: NDArray[Any]) -> NDArray[Any]:
        return a if every else a[rows]

    counts = kept(arrays.counts)
    stamps = kept(recv_s if scan.stamp == "receive" else arrays.stamps_s())
    recv = kept(recv_s)
    floats = kept(arrays.floats)
    a0, amax, inc = floats[:, 0], floats[:, 1], floats[:, 2]
    t_inc, scan_time, rmin, rmax = (floats[:, k].copy() for k in (3, 4, 5, 6))
    span, span_note = _angle_span(a0, amax, inc, counts, scan, where)
    N = int(counts.max())
    ranges = np.ascontiguousarray(kept(arrays.ranges)[:, :N])
    step = (amax - a0) / np.maximum(counts - 1, 1) if span else inc
    mu = _bearings(a0, step, N)
    icounts = kept(arrays.intensity_counts)
    good = icounts == counts
    n_intens_bad = int(np.sum(~good & (icounts > 0)))
    if good.all() and arrays.intensities.shape[1] >= N:
        intens = np.ascontiguousarray(kept(arrays.intensities)[:, :N])
    else:
        intens = np.zeros((S, N))
        width = min(N, arrays.intensities.shape[1])
        intens[:, :width] = np.where(good[:, None], kept(arrays.intensities)[:, :width], 0.0)
    # time_increment = 0 (or non-finite): the mirror turns 2 pi per scan_time at a constant rate
    bad_ti = ~np.isfinite(t_inc) | (t_inc == 0.0)
    assumed: float | None = None
    notes: list[str] = [span_note] if span_note else []
    if np.any(bad_ti):
        period = np.where(np.isfinite(scan_time) & (scan_time > 0), scan_time, np.nan)
        fallback = float(np.median(np.diff(stamps))) if S > 1 else 0.0
        period = np.where(np.isfinite(period), period, fallback)
        per_rev = 2.0 * math.pi / np.abs(inc)
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
    scans = Scans(
        stamps_s=stamps, ranges_m=ranges, intensities=intens, mu_rad=mu, time_increment_s=t_inc,
        scan_time_s=float(np.median(scan_time)),
        range_min_m=float(np.nanmax(rmin)) if np.isfinite(rmin).any() else 0.0,
        range_max_m=float(np.nanmin(rmax)) if np.isfinite(rmax).any() else math.inf,
        frame_id=arrays.frame_ids[int(rows[0])], source=where, beam_counts=counts,
    )
    rep = {"skipped": skipped, "masked": masked, "n_assumed": int(bad_ti.sum()), "assumed": assumed,
           "recv_s": recv, "_kept_rows": rows}
    return scans, rep, notes


def _bearings(a0: NDArray[np.float64], step: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """Beam i's bearing angle_min + i step (S, n) [rad] of each scan; computed once when every scan has the same
    angle_min and step (a scanner's driver: the same bits)."""
    if a0.size and np.all(a0 == a0[0]) and np.all(step == step[0]):
        row = a0[0] + np.arange(n) * step[0]
        mu = np.empty((a0.size, n))
        mu[:] = row
        return mu
    mu = np.multiply(np.arange(n)[None, :], step[:, None])
    mu += a0[:, None]
    return mu


def _usable_rows(arrays: ScanArrays, recv_s: NDArray[np.float64], scan: ScanSource, where: str
                 ) -> tuple[NDArray[np.int64], Counter[str]]:
    """The rows of the scans that can be used, sorted by stamp (stable), and the count of those skipped (by
    reason)."""
    n = arrays.counts
    t = recv_s if scan.stamp == "receive" else arrays.stamps_s()
    a0, inc = arrays.field("angle_min"), arrays.field("angle_increment")
    empty = n == 0
    bad_inc = ~empty & ~(np.isfinite(inc) & (inc != 0.0))
    bad_a0 = ~empty & ~bad_inc & ~np.isfinite(a0)
    bad_t = ~empty & ~bad_inc & ~bad_a0 & ~np.isfinite(t)
    skipped: Counter[str] = Counter({k: int(v.sum()) for k, v in (("empty", empty), ("bad_angle_increment", bad_inc),
                                                                   ("bad_angle_min", bad_a0), ("bad_stamp", bad_t))
                                     if v.any()})
    rows = np.flatnonzero(~(empty | bad_inc | bad_a0 | bad_t))
    if not rows.size:
        raise InputError(f"{where}: no usable scan in {n.size} messages (skipped: "
                         f"{', '.join(f'{k} {v}' for k, v in sorted(skipped.items()))})")
    return rows[np.argsort(t[rows], kind="stable")], skipped


#: a scan whose angle_max lies this many increments or more from angle_min + (N - 1) angle_increment (and that is
#: not a full revolution) has fields that disagree: which of them is right is the rig file's ``scan.angles``
SPAN_TOLERANCE = 0.5


def _span_offs(a0: NDArray[np.float64], amax: NDArray[np.float64], inc: NDArray[np.float64],
               counts: NDArray[np.int64]) -> NDArray[np.float64]:
    """(angle_max - angle_min) / angle_increment - (N - 1) of each scan of N beams: 0 when its fields agree, 0 too
    for a full revolution whose last beam lies one increment before angle_max (a 360 deg scanner); NaN without
    angle_max or with fewer than 2 beams."""
    with np.errstate(invalid="ignore", divide="ignore"):
        span = amax - a0
        off = span / inc - (counts - 1).astype(np.float64)
        full = (np.abs(off - 1.0) < SPAN_TOLERANCE) & (np.abs(np.abs(span) - 2.0 * math.pi) < 1.5 * np.abs(inc))
    off = np.where(full, 0.0, off)
    return np.where((counts < 2) | ~np.isfinite(amax), np.nan, off)


def _angle_span(a0: NDArray[np.float64], amax: NDArray[np.float64], inc: NDArray[np.float64],
                counts: NDArray[np.int64], scan: ScanSource, where: str) -> tuple[bool, str]:
    """Whether the beams' bearings come from the span (angle_max - angle_min) / (N - 1) rather than the increment,
    and the note saying so ("" when the scans' fields agree).

    Raises:
        InputError: the fields disagree (median over the scans) and the rig file does not say which to use.
    """
    offs = _span_offs(a0, amax, inc, counts)
    finite = np.flatnonzero(np.isfinite(offs))
    off = float(np.median(offs[finite])) if finite.size else 0.0
    if abs(off) < SPAN_TOLERANCE:
        return False, ""
    k = int(finite[0])
    n = int(counts[k])
    first_min, first_inc, first_max = float(a0[k]), float(inc[k]), float(amax[k])
    last = first_min + (n - 1) * first_inc
    what = (f"angle_increment {first_inc:.7g} rad puts the last of {n} beams at {last:.6g} rad, "
            f"but angle_max is {first_max:.6g} rad ({off:+.2f} increments, median over the scans)")
    if scan.angles is None:
        raise InputError(f"{where}: {what}: the scan's fields disagree (a driver's off-by-one?); set scan.angles in "
                         "the rig file: increment (beam i at angle_min + i angle_increment) or span (at angle_min "
                         "+ i (angle_max - angle_min) / (N - 1))")
    return scan.angles == "span", f"{where}: {what}; the bearings from the {scan.angles} (scan.angles)"


def _mask(ranges: np.ndarray, intens: np.ndarray, counts: np.ndarray, rmin: np.ndarray, rmax: np.ndarray
          ) -> Counter[str]:
    """Mask (NaN) the C-contiguous ranges that are no return (0, +-inf, outside [range_min, range_max] of their
    scan) and zero the intensities of padding and non-finite ones, in place; the count of masked values by reason.

    Only the values outside [range_min, range_max] (NaN, infinite, zero or not, a few in a scan) are looked at
    one by one: a pass over the (S, N) values finds them."""
    big = np.finfo(np.float64).max
    with np.errstate(invalid="ignore"):
        inside = ranges >= np.maximum(rmin, -big)[:, None]
        inside &= ranges <= np.minimum(rmax, big)[:, None]
        if not np.all(rmin > 0.0):  # a zero is no return even where range_min allows it
            inside &= ranges != 0.0
    flat = ranges.reshape(-1)  # a view: ranges is C-contiguous
    at = np.flatnonzero(np.logical_not(inside, out=inside))
    rows, cols = np.divmod(at, ranges.shape[1])
    v = flat[at]
    valid = cols < counts[rows]  # not padding
    with np.errstate(invalid="ignore"):
        zero = (v == 0.0) & valid
        nan = np.isnan(v) & valid
        inf = np.isinf(v)
        low = np.isfinite(v) & ~zero & (v < rmin[rows])
        high = np.isfinite(v) & (v > rmax[rows])
    masked: Counter[str] = Counter()
    for name, m in (("zero", zero), ("nan", nan), ("inf", inf), ("below_range_min", low),
                    ("above_range_max", high)):
        c = int(m.sum())
        if c:
            masked[name] = c
    flat[at[zero | inf | low | high]] = np.nan
    bad = ~np.isfinite(intens)
    if bad.any():
        intens[bad] = 0.0
    if counts.min() < ranges.shape[1]:
        intens[np.arange(ranges.shape[1])[None, :] >= counts[:, None]] = 0.0
    return masked


__all__ = ["is_laserscan", "is_multiecho", "laser_arrays", "scans_from", "scans_from_arrays", "select_echo"]
