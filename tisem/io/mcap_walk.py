"""One front-to-back pass over the data section of an MCAP file (see `tisem.io.mcap_records`).

`Walk.run` yields Schema, Channel, `McapMessage` and `LostMessages` records in data order and
appends to the report what it could not use: chunks that fail their checks (their loss counted
from the message index records after them, or from their own records), records whose header
is damaged (reading goes on at the next intact record, `tisem.io.mcap_resync`), a file cut
short, CRC mismatches, and a chunk index that disagrees with the data. What it yields is
`tisem.io.mcap_items`; how many messages each loss held, and what no CRC covered, is counted
by its `Ledger` (`tisem.io.mcap_losses`).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from typing import TYPE_CHECKING, BinaryIO

from mcap.opcode import Opcode
from mcap.records import Channel

from tisem.io.mcap_chunks import (
    UNTRUSTED,
    BadChunk,
    checked_records,
    chunk_header,
    inflate,
    inner_records,
    messages_in_damaged,
    salvaged_records,
)
from tisem.io.mcap_items import LostMessages, chunk_items, record_item, unvouched_statics
from tisem.io.mcap_losses import Ledger
from tisem.io.mcap_report import Loss, ReadReport, error_text, one_line
from tisem.io.mcap_resync import RecordFinder, index_disagreements
from tisem.io.mcap_summary import (
    MAGIC,
    RECORD_HEADER,
    Malformed,
    attachment_problem,
    crc_of_range,
    opcode_name,
    valid_opcode,
)

if TYPE_CHECKING:
    from tisem.io.mcap_records import McapRecords


# a chunk record's fields before its compression's name and after it (times, size, CRC, the
# name's length; the data's length): 40 bytes and the name, "zstd" or "lz4" at most
_CHUNK_FIXED = 40
_LONGEST_COMPRESSION = 16


def _time_range(start: int, end: int) -> str:
    return f"log time {start / 1e9:.3f}-{end / 1e9:.3f} s"


def _why(e: Exception) -> str:
    return one_line(str(e)) if isinstance(e, (BadChunk, Malformed)) else error_text(e)


class Walk:
    """One front-to-back pass over the data section: the state of a `records` call."""

    def __init__(self, owner: McapRecords, f: BinaryIO, report: ReadReport) -> None:
        self.o, self.f, self.report = owner, f, report
        self.channels: dict[int, Channel] = dict(owner.summary.channels) if owner.summary else {}
        self.ledger = Ledger(report, self.channels)
        self.seen: dict[int, int] = {}  # chunk offset -> its record's length in bytes
        self.reached = len(MAGIC)  # how far the walk got
        # where the record before the current one started, and whether its length was vouched
        # for (a chunk that checked out): a damaged length elsewhere may have misled the walk
        # by a few bytes, so the next intact record is looked for from just after that record
        self.previous, self.previous_sure = len(MAGIC) - 1, True
        self.last_sure = len(MAGIC) - 1  # where the last vouched-for record started
        self.chunk_ok = False  # the last chunk checked out
        self.finder = RecordFinder(f, owner.limit, owner.index)

    # -- the walk
    def run(self) -> Iterator:
        yield from self._walk()
        yield from self.ledger.settle()

    def _walk(self) -> Iterator:
        pos, limit, cut = len(MAGIC), self.o.limit, self.o.footer is None
        while pos is not None:
            self.reached = pos
            if pos >= limit:
                yield from self.ledger.settle()
                self._no_data_end(pos)
                return
            inside = self._listed_inside(pos)
            if inside is not None:
                self.report.losses.append(
                    Loss(
                        f"byte {self.previous}",
                        f"the record there claims {pos - inside} byte(s) "
                        f"too many: the chunk index has a chunk at byte {inside}, inside it; "
                        f"reading went on there",
                    )
                )
                pos = inside
                continue
            self.f.seek(pos)
            head = self.f.read(RECORD_HEADER)
            opcode = head[0]
            if opcode != Opcode.MESSAGE_INDEX:
                yield from self.ledger.settle()
            if len(head) < RECORD_HEADER:  # only where there is no footer
                self.report.losses.append(
                    Loss(
                        f"byte {pos}",
                        f"the file ends inside a record header ({len(head)} of 9 bytes): cut short",
                    )
                )
                return
            length = struct.unpack_from("<Q", head, 1)[0]
            end = pos + RECORD_HEADER + length
            expected = self.finder.expected_at(pos)
            if opcode != Opcode.CHUNK and end <= limit and self._holds_a_chunk(pos, length):
                yield from self.ledger.settle()  # (a message index does not settle, a chunk does)
                self.report.losses.append(
                    Loss(
                        f"byte {pos}",
                        f"the record there has opcode {opcode:#x}, but holds an intact chunk: "
                        f"its opcode is damaged; read as the chunk it is",
                    )
                )
                start, pos = pos, (yield from self._chunk(pos, length))
                self._after(start, self.chunk_ok)
            elif expected is not None and opcode != expected:
                # the index puts a chunk or a message index record here: its opcode is damaged
                # (a message index turned message would be taken for a cloud)
                pos = yield from self._wrong_opcode(pos, opcode, expected, end)
            elif not valid_opcode(opcode):
                pos = yield from self._broken(pos, f"invalid record opcode {opcode:#x}")
            elif end > limit and cut and (nxt := self._next_record(pos)) is not None:
                # past the end of a file without a footer, yet an intact record follows: the
                # length is damaged, the file is not cut there
                pos = yield from self._broken(
                    pos,
                    f"the {opcode_name(opcode)} record claims "
                    f"{length} bytes, past the end of the file",
                    nxt,
                )
            elif end > limit and cut:
                yield from self._cut_record(pos, opcode, length)
                return
            elif end > limit:
                pos = yield from self._broken(
                    pos,
                    f"the {opcode_name(opcode)} record claims "
                    f"{length} bytes, past the end of the data",
                )
            elif opcode == Opcode.CHUNK:
                start, pos = pos, (yield from self._chunk(pos, length))
                self._after(start, self.chunk_ok)
            elif opcode == Opcode.DATA_END:
                self._data_end(pos, length)
                return
            elif opcode == Opcode.FOOTER:  # a footer the file's end did not show
                return
            else:
                yield from self._top_level(pos, opcode, length)
                self._after(pos, opcode == Opcode.MESSAGE)
                pos = end

    def _holds_a_chunk(self, pos: int, length: int) -> bool:
        """Whether the record at `pos` (of another opcode) holds an intact chunk (its data
        fills the record, inflates to the size it declares, its records fill that, and its CRC,
        where it has one, matches): a flipped bit turns a chunk into a message index, a footer,
        a private record ..., all of which the walk would pass over, and its messages with it.
        Its first bytes decide for every other record: a chunk's compression is a short name,
        and its data fills the record exactly."""
        if length < _CHUNK_FIXED:
            return False
        self.f.seek(pos + RECORD_HEADER)
        try:
            first = self.f.read(_CHUNK_FIXED)
            name_length = struct.unpack_from("<I", first, 28)[0]
            if name_length > _LONGEST_COMPRESSION or _CHUNK_FIXED + name_length > length:
                return False
            self.f.seek(pos + RECORD_HEADER + 32 + name_length)
            (declared,) = struct.unpack("<Q", self.f.read(8))
            if _CHUNK_FIXED + name_length + declared != length:
                return False
            self.f.seek(pos + RECORD_HEADER)
            checked_records(chunk_header(self.f.read(length)))  # (BadChunk where it is not one)
            return True
        except (*UNTRUSTED, struct.error):
            return False
        finally:
            self.f.seek(pos + RECORD_HEADER)

    def _wrong_opcode(self, pos: int, opcode: int, expected: int, end: int) -> Iterator:
        why = (
            f"the chunk index has a {opcode_name(expected)} record here, the data opcode "
            f"{opcode:#x}"
        )
        if expected == Opcode.CHUNK or end > self.o.limit:
            return (yield from self._broken(pos, why))
        self.report.losses.append(
            Loss(f"byte {pos}", f"{why}: taken as a damaged message index record")
        )
        self._after(pos, False)
        return end

    def _after(self, start: int, sure: bool) -> None:
        """The record at `start` was walked; `sure`: its length was vouched for."""
        self.previous, self.previous_sure = start, sure
        if sure:
            self.last_sure = start

    def _listed_inside(self, pos: int) -> int | None:
        """A chunk the index lists inside the record before (whose length nothing vouched
        for): that record's length was damaged, and the walk must go back to the chunk."""
        if self.previous_sure:
            return None
        return self.finder.listed_chunk(self.previous, pos, self.seen)

    def _top_level(self, pos: int, opcode: int, length: int) -> Iterator:
        """A record outside chunks (unchunked files keep their messages here)."""
        if opcode == Opcode.ATTACHMENT:
            self._attachment(pos, length)
            return
        if opcode not in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.MESSAGE_INDEX):
            return  # header, metadata, private records
        content = self.f.read(length)
        if opcode == Opcode.MESSAGE_INDEX:
            self.ledger.message_index(content)
            return
        self.ledger.outside += opcode == Opcode.MESSAGE
        try:
            rec = record_item(opcode, content, False, self.channels)
        except Malformed as e:
            loss = Loss(f"{opcode_name(opcode)} record at byte {pos}", f"unparseable ({e})")
            self.report.losses.append(loss)
            if opcode == Opcode.MESSAGE:
                loss.uncounted = True
                yield LostMessages(None, None, loss.where)
            return
        yield rec

    def _items(self, records, checked: bool, where: str) -> Iterator:
        """The items of a chunk's records (`mcap_items.chunk_items`)."""
        return chunk_items(records, checked, where, self.channels, self.report)

    # -- chunks
    def _chunk(self, pos: int, length: int) -> Iterator:
        """The chunk at `pos`; returns where the next record starts."""
        self.seen[pos] = RECORD_HEADER + length
        where, head = f"chunk at byte {pos}", None
        try:
            head = chunk_header(self.f.read(length))
            where += f" ({_time_range(head.start_time, head.end_time)})"
            records, checked = checked_records(head)
        except UNTRUSTED as e:
            fixed = yield from self._chunk_by_index(pos, where)
            self.chunk_ok = fixed is not None
            if fixed is not None:
                return fixed
            loss = Loss(where, f"chunk skipped ({_why(e)})")
            self.report.losses.append(loss)
            self.ledger.count_from_index(loss, messages_in_damaged(head) if head else None)
            if head is not None:  # (the sensor's mount, in case it is nowhere else)
                yield from unvouched_statics(salvaged_records(head), where, self.channels)
            return pos + RECORD_HEADER + length
        self.ledger.no_crc += not checked
        self.chunk_ok = True
        yield from self._items(records, checked, where)
        return pos + RECORD_HEADER + length

    def _chunk_by_index(self, pos: int, where: str) -> Iterator:
        """When the index lists a chunk at `pos` with another length and the chunk checks out
        at that length, its record length field was what was damaged: use the chunk."""
        for entry in self.o.index.get(pos, ()):
            if entry.chunk_length < RECORD_HEADER or pos + entry.chunk_length > self.o.limit:
                continue
            if entry.chunk_length == self.seen.get(pos):
                continue
            self.f.seek(pos + RECORD_HEADER)
            try:
                records, checked = checked_records(
                    chunk_header(self.f.read(entry.chunk_length - RECORD_HEADER))
                )
            except UNTRUSTED:
                continue
            self.report.losses.append(
                Loss(
                    where,
                    "its record header is damaged; the chunk "
                    "index gives its length, and it checks out at that "
                    "length",
                )
            )
            self.seen[pos] = entry.chunk_length
            self.ledger.no_crc += not checked
            yield from self._items(records, checked, where)
            return pos + entry.chunk_length
        return None

    # -- damage to the record structure
    def _broken(self, pos: int, why: str, nxt: int | None = None) -> Iterator:
        """The record at `pos` cannot be read: go on at the next record that checks out and
        account for what lay between. Returns that position, or None when there is none."""
        fixed = yield from self._chunk_by_index(pos, f"chunk at byte {pos}")
        if fixed is not None:
            return fixed
        after = pos if self.previous_sure else self.previous
        if nxt is None:
            nxt = self._next_record(after)
        end = self.o.limit if nxt is None else nxt
        if nxt is not None and nxt < pos:  # the record before claimed too many bytes
            self.report.losses.append(
                Loss(
                    f"byte {self.previous}",
                    f"the record there claims "
                    f"{pos - nxt} byte(s) too many; reading went on at "
                    f"byte {nxt}, the next record that checks out",
                )
            )
            return nxt
        loss = Loss(
            f"bytes {pos}-{end}",
            why
            + (
                "; nothing after it could be read"
                if nxt is None
                else f"; reading went on at byte {nxt}, the next record that checks out"
            ),
        )
        self.report.losses.append(loss)
        counts = (
            self.finder.indexed_counts(self.last_sure + 1, end, self.seen)
            if self.o.summary is not None
            else None
        )
        if counts is None and nxt is not None and self._at(nxt, 1)[0] == Opcode.MESSAGE_INDEX:
            # the stretch ends where a chunk's message index records start: it was that chunk
            self.ledger.count_from_index(loss)
            return nxt
        yield from self.ledger.account(loss, counts)
        return nxt

    def _next_record(self, pos: int) -> int | None:
        return self.finder.next_record(pos, bool(self.seen or self.o.index), self.channels)

    def _at(self, pos: int, size: int) -> bytes:
        self.f.seek(pos)
        return self.f.read(size)

    # -- the ends of the data
    def _cut_record(self, pos: int, opcode: int, length: int) -> Iterator:
        """The file ends inside a record: say so, and yield what a cut chunk still holds."""
        have = self.o.size - pos - RECORD_HEADER
        loss = Loss(
            f"byte {pos}",
            f"the file ends inside a {opcode_name(opcode)} record "
            f"({have} of {length} bytes present): cut short; anything after it is lost",
        )
        self.report.losses.append(loss)
        if opcode != Opcode.CHUNK:
            return
        try:
            head = chunk_header(self._at(pos + RECORD_HEADER, have), complete=False)
            loss.where = f"chunk at byte {pos} ({_time_range(head.start_time, head.end_time)})"
            records = inner_records(inflate(head, complete=False), complete=False)
        except UNTRUSTED:
            return
        self.report.partial_chunk_messages += sum(op == Opcode.MESSAGE for op, _ in records)
        yield from self._items(records, False, loss.where)

    def _no_data_end(self, pos: int) -> None:
        if self.o.footer is None:
            self.report.losses.append(
                Loss(
                    f"end of file (byte {self.o.size})",
                    "no data-end record or footer: the "
                    "recording was cut short at a record boundary; what followed is unknown",
                )
            )
        else:
            self.report.losses.append(
                Loss(f"byte {pos}", "the data section ends without a data-end record")
            )

    def _data_end(self, pos: int, length: int) -> None:
        """The data section's CRC is checked once the walk is over (`McapRecords`), from
        where the footer puts this record; without a footer, here."""
        self.reached = self.o.limit
        if self.o.footer is None and self.o.data_crc is None:
            crc = struct.unpack("<I", self.f.read(4))[0] if length >= 4 else 0
            self.o.data_crc = (
                "absent"
                if crc == 0
                else "match"
                if crc_of_range(self.f, 0, pos) == crc
                else "mismatch"
            )

    def _attachment(self, pos: int, length: int) -> None:
        problem = attachment_problem(self.f, pos, length)
        if problem is not None:
            self.report.losses.append(Loss(f"attachment at byte {pos}", problem))

    def finish(self) -> None:
        """After the walk: what the CRCs could not cover, and the index against the data."""
        self.ledger.note_unchecked(self.o.data_crc)
        if self.o.summary is not None and self.o.summary.chunk_indexes:
            problems = index_disagreements(self.o.index, self.seen, self.reached)
            if problems:
                self.report.losses.append(
                    Loss(
                        "chunk index (summary section)",
                        f"disagrees with the data "
                        f"({'; '.join(problems)}): the file was read from its data",
                    )
                )
