"""rosbag2 storage files read directly and tolerantly: MCAP and sqlite3, with or without metadata.yaml.

rosbags (the library) stops at the first damaged byte of a bag and needs metadata.yaml; this module keeps every
message that can still be read and says what it skipped (:class:`ReadLog`):

- MCAP with a readable summary: the chunks are read one at a time through the summary's chunk index, in
  log-time order (as the mcap library does). A chunk that does not match its index entry, cannot be
  decompressed, fails its CRC or holds a damaged record is read record by record: past a damaged record the
  reader searches forward for the next plausible message record (a known channel and a log time inside the
  chunk's span, from the index), so the intact messages of a damaged chunk are kept too.
- MCAP without a summary (a truncated file, a damaged footer): the file is read front to back; past a damaged
  record the reader searches for the next chunk whose header fields agree with each other and with its
  length; a chunk cut by the end of the file gives the messages it holds in full.
- sqlite3 (.db3): the topics table, then every readable row key (id, topic, timestamp) in id order, seeking
  past an unreadable id (at most MAX_BAD_IDS in a row: a truncated file ends the table), then each row's data
  in time order; a row whose data cannot be read is skipped.

A folder is read through its metadata.yaml's file list when it has one, else its *.mcap and *.db3 files;
the storage of a file comes from its first bytes. Compressed bag files and ROS 1 bags are not read here
(:class:`Unsupported`; rosbags reads them).
"""
from __future__ import annotations

import heapq
import mmap
import re
import sqlite3
import struct
import zlib
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator
from urllib.parse import quote

#: (topic, message type, log time ns, serialized CDR message)
Raw = tuple[str, str, int, bytes]

MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x02, 0x03, 0x04, 0x05, 0x06
OP_MESSAGE_INDEX, OP_DATA_END = 0x07, 0x0F
COMPRESSIONS = ("", "zstd", "lz4")
MESSAGE_HEAD = 22  # bytes of a message record body before its data: channel u16, sequence u32, two u64 times
MAX_BAD_IDS = 4096  # sqlite3: unreadable row ids in a row before the rest of the table counts as lost
MAX_NOTES = 8  # damages described in a ReadLog; further ones are counted
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length


class Unsupported(Exception):
    """A bag file this module does not read (a compressed bag file, a ROS 1 bag): rosbags reads it."""


@dataclass
class ReadLog:
    """What a tolerant read met. Counts: messages read; of them ``recovered``, read from a damaged chunk or past
    a damage (what a reader that stops at the first error loses); MCAP chunks damaged (not read as one piece)
    and lost (gave nothing); bytes passed over in searches for the next valid record; sqlite3 row ids
    unreadable between readable rows; messages that do not deserialise (counted by bag.read_messages).
    ``notes``: one line per damage or oddity, for people."""

    messages: int = 0
    chunks_damaged: int = 0
    chunks_lost: int = 0
    bytes_skipped: int = 0
    rows_skipped: int = 0
    recovered: int = 0
    undecodable: int = 0
    chunks_skipped: int = 0  # MCAP chunks the index shows hold none of the wanted topics (not read)
    notes: list[str] = field(default_factory=list)
    more_notes: int = 0  # damages beyond MAX_NOTES, counted only
    _damaged: bool = False

    def note(self, text: str) -> None:
        """Say something about the read that is not damage (no summary, no metadata.yaml)."""
        if len(self.notes) < MAX_NOTES:
            self.notes.append(text)
        else:
            self.more_notes += 1

    def damage(self, text: str) -> None:
        """Record a damage; every message read after it (in file order) counts as recovered."""
        self._damaged = True
        self.note(text)

    def message(self, past_damage: bool | None = None) -> None:
        """Count a message read; ``past_damage`` None: after any damage recorded so far."""
        self.messages += 1
        self.recovered += self._damaged if past_damage is None else past_damage

    def summary(self) -> str:
        """One line of what was skipped and kept, '' for an undamaged read."""
        if not (self._damaged or self.undecodable):
            return ""
        parts = [f"{self.messages} messages read, {self.recovered} of them past damage"]
        for key, what in (("chunks_damaged", "MCAP chunks damaged"), ("chunks_lost", "MCAP chunks lost"),
                          ("bytes_skipped", "bytes skipped"), ("rows_skipped", "sqlite3 rows unreadable"),
                          ("undecodable", "messages undecodable")):
            if getattr(self, key):
                parts.append(f"{getattr(self, key)} {what}")
        return "damaged bag: " + ", ".join(parts)

    def counts(self) -> dict[str, int]:
        """The counts, for a machine-readable summary."""
        return {k: getattr(self, k) for k in ("messages", "recovered", "chunks_damaged", "chunks_lost", "bytes_skipped",
                                              "rows_skipped", "undecodable")}

    def lines(self) -> list[str]:
        """The notes and the summary line, for a replay summary."""
        more = [f"{self.more_notes} more damages not described"] if self.more_notes else []
        return self.notes + more + ([self.summary()] if self.summary() else [])


