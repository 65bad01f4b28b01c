"""A ROS 1 bag read record by record from its start, without its index.

`rosbag record` writes a bag's index (connections, chunk positions) when it closes; a recording
that did not close (the recorder killed, the power lost: `NAME.bag.active`) or a bag cut short
has none, and `rosbags` cannot open it. The records themselves describe the bag (format 2.0):
each is a header of `name=value` fields (`op` says what it is) and a data part; chunks hold the
connection and message records, uncompressed, bz2 or lz4. `Ros1LinearRecords` walks them in
file order and gives `McapScanReader` the same stream `tisem.io.bag_records` gives for other
bags; a chunk the file ends inside gives the records it still holds whole, and the loss is
reported. Message types come from the connections' own definitions.
"""

from __future__ import annotations

import bz2
import mmap
import struct
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import lz4.frame
from mcap.records import Channel, Schema
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.msg import normalize_msgtype

from tisem.errors import DatasetError
from tisem.io.mcap_records import LostMessages, McapMessage, ReadReport
from tisem.io.mcap_report import Loss

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_BAG_HEADER, OP_CHUNK, OP_CONNECTION = 0x02, 0x03, 0x05, 0x07
MAX_CHUNK_BYTES = 1 << 31  # a chunk declaring more is damage


class Malformed(ValueError):
    """Bytes that are no record (a damaged header, a length past the data)."""


def _header(buf, at: int, end: int) -> tuple[dict[str, bytes], int]:
    """The fields of the record header at `at` (its 4-byte length first) and where its data
    length starts."""
    if at + 4 > end:
        raise Malformed("a record header length past the end")
    (size,) = struct.unpack_from("<I", buf, at)
    stop = at + 4 + size
    if stop > end:
        raise Malformed(f"a record header of {size} bytes past the end")
    return _fields(buf, at + 4, stop), stop


def _fields(buf, pos: int, stop: int) -> dict[str, bytes]:
    """The `name=value` fields in buf[pos:stop], each after its 4-byte length."""
    fields = {}
    while pos < stop:
        if pos + 4 > stop:
            raise Malformed("a header field length past its header")
        (n,) = struct.unpack_from("<I", buf, pos)
        field = bytes(buf[pos + 4 : pos + 4 + n])
        if pos + 4 + n > stop or b"=" not in field:
            raise Malformed("a header field that is no name=value")
        name, value = field.split(b"=", 1)
        fields[name.decode("ascii", "replace")] = value
        pos += 4 + n
    return fields


def _u32(fields: dict[str, bytes], name: str) -> int:
    value = fields.get(name, b"")
    if len(value) != 4:
        raise Malformed(f"a record without a 4-byte {name!r}")
    return struct.unpack("<I", value)[0]


def _framed(buf, at: int, end: int, cut: str) -> tuple[dict[str, bytes], int, int]:
    """(header fields, data start, data end) of the record at `at`; `Malformed(cut)` when its
    data length lies past `end` (its data may: the caller decides what that costs)."""
    fields, pos = _header(buf, at, end)
    if pos + 4 > end:
        raise Malformed(cut)
    (size,) = struct.unpack_from("<I", buf, pos)
    return fields, pos + 4, pos + 4 + size


def _records(buf, at: int, end: int) -> Iterator[tuple[int, dict[str, bytes], Any, int]]:
    """(op, header fields, data, record start) of each whole record in buf[at:end]; `Malformed`
    at the first one that is not whole (the caller says where)."""
    while at < end:
        fields, start, stop = _framed(buf, at, end, "a record's data length past the end")
        if stop > end:
            raise Malformed(f"a record's {stop - start} data bytes past the end")
        op = fields.get("op", b"")
        if len(op) != 1:
            raise Malformed("a record without an op")
        yield op[0], fields, memoryview(buf)[start:stop], at
        at = stop


def _inflate(compression: bytes, data, size: int) -> tuple[bytes, bool]:
    """A chunk's records, and whether they are all there (a cut chunk gives what it holds)."""
    if size > MAX_CHUNK_BYTES:
        raise Malformed(f"a chunk that declares {size} bytes")
    if compression == b"none":
        return bytes(data[:size]), len(data) >= size
    if compression == b"bz2":
        dec = bz2.BZ2Decompressor()
        out = dec.decompress(bytes(data), max_length=size + 1)
    elif compression == b"lz4":
        dec = lz4.frame.LZ4FrameDecompressor()
        out = dec.decompress(bytes(data), max_length=size + 1)
    else:
        raise Malformed(f"a chunk compressed as {compression!r}")
    return out[:size], len(out) >= size


