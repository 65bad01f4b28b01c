"""Rows of a `.db3` read from its leaf pages (tisem.io.db3_pages), for rows whose path
through the table's tree is lost: checked against SQLite's own reading of intact files, and on
a recording cut short before the interior pages rosbag2's inserts leave at its end."""

from __future__ import annotations

import sqlite3
import struct
from collections import Counter

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the rosbags package (tisem[mcap]) is not installed")

from tisem.io.db3_pages import Columns, LeafRows, _message, _varint  # noqa: E402
from tisem.io.db3_rows import Db3RowRecords  # noqa: E402
from tisem.io.mcap_records import LostMessages, McapMessage, ReadReport  # noqa: E402
from tisem.testing.bag_damage import write_db3  # noqa: E402

PAGE = 4096
CLOUD = ("/velodyne_points", "sensor_msgs/msg/PointCloud2")
TF = ("/tf", "tf2_msgs/msg/TFMessage")


def messages(n: int, sizes, seed: int = 0) -> list[tuple[str, str, int, bytes]]:
    """n (topic, type, stamp, data) rows, clouds and /tf alternating, of random bytes (the rows
    are read here, never decoded) and the sizes `sizes(rng)` draws."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        topic, typ = CLOUD if k % 2 else TF
        out.append((topic, typ, 1_000_000 * k, rng.bytes(int(sizes(rng)))))
    return out


def columns_of(db3) -> Columns:
    with sqlite3.connect(db3) as db:
        names = [row[1] for row in db.execute("PRAGMA table_info(messages)")]
    db.close()
    return Columns(
        len(names), names.index("id"), *map(names.index, ("topic_id", "timestamp", "data"))
    )


def test_varints_read_as_sqlite_writes_them():
    for value, encoded in [
        (0, b"\x00"),
        (127, b"\x7f"),
        (128, b"\x81\x00"),
        (16383, b"\xff\x7f"),
        (2**57, b"\x81\x80\x80\x80\x80\x80\x80\x80\x00"),  # 9 bytes: the last holds 8 bits
        (2**64 - 1, b"\xff" * 9),
    ]:
        assert _varint(encoded + b"\x55", 0, len(encoded) + 1) == (value, len(encoded))
    with pytest.raises(ValueError, match="runs past its page"):
        _varint(b"\x81\x82", 0, 2)


def test_every_row_of_an_intact_file_reads_as_sqlite_reads_it(tmp_path):
    """Payloads from empty to five pages long: on the page alone, split at every local size
    the format's rule gives, and over overflow chains; SQLite is the reference."""
    rows = messages(
        400, lambda rng: rng.choice([rng.integers(0, 600), rng.integers(3_000, 21_000)])
    )
    db3 = write_db3(tmp_path / "bag", rows)
    with sqlite3.connect(db3) as db:
        expected = {
            i: (t, s, bytes(d))
            for i, t, s, d in db.execute("SELECT id, topic_id, timestamp, data FROM messages")
        }
    db.close()
    assert len(expected) == 400
    with LeafRows(db3, columns_of(db3)) as pages:
        assert {i: pages.get(i) for i in expected} == expected
        assert pages.get(401) is None  # (topics' and metadata's rows share ids: not messages)


def _tree_pages(data: bytes, root: int) -> tuple[list[int], list[int]]:
    """(interior pages, leaf pages) of the table b-tree rooted at page `root`."""
    interior, leaves, todo = [], [], [root]
    while todo:
        number = todo.pop()
        page = data[(number - 1) * PAGE : number * PAGE]
        if page[0] == 0x0D:
            leaves.append(number)
            continue
        assert page[0] == 0x05
        interior.append(number)
        cells = struct.unpack_from(">H", page, 3)[0]
        for i in range(cells):
            (at,) = struct.unpack_from(">H", page, 12 + 2 * i)
            todo.append(struct.unpack_from(">I", page, at)[0])
        todo.append(struct.unpack_from(">I", page, 8)[0])
    return interior, leaves


