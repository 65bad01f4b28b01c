"""A damaged ROS 1 bag, read record by record (tisem.io.ros1_linear), loses what the damage hit
and no more: the walk reads on after bytes that break its chain of record lengths, and takes a
connection whose own record was lost, or whose message definition is damaged, from the copy in
the bag's index section."""

from __future__ import annotations

import bz2
import struct

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the rosbags package (tisem[mcap]) is not installed")

import test_rosbag_read  # noqa: E402
from mcap.records import Channel, Schema  # noqa: E402
from rosbags.rosbag1 import Writer as Ros1Writer  # noqa: E402
from test_rosbag_read import ros1_bag  # noqa: E402

from tisem.io.bag_open import open_scan_reader  # noqa: E402
from tisem.io.bag_records import RosbagRecords  # noqa: E402
from tisem.io.mcap_reader import McapOptions, McapScanReader  # noqa: E402
from tisem.io.mcap_records import LostMessages, ReadReport  # noqa: E402
from tisem.io.ros1_linear import (  # noqa: E402
    MAGIC,
    OP_CHUNK,
    OP_CONNECTION,
    OP_MESSAGE,
    Ros1LinearRecords,
    _inflate,
    _records,
)
from tisem.io.semantickitti import SemanticKittiSequence  # noqa: E402
from tisem.scan import Scan  # noqa: E402

BZ2 = Ros1Writer.CompressionFormat.BZ2
recording = test_rosbag_read.recording  # (the fixture: a tiny sequence and its messages)


def chunks(data: bytes) -> list[tuple[int, int, list]]:
    """(byte, data bytes, [(op, topic) of its records]) of each chunk of a bag."""
    found = []
    for op, fields, body, at in _records(data, len(MAGIC), len(data)):
        if op == OP_CHUNK:
            inner, _ = _inflate(fields["compression"], body, struct.unpack("<I", fields["size"])[0])
            held = [(o, f.get("topic")) for o, f, _, _ in _records(inner, 0, len(inner))]
            found.append((at, len(body), held))
    return found


def read(path):
    reader = open_scan_reader(path, McapOptions(gt_field="gt_label"))
    return [s for s in reader if isinstance(s, Scan)], reader.report


def same_clouds(scans, expected, indices) -> bool:
    return len(scans) == len(indices) and all(
        np.array_equal(s.points_sensor, expected[k].points_sensor)
        and np.array_equal(s.labels, expected[k].labels)
        for s, k in zip(scans, indices)
    )


def test_bytes_inserted_between_records_cost_no_scan(recording):
    """Bytes inserted before a chunk shift every position the index holds (rosbags cannot use
    it) and break the chain of record lengths there: the walk reads on at the chunk."""
    seq_dir, messages, tmp = recording
    data = ros1_bag(tmp / "inserted.bag", messages, BZ2, chunk_bytes=4096).read_bytes()
    at = chunks(data)[2][0]
    junk = bytes(range(200, 237))
    bag = tmp / "inserted_damaged.bag"
    bag.write_bytes(data[:at] + junk + data[at:])
    scans, report = read(bag)
    assert same_clouds(scans, list(SemanticKittiSequence(seq_dir)), range(4))
    (loss,) = report.losses
    assert loss.where == f"record at byte {at}" and loss.uncounted
    assert loss.what.endswith(f"read on from byte {at + len(junk)}")


def test_an_overwritten_chunk_header_costs_that_chunk_alone(recording):
    """Zeros over a chunk's header (its lengths gone): that chunk's scan is lost, the walk
    finds the records after it, and the scans there are read."""
    seq_dir, messages, tmp = recording
    data = bytearray(ros1_bag(tmp / "zeroed.bag", messages, BZ2, chunk_bytes=4096).read_bytes())
    at, size, _ = chunks(bytes(data))[2]  # the third cloud's
    data[at : at + 40] = bytes(40)
    bag = tmp / "zeroed_damaged.bag"
    bag.write_bytes(bytes(data))
    scans, report = read(bag)
    assert same_clouds(scans, list(SemanticKittiSequence(seq_dir)), (0, 1, 3))
    (loss,) = report.losses
    assert loss.where == f"record at byte {at}" and "read on from byte" in loss.what
    resumed = int(loss.what.rsplit(" ", 1)[1])
    assert at + size < resumed < len(data)  # (after the chunk's data: nothing read twice)


