"""A ROS 2 bag (rosbag2 version 9, MCAP storage) written in bulk: the folder rosbags' Writer writes, byte for byte.

rosbags' ``Writer`` (rosbags.rosbag2, 0.11) costs about 6 us of Python per message: a record assembled field by
field for each. Here every message record's 31-byte head (opcode, length, channel id, sequence, log and publish
time) is one row of a numpy structured array, the records are split into chunks where rosbags splits them (a chunk
is closed after the message that takes its content past 1 MiB) and each chunk's data is one ``bytes.join`` of the
heads and the messages' bytes (rows of a (messages, bytes) matrix when a topic's messages are all of one length,
as lrfcal.io.wire.encode_laserscans gives them; any bytes-like objects otherwise).

The file, as the MCAP specification (https://mcap.dev/spec) defines its records and rosbags fills them:

* magic, Header (profile ``ros2``, library ``rosbags-<version>``: the writer whose file this is, byte for byte);
* the chunks (uncompressed, CRC 0): the first holds, before its messages, a Channel record per topic (ids from 1,
  ``cdr``, metadata ``offered_qos_profiles``: none), each after its type's Schema record when the type is new
  (ids from 1); each chunk is followed by its MessageIndex records, one per channel in the order the channel first
  appears in the chunk, entries in the order written;
* Metadata ``rosbag2`` (``serialized_metadata``: rosbag2's metadata of the bag), DataEnd (CRC 0);
* the summary: Schemas, Channels, ChunkIndexes, MetadataIndex, Statistics (every channel's count, sorted by id),
  SummaryOffsets; Footer (CRC 0), magic;

and beside it ``metadata.yaml`` as rosbags dumps it (ruamel.yaml, safe, block style). Message sequence numbers are
0 and publish times equal the log times, as rosbags writes them. tests/test_bulk_bags.py compares both files with
those rosbags' Writer writes for the same messages.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from io import StringIO
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.io.bag_raw import INDEX_OP, MESSAGE_HEAD, MESSAGE_OP

MAGIC = b"\x89MCAP0\r\n"
#: a chunk is closed after the message that takes its content past this size [bytes] (rosbags' McapWriter)
CHUNK_BYTES = 2**20
_NO_TIME = 2**63 - 1  # rosbags' start time of a chunk (and of a bag) without messages
_ENTRY = np.dtype([("log", "<u8"), ("offset", "<u8")])  # a MessageIndex entry
_IDL = "=" * 80 + "\nIDL: "
#: the offered QoS profiles of a topic that declares none, as rosbags' Writer dumps them
_NO_QOS = "[]"

#: a topic's messages: rows of one length (n, L) uint8, or one bytes-like object each (n,)
Messages = NDArray[np.uint8] | Sequence[bytes | memoryview]


@dataclass(frozen=True)
class BagTopic:
    """One connection of the bag: ``topic``, ``msgtype`` and the type's definition (``msgdef``, ROS 2 .msg text
    with its dependencies, as rosbags generates it) and hash (``rihs01``, ``RIHS01_<sha256>``)."""

    topic: str
    msgtype: str
    msgdef: str
    rihs01: str

    @staticmethod
    def of(topic: str, msgtype: str, typestore: Any) -> BagTopic:
        """The connection rosbags' ``Writer.add_connection(topic, msgtype, typestore=typestore)`` adds."""
        msgdef, _ = typestore.generate_msgdef(msgtype, ros_version=2)
        return BagTopic(topic, msgtype, msgdef, typestore.hash_rihs01(msgtype))

    @staticmethod
    def humble(topic: str, msgtype: str) -> BagTopic:
        """:meth:`of` with ROS 2 Humble's store; LaserScan, JointState and MultiEchoLaserScan (the simulator's)
        from their definitions in lrfcal.io, without loading that store (some 900 message classes, 0.04 s)."""
        store = _known_types()
        if msgtype not in store.fielddefs:
            from rosbags.typesys import Stores, get_typestore

            store = get_typestore(Stores.ROS2_HUMBLE)
        return BagTopic.of(topic, msgtype, store)


@lru_cache(maxsize=1)
def _known_types() -> Any:
    """A type store of lrfcal.io's copies of ROS 2 Humble's definitions (bag_messages.BULK_FIELDDEFS,
    multiecho.FIELDDEFS; tests/test_bulk_bags.py and tests/test_multiecho.py compare them with Humble's)."""
    from rosbags.typesys import Stores, get_typestore

    from lrfcal.io.bag_messages import BULK_FIELDDEFS
    from lrfcal.io.multiecho import FIELDDEFS

    store = get_typestore(Stores.EMPTY)
    store.register({**BULK_FIELDDEFS, **FIELDDEFS})
    return store