class Ros1LinearRecords:
    """The Schema, Channel and message records of a ROS 1 bag, in file order (see the module
    docstring); `decoders` decodes its messages with the types its connections define."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.excess: Counter = Counter()
        self.data_crc: str | None = None
        self.decoders = Ros1Decoders(self.path)
        try:
            with open(self.path, "rb") as f:
                head = f.read(len(MAGIC))
        except OSError as exc:
            raise DatasetError(f"{self.path}: cannot open ({exc.strerror})") from None
        if head != MAGIC:
            raise DatasetError(f"{self.path}: not a ROS 1 bag of format 2.0")

    def records(
        self, report: ReadReport
    ) -> Iterator[Schema | Channel | McapMessage | LostMessages]:
        with open(self.path, "rb") as f:
            size = f.seek(0, 2)
            if size <= len(MAGIC):
                return
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
                yield from self._walk(buf, size, report)

    def _walk(self, buf, size: int, report: ReadReport) -> Iterator:
        schemas: dict[str, int] = {}
        channels: dict[int, str] = {}  # conn -> topic
        at = len(MAGIC)
        while at < size:
            try:
                fields, start, end = _framed(buf, at, size, "the file ends inside it (cut short)")
            except Malformed as exc:  # the chain of record lengths is broken here
                yield _lost(report, f"record at byte {at}", f"{exc}; anything after it is lost")
                return
            data = memoryview(buf)[start : min(end, size)]
            op = (fields.get("op") or b"\0")[0]
            kind = "chunk" if op == OP_CHUNK else "record"
            try:
                if op == OP_CHUNK:
                    yield from self._chunk(fields, data, end <= size, schemas, channels, report)
                elif end > size:
                    raise Malformed("the file ends inside it (cut short)")
                elif op in (OP_CONNECTION, OP_MESSAGE):
                    yield from self._record(op, fields, data, schemas, channels, report)
            except (Malformed, OSError, EOFError, RuntimeError, ValueError) as exc:
                # a damaged record whose length holds: the walk goes on after it
                after = "; anything after it is lost" if end > size else ""
                yield _lost(report, f"{kind} at byte {at}", f"{exc}{after}")
            if end > size:
                return
            at = end

    def _chunk(self, fields, data, whole: bool, schemas, channels, report) -> Iterator:
        """The connections and messages of a chunk; for a cut or damaged one, what it holds
        whole, then `Malformed`."""
        records, complete = _inflate(fields.get("compression", b""), data, _u32(fields, "size"))
        try:
            for op, inner, body, _ in _records(records, 0, len(records)):
                if op in (OP_CONNECTION, OP_MESSAGE):
                    yield from self._record(op, inner, body, schemas, channels, report)
        except Malformed:
            if complete:
                raise
        if not whole:
            raise Malformed("the file ends inside it (cut short)")
        if not complete:
            raise Malformed("it inflates to fewer bytes than it declares")

    def _record(self, op: int, fields, data, schemas, channels, report) -> Iterator:
        conn = _u32(fields, "conn")
        if op == OP_CONNECTION:
            if conn in channels:
                return
            inner = _fields(data, 0, len(data))  # (the connection's own header)
            msgtype = normalize_msgtype(inner.get("type", b"").decode("utf-8", "replace"))
            topic = fields.get("topic", b"").decode("utf-8", "replace")
            if msgtype not in schemas:
                schemas[msgtype] = len(schemas) + 1
                yield Schema(
                    id=schemas[msgtype],
                    name=msgtype,
                    encoding="ros1msg",
                    data=inner.get("message_definition", b""),
                )
            channels[conn] = topic
            yield Channel(
                id=conn,
                topic=topic,
                schema_id=schemas[msgtype],
                message_encoding="ros1",
                metadata={},
            )
            return
        if conn not in channels:  # (its connection record was in damaged data)
            return
        sec, nsec = struct.unpack("<II", fields.get("time", b"\0" * 8)[:8].ljust(8, b"\0"))
        report.messages[channels[conn]] += 1
        yield McapMessage(
            channel_id=conn, log_time=sec * 10**9 + nsec, data=bytes(data), crc_checked=False
        )


def _lost(report: ReadReport, where: str, what: str) -> LostMessages:
    """Damage that held an unknown number of messages: reported, and marked in the stream."""
    report.losses.append(Loss(where, what, uncounted=True))
    return LostMessages(None, None, where)


class Ros1Decoders:
    """`decode(channel, schema, data)` for ROS 1 messages, each type registered from its
    connection's definition (ROS 1 bags carry them) the first time it is met."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._typestore = get_typestore(Stores.EMPTY)
        self._known: set[str] = set()

    def decode(self, channel: Channel, schema: Schema | None, data: bytes) -> Any:
        if schema is None:
            raise DatasetError(f"{self.path}: topic {channel.topic} has no message type")
        if schema.name not in self._known:
            text = bytes(schema.data).decode("utf-8", "replace")
            self._typestore.register(get_types_from_msg(text, schema.name))
            self._known.add(schema.name)
        return self._typestore.deserialize_ros1(data, schema.name)
