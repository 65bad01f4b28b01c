"""Rows of a `.db3`'s messages table read from its leaf pages, without the tree above them.

SQLite finds a row through the interior pages of its table's tree, and rosbag2's inserts put
those late in the file: when the table's root first splits, every row written so far moves to a
new leaf page at the file's end of that moment, and each later split of an interior page does
the same with the pointers to hundreds of leaves. A file cut short (a copy that did not finish,
a full disk) therefore loses the path to rows whose own pages, and the cloud data on their
overflow pages, all lie before the cut: SQLite says "malformed" for each. `LeafRows` reads
such rows the way the file format defines them (https://www.sqlite.org/fileformat2.html): every
page whose type byte says "table leaf" is parsed, and a cell whose record has the messages
table's shape, and whose overflow chain runs whole through pages the file holds, is a row.
`tisem.io.db3_rows` asks it only for rows SQLite cannot reach.
"""

from __future__ import annotations

import bisect
import mmap
from dataclasses import dataclass
from pathlib import Path

TABLE_LEAF = 0x0D
HEADER = 100  # the database header, before page 1's b-tree page header


@dataclass(frozen=True)
class Columns:
    """Where the messages table keeps its values: the record's number of columns and the
    places of the row id's alias (stored as NULL), topic_id, timestamp and data."""

    count: int
    rowid: int
    topic_id: int
    timestamp: int
    data: int


def _varint(buf, at: int, end: int) -> tuple[int, int]:
    """(value, position after it) of the SQLite varint at `at`; ValueError past `end`."""
    value = 0
    for i in range(9):
        if at + i >= end:
            raise ValueError("a varint runs past its page")
        byte = buf[at + i]
        if i == 8:
            return (value << 8) | byte, at + 9
        value = (value << 7) | (byte & 0x7F)
        if byte < 0x80:
            return value, at + i + 1
    raise AssertionError("unreachable")


def _serial_size(serial: int) -> int:
    """Bytes a record value of this serial type takes (file format, 2.1)."""
    if serial < 12:
        sizes = (0, 1, 2, 3, 4, 6, 8, 8, 0, 0)
        if serial >= len(sizes):
            raise ValueError(f"reserved serial type {serial}")
        return sizes[serial]
    return (serial - 12) // 2 if serial % 2 == 0 else (serial - 13) // 2


def _integer(raw: bytes, serial: int) -> int | None:
    if serial in (8, 9):
        return serial - 8
    if 1 <= serial <= 6:
        return int.from_bytes(raw, "big", signed=True)
    return None


class _File:
    """The file's pages, mapped (nothing is read into memory beyond what is parsed)."""

    def __init__(self, buf, page_size: int, usable: int) -> None:
        self.buf, self.page, self.usable = buf, page_size, usable
        self.pages = len(buf) // page_size  # whole pages only: a cut page holds no row

    def local_size(self, payload: int) -> int:
        """How much of a table leaf cell's payload is on the page itself (file format, 1.6)."""
        most = self.usable - 35
        if payload <= most:
            return payload
        least = (self.usable - 12) * 32 // 255 - 23
        k = least + (payload - least) % (self.usable - 4)
        return k if k <= most else least

    def payload(self, at: int, local: int, total: int, end: int) -> bytes | None:
        """The payload of a cell whose local part starts at `at`: the local bytes and its
        overflow chain, None where the chain leaves the file, loops, or ends short."""
        if at + local > end or total > local + self.pages * (self.usable - 4):
            return None
        parts = [self.buf[at : at + local]]
        got = local
        if got < total:
            if at + local + 4 > end:
                return None
            nxt = int.from_bytes(self.buf[at + local : at + local + 4], "big")
            seen = set()
            while got < total:
                if not 1 <= nxt <= self.pages or nxt in seen:
                    return None
                seen.add(nxt)
                start = (nxt - 1) * self.page
                take = min(self.usable - 4, total - got)
                parts.append(self.buf[start + 4 : start + 4 + take])
                got += take
                nxt = int.from_bytes(self.buf[start : start + 4], "big")
        return b"".join(parts)

    def leaf(self, number: int) -> tuple[int, int] | None:
        """(where its cell pointers start, how many) of table leaf page `number`, None for a
        page of another kind or a header that does not fit its page."""
        base = (number - 1) * self.page
        head = base + (HEADER if number == 1 else 0)
        if self.buf[head] != TABLE_LEAF:
            return None
        count = int.from_bytes(self.buf[head + 3 : head + 5], "big")
        if head + 8 + 2 * count > base + self.usable:
            return None
        return head + 8, count

    def cell(self, number: int, pointers: int, count: int, i: int):
        """(rowid, payload size, offset of its local part, page end) of cell i of a table leaf
        page (`leaf`), None where its pointer or header leaves the page."""
        base = (number - 1) * self.page
        end = base + self.usable
        at = base + int.from_bytes(self.buf[pointers + 2 * i : pointers + 2 * i + 2], "big")
        if not pointers + 2 * count <= at < end:
            return None
        try:
            payload, at = _varint(self.buf, at, end)
            rowid, at = _varint(self.buf, at, end)
        except ValueError:
            return None
        return rowid, payload, at, end


def _message(record: bytes, columns: Columns) -> tuple[int, int, bytes] | None:
    """(topic_id, timestamp, data) of a messages table record, None for another shape."""
    try:
        size, at = _varint(record, 0, len(record))
        if size > len(record):
            return None
        serials = []
        while at < size:
            serial, at = _varint(record, at, size)
            serials.append(serial)
    except ValueError:
        return None
    if at != size or len(serials) != columns.count or serials[columns.rowid] != 0:
        return None
    values, pos = [], size
    for serial in serials:
        try:
            n = _serial_size(serial)
        except ValueError:
            return None
        values.append((serial, record[pos : pos + n]))
        pos += n
    if pos != len(record):
        return None
    (ts, topic), (tt, stamp), (td, data) = (
        values[columns.topic_id],
        values[columns.timestamp],
        values[columns.data],
    )
    topic_id, timestamp = _integer(topic, ts), _integer(stamp, tt)
    if topic_id is None or timestamp is None or td < 12 or td % 2:
        return None
    return topic_id, timestamp, bytes(data)


