"""A rosbag2 `.db3` read row by row, around damaged database pages.

`rosbags` reads a `.db3` through whole-table queries: one damaged page of the messages table
(or of its index) and it cannot open the bag, or stops part-way. SQLite still finds most rows
by their id, each through its own path in the table's tree, so `Db3RowRecords` asks for them
one at a time: a row on a damaged page is one lost message, the others are mapped. It gives
`McapScanReader` the same stream `tisem.io.bag_records` gives for other bags. The types are
the Humble type store's, plus any the bag defines in its `message_definitions` table.
"""

from __future__ import annotations

import sqlite3
from collections import Counter
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

from mcap.records import Channel, Schema
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from tisem.errors import DatasetError
from tisem.io.bag_records import RosbagDecoders
from tisem.io.db3_pages import Columns, LeafRows
from tisem.io.mcap_items import unknown_loss
from tisem.io.mcap_records import LostMessages, McapMessage, ReadReport
from tisem.io.mcap_report import Loss, id_ranges, one_line

# ids probed past the last row found when the table cannot say its largest id
MAX_ID_GAP = 1_000

# what reading a damaged database raises: sqlite's errors, and UnicodeDecodeError where the
# text sqlite3 decodes (a garbled schema in its message) is not UTF-8
DAMAGE = (sqlite3.DatabaseError, UnicodeDecodeError)


class Db3RowRecords:
    """The Schema, Channel and message records of the `.db3` files of one recording (its
    splits, in order), their messages by id (see the module docstring); `decoders` decodes
    them. Topics are numbered across the files (every split numbers its own)."""

    def __init__(self, paths: list[Path]) -> None:
        self.parts = [_Db3File(Path(p)) for p in paths]
        self.path = self.parts[0].path
        self.excess: Counter = Counter()
        self.data_crc: str | None = None
        typestore = get_typestore(Stores.ROS2_HUMBLE)
        for part in self.parts:
            for typ, text in part.definitions:
                try:
                    typestore.register(get_types_from_msg(text, typ))
                except Exception:  # noqa: BLE001 - a damaged definition: the Humble one stands
                    pass
        self.decoders = RosbagDecoders(typestore, False, self.path)

    def records(
        self, report: ReadReport
    ) -> Iterator[Schema | Channel | McapMessage | LostMessages]:
        schemas: dict[str, int] = {}
        channels: dict[tuple[str, str], int] = {}  # (topic, type) -> channel id
        for part in self.parts:
            ids = {}  # the file's topic id -> channel id
            for tid, (topic, typ) in sorted(part.topics.items()):
                if typ not in schemas:
                    schemas[typ] = len(schemas) + 1
                    yield Schema(id=schemas[typ], name=typ, encoding="ros2msg", data=b"")
                if (topic, typ) not in channels:
                    channels[topic, typ] = len(channels) + 1
                    yield Channel(
                        id=channels[topic, typ],
                        topic=topic,
                        schema_id=schemas[typ],
                        message_encoding="cdr",
                        metadata={},
                    )
                ids[tid] = channels[topic, typ]
            yield from part.messages(report, ids, len(self.parts) > 1)


