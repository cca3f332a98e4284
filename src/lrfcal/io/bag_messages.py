"""Opening a bag and reading its decoded messages' fields: what the bag reader (lrfcal.io.bag) and ``lrfcal
inspect`` (lrfcal.io.inspection) share.

Messages are decoded with the definitions the bag carries (rosbags' AnyReader registers them from every
connection's message definition, ROS 1 and ROS 2 alike), so custom types need no ROS installation; types a bag
does not define fall back to the ROS 2 Humble store. MultiEchoLaserScan, a scanner's every echo, is decoded with
numpy instead (lrfcal.io.multiecho: a tenth of the time).
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.io import multiecho
from lrfcal.io.multiecho import MULTIECHO_TYPE

LASERSCAN_TYPES = ("sensor_msgs/msg/LaserScan",)
JOINTSTATE_TYPE = "sensor_msgs/msg/JointState"
DYNAMIXEL_JOINTSTATE_TYPE = "dynamixel_msgs/msg/JointState"
TF_TYPE = "tf2_msgs/msg/TFMessage"


def one_line(err: BaseException) -> str:
    """An exception's message on one line (the exception's type name when it has none)."""
    text = " ".join(str(err).split())
    return text or type(err).__name__


def open_reader(path: Path) -> Any:
    """An unopened AnyReader for a ROS 1 .bag file, a ROS 2 bag folder, or a single .mcap/.db3 file."""
    from rosbags.highlevel import AnyReader

    if not path.exists():
        raise InputError(f"{path}: bag not found (no such file or folder; a bag is a ROS 1 .bag file, a ROS 2 bag "
                         "folder or its .mcap/.db3 file, which --bag takes)")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        if (path / "bag").exists():
            raise InputError(f"{path}: a recording folder, not a bag: pass its bag, {path / 'bag'}")
        raise InputError(_not_a_bag_folder(path))
    from lrfcal.io.bag_recover import wal_copy, with_recovery

    read_from, tmp = path, None
    if path.suffix == ".db3" or path.is_dir():
        try:
            copied = wal_copy(path)
        except Exception as err:  # sqlite cannot merge the log
            raise InputError(f"{path}: cannot merge the sqlite write-ahead log beside the .db3 ({one_line(err)}): "
                             f"open the bag once with sqlite3 (it merges the log), or give a complete copy") from None
        if copied is not None:
            read_from, tmp = copied
    try:
        reader = AnyReader([read_from], default_typestore=_HumbleDefaults())  # type: ignore[arg-type]
    except Exception as err:  # rosbags raises several unrelated types for unreadable input
        raise InputError(f"{path}: cannot open bag: {one_line(err)}") from None
    with_recovery(reader)  # a bag cut short is read up to its last complete record (lrfcal.io.bag_recover)
    if tmp is not None:
        wal = (tmp, f"{path}: its sqlite write-ahead log (.db3-wal) not merged (the recorder did not close the bag): "
                    "read from a copy with the log merged")
        setattr(reader, "lrfcal_wal", wal)  # noqa: B010 - read by lrfcal.io.bag_recover (rosbags' reader has no slot)
    return reader


class _HumbleDefaults:
    """AnyReader's default typestore (the types of a bag that defines none), ROS 2 Humble's store loaded only when
    such a bag asks for it: importing it builds some 900 message classes, 0.06 s of every bag read otherwise."""

    @property
    def fielddefs(self) -> Any:
        from rosbags.typesys import Stores, get_typestore

        return get_typestore(Stores.ROS2_HUMBLE).fielddefs


def _not_a_bag_folder(path: Path) -> str:
    """The one line for a folder without metadata.yaml: empty, or holding what (a lone .mcap/.db3 is readable
    by itself)."""
    try:
        names = sorted(p.name for p in path.iterdir())
    except OSError as e:
        return f"{path}: cannot read the bag folder ({e.strerror})"
    if not names:
        return (f"{path}: empty folder, not a ROS 2 bag (a bag folder holds metadata.yaml and its .mcap or .db3 "
                f"file): copy the recording's bag completely, or give the bag's path")
    data = [n for n in names if n.endswith((".mcap", ".db3"))]
    if data:
        return (f"{path}: metadata.yaml missing from the bag folder (it holds {', '.join(data[:3])}): give that file "
                f"itself, {path / data[0]}, or copy the bag folder completely")
    shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    return (f"{path}: not a ROS 2 bag folder (no metadata.yaml; it holds {shown}): give a ROS 2 bag folder, a "
            f".mcap/.db3 file or a ROS 1 .bag file")


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


def decode_message(reader: Any, raw: bytes, msgtype: str) -> Any:
    """A message of an open AnyReader decoded: a MultiEchoLaserScan by lrfcal.io.multiecho (rosbags' decoder where
    that cannot: big-endian CDR), every other type by rosbags."""
    if msgtype == MULTIECHO_TYPE:
        try:
            return multiecho.decode(raw, cdr=reader.is2)
        except (ValueError, struct.error):
            pass
    return reader.deserialize(raw, msgtype)


#: the types read in bulk (lrfcal.io.bag_arrays), with the types their definitions use
BULK_TYPES = {"sensor_msgs/msg/LaserScan": "scan", JOINTSTATE_TYPE: "joint"}
_BULK_USES = ("std_msgs/msg/Header", "builtin_interfaces/msg/Time")


#: rosbags' field definitions of the bulk types and the types they use, as ROS 2 Humble's store holds them
#: (rosbags.interfaces.Nodetype: 1 BASE, 2 NAME, 4 SEQUENCE, an IntEnum equal to these numbers), here so that a bag
#: read need not load that store (:class:`_HumbleDefaults`; tests/test_bulk_bags.py compares them with it)
_BASE, _NAME, _SEQUENCE = 1, 2, 4
_F32, _F64 = (_BASE, ("float32", 0)), (_BASE, ("float64", 0))
BULK_FIELDDEFS: dict[str, tuple[list[Any], list[tuple[str, Any]]]] = {
    "sensor_msgs/msg/LaserScan": ([], [
        ("header", (_NAME, "std_msgs/msg/Header")), ("angle_min", _F32), ("angle_max", _F32),
        ("angle_increment", _F32), ("time_increment", _F32), ("scan_time", _F32), ("range_min", _F32),
        ("range_max", _F32), ("ranges", (_SEQUENCE, (_F32, 0))), ("intensities", (_SEQUENCE, (_F32, 0)))]),
    JOINTSTATE_TYPE: ([], [
        ("header", (_NAME, "std_msgs/msg/Header")), ("name", (_SEQUENCE, ((_BASE, ("string", 0)), 0))),
        ("position", (_SEQUENCE, (_F64, 0))), ("velocity", (_SEQUENCE, (_F64, 0))),
        ("effort", (_SEQUENCE, (_F64, 0)))]),
    "std_msgs/msg/Header": ([], [("stamp", (_NAME, "builtin_interfaces/msg/Time")),
                                 ("frame_id", (_BASE, ("string", 0)))]),
    "builtin_interfaces/msg/Time": ([], [("sec", (_BASE, ("int32", 0))), ("nanosec", (_BASE, ("uint32", 0)))]),
}


def bulk_kind(reader: Any, msgtype: str) -> str | None:
    """"scan" or "joint" when ``msgtype`` is LaserScan or JointState as ROS defines it (the layout lrfcal.io.wire
    reads: the same fields in ROS 1 Noetic and ROS 2 Humble but the header's seq, ROS 1 only), None for every other
    type and for a bag that defines one of them otherwise."""
    kind = BULK_TYPES.get(msgtype)
    if kind is None:
        return None
    have = reader.typestore.fielddefs
    ref = dict(BULK_FIELDDEFS)
    if not reader.is2:
        consts, fields = ref["std_msgs/msg/Header"]
        ref["std_msgs/msg/Header"] = (consts, [("seq", (_BASE, ("uint32", 0))), *fields])
    return kind if all(have.get(t) == ref[t] for t in (msgtype, *_BULK_USES)) else None


def ns_to_s_array(t_ns: NDArray[np.int64]) -> NDArray[np.float64]:
    """:func:`ns_to_s` of each element of ``t_ns`` (M,), to the bit."""
    return (t_ns // 1_000_000_000).astype(np.float64) + 1e-9 * (t_ns % 1_000_000_000).astype(np.float64)


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


__all__ = ["BULK_FIELDDEFS", "BULK_TYPES", "DYNAMIXEL_JOINTSTATE_TYPE", "JOINTSTATE_TYPE", "LASERSCAN_TYPES",
           "MULTIECHO_TYPE", "TF_TYPE", "bulk_kind", "complete_types", "get_field", "ns_to_s", "ns_to_s_array",
           "one_line", "open_reader", "stamp_s"]
