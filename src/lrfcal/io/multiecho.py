"""sensor_msgs/MultiEchoLaserScan read from and written to its wire format with numpy.

urg_node publishes the UTM-30LX-EW's separate echoes as a MultiEchoLaserScan (its ``echoes`` topic): per beam a
sensor_msgs/LaserEcho (a float32[] of up to 3 ranges) and one of as many intensities. A generic decoder (rosbags)
makes 2 x 1080 LaserEcho objects per message: about 2 ms each, 50 s for a 10-minute recording at 40 Hz. Here a
message's LaserEcho arrays become :class:`Echoes`, each beam's echo count and all the echoes in one flat array, in
about a tenth of that; rosbags still opens the bag and decodes every other type.

Wire formats (the message definition: header, 7 float32 fields, LaserEcho[] ranges, LaserEcho[] intensities; a
LaserEcho is float32[] echoes):

- ROS 1 serialisation: little endian, no padding; the header is uint32 seq, time (uint32 sec, nsec), string frame_id
  (uint32 length, then the bytes).
- CDR (ROS 2, rosbag2): a 4-byte encapsulation header (00 01 00 00: CDR little endian; big endian is left to
  rosbags), then the fields aligned to their size from the byte after it; the header is int32 sec, uint32 nanosec,
  string frame_id (uint32 length including a terminating NUL, the bytes, the NUL). After the string every field is
  a 4-byte word, so the rest of the message is words from the first 4-aligned offset on.

Both are checked against rosbags' own serialisers (tests/test_multiecho.py).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

MULTIECHO_TYPE = "sensor_msgs/msg/MultiEchoLaserScan"
_FLOATS = ("angle_min", "angle_max", "angle_increment", "time_increment", "scan_time", "range_min", "range_max")
_CDR_LE = b"\x00\x01\x00\x00"
_ECHOES = (4, ((2, "sensor_msgs/msg/LaserEcho"), 0))  # rosbags.interfaces.Nodetype: 1 BASE, 2 NAME, 4 SEQUENCE
#: rosbags' field definitions of MultiEchoLaserScan and LaserEcho as ROS 2 Humble's store holds them (its header:
#: lrfcal.io.bag_messages.BULK_FIELDDEFS), so that writing one need not load that store (tests/test_multiecho.py)
FIELDDEFS: dict[str, tuple[list[Any], list[tuple[str, Any]]]] = {
    MULTIECHO_TYPE: ([], [("header", (2, "std_msgs/msg/Header")), *((f, (1, ("float32", 0))) for f in _FLOATS),
                          ("ranges", _ECHOES), ("intensities", _ECHOES)]),
    "sensor_msgs/msg/LaserEcho": ([], [("echoes", (4, ((1, ("float32", 0)), 0)))]),
}


@dataclass(frozen=True)
class Echoes:
    """A LaserEcho[] field: ``counts`` (N,) the echoes of each beam, ``values`` (sum(counts),) float32, beam by beam.
    Its length is the number of beams, as the field's is."""

    counts: NDArray[np.int64]
    values: NDArray[np.float32]

    def __len__(self) -> int:
        return int(self.counts.size)

    @staticmethod
    def of(field: Any) -> Echoes:
        """The Echoes of a decoded LaserEcho[] (objects with ``echoes``) or of Echoes (returned as they are)."""
        if isinstance(field, Echoes):
            return field
        counts = np.array([len(e.echoes) for e in field], dtype=np.int64)
        values = (np.concatenate([np.asarray(e.echoes, dtype=np.float32) for e in field]) if counts.sum()
                  else np.zeros(0, dtype=np.float32))
        return Echoes(counts, values)

    @staticmethod
    def of_rows(rows: NDArray[np.floating], keep: NDArray[np.bool_]) -> Echoes:
        """The Echoes of (N, E) values where ``keep`` (N, E) marks a beam's echoes (kept in row order)."""
        return Echoes(keep.sum(axis=1).astype(np.int64), np.asarray(rows, dtype=np.float32)[keep])


@dataclass(frozen=True)
class Stamp:
    sec: int
    nanosec: int


@dataclass(frozen=True)
class Header:
    stamp: Stamp
    frame_id: str


