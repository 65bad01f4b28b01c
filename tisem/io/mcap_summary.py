"""MCAP records from untrusted bytes, and the footer and summary section of a file.

Every field is read through `Fields`, which checks each length against the bytes that are
really there before taking them: a damaged length (2^32, 2^63) is a `Malformed` record, never a
huge allocation or a short read taken for a whole one. The summary (schemas, channels, chunk
index, statistics) is used only when its CRC matches (or it carries none) and it holds nothing
but summary records; otherwise `read_summary` says why, and the file is read from its data.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from typing import BinaryIO

from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Schema, Statistics

MAGIC = b"\x89MCAP0\r\n"
RECORD_HEADER = 9  # opcode u8 + content length u64
FOOTER_RECORD = RECORD_HEADER + 20  # summary start, offset start, crc
DATA_END_RECORD = RECORD_HEADER + 4  # the data section's crc
TAIL = FOOTER_RECORD + len(MAGIC)  # what a whole file ends with
SUMMARY_OPCODES = frozenset(
    (
        Opcode.SCHEMA,
        Opcode.CHANNEL,
        Opcode.CHUNK_INDEX,
        Opcode.ATTACHMENT_INDEX,
        Opcode.METADATA_INDEX,
        Opcode.STATISTICS,
        Opcode.SUMMARY_OFFSET,
    )
)
_CRC_PIECE = 1 << 22  # bytes per read while checking a CRC


class Malformed(ValueError):
    """Bytes that do not parse as the record they should be (the message says where)."""


def valid_opcode(opcode: int) -> bool:
    """Opcodes the format defines (0x01-0x10) or reserves for private records (0x80-0xff)."""
    return 0x01 <= opcode <= 0x10 or opcode >= 0x80


def opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower().replace("_", " ")
    except ValueError:
        return f"opcode {opcode:#x}"


class Fields:
    """A cursor over one record's content that refuses to read past its end."""

    def __init__(self, buf, what: str) -> None:
        self.buf = memoryview(buf)
        self.pos = 0
        self.what = what

    @property
    def left(self) -> int:
        return len(self.buf) - self.pos

    def take(self, n: int) -> memoryview:
        if n > self.left:
            raise Malformed(
                f"{self.what}: a field at byte {self.pos} of the record needs {n} "
                f"bytes, {self.left} are left"
            )
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def u16(self) -> int:
        return struct.unpack("<H", self.take(2))[0]

    def u32(self) -> int:
        return struct.unpack("<I", self.take(4))[0]

    def u64(self) -> int:
        return struct.unpack("<Q", self.take(8))[0]

    def text(self) -> str:
        raw = self.take(self.u32())
        try:
            return bytes(raw).decode("utf-8")
        except UnicodeDecodeError:
            raise Malformed(f"{self.what}: a string is not UTF-8") from None

    def blob(self, length_bytes: int = 4) -> memoryview:
        return self.take(self.u32() if length_bytes == 4 else self.u64())

    def id_map(self) -> dict[int, int]:
        """A u32-byte-length-prefixed map of u16 -> u64 (chunk index and statistics)."""
        inner = Fields(self.blob(), self.what)
        out = {}
        while inner.left:
            key = inner.u16()
            out[key] = inner.u64()
        return out

    def text_map(self) -> dict[str, str]:
        inner = Fields(self.blob(), self.what)
        out = {}
        while inner.left:
            key = inner.text()
            out[key] = inner.text()
        return out


# ---- record contents -------------------------------------------------------------------------


def _done(f: Fields, exact: bool) -> None:
    """Later versions of the format may append fields to a record: extra bytes are allowed,
    except where a record found by searching the bytes must prove it is one."""
    if exact and f.left:
        raise Malformed(f"{f.what}: {f.left} byte(s) after its last field")


def parse_schema(buf, exact: bool = False) -> Schema:
    f = Fields(buf, "schema record")
    schema = Schema(id=f.u16(), name=f.text(), encoding=f.text(), data=bytes(f.blob()))
    _done(f, exact)
    return schema


def parse_channel(buf, exact: bool = False) -> Channel:
    f = Fields(buf, "channel record")
    channel = Channel(
        id=f.u16(),
        schema_id=f.u16(),
        topic=f.text(),
        message_encoding=f.text(),
        metadata=f.text_map(),
    )
    _done(f, exact)
    return channel


def parse_chunk_index(buf) -> ChunkIndex:
    f = Fields(buf, "chunk index record")
    start, end, offset, length = f.u64(), f.u64(), f.u64(), f.u64()
    offsets = f.id_map()
    return ChunkIndex(
        message_start_time=start,
        message_end_time=end,
        chunk_start_offset=offset,
        chunk_length=length,
        message_index_offsets=offsets,
        message_index_length=f.u64(),
        compression=f.text(),
        compressed_size=f.u64(),
        uncompressed_size=f.u64(),
    )


def parse_statistics(buf) -> Statistics:
    f = Fields(buf, "statistics record")
    counts = dict(
        message_count=f.u64(),
        schema_count=f.u16(),
        channel_count=f.u32(),
        attachment_count=f.u32(),
        metadata_count=f.u32(),
        chunk_count=f.u32(),
        message_start_time=f.u64(),
        message_end_time=f.u64(),
    )
    return Statistics(channel_message_counts=f.id_map(), **counts)


def parse_message_index(buf) -> tuple[int, int]:
    """(channel id, number of messages) of a MessageIndex record."""
    f = Fields(buf, "message index record")
    channel_id = f.u16()
    entries = f.blob()
    if len(entries) % 16:
        raise Malformed(
            f"message index record: {len(entries)} bytes of entries is not a multiple of 16"
        )
    return channel_id, len(entries) // 16