def test_a_chunk_rosbags_passes_over_is_found_by_the_index_counts(recording):
    """Zeros over a chunk's size and data length (and its stream's start) leave a chunk that
    rosbags reads as empty, without a word, though the index lists its cloud: the bag is then
    read record by record, which says where the damage was and marks the scans after it."""
    seq_dir, messages, tmp = recording
    data = bytearray(ros1_bag(tmp / "emptied.bag", messages, BZ2, chunk_bytes=4096).read_bytes())
    at = chunks(bytes(data))[2][0]  # the third cloud's
    size_at = data.index(b"size=", at) + len(b"size=")
    data[size_at + 1 : size_at + 177] = bytes(176)  # "size" 122 bytes, its data none
    bag = tmp / "emptied_damaged.bag"
    bag.write_bytes(bytes(data))
    scans, report = read(bag)
    assert same_clouds(scans, list(SemanticKittiSequence(seq_dir)), (0, 1, 3))
    assert report.losses and report.losses[0].where == f"chunk at byte {at}"
    assert sorted(report.suspect) == [2]  # the fourth cloud, numbered 2
    # read through rosbags alone: the shortfall is a loss, and from the second pass on (the
    # scans' pass, after the survey's) every scan follows it, as where it was is unknown
    records, first = RosbagRecords(bag, "ROS 1 bag", "ros1"), ReadReport()
    assert isinstance(list(records.records(first))[-1], LostMessages)
    assert (
        "rosbags yielded fewer messages than the bag's index lists (1 on /tf, 1 on "
        "/velodyne_points)" in (first.lines()[0])
    )
    second = [r for r in records.records(ReadReport()) if not isinstance(r, (Schema, Channel))]
    assert isinstance(second[0], LostMessages) and second[0].count is None


