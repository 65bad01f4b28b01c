"""A ROS 1 bag read record by record from its start, without its index.

`rosbag record` writes a bag's index (connections, chunk positions) when it closes; a recording
that did not close (the recorder killed, the power lost: `NAME.bag.active`) or a bag cut short
has none, and `rosbags` cannot open it. The records themselves describe the bag (format 2.0):
each is a header of `name=value` fields (`op` says what it is) and a data part; chunks hold the
connection and message records, uncompressed, bz2 or lz4. `Ros1LinearRecords` walks them in
file order and gives `McapScanReader` the same stream `tisem.io.bag_records` gives for other
bags; a chunk the file ends inside gives the records it still holds whole, and the loss is
reported. Message types come from the connections' own definitions.

Damage costs what it hit, not what follows it: where the chain of record lengths breaks (bytes
overwritten or inserted), the walk reads on from the next place where two whole records follow
one another, and a message whose connection record was in damaged data takes the copy of that
record in the bag's index section (written at the end, when the recording closed).
"""

from __future__ import annotations

import bz2
import mmap
import struct
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import lz4.frame
from mcap.records import Channel, Schema
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.msg import normalize_msgtype

from tisem.errors import DatasetError
from tisem.io.mcap_chunks import stepped_prefix
from tisem.io.mcap_items import Unvouched, is_static_tf, unknown_loss
from tisem.io.mcap_records import LostMessages, McapMessage, ReadReport
from tisem.io.mcap_report import Loss

MAGIC = b"#ROSBAG V2.0\n"
OPS = range(2, 8)
OP_MESSAGE, OP_BAG_HEADER, OP_INDEX_DATA, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = OPS
MAX_CHUNK_BYTES = 1 << 31  # a chunk declaring more is damage
# Finding the next record after damage: every record header holds the field `op=X` (its 4-byte
# length, 4, first), in any place among the header's fields (rosbag's C++ writer sorts them by
# name, rosbags writes `op` first); fewer than this many bytes of other fields come before it.
OP_FIELD = b"\x04\x00\x00\x00op="
FIELDS_BEFORE_OP = 256
MAX_HEADER_BYTES = 1 << 16  # the headers rosbag writes are tens of bytes
_BAG_HEADER_BYTES = 1 << 13  # the bag header record, padded to 4096 bytes


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
        yield _op(fields), fields, memoryview(buf)[start:stop], at
        at = stop


def _whole_records(buf) -> tuple[list[tuple[int, dict[str, bytes], Any]], str]:
    """(op, header fields, data) of the whole records at the start of buf, up to the first
    that is not, and why that one is not ("" where all are)."""
    out = []
    try:
        for op, fields, data, _ in _records(buf, 0, len(buf)):
            out.append((op, fields, data))
    except Malformed as exc:
        return out, str(exc)
    return out, ""


def _index_data_after(buf, end: int, size: int) -> Counter:
    """Messages per connection that the index data records right after a chunk (ending at
    `end`) list: rosbag writes one per connection of the chunk. Empty where none follows."""
    counts = Counter()
    try:
        for op, fields, _, _ in _records(buf, end, size):
            if op != OP_INDEX_DATA:
                break
            counts[_u32(fields, "conn")] += _u32(fields, "count")
    except Malformed:
        pass
    return counts


def _disguised_chunk(fields: dict[str, bytes], at: int, report: ReadReport) -> int | None:
    """OP_CHUNK for a record whose op field is damaged but whose header is a chunk's (a
    compression and a size: no other record has them), said in the report; else None. A
    chunk read as an index data record or a chunk info record would be passed over, and its
    messages with it, with nothing said."""
    op = fields.get("op", b"")
    if op == bytes([OP_CHUNK]) or "compression" not in fields or "size" not in fields:
        return None
    report.losses.append(
        Loss(
            f"chunk at byte {at}",
            f"its op field is damaged ({bytes(op)!r}); read as the chunk its header is",
        )
    )
    return OP_CHUNK


def _static_only(described: tuple[str, str, bytes]) -> tuple[str, str, bytes] | None:
    """A connection's (topic, type, definition) if its topic is /tf_static's, else None."""
    return described if is_static_tf(described[0]) else None


