"""After a record whose header is damaged: where the next intact record starts, and what the
stretch in between held.

A damaged length or opcode leaves no way to step to the next record, so the next one is looked
for: first among the chunks the index lists, then in the bytes themselves, where a candidate
must be consistent in every field that can be checked without trusting it (a chunk's
compression name, its data length against its record length, and a valid record right after
it). What the skipped stretch held is counted from the message index records of the chunks
the index places there; without an index the count is unknown, and the reader says so.
Where the index puts a record (`RecordFinder.expected_at`, `listed_chunk`) also tells a
damaged opcode or length. After a pass, `index_disagreements` compares the index with the
chunks the data held.
"""

from __future__ import annotations

import bisect
import re
import struct
from collections import Counter
from typing import BinaryIO

from mcap.opcode import Opcode
from mcap.records import ChunkIndex

from tisem.io.mcap_chunks import COMPRESSIONS
from tisem.io.mcap_summary import (
    MAGIC,
    RECORD_HEADER,
    Malformed,
    parse_channel,
    parse_message_index,
    parse_schema,
    read_record,
    valid_opcode,
)

_SCAN_WINDOW = 1 << 20  # bytes per read while looking for the next intact record
_MAX_DEFINITION = 1 << 20  # a schema or channel record longer than this is not one


class RecordFinder:
    """Looks for intact records in the data section [8, limit) of an open file."""

    def __init__(self, f: BinaryIO, limit: int, index: dict[int, list[ChunkIndex]]) -> None:
        self.f, self.limit, self.index = f, limit, index
        self.listed = sorted(index)  # chunk offsets the index gives
        self.index_records = {  # ... and where it puts their message index records
            at for entries in index.values() for at in entries[0].message_index_offsets.values()
        }

    def expected_at(self, pos: int) -> int | None:
        """The opcode of the record the index puts at `pos` (a chunk or a message index
        record), or None where it puts none."""
        if pos in self.index:
            return Opcode.CHUNK
        return Opcode.MESSAGE_INDEX if pos in self.index_records else None

    def listed_chunk(self, start: int, end: int, skip) -> int | None:
        """The first chunk the index lists after `start` and before `end` that looks intact
        (but not at the offsets in `skip`, chunks already read), or None."""
        i = bisect.bisect_right(self.listed, start)
        while i < len(self.listed) and self.listed[i] < end:
            if self.listed[i] not in skip and self.looks_like_chunk(self.listed[i]):
                return self.listed[i]
            i += 1
        return None

    def _at(self, pos: int, size: int) -> bytes:
        self.f.seek(pos)
        return self.f.read(size)

    def _record_follows(self, end: int) -> bool:
        if end == self.limit:
            return True
        head = self._at(end, RECORD_HEADER)
        return (
            len(head) == RECORD_HEADER
            and valid_opcode(head[0])
            and end + RECORD_HEADER + struct.unpack_from("<Q", head, 1)[0] <= self.limit
        )

    def looks_like_chunk(self, pos: int) -> bool:
        head = self._at(pos, RECORD_HEADER + 48)
        if len(head) < RECORD_HEADER + 48 or head[0] != Opcode.CHUNK:
            return False
        length = struct.unpack_from("<Q", head, 1)[0]
        name_length = struct.unpack_from("<I", head, RECORD_HEADER + 28)[0]
        if name_length > 4 or pos + RECORD_HEADER + length > self.limit:
            return False
        name = head[RECORD_HEADER + 32 : RECORD_HEADER + 32 + name_length]
        data = struct.unpack_from("<Q", head, RECORD_HEADER + 32 + name_length)[0]
        return (
            name.decode("latin-1") in COMPRESSIONS
            and 40 + name_length + data == length
            and self._record_follows(pos + RECORD_HEADER + length)
        )

    def looks_like_message(self, pos: int, channels) -> bool:
        head = self._at(pos, RECORD_HEADER + 2)
        if len(head) < RECORD_HEADER + 2 or head[0] != Opcode.MESSAGE:
            return False
        length = struct.unpack_from("<Q", head, 1)[0]
        end = pos + RECORD_HEADER + length
        return (
            length >= 22
            and end <= self.limit
            and self._record_follows(end)
            and struct.unpack_from("<H", head, RECORD_HEADER)[0] in channels
        )

    def looks_like_message_index(self, pos: int, channels) -> bool:
        head = self._at(pos, RECORD_HEADER + 6)
        if len(head) < RECORD_HEADER + 6 or head[0] != Opcode.MESSAGE_INDEX:
            return False
        length = struct.unpack_from("<Q", head, 1)[0]
        channel_id, entries = struct.unpack_from("<HI", head, RECORD_HEADER)
        end = pos + RECORD_HEADER + length
        return (
            entries == length - 6
            and entries % 16 == 0
            and (channel_id in channels or not channels)
            and end <= self.limit
            and self._record_follows(end)
        )

    def looks_like_definition(self, pos: int) -> bool:
        """A Schema or Channel record that parses and fills its record exactly, with printable
        names."""
        head = self._at(pos, RECORD_HEADER)
        if len(head) < RECORD_HEADER or head[0] not in (Opcode.SCHEMA, Opcode.CHANNEL):
            return False
        length = struct.unpack_from("<Q", head, 1)[0]
        end = pos + RECORD_HEADER + length
        if not 8 <= length <= _MAX_DEFINITION or end > self.limit:
            return False
        content = self.f.read(length)
        try:
            if head[0] == Opcode.SCHEMA:
                rec = parse_schema(content, exact=True)
                names = (rec.name, rec.encoding)
            else:
                rec = parse_channel(content, exact=True)
                names = (rec.topic, rec.message_encoding)
        except Malformed:
            return False
        return all(n.isprintable() and n for n in names) and self._record_follows(end)

    def next_record(self, pos: int, chunked: bool, channels) -> int | None:
        """The first position after `pos` where an intact record starts, or None: in chunked
        files a chunk or a message index record (which follows its chunk, so it counts what
        the damaged stretch held), in the others also a schema, a channel or a message of a
        known channel."""
        listed = sorted(o for o in self.index if pos < o < self.limit)
        bound = next((o for o in listed if self.looks_like_chunk(o)), self.limit)
        checks = {
            Opcode.CHUNK: self.looks_like_chunk,
            Opcode.MESSAGE_INDEX: lambda p: self.looks_like_message_index(p, channels),
        }
        if not chunked:
            checks.update(
                {
                    Opcode.MESSAGE: lambda p: self.looks_like_message(p, channels),
                    Opcode.SCHEMA: self.looks_like_definition,
                    Opcode.CHANNEL: self.looks_like_definition,
                }
            )
        wanted = re.compile(b"[" + b"".join(re.escape(bytes([o])) for o in checks) + b"]")
        at = pos + 1
        while at < bound:
            window = self._at(at, min(_SCAN_WINDOW, bound - at))
            if not window:
                break
            for hit in wanted.finditer(window):
                if checks[window[hit.start()]](at + hit.start()):
                    return at + hit.start()
            at += len(window)
        return bound if bound < self.limit else None

    def indexed_counts(self, start: int, end: int, skip=()) -> Counter | None:
        """Messages per channel the chunk index places in [start, end) (but not at the offsets
        in `skip`, chunks already read or lost), counted from their message index records in
        the data; None when one cannot be read."""
        if not self.index:  # an index of no chunks says nothing
            return None
        counts = Counter()
        for offset, entries in self.index.items():
            if not start <= offset < end or offset in skip:
                continue
            for channel_id, at in entries[0].message_index_offsets.items():
                if not len(MAGIC) <= at < self.limit:
                    return None
                rec = read_record(self.f, at, self.limit)
                if isinstance(rec, str) or rec[0] != Opcode.MESSAGE_INDEX:
                    return None
                try:
                    found, n = parse_message_index(rec[1])
                except Malformed:
                    return None
                if found != channel_id:
                    return None
                counts[channel_id] += n
        return counts


