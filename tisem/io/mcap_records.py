"""The record layer of an MCAP file, damaged or not: Schema, Channel and Message records, and
a report of everything that could not be used.

The stock `mcap` reader returns nothing for a truncated file (reading the footer fails first),
returns corrupted bytes silently unless asked to check CRCs, and then stops at the first bad
chunk. So records are read here: through the chunk index when the summary is intact (a chunk
whose own header is damaged cannot derail the others), linearly otherwise. Each chunk is
decompressed and CRC-checked on its own; a bad one is skipped and its loss counted from the
message index records; a file cut short gives every message that was completely written (also
from the partial last chunk, whose prefix is intact); everything lost goes into a `ReadReport`.
"""
from __future__ import annotations

import io
import itertools
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema

from tisem.errors import DatasetError, SkippedScan

MAGIC = b"\x89MCAP0\r\n"


# ---- what was lost ---------------------------------------------------------------------------

@dataclass
class Loss:
    """One piece of the file that could not be used."""

    where: str                      # e.g. "chunk at byte 1234 (log time 1.0-1.2 s)"
    what: str                       # why it was lost
    messages: int | None = None     # how many messages it held, None when unknowable
    topics: Counter = field(default_factory=Counter)

    def line(self) -> str:
        held = ("" if self.messages is None else
                f": {self.messages} message(s) lost" +
                (f" ({', '.join(f'{n} on {t}' for t, n in sorted(self.topics.items()))})"
                 if self.topics else ""))
        return f"{self.where}: {self.what}{held}"


@dataclass
class ReadReport:
    """Everything the reader could not use, and why. Empty `losses` = the file was whole."""

    path: str = ""
    losses: list[Loss] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    messages: Counter = field(default_factory=Counter)       # topic -> messages recovered
    skipped: list[SkippedScan] = field(default_factory=list)
    unknown_labels: int = 0          # points whose label id is unknown (-> 0)
    unknown_gt_labels: int = 0
    partial_chunk_messages: int = 0  # recovered from a chunk the file ends inside

    def lines(self) -> list[str]:
        out = [loss.line() for loss in self.losses] + list(self.notes)
        if self.partial_chunk_messages:
            out.append(f"{self.partial_chunk_messages} message(s) recovered from the incomplete "
                       f"last chunk (its CRC cannot be checked; cut files keep their bytes)")
        out += [f"skipped scan {s.index} ({s.name}): {s.reason}" for s in self.skipped]
        if self.unknown_labels:
            out.append(f"{self.unknown_labels} point(s) with an unknown label id mapped to 0")
        if self.unknown_gt_labels:
            out.append(f"{self.unknown_gt_labels} point(s) with an unknown ground-truth id -> 0")
        return out

    def to_dict(self) -> dict:
        return {"path": self.path, "damaged": bool(self.losses),
                "losses": [loss.line() for loss in self.losses], "notes": list(self.notes),
                "messages": dict(self.messages),
                "skipped_scans": [{"index": s.index, "name": s.name, "reason": s.reason}
                                  for s in self.skipped],
                "unknown_labels": self.unknown_labels,
                "unknown_gt_labels": self.unknown_gt_labels,
                "partial_chunk_messages": self.partial_chunk_messages}


# ---- records and chunks from bytes -----------------------------------------------------------

class _BadChunk(Exception):
    """A chunk whose bytes cannot be trusted (the message says why); it is skipped whole."""


@dataclass
class LostMessages:
    """Yielded where a skipped chunk held `count` messages of a channel (from its message
    index), so that readers can keep numbering messages as in the intact file."""

    channel_id: int
    count: int
    where: str


def _message(buf) -> Message:
    channel_id, sequence, log_time, publish_time = struct.unpack_from("<HIQQ", buf, 0)
    return Message(channel_id=channel_id, sequence=sequence, log_time=log_time,
                   publish_time=publish_time, data=bytes(buf[22:]))