# ------------------------------------------------------------------ files of a bag
def is_bag_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder holding a rosbag2 bag: its metadata.yaml or storage files (*.mcap, *.db3)."""
    path = Path(path)
    return path.is_dir() and any(p.name == "metadata.yaml" or p.suffix in (".mcap", ".db3") for p in path.iterdir())


def has_metadata(folder: str | Path) -> bool:
    """Whether ``folder`` holds a readable rosbag2 metadata.yaml (a recorded bag's, not any file of that name)."""
    return bool(_metadata(Path(folder)))


def bag_files(path: str | Path) -> list[Path]:
    """The storage files of a bag folder (metadata.yaml's list when it has one and they exist, else its
    *.mcap and *.db3 files in split order) or the file itself. Unsupported for a compressed bag."""
    path = Path(path)
    if path.is_file():
        return [path]
    meta = _metadata(path)
    if meta.get("compression_mode"):
        raise Unsupported(f"compressed bag ({meta.get('compression_mode')} {meta.get('compression_format')})")
    listed = [path / f for f in meta.get("relative_file_paths") or []]
    if listed and all(f.is_file() for f in listed):
        return listed
    found = [f for f in path.iterdir() if f.suffix in (".mcap", ".db3") and f.is_file()]
    if not found:
        raise Unsupported(f"no .mcap or .db3 file in {path}")
    return sorted(found, key=lambda f: [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", f.name)])


def listed_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """{topic: (message type, message count)} as a bag's metadata.yaml lists them (a folder's, or for a storage
    file the one beside it that lists it; {} without one): what the bag held when it was recorded, whatever its
    storage gives now."""
    path = Path(path)
    meta = _metadata(path) if path.is_dir() else _metadata(path.parent)
    if path.is_file() and path.name not in (meta.get("relative_file_paths") or []):
        meta = {}  # a file listed by no metadata.yaml beside it
    entries = meta.get("topics_with_message_count") or []
    table = {}
    for e in entries if isinstance(entries, list) else []:
        topic = e.get("topic_metadata") if isinstance(e, dict) else None
        if isinstance(topic, dict) and topic.get("name"):
            count = e.get("message_count")
            table[str(topic["name"])] = (str(topic.get("type", "")), count if isinstance(count, int) else 0)
    return table


def _metadata(folder: Path) -> dict:
    """rosbag2_bagfile_information of metadata.yaml, {} when it is missing or unreadable."""
    return _read_metadata(folder)[0]


def _read_metadata(folder: Path) -> tuple[dict, str]:
    """(rosbag2_bagfile_information of metadata.yaml or {}, what is wrong with the file: "" nothing)."""
    import yaml

    file = folder / "metadata.yaml"
    if not file.is_file():
        return {}, "no metadata.yaml"
    try:
        doc = yaml.safe_load(file.read_text())
        info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
        if not isinstance(info, dict) or not info:
            return {}, "metadata.yaml holds no rosbag2_bagfile_information"
        return dict(info), ""
    except (OSError, yaml.YAMLError, AttributeError, TypeError, ValueError) as e:
        return {}, f"metadata.yaml unreadable ({type(e).__name__})"


def storage_of(file: Path) -> str:
    """'mcap' or 'sqlite3' from the file's first bytes, else from its suffix (a damaged head); Unsupported."""
    with open(file, "rb") as f:
        head = f.read(16)
    if head.startswith(MCAP_MAGIC) or (file.suffix == ".mcap" and not head.startswith(SQLITE_MAGIC)):
        return "mcap"
    if head.startswith(SQLITE_MAGIC) or file.suffix == ".db3":
        return "sqlite3"
    raise Unsupported(f"{file.name} is neither MCAP nor sqlite3")


def read_raw(path: str | Path, topics: Iterable[str] | None, log: ReadLog) -> Iterator[Raw]:
    """Every readable message of the wanted topics (None: all), file by file, in log-time order per file."""
    wanted = None if topics is None else set(topics)
    if Path(path).is_dir():
        problem = _read_metadata(Path(path))[1]
        if problem:
            log.note(f"{problem} in {Path(path).name}: its storage files read directly")
    for file in bag_files(path):
        if storage_of(file) == "mcap":
            yield from _mcap_messages(file, wanted, log)
        else:
            yield from _sqlite_messages(file, wanted, log)


def topic_table(path: str | Path, log: ReadLog | None = None) -> dict[str, tuple[str, int]]:
    """{topic: (message type, message count)} over the bag's files: MCAP from its summary statistics (else
    from a read of the file), sqlite3 from its tables (a damaged table: its readable rows)."""
    log = log or ReadLog()
    table: dict[str, tuple[str, int]] = {}
    for file in bag_files(path):
        if storage_of(file) == "mcap":
            part = _mcap_topics(file, log)
        else:
            part = _sqlite_topics(file, log)
        for topic, (kind, n) in part.items():
            table[topic] = (kind, table.get(topic, (kind, 0))[1] + n)
    return table


# ------------------------------------------------------------------ MCAP
@contextmanager
def _open_mcap(file: Path, log: ReadLog) -> Iterator[_Mcap | None]:
    """The file mapped as an _Mcap, None for an empty file (noted)."""
    if file.stat().st_size == 0:
        log.damage(f"{file.name}: empty file")
        yield None
        return
    with open(file, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        yield _Mcap(file.name, f, buf, log)


def _mcap_messages(file: Path, wanted: set[str] | None, log: ReadLog) -> Iterator[Raw]:
    with _open_mcap(file, log) as m:
        if m is not None:
            yield from m.messages(wanted)


def _mcap_topics(file: Path, log: ReadLog) -> dict[str, tuple[str, int]]:
    with _open_mcap(file, log) as m:
        return m.topic_counts() if m is not None else {}


@dataclass
class _ChunkHead:
    """A chunk record's header: log-time span (ns), sizes (bytes), records at [start, end) of the file."""

    t0: int
    t1: int
    uncompressed: int
    crc: int
    compression: str
    start: int
    end: int


def _string(buf: Any, pos: int, end: int) -> tuple[str, int]:
    """A length-prefixed UTF-8 string at pos -> (text, position after it); ValueError past end."""
    (n,) = _U32.unpack_from(buf, pos)
    if pos + 4 + n > end:
        raise ValueError("string beyond its record")
    return bytes(buf[pos + 4:pos + 4 + n]).decode(), pos + 4 + n


#: bytes before a chunk given back with it: a page fault maps the pages around it too (64 KiB by default), so
#: reading a chunk maps again the end of the one before, already given back
RELEASE_BEHIND = 1 << 21


class _Mcap:
    """One mapped MCAP file: its schemas and channels, and its messages read tolerantly."""

    def __init__(self, name: str, fileobj: Any, buf: mmap.mmap, log: ReadLog):
        self.name, self.file, self.buf, self.size, self.log = name, fileobj, buf, len(buf), log
        self.schemas: dict[int, str] = {}
        self.channels: dict[int, tuple[str, int]] = {}  # id -> (topic, schema id)

    # ---------------------------------------------------------------- entry points
    def messages(self, wanted: set[str] | None) -> Iterator[Raw]:
        """Every readable message of the wanted topics, in log-time order (indexed) or file order."""
        for t, cid, src, a, b in self._events(wanted):
            topic, sid = self.channels[cid]
            if wanted is None or topic in wanted:
                self.log.message()
                yield topic, self.schemas.get(sid, ""), t, bytes(src[a:b])

    def topic_counts(self) -> dict[str, tuple[str, int]]:
        """{topic: (type, count)}: summary statistics, else a count over a read of the file."""
        summary = self._summary()
        if summary is not None and summary.statistics is not None and summary.channels:
            self._learn(summary)
            counts = summary.statistics.channel_message_counts
            return {topic: (self.schemas.get(sid, ""), counts.get(cid, 0))
                    for cid, (topic, sid) in self.channels.items()}
        per: dict[int, int] = {}
        for _, cid, *_ in self._events():
            per[cid] = per.get(cid, 0) + 1
        return {topic: (self.schemas.get(sid, ""), per.get(cid, 0)) for cid, (topic, sid) in self.channels.items()}

    def _events(self, wanted: set[str] | None = None) -> Iterator[tuple[int, int, Any, int, int]]:
        """(log time ns, channel id, buffer, data start, data end) of every readable message; with ``wanted``
        (topics), chunks the index shows hold none of them are not read, and chunk messages of other topics
        may be left out."""
        summary = self._summary()
        if summary is not None and summary.chunk_indexes:
            self._learn(summary)
            return self._indexed(summary.chunk_indexes, wanted)
        return self._linear(wanted)

    def _summary(self) -> Any:
        """The mcap library's Summary, None when the file has none or it cannot be read (noted)."""
        from mcap.reader import SeekingReader

        try:
            self.file.seek(0)
            summary = SeekingReader(self.file).get_summary()
        except Exception as e:  # noqa: BLE001 - any failure means: read without the index
            why = f"{type(e).__name__}: {e}"
            self.log.note(f"{self.name}: no readable summary ({why[:80]}); read front to back")
            return None
        if summary is not None and any(ci.chunk_start_offset + ci.chunk_length > self.size
                                       for ci in summary.chunk_indexes):
            self.log.note(f"{self.name}: summary points past the end of the file; read front to back")
            return None
        return summary

    def _learn(self, summary: Any) -> None:
        self.schemas.update({sid: s.name for sid, s in summary.schemas.items()})
        self.channels.update({cid: (c.topic, c.schema_id) for cid, c in summary.channels.items()})

    # ---------------------------------------------------------------- with the chunk index
    def _indexed(self, indexes: list, wanted: set[str] | None) -> Iterator[tuple[int, int, Any, int, int]]:
        """Chunks in log-time order, their messages merged by log time (ties: file order)."""
        heap: list = [(ci.message_start_time, 0, ci.chunk_start_offset, 0, ci) for ci in indexes
                      if not self._none_wanted(ci, wanted)]
        self.log.chunks_skipped += len(indexes) - len(heap)
        heapq.heapify(heap)
        while heap:
            t, kind, offset, seq, item = heapq.heappop(heap)
            if kind == 1:
                yield item
                continue
            for k, msg in enumerate(sorted(self._indexed_chunk(item, wanted), key=lambda m: m[0])):
                heapq.heappush(heap, (msg[0], 1, offset, k, msg))

    def _none_wanted(self, ci: Any, wanted: set[str] | None) -> bool:
        """The chunk's message indexes name only known channels, none of a wanted topic (no index: read it)."""
        ids = set(ci.message_index_offsets or ())
        return (wanted is not None and bool(ids) and ids <= self.channels.keys()
                and not any(self.channels[cid][0] in wanted for cid in ids))

    def _indexed_chunk(self, ci: Any, wanted: set[str] | None) -> list[tuple[int, int, Any, int, int]]:
        """Messages of the chunk of an index entry; its records are located from the index (not the possibly
        damaged header), checked against the header, and read record by record when anything disagrees."""
        start = ci.chunk_start_offset + 9 + 32 + len(ci.compression.encode()) + 8
        head = self._chunk_head(ci.chunk_start_offset)
        agrees = (head is not None and head.start == start and head.end == start + ci.compressed_size
                  and head.compression == ci.compression and ci.chunk_start_offset + ci.chunk_length == head.end)
        chunk = _ChunkHead(ci.message_start_time, ci.message_end_time, ci.uncompressed_size,
                           head.crc if agrees else 0, ci.compression, start, start + ci.compressed_size)
        return self._chunk_messages(chunk, ci.chunk_start_offset, "" if agrees else "header does not match the index",
                                    wanted)

    # ---------------------------------------------------------------- chunks
    def _chunk_head(self, pos: int) -> _ChunkHead | None:
        """The chunk record at pos when its fields agree with each other and its length (its records may run
        past the end of the file: a truncated chunk), else None."""
        buf = self.buf
        head = 9 + _CHUNK_HEAD.size  # opcode, length, then the fixed fields up to the compression name
        if pos + head > self.size or buf[pos] != OP_CHUNK:
            return None
        (length,) = _U64.unpack_from(buf, pos + 1)
        t0, t1, size, crc, n = _CHUNK_HEAD.unpack_from(buf, pos + 9)
        if n > 8 or pos + head + n + 8 > self.size or t0 > t1:
            return None
        compression = bytes(buf[pos + head:pos + head + n]).decode("ascii", "replace")
        (records,) = _U64.unpack_from(buf, pos + head + n)
        if (compression not in COMPRESSIONS or _CHUNK_HEAD.size + n + 8 + records != length
                or (not compression and size != records)):
            return None
        start = pos + head + n + 8
        return _ChunkHead(t0, t1, size, crc, compression, start, start + records)

    def _chunk_messages(self, chunk: _ChunkHead, at: int, problem: str, wanted: set[str] | None = None
                        ) -> list[tuple[int, int, Any, int, int]]:
        """Messages of the chunk at byte ``at`` (of the ``wanted`` topics; None all): decompressed (a truncated
        zstd/lz4 chunk as far as it goes), CRC-checked, records read one by one with a search past damaged ones;
        a damage is noted once. The chunk's mapped pages are given back (_release): messages of an uncompressed
        chunk are copied out of the map first."""
        data, start, end, data_problem = self._chunk_data(chunk)
        skipped = self.log.bytes_skipped
        out = [] if data is None else list(self._records(data, start, end, chunk.t0, chunk.t1))
        skipped = self.log.bytes_skipped - skipped
        problems = [p for p in (problem, data_problem, f"{skipped} bytes of damaged records" if skipped else "") if p]
        if problems:
            self.log.chunks_damaged += 1
            self.log.chunks_lost += not out
            self.log.damage(f"{self.name}: chunk at byte {at}: {'; '.join(problems)}; {len(out)} messages kept")
        if wanted is not None:
            out = [m for m in out if self.channels.get(m[1], ("",))[0] in wanted]
        if data is self.buf:
            out = [(t, cid, bytes(buf[a:b]), 0, b - a) for t, cid, buf, a, b in out]
        self._release(at, chunk.end)
        return out

    def _release(self, start: int, end: int) -> None:
        """Give back the mapped pages of bytes [start, end), read already: the process's resident memory stays
        the same over a bag of any size instead of growing by the file (they are read again from the file if
        touched; MADV_DONTNEED on a read-only file mapping loses nothing)."""
        if not hasattr(mmap, "MADV_DONTNEED"):
            return
        start = max(0, start - RELEASE_BEHIND)
        first, end = start - start % mmap.PAGESIZE, min(end, self.size)
        if end > first:
            try:
                self.buf.madvise(mmap.MADV_DONTNEED, first, end - first)
            except OSError:  # EINVAL on locked memory (mlockall, as real-time processes do): keep the pages
                pass

    def _chunk_data(self, chunk: _ChunkHead) -> tuple[Any, int, int, str]:
        """(buffer, start, end, problem): the records at buffer[start:end], in the mapped file (uncompressed)
        or in the decompressed bytes; buffer None when nothing can be decompressed."""
        cut = chunk.end > self.size
        if chunk.compression:
            raw = bytes(self.buf[chunk.start:min(chunk.end, self.size)])
            try:
                data = _decompress(chunk.compression, raw, chunk.uncompressed)
            except Exception as e:  # noqa: BLE001 - every codec raises its own type
                return None, 0, 0, f"cannot decompress ({type(e).__name__}: {e})"
            start, end, cut = 0, len(data), cut or len(data) < chunk.uncompressed
        else:
            data, start, end = self.buf, chunk.start, min(chunk.end, self.size)
        if cut:
            return data, start, end, "cut by the end of the file"
        if chunk.crc and zlib.crc32(memoryview(data)[start:end]) != chunk.crc:  # a view: the mapped file uncopied
            return data, start, end, "CRC mismatch; read record by record"
        return data, start, end, ""

    def _records(self, buf: Any, pos: int, end: int, t0: int, t1: int) -> Iterator[tuple[int, int, Any, int, int]]:
        """Messages of the records in buf[pos:end] (a chunk's), learning schemas and channels; past a damaged
        record, the next plausible message record."""
        while pos + 9 <= end:
            op = buf[pos]
            (length,) = _U64.unpack_from(buf, pos + 1)
            nxt = pos + 9 + length
            ok = nxt <= end and (op in (OP_SCHEMA, OP_CHANNEL) and self._definition(op, buf, pos + 9, nxt)
                                 or op == OP_MESSAGE and self._message_ok(buf, pos, end, t0, t1))
            if not ok:
                found = self._search_message(buf, pos + 1, end, t0, t1)
                self.log.bytes_skipped += found - pos
                pos = found
                continue
            if op == OP_MESSAGE:
                yield self._message(buf, pos + 9, nxt)
            pos = nxt

    def _message_ok(self, buf: Any, pos: int, end: int, t0: int, t1: int) -> bool:
        """A plausible message record at pos: it fits, its channel is known, its log time is in [t0, t1]."""
        if pos + 9 + MESSAGE_HEAD > end or buf[pos] != OP_MESSAGE:
            return False
        (length,) = _U64.unpack_from(buf, pos + 1)
        (cid,) = _U16.unpack_from(buf, pos + 9)
        (t,) = _U64.unpack_from(buf, pos + 15)
        return MESSAGE_HEAD <= length and pos + 9 + length <= end and cid in self.channels and t0 <= t <= t1

    def _search_message(self, buf: Any, pos: int, end: int, t0: int, t1: int) -> int:
        """Position of the next plausible message record at or after pos, else end."""
        while True:
            pos = buf.find(b"\x05", pos, end)
            if pos < 0:
                return end
            if self._message_ok(buf, pos, end, t0, t1):
                return pos
            pos += 1

    def _message(self, buf: Any, body: int, end: int) -> tuple[int, int, Any, int, int]:
        (cid,) = _U16.unpack_from(buf, body)
        (t,) = _U64.unpack_from(buf, body + 6)
        return t, cid, buf, body + MESSAGE_HEAD, end

    def _definition(self, op: int, buf: Any, pos: int, end: int) -> bool:
        """Learn a schema or channel record at buf[pos:end]; False when it does not parse."""
        try:
            (rid,) = _U16.unpack_from(buf, pos)
            if op == OP_SCHEMA:
                self.schemas.setdefault(rid, _string(buf, pos + 2, end)[0])
            else:
                (sid,) = _U16.unpack_from(buf, pos + 2)
                topic, _ = _string(buf, pos + 4, end)
                self.channels.setdefault(rid, (topic, sid))
            return True
        except (ValueError, struct.error, UnicodeDecodeError):
            return False

    # ---------------------------------------------------------------- without the index
    def _linear(self, wanted: set[str] | None = None) -> Iterator[tuple[int, int, Any, int, int]]:
        """Records front to back; past a damaged one, the next chunk whose header is consistent."""
        buf, pos = self.buf, len(MCAP_MAGIC)
        if bytes(buf[:8]) != MCAP_MAGIC:
            self.log.damage(f"{self.name}: no MCAP magic; searching for chunks")
            pos = self._search_chunk(0)
        while pos + 9 <= self.size:
            op = buf[pos]
            (length,) = _U64.unpack_from(buf, pos + 1)
            if op in (OP_FOOTER, OP_DATA_END):
                return
            head = self._chunk_head(pos) if op == OP_CHUNK else None
            if head is not None:
                yield from self._chunk_messages(head, pos, "", wanted)
                pos = head.end
            elif self._top_record_ok(op, pos, length):
                if op == OP_MESSAGE:
                    yield self._message(buf, pos + 9, pos + 9 + length)
                pos += 9 + length
            else:
                found = self._search_chunk(pos + 1)
                self.log.bytes_skipped += found - pos
                self.log.damage(f"{self.name}: damaged record at byte {pos}; {found - pos} bytes skipped "
                                f"to the next chunk")
                pos = found

    def _top_record_ok(self, op: int, pos: int, length: int) -> bool:
        """A record outside chunks that fits and, when it can be checked, parses (messages: a known channel)."""
        end = pos + 9 + length
        if not 0x01 <= op <= 0x0F or op == OP_CHUNK or end > self.size:
            return False
        if op in (OP_SCHEMA, OP_CHANNEL):
            return self._definition(op, self.buf, pos + 9, end)
        if op == OP_MESSAGE:
            return self._message_ok(self.buf, pos, end, 0, 2**64 - 1)
        if op == OP_MESSAGE_INDEX:
            return length >= 6 and _U32.unpack_from(self.buf, pos + 11)[0] == length - 6
        return True

    def _search_chunk(self, pos: int) -> int:
        """Position of the next consistent chunk header at or after pos, else the file size."""
        while True:
            pos = self.buf.find(b"\x06", pos)
            if pos < 0:
                return self.size
            if self._chunk_head(pos) is not None:
                return pos
            pos += 1


def _decompress(compression: str, raw: bytes, size: int) -> bytes:
    """Decompressed chunk records; a truncated zstd or lz4 frame gives what it holds."""
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompressobj().decompress(raw)
    import lz4.frame

    return lz4.frame.LZ4FrameDecompressor().decompress(raw, max_length=size)


# ------------------------------------------------------------------ sqlite3
def _connect(file: Path) -> sqlite3.Connection:
    """Read-only connection; immutable (no locks, no journal) unless a write-ahead log sits beside the file.
    writable_schema lets SQLite open a file shorter than its header says (a truncated bag) instead of calling
    the whole file malformed; the connection is read-only, nothing can be written."""
    immutable = "" if Path(str(file) + "-wal").exists() else "&immutable=1"
    con = sqlite3.connect(f"file:{quote(str(file.resolve()))}?mode=ro{immutable}", uri=True)
    con.execute("PRAGMA writable_schema = ON")
    return con


def _sqlite_tables(con: sqlite3.Connection, file: Path, log: ReadLog) -> dict[int, tuple[str, str]] | None:
    """{topic id: (name, type)} of the topics table, None when it cannot be read (noted)."""
    try:
        return {int(i): (str(n), str(t)) for i, n, t in con.execute("SELECT id, name, type FROM topics")}
    except sqlite3.DatabaseError as e:
        log.damage(f"{file.name}: topics table unreadable ({e})")
        return None


def _row_keys(con: sqlite3.Connection, file: Path, log: ReadLog) -> tuple[list[tuple[int, int, int]], float]:
    """(timestamp ns, id, topic id) of every readable row, in id order, and the first unreadable id (inf when
    none); past an unreadable id the cursor seeks on (an id at a time, at most MAX_BAD_IDS in a row)."""
    keys, last, bad, first_error, first_bad = [], 0, 0, None, float("inf")
    while bad <= MAX_BAD_IDS:
        try:
            for rid, tid, ts in con.execute("SELECT id, topic_id, timestamp FROM messages WHERE id > ? ORDER BY id",
                                            (last,)):
                keys.append((int(ts), int(rid), int(tid)))
                log.rows_skipped += bad  # ids passed over before this readable row
                last, bad = int(rid), 0
            break
        except sqlite3.DatabaseError as e:
            first_error = first_error or f"after row id {last}: {e}"
            first_bad = min(first_bad, last + 1)
            last, bad = last + 1, bad + 1
    if first_error:
        log.damage(f"{file.name}: messages table damaged ({first_error}){_truncation(file)}; "
                   f"{len(keys)} rows readable" + (", the rest unreadable" if bad > MAX_BAD_IDS else ""))
    return keys, first_bad


def _truncation(file: Path) -> str:
    """', file truncated: n of m pages' when the file is shorter than its header says, else ''."""
    with open(file, "rb") as f:
        head = f.read(100)
    if len(head) < 100:
        return ", file truncated inside its header"
    page = int.from_bytes(head[16:18], "big")
    page = 65536 if page in (0, 1) else page  # SQLite writes 64 KiB pages as 1
    pages = int.from_bytes(head[28:32], "big")
    have = file.stat().st_size // page
    return f", file truncated: {have} of {pages} pages" if have < pages else ""


def _sqlite_messages(file: Path, wanted: set[str] | None, log: ReadLog) -> Iterator[Raw]:
    """Readable rows of the wanted topics in (timestamp, id) order."""
    con = _connect(file)
    try:
        topics = _sqlite_tables(con, file, log)
        if topics is None:
            return
        keep = {tid for tid, (name, _) in topics.items() if wanted is None or name in wanted}
        keys, first_bad = _row_keys(con, file, log)
        for ts, rid, tid in sorted(keys):
            if tid not in keep:
                continue
            try:
                (data,) = con.execute("SELECT data FROM messages WHERE id = ?", (rid,)).fetchone()
            except (sqlite3.DatabaseError, TypeError) as e:
                log.rows_skipped += 1
                log.damage(f"{file.name}: row {rid} unreadable ({e})")
                first_bad = min(first_bad, rid)
                continue
            log.message(past_damage=rid > first_bad)
            name, kind = topics[tid]
            yield name, kind, ts, bytes(data)
    finally:
        con.close()


def _sqlite_topics(file: Path, log: ReadLog) -> dict[str, tuple[str, int]]:
    """{topic: (type, rows)}: counted by sqlite, or over the readable rows of a damaged table."""
    con = _connect(file)
    try:
        topics = _sqlite_tables(con, file, log) or {}
        try:
            counts = dict(con.execute("SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id").fetchall())
        except sqlite3.DatabaseError:
            counts = {}
            for _, _, tid in _row_keys(con, file, ReadLog())[0]:
                counts[tid] = counts.get(tid, 0) + 1
        return {name: (kind, int(counts.get(tid, 0))) for tid, (name, kind) in topics.items()}
    finally:
        con.close()