def _string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def _record(op: int, body: bytes) -> bytes:
    return struct.pack("<BQ", op, len(body)) + body


def _schemas_and_channels(topics: Sequence[BagTopic]) -> tuple[list[bytes], list[bytes], bytes]:
    """The Schema records (one per type, ids from 1 in the order first named), the Channel records (ids from 1)
    and both as the first chunk holds them: each topic's channel after its type's schema when that is new."""
    schema_ids: dict[str, int] = {}
    schemas, channels, both = [], [], []
    qos = _string("offered_qos_profiles") + _string(_NO_QOS)
    for cid, t in enumerate(topics, start=1):
        if t.msgtype not in schema_ids:
            schema_ids[t.msgtype] = len(schema_ids) + 1
            encoding = "ros2idl" if t.msgdef.startswith(_IDL) else "ros2msg"
            schemas.append(_record(0x03, struct.pack("<H", schema_ids[t.msgtype]) + _string(t.msgtype)
                                   + _string(encoding) + _string(t.msgdef)))
            both.append(schemas[-1])
        channels.append(_record(0x04, struct.pack("<HH", cid, schema_ids[t.msgtype]) + _string(t.topic)
                                + _string("cdr") + struct.pack("<I", len(qos)) + qos))
        both.append(channels[-1])
    return schemas, channels, b"".join(both)


def _payloads(messages: Sequence[Messages]) -> tuple[list[Any], NDArray[np.int64], NDArray[np.int64]]:
    """Every message's bytes (topic by topic), each one's length and where each topic's messages begin (T+1,)."""
    views: list[Any] = []
    lengths = []
    for m in messages:
        if isinstance(m, np.ndarray):
            rows, width = m.shape
            flat = np.ascontiguousarray(m, dtype=np.uint8).reshape(-1).data
            views += [flat[a:a + width] for a in range(0, rows * width, width)]
            lengths.append(np.full(rows, width, dtype=np.int64))
        else:
            some = [v if isinstance(v, bytes) else memoryview(v).cast("B") for v in m]
            views += some
            lengths.append(np.fromiter(map(len, some), dtype=np.int64, count=len(some)))
    counts = [len(n) for n in lengths]
    first = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return views, (np.concatenate(lengths) if lengths else np.zeros(0, dtype=np.int64)), first


def _chunk_bounds(ends: NDArray[np.int64], prefix: int) -> list[tuple[int, int]]:
    """The chunks [(first, past last)] of records ending at ``ends`` (N,) [bytes from the first record], the first
    chunk holding ``prefix`` bytes before them: each closed after the record that takes it past CHUNK_BYTES."""
    n = ends.size
    if n == 0:
        return [(0, 0)] if prefix else []
    bounds, s = [], 0
    while s < n:
        base = int(ends[s - 1]) if s else 0
        j = int(np.searchsorted(ends, CHUNK_BYTES - (prefix if s == 0 else 0) + base, side="right"))
        e = min(max(j, s) + 1, n)
        bounds.append((s, e))
        s = e
    return bounds


class _File:
    """The file's parts in order, and the offset of the next one."""

    def __init__(self) -> None:
        self.parts: list[Any] = []
        self.pos = 0

    def add(self, data: bytes) -> int:
        """Append ``data``; its offset."""
        at = self.pos
        self.parts.append(data)
        self.pos += len(data)
        return at


def _chunks(f: _File, prefix: bytes, heads: NDArray[Any], pieces: list[Any], sizes: NDArray[np.int64]
            ) -> list[bytes]:
    """Write the chunks, each followed by its message indexes, into ``f``; their ChunkIndex records."""
    ends = np.cumsum(sizes)
    starts = ends - sizes
    index = []
    for s, e in _chunk_bounds(ends, len(prefix)):
        p0 = len(prefix) if s == 0 else 0
        size = p0 + (int(ends[e - 1] - starts[s]) if e > s else 0)
        log = heads["log_time"][s:e]
        t0, t1 = (int(log.min()), int(log.max())) if e > s else (_NO_TIME, 0)
        chunk_at = f.add(struct.pack("<BQQQQII", 0x06, 40 + size, t0, t1, size, 0, 0) + struct.pack("<Q", size))
        if p0:
            f.parts.append(prefix)
        f.parts += pieces[2 * s:2 * e]
        f.pos += size
        chunk_end = f.pos
        chans = heads["channel"][s:e]
        offsets = (starts[s:e] - (starts[s] if e > s else 0) + p0).astype("<u8")
        uniq, first = np.unique(chans, return_index=True)
        where = []
        for cid in uniq[np.argsort(first, kind="stable")].tolist():
            sel = chans == cid
            entries = np.empty(int(sel.sum()), dtype=_ENTRY)
            entries["log"], entries["offset"] = log[sel], offsets[sel]
            where.append(struct.pack("<HQ", cid, f.add(
                _record(INDEX_OP, struct.pack("<HI", cid, entries.nbytes) + entries.tobytes()))))
        index.append(_record(0x08, struct.pack("<QQQQI", t0, t1, chunk_at, chunk_end - chunk_at, 10 * len(where))
                             + b"".join(where) + struct.pack("<Q", f.pos - chunk_end) + _string("")
                             + struct.pack("<QQ", size, size)))
    return index