def _record(opcode: int, buf):
    """Schema, Channel or Message from a record's content; None for every other record."""
    if opcode == Opcode.MESSAGE:
        return _message(buf)
    if opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
        stream = ReadDataStream(io.BytesIO(bytes(buf)))
        return Schema.read(stream) if opcode == Opcode.SCHEMA else Channel.read(stream)
    return None


def _chunk_fields(buf):
    """(start, end, uncompressed size, crc, compression, data) of a chunk record's content.
    `data` may be shorter than declared when the file ends inside the chunk."""
    start, end, size, crc, clen = struct.unpack_from("<QQQII", buf, 0)
    compression = bytes(buf[32:32 + clen]).decode()
    (dlen,) = struct.unpack_from("<Q", buf, 32 + clen)
    data = memoryview(buf)[40 + clen:40 + clen + dlen]          # a view: chunks are big
    return start, end, size, crc, compression, data, dlen


def _inflate(compression: str, data, size: int, complete: bool):
    if compression == "":
        return data
    if compression == "zstd":
        if complete:
            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        return zstandard.ZstdDecompressor().decompressobj().decompress(bytes(data))
    if compression == "lz4":
        if complete:
            return lz4.frame.decompress(data)       # takes the buffer: no copy of the input
        return lz4.frame.LZ4FrameDecompressor().decompress(bytes(data))
    raise _BadChunk(f"unsupported compression {compression!r}")


def _inner_records(data: bytes, complete: bool) -> list:
    """Records inside a decompressed chunk. In a complete chunk a record that overruns it means
    corruption (the whole chunk is rejected); in a partial one it is where the cut was."""
    out, pos, view = [], 0, memoryview(data)
    while pos < len(data):
        if pos + 9 > len(data):
            break
        opcode, length = struct.unpack_from("<BQ", data, pos)
        end = pos + 9 + length
        if end > len(data):
            break
        rec = _record(opcode, view[pos + 9:end])
        if rec is not None:
            out.append(rec)
        pos = end
    if complete and pos != len(data):
        raise _BadChunk("its records do not fill it exactly")
    return out


def _read_at(f, pos: int, n: int) -> bytes:
    f.seek(pos)
    return f.read(n)


def _time_range(start: int, end: int) -> str:
    return f"log time {start / 1e9:.3f}-{end / 1e9:.3f} s"


# the records the linear reader needs the content of (others are skipped unread)
_DATA_OPCODES = (Opcode.CHUNK, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE)

# untrusted bytes: any of these from a decompressor or parser means "this chunk is bad"
_CHUNK_ERRORS = (_BadChunk, zstandard.ZstdError, RuntimeError, struct.error, ValueError,
                 UnicodeDecodeError, McapError, EOFError)


