"""Bags cut short (the rig lost power, the disk filled, the copy stopped): read up to the last complete record, and
say how much was recovered (docs/formats.md, "Cut recordings").

* **MCAP** (ROS 2; the MCAP specification, mcap.dev/spec): a writer writes the data section (the Header, then
  Schema, Channel and Chunk records, each chunk followed by its MessageIndex records), then the DataEnd record, the
  summary (the index) and the Footer, whose last 8 bytes are the magic. A file cut short has no Footer; rosbags
  refuses it ("File end magic is invalid"). :class:`RecoveringMcapReader` walks the records from the Header on,
  stops at the first one that does not fit in the file or whose chunk does not decompress (its CRC), and reads the
  data before it as an unindexed MCAP file (which the specification allows: the summary is optional).
* **ROS 1** (the rosbag format 2.0, wiki.ros.org/Bags/Format/2.0): the bag header's ``index_pos`` points to the
  connection and chunk-info records written when the bag is closed; a bag cut short has them not (index_pos 0 or
  past the end). :class:`RecoveringRos1Reader` reads the chunk records one after the other from the first record
  after the bag header, the connection records inside them included, up to the last complete chunk.
* **sqlite3** (ROS 2 .db3): rosbags opens the file ``immutable``, which reads no write-ahead log: rows a recorder
  left in ``NAME.db3-wal`` would be silently missing. A .db3 with a WAL beside it is read from a copy of both in a
  temporary folder, where sqlite merges the log (the input is never modified). A .db3 cut short is refused by
  sqlite ("database disk image is malformed"); no recovery is attempted: the pages of a B-tree cut anywhere do not
  say which rows they held (`sqlite3 FILE .recover` may get some back; then give the recovered file).

Each reader keeps what it recovered in ``recovered`` (a :class:`Recovered`, None for a complete file), which
:func:`recovered_notes` turns into the lines the calibration repeats in its notes.
"""

from __future__ import annotations

import os
import shutil
import struct
import tempfile
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Any

#: the MCAP magic (mcap.dev/spec: the first and the last 8 bytes of a complete file)
MCAP_MAGIC = b"\x89MCAP0\r\n"
#: MCAP record opcodes (mcap.dev/spec)
MCAP_HEADER, MCAP_FOOTER, MCAP_CHUNK, MCAP_DATA_END = 0x01, 0x02, 0x06, 0x0F


@dataclass(frozen=True)
class Recovered:
    """What was read of a file cut short: ``path``, its size and the bytes read [B], the messages recovered, their
    time span [s] (log times), and how the file ended (``why``)."""

    path: str
    size_bytes: int
    read_bytes: int
    n_messages: int
    span_s: float
    why: str

    def line(self, expected_messages: int | None = None) -> str:
        """The note: what was recovered, of how much."""
        of = f" of the {expected_messages} its metadata.yaml lists" if expected_messages else ""
        return (f"{self.path}: cut short ({self.why}): read up to its last complete record, {self.read_bytes} of "
                f"{self.size_bytes} bytes ({self.read_bytes / max(self.size_bytes, 1):.0%}): {self.n_messages} "
                f"messages{of}, {self.span_s:.2f} s; the rest is lost")


def _mcap_data_end(f: Any, start: int, size: int) -> tuple[int, str]:
    """The end of the last complete record of an MCAP data section that starts at ``start`` in a file of ``size``
    bytes (its chunks checked to decompress), and how the walk ended."""
    from rosbags.rosbag2.storage_mcap import decompress

    pos = start
    while pos + 9 <= size:
        f.seek(pos)
        head = f.read(9)
        op, length = head[0], struct.unpack_from("<Q", head, 1)[0]
        end = pos + 9 + length
        if end > size:
            return pos, f"its last record, at byte {pos}, ends past the file's end"
        if op in (MCAP_DATA_END, MCAP_FOOTER):
            return pos, "no summary"
        if op == MCAP_CHUNK:
            body = f.read(length)
            try:
                _, _, usize, crc = struct.unpack_from("<QQQI", body, 0)
                clen = struct.unpack_from("<I", body, 28)[0]
                compression = body[32:32 + clen].decode()
                csize = struct.unpack_from("<Q", body, 32 + clen)[0]
                data = body[40 + clen:40 + clen + csize]
                if len(data) != csize:
                    raise ValueError("short chunk")
                decompress(data, compression, usize, crc)
            except Exception:  # a chunk half written: the data end before it
                return pos, f"its chunk at byte {pos} is incomplete"
        pos = end
    return pos, "no summary and no footer"