def test_an_intact_bag_is_not_short_of_its_index_whatever_its_topic_names(tmp_path):
    """rosbags names a topic `/a//b/` `/a/b`: the index's counts are compared under its names,
    so an intact bag with such a topic reports nothing lost."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    text = store.types["std_msgs/msg/String"]
    bag = tmp_path / "odd.bag"
    with Ros1Writer(bag) as writer:
        conn = writer.add_connection("/a//b/", text.__msgtype__, typestore=store)
        for k in range(3):
            writer.write(conn, k * 1000, store.serialize_ros1(text(data="x"), text.__msgtype__))
    records, report = RosbagRecords(bag, "ROS 1 bag", "ros1"), ReadReport()
    assert sum(isinstance(r, LostMessages) for r in records.records(report)) == 0
    assert report.messages == {"/a/b": 3} and report.lines() == [] and records.short is None


def test_a_lost_connection_record_is_taken_from_the_index(recording):
    """A chunk per message: the first cloud's chunk also holds the clouds' connection record.
    Damaged, it costs that cloud; the other clouds name the connection from its copy in the
    index section (without it, no cloud could be decoded)."""
    seq_dir, messages, tmp = recording
    data = bytearray(ros1_bag(tmp / "conn.bag", messages, BZ2, chunk_bytes=1).read_bytes())
    (at, size, _) = next(
        c for c in chunks(bytes(data)) if (OP_CONNECTION, b"/velodyne_points") in c[2]
    )
    middle = at + 100 + size // 2
    data[middle : middle + 64] = bytes(x ^ 0xFF for x in data[middle : middle + 64])
    bag = tmp / "conn_damaged.bag"
    bag.write_bytes(bytes(data))
    scans, report = read(bag)
    assert same_clouds(scans, list(SemanticKittiSequence(seq_dir)), (1, 2, 3))
    assert [s.index for s in scans] == [1, 2, 3]  # the index counts the chunk: numbers kept
    (loss,) = report.losses
    assert loss.where == f"chunk at byte {at}" and loss.line().endswith(
        ": 1 message(s) lost (1 on /velodyne_points)"
    )
    assert report.suspect == {}


def test_a_damaged_message_definition_is_taken_from_the_index(recording):
    """A bag whose index rosbags cannot use (its position zeroed, as in a recording that did
    not close) and whose clouds' connection record, in an uncompressed chunk, has a damaged
    message definition: the definition of the copy in the index section decodes them."""
    seq_dir, messages, tmp = recording
    data = bytearray(ros1_bag(tmp / "definition.bag", messages, chunk_bytes=4096).read_bytes())
    at = data.index(b"index_pos=") + len(b"index_pos=")
    data[at : at + 8] = bytes(8)
    text = data.index(b"uint32 height")  # (the first copy: in the clouds' first chunk)
    data[text : text + 40] = bytes(40)
    bag = tmp / "definition_damaged.bag"
    bag.write_bytes(bytes(data))
    scans, report = read(bag)
    assert same_clouds(scans, list(SemanticKittiSequence(seq_dir)), range(4))
    assert report.losses == []


def test_bytes_inserted_in_an_uncompressed_cloud_lose_that_cloud(recording):
    """ROS 1 bags hold no checksums: bytes inserted inside a cloud's data of an uncompressed
    chunk go unnoticed in the cloud itself, but push the chunk's end out of line with the
    record after it. The cloud, which may hold them, is lost with the chunk's report."""
    seq_dir, messages, tmp = recording
    data = ros1_bag(tmp / "plain.bag", messages, chunk_bytes=4096).read_bytes()
    at, size, held = chunks(data)[2]
    assert held[-1] == (2, None)  # (the chunk ends with its cloud)
    middle = at + size // 2
    bag = tmp / "plain_inserted.bag"
    bag.write_bytes(data[:middle] + bytes(range(5)) + data[middle:])
    scans, report = read(bag)
    expected = list(SemanticKittiSequence(seq_dir))
    assert same_clouds(scans, expected, (0, 1, 3))
    assert report.losses[0].where == f"chunk at byte {at}"
    assert "out of line" in report.losses[0].what
    assert scans[-1].index in report.suspect  # (after a loss of unknown size)


def test_a_closed_bag_cut_between_two_records_says_so(recording):
    """A cut that falls between two records leaves every record whole; the bag header still
    says where the index was written, past the end: the cut is reported."""
    seq_dir, messages, tmp = recording
    data = ros1_bag(tmp / "whole_records.bag", messages, BZ2, chunk_bytes=4096).read_bytes()
    at = chunks(data)[2][0]
    bag = tmp / "cut_between.bag"
    bag.write_bytes(data[:at])
    scans, report = read(bag)
    assert same_clouds(scans, list(SemanticKittiSequence(seq_dir)), (0, 1))
    (loss,) = report.losses
    assert loss.where == f"the file's end (byte {at})" and "cut short" in loss.what


def lz4_block_sizes(frame: bytes) -> list[int]:
    """Where each block-size field of an lz4 frame (python-lz4's: no checksums) starts."""
    flags = frame[4]
    at = 4 + 2 + (8 if flags & 0x08 else 0) + 1  # magic, FLG and BD, content size, HC
    places = []
    while True:
        (size,) = struct.unpack_from("<I", frame, at)
        if size == 0:  # the end mark
            return places
        places.append(at)
        at += 4 + (size & 0x7FFFFFFF)