class _Db3File:
    """One `.db3`: its topics and message definitions on opening, its messages by id."""

    def __init__(self, path: Path) -> None:
        self.path = path
        with closing(self._connect()) as db:
            try:
                rows = db.execute("SELECT id, name, type FROM topics").fetchall()
            except DAMAGE as exc:
                raise DatasetError(
                    f"{self.path}: its topics table is unreadable ({one_line(str(exc))})"
                ) from None
            self.topics = {  # (sqlite keeps whatever a damaged page holds: check the types)
                i: (name, typ)
                for i, name, typ in rows
                if isinstance(i, int) and isinstance(name, str) and isinstance(typ, str)
            }
            self.definitions = self._definitions(db)
            self.columns = self._columns(db)

    def _connect(self) -> sqlite3.Connection:
        try:  # immutable: no journal or lock files next to a damaged recording
            db = sqlite3.connect(f"file:{self.path}?mode=ro&immutable=1", uri=True)
        except sqlite3.Error as exc:
            raise DatasetError(f"{self.path}: cannot open ({one_line(str(exc))})") from None
        # a file shorter than its header says (cut short) is refused as a whole ("malformed"),
        # even the pages it still holds, unless the schema is writable: then sqlite reads the
        # pages there are and calls a row on a missing page malformed (one lost message). The
        # connection stays read-only and immutable: nothing is written
        db.execute("PRAGMA writable_schema=ON")
        # text a damaged page garbled is not UTF-8: decoded with replacement characters, a
        # damaged name matches nothing, where sqlite3's own decoding would raise mid-query
        db.text_factory = lambda raw: raw.decode("utf-8", "replace")
        return db

    @staticmethod
    def _definitions(db: sqlite3.Connection) -> list[tuple[str, str]]:
        """(type, .msg text) the bag stores (rosbag2 schema 4 and later; Humble stores none)."""
        try:
            rows = db.execute(
                "SELECT topic_type, encoded_message_definition FROM message_definitions "
                "WHERE encoding = 'ros2msg'"
            ).fetchall()
        except DAMAGE:
            return []
        return [(str(t), str(d)) for t, d in rows if t and d]

    @staticmethod
    def _columns(db: sqlite3.Connection) -> Columns | None:
        """Where the messages table's records keep the id's alias, topic_id, timestamp and
        data (for rows read from their pages), None where its declaration does not say."""
        try:
            info = db.execute("PRAGMA table_info(messages)").fetchall()
        except DAMAGE:
            return None
        names = [str(row[1]) for row in info]
        keys = [str(row[1]) for row in info if row[5] == 1 and str(row[2]).upper() == "INTEGER"]
        wanted = ("topic_id", "timestamp", "data")
        if len(keys) != 1 or not all(names.count(n) == 1 for n in wanted):
            return None
        return Columns(len(names), names.index(keys[0]), *(names.index(n) for n in wanted))

    def messages(self, report: ReadReport, ids: dict[int, int], named: bool) -> Iterator:
        """Its messages on the channels `ids` gives its topics; `named`: losses name the file."""
        unreadable: list[int] = []
        from_pages: list[int] = []
        yield from short_page_loss(self.path, report, named)
        with closing(self._connect()) as db, _PagesWhenNeeded(self) as pages:
            last = self._last_id(db)
            k, found = 0, 0
            # to the largest id, or while rows turn up when the table cannot say it; a run of
            # ids without a row much longer than that ends it either way (a damaged max)
            while (k < last if last >= 0 else k - found < MAX_ID_GAP) and (
                k - found < 100 * MAX_ID_GAP
            ):
                k += 1
                try:
                    row = db.execute(
                        "SELECT topic_id, timestamp, data FROM messages WHERE id = ?", (k,)
                    ).fetchone()
                except DAMAGE:
                    row = ()
                if row is None or not _whole(row, self.topics):
                    # (rosbag2 numbers its rows 1, 2, ...: below the largest id, in a file that
                    # rosbags could not read, a row that is not there was on a damaged page;
                    # its own page may be whole, with the tree above it lost: db3_pages)
                    probed, row = row is None and last < 0, pages.get(k)
                    if row is not None and _whole(row, self.topics):
                        from_pages.append(k)
                    elif probed:
                        continue  # (probing past the end, or a gap in the ids)
                if row is None or not _whole(row, self.topics):
                    unreadable.append(k)
                    yield LostMessages(None, None, f"{self.path.name}: messages table row {k}")
                    continue
                found = k
                report.messages[self.topics[row[0]][0]] += 1
                yield McapMessage(
                    channel_id=ids[row[0]], log_time=row[1], data=bytes(row[2]), crc_checked=False
                )
        where = f"{self.path.name}: messages table" if named else "messages table"
        if from_pages:
            report.notes.append(
                f"{where} rows {id_ranges(from_pages)} read from their own pages: the table's "
                f"tree above them is on damaged or missing pages"
            )
        self._report(report, where, unreadable, found if last < 0 else None)

    @staticmethod
    def _report(
        report: ReadReport, table: str, unreadable: list[int], end_unknown_after: int | None
    ) -> None:
        """The unreadable rows as losses; with the table's end unknown, those after the last
        row found may be no rows at all: an unknown number of messages."""
        lost = [k for k in unreadable if end_unknown_after is None or k < end_unknown_after]
        if lost:
            report.losses.append(
                Loss(
                    f"{table} rows {id_ranges(lost)}",
                    "on damaged database pages",
                    messages=len(lost),
                )
            )
        if len(lost) < len(unreadable):
            report.losses.append(
                Loss(
                    f"{table} after row {end_unknown_after}",
                    "its end is on damaged database pages",
                    uncounted=True,
                )
            )

    @staticmethod
    def _last_id(db: sqlite3.Connection) -> int:
        """The largest message id, or -1 when the table cannot say (then ids are probed)."""
        try:
            (last,) = db.execute("SELECT max(id) FROM messages").fetchone()
        except DAMAGE:
            return -1
        if last is None:
            return 0  # (no messages)
        return last if isinstance(last, int) and 0 <= last < 2**62 else -1