def _make_mcap_reader() -> type:
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.rosbag2.storage_mcap import McapReader

    class RecoveringMcapReader(McapReader):
        """rosbags' McapReader that reads an MCAP file cut short up to its last complete record (module
        docstring); ``recovered`` says what was read (None: the file was complete)."""

        recovered: Recovered | None = None

        def _open(self) -> None:
            try:
                super()._open()
                return
            except (ReaderError, OSError, struct.error) as err:
                if self.data_start == 0:  # not even the header: nothing to recover
                    raise
                why = str(err)
            assert self.bio is not None
            self.schemas.clear()
            self.channels.clear()
            self.chunks.clear()
            self.connections.clear()
            self.statistics = None
            size = os.fstat(self.bio.fileno()).st_size
            self.data_end, how = _mcap_data_end(self.bio, self.data_start, size)
            self.meta_scan()
            assert self.statistics is not None
            stats = self.statistics
            self.connections = [c._replace(msgcount=stats.channel_message_counts.get(c.id, 0))
                                for c in self.connections]
            n = stats.message_count
            reason = "no footer" if "magic" in why or "footer" in why.lower() else why.rstrip(".")
            if not n:
                raise ReaderError(f"cut short ({reason}; {how}): no complete chunk, no message to recover in its "
                                  f"{size} bytes")
            self.metadata = self.metadata._replace(
                duration=stats.end_time - stats.start_time + 1 if n else 0,
                start_time=stats.start_time if n else 2**63 - 1,
                end_time=stats.end_time + 1 if n else 0, message_count=n)
            self.recovered = Recovered(str(self.path), size, self.data_end, n,
                                       (stats.end_time - stats.start_time) * 1e-9 if n else 0.0,
                                       f"{reason}; {how}")

    return RecoveringMcapReader


def _make_ros1_reader() -> type:
    from rosbags.rosbag1.reader import ChunkInfo, Header, IndexData, Reader, ReaderError, RecordType, read_uint32

    class RecoveringRos1Reader(Reader):
        """rosbags' ROS 1 Reader that reads a bag without its index (cut short) chunk by chunk (module docstring);
        ``recovered`` says what was read (None: the bag was complete)."""

        recovered: Recovered | None = None

        def open(self) -> None:
            try:
                super().open()
                return
            except Exception as err:  # rosbags raises several types for an index cut off
                why = " ".join(str(err).split()).rstrip(".") or type(err).__name__
                if self.bio is not None:
                    self.bio.close()
                    self.bio = None
                if any(w in why for w in ("magic", "version", "encryption", "empty", "Could not open")):
                    raise
            self.bio = self.path.open("rb")
            try:
                self._recover(why)
            except BaseException:
                self.bio.close()
                self.bio = None
                raise

        def _recover(self, why: str) -> None:
            bio = self.bio
            assert bio is not None
            size = os.fstat(bio.fileno()).st_size
            bio.readline()  # the magic, checked by open
            index_pos = Header.read(bio, RecordType.BAGHEADER).get_uint64("index_pos")
            bio.seek(read_uint32(bio), os.SEEK_CUR)  # the bag header's padding
            if index_pos == 0 or index_pos >= size:
                why = (f"no index: the bag header's index_pos is {index_pos}" + ("" if index_pos == 0 else
                       f", past the file's {size} bytes"))
            conns: dict[int, Any] = {}
            indexes: dict[int, list[Any]] = {}
            infos = []
            pos = end = bio.tell()
            while pos < size:
                try:
                    bio.seek(pos)
                    op = Header.read(bio).get_uint8("op")
                    n = read_uint32(bio)
                    following = bio.tell() + n
                    if following > size:
                        break
                    if op == RecordType.CHUNK:
                        bio.seek(pos)
                        chunk = self.read_chunk()
                        bio.seek(chunk.datapos)
                        found = _chunk_messages(chunk.decompressor(bio.read(chunk.datasize)), conns, self)
                        for cid, t_ns, offset in found:
                            indexes.setdefault(cid, []).append(IndexData(t_ns, pos, offset))
                        if found:
                            self.chunks[pos] = chunk
                            times = [t for _, t, _ in found]
                            counts: dict[int, int] = {}
                            for cid, _, _ in found:
                                counts[cid] = counts.get(cid, 0) + 1
                            infos.append(ChunkInfo(pos, min(times), max(times) + 1, counts))
                    elif op == RecordType.CONNECTION:
                        bio.seek(pos)
                        conn = self.read_connection()
                        conns.setdefault(conn.id, conn)
                    pos = end = following
                except Exception:  # a record half written (or a chunk that does not decompress): the end
                    break
            if not indexes:
                raise ReaderError(f"{why}; and no complete chunk with messages found reading it chunk by chunk")
            self.indexes = {cid: sorted(idx) for cid, idx in indexes.items()}
            self.connections = [conns[c]._replace(msgcount=len(self.indexes[c])) for c in sorted(self.indexes)
                                if c in conns]
            self.chunk_infos = infos
            n_msgs = sum(len(v) for v in self.indexes.values())
            t0, t1 = min(i.start_time for i in infos), max(i.end_time for i in infos) - 1
            self.recovered = Recovered(str(self.path), size, end, n_msgs, (t1 - t0) * 1e-9,
                                       f"{why}; read chunk by chunk")

    return RecoveringRos1Reader