def read_records(db3) -> tuple[list, ReadReport]:
    report = ReadReport()
    out = [
        r for r in Db3RowRecords([db3]).records(report) if isinstance(r, McapMessage | LostMessages)
    ]
    return out, report


def test_rows_below_interior_pages_a_cut_took_are_read_from_their_own_pages(tmp_path):
    """rosbag2 inserts leave a table's interior pages late in the file: cut before the one
    above the first leaves, the file still holds those leaves and their rows' data, and SQLite
    calls every one of them malformed. Each row whose cell and overflow pages lie before the
    cut is read, byte for byte the intact file's, in id order; the rest are reported."""
    rows = messages(1_400, lambda rng: rng.integers(1_200, 2_600))  # (two or three a leaf)
    db3 = write_db3(tmp_path / "bag", rows)
    data = db3.read_bytes()
    with sqlite3.connect(db3) as db:
        (root,) = db.execute(
            "SELECT rootpage FROM sqlite_master WHERE name = 'messages'"
        ).fetchone()
        intact = [
            (s, bytes(d)) for s, d in db.execute("SELECT timestamp, data FROM messages ORDER BY id")
        ]
    db.close()
    interior, leaves = _tree_pages(data, root)
    assert len(interior) > 2  # a tree of three levels, as a long recording's
    first_parent = min(p for p in interior if p != root)
    assert min(leaves) < first_parent  # leaves the cut keeps, their parent lost
    db3.write_bytes(data[: (first_parent - 1) * PAGE])

    read, report = read_records(db3)
    got = [(m.log_time, m.data) for m in read if isinstance(m, McapMessage)]
    assert len(got) > 500
    assert got == intact[: len(got)]  # the rows before the cut, identical, none skipped
    assert read[: len(got)] == [m for m in read if isinstance(m, McapMessage)]
    assert isinstance(read[len(got)], LostMessages)
    (note,) = [n for n in report.notes if "read from their own pages" in n]
    assert note.startswith(f"messages table rows 1-{len(got)} ")
    assert Counter(report.messages) == Counter(topic for topic, _, _, _ in rows[: len(got)])


def test_a_stale_page_that_disagrees_with_the_live_one_gives_no_row(tmp_path):
    """Two leaf pages that hold different rows of one id (a freed page's old copy beside the
    page that replaced it): neither is taken."""
    rows = messages(6, lambda rng: 100)
    db3 = write_db3(tmp_path / "bag", rows)
    data = bytearray(db3.read_bytes())
    with sqlite3.connect(db3) as db:
        (root,) = db.execute(
            "SELECT rootpage FROM sqlite_master WHERE name = 'messages'"
        ).fetchone()
    db.close()
    leaf = data[(root - 1) * PAGE : root * PAGE]
    assert leaf[0] == 0x0D
    stale = bytearray(leaf)
    cell = struct.unpack_from(">H", stale, 8)[0]  # the first cell: row 1's
    stale[cell + 20] ^= 0xFF  # inside its data
    db3.write_bytes(bytes(data) + bytes(stale))  # one page more at the end
    with LeafRows(db3, columns_of(db3)) as pages:
        assert pages.get(1) is None
        assert pages.get(2) is not None and pages.get(2)[2] == rows[1][3]