class _PagesWhenNeeded:
    """`LeafRows` of a file, opened at the first row SQLite cannot give (it passes over every
    page), and only for a file whose messages table says where its values are."""

    def __init__(self, part: _Db3File) -> None:
        self.part, self.rows = part, None

    def get(self, rowid: int) -> tuple | None:
        if self.part.columns is None:
            return None
        if self.rows is None:
            self.rows = LeafRows(self.part.path, self.part.columns)
        return self.rows.get(rowid)

    def __enter__(self) -> _PagesWhenNeeded:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.rows is not None:
            self.rows.close()


def _whole(row: tuple, topics: dict) -> bool:
    """Whether a messages row holds a known topic, an integer stamp and bytes (a damaged page
    can hold anything)."""
    return (
        len(row) == 3
        and isinstance(row[0], int)
        and row[0] in topics
        and isinstance(row[1], int)
        and 0 <= row[1] < 2**63
        and isinstance(row[2], bytes)
    )


def short_page_loss(path: Path, report: ReadReport, named: bool) -> Iterator[LostMessages]:
    """A loss, first in the stream, for a `.db3` that ends inside a page (cut, or bytes
    inserted): sqlite reads what its short page lacks as zeros, unchecked, and which rows lay
    there is not known, so every row after the mark is suspect. Its header gives the page
    size (bytes 16-17, big-endian; 1 means 65536). A file cut at a page's end reads whole
    pages: the loss then only says so, and the rows on the missing pages are lost one by one."""
    try:
        with open(path, "rb") as f:
            head = f.read(100)
            size = f.seek(0, 2)
    except OSError:
        return  # (opening it says so)
    page = int.from_bytes(head[16:18], "big") if len(head) >= 18 else 0
    page = 65536 if page == 1 else page
    if page < 512 or page & (page - 1):
        return  # (a damaged header: sqlite says what it makes of it)
    where = f"{path.name}: its end" if named else "the file's end"
    if size % page:
        what = (
            f"the file ends {size % page} bytes into a page of {page} (cut short, or bytes "
            f"inserted): rows on that page may read as zeros"
        )
        yield unknown_loss(report, where, what)
    elif size // page < (declared := _pages_in_header(head)):
        what = f"the file holds {size // page} of the {declared} pages its header gives (cut short)"
        report.losses.append(Loss(where, what, uncounted=True))


def _pages_in_header(head: bytes) -> int:
    """The database's size in pages by its header (bytes 28-31), 0 where the header does not
    vouch for it: SQLite trusts that field only while the change counter (bytes 24-27) equals
    the version it was written at (bytes 92-95)."""
    if len(head) < 100 or head[24:28] != head[92:96]:
        return 0
    return int.from_bytes(head[28:32], "big")