def _free_pages(file: _File) -> set[int]:
    """The pages on the database's freelist (header bytes 32-35: its first trunk page; each
    trunk: the next trunk, a count, the leaf page numbers), as far as the file holds them
    whole and no further than the header's count of them (bytes 36-39); the walk stops at a
    loop or a count that does not fit its trunk."""
    free: set[int] = set()
    total = int.from_bytes(file.buf[36:40], "big")
    trunk = int.from_bytes(file.buf[32:36], "big")
    while 1 <= trunk <= file.pages and trunk not in free and len(free) < total:
        free.add(trunk)
        at = (trunk - 1) * file.page
        nxt = int.from_bytes(file.buf[at : at + 4], "big")
        count = int.from_bytes(file.buf[at + 4 : at + 8], "big")
        if 8 + 4 * count > file.usable:
            break
        for k in range(count):
            free.add(int.from_bytes(file.buf[at + 8 + 4 * k : at + 12 + 4 * k], "big"))
        trunk = nxt
    return free


class LeafRows:
    """The messages table's rows on the file's table leaf pages, by id (`get`). Opening it
    passes over every page once and notes each leaf's smallest and largest row id: a
    recording of any size costs a few numbers per page, and a row's bytes are read when asked
    for. Pages on the freelist are left out: they hold deleted rows."""

    # a lookup walks back over at most this many leaves whose ranges begin at or below the
    # id; more that may hold it means damage (or copies), and the id is then ambiguous
    MAX_STEPS = 64

    def __init__(self, path: Path, columns: Columns) -> None:
        self.columns = columns
        self._file = None
        self._firsts, self._lasts, self._reach, self._pages = [], [], [], []
        # leaves whose ids span far more than their cells do (a damaged id): looked at by
        # every lookup, kept out of the others' running reach, which they would stretch
        self._wide: list[tuple[int, int, int]] = []
        with open(path, "rb") as f:
            try:
                buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
            except ValueError:  # an empty file
                return
        page = int.from_bytes(buf[16:18], "big") if len(buf) >= HEADER else 0
        page = 65536 if page == 1 else page
        if page < 512 or page & (page - 1) or buf[20] > page - 480:
            buf.close()
            return
        self._file = file = _File(buf, page, page - buf[20])
        free = _free_pages(file)
        ranges = []
        for number in range(1, file.pages + 1):
            leaf = None if number in free else file.leaf(number)
            if leaf is None:
                continue
            ids = [c[0] for i in range(leaf[1]) if (c := file.cell(number, *leaf, i))]
            if not ids:
                continue
            first, last = min(ids), max(ids)
            if last - first > max(64, 8 * len(ids)):  # (rosbag2 numbers rows 1, 2, ...)
                self._wide.append((first, last, number))
            else:
                ranges.append((first, last, number))
        ranges.sort()
        reach = -1
        for first, last, number in ranges:
            reach = max(reach, last)  # (the largest last id of this leaf and those before it)
            self._firsts.append(first)
            self._lasts.append(last)
            self._reach.append(reach)
            self._pages.append(number)

    def _leaves(self, rowid: int) -> list[int] | None:
        """The leaves whose id range holds `rowid`; None where there may be more than
        MAX_STEPS of them (ambiguous)."""
        found = [number for first, last, number in self._wide if first <= rowid <= last]
        k = bisect.bisect_right(self._firsts, rowid) - 1
        for _ in range(self.MAX_STEPS):
            if k < 0 or self._reach[k] < rowid:
                return found
            if self._lasts[k] >= rowid:
                found.append(self._pages[k])
            k -= 1
        return None if k >= 0 and self._reach[k] >= rowid else found

    def _cells(self, number: int, rowid: int) -> list[tuple]:
        """The cells of leaf `number` with id `rowid`: a binary search over its cells (in id
        order), or a look at each where a cell met does not parse."""
        leaf = self._file.leaf(number)
        if leaf is None:  # (the file changed since it was indexed)
            return []
        lo, hi = 0, leaf[1] - 1
        while lo <= hi:
            mid = (lo + hi) // 2
            cell = self._file.cell(number, *leaf, mid)
            if cell is None:
                break
            if cell[0] == rowid:
                return [cell]
            lo, hi = (mid + 1, hi) if cell[0] < rowid else (lo, mid - 1)
        else:
            return []
        cells = (self._file.cell(number, *leaf, i) for i in range(leaf[1]))
        return [c for c in cells if c is not None and c[0] == rowid]

    def get(self, rowid: int) -> tuple[int, int, bytes] | None:
        """(topic_id, timestamp, data) of row `rowid`, None where no page holds it whole, or
        two pages hold different rows of that id (a stale page beside the live one: neither
        can be trusted), or too many leaves may hold it to look at."""
        leaves = self._leaves(rowid)
        if leaves is None:
            return None
        rows = set()
        for number in leaves:
            for _, size, at, end in self._cells(number, rowid):
                record = self._file.payload(at, self._file.local_size(size), size, end)
                row = None if record is None else _message(record, self.columns)
                if row is not None:  # (else another table's cell, or one whose data is gone)
                    rows.add(row)
        return rows.pop() if len(rows) == 1 else None

    def close(self) -> None:
        if self._file is not None:
            self._file.buf.close()
            self._file = None

    def __enter__(self) -> LeafRows:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