def _heads(log_ns: NDArray[np.int64], channel: NDArray[np.int64], lengths: NDArray[np.int64]) -> NDArray[Any]:
    """The Message records' heads (N,) of :data:`lrfcal.io.bag_raw.MESSAGE_HEAD`: channel ids from 1, sequence 0,
    publish time = log time."""
    heads = np.zeros(log_ns.size, dtype=MESSAGE_HEAD)
    heads["op"] = MESSAGE_OP
    heads["length"] = 22 + lengths
    heads["channel"] = channel + 1
    heads["log_time"] = heads["publish_time"] = log_ns
    return heads


def _summary(f: _File, schemas: list[bytes], channels: list[bytes], index: list[bytes], metadata_at: int,
             metadata_end: int, stats: bytes) -> None:
    """The summary section (schemas, channels, chunk indexes, metadata index, statistics, offsets), footer, magic."""
    groups = []
    for op, records in ((0x03, schemas), (0x04, channels), (0x08, index)):
        at = f.pos
        for r in records:
            f.add(r)
        groups.append((op, at, f.pos - at))
    at = f.add(_record(0x0D, struct.pack("<QQ", metadata_at, metadata_end - metadata_at) + _string("rosbag2")))
    groups.append((0x0D, at, f.pos - at))
    at = f.add(stats)
    groups.append((0x0B, at, f.pos - at))
    summary_at, offsets_at = groups[0][1], f.pos
    for op, at, length in groups:
        if length or op in (0x0D, 0x0B):
            f.add(_record(0x0E, struct.pack("<BQQ", op, at, length)))
    f.add(_record(0x02, struct.pack("<QQI", summary_at, offsets_at, 0)))
    f.add(MAGIC)


def _metadata(topics: Sequence[BagTopic], counts: list[int], t0: int, t1: int, mcap_name: str) -> dict[str, Any]:
    """rosbag2's metadata of the bag (rosbags' Writer.close: ``rosbag2_bagfile_information``'s content)."""
    duration, total = max(0, t1 - t0), sum(counts)
    return {
        "version": 9,
        "storage_identifier": "mcap",
        "relative_file_paths": [mcap_name],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": t0},
        "message_count": total,
        "topics_with_message_count": [
            {"topic_metadata": {"name": t.topic, "type": t.msgtype, "serialization_format": "cdr",
                                "offered_qos_profiles": [], "type_description_hash": t.rihs01},
             "message_count": c}
            for t, c in zip(topics, counts, strict=True)],
        "compression_format": "",
        "compression_mode": "",
        "files": [{"path": mcap_name, "starting_time": {"nanoseconds_since_epoch": t0},
                   "duration": {"nanoseconds": duration}, "message_count": total}],
        "custom_data": None,
        "ros_distro": "rosbags",
    }


@lru_cache(maxsize=1)
def _library() -> str:
    """The Header's library: rosbags' own, whose file this is byte for byte (rosbags writes ``rosbags-<version>``)."""
    from importlib.metadata import version

    return f"rosbags-{version('rosbags')}"


def _yaml(data: dict[str, Any]) -> str:
    from ruamel.yaml import YAML

    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    out = StringIO()
    yaml.dump(data, out)
    return out.getvalue()


def _write_parts(path: Path, parts: list[Any]) -> None:
    """A new file ``path`` of ``parts`` (bytes-like) one after the other: gathered by the kernel (``os.writev``,
    IOV_MAX parts a call) where it can, without first joining them into one buffer."""
    import os

    if not hasattr(os, "writev"):
        with path.open("xb") as out:
            out.write(b"".join(parts))
        return
    batch = max(16, min(1024, os.sysconf("SC_IOV_MAX")))
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        for a in range(0, len(parts), batch):
            some = parts[a:a + batch]
            done = os.writev(fd, some)
            if done < sum(map(len, some)):  # a short write (parts are bytes or byte views): the rest, joined
                rest = memoryview(b"".join(some))[done:]
                while rest:
                    rest = rest[os.write(fd, rest):]
    finally:
        os.close(fd)