def _chunk_messages(data: bytes, conns: dict[int, Any], reader: Any) -> list[tuple[int, int, int]]:
    """(connection id, time [ns], offset) of each message data record in a ROS 1 chunk's records; its connection
    records added to ``conns``."""
    from rosbags.rosbag1.reader import Header, RecordType, read_uint32

    out = []
    bio = BytesIO(data)
    while bio.tell() < len(data):
        pos = bio.tell()
        rec = Header.read(bio)
        op = rec.get_uint8("op")
        if op == RecordType.CONNECTION:
            bio.seek(pos)
            saved, reader.bio = reader.bio, bio
            try:
                conn = reader.read_connection()
            finally:
                reader.bio = saved
            conns.setdefault(conn.id, conn)
            continue
        n = read_uint32(bio)
        if op == RecordType.MSGDATA:
            out.append((rec.get_uint32("conn"), rec.get_time("time"), pos))
        bio.seek(n, os.SEEK_CUR)
    return out


def with_recovery(any_reader: Any) -> None:
    """Let an unopened AnyReader read bags cut short: its ROS 2 MCAP storages by the RecoveringMcapReader, its ROS 1
    bags by the RecoveringRos1Reader (module docstring)."""
    from rosbags.rosbag2.storage_mcap import McapReader

    if not any_reader.is2:
        ros1 = _make_ros1_reader()
        any_reader.readers = [ros1(r.path) for r in any_reader.readers]
        return
    mcap = _make_mcap_reader()
    for reader in any_reader.readers:
        storage = reader.storage
        if type(storage) is McapReader:
            reader.storage = mcap(storage.path)
        elif hasattr(storage, "STORAGE_PLUGINS"):  # a bag folder: its files by the recovering reader
            storage.STORAGE_PLUGINS = {**storage.STORAGE_PLUGINS, "mcap": mcap}


def recovered_notes(any_reader: Any) -> tuple[str, ...]:
    """The notes of what was recovered of each file of an open AnyReader cut short, or read from a copy with its
    write-ahead log merged (lrfcal.io.bag_messages.open_reader) (empty: all complete)."""
    out = []
    wal = getattr(any_reader, "lrfcal_wal", None)
    if wal is not None:
        out.append(wal[1])
    for reader in any_reader.readers:
        storage = getattr(reader, "storage", reader)
        parts = list({id(x): x for x in (*getattr(storage, "storages", []), storage, reader)}.values())
        expected = None
        meta = getattr(storage, "metadata", None)
        if getattr(storage, "storages", None) and meta is not None:
            expected = int(getattr(meta, "message_count", 0)) or None
        for part in parts:
            rec = getattr(part, "recovered", None)
            if isinstance(rec, Recovered):
                out.append(rec.line(expected if expected and expected > rec.n_messages else None))
    return tuple(out)


def wal_copy(path: Path) -> tuple[Path, tempfile.TemporaryDirectory[str]] | None:
    """For a .db3 (or a bag folder holding one) with a write-ahead log beside it: a copy of the bag in a temporary
    folder, where sqlite merges the log when it opens the copy (module docstring), and the folder (remove it when
    done); None when there is no WAL."""
    db3s = [path] if path.is_file() else sorted(path.glob("*.db3"))
    if not any(Path(f"{p}-wal").is_file() and Path(f"{p}-wal").stat().st_size > 0 for p in db3s):
        return None
    import sqlite3

    tmp = tempfile.TemporaryDirectory(prefix=".lrfcal-wal-")
    root = Path(tmp.name)
    if path.is_file():
        copies = [root / path.name]
        shutil.copy2(path, copies[0])
        shutil.copy2(f"{path}-wal", root / f"{path.name}-wal")
        target = copies[0]
    else:
        target = root / path.name
        shutil.copytree(path, target)
        copies = sorted(target.glob("*.db3"))
    for db in copies:
        con = sqlite3.connect(db)
        try:
            con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        finally:
            con.close()
    return target, tmp


__all__ = ["MCAP_MAGIC", "Recovered", "recovered_notes", "wal_copy", "with_recovery"]