def _op(fields: dict[str, bytes]) -> int:
    """A record's op; `Malformed` for a header without one that a bag holds (zeroed bytes
    parse as empty headers: the walk would step through them out of line with the records)."""
    op = fields.get("op", b"")
    if len(op) != 1 or op[0] not in OPS:
        raise Malformed("a record header without a known op")
    return op[0]


def _next_record(buf, after: int, size: int) -> int | None:
    """Where the first record after byte `after` starts that is whole and followed by another
    whole record header (or by the file's end), or None: random or compressed bytes pass that
    by chance next to never."""
    pos = after
    while (pos := buf.find(OP_FIELD, pos + 1)) >= 0:
        if pos + len(OP_FIELD) < size and buf[pos + len(OP_FIELD)] in OPS:
            at = _header_start(
                buf, pos, after, lambda at: at if _starts_records(buf, at, pos, size) else None
            )
            if at is not None:
                return at
    return None


def _header_start(buf, op_at: int, floor: int, read: Callable[[int], Any]) -> Any:
    """What `read(at)` gives for the nearest byte `at` before the `op` field at `op_at`, and
    after `floor`, where it gives anything but None (a record header there: the field's 4-byte
    length and the fields before it, of fewer than FIELDS_BEFORE_OP bytes, lie between), or
    None."""
    for at in range(op_at - 4, max(floor, op_at - 4 - FIELDS_BEFORE_OP), -1):
        if (got := read(at)) is not None:
            return got
    return None


def _starts_records(buf, at: int, op_at: int, size: int) -> bool:
    """Whether a whole record whose header holds the `op` field at `op_at` starts at `at`, and
    the file ends or another record header follows it."""
    (header,) = struct.unpack_from("<I", buf, at)
    if not op_at + len(OP_FIELD) < at + 4 + header <= min(size, at + 4 + MAX_HEADER_BYTES):
        return False
    try:
        fields, _, end = _framed(buf, at, size, "")
        _op(fields)
    except Malformed:
        return False
    return end <= size and _followed(buf, end, size)


def _followed(buf, end: int, size: int) -> bool:
    """Whether the file ends at `end` (or the data of the record that ends there do), or a
    record header with a known op starts there."""
    if end >= size:
        return True
    try:
        _op(_header(buf, end, size)[0])
    except Malformed:
        return False
    return True


def _index_position(buf, size: int) -> int:
    """Where the bag header says the index section starts: 0 for a recording that did not
    close (or a damaged bag header)."""
    try:
        fields, _, _ = _framed(buf, len(MAGIC), size, "")
        if _op(fields) != OP_BAG_HEADER:
            return 0
        return struct.unpack("<Q", fields.get("index_pos", b""))[0]
    except (Malformed, struct.error):
        return 0


def _index_section(buf, size: int) -> tuple[dict[int, str], dict[int, Counter]] | None:
    """(conn -> topic, chunk position -> messages per conn) from a closed bag's index section
    (its connection and chunk info records), or None where the bag has no index or it does
    not parse whole."""
    at = _index_position(buf, size)
    if not len(MAGIC) < at < size:
        return None
    topics: dict[int, str] = {}
    chunks: dict[int, Counter] = {}
    try:
        for op, fields, data, _ in _records(buf, at, size):
            if op == OP_CONNECTION:
                topics[_u32(fields, "conn")] = bytes(fields.get("topic", b"")).decode("utf-8")
            elif op == OP_CHUNK_INFO:
                pairs = _u32(fields, "count")
                if len(data) != 8 * pairs:
                    return None
                (pos,) = struct.unpack("<Q", fields.get("chunk_pos", b""))
                counts = chunks.setdefault(pos, Counter())
                for k in range(pairs):
                    conn, n = struct.unpack_from("<II", data, 8 * k)
                    counts[conn] += n
    except (ValueError, struct.error, UnicodeDecodeError):  # (Malformed is one)
        return None
    if any(set(counts) - set(topics) for counts in chunks.values()):
        return None
    return topics, chunks