def _offsets(offsets) -> str:
    shown = ", ".join(str(o) for o in sorted(offsets)[:5])
    return shown + (f" and {len(offsets) - 5} more" if len(offsets) > 5 else "")


def index_disagreements(index: dict[int, list], seen: dict[int, int], reached: int) -> list[str]:
    """How a chunk index (offset -> entries) disagrees with the chunks the data holds
    (offset -> record length) up to byte `reached`; empty when it agrees."""
    problems = []
    dupes = {o: len(es) - 1 for o, es in index.items() if len(es) > 1}
    if dupes:
        n = sum(dupes.values())
        problems.append(
            f"{n} duplicated {'entry' if n == 1 else 'entries'} for the chunk(s) "
            f"at byte {_offsets(dupes)}"
        )
    missing = [o for o in seen if o not in index]
    if missing:
        problems.append(f"no entry for the chunk(s) at byte {_offsets(missing)}")
    extra = [o for o in index if o not in seen and o < reached]
    if extra:
        problems.append(f"entries for chunks the data does not have, at byte {_offsets(extra)}")
    wrong = [o for o in seen if o in index and all(e.chunk_length != seen[o] for e in index[o])]
    if wrong:
        problems.append(f"other lengths for the chunk(s) at byte {_offsets(wrong)}")
    return problems
