"""The serialised messages of some connections of an open bag, in bag order, fast.

rosbags' reader yields a bag's messages one by one through Python file reads (an MCAP chunk's records each read,
wrapped and sorted), about half the time of reading a recording. An indexed MCAP file (what rosbag2 and this
project's simulator write: chunks, each followed by a MessageIndex record per channel of (log time, offset) pairs;
the MCAP specification, mcap.dev/spec) is read here chunk by chunk: the chunk's records in one read (decompressed
by rosbags' own function), the wanted channels' message records found from their index with numpy. The order is
rosbags' own: by log time, then by the chunk's place in the file, then by the record's place in the chunk.

Anything else (ROS 1 bags, sqlite3, unindexed or several-file MCAP bags, per-message compression, any surprise in
the file) is read by rosbags' reader, as before.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: the MCAP opcodes of a Message record and of a MessageIndex record (mcap.dev/spec; lrfcal.io.mcap_write writes them)
MESSAGE_OP, INDEX_OP = 0x05, 0x07
#: a message record's head: opcode, record length (uint64), channel id (uint16), sequence (uint32), log time and
#: publish time (uint64)
MESSAGE_HEAD = np.dtype([("op", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"),
                         ("log_time", "<u8"), ("publish_time", "<u8")])


class _NotIndexed(Exception):
    """The MCAP file is not one this reader takes: rosbags reads it."""


@dataclass(frozen=True)
class RawTopic:
    """The serialised messages (M) of some connections in bag order: log times ``times_ns`` (M,) [ns], the
    messages' bytes in ``blob`` (in file order) at ``starts`` with ``lengths`` (M,)."""

    times_ns: NDArray[np.int64]
    blob: bytes | bytearray
    starts: NDArray[np.int64]
    lengths: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.times_ns.size)

    def message(self, i: int) -> memoryview:
        """Message i's bytes."""
        s = int(self.starts[i])
        return memoryview(self.blob)[s:s + int(self.lengths[i])]

    def packed(self) -> bool:
        """The messages lie in ``blob`` end to end in bag order, nothing else in it."""
        ends = np.cumsum(self.lengths)
        return bool(np.array_equal(self.starts, ends - self.lengths)) and (ends[-1] if ends.size else 0) == len(
            self.blob)

    @staticmethod
    def of(times_ns: Sequence[int], raws: Sequence[bytes | memoryview]) -> RawTopic:
        """The messages ``raws`` logged at ``times_ns``, in this order."""
        lengths = np.fromiter(map(len, raws), dtype=np.int64, count=len(raws))
        return RawTopic(np.array(times_ns, dtype=np.int64), b"".join(raws), np.cumsum(lengths) - lengths, lengths)


def raw_messages(reader: Any, groups: Sequence[Sequence[Any]], fast: bool = True,
                 progress: Callable[[int], None] | None = None) -> list[RawTopic]:
    """Per group of connections of the open AnyReader ``reader``: its messages, in the order its
    ``messages(connections=group)`` gives (an indexed MCAP file is read once for all groups). ``fast`` False: by
    rosbags' reader whatever the file. ``progress(k)``: called with the messages read so far while rosbags reads."""
    storage = _single_mcap(reader) if fast else None
    if storage is not None:
        try:
            return _mcap_messages(storage, [{c.topic for c in g} for g in groups])
        except (_NotIndexed, ValueError, OSError, KeyError, IndexError):
            pass
    out = []
    done = 0
    for group in groups:
        times, raws = [], []
        for _, t_ns, raw in reader.messages(connections=list(group)) if group else ():
            times.append(t_ns)
            raws.append(raw)
            done += 1
            if progress is not None and done % 256 == 0:
                progress(done)
        out.append(RawTopic.of(times, raws))
    return out


def _single_mcap(reader: Any) -> Any:
    """The one McapReader storage of a one-file ROS 2 bag (None otherwise)."""
    from rosbags.rosbag2.storage_mcap import McapReader

    if not reader.is2 or len(reader.readers) != 1:
        return None
    storage = reader.readers[0].storage
    if isinstance(storage, McapReader):
        return storage
    storages = getattr(storage, "storages", [])
    if len(storages) != 1 or not isinstance(storages[0], McapReader):
        return None
    if storage.metadata.compression_mode == "message":
        return None
    return storages[0]