def indexed_topic_counts(path: str | Path) -> Counter | None:
    """Messages per topic that a closed ROS 1 bag's index section lists (its chunk info
    records' counts, by the topics of its connection records), or None where the bag has no
    index or it does not parse whole: what a reader of the index should have yielded."""
    try:
        with open(path, "rb") as f:
            size = f.seek(0, 2)
            if size <= len(MAGIC):
                return None
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
                index = _index_section(buf, size)
    except OSError:
        return None
    if index is None:
        return None
    topics, chunks = index
    counts = Counter()
    for per_conn in chunks.values():
        for conn, n in per_conn.items():
            counts[topics[conn]] += n
    return counts


def _connection_records(buf, size: int) -> dict[int, list[tuple[dict[str, bytes], bytes]]]:
    """conn -> [(header fields, data)] of the whole connection records anywhere in the file: a
    bag that closed holds a copy of each in its index section, after the chunks, which a walk
    from the start meets last (and whose `index_pos` damage before it may have shifted)."""

    def whole_connection(at: int) -> tuple | None:
        """(header fields, data start, end) of a whole connection record at `at`, or None."""
        try:
            fields, start, end = _framed(buf, at, size, "")
        except Malformed:
            return None
        whole = (
            end <= size
            and fields.get("op") == bytes([OP_CONNECTION])
            and len(fields.get("conn", b"")) == 4
        )
        return (fields, start, end) if whole else None

    found: dict[int, list] = {}
    pos = 0
    while (pos := buf.find(OP_FIELD + bytes([OP_CONNECTION]), pos + 1)) >= 0:
        record = _header_start(buf, pos, 0, whole_connection)
        if record is not None:
            fields, start, end = record
            found.setdefault(_u32(fields, "conn"), []).append((fields, bytes(buf[start:end])))
    return found


def _inflate(compression: bytes, data, size: int) -> tuple[bytes, str]:
    """A chunk's records, and why they are not all there ("" when they are; a cut chunk gives
    what it holds)."""
    if size > MAX_CHUNK_BYTES:
        raise Malformed(f"a chunk that declares {size} bytes")
    if compression == b"none":
        if len(data) > size:
            raise Malformed("its data are longer than it declares")
        return bytes(data), "" if len(data) == size else "it holds fewer bytes than it declares"
    if compression == b"bz2":
        dec = bz2.BZ2Decompressor()
    elif compression == b"lz4":
        dec = lz4.frame.LZ4FrameDecompressor()
    else:
        raise Malformed(f"a chunk compressed as {compression!r}")
    out = dec.decompress(bytes(data), max_length=size + 1)
    # on to the stream's end, where bz2 checks its last block (and lz4 its frame): stopped at
    # max_length, a decompressor returns damaged bytes unchecked
    while len(out) <= size and not dec.eof and not dec.needs_input:
        out += dec.decompress(b"", max_length=size + 1 - len(out))
    if len(out) > size:
        raise Malformed("it inflates to more bytes than it declares")
    if len(out) < size:
        return out, "it inflates to fewer bytes than it declares"
    return out, "" if dec.eof else "its compressed stream does not end in it"


def _inflated_before_damage(compression: bytes, data, size: int) -> bytes:
    """What a chunk whose stream fails inflates to before the failure, at most `size` bytes
    (`mcap_chunks.stepped_prefix`)."""
    if compression == b"none":
        return bytes(data[:size])
    if compression not in (b"bz2", b"lz4"):
        return b""
    dec = bz2.BZ2Decompressor() if compression == b"bz2" else lz4.frame.LZ4FrameDecompressor()
    return stepped_prefix(dec, data, size)


