"""tisem.io.bag_open (map_mcap.py's input): what `ros2 bag record` and the `rosbags` library
write — a rosbag2 folder split in two MCAP files with QoS, sqlite3 (`.db3`) bags, per-message
and per-file compression, a ROS 1 bag — gives the scans of the SemanticKITTI folder they were
made from (end to end: the same predictions), and what cannot be read is refused in one line
that says how to convert it."""

from __future__ import annotations

import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags", reason="the rosbags package (tisem[mcap]) is not installed")

from rosbags.interfaces import (  # noqa: E402  # noqa: E402
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag1 import Writer as Ros1Writer  # noqa: E402
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer  # noqa: E402,E501
from rosbags.rosbag2 import Reader as Ros2Reader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from test_mcap_kitti import write_tiny_sequence  # noqa: E402
from test_pointcloud2 import decoded_clouds  # noqa: E402

from tisem.errors import DatasetError  # noqa: E402
from tisem.io.bag_open import identify, open_scan_reader  # noqa: E402
from tisem.io.kitti_mcap import write_kitti_mcap  # noqa: E402
from tisem.io.mapfile import load_map_file  # noqa: E402
from tisem.io.mcap_reader import McapOptions  # noqa: E402
from tisem.io.pointcloud2 import unpack_rgb  # noqa: E402
from tisem.io.semantickitti import SemanticKittiSequence  # noqa: E402
from tisem.labels import CLASS_COLORS_RGB  # noqa: E402
from tisem.scan import Scan  # noqa: E402
from tisem.testing.bag_damage import write_ros1_bag  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
NEVER = QosTime(0, 0)


def qos(transient_local: bool) -> Qos:
    return Qos(
        QosHistory.KEEP_LAST,
        1 if transient_local else 10,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        NEVER,
        NEVER,
        QosLiveliness.AUTOMATIC,
        NEVER,
        False,
    )


def recorded_messages(seq_dir: Path, tmp: Path) -> list[tuple[str, str, int, bytes]]:
    """(topic, type, log time ns, CDR bytes) of the sequence as a recorder would store them."""
    write_kitti_mcap(seq_dir, tmp / "source", output_format="rosbag2")
    with Ros2Reader(tmp / "source") as reader:
        return [(c.topic, c.msgtype, t, bytes(data)) for c, t, data in reader.messages()]


def rosbags_bag(
    folder: Path, messages, storage: StoragePlugin, compression: CompressionMode | None = None
) -> Path:
    """One rosbag2 folder written by rosbags' own writer, every topic with its QoS."""
    writer = Writer(folder, version=9, storage_plugin=storage)
    if compression is not None:
        writer.set_compression(compression, CompressionFormat.ZSTD)
    with writer:
        connections = {}
        for topic, msgtype, t, data in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(
                    topic,
                    msgtype,
                    typestore=HUMBLE,
                    offered_qos_profiles=[qos(topic == "/tf_static")],
                )
            writer.write(connections[topic], t, data)
    return folder


def split_bag(folder: Path, messages, tmp: Path) -> Path:
    """A bag split in two MCAP files, as `ros2 bag record --max-bag-size` leaves it: two
    rosbags-written halves put in one folder, with one metadata.yaml listing both in order."""
    half = len(messages) // 2
    parts = [
        rosbags_bag(tmp / f"part{i}", chunk, StoragePlugin.MCAP)
        for i, chunk in enumerate((messages[:half], messages[half:]))
    ]
    folder.mkdir()
    metas = [
        yaml.safe_load((p / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        for p in parts
    ]
    merged = metas[0]
    merged["relative_file_paths"], merged["files"] = [], []
    counts: dict[str, dict] = {}
    for i, (part, meta) in enumerate(zip(parts, metas)):
        name = f"{folder.name}_{i}.mcap"
        shutil.move(next(part.glob("*.mcap")), folder / name)
        merged["relative_file_paths"].append(name)
        merged["files"] += [{**f, "path": name} for f in meta["files"]]
        for topic in meta["topics_with_message_count"]:
            entry = counts.setdefault(
                topic["topic_metadata"]["name"], {**topic, "message_count": 0}
            )
            entry["message_count"] += topic["message_count"]
    merged["topics_with_message_count"] = list(counts.values())
    merged["message_count"] = sum(m["message_count"] for m in metas)
    end = max(
        m["starting_time"]["nanoseconds_since_epoch"] + m["duration"]["nanoseconds"] for m in metas
    )
    merged["duration"]["nanoseconds"] = end - merged["starting_time"]["nanoseconds_since_epoch"]
    (folder / "metadata.yaml").write_text(
        yaml.safe_dump({"rosbag2_bagfile_information": merged}, sort_keys=False)
    )
    return folder


def humble_db3(path: Path) -> Path:
    """A `.db3` as Humble writes it: storage schema 3, no message definitions stored (the
    reader must know the types itself)."""
    db = sqlite3.connect(path)
    with db:  # commits
        db.execute("DROP TABLE message_definitions")
        db.execute("UPDATE schema SET schema_version = 3")
    db.close()
    return path


def ros1_bag(path: Path, messages, compression=None, chunk_bytes: int | None = None) -> Path:
    """The same messages as a ROS 1 bag, its chunks compressed with `compression` (a
    Ros1Writer.CompressionFormat) and closed after `chunk_bytes`."""
    name = None if compression is None else compression.name
    return write_ros1_bag(path, messages, name, chunk_bytes)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bags")
    seq = write_tiny_sequence(tmp / "seq", n_scans=4, n_points=500)
    return seq, recorded_messages(seq, tmp), tmp


def make_input(form: str, messages, tmp: Path) -> Path:
    tmp.mkdir(parents=True, exist_ok=True)
    if form == "split mcap":
        return split_bag(tmp / form.replace(" ", "_"), messages, tmp / "work_split")
    if form == "db3 folder":
        return rosbags_bag(tmp / "db3_bag", messages, StoragePlugin.SQLITE3)
    if form == "humble db3 file":
        return humble_db3(
            next(rosbags_bag(tmp / "db3_only", messages, StoragePlugin.SQLITE3).glob("*.db3"))
        )
    if form == "per-message zstd":
        return rosbags_bag(tmp / "msg_zstd", messages, StoragePlugin.MCAP, CompressionMode.MESSAGE)
    if form == "per-file zstd":
        return rosbags_bag(tmp / "file_zstd", messages, StoragePlugin.SQLITE3, CompressionMode.FILE)
    if form == "ros1":
        return ros1_bag(tmp / "drive.bag", messages)
    raise ValueError(form)


FORMS = ["split mcap", "db3 folder", "humble db3 file", "per-message zstd", "per-file zstd", "ros1"]


@pytest.mark.parametrize("form", FORMS)
def test_every_bag_form_gives_the_scans_of_the_folder(recording, form):
    seq_dir, messages, tmp = recording
    path = make_input(form, messages, tmp / form.replace(" ", "_"))
    reader = open_scan_reader(path, McapOptions(gt_field="gt_label"))
    expected = SemanticKittiSequence(seq_dir)
    assert reader.topic == "/velodyne_points" and reader.frame_id == "velodyne"
    assert reader.total == len(expected) == 4 and reader.report.losses == []
    got = list(reader)
    assert all(isinstance(s, Scan) for s in got)
    for a, b in zip(expected, got):
        assert b.index == a.index and b.stamp_s == pytest.approx(a.stamp_s, abs=1e-9)
        assert np.array_equal(a.points_sensor, b.points_sensor)
        assert np.array_equal(a.labels, b.labels) and np.array_equal(a.gt_labels, b.gt_labels)
        assert np.abs(a.T_world_sensor - b.T_world_sensor).max() < 1e-6


def test_an_uncompressed_mcap_bag_is_read_file_by_file_and_survives_damage(recording):
    """The split MCAP files go through tisem's own reader: a damaged second file still gives
    what it holds, and the loss names the file."""
    _, messages, tmp = recording
    folder = split_bag(tmp / "cut_bag", messages, tmp / "work_cut")
    found = identify(folder)
    assert found.kind == "mcap-split"
    assert [f.name for f in found.files] == ["cut_bag_0.mcap", "cut_bag_1.mcap"]
    second = folder / "cut_bag_1.mcap"
    data = second.read_bytes()
    second.write_bytes(data[: int(len(data) * 0.7)])
    reader = open_scan_reader(folder, McapOptions(gt_field="gt_label"))
    scans = [s for s in reader if isinstance(s, Scan)]
    assert 2 <= len(scans) < 4 and [s.index for s in scans] == list(range(len(scans)))
    assert any(line.startswith("cut_bag_1.mcap: ") for line in reader.report.lines())


def rewrite_mcap(path: Path, change, chunked: bool = True) -> None:
    """Write the MCAP file again, message by message, with `change(k, data)` applied to the data
    of its k-th point cloud; `chunked` False: no chunks (rosbag2's `fastwrite` preset), so no
    CRC covers a message."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        items = list(reader.iter_messages(log_time_order=False))
    with open(path, "wb") as out:
        # small uncompressed chunks, as rosbag2 writes them: a cut keeps the chunks before it
        writer = McapWriter(
            out, chunk_size=4096, compression=CompressionType.NONE, use_chunking=chunked
        )
        writer.start(profile="ros2", library="test")
        schemas = {
            sid: writer.register_schema(s.name, s.encoding, s.data)
            for sid, s in summary.schemas.items()
        }
        channels = {
            cid: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id])
            for cid, c in summary.channels.items()
        }
        k = 0
        for _, channel, message in items:
            data = message.data
            if channel.topic == "/velodyne_points":
                data, k = change(k, data), k + 1
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        writer.finish()


def test_a_bag_compressed_message_by_message_is_read_by_tisem_and_survives_damage(recording):
    """Each message a zstd frame of its own: tisem's reader inflates them one by one (in the
    folder or in one split given alone), so a frame that does not inflate costs its scan
    alone, and a cut file keeps what it holds."""
    seq_dir, messages, tmp = recording
    folder = rosbags_bag(tmp / "each_zstd", messages, StoragePlugin.MCAP, CompressionMode.MESSAGE)
    found = identify(folder)
    assert found.kind == "mcap-split" and found.zstd_messages
    (split,) = found.files
    expected = list(SemanticKittiSequence(seq_dir))
    alone = open_scan_reader(split, McapOptions(gt_field="gt_label"))  # one split, given alone
    assert [s.index for s in alone if isinstance(s, Scan)] == [0, 1, 2, 3]
    rewrite_mcap(split, lambda k, data: data[: len(data) // 2] if k == 1 else data)
    reader = open_scan_reader(folder, McapOptions(gt_field="gt_label"))
    got = list(reader)
    assert [type(s).__name__ for s in got] == ["Scan", "SkippedScan", "Scan", "Scan"]
    for a, b in zip(expected, got):
        if isinstance(b, Scan):
            assert np.array_equal(a.points_sensor, b.points_sensor)
            assert np.array_equal(a.labels, b.labels)
    (line,) = [x for x in reader.report.lines() if "does not inflate" in x]
    assert line.startswith(f"{split.name}: message at log time ")
    assert line.endswith("1 message(s) lost (1 on /velodyne_points)")
    data = split.read_bytes()
    split.write_bytes(data[: int(len(data) * 0.8)])
    cut = open_scan_reader(folder, McapOptions(gt_field="gt_label"))
    scans = [s for s in cut if isinstance(s, Scan)]
    assert 1 <= len(scans) < 4 and scans[0].index == 0


@pytest.mark.parametrize("chunked", [True, False])
def test_a_frame_that_does_not_inflate_outside_any_crc_marks_the_scans_after_it(recording, chunked):
    """A per-message frame that does not inflate is one lost message on its record's channel.
    In a CRC-checked chunk that channel is vouched for; outside any chunk the damage may have
    changed it too, so the scans after it may be numbered otherwise than in the intact file:
    they are mapped, and marked."""
    seq_dir, messages, tmp = recording
    folder = rosbags_bag(
        tmp / f"each_zstd_{chunked}", messages, StoragePlugin.MCAP, CompressionMode.MESSAGE
    )
    (split,) = identify(folder).files
    rewrite_mcap(split, lambda k, data: data[: len(data) // 2] if k == 1 else data, chunked)
    reader = open_scan_reader(folder, McapOptions(gt_field="gt_label"))
    got = list(reader)
    assert [type(s).__name__ for s in got] == ["Scan", "SkippedScan", "Scan", "Scan"]
    (line,) = [line for line in reader.report.lines() if "does not inflate" in line]
    if chunked:
        assert reader.report.suspect == {}
        assert "may have changed its channel" not in line
    else:
        assert sorted(reader.report.suspect) == [2, 3]
        assert "counted from its damaged bytes" in reader.report.suspect[2]
        assert line.endswith(
            "no CRC covers its record, so the damage may have changed its channel: "
            "1 message(s) lost (1 on /velodyne_points)"
        )


def test_a_db3_with_damaged_pages_is_read_around_them(recording, tmp_path):
    """Every page of a .db3 zeroed in turn (where the damage lands depends on sqlite's page
    layout): rosbags cannot open most of them, or stops part-way; read row by row, each row
    on a damaged page is a lost message and the others are mapped. What cannot be read at all
    (the topics table, the table's root) is refused in one line."""
    seq_dir, messages, tmp = recording
    bag = rosbags_bag(tmp_path / "db3", messages, StoragePlugin.SQLITE3)
    (db,) = bag.glob("*.db3")
    data, page = db.read_bytes(), 4096
    stamps = [a.stamp_s for a in SemanticKittiSequence(seq_dir)]
    row_by_row = with_losses = 0
    for at in range(page, len(data), page):
        db.write_bytes(data[:at] + bytes(page) + data[at + page :])
        try:
            reader = open_scan_reader(bag, McapOptions(gt_field="gt_label"))
            got = list(reader)
        except DatasetError as e:
            assert "\n" not in str(e) and str(bag) in str(e)
            continue
        scans = [s for s in got if isinstance(s, Scan)]
        # (a zeroed page inside a message's bytes goes unnoticed: sqlite has no CRC)
        assert [s.index for s in scans] == list(range(len(scans)))
        assert all(any(s.stamp_s == pytest.approx(t, abs=1e-9) for t in stamps) for s in scans)
        row_by_row += any("read row by row" in n for n in reader.report.notes)
        with_losses += bool(scans) and bool(reader.report.losses)
    assert row_by_row >= 3 and with_losses >= 3


@pytest.mark.parametrize("form", ["split mcap", "per-message zstd", "db3 folder"])
@pytest.mark.parametrize("metadata", ["missing", "not UTF-8"])
def test_a_bag_without_usable_metadata_is_read_from_its_files(recording, form, metadata):
    """A recording that did not close has no metadata.yaml (rosbag2 writes it at the end): its
    MCAP files are read in split order (messages compressed one by one are recognised by their
    bytes), or its one .db3; the report says so."""
    seq_dir, messages, tmp = recording
    folder = make_input(form, messages, tmp / f"no_meta_{metadata}")
    if metadata == "missing":
        (folder / "metadata.yaml").unlink()
    else:
        (folder / "metadata.yaml").write_bytes(b"rosbag2_bagfile_information:\n  \xe1\xff\n")
    reader = open_scan_reader(folder, McapOptions(gt_field="gt_label"))
    got = list(reader)
    expected = list(SemanticKittiSequence(seq_dir))
    assert len(got) == len(expected) == 4 and reader.report.losses == []
    for a, b in zip(expected, got):
        assert b.index == a.index and np.array_equal(a.points_sensor, b.points_sensor)
        assert np.array_equal(a.labels, b.labels)
    why = "no metadata.yaml" if metadata == "missing" else "metadata.yaml is damaged"
    (note,) = [n for n in reader.report.notes if n.startswith(why)]
    files = sorted(p.name for p in folder.iterdir() if p.suffix in (".mcap", ".db3"))
    assert all(name in note for name in files)
    assert "ros2 bag reindex" in note


def test_a_db3_folder_whose_metadata_rosbags_rejects_is_read_from_its_db3(recording):
    seq_dir, messages, tmp = recording
    folder = make_input("db3 folder", messages, tmp / "db3_no_version")
    meta = yaml.safe_load((folder / "metadata.yaml").read_text())
    del meta["rosbag2_bagfile_information"]["version"]  # parses, but rosbags needs it
    (folder / "metadata.yaml").write_text(yaml.safe_dump(meta))
    reader = open_scan_reader(folder, McapOptions(gt_field="gt_label"))
    got = [s.points_sensor for s in reader]
    assert len(got) == 4 and all(
        np.array_equal(a.points_sensor, b) for a, b in zip(SemanticKittiSequence(seq_dir), got)
    )
    assert any("messages were read row by row" in n for n in reader.report.notes)
    (db3,) = folder.glob("*.db3")
    db3.write_bytes(b"SQLite format 3\x00" + bytes(100))  # and with its one file unreadable
    assert "topics table is unreadable" in one_line_refusal(folder)


@pytest.mark.parametrize("compression", [None, "BZ2", "LZ4"])
def test_a_ros1_bag_without_its_index_is_read_record_by_record(recording, compression):
    """A ROS 1 recording that did not close has no index (`rosbags` cannot open it): its
    chunks are read in file order, uncompressed, bz2 or lz4; a cut one gives the scans of the
    chunks it holds whole, and says where it ends."""
    seq_dir, messages, tmp = recording
    fmt = None if compression is None else getattr(Ros1Writer.CompressionFormat, compression)
    bag = ros1_bag(tmp / f"chunks_{compression}.bag", messages, fmt, chunk_bytes=4096)
    data = bag.read_bytes()
    at = data.index(b"index_pos=") + len(b"index_pos=")
    open_bag = tmp / f"open_{compression}.bag.active"
    open_bag.write_bytes(data[:at] + bytes(8) + data[at + 8 :])  # as `rosbag record` starts it
    expected = list(SemanticKittiSequence(seq_dir))
    reader = open_scan_reader(open_bag, McapOptions(gt_field="gt_label"))
    got = list(reader)
    assert len(got) == 4 and reader.report.losses == []
    for a, b in zip(expected, got):
        assert b.index == a.index and b.stamp_s == pytest.approx(a.stamp_s, abs=1e-9)
        assert np.array_equal(a.points_sensor, b.points_sensor)
        assert np.array_equal(a.labels, b.labels) and np.array_equal(a.gt_labels, b.gt_labels)
        assert np.abs(a.T_world_sensor - b.T_world_sensor).max() < 1e-6
    assert any("records were read in file order" in n for n in reader.report.notes)
    cut = tmp / f"cut_{compression}.bag"
    cut.write_bytes(data[: int(len(data) * 0.75)])
    reader = open_scan_reader(cut, McapOptions(gt_field="gt_label"))
    scans = [s for s in reader if isinstance(s, Scan)]
    assert 1 <= len(scans) < 4 and [s.index for s in scans] == list(range(len(scans)))
    assert all(np.array_equal(expected[s.index].points_sensor, s.points_sensor) for s in scans)
    (loss,) = reader.report.losses
    assert loss.where.startswith("chunk at byte ") and "cut short" in loss.what


def test_a_ros1_bag_of_tf_before_tf2_is_read(recording):
    """Bags of older ROS 1 releases carry /tf and /tf_static as `tf/tfMessage`, not
    `tf2_msgs/TFMessage` (the same fields): read by `rosbags` and record by record (without
    the index), the scans and their poses are those of the tf2 bag."""
    seq_dir, messages, tmp = recording
    bag = write_ros1_bag(tmp / "old_tf.bag", messages, old_tf=True)
    assert b"tf/tfMessage" in bag.read_bytes()
    data = bag.read_bytes()
    at = data.index(b"index_pos=") + len(b"index_pos=")
    open_bag = tmp / "old_tf_open.bag"
    open_bag.write_bytes(data[:at] + bytes(8) + data[at + 8 :])
    expected = list(SemanticKittiSequence(seq_dir))
    for path in (bag, open_bag):
        got = list(open_scan_reader(path, McapOptions(gt_field="gt_label")))
        assert [s.index for s in got] == [0, 1, 2, 3]
        for a, b in zip(expected, got):
            assert np.array_equal(a.points_sensor, b.points_sensor)
            assert np.abs(a.T_world_sensor - b.T_world_sensor).max() < 1e-6


def test_a_damaged_chunk_of_a_ros1_bag_costs_that_chunk_alone(recording):
    """rosbags stops at the first chunk that does not inflate; read record by record, the
    chunks after it are mapped too, and the bag's index says what the lost one held (the
    scans after it keep their numbers)."""
    from tisem.io.ros1_linear import MAGIC, OP_CHUNK, _records

    seq_dir, messages, tmp = recording
    fmt = Ros1Writer.CompressionFormat.BZ2
    bag = ros1_bag(tmp / "damaged_chunk.bag", messages, fmt, chunk_bytes=4096)
    data = bytearray(bag.read_bytes())
    chunks = [
        (at, len(d)) for op, _, d, at in _records(data, len(MAGIC), len(data)) if op == OP_CHUNK
    ]
    at, n = chunks[2]  # the third cloud's
    middle = at + 200 + n // 2
    data[middle : middle + 64] = bytes(x ^ 0xFF for x in data[middle : middle + 64])
    bag.write_bytes(bytes(data))
    reader = open_scan_reader(bag, McapOptions(gt_field="gt_label"))
    scans = [s for s in reader if isinstance(s, Scan)]
    expected = list(SemanticKittiSequence(seq_dir))
    assert [s.index for s in scans] == [0, 1, 3]
    for s, k in zip(scans, (0, 1, 3)):
        assert np.array_equal(s.points_sensor, expected[k].points_sensor)
    (loss,) = reader.report.losses
    assert loss.where == f"chunk at byte {at}"
    assert loss.line().endswith(": 2 message(s) lost (1 on /tf, 1 on /velodyne_points)")


def test_without_rosbags_a_bag_that_needs_it_is_refused_in_one_line(recording, monkeypatch):
    """Not read around either: the refusal says what to install, nothing else."""
    import importlib.util

    _, messages, tmp = recording
    bag = ros1_bag(tmp / "no_rosbags.bag", messages)
    cut = tmp / "no_rosbags_cut.bag"
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda n, *a: None if n == "rosbags" else find_spec(n, *a)
    )
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # (an import of it fails)
    for path in (bag, cut):
        text = one_line_refusal(path)
        assert text.endswith(
            "needs the `rosbags` package: pip install 'tisem[mcap]' (or pip install rosbags)"
        )


def test_split_db3_files_without_metadata_are_read_in_split_order(recording):
    """A Humble recording (sqlite3 storage) split by size and killed: its .db3 files and no
    metadata.yaml; rosbags cannot read them without it, so they are read row by row, in split
    order (NAME_2 before NAME_10)."""
    seq_dir, messages, tmp = recording
    folder = tmp / "killed_split_db3"
    folder.mkdir()
    cuts = [0, 4, 7, len(messages)]  # three splits: _0, _2, _10
    for name, a, b in zip(("killed_0", "killed_2", "killed_10"), cuts, cuts[1:]):
        part = rosbags_bag(tmp / f"part_{name}", messages[a:b], StoragePlugin.SQLITE3)
        shutil.move(next(part.glob("*.db3")), folder / f"{name}.db3")
    reader = open_scan_reader(folder, McapOptions(gt_field="gt_label"))
    got = list(reader)
    expected = list(SemanticKittiSequence(seq_dir))
    assert len(got) == 4 and reader.report.losses == []
    for a, b in zip(expected, got):
        assert b.index == a.index and np.array_equal(a.points_sensor, b.points_sensor)
    (note,) = [n for n in reader.report.notes if n.startswith("no metadata.yaml")]
    assert "killed_0.db3, killed_2.db3, killed_10.db3" in note and "row by row" in note


def one_line_refusal(path: Path) -> str:
    with pytest.raises(DatasetError) as info:
        open_scan_reader(path)
    text = str(info.value)
    assert "\n" not in text and str(path) in text
    return text


def test_what_cannot_be_read_is_refused_in_one_line_with_the_conversion(recording):
    _, messages, tmp = recording
    junk = tmp / "drive.bin"
    junk.write_bytes(b"\x00garbage" * 10)
    assert "ros2 bag convert" in one_line_refusal(junk)
    bag = ros1_bag(tmp / "whole.bag", messages)
    cut = tmp / "cut.bag"
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size // 10])  # before the first cloud
    text = one_line_refusal(cut)
    assert "ROS 1 bag" in text and "rosbag reindex" in text and "no point-cloud" in text
    old = tmp / "old.bag"
    old.write_bytes(b"#ROSBAG V1.2\n" + b"\x00" * 64)
    assert "rosbag fix" in one_line_refusal(old)
    loose = tmp / "loose"
    loose.mkdir()
    (loose / "x_0.mcap").write_bytes(b"")
    assert "ros2 bag reindex" in one_line_refusal(loose)
    compressed = rosbags_bag(
        tmp / "zstd_each", messages, StoragePlugin.MCAP, CompressionMode.MESSAGE
    )
    per_file = rosbags_bag(tmp / "zstd_file", messages, StoragePlugin.MCAP, CompressionMode.FILE)
    assert "give the bag folder" in one_line_refusal(next(per_file.glob("*.zstd")))
    meta = yaml.safe_load((compressed / "metadata.yaml").read_text())
    meta["rosbag2_bagfile_information"]["storage_identifier"] = "cassette"
    (compressed / "metadata.yaml").write_text(yaml.safe_dump(meta))
    assert "'cassette'" in one_line_refusal(compressed)
    empty = tmp / "metadata_only"
    empty.mkdir()
    (empty / "metadata.yaml").write_bytes(b"rosbag2_bagfile_information:\n  \xe1\xff\n")
    assert "metadata.yaml: not rosbag2 metadata" in one_line_refusal(empty)


@pytest.mark.slow
def test_bags_give_the_predictions_of_the_folder(recording, tmp_path):
    """End to end through the apps: a split MCAP bag and a .db3 bag are mapped into the same
    predictions as the SemanticKITTI folder; the map's bag holds the map of map.npz; a bad
    input is one line, no traceback."""
    seq_dir, messages, tmp = recording
    split = split_bag(tmp_path / "split", messages, tmp_path / "work")
    db3 = rosbags_bag(tmp_path / "db3", messages, StoragePlugin.SQLITE3)
    common = ["--arch", "cpu", "--threads", "1", "--no-progress"]
    runs = {
        "kitti": [REPO / "apps" / "map_kitti.py", "--data", seq_dir],
        "split": [REPO / "apps" / "map_mcap.py", split, "--gt-field", "gt_label", "--save-scans"],
        "db3": [REPO / "apps" / "map_mcap.py", db3, "--gt-field", "gt_label"],
    }
    for name, args in runs.items():
        done = subprocess.run(
            [sys.executable, *map(str, args), *common, "--out", str(tmp_path / f"out_{name}")],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr[-3000:]
    for k in range(4):
        want = np.fromfile(
            tmp_path / "out_kitti/sequences/00/predictions" / f"{k:06d}.label", "<u4"
        )
        for name in ("split", "db3"):
            got = np.fromfile(
                tmp_path / f"out_{name}/sequences/00/predictions/{k:06d}.label", "<u4"
            )
            assert np.mean(want == got) >= 0.999, (name, k)
    snap = load_map_file(tmp_path / "out_split" / "map.npz")[0]
    clouds = decoded_clouds(tmp_path / "out_split" / "map_ros2")
    (cloud,) = clouds["/semantic_map"]
    assert np.array_equal(cloud["label"], snap.labels()) and len(clouds["/semantic_scans"]) == 4
    assert np.array_equal(
        np.stack([cloud["x"], cloud["y"], cloud["z"]], 1), snap.centers().astype(np.float32)
    )
    assert np.array_equal(unpack_rgb(cloud["rgb"]), CLASS_COLORS_RGB[snap.labels()])
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"not a bag at all")
    done = subprocess.run(
        [
            sys.executable,
            str(REPO / "apps" / "map_mcap.py"),
            str(junk),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2 and "not a recording tisem reads" in done.stderr
    assert "Traceback" not in done.stderr