def attachment_problem(f: BinaryIO, pos: int, length: int) -> str | None:
    """What is wrong with the Attachment record at `pos` (content `length` bytes), or None.
    Its CRC covers its fields and data, which are read piece by piece (tisem does not use
    attachments, so they are only checked)."""
    start = pos + RECORD_HEADER
    f.seek(start)
    fields = Fields(f.read(min(length, 1 << 16)), "attachment record")
    try:
        fields.u64(), fields.u64()
        name = fields.text()
        fields.text()
        size = fields.u64()
        body = fields.pos + size
        if body + 4 > length:
            raise Malformed(f"its data claims {size} bytes, the record holds less")
    except Malformed as e:
        return f"unparseable ({e})"
    f.seek(start + body)
    crc = struct.unpack("<I", f.read(4))[0]
    if crc and crc_of_range(f, start, start + body) != crc:
        return f"{name!r}: its CRC does not match (tisem does not use attachments)"
    return None


# ---- footer and summary ----------------------------------------------------------------------


def read_record(f: BinaryIO, pos: int, end: int) -> tuple[int, bytes] | str:
    """(opcode, content) of the record at `pos`, or why it cannot be one ending by `end`."""
    f.seek(pos)
    head = f.read(RECORD_HEADER)
    if len(head) < RECORD_HEADER:
        return f"the record header at byte {pos} is cut off"
    opcode, length = struct.unpack("<BQ", head)
    if not valid_opcode(opcode):
        return f"invalid record opcode {opcode:#x} at byte {pos}"
    if length > end - pos - RECORD_HEADER:
        return (
            f"the {opcode_name(opcode)} record at byte {pos} claims {length} bytes, more "
            f"than the {end - pos - RECORD_HEADER} left"
        )
    return opcode, f.read(length)


def crc_of_range(f: BinaryIO, start: int, end: int, crc: int = 0) -> int:
    f.seek(start)
    pos = start
    while pos < end:
        piece = f.read(min(_CRC_PIECE, end - pos))
        if not piece:
            break
        crc = zlib.crc32(piece, crc)
        pos += len(piece)
    return crc


@dataclass
class Footer:
    offset: int  # where the footer record starts (the data or summary ends here)
    summary_start: int  # 0 = no summary
    summary_crc: int
    data_end_at: int | None = None  # where the DataEnd record is, when found ...
    data_end_crc: int = 0  # ... and its data-section CRC (0: none)


@dataclass
class Summary:
    """What a trusted summary section gives: the index the data is checked against."""

    start: int
    crc_checked: bool
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunk_indexes: list[ChunkIndex] = field(default_factory=list)
    statistics: Statistics | None = None


def read_footer(f: BinaryIO, size: int) -> Footer | None:
    """The footer of a whole file; None when the file does not end with one (cut short or
    damaged): then it is read from its data to its end."""
    if size < len(MAGIC) + TAIL:
        return None
    f.seek(size - TAIL)
    tail = f.read(TAIL)
    opcode, length, summary_start, _, summary_crc = struct.unpack_from("<BQQQI", tail)
    if tail[-len(MAGIC) :] != MAGIC or opcode != Opcode.FOOTER or length != 20:
        return None
    footer = Footer(size - TAIL, summary_start, summary_crc)
    # the DataEnd record sits right before the summary (or the footer, without one)
    data_end = (
        summary_start if len(MAGIC) <= summary_start <= footer.offset else footer.offset
    ) - DATA_END_RECORD
    if data_end >= len(MAGIC):
        f.seek(data_end)
        opcode, length, crc = struct.unpack("<BQI", f.read(DATA_END_RECORD))
        if opcode == Opcode.DATA_END and length == 4:
            footer.data_end_at, footer.data_end_crc = data_end, crc
    return footer


def read_summary(f: BinaryIO, footer: Footer) -> tuple[Summary | None, str | None]:
    """(summary, None), or (None, why it is not used); (None, None) when there is none."""
    start, end = footer.summary_start, footer.offset
    if start == 0:
        return None, None
    if not len(MAGIC) <= start <= end:
        return None, (
            f"the footer's summary offset {start} lies outside the file's {len(MAGIC)}..{end}"
        )
    if footer.summary_crc:
        crc = crc_of_range(f, start, end + RECORD_HEADER + 16)  # up to the footer's crc field
        if crc != footer.summary_crc:
            return None, "the summary section's CRC does not match (corrupted bytes)"
    summary = Summary(start=start, crc_checked=bool(footer.summary_crc))
    pos = start
    while pos < end:
        rec = read_record(f, pos, end)
        if isinstance(rec, str):
            return None, f"the summary section is malformed: {rec}"
        opcode, content = rec
        if opcode not in SUMMARY_OPCODES:
            return None, (
                f"the summary section holds a {opcode_name(opcode)} record (at byte "
                f"{pos}): its offset in the footer is wrong"
            )
        try:
            if opcode == Opcode.SCHEMA:
                schema = parse_schema(content)
                summary.schemas[schema.id] = schema
            elif opcode == Opcode.CHANNEL:
                channel = parse_channel(content)
                summary.channels[channel.id] = channel
            elif opcode == Opcode.CHUNK_INDEX:
                summary.chunk_indexes.append(parse_chunk_index(content))
            elif opcode == Opcode.STATISTICS:
                summary.statistics = parse_statistics(content)
        except Malformed as e:
            return None, f"the summary section is malformed at byte {pos}: {e}"
        pos += RECORD_HEADER + len(content)
    return summary, None