class Ros1LinearRecords:
    """The Schema, Channel and message records of a ROS 1 bag, in file order (see the module
    docstring); `decoders` decodes its messages with the types its connections define."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.excess: Counter = Counter()
        self.data_crc: str | None = None
        self.decoders = Ros1Decoders(self.path)
        self._maps: _Connections | None = None  # (the walk's: connections met, their copies)
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
        self._maps = _Connections(lambda: _connection_records(buf, size))
        self._buf, self._size, self._index = buf, size, None  # (the index: read at need)
        at = len(MAGIC)
        cut = False  # (a loss already says that the rest of the file is lost)
        while at < size:
            try:
                fields, start, end = _framed(buf, at, size, "the file ends inside it (cut short)")
                op = _disguised_chunk(fields, at, report) or _op(fields)
            except Malformed as exc:  # the chain of record lengths is broken here
                lost, at = _lost_up_to_next(report, buf, f"record at byte {at}", exc, at, size)
                cut = at >= size
                yield lost
                continue
            data = memoryview(buf)[start : min(end, size)]
            kind = "chunk" if op == OP_CHUNK else "record"
            read = 0  # messages of the chunk yielded (or marked lost) before damage stopped it
            try:
                if op == OP_CHUNK:
                    # bytes inserted in an uncompressed one push its end past its length: no
                    # check tells, but the record after it is then out of line
                    out_of_line = fields.get("compression") == b"none" and not _followed(
                        buf, end, size
                    )
                    where = f"chunk at byte {at}"
                    for item in self._chunk(fields, data, end <= size, out_of_line, where, report):
                        read += isinstance(item, McapMessage | LostMessages)
                        yield item
                elif end > size:
                    raise Malformed("the file ends inside it (cut short)")
                elif op in (OP_CONNECTION, OP_MESSAGE):
                    yield from self._record(op, fields, data, report)
                elif at in self._chunk_counts():  # (a chunk whose op and header are damaged)
                    why = (
                        f"its header is damaged (it reads as op {op}); the bag's index lists a "
                        "chunk here"
                    )
                    yield from self._lost_chunk(at, end, f"chunk at byte {at}", why, report)
            except (Malformed, OSError, EOFError, RuntimeError, ValueError) as exc:
                if end <= size:  # a damaged record whose length holds: the walk goes on after it
                    if op == OP_CHUNK:
                        where = f"{kind} at byte {at}"
                        yield from self._lost_chunk(at, end, where, str(exc), report, read > 0)
                        # (the sensor's mount, in case it is nowhere else)
                        yield from self._unvouched_statics(fields, data, where)
                    else:
                        yield unknown_loss(report, f"{kind} at byte {at}", str(exc))
                elif op == OP_CHUNK and fields.get("compression") == b"none":
                    # its records, the format of the bag's own, were read to the file's end
                    yield unknown_loss(
                        report, f"{kind} at byte {at}", f"{exc}; anything after it is lost"
                    )
                    cut = True
                else:  # cut short, or its length is damaged: records may follow its header
                    lost, end = _lost_up_to_next(
                        report, buf, f"{kind} at byte {at}", exc, start, size
                    )
                    cut = end >= size
                    yield lost
            at = end
        index_at = _index_position(buf, size)
        if not cut and index_at >= size:  # a closed bag cut between two records
            yield unknown_loss(
                report,
                f"the file's end (byte {size})",
                f"the bag's index was written at byte {index_at}: the file was cut short",
            )
        self._maps.report_unknown(report)

    def _chunk(self, fields, data, whole: bool, out_of_line: bool, where: str, report) -> Iterator:
        """The connections and messages of a chunk; a cut one gives the records it holds whole,
        then `Malformed`. Damage inside a chunk the file holds whole (records that do not add
        up, a stream that inflates short or does not end, the record after it `out_of_line`)
        is reported first, so that the reader marks what follows suspect, and the last record
        before it is lost with it: it may hold bytes that are not its own."""
        records, short = _inflate(fields.get("compression", b""), data, _u32(fields, "size"))
        held, broken = _whole_records(records)
        if out_of_line and not broken:
            broken = "the record after it is out of line (bytes inserted in it?)"
        if whole and (short or broken):
            yield unknown_loss(report, where, short or broken)
            held = held[:-1]
        for op, inner, body in held:
            if op in (OP_CONNECTION, OP_MESSAGE):
                yield from self._record(op, inner, body, report)
        if not whole:
            raise Malformed("the file ends inside it (cut short)")

    def _chunk_counts(self) -> dict[int, Counter]:
        """Chunk position -> messages per connection, from the bag's index section (read the
        first time damage asks; empty for a bag without one)."""
        if self._index is None:
            self._index = _index_section(self._buf, self._size) or ({}, {})
        return self._index[1]

    def _lost_chunk(
        self, at: int, end: int, where: str, why: str, report: ReadReport, partly: bool = False
    ) -> Iterator:
        """The loss of the chunk at byte `at` (its record ends at `end`), counted where the
        bag's index lists what it held (its chunk info record, per connection) and the index
        data records after the chunk agree, so that the scans after it keep their numbers;
        else, or where some of it was read (`partly`), of an unknown number of messages."""
        held = self._chunk_counts().get(at) or Counter()
        after = _index_data_after(self._buf, end, self._size)
        if partly or (after and after != held):
            held = Counter()
        # (a connection whose record was in the chunk: from the index's copy, yielded before
        # its lost messages, as the chunk would have)
        yield from self._maps.known(sorted(held))
        if not held or any(conn not in self._maps.channels for conn in held):
            yield unknown_loss(report, where, why)
            return
        topics = Counter()
        for conn, n in held.items():  # (several connections can share a topic)
            topics[self._maps.channels[conn]] += n
        report.losses.append(Loss(where, why, sum(held.values()), topics=topics))
        for conn, n in sorted(held.items()):
            yield LostMessages(conn, n, where)

    def _unvouched_statics(self, fields, data, where: str) -> Iterator[Unvouched]:
        """The /tf_static messages among the whole records a chunk that does not inflate
        still gives before its damage (`Unvouched`: read only where nothing else gives the
        sensor's mount). Their connections are the chunk's own records, or the index's
        copies; none of them is taken into the walk's."""
        try:
            size = _u32(fields, "size")
        except Malformed:
            return
        if size > MAX_CHUNK_BYTES:
            return
        prefix = _inflated_before_damage(fields.get("compression", b""), data, size)
        own: dict[int, tuple[str, str, bytes] | None] = {}  # conn -> a /tf_static one's
        for op, inner, body in _whole_records(prefix)[0]:
            try:
                conn = _u32(inner, "conn")
                if op == OP_CONNECTION:
                    own[conn] = _static_only(_described(inner, body))
                    continue
            except Malformed:
                continue  # (a damaged record: the index's copy of a connection may serve)
            if op != OP_MESSAGE:
                continue
            if conn not in own:  # (the index's copy, looked at once per connection)
                own[conn] = self._maps.static_copy(conn)
            if own[conn] is None:
                continue
            topic, msgtype, definition = own[conn]
            sec, nsec = struct.unpack("<II", inner.get("time", b"\0" * 8)[:8].ljust(8, b"\0"))
            yield Unvouched(
                where,
                Channel(id=conn, topic=topic, schema_id=0, message_encoding="ros1", metadata={}),
                Schema(id=0, name=msgtype, encoding="ros1msg", data=definition),
                McapMessage(conn, sec * 10**9 + nsec, bytes(body), crc_checked=False),
            )

    def _record(self, op: int, fields, data, report) -> Iterator:
        conn = _u32(fields, "conn")
        if op == OP_CONNECTION:
            yield from self._maps.connect(conn, fields, data)
            return
        if conn not in self._maps.channels:  # its connection record was in damaged data
            yield from self._maps.from_copy(conn)
            if conn not in self._maps.channels:
                return
        sec, nsec = struct.unpack("<II", fields.get("time", b"\0" * 8)[:8].ljust(8, b"\0"))
        report.messages[self._maps.channels[conn]] += 1
        yield McapMessage(
            channel_id=conn, log_time=sec * 10**9 + nsec, data=bytes(data), crc_checked=False
        )


class _Connections:
    """The connections a walk has met (conn -> topic), their message types as Schema ids, and
    the other copies of their records (`copies`: the index section's), for a message whose own
    connection record was lost and a record whose message definition is damaged."""

    def __init__(self, find_copies: Callable[[], dict[int, tuple]]) -> None:
        self._find_copies = find_copies
        self._copies: dict[int, tuple] | None = None
        self.schemas: dict[str, int] = {}
        self.channels: dict[int, str] = {}
        self.unknown: Counter = Counter()  # conn -> messages of no known connection

    def copies(self) -> dict[int, tuple]:
        if self._copies is None:  # (searched once, when damage first needs it)
            self._copies = self._find_copies()
        return self._copies

    def connect(self, conn: int, fields, data) -> Iterator[Schema | Channel]:
        """The Schema (the first time its type is met) and Channel of a connection record."""
        if conn in self.channels:
            return
        topic, msgtype, definition = _described(fields, data)
        if not _parses(definition, msgtype):  # damaged: a copy whose definition is whole
            topic, msgtype, definition = next(
                self._whole_copies(conn), (topic, msgtype, definition)
            )
        if msgtype not in self.schemas:
            self.schemas[msgtype] = len(self.schemas) + 1
            yield Schema(
                id=self.schemas[msgtype], name=msgtype, encoding="ros1msg", data=definition
            )
        self.channels[conn] = topic
        yield Channel(
            id=conn,
            topic=topic,
            schema_id=self.schemas[msgtype],
            message_encoding="ros1",
            metadata={},
        )

    def _whole_copies(self, conn: int) -> Iterator[tuple[str, str, bytes]]:
        """(topic, type, definition) of each copy of the connection's record that parses."""
        for fields, data in self.copies().get(conn, []):
            try:
                copy = _described(fields, data)
            except Malformed:
                continue
            if _parses(copy[2], copy[1]):
                yield copy

    def static_copy(self, conn: int) -> tuple[str, str, bytes] | None:
        """(topic, type, definition) of a whole copy of the connection's record if it is a
        /tf_static connection (the topic is looked at before the definition is parsed)."""
        for fields, data in self.copies().get(conn, []):
            if not is_static_tf(bytes(fields.get("topic", b"")).decode("utf-8", "replace")):
                continue
            try:
                copy = _described(fields, data)
            except Malformed:
                continue
            if _parses(copy[2], copy[1]):
                return copy
        return None

    def known(self, conns: list[int]) -> Iterator[Schema | Channel]:
        """The Schema and Channel of each connection not met yet, from a whole copy of its
        record (none where it has none: `channels` then lacks it)."""
        for conn in conns:
            if conn in self.channels:
                continue
            for fields, data in self.copies().get(conn, []):
                try:
                    yield from self.connect(conn, fields, data)
                    break
                except Malformed:
                    continue

    def from_copy(self, conn: int) -> Iterator[Schema | Channel | LostMessages]:
        """The connection from another copy of its record; else the message is lost (on a
        channel no record names: the scans after it are numbered as suspect)."""
        yield from self.known([conn])
        if conn not in self.channels:
            self.unknown[conn] += 1
            yield LostMessages(conn, 1, f"connection {conn}")

    def report_unknown(self, report: ReadReport) -> None:
        """The messages lost for want of their connection, one loss per connection."""
        for conn, n in sorted(self.unknown.items()):
            report.losses.append(
                Loss(f"connection {conn}", "its connection record was in damaged data", n)
            )


def _described(fields, data) -> tuple[str, str, bytes]:
    """(topic, message type, message definition) of a connection record."""
    inner = _fields(data, 0, len(data))  # (the connection's own header)
    msgtype = normalize_msgtype(inner.get("type", b"").decode("utf-8", "replace"))
    topic = fields.get("topic", b"").decode("utf-8", "replace")
    return topic, msgtype, inner.get("message_definition", b"")


def _parses(definition: bytes, msgtype: str) -> bool:
    try:
        get_types_from_msg(definition.decode("utf-8", "replace"), msgtype)
    except Exception:  # (rosbags raises TypesysError, and others on text it cannot read)
        return False
    return True


def _lost_up_to_next(
    report: ReadReport, buf, where: str, exc: Exception, after: int, size: int
) -> tuple[LostMessages, int]:
    """The loss of a record the walk cannot step over, and where it reads on: the next whole
    record after byte `after` (`_next_record`), or the file's end."""
    resume = _next_record(buf, after, size)
    if resume is None:
        return unknown_loss(report, where, f"{exc}; anything after it is lost"), size
    return unknown_loss(report, where, f"{exc}; read on from byte {resume}"), resume


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
