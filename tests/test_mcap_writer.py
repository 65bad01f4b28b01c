"""map.mcap read back with the plain `mcap` library: the same voxels, labels, colours and
probabilities as the snapshot; scans round-trip through our own reader."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from tisem.io.mcap_reader import McapOptions, McapScanReader
from tisem.io.mcap_writer import MAP_TOPIC, SCANS_TOPIC, Ros2McapWriter, ros2_msgdef, write_map_mcap
from tisem.io.pointcloud2 import foxglove_cloud_to_array
from tisem.labels import CLASS_COLORS_RGB, class_table
from tisem.scan import Scan
from tisem.snapshot import MapSnapshot


def snapshot(n: int = 500, seed: int = 0, resolution_m: float = 0.2) -> MapSnapshot:
    rng = np.random.default_rng(seed)
    keys = np.unique(rng.integers(-400, 400, (n, 3)), axis=0)  # negative keys included
    counts = rng.random((len(keys), 20)).astype(np.float32) ** 4
    counts[:5] = 0  # voxels without evidence
    order = MapSnapshot.sort_order(keys)
    return MapSnapshot(
        keys=keys[order],
        counts=counts,
        t_last=rng.random(len(keys)) + 5,
        ell_m=np.full(len(keys), 0.4, np.float32),
        resolution_m=resolution_m,
    )


def read_back(path):
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        messages = [(ch.topic, m.log_time, msg) for _, ch, m, msg in reader.iter_decoded_messages()]
        metadata = {r.name: r.metadata for r in reader.iter_metadata()}
    return messages, metadata


@pytest.mark.parametrize("resolution_m", [0.2, 0.15])
def test_map_reads_back_as_the_same_voxels_and_labels(tmp_path, resolution_m):
    snap = snapshot(resolution_m=resolution_m)
    info = write_map_mcap(tmp_path / "map.mcap", snap)
    assert info["voxels"] == len(snap) and info["scans"] == 0
    messages, metadata = read_back(tmp_path / "map.mcap")
    ((topic, log_time, msg),) = messages
    assert topic == MAP_TOPIC and msg.frame_id == "map"
    assert log_time == int(round(snap.t_last.max() * 1e9))
    pts = foxglove_cloud_to_array(msg)
    assert pts.dtype.names == (
        "x",
        "y",
        "z",
        "red",
        "green",
        "blue",
        "alpha",
        "label",
        "probability",
    )
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], 1).astype(np.float64)
    assert np.array_equal(np.floor(xyz / resolution_m).astype(np.int64), snap.keys)
    assert np.abs(xyz - snap.centers()).max() < 1e-4
    assert np.array_equal(pts["label"], snap.labels())
    assert np.array_equal(pts["probability"], snap.confidence().astype(np.float32))
    rgba = np.stack([pts[c] for c in ("red", "green", "blue", "alpha")], 1)
    assert np.array_equal(rgba[:, :3], CLASS_COLORS_RGB[snap.labels()])
    assert np.all(rgba[:, 3] == 255)
    table = {int(k): json.loads(v) for k, v in metadata["semantic_classes"].items()}
    assert [table[i] for i in range(20)] == class_table()
    assert float(metadata["tisem_map"]["resolution_m"]) == resolution_m


def test_scans_are_written_with_their_pose_and_read_back(tmp_path):
    rng = np.random.default_rng(3)
    scans = []
    for k in range(3):
        T = np.eye(4)
        T[:3, 3] = [k, 2.0 * k, 0.5]
        scans.append(
            Scan(
                points_sensor=rng.normal(size=(50, 3)) * 5,
                T_world_sensor=T,
                stamp_s=10.0 + 0.1 * k,
                labels=rng.integers(1, 20, 50),
                gt_labels=rng.integers(0, 20, 50),
                index=k,
            )
        )
    mapped = [rng.integers(0, 20, 50) for _ in scans]
    info = write_map_mcap(
        tmp_path / "map.mcap",
        snapshot(50),
        frame_id="odom",
        scans=((s, m) for s, m in zip(scans, mapped)),
    )
    assert info["scans"] == 3
    messages, _ = read_back(tmp_path / "map.mcap")
    assert [t for t, *_ in messages] == [MAP_TOPIC] + [SCANS_TOPIC] * 3
    assert messages[0][1] == 10_000_000_000  # the map is there from the start
    back = list(
        McapScanReader(
            tmp_path / "map.mcap",
            McapOptions(
                topic=SCANS_TOPIC, map_frame="odom", label_space="train", gt_field="gt_label"
            ),
        )
    )
    for s, b, m in zip(scans, back, mapped):
        assert np.abs(b.T_world_sensor - s.T_world_sensor).max() < 1e-12
        assert np.array_equal(b.labels, m) and np.array_equal(b.gt_labels, s.gt_labels)
        assert np.allclose(b.points_world(), s.points_world(), atol=1e-5)
    input_labels = foxglove_cloud_to_array(messages[1][2])["input_label"]
    assert np.array_equal(input_labels, scans[0].labels)


def test_an_empty_map_and_a_mismatched_scan(tmp_path):
    empty = MapSnapshot(
        np.zeros((0, 3), np.int64),
        np.zeros((0, 20), np.float32),
        np.zeros(0),
        np.zeros(0, np.float32),
        0.2,
    )
    write_map_mcap(tmp_path / "empty.mcap", empty)
    ((_, _, msg),), _ = read_back(tmp_path / "empty.mcap")
    assert len(foxglove_cloud_to_array(msg)) == 0
    scan = Scan(np.zeros((4, 3)), np.eye(4), 0.0, labels=np.zeros(4))
    with pytest.raises(ValueError, match="3,.*mapped labels for 4 points"):
        write_map_mcap(tmp_path / "bad.mcap", empty, scans=[(scan, np.zeros(3))])


def test_ros2_schemas_use_the_rosbag2_spelling(tmp_path):
    text = ros2_msgdef("sensor_msgs/msg/PointCloud2")
    assert "MSG: std_msgs/Header\n" in text and "MSG: sensor_msgs/PointField\n" in text
    assert "=" * 80 + "\n" in text and "/msg/Header" not in text
    with Ros2McapWriter(tmp_path / "x.mcap", compression="lz4") as w:
        w.write_transforms([("map", "a", 0, np.eye(4))], 0)
    with open(tmp_path / "x.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        (schema,) = reader.get_summary().schemas.values()
        assert schema.name == "tf2_msgs/msg/TFMessage" and schema.encoding == "ros2msg"
    with pytest.raises(ValueError, match="compression"):
        Ros2McapWriter(tmp_path / "y.mcap", compression="gzip")