class McapRecords:
    """Schema, Channel and Message records of an MCAP file, in file order, surviving damage."""

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        try:
            self.size = Path(path).stat().st_size
        except OSError as e:
            raise DatasetError(f"{path}: cannot open ({e.strerror})") from None
        if self.size == 0:
            raise DatasetError(f"{path}: the file is empty")
        with open(path, "rb") as f:
            if f.read(8) != MAGIC:
                raise DatasetError(f"{path}: not an MCAP file (it does not start with the MCAP "
                                   f"magic bytes)")
            try:  # the summary: schemas, channels, chunk index, message counts
                f.seek(0)
                self.summary = make_reader(f).get_summary()
            # a damaged summary or footer makes the stock reader raise any of these; without a
            # summary the file is read linearly
            except (McapError, ValueError, struct.error, OSError, UnicodeDecodeError):
                self.summary = None
        self._no_crc = 0

    def records(self, report: ReadReport) -> Iterator[Schema | Channel | Message | LostMessages]:
        """Yield Schema, Channel, Message and LostMessages records; count messages per topic
        and append what was dropped to `report`."""
        channels: dict[int, Channel] = {}
        orphans = Counter()
        self._no_crc = 0
        with open(self.path, "rb") as f:
            if self.summary is not None:
                # the summary repeats schemas and channels: they survive a lost chunk
                source = [*self.summary.schemas.values(), *self.summary.channels.values()]
                if self.summary.chunk_indexes:
                    source = itertools.chain(source, self._indexed(f, report))
                else:
                    report.notes.append("no chunk index: the file was read linearly")
                    source = itertools.chain(source, self._linear(f, report))
            else:
                report.notes.append("no summary section (cut short, or written without one): "
                                    "the file was read linearly")
                source = self._linear(f, report)
            for rec in source:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is None:                    # its Channel record was in a lost chunk
                        orphans[rec.channel_id] += 1
                        continue
                    report.messages[ch.topic] += 1
                yield rec
        if self._no_crc:
            report.notes.append(f"{self._no_crc} chunk(s) carry no CRC (rosbag2's default): "
                                f"corrupted bytes inside them cannot be detected")
        for cid, n in orphans.items():
            report.losses.append(Loss(f"channel {cid}", "its Channel record was lost, so its "
                                      "messages cannot be decoded", messages=n,
                                      topics=Counter({f"channel {cid}": n})))
        self._check_counts(report)

    # -- chunks
    def _chunk(self, buf, complete: bool = True) -> list:
        _, _, size, crc, compression, data, _ = _chunk_fields(buf)
        data = _inflate(compression, data, size, complete)
        if complete:
            if len(data) != size:
                raise _BadChunk(f"it inflates to {len(data)} bytes, not {size}")
            if crc == 0:
                self._no_crc += 1
            elif zlib.crc32(data) != crc:
                raise _BadChunk("its CRC does not match: corrupted bytes")
        return _inner_records(data, complete)

    def _safe_chunk(self, buf, where: str, report: ReadReport) -> tuple[list, Loss | None]:
        try:
            return self._chunk(buf), None
        except _CHUNK_ERRORS as e:
            why = str(e) if isinstance(e, _BadChunk) else f"{type(e).__name__}: {e}"
            loss = Loss(where, f"chunk skipped ({why})", messages=0)
            report.losses.append(loss)
            return [], loss

    def _indexed(self, f, report: ReadReport) -> Iterator:
        """Chunk by chunk through the chunk index: a chunk's damage stays in that chunk."""
        for ci in sorted(self.summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            pos = ci.chunk_start_offset
            span = _time_range(ci.message_start_time, ci.message_end_time)
            where = f"chunk at byte {pos} ({span})"
            ok = 9 <= ci.chunk_length and pos + ci.chunk_length <= self.size
            if ok:
                opcode, length = struct.unpack("<BQ", _read_at(f, pos, 9))
                ok = opcode == Opcode.CHUNK and 9 + length == ci.chunk_length
            if ok:
                records, loss = self._safe_chunk(f.read(length), where, report)
                yield from records
            else:
                loss = Loss(where, "chunk skipped (its record header does not match the index)",
                            messages=0)
                report.losses.append(loss)
            if loss is not None:
                for off in ci.message_index_offsets.values():
                    lost = self._count_lost(f, off, loss, self.summary.channels)
                    if lost is not None:
                        yield lost

    def _count_lost(self, f, pos: int, loss: Loss, channels: dict) -> LostMessages | None:
        """Add the messages a MessageIndex record (at `pos`) lists to a lost chunk's count."""
        try:
            opcode, length, channel_id, nbytes = struct.unpack("<BQHI", _read_at(f, pos, 15))
        except struct.error:
            return None
        if opcode != Opcode.MESSAGE_INDEX or pos + 9 + length > self.size:
            return None
        n = nbytes // 16                                # (log_time, offset) pairs
        ch = channels.get(channel_id)
        loss.messages = (loss.messages or 0) + n
        loss.topics[ch.topic if ch else f"channel {channel_id}"] += n
        return LostMessages(channel_id, n, loss.where) if n else None

    def _linear(self, f, report: ReadReport) -> Iterator:
        """Record after record from the start; stops where the file is cut or unparseable."""
        pos, size = 8, self.size
        last_loss: Loss | None = None           # the MessageIndex records after a bad chunk
        channels: dict[int, Channel] = dict(self.summary.channels) if self.summary else {}
        while True:
            if pos == size:
                report.losses.append(Loss(f"end of file (byte {size})", "no data-end record or "
                                          "footer: the recording was cut short at a record "
                                          "boundary; what followed is unknown"))
                return
            if pos + 9 > size:
                report.losses.append(Loss(f"byte {pos}", f"the file ends inside a record header "
                                          f"({size - pos} of 9 bytes): cut short"))
                return
            opcode, length = struct.unpack("<BQ", _read_at(f, pos, 9))
            end = pos + 9 + length
            if opcode == 0 or 0x10 < opcode < 0x80:   # 0x80-0xff are private, legal records
                report.losses.append(Loss(f"byte {pos}", f"invalid record opcode {opcode:#x}: "
                                          f"the file is corrupt from here on"))
                return
            if end > size:
                yield from self._cut_record(f, pos, opcode, length, report)
                return
            if opcode == Opcode.MESSAGE_INDEX:
                if last_loss is not None:
                    lost = self._count_lost(f, pos, last_loss, channels)
                    if lost is not None:
                        yield lost
                pos = end
                continue
            buf = f.read(length) if opcode in _DATA_OPCODES else b""
            if opcode == Opcode.CHUNK:
                where = f"chunk at byte {pos}"
                if length >= 16:
                    where += f" ({_time_range(*struct.unpack_from('<QQ', buf, 0))})"
                records, last_loss = self._safe_chunk(buf, where, report)
                for rec in records:
                    if isinstance(rec, Channel):
                        channels[rec.id] = rec
                    yield rec
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):   # unchunked files
                try:
                    rec = _record(opcode, buf)
                    if isinstance(rec, Channel):
                        channels[rec.id] = rec
                    yield rec
                except _CHUNK_ERRORS as e:
                    report.losses.append(Loss(f"record at byte {pos}", f"unparseable "
                                              f"({type(e).__name__})", messages=None))
            elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                return                                  # the summary follows: data complete
            pos = end

    def _cut_record(self, f, pos: int, opcode: int, length: int, report: ReadReport):
        """The file ends inside a record: say so, and yield what a cut chunk still holds."""
        have = self.size - pos - 9
        try:
            name = Opcode(opcode).name.lower().replace("_", " ")
        except ValueError:
            name = f"opcode {opcode:#x}"
        loss = Loss(f"byte {pos}", f"the file ends inside a {name} record ({have} of {length} "
                    f"bytes present): cut short; anything after it is lost")
        report.losses.append(loss)
        if opcode != Opcode.CHUNK:
            return
        buf = _read_at(f, pos + 9, have)
        try:
            start, stop = struct.unpack_from("<QQ", buf, 0)
            loss.where = f"chunk at byte {pos} ({_time_range(start, stop)})"
            records = _inner_records(self._chunk_prefix(buf), complete=False)
        except _CHUNK_ERRORS:
            return
        report.partial_chunk_messages += sum(isinstance(r, Message) for r in records)
        yield from records

    @staticmethod
    def _chunk_prefix(buf) -> bytes:
        """What the first bytes of a cut chunk inflate to (a prefix of its records)."""
        _, _, size, _, compression, data, _ = _chunk_fields(buf)
        return _inflate(compression, data, size, complete=False)

    def _check_counts(self, report: ReadReport) -> None:
        """With a summary, compare what was read with the recorded message counts."""
        stats = self.summary.statistics if self.summary else None
        if stats is None:
            return
        missing = Counter()
        for cid, n in stats.channel_message_counts.items():
            ch = self.summary.channels.get(cid)
            topic = ch.topic if ch else f"channel {cid}"
            if report.messages[topic] < n:
                missing[topic] = n - report.messages[topic]
        accounted = Counter()
        for loss in report.losses:
            accounted.update(loss.topics)
        unaccounted = missing - accounted
        if unaccounted:
            report.losses.append(Loss("summary statistics", "messages counted in the summary "
                                      "were not found", messages=sum(unaccounted.values()),
                                      topics=unaccounted))
