"""tisem.io.bag_open (map_mcap.py's input): what `ros2 bag record` and the `rosbags` library
write — a rosbag2 folder split in two MCAP files with QoS, sqlite3 (`.db3`) bags, per-message
and per-file compression, a ROS 1 bag — gives the scans of the SemanticKITTI folder they were
made from (end to end: the same predictions), and what cannot be read is refused in one line
that says how to convert it."""

from __future__ import annotations

import dataclasses
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
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402
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


def ros1_bag(path: Path, messages) -> Path:
    """The same messages as a ROS 1 bag (ROS 1 headers carry a `seq`; noetic has no tf2)."""
    noetic = get_typestore(Stores.ROS1_NOETIC)
    noetic.register(
        get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
    )

    def to_ros1(obj):
        if dataclasses.is_dataclass(obj):
            cls = noetic.types[obj.__msgtype__]
            return cls(
                **{
                    f.name: to_ros1(getattr(obj, f.name)) if hasattr(obj, f.name) else 0
                    for f in dataclasses.fields(cls)
                }
            )
        return [to_ros1(x) for x in obj] if isinstance(obj, list) else obj

    with Ros1Writer(path) as writer:
        connections = {}
        for topic, msgtype, t, data in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=noetic)
            msg = to_ros1(HUMBLE.deserialize_cdr(data, msgtype))
            writer.write(connections[topic], t, noetic.serialize_ros1(msg, msgtype))
    return path


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
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    text = one_line_refusal(cut)
    assert "ROS 1 bag" in text and "rosbag reindex" in text
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
    assert "give the folder" in one_line_refusal(next(compressed.glob("*.mcap")))
    per_file = rosbags_bag(tmp / "zstd_file", messages, StoragePlugin.MCAP, CompressionMode.FILE)
    assert "give the bag folder" in one_line_refusal(next(per_file.glob("*.zstd")))
    meta = yaml.safe_load((compressed / "metadata.yaml").read_text())
    meta["rosbag2_bagfile_information"]["storage_identifier"] = "cassette"
    (compressed / "metadata.yaml").write_text(yaml.safe_dump(meta))
    assert "'cassette'" in one_line_refusal(compressed)


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
