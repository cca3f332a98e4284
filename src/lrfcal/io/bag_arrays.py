"""A topic's LaserScans or JointStates as arrays, whichever way they were decoded.

Two ways lead to the same arrays, to the bit (tests/test_bulk_bags.py):

* in bulk from the serialised messages (:func:`decode_scans`, :func:`decode_joints`): lrfcal.io.wire reads every
  message of one layout at once with numpy; a message it does not recognise (another layout, big-endian CDR, a
  truncated message) is decoded by the ``fallback`` the caller gives (rosbags) and joins the others by its row;
* from decoded message objects (:func:`scans_of`, :func:`joints_of`): rosbags' objects, lrfcal.io.multiecho's
  MultiEchoScan (one echo per beam chosen: lrfcal.io.bag_scans.select_echo), a LaserScan inside a custom message,
  a simulation's messages never serialised.

Array shapes: M messages in bag order, N the largest beam count, K the largest intensity count, P the largest
position count.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.io.bag_raw import RawTopic
from lrfcal.io.wire import SCAN_FLOATS, Layout, column, jointstate_layout, laserscan_layout, same_layout, stamps


@dataclass(frozen=True)
class ScanArrays:
    """LaserScans (M): header stamps ``sec``, ``nanosec`` (M,) (``has_header`` False: the scans have none, 0),
    ``frame_ids`` (M), the float fields (M, 7) in :data:`lrfcal.io.wire.SCAN_FLOATS` order, ``counts`` (M,) beams,
    ``ranges`` (M, N) [m] (NaN past a scan's beams), ``intensity_counts`` (M,), ``intensities`` (M, K) (0 past)."""

    sec: NDArray[np.int64]
    nanosec: NDArray[np.int64]
    frame_ids: list[str]
    floats: NDArray[np.float64]
    counts: NDArray[np.int64]
    ranges: NDArray[np.float64]
    intensity_counts: NDArray[np.int64]
    intensities: NDArray[np.float64]
    has_header: bool = True

    def field(self, name: str) -> NDArray[np.float64]:
        """One of the float fields (M,), by its message name (angle_min, ..., range_max)."""
        return self.floats[:, SCAN_FLOATS.index(name)]

    def stamps_s(self) -> NDArray[np.float64]:
        """header.stamp [s] (M,), rounded as lrfcal.io.bag_messages.stamp_s rounds one."""
        return self.sec.astype(np.float64) + 1e-9 * self.nanosec.astype(np.float64)


@dataclass(frozen=True)
class JointArrays:
    """JointStates (M): header stamps ``sec``, ``nanosec`` (M,), the joint ``names`` of each message,
    ``positions`` (M, P) [rad] (NaN past a message's positions) and ``position_counts`` (M,)."""

    sec: NDArray[np.int64]
    nanosec: NDArray[np.int64]
    names: list[tuple[str, ...]]
    positions: NDArray[np.float64]
    position_counts: NDArray[np.int64]

    def stamps_s(self) -> NDArray[np.float64]:
        """header.stamp [s] (M,), rounded as lrfcal.io.bag_messages.stamp_s rounds one."""
        return self.sec.astype(np.float64) + 1e-9 * self.nanosec.astype(np.float64)


def _padded(rows: Sequence[NDArray[np.float64]], width: int, fill: float) -> NDArray[np.float64]:
    out = np.full((len(rows), width), fill)
    for k, r in enumerate(rows):
        out[k, :r.shape[-1]] = r
    return out


def _stack(parts: Sequence[Any], order: NDArray[np.int64]) -> Any:
    """The parts (all ScanArrays or all JointArrays) as one: row k of the parts laid end to end becomes row
    ``order[k]`` of the result (``order``: a permutation; narrower parts padded as they are)."""
    first = parts[0]
    inverse = np.empty_like(order)
    inverse[order] = np.arange(order.size)

    def cat(name: str, fill: float | None = None) -> Any:
        vals = [getattr(p, name) for p in parts]
        if isinstance(vals[0], list):
            joined = [v for val in vals for v in val]
            return [joined[i] for i in inverse]
        if fill is not None:
            width = max(v.shape[1] for v in vals)
            vals = [np.pad(v, ((0, 0), (0, width - v.shape[1])), constant_values=fill) for v in vals]
        return np.concatenate(vals)[inverse]

    if isinstance(first, ScanArrays):
        return ScanArrays(cat("sec"), cat("nanosec"), cat("frame_ids"), cat("floats"), cat("counts"),
                          cat("ranges", np.nan), cat("intensity_counts"), cat("intensities", 0.0),
                          all(p.has_header for p in parts))
    return JointArrays(cat("sec"), cat("nanosec"), cat("names"), cat("positions", np.nan), cat("position_counts"))


#: layouts read in bulk among the messages of one length; past them (a frame id or joint names that change with
#: every message) the rest is left to the fallback, so that the work stays linear in the messages
MAX_LAYOUTS = 64


def _blocks(raw: RawTopic, parse: Callable[[bytes, bool], Layout | None], cdr: bool
            ) -> tuple[list[tuple[NDArray[np.int64], NDArray[np.uint8], Layout]], list[int]]:
    """The messages cut into blocks of one layout: (their rows, their bytes (m, L), the layout), and the rows that
    do not parse (or lie past :data:`MAX_LAYOUTS`). Messages of one length laid end to end are read where they lie,
    without a copy."""
    sizes, group = np.unique(raw.lengths, return_inverse=True)
    blocks, odd = [], []
    for g, size in enumerate(sizes.tolist()):
        idx = np.arange(len(raw)) if sizes.size == 1 else np.flatnonzero(group == g)
        if sizes.size == 1 and raw.packed():
            mat = np.frombuffer(raw.blob, dtype=np.uint8).reshape(idx.size, size)
        else:
            mat = np.frombuffer(b"".join([raw.message(i) for i in idx.tolist()]), dtype=np.uint8)
            mat = mat.reshape(idx.size, size)
        rest = np.arange(idx.size)
        n_layouts = 0
        while rest.size:
            if n_layouts == MAX_LAYOUTS:
                odd.extend(idx[rest].tolist())
                break
            layout = parse(mat[rest[0]].tobytes(), cdr)
            if layout is None:
                odd.append(int(idx[rest[0]]))
                rest = rest[1:]
                continue
            n_layouts += 1
            same = same_layout(mat, layout, int(rest[0]), rest)
            rows = rest[same]
            blocks.append((idx[rows], mat if rows.size == idx.size else mat[rows], layout))
            rest = rest[~same]
    return blocks, odd


def _scan_block(mat: NDArray[np.uint8], layout: Layout, cdr: bool) -> ScanArrays:
    m = mat.shape[0]
    sec, nanosec = stamps(mat, layout, cdr)
    (r_at, n), (i_at, k) = layout.arrays
    return ScanArrays(sec, nanosec, [layout.frame_id] * m,
                      column(mat, layout.floats_at, 7, "<f4").astype(np.float64),
                      np.full(m, n, dtype=np.int64), column(mat, r_at, n, "<f4").astype(np.float64),
                      np.full(m, k, dtype=np.int64), column(mat, i_at, k, "<f4").astype(np.float64))


def _joint_block(mat: NDArray[np.uint8], layout: Layout, cdr: bool) -> JointArrays:
    m = mat.shape[0]
    sec, nanosec = stamps(mat, layout, cdr)
    p_at, n = layout.arrays[0]
    return JointArrays(sec, nanosec, [layout.names] * m, column(mat, p_at, n, "<f8").astype(np.float64),
                       np.full(m, n, dtype=np.int64))


def _decode(raw: RawTopic, cdr: bool, parse: Callable[[bytes, bool], Layout | None],
            block: Callable[[NDArray[np.uint8], Layout, bool], Any], of: Callable[[list[Any]], Any],
            fallback: Callable[[int], Any]) -> Any:
    blocks, odd = _blocks(raw, parse, cdr)
    parts = [block(mat, layout, cdr) for _, mat, layout in blocks]
    rows = [idx for idx, _, _ in blocks]
    if odd:
        parts.append(of([fallback(i) for i in odd]))
        rows.append(np.array(odd, dtype=np.int64))
    if len(parts) == 1 and np.array_equal(rows[0], np.arange(len(raw))):
        return parts[0]
    return _stack(parts, np.concatenate(rows))


def decode_scans(raw: RawTopic, cdr: bool, fallback: Callable[[int], Any]) -> ScanArrays:
    """The serialised sensor_msgs/LaserScans ``raw`` (M; CDR or ROS 1) as arrays; ``fallback(i)`` decodes message
    i where lrfcal.io.wire does not recognise it (rosbags). M >= 1."""
    return _decode(raw, cdr, laserscan_layout, _scan_block, scans_of, fallback)


def decode_joints(raw: RawTopic, cdr: bool, fallback: Callable[[int], Any]) -> JointArrays:
    """The serialised sensor_msgs/JointStates ``raw`` (M; CDR or ROS 1) as arrays; ``fallback`` as in
    :func:`decode_scans`. M >= 1."""
    return _decode(raw, cdr, jointstate_layout, _joint_block, joints_of, fallback)


Pick = Callable[[Any], "tuple[NDArray[np.float64], NDArray[np.float64]] | None"]


def scans_of(lasers: Sequence[Any], pick: Pick | None = None) -> ScanArrays:
    """Decoded LaserScans (objects with the message's fields; angle_max may be missing: NaN; M >= 1) as arrays.
    ``pick(scan)``: its ranges and intensities (N,) where they are not the fields themselves (one echo per beam of a
    MultiEchoLaserScan: lrfcal.io.bag_scans.laser_arrays), None where they are."""
    ranges, intens = [], []
    for ls in lasers:
        picked = pick(ls) if pick is not None else None
        r, i = picked if picked is not None else (np.asarray(ls.ranges, dtype=np.float64),
                                                  np.asarray(ls.intensities, dtype=np.float64))
        ranges.append(r)
        intens.append(i)
    counts = np.array([r.size for r in ranges], dtype=np.int64)
    icounts = np.array([i.size for i in intens], dtype=np.int64)
    has_header = all(getattr(getattr(ls, "header", None), "stamp", None) is not None for ls in lasers)
    sec = np.array([int(ls.header.stamp.sec) if has_header else 0 for ls in lasers], dtype=np.int64)
    nanosec = np.array([int(ls.header.stamp.nanosec) if has_header else 0 for ls in lasers], dtype=np.int64)
    return ScanArrays(sec, nanosec, [str(ls.header.frame_id) if hasattr(ls, "header") else "" for ls in lasers],
                      np.array([[_float(ls, f) for f in SCAN_FLOATS] for ls in lasers]).reshape(-1, 7),
                      counts, _padded(ranges, int(counts.max(initial=0)), np.nan), icounts,
                      _padded(intens, int(icounts.max(initial=0)), 0.0), has_header)


def _float(ls: Any, name: str) -> float:
    """A float field of a decoded LaserScan; a missing angle_max (a scan log's rows) is NaN."""
    v = getattr(ls, name, None) if name == "angle_max" else getattr(ls, name)
    return math.nan if v is None else float(v)


def joints_of(messages: Sequence[Any]) -> JointArrays:
    """Decoded sensor_msgs/JointStates (M >= 1) as arrays."""
    pos = [np.asarray(m.position, dtype=np.float64) for m in messages]
    counts = np.array([p.size for p in pos], dtype=np.int64)
    return JointArrays(np.array([int(m.header.stamp.sec) for m in messages], dtype=np.int64),
                       np.array([int(m.header.stamp.nanosec) for m in messages], dtype=np.int64),
                       [tuple(str(n) for n in m.name) for m in messages],
                       _padded(pos, int(counts.max(initial=0)), np.nan), counts)


__all__ = ["MAX_LAYOUTS", "JointArrays", "ScanArrays", "decode_joints", "decode_scans", "joints_of", "scans_of"]
