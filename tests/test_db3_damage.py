"""A damaged `.db3` read row by row (tisem.io.db3_rows): SQLite checks no page, so what it
cannot vouch for is reported rather than passed on. A row missing below the largest id (rosbag2
numbers its rows 1, 2, ...) is a lost message, and a file that ends inside a page (cut, or bytes
inserted), whose short page sqlite reads as zeros, marks every scan suspect."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the rosbags package (tisem[mcap]) is not installed")

import test_rosbag_read  # noqa: E402
from test_rosbag_read import make_input  # noqa: E402

from tisem.io.bag_open import BagInput, _open, open_scan_reader  # noqa: E402
from tisem.io.mcap_reader import McapOptions  # noqa: E402
from tisem.io.semantickitti import SemanticKittiSequence  # noqa: E402
from tisem.scan import Scan  # noqa: E402

recording = test_rosbag_read.recording  # (the fixture: a tiny sequence and its messages)


def read(path):
    reader = open_scan_reader(path, McapOptions(gt_field="gt_label"))
    return [s for s in reader if isinstance(s, Scan)], reader.report


def test_a_row_missing_below_the_largest_id_is_a_lost_message(recording):
    """Read row by row (as a `.db3` rosbags stops reading is), a row sqlite no longer returns
    below the largest id (deleted here; a damaged page's rows can vanish so) is the third
    cloud, reported lost, and the scans after it suspect, not silently renumbered."""
    seq_dir, messages, tmp = recording
    folder = make_input("db3 folder", messages, tmp / "missing_row")
    (db3,) = folder.glob("*.db3")
    with sqlite3.connect(db3) as db:
        (clouds,) = db.execute("SELECT id FROM topics WHERE name = '/velodyne_points'").fetchone()
        rows = [r for (r,) in db.execute("SELECT id FROM messages WHERE topic_id = ?", (clouds,))]
        db.execute("DELETE FROM messages WHERE id = ?", (sorted(rows)[2],))
    db.close()
    reader = _open(BagInput(db3, "db3-rows", "a .db3", (db3,)), McapOptions(gt_field="gt_label"))
    scans = [s for s in reader if isinstance(s, Scan)]
    expected = list(SemanticKittiSequence(seq_dir))
    assert [s.index for s in scans] == [0, 1, 2]
    for s, k in zip(scans, (0, 1, 3)):
        assert np.array_equal(s.points_sensor, expected[k].points_sensor)
    (loss,) = reader.report.losses
    assert loss.where == f"messages table rows {sorted(rows)[2]}" and loss.messages == 1
    assert 2 in reader.report.suspect


def test_a_db3_that_ends_inside_a_page_marks_its_scans_suspect(recording):
    seq_dir, messages, tmp = recording
    db3 = make_input("humble db3 file", messages, tmp / "cut_page")
    data = db3.read_bytes()
    assert len(data) % 4096 == 0
    db3.write_bytes(data[:-100])
    scans, report = read(db3)
    assert scans and all(s.index in report.suspect for s in scans)
    assert report.losses[0].where == "the file's end" and report.losses[0].uncounted
    assert "3996 bytes into a page of 4096" in report.losses[0].what


def test_a_db3_cut_short_by_whole_pages_gives_the_scans_on_the_pages_left(recording):
    """SQLite refuses a file shorter than its header says as a whole ("malformed"), though the
    pages it holds are whole: the scans whose rows lie on them are read, each identical to the
    intact file's, and the cut is reported with the pages missing."""
    seq_dir, messages, tmp = recording
    db3 = make_input("humble db3 file", messages, tmp / "cut_pages")
    data = db3.read_bytes()
    pages = len(data) // 4096
    db3.write_bytes(data[: -2 * 4096])
    scans, report = read(db3)
    expected = list(SemanticKittiSequence(seq_dir))
    assert 0 < len(scans) < len(expected)
    assert [s.index for s in scans] == list(range(len(scans)))
    for s in scans:
        assert np.array_equal(s.points_sensor, expected[s.index].points_sensor)
        assert np.array_equal(s.labels, expected[s.index].labels)
    assert report.losses[0].where == "the file's end"
    assert report.losses[0].what == (
        f"the file holds {pages - 2} of the {pages} pages its header gives (cut short)"
    )
    assert any(loss.where.startswith("messages table after row") for loss in report.losses)