def test_deleted_rows_on_freed_pages_are_not_read(tmp_path):
    """Rows deleted with their pages (SQLite's secure_delete off, as upstream builds have it)
    still sit on the freelist's pages, cells and all: they are no rows."""
    rows = messages(600, lambda rng: 1_500)
    db3 = write_db3(tmp_path / "bag", rows)
    with sqlite3.connect(db3) as db:
        db.execute("PRAGMA secure_delete = OFF")
        db.execute("DELETE FROM messages WHERE id BETWEEN 100 AND 400")
        (free,) = db.execute("PRAGMA freelist_count").fetchone()
    db.close()
    assert free > 50
    data = db3.read_bytes()
    stale = [  # the freed leaves that still list deleted rows
        n
        for n in range(2, len(data) // PAGE + 1)
        if data[(n - 1) * PAGE] == 0x0D and struct.unpack_from(">H", data, (n - 1) * PAGE + 3)[0]
    ]
    with LeafRows(db3, columns_of(db3)) as pages:
        assert all(pages.get(i) is None for i in range(100, 401))
        assert pages.get(99) == (1, rows[98][2], rows[98][3])  # (topic ids: /tf 1, clouds 2)
        assert pages.get(401) is not None
    assert len(stale) > free // 2  # (what the freelist walk keeps out)


def test_a_record_header_longer_than_its_record_is_no_row():
    cols = Columns(4, 0, 1, 2, 3)
    assert _message(b"\x81\x00\x00", cols) is None  # (a header of 128 bytes in 3)
    # (serial types: NULL, two 1-byte integers, then 16 = a blob of 2 bytes, 17 = text of 2)
    assert _message(b"\x05\x00\x01\x01\x11\x07\x08ab", cols) is None  # (text: no blob)
    assert _message(b"\x05\x00\x01\x01\x10\x07\x08abc", cols) is None  # (a byte too many)
    assert _message(b"\x05\x00\x01\x01\x10\x07\x08ab", cols) == (7, 8, b"ab")


def _leaf_of(data: bytes, rowid: int) -> tuple[int, int]:
    """(page number, cells) of the table leaf that holds `rowid` among its first and last."""
    for n in range(2, len(data) // PAGE + 1):
        base = (n - 1) * PAGE
        if data[base] != 0x0D:
            continue
        count = struct.unpack_from(">H", data, base + 3)[0]
        ids = []
        for i in range(count):
            at = base + struct.unpack_from(">H", data, base + 8 + 2 * i)[0]
            _, at = _varint(data, at, base + PAGE)
            ids.append(_varint(data, at, base + PAGE)[0])
        if ids and ids[0] <= rowid <= ids[-1] and count > 5:
            return n, count
    raise AssertionError(f"no leaf of several cells holds row {rowid}")


@pytest.mark.parametrize("damage", ["first cell's pointer", "last cell's id"])
def test_one_damaged_cell_of_a_leaf_costs_that_row_alone(tmp_path, damage):
    """A leaf is indexed by every cell that parses, not by its first and last alone; a leaf
    whose ids span far more than its cells (a damaged id) is looked at apart, so it neither
    hides its other rows nor stretches the search for everyone else's."""
    rows = messages(3_000, lambda rng: 150)
    db3 = write_db3(tmp_path / "bag", rows)
    data = bytearray(db3.read_bytes())
    number, count = _leaf_of(bytes(data), 1_500)
    base = (number - 1) * PAGE
    if damage == "first cell's pointer":
        struct.pack_into(">H", data, base + 8, 0)  # (into the page's header)
    else:  # the last cell's rowid varint made 9 bytes of 0xff: an id near 2^64
        at = base + struct.unpack_from(">H", data, base + 8 + 2 * (count - 1))[0]
        _, at = _varint(data, at, base + PAGE)
        data[at : at + 9] = b"\xff" * 9
    db3.write_bytes(bytes(data))
    with LeafRows(db3, columns_of(db3)) as pages:
        got = {i: pages.get(i) for i in range(1, 3_001)}
    lost = [i for i, row in got.items() if row is None]
    assert len(lost) == 1
    assert all(got[i] == (1 + (i - 1) % 2, rows[i - 1][2], rows[i - 1][3]) for i in got if got[i])


def test_a_row_on_more_leaves_than_a_lookup_walks_is_no_row(tmp_path):
    """Copies of a leaf beyond LeafRows.MAX_STEPS (damage, or pages copied into the file):
    which is the live one cannot be told, so its rows are none; other rows read as before."""
    rows = messages(3_000, lambda rng: 150)
    db3 = write_db3(tmp_path / "bag", rows)
    data = db3.read_bytes()
    number, _ = _leaf_of(data, 1_500)
    leaf = data[(number - 1) * PAGE : number * PAGE]
    db3.write_bytes(data + leaf * (LeafRows.MAX_STEPS + 2))
    with LeafRows(db3, columns_of(db3)) as pages:
        assert pages.get(1_500) is None
        assert pages.get(10) == (2, rows[9][2], rows[9][3])