def test_a_damaged_first_chunk_s_sensor_mount_is_read_and_every_scan_marked(tmp_path):
    """The first chunk holds /tf_static, the sensor's mount, and nothing else does: its lz4
    stream broken in its third block (of 64 kB), the mount is read from the records the
    blocks before give; the clouds of the other chunks are mapped, and all marked."""
    from test_mcap_kitti import write_tiny_sequence
    from test_rosbag_read import recorded_messages

    seq = write_tiny_sequence(tmp_path / "seq", n_scans=4, n_points=8_000)
    messages = recorded_messages(seq, tmp_path)
    lz4 = Ros1Writer.CompressionFormat.LZ4
    data = bytearray(
        ros1_bag(tmp_path / "big.bag", messages, lz4, chunk_bytes=100_000).read_bytes()
    )
    at, size, held = chunks(bytes(data))[0]
    assert held == [  # (a connection record gives a topic, a message its connection's)
        (OP_CONNECTION, b"/tf_static"),
        (OP_MESSAGE, None),
        (OP_CONNECTION, b"/tf"),
        (OP_MESSAGE, None),
        (OP_CONNECTION, b"/velodyne_points"),
        (OP_MESSAGE, None),
    ]
    body = at + bytes(data[at:]).index(b"\x04\x22\x4d\x18", 0)  # the chunk's lz4 frame
    third = body + lz4_block_sizes(bytes(data[body : body + size]))[2]
    data[third : third + 4] = struct.pack("<I", 0x7FFFFFF0)  # a block no frame has
    bag = tmp_path / "damaged.bag"
    bag.write_bytes(bytes(data))
    scans, report = read(bag)
    assert same_clouds(scans, list(SemanticKittiSequence(seq)), [1, 2, 3])
    assert [s.index for s in scans] == [1, 2, 3]  # (the index counts the chunk's messages)
    assert sorted(report.suspect) == [1, 2, 3]
    assert set(report.suspect.values()) == {
        "its pose uses a static transform read from a damaged chunk, whose bytes nothing "
        f"vouches for (base_link -> velodyne from the chunk at byte {at}); --static-tf gives "
        "it instead"
    }
    assert report.losses[0].where == f"chunk at byte {at}"


def test_a_bz2_stream_damaged_in_a_block_gives_the_blocks_before_it():
    """bz2 checks each block as it ends: the blocks before the damaged one are what the
    stream held, byte for byte, and nothing of the damaged one is given."""
    from tisem.io.ros1_linear import _inflated_before_damage

    data = np.random.default_rng(0).bytes(350_000)
    stream = bytearray(bz2.compress(data, compresslevel=1))  # (blocks of 100 kB)
    stream[-2_000] ^= 0x10  # in the last block
    prefix = _inflated_before_damage(b"bz2", stream, len(data))
    assert len(prefix) >= 290_000 and data.startswith(prefix) and len(prefix) < len(data)
    assert _inflated_before_damage(b"bz2", stream[:10], len(data)) == b""
    assert _inflated_before_damage(b"none", data, 100) == data[:100]


@pytest.mark.parametrize("op", [3, 4, 6])
@pytest.mark.parametrize("header", ["a chunk's", "damaged too"])
def test_a_chunk_whose_op_field_is_damaged_is_not_passed_over(recording, op, header):
    """A flipped bit turns a chunk's op into a bag header's, an index data record's or a chunk
    info record's, which a walk passes over, and its clouds with it. A header that is still a
    chunk's (compression, size) is read as the chunk it is; one damaged beyond that is a
    chunk lost, counted from the bag's index: either way the scans keep their numbers."""
    seq_dir, messages, tmp = recording
    name = f"op{op}_{header.split()[0]}"
    data = bytearray(ros1_bag(tmp / f"{name}.bag", messages, BZ2, chunk_bytes=4096).read_bytes())
    at, _, _ = chunks(bytes(data))[2]  # the third cloud's
    op_at = bytes(data).index(b"op=\x05", at) + 3
    data[op_at] = op
    if header == "damaged too":
        name_at = bytes(data).index(b"compression=", at)
        data[name_at : name_at + 11] = b"compressiom"
    bag = tmp / f"{name}_damaged.bag"
    bag.write_bytes(bytes(data))
    scans, report = read(bag)
    expected = list(SemanticKittiSequence(seq_dir))
    if header == "a chunk's":
        assert same_clouds(scans, expected, range(4))
        assert report.losses[0].where == f"chunk at byte {at}"
        assert "its op field is damaged" in report.losses[0].what
        return
    assert [s.index for s in scans] == [0, 1, 3]
    assert same_clouds(scans, expected, (0, 1, 3))
    (loss,) = [x for x in report.losses if x.where == f"chunk at byte {at}"]
    assert loss.messages == 2 and "the bag's index lists a chunk here" in loss.what