def _mcap_messages(storage: Any, topics: list[set[str]]) -> list[RawTopic]:
    from rosbags.rosbag2.storage_mcap import decompress

    channels = [{cid for cid, ch in storage.channels.items() if ch.topic in group} for group in topics]
    chunks = sorted(storage.chunks, key=lambda ch: ch.chunk_start_offset)
    if not chunks:
        raise _NotIndexed
    keys: list[list[NDArray[np.int64]]] = [[] for _ in topics]
    views: list[list[memoryview]] = [[] for _ in topics]
    with open(storage.path, "rb") as f:
        for chunk in chunks:
            wanted = [[cid for cid in group if cid in chunk.message_index_offsets] for group in channels]
            if not any(wanted):
                continue
            f.seek(chunk.chunk_start_offset + 9 + 24)
            crc = int.from_bytes(f.read(4), "little")
            f.seek(chunk.chunk_start_offset + 9 + 40 + len(chunk.compression))
            data = memoryview(decompress(f.read(chunk.compressed_size), chunk.compression, chunk.uncompressed_size,
                                         crc))
            for k, cids in enumerate(wanted):
                if not cids:
                    continue
                times, offsets = _indexed(f, chunk, cids)
                start, length = _located(data, offsets, times, cids)
                views[k].extend(data[a:a + n] for a, n in zip(start.tolist(), length.tolist(), strict=True))
                keys[k].append(np.stack([times, np.full(times.size, chunk.chunk_start_offset), offsets]))
    out = []
    for k_list, v in zip(keys, views, strict=True):
        if not k_list:
            out.append(RawTopic.of([], []))
            continue
        key = np.concatenate(k_list, axis=1)
        order = np.lexsort(key[::-1])  # by log time, then chunk, then place in the chunk
        out.append(RawTopic.of(key[0][order], [v[i] for i in order.tolist()]))
    return out


def _indexed(f: Any, chunk: Any, wanted: list[int]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(log times, offsets in the chunk's records) of the wanted channels' messages in a chunk, from its
    MessageIndex records, in the order of their place in the chunk."""
    times, offsets = [], []
    for cid in wanted:
        f.seek(chunk.message_index_offsets[cid])
        head = f.read(15)
        if len(head) != 15 or head[0] != INDEX_OP or int.from_bytes(head[9:11], "little") != cid:
            raise _NotIndexed
        pairs = np.frombuffer(f.read(int.from_bytes(head[11:15], "little")), dtype="<u8").reshape(-1, 2)
        times.append(pairs[:, 0].astype(np.int64))
        offsets.append(pairs[:, 1].astype(np.int64))
    t, o = np.concatenate(times), np.concatenate(offsets)
    order = np.argsort(o, kind="stable")
    return t[order], o[order]


def _located(data: bytes | memoryview, offsets: NDArray[np.int64], times: NDArray[np.int64], wanted: list[int]
             ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(start, length) of each message's serialised bytes in the chunk's records ``data``, its record checked
    against the index (a message record of a wanted channel at the log time the index gives)."""
    size = MESSAGE_HEAD.itemsize
    if offsets.size and (offsets.min() < 0 or offsets.max() + size > len(data)):
        raise _NotIndexed
    u8 = np.frombuffer(data, dtype=np.uint8)
    heads = u8[offsets[:, None] + np.arange(size)].view(MESSAGE_HEAD)[:, 0]
    length = heads["length"].astype(np.int64) - (size - 9)
    ok = ((heads["op"] == MESSAGE_OP) & np.isin(heads["channel"], wanted)
          & (heads["log_time"].astype(np.int64) == times) & (length >= 0)
          & (offsets + size + length <= len(data)))
    if not ok.all():
        raise _NotIndexed
    return offsets + size, length


__all__ = ["INDEX_OP", "MESSAGE_HEAD", "MESSAGE_OP", "RawTopic", "raw_messages"]
