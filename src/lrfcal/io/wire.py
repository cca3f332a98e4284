"""sensor_msgs/LaserScan and sensor_msgs/JointState read from and written to their wire formats with numpy, many
messages at once.

A bag holds thousands of these messages of one layout: the same frame id, beam count, joint names. A generic decoder
(rosbags) builds Python objects field by field for each; here the first message of a run is parsed once (its
:class:`Layout`: where each field sits), every message of the same length whose layout bytes (string lengths, the
strings, the array counts) equal the first's is taken to share that layout, and each field is read as a column of
the (messages, bytes) matrix. Messages that do not parse are left to the caller (lrfcal.io.bag_arrays: rosbags).
Writing is the same in reverse: one message's bytes laid out once, copied M times, the fields written as columns
(:func:`encode_laserscans`, :func:`encode_joint_states`: the simulator's bag, lrfsim.recording).

Wire formats (the message definitions: std_msgs/Header header, then LaserScan's 7 float32 fields, float32[] ranges,
float32[] intensities; JointState's string[] name, float64[] position, velocity, effort):

- ROS 1 serialisation (roscpp serialization.h): little endian, no padding; the header is uint32 seq, time (uint32
  sec, nsec), string frame_id; a string or array is a uint32 count, then its bytes / elements.
- CDR (ROS 2, OMG CDR as rosbag2 stores it): a 4-byte encapsulation header (00 01 xx xx: little endian; big endian
  is left to rosbags), then every primitive aligned to its size from the byte after it; the header is int32 sec,
  uint32 nanosec, string frame_id (uint32 length including a terminating NUL, the bytes, the NUL); a float64 array
  aligns its elements to 8 bytes when it has any.

Both are checked against rosbags' own serialisers, bit for bit (tests/test_bulk_bags.py).

Array shapes: M messages, N the largest beam count, P the largest position count.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: LaserScan's float32 fields in wire order
SCAN_FLOATS = ("angle_min", "angle_max", "angle_increment", "time_increment", "scan_time", "range_min",
               "range_max")


@dataclass(frozen=True)
class Layout:
    """Where the fields of one message sit (byte offsets from the message's start) and what they hold.

    ``checks``: byte ranges [start, stop) that another message of the same length must share to share this layout
    (the encapsulation, the string lengths and strings, the array counts, the padding between them)."""

    stamp_at: int
    frame_id: str
    checks: tuple[tuple[int, int], ...]
    #: LaserScan: the 7 floats, then ranges and intensities (offset, count); JointState: names, position
    floats_at: int = -1
    arrays: tuple[tuple[int, int], ...] = ()
    names: tuple[str, ...] = ()


class _Cursor:
    """Reads one serialised message: CDR (aligned from byte 4) or ROS 1 (unaligned). Raises ValueError on anything
    that is not such a message."""

    def __init__(self, buf: bytes, cdr: bool) -> None:
        self.buf, self.cdr = buf, cdr
        if cdr and (len(buf) < 4 or buf[0] != 0 or buf[1] != 1):
            raise ValueError("not little-endian CDR")
        self.pos = 4  # CDR: after the encapsulation; ROS 1: after the header's seq

    def align(self, n: int) -> None:
        if self.cdr:
            self.pos = 4 + ((self.pos - 4 + n - 1) // n) * n

    def u32(self) -> int:
        self.align(4)
        if self.pos + 4 > len(self.buf):
            raise ValueError("short message")
        (v,) = struct.unpack_from("<I", self.buf, self.pos)
        self.pos += 4
        return int(v)

    def string(self) -> str:
        n = self.u32()
        end = self.pos + n
        if end > len(self.buf) or (self.cdr and (n < 1 or self.buf[end - 1] != 0)):
            raise ValueError("bad string")
        text = self.buf[self.pos:end - 1 if self.cdr else end].decode()
        self.pos = end
        return text

    def array(self, size: int) -> tuple[int, int, int]:
        """(offset of the count, offset of the elements, count) of an array of ``size``-byte elements, skipped."""
        self.align(4)
        count_at = self.pos
        n = self.u32()
        if n:
            self.align(size)
        at = self.pos
        self.pos += n * size
        if self.pos > len(self.buf):
            raise ValueError("array longer than the message")
        return count_at, at, n

    def header(self) -> tuple[int, str]:
        stamp_at = self.pos
        self.pos += 8
        return stamp_at, self.string()


def laserscan_layout(buf: bytes, cdr: bool) -> Layout | None:
    """The layout of one serialised LaserScan, None when it is not one (or big-endian CDR)."""
    try:
        c = _Cursor(buf, cdr)
        stamp_at, frame = c.header()
        c.align(4)
        floats_at = c.pos
        c.pos += 28
        ranges = c.array(4)
        intens = c.array(4)
    except (ValueError, UnicodeDecodeError):
        return None
    if c.pos != len(buf):
        return None
    checks = ((0, 4 if cdr else 0), (stamp_at + 8, floats_at)) + tuple((a[0], a[1]) for a in (ranges, intens))
    return Layout(stamp_at, frame, checks, floats_at, tuple((a[1], a[2]) for a in (ranges, intens)))


def jointstate_layout(buf: bytes, cdr: bool) -> Layout | None:
    """The layout of one serialised JointState, None when it is not one (or big-endian CDR)."""
    try:
        c = _Cursor(buf, cdr)
        stamp_at, frame = c.header()
        names = tuple(c.string() for _ in range(c.u32()))
        names_end = c.pos
        arrays = tuple(c.array(8) for _ in range(3))
    except (ValueError, UnicodeDecodeError):
        return None
    if c.pos != len(buf):
        return None
    checks = ((0, 4 if cdr else 0), (stamp_at + 8, names_end)) + tuple((a[0], a[1]) for a in arrays)
    return Layout(stamp_at, frame, checks, -1, tuple((a[1], a[2]) for a in arrays), names)


def same_layout(mat: NDArray[np.uint8], layout: Layout, first: int, rows: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Which of the rows ``rows`` (k,) of ``mat`` (m, L) (messages of L bytes) share the layout of row ``first``
    (k,)."""
    same = np.ones(rows.size, dtype=bool)
    whole = rows.size == mat.shape[0]  # every row, in order: compared where they lie
    for a, b in layout.checks:
        if b > a:
            part = mat[:, a:b] if whole else mat[rows, a:b]
            same &= (part == mat[first, a:b]).all(axis=1)
    return same


def stamps(mat: NDArray[np.uint8], layout: Layout, cdr: bool) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """header.stamp sec, nanosec (m,) of the rows of ``mat`` that share ``layout``."""
    words = mat[:, layout.stamp_at:layout.stamp_at + 8].view("<u4")
    sec = words[:, 0].view("<i4") if cdr else words[:, 0]
    return sec.astype(np.int64), words[:, 1].astype(np.int64)


def column(mat: NDArray[np.uint8], at: int, count: int, dtype: str) -> NDArray[np.generic]:
    """``count`` elements of ``dtype`` from byte ``at`` of every row of ``mat`` (m, count) (a view)."""
    size = np.dtype(dtype).itemsize
    return mat[:, at:at + count * size].view(dtype)


class _Builder:
    """Writes one message's fixed parts (CDR from byte 4 aligned, or ROS 1) and leaves its values zero."""

    def __init__(self, cdr: bool) -> None:
        self.cdr = cdr
        self.buf = bytearray(b"\x00\x01\x00\x00" if cdr else b"\x00" * 4)  # encapsulation / the header's seq

    def align(self, n: int) -> None:
        if self.cdr:
            self.buf += b"\x00" * (-(len(self.buf) - 4) % n)

    def u32(self, v: int) -> None:
        self.align(4)
        self.buf += struct.pack("<I", v)

    def string(self, text: str) -> None:
        data = text.encode() + (b"\x00" if self.cdr else b"")
        self.u32(len(data))
        self.buf += data

    def array(self, size: int, count: int) -> None:
        self.u32(count)
        if count:
            self.align(size)
        self.buf += b"\x00" * (size * count)


def _filled(template: bytes, layout: Layout | None, m: int, sec: NDArray[np.int64], nanosec: NDArray[np.int64],
            cdr: bool) -> tuple[NDArray[np.uint8], Layout]:
    """``m`` copies (m, L) of a message's bytes with each one's header stamp written in."""
    assert layout is not None
    mat = np.tile(np.frombuffer(template, dtype=np.uint8), (m, 1))
    words = mat[:, layout.stamp_at:layout.stamp_at + 8].view("<u4")
    words[:, 0] = sec.astype("<i4" if cdr else "<u4").view("<u4")
    words[:, 1] = nanosec
    return mat, layout


def encode_laserscans(sec: NDArray[np.int64], nanosec: NDArray[np.int64], frame_id: str, floats: NDArray[np.float32],
                      ranges: NDArray[np.floating], intensities: NDArray[np.floating], cdr: bool = True
                      ) -> NDArray[np.uint8]:
    """M LaserScans of one layout serialised (M, L), row k the bytes rosbags' serialiser gives for message k:
    header stamps ``sec``, ``nanosec`` (M,), ``frame_id``, the float fields (7,) (:data:`SCAN_FLOATS` order, the
    same in every message) or (M, 7), ``ranges`` (M, N) and ``intensities`` (M, K) as float32 (float64 values are
    rounded to float32 as they are written in, as ``astype(np.float32)`` rounds them)."""
    b = _Builder(cdr)
    b.buf += b"\x00" * 8
    b.string(frame_id)
    b.align(4)
    b.buf += b"\x00" * 28
    b.array(4, ranges.shape[1])
    b.array(4, intensities.shape[1])
    mat, layout = _filled(bytes(b.buf), laserscan_layout(bytes(b.buf), cdr), ranges.shape[0], sec, nanosec, cdr)
    column(mat, layout.floats_at, 7, "<f4")[:] = floats
    for (at, n), values in zip(layout.arrays, (ranges, intensities), strict=True):
        column(mat, at, n, "<f4")[:] = values
    return mat


def encode_joint_states(sec: NDArray[np.int64], nanosec: NDArray[np.int64], frame_id: str, names: tuple[str, ...],
                        position: NDArray[np.float64], velocity: NDArray[np.float64], effort: NDArray[np.float64],
                        cdr: bool = True) -> NDArray[np.uint8]:
    """M JointStates of one layout serialised (M, L), row k the bytes rosbags' serialiser gives for message k:
    header stamps ``sec``, ``nanosec`` (M,), ``frame_id``, the joint ``names``, position, velocity and effort
    (M, P), (M, V), (M, E) [rad, rad/s, N m]."""
    b = _Builder(cdr)
    b.buf += b"\x00" * 8
    b.string(frame_id)
    b.u32(len(names))
    for name in names:
        b.string(name)
    for values in (position, velocity, effort):
        b.array(8, values.shape[1])
    mat, layout = _filled(bytes(b.buf), jointstate_layout(bytes(b.buf), cdr), position.shape[0], sec, nanosec, cdr)
    for (at, n), values in zip(layout.arrays, (position, velocity, effort), strict=True):
        column(mat, at, n, "<f8")[:] = values
    return mat


__all__ = ["SCAN_FLOATS", "Layout", "column", "encode_joint_states", "encode_laserscans", "jointstate_layout",
           "laserscan_layout", "same_layout", "stamps"]