def test_a_chunk_damaged_after_some_of_it_was_read_is_not_counted_whole(tmp_path):
    """A damaged connection record in the middle of a chunk (a topic first heard there)
    stops the chunk after the messages before it were read: the index's count of the whole
    chunk would count those twice, so the loss is of an unknown number, and the scans after
    it are marked, not renumbered unmarked."""
    from rosbags.typesys import Stores, get_typestore
    from test_mcap_kitti import write_tiny_sequence
    from test_rosbag_read import recorded_messages

    humble = get_typestore(Stores.ROS2_HUMBLE)
    text = humble.types["std_msgs/msg/String"]
    seq = write_tiny_sequence(tmp_path / "seq", n_scans=9, n_points=500)
    messages = recorded_messages(seq, tmp_path)
    clouds = [m for m in messages if m[0] == "/velodyne_points"]
    late = humble.serialize_cdr(text(data="hi"), "std_msgs/msg/String")
    messages = sorted(
        [*messages, ("/late", "std_msgs/msg/String", clouds[1][2] + 1, late)], key=lambda m: m[2]
    )
    data = bytearray(ros1_bag(tmp_path / "a.bag", messages, None, chunk_bytes=40_000).read_bytes())
    first = chunks(bytes(data))[0][0]
    k = bytes(data).index(b"topic=/late", first)
    field = bytes(data).index(b"message_definition=", k) - 4  # (its 4-byte length)
    data[field + 3] ^= 0x40  # a field length far past the record
    bag = tmp_path / "b.bag"
    bag.write_bytes(bytes(data))
    # (rosbags reads this bag whole, by its index: the walk is what reads around damage)
    records = Ros1LinearRecords(bag)
    reader = McapScanReader(
        bag, McapOptions(gt_field="gt_label"), records=records, decoders=records.decoders
    )
    scans = [s for s in reader if isinstance(s, Scan)]
    expected = list(SemanticKittiSequence(seq))
    assert len(scans) == 8
    for scan in scans:  # every scan is the intact one of its number, or marked
        same = np.array_equal(scan.points_sensor, expected[scan.index].points_sensor)
        assert same or scan.index in reader.report.suspect
    assert sum(loss.uncounted for loss in reader.report.losses) == 1


def _connection_copy(topic: bytes, definition: bytes) -> tuple[dict, bytes]:
    """(record fields, data) of an index copy of connection 7's record."""
    own = {b"topic": topic, b"type": b"test_msgs/X", b"message_definition": definition}
    data = b"".join(struct.pack("<I", len(k) + 1 + len(v)) + k + b"=" + v for k, v in own.items())
    return {"topic": topic, "conn": struct.pack("<I", 7)}, data


@pytest.mark.parametrize(
    "copies, expected",
    [
        # the /tf_static copy, though another whole copy comes first
        ([(b"/tf", b"int32 x\n"), (b"/tf_static", b"int32 y\n")], b"int32 y\n"),
        # the /tf_static copy's definition is damaged: not the other copy, which is /tf's
        ([(b"/tf_static", b"int32 ( y\n"), (b"/tf", b"int32 x\n")], None),
        ([(b"/tf", b"int32 x\n")], None),
    ],
)
def test_a_static_copy_is_the_copy_whose_topic_is_tf_static(copies, expected):
    """A /tf_static message whose chunk's own connection record was lost is read on an index
    copy of that record: the copy that names /tf_static, never another copy of the connection
    (the index can hold copies that disagree, where damage changed one)."""
    from tisem.io.ros1_linear import _Connections

    held = {7: [_connection_copy(topic, definition) for topic, definition in copies]}
    got = _Connections(lambda: held).static_copy(7)
    if expected is None:
        assert got is None
    else:
        assert got == ("/tf_static", "test_msgs/msg/X", expected)