@dataclass(frozen=True)
class MultiEchoScan:
    """A decoded MultiEchoLaserScan: the fields of the message definition, LaserEcho[] as :class:`Echoes`. The float
    fields hold float32 values."""

    header: Any  # .stamp.sec, .stamp.nanosec, .frame_id
    angle_min: float
    angle_max: float
    angle_increment: float
    time_increment: float
    scan_time: float
    range_min: float
    range_max: float
    ranges: Echoes
    intensities: Echoes


def decode(raw: bytes | memoryview, cdr: bool) -> MultiEchoScan:
    """A MultiEchoLaserScan from its ROS 1 (``cdr`` False) or CDR little-endian serialisation.

    Raises:
        ValueError: not such a message (too short, inconsistent lengths) or big-endian CDR.
    """
    buf = bytes(raw)
    if cdr:
        if buf[:4] != _CDR_LE:
            raise ValueError(f"CDR encapsulation {buf[:4].hex()} is not little endian")
        sec, nanosec, n = struct.unpack_from("<iII", buf, 4)
        frame = buf[16:16 + n - 1] if n else b""
        off = 4 + _align4(12 + n)
    else:
        _seq, sec, nanosec, n = struct.unpack_from("<4I", buf, 0)
        frame = buf[16:16 + n]
        off = 16 + n
    a_min, a_max, a_inc, t_inc, scan_time, r_min, r_max = struct.unpack_from("<7f", buf, off)
    ranges, off = _echoes(buf, off + 28)
    intensities, off = _echoes(buf, off)
    if off != len(buf):
        raise ValueError(f"{len(buf) - off} bytes after the intensities")
    return MultiEchoScan(Header(Stamp(int(sec), int(nanosec)), frame.decode()), a_min, a_max, a_inc, t_inc, scan_time,
                         r_min, r_max, ranges, intensities)


def _align4(n: int) -> int:
    return (n + 3) & ~3


def _echoes(buf: bytes, off: int) -> tuple[Echoes, int]:
    """The LaserEcho[] starting at byte ``off`` of ``buf`` and the offset after it."""
    words = np.frombuffer(buf, dtype="<u4", offset=off, count=(len(buf) - off) // 4)
    w = words.tolist()
    n = w[0]
    counts = [0] * n
    p = 1
    for b in range(n):  # each beam's count, then its echoes: the counts are found one after the other
        c = w[p]
        counts[b] = c
        p += 1 + c
    if p > len(w):
        raise ValueError("LaserEcho[] longer than the message")
    cnt = np.array(counts, dtype=np.int64)
    values = words[:p][~_count_words(cnt)].view("<f4").astype(np.float32)
    return Echoes(cnt, values), off + 4 * p


def _count_words(counts: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Which words (1 + N + sum(counts),) of a LaserEcho[] of beams with ``counts`` (N,) echoes are counts: the first
    (the beam count), and beam b's at 1 + sum_{c < b} (1 + counts_c)."""
    is_count = np.zeros(1 + counts.size + int(counts.sum()), dtype=bool)
    is_count[0] = True
    is_count[np.cumsum(counts + 1) - counts] = True
    return is_count


def encode_cdr(msg: MultiEchoScan) -> bytes:
    """The CDR little-endian serialisation of ``msg`` (the bytes rosbags' serialize_cdr gives for the same message)."""
    st = msg.header.stamp
    frame = msg.header.frame_id.encode() + b"\x00"
    head = struct.pack("<iII", int(st.sec), int(st.nanosec), len(frame)) + frame
    head += b"\x00" * (_align4(len(head)) - len(head))
    floats = struct.pack("<7f", *(float(getattr(msg, f)) for f in _FLOATS))
    return b"".join((_CDR_LE, head, floats, _echo_words(msg.ranges), _echo_words(msg.intensities)))


def _echo_words(e: Echoes) -> bytes:
    """A LaserEcho[] as words: the beam count, then each beam's count and its echoes."""
    is_count = _count_words(e.counts)
    words = np.empty(is_count.size, dtype="<u4")
    words[is_count] = np.r_[e.counts.size, e.counts]
    words[~is_count] = np.asarray(e.values, dtype="<f4").view("<u4")
    return words.tobytes()


__all__ = ["FIELDDEFS", "MULTIECHO_TYPE", "Echoes", "Header", "MultiEchoScan", "Stamp", "decode", "encode_cdr"]