def _check(topics: Sequence[BagTopic], messages: Sequence[Messages], log_ns: NDArray[np.int64],
           channel: NDArray[np.int64], index: NDArray[np.int64]) -> None:
    """Refuse arguments rosbags' Writer would refuse or this writer would misread (a programming error)."""
    names = [(t.topic, t.msgtype) for t in topics]
    if len(set(names)) != len(names) or len(messages) != len(topics):
        raise ValueError(f"bag topics {names}: each once, with one message collection each ({len(messages)} given)")
    for t, m in zip(topics, messages, strict=True):
        if isinstance(m, np.ndarray) and (m.dtype != np.uint8 or m.ndim != 2):
            raise ValueError(f"bag topic {t.topic}: messages as an array must be (n, bytes) uint8, not {m.dtype} "
                             f"{m.shape}")
    if not (log_ns.shape == channel.shape == index.shape and log_ns.ndim == 1):
        raise ValueError(f"log times, topics and indices of one shape (N,) expected: {log_ns.shape}, "
                         f"{channel.shape}, {index.shape}")
    counts = np.array([len(m) for m in messages], dtype=np.int64)
    if log_ns.size and (log_ns.min() < 0 or channel.min() < 0 or channel.max() >= len(topics) or index.min() < 0
                        or np.any(index >= counts[np.clip(channel, 0, max(len(topics) - 1, 0))])):
        raise ValueError("a message's log time is negative, or its topic or its index in the topic out of range")


def write_rosbag2_mcap(path: str | Path, topics: Sequence[BagTopic], messages: Sequence[Messages],
                       log_ns: NDArray[np.int64], channel: NDArray[np.int64], index: NDArray[np.int64]) -> None:
    """Write the bag folder ``path`` (it must not exist; made with its parents): ``path/<name>.mcap`` and
    ``path/metadata.yaml``, the files rosbags' Writer (version 9, MCAP, no compression, no QoS profiles) writes
    when ``topics`` are added in order and message ``j`` (``messages[channel[j]][index[j]]``, the topic's
    serialised message) is written at log time ``log_ns[j]`` [ns], for j in file order.

    ``topics`` (T,); ``messages`` (T,): each topic's messages (:data:`Messages`); ``log_ns``, ``channel`` (a topic's
    position in ``topics``) and ``index`` (N,) integers.

    Raises:
        ValueError: a topic given twice, messages not (n, bytes) uint8 or bytes-like, a negative log time, a topic
            or an index out of range (rosbags' Writer refuses the first and the negative time too).
        FileExistsError: ``path`` exists.
    """
    path = Path(path)
    log_ns, channel, index = (np.asarray(v, dtype=np.int64) for v in (log_ns, channel, index))
    _check(topics, messages, log_ns, channel, index)
    views, lengths, first = _payloads(messages)
    which = first[channel] + index
    heads = _heads(log_ns, channel, lengths[which])
    head_bytes = memoryview(heads.tobytes())
    pieces: list[Any] = [None] * (2 * log_ns.size)
    pieces[0::2] = [head_bytes[a:a + MESSAGE_HEAD.itemsize] for a in range(0, heads.nbytes, MESSAGE_HEAD.itemsize)]
    pieces[1::2] = list(map(views.__getitem__, which.tolist()))
    schemas, channels, prefix = _schemas_and_channels(topics)

    f = _File()
    f.add(MAGIC + _record(0x01, _string("ros2") + _string(_library())))
    index_records = _chunks(f, prefix, heads, pieces, 31 + lengths[which])
    counts = np.bincount(channel, minlength=len(topics)).tolist()
    t0, t1 = (int(log_ns.min()), int(log_ns.max())) if log_ns.size else (_NO_TIME, 0)
    mcap_name = f"{path.name}.mcap"
    meta = _metadata(topics, counts, t0, t1, mcap_name)
    inner = _string("serialized_metadata") + _string(_yaml(meta).strip())
    metadata_at = f.add(_record(0x0C, _string("rosbag2") + struct.pack("<I", len(inner)) + inner))
    metadata_end = f.add(_record(0x0F, struct.pack("<I", 0)))
    stats = _record(0x0B, struct.pack("<QHIIIIQQI", log_ns.size, len(schemas), len(channels), 0, 1,
                                      len(index_records), t0, t1, 10 * len(topics))
                    + b"".join(struct.pack("<HQ", cid, c) for cid, c in enumerate(counts, start=1)))
    _summary(f, schemas, channels, index_records, metadata_at, metadata_end, stats)

    path.mkdir(mode=0o755, parents=True)
    _write_parts(path / mcap_name, f.parts)
    tmp = path / "metadata.yaml.tmp"
    tmp.write_text(_yaml({"rosbag2_bagfile_information": meta}), "utf8")
    tmp.replace(path / "metadata.yaml")


__all__ = ["CHUNK_BYTES", "BagTopic", "Messages", "write_rosbag2_mcap"]
