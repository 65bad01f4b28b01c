"""The map and the labelled scans as `sensor_msgs/msg/PointCloud2` (tisem.io.rosbag_map): what
`rosbags` decodes from the bag — fields read by their declared offsets and datatypes, not by
tisem's decoder — is the map of map.npz (voxel centres, labels, colours as RViz's packed
`rgb`, probabilities) and the scans in the map frame; /semantic_map is offered
transient_local."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the rosbags package (tisem[mcap]) is not installed")

from rosbags.interfaces import QosDurability  # noqa: E402
from rosbags.rosbag2 import Reader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from tisem.config import MapperConfig, to_dict  # noqa: E402
from tisem.io.mapfile import load_map_file, save_map  # noqa: E402
from tisem.io.pointcloud2 import pack_rgb, unpack_rgb  # noqa: E402
from tisem.io.rosbag_map import write_map_bag  # noqa: E402
from tisem.labels import CLASS_COLORS_RGB  # noqa: E402
from tisem.scan import Scan  # noqa: E402
from tisem.snapshot import MapSnapshot  # noqa: E402

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
# sensor_msgs/PointField datatypes, from the message definition
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def decoded_clouds(bag: Path) -> dict[str, list[np.ndarray]]:
    """topic -> the clouds of a bag as structured arrays, decoded by rosbags and numpy only."""
    out: dict[str, list[np.ndarray]] = {}
    with Reader(bag) as reader:
        for conn, _, data in reader.messages():
            msg = HUMBLE.deserialize_cdr(data, conn.msgtype)
            order = ">" if msg.is_bigendian else "<"
            dtype = np.dtype(
                {
                    "names": [f.name for f in msg.fields],
                    "formats": [order + POINTFIELD_TYPES[f.datatype] for f in msg.fields],
                    "offsets": [f.offset for f in msg.fields],
                    "itemsize": msg.point_step,
                }
            )
            assert msg.row_step == msg.point_step * msg.width and msg.height == 1
            out.setdefault(conn.topic, []).append(np.frombuffer(msg.data.tobytes(), dtype))
    return out


def test_packed_rgb_is_the_uint32_rviz_reads():
    rgb = np.array([[255, 0, 0], [0, 128, 255], [1, 2, 3]], np.uint8)
    packed = pack_rgb(rgb)
    assert packed.dtype == np.float32
    assert packed.view("<u4").tolist() == [0xFF0000, 0x0080FF, 0x010203]
    assert np.array_equal(unpack_rgb(packed), rgb)


def synthetic_snapshot(n: int = 300, seed: int = 0) -> MapSnapshot:
    rng = np.random.default_rng(seed)
    keys = np.unique(rng.integers(-500, 500, (n, 3)), axis=0)
    counts = rng.random((len(keys), 20)).astype(np.float32) ** 4
    counts[::7] = 0.0  # voxels without evidence: label 0
    order = MapSnapshot.sort_order(keys)
    return MapSnapshot(
        keys=keys[order],
        counts=counts[order],
        t_last=rng.uniform(1.0, 9.0, len(keys)),
        ell_m=np.full(len(keys), 0.3, np.float32),
        resolution_m=0.2,
    )


def test_map_bag_decodes_into_the_map_of_map_npz(tmp_path):
    save_map(tmp_path / "map.npz", synthetic_snapshot(), to_dict(MapperConfig()))
    snap = load_map_file(tmp_path / "map.npz")[0]
    pose = np.eye(4)
    pose[:3, 3] = [10.0, -5.0, 1.5]
    pose[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    rng = np.random.default_rng(1)
    scan = Scan(
        points_sensor=rng.uniform(-5, 5, (50, 3)).astype(np.float32),
        T_world_sensor=pose,
        stamp_s=2.5,
        labels=rng.integers(0, 20, 50).astype(np.int32),
        gt_labels=rng.integers(0, 20, 50).astype(np.int32),
        index=0,
    )
    mapped = rng.integers(0, 20, 50)
    info = write_map_bag(tmp_path / "map_ros2", snap, "map", scans=[(scan, mapped)])
    assert info["voxels"] == len(snap) and info["scans"] == 1

    with Reader(tmp_path / "map_ros2") as reader:
        durability = {c.topic: c.ext.offered_qos_profiles[0].durability for c in reader.connections}
    assert durability == {
        "/semantic_map": QosDurability.TRANSIENT_LOCAL,
        "/semantic_scans": QosDurability.VOLATILE,
    }
    clouds = decoded_clouds(tmp_path / "map_ros2")
    (cloud,) = clouds["/semantic_map"]
    assert cloud.dtype.names == ("x", "y", "z", "rgb", "label", "probability")
    assert all(cloud.dtype.fields[n][1] % 4 == 0 for n in ("x", "y", "z", "rgb", "probability"))
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], 1)
    assert np.array_equal(xyz, snap.centers().astype(np.float32))
    labels = snap.labels()
    assert np.array_equal(cloud["label"], labels) and (labels == 0).any()
    assert np.array_equal(unpack_rgb(cloud["rgb"]), CLASS_COLORS_RGB[labels])
    assert np.array_equal(cloud["probability"], snap.confidence().astype(np.float32))

    (scan_cloud,) = clouds["/semantic_scans"]
    got = np.stack([scan_cloud["x"], scan_cloud["y"], scan_cloud["z"]], 1)
    assert np.abs(got - scan.points_world()).max() < 1e-5
    assert np.array_equal(scan_cloud["label"], mapped)
    assert np.array_equal(scan_cloud["input_label"], scan.labels)
    assert np.array_equal(scan_cloud["gt_label"], scan.gt_labels)
    assert np.array_equal(unpack_rgb(scan_cloud["rgb"]), CLASS_COLORS_RGB[mapped])


def test_recording_maps_are_written_in_one_pass_and_cleared_by_overwrite(tmp_path):
    """map.mcap (Foxglove) and map_ros2/ get the same map and the same scans from one pass
    over them; --overwrite's clearing removes both and nothing else."""
    from mcap.reader import make_reader

    from tisem.outputs import clear_previous_run, write_recording_maps

    snap = synthetic_snapshot(120)
    rng = np.random.default_rng(2)
    scans = (
        Scan(
            points_sensor=rng.uniform(-5, 5, (30, 3)).astype(np.float32),
            T_world_sensor=np.eye(4),
            stamp_s=1.0 + k,
            index=k,
            labels=rng.integers(0, 20, 30).astype(np.int32),
        )
        for k in range(3)
    )
    passed = []

    def once():
        for scan in scans:  # a generator: it can be read only once
            passed.append(scan.index)
            yield scan, scan.labels

    info = write_recording_maps(tmp_path, snap, "map", once())
    assert passed == [0, 1, 2] and info["scans"] == 3 and info["voxels"] == len(snap)
    clouds = decoded_clouds(info["bag"])
    assert len(clouds["/semantic_scans"]) == 3 and len(clouds["/semantic_map"][0]) == len(snap)
    with open(info["mcap"], "rb") as f:
        topics = [ch.topic for _, ch, _ in make_reader(f).iter_messages()]
    assert topics.count("/semantic_map") == 1 and topics.count("/semantic_scans") == 3
    (tmp_path / "notes.txt").write_text("mine")
    assert clear_previous_run(tmp_path) == 3  # map.mcap, metadata.yaml, the bag's mcap
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_with_free_space_the_recordings_hold_the_static_map_and_the_trails_apart(tmp_path):
    """The voxels seen through leave /semantic_map (as they leave map.ply) and go to
    /semantic_map_dynamic, in map.mcap and in map_ros2/ alike, offered transient_local."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from tisem.io.pointcloud2 import foxglove_cloud_to_array
    from tisem.outputs import write_recording_maps

    snap = synthetic_snapshot(200)
    rng = np.random.default_rng(3)
    snap.occupancy = rng.uniform(-4, 4, len(snap)).astype(np.float32)
    snap.empty_evidence = 2.0
    empty = snap.empty()
    assert 0 < empty.sum() < len(snap)
    info = write_recording_maps(tmp_path, snap, "map")
    assert info["voxels"] == (~empty).sum() and info["dynamic_voxels"] == empty.sum()
    layers = {"/semantic_map": snap.static_map(), "/semantic_map_dynamic": snap.dynamic_layer()}
    clouds = decoded_clouds(info["bag"])
    with open(info["mcap"], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        foxglove = {ch.topic: msg for _, ch, _, msg in reader.iter_decoded_messages()}
    assert set(clouds) == set(foxglove) == set(layers)
    for topic, layer in layers.items():
        (cloud,) = clouds[topic]
        xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], 1)
        assert np.array_equal(xyz, layer.centers().astype(np.float32)), topic
        assert np.array_equal(cloud["label"], layer.labels()), topic
        assert np.array_equal(foxglove_cloud_to_array(foxglove[topic])["label"], layer.labels())
    with Reader(info["bag"]) as reader:
        durability = {c.topic: c.ext.offered_qos_profiles[0].durability for c in reader.connections}
    assert durability == dict.fromkeys(layers, QosDurability.TRANSIENT_LOCAL)


def test_each_scans_dynamic_points_have_their_own_topic(tmp_path):
    """Scans given with free-space flags: their flagged points, and only those, on
    /dynamic_points in map.mcap and map_ros2/; a scan with no flagged point (or no flags)
    adds no message there."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from tisem.io.pointcloud2 import foxglove_cloud_to_array
    from tisem.outputs import write_recording_maps

    rng = np.random.default_rng(4)
    scans, flags = [], [rng.random(40) < 0.3, np.zeros(40, bool), None]
    for k in range(3):
        pose = np.eye(4)
        pose[:3, 3] = [2.0 * k, 1.0, 1.7]
        scans.append(
            Scan(
                points_sensor=rng.uniform(-5, 5, (40, 3)).astype(np.float32),
                T_world_sensor=pose,
                stamp_s=1.0 + k,
                index=k,
                labels=rng.integers(0, 20, 40).astype(np.int32),
            )
        )
    items = [(s, s.labels, f) for s, f in zip(scans, flags)]
    snap = synthetic_snapshot(50)
    snap.occupancy = np.where(np.arange(len(snap)) % 5 == 0, -3.0, 1.0).astype(np.float32)
    snap.empty_evidence = 2.0
    info = write_recording_maps(tmp_path, snap, "map", iter(items))
    assert info["scans"] == 3
    assert info["dynamic_voxels"] == snap.empty().sum() > 0  # the layer's, not a scan's flags
    (bag_cloud,) = decoded_clouds(info["bag"])["/dynamic_points"]
    with open(info["mcap"], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        found = [
            (m.sequence, msg)
            for _, ch, m, msg in reader.iter_decoded_messages()
            if ch.topic == "/dynamic_points"
        ]
    ((sequence, msg),) = found
    assert sequence == 0
    xyz = np.stack([bag_cloud["x"], bag_cloud["y"], bag_cloud["z"]], 1)
    assert np.abs(xyz - scans[0].points_world()[flags[0]]).max() < 1e-5  # the map frame
    assert np.array_equal(bag_cloud["label"], scans[0].labels[flags[0]])
    assert np.array_equal(foxglove_cloud_to_array(msg)["label"], scans[0].labels[flags[0]])
    with pytest.raises(ValueError, match="scan 0: .* dynamic flags for 40 points"):
        write_recording_maps(
            tmp_path, synthetic_snapshot(50), "map", [(scans[0], scans[0].labels, np.ones(3, bool))]
        )
