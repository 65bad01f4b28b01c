"""McapScanReader on whole recordings: poses, labels, topics, pose sources, foxglove logs."""

from __future__ import annotations

import re
import struct

import numpy as np
import pytest

from tisem.errors import DatasetError, SkippedScan
from tisem.io.mcap_items import McapMessage
from tisem.io.mcap_reader import McapOptions, McapScanReader
from tisem.io.mcap_writer import Ros2McapWriter, pose_msg
from tisem.io.stamps import ros_time
from tisem.labels import raw_to_train
from tisem.synth.mcap_log import T_BASE_LIDAR, synthetic_points, synthetic_pose, write_synthetic_log

T0 = 100_000_000_000


def scans_of(path, **options) -> list:
    return list(McapScanReader(path, McapOptions(**options)))


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_scans_carry_header_stamp_poses_labels_and_names(tmp_path, compression):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=4, n_points=500, compression=compression)
    reader = McapScanReader(path)
    assert (reader.topic, reader.frame_id, reader.total) == ("/velodyne_points", "velodyne", 4)
    scans = list(reader)
    assert [s.index for s in scans] == [0, 1, 2, 3]
    for s, stamp, T, pts in zip(
        scans, truth["stamps_ns"], truth["T_world_sensor"], truth["points"]
    ):
        # the pose is the tf chain at the header stamp, interpolated between 50 Hz samples; at
        # the log time (35 ms later, 5 m/s) it would be 0.175 m off
        assert np.abs(s.T_world_sensor - T).max() < 1e-9
        assert s.stamp_s == stamp / 1e9 and s.source.log_time_ns - stamp == 35_000_000
        assert s.name == f"/velodyne_points@{stamp // 10**9}.{stamp % 10**9:09d}"
        assert np.array_equal(s.points_sensor[:, 1], pts["y"])
        assert np.array_equal(s.labels, raw_to_train(pts["label"])[0])
        assert s.gt_labels is None and s.probs is None
    assert reader.report.lines() == [] and not reader.report.to_dict()["damaged"]
    # iterating again gives the same scans (the pipeline reads twice for the final map)
    assert [s.name for s in reader] == [s.name for s in scans]


def test_first_last_select_by_message_order(tmp_path):
    write_synthetic_log(tmp_path / "log.mcap", n_scans=5, n_points=50)
    reader = McapScanReader(tmp_path / "log.mcap", McapOptions(first=1, last=3))
    assert reader.total == 3 and [s.index for s in reader] == [1, 2, 3]
    # and stops reading at `last`: a chunk of a long log does not read the rest of it
    records, clouds = reader._records.records, []

    def counted(report):
        for rec in records(report):
            cloud = isinstance(rec, McapMessage) and rec.channel_id in reader._channels
            if cloud and reader._channels[rec.channel_id].topic == reader.topic:
                clouds.append(rec)
            yield rec

    reader._records.records = counted
    assert [s.index for s in reader] == [1, 2, 3] and len(clouds) == 4


def write_fields_log(path, arr_fields, label_dtype="<u2", n=64, frames=2):
    """Clouds with extra fields (probabilities, gt) on a static map -> velodyne chain."""
    rng = np.random.default_rng(0)
    with Ros2McapWriter(path) as w:
        w.write_transforms([("map", "velodyne", 0, T_BASE_LIDAR)], 0, static=True)
        arrays = []
        for i in range(frames):
            arr = synthetic_points(n, rng, label_dtype, extra_fields=arr_fields)
            arrays.append(arr)
            w.write_cloud("/points", arr, "velodyne", (i + 1) * 10**8, (i + 1) * 10**8)
    return arrays


def test_train_label_space_probabilities_and_ground_truth(tmp_path):
    path = tmp_path / "f.mcap"
    arrays = write_fields_log(path, (("gt", "<u4"), ("train", "u1"), ("probs", "<f4", (20,))))
    rng = np.random.default_rng(1)
    # rewrite with known contents: train ids with two out-of-range values, GT raw with instances
    for arr in arrays:
        arr["train"] = rng.integers(0, 20, len(arr))
        arr["train"][:2] = [20, 255]
        arr["gt"] = arr["label"].astype(np.uint32) | (7 << 16)
        arr["gt"][0] = 1234  # not a SemanticKITTI id
        arr["probs"] = rng.random((len(arr), 20))
    with Ros2McapWriter(path) as w:
        w.write_transforms([("map", "velodyne", 0, np.eye(4))], 0, static=True)
        for i, arr in enumerate(arrays):
            w.write_cloud("/points", arr, "velodyne", (i + 1) * 10**8, (i + 1) * 10**8)

    reader = McapScanReader(
        path, McapOptions(label_field="train", label_space="train", gt_field="gt")
    )
    scans = list(reader)
    # the GT field follows the label space: here train ids, so raw GT values are out of range
    assert reader.report.unknown_labels == 4
    assert np.array_equal(scans[0].labels[2:], arrays[0]["train"][2:]) and scans[0].labels[0] == 0

    raw = McapScanReader(path, McapOptions(gt_field="gt"))
    s = list(raw)[0]
    assert np.array_equal(s.gt_labels[1:], raw_to_train(arrays[0]["label"][1:])[0])
    assert raw.report.unknown_gt_labels == 2 and "unknown ground-truth" in raw.report.lines()[-1]

    p = list(McapScanReader(path, McapOptions(prob_field="probs")))[1]
    assert p.labels is None and np.array_equal(p.probs, arrays[1]["probs"].astype(np.float32))


def test_train_ids_in_the_label_field_are_found_by_default(tmp_path, caplog):
    """A recording whose label field holds train ids, read with the default label space
    ("auto"), gives the scans "train" gives, and says so once; "raw" counts them unknown."""
    path = tmp_path / "f.mcap"
    arrays = write_fields_log(path, (), label_dtype="u1", frames=3)
    rng = np.random.default_rng(2)
    for arr in arrays:
        arr["label"] = rng.integers(0, 20, len(arr))
    with Ros2McapWriter(path) as w:
        w.write_transforms([("map", "velodyne", 0, np.eye(4))], 0, static=True)
        for i, arr in enumerate(arrays):
            w.write_cloud("/points", arr, "velodyne", (i + 1) * 10**8, (i + 1) * 10**8)
    with caplog.at_level("WARNING"):
        reader = McapScanReader(path)
        found = list(reader)
    said = [r.getMessage() for r in caplog.records if "train ids, not raw" in r.getMessage()]
    assert len(said) == 1 and "field 'label'" in said[0]
    assert reader.train_ids.sources == {"labels": 3} and reader.report.unknown_labels == 0
    for s, arr in zip(found, arrays):
        assert np.array_equal(s.labels, arr["label"])
    raw = McapScanReader(path, McapOptions(label_space="raw"))
    list(raw)
    assert raw.report.unknown_labels > 0 and raw.train_ids.sources == {}


def _labelled_log(path, labels: list[list[int]]) -> list:
    """A recording of one cloud per entry of `labels`, its label field those values repeated
    (no values: a cloud of no points)."""
    arrays = write_fields_log(path, (), label_dtype="u1", frames=len(labels))
    for k, values in enumerate(labels):
        arrays[k] = arrays[k][: len(arrays[k]) if values else 0]
        arrays[k]["label"] = np.resize(values, len(arrays[k]))
    with Ros2McapWriter(path) as w:
        w.write_transforms([("map", "velodyne", 0, np.eye(4))], 0, static=True)
        for i, arr in enumerate(arrays):
            w.write_cloud("/points", arr, "velodyne", (i + 1) * 10**8, (i + 1) * 10**8)
    return arrays


def test_clouds_that_fit_both_spaces_follow_the_first_that_fits_one(tmp_path):
    """Clouds without a class only train ids name (car 1, sidewalk 11, building 13: raw ids
    too), before the first that names road (9), are read as train ids too, in a run of the
    whole recording or of a part of it; where no cloud fits one space only, as raw ids."""
    path = tmp_path / "f.mcap"
    as_train, as_raw = [1, 11, 13], raw_to_train(np.array([1, 11, 13]))[0].tolist()
    _labelled_log(path, [[1, 11, 13], [1, 11, 13], [9, 1, 11], [1, 11, 13]])
    reader = McapScanReader(path)
    assert [s.labels.tolist()[:3] for s in reader] == [as_train, as_train, [9, 1, 11], as_train]
    assert reader.train_ids.sources == {"labels": 4}
    (first,) = scans_of(path, first=0, last=0)  # the chunk before the deciding cloud
    assert first.labels.tolist()[:3] == as_train
    _labelled_log(path, [[1, 11, 13], [1, 11, 13]])
    assert [s.labels.tolist()[:3] for s in scans_of(path)] == [as_raw, as_raw]
    _labelled_log(path, [[], [9, 1, 11], [1, 11, 13]])  # a cloud of no points decides nothing
    assert scans_of(path)[2].labels.tolist()[:3] == as_train


def test_the_survey_decodes_no_more_clouds_once_the_label_space_is_decided(tmp_path, monkeypatch):
    """Where the first cloud decides the label field's space (a recording of labels nearly
    always), the survey decodes one cloud, as without the search; where none does, it looks
    at SPACE_SEARCH_LIMIT clouds at most."""
    import tisem.io.mcap_survey as survey

    decoded = []
    real = survey.cloud_parts
    monkeypatch.setattr(survey, "cloud_parts", lambda *a: decoded.append(1) or real(*a))
    path = tmp_path / "f.mcap"
    _labelled_log(path, [[9, 1, 11]] + [[1, 11, 13]] * 5)
    McapScanReader(path)
    assert len(decoded) == 1
    decoded.clear()
    monkeypatch.setattr(survey, "SPACE_SEARCH_LIMIT", 4)
    _labelled_log(path, [[1, 11, 13]] * 6)
    McapScanReader(path)
    assert len(decoded) == 4


def test_a_probability_field_of_the_wrong_width_skips_with_a_reason(tmp_path):
    write_fields_log(tmp_path / "f.mcap", (("probs", "<f4", (3,)),), frames=1)
    (item,) = scans_of(tmp_path / "f.mcap", prob_field="probs")
    assert isinstance(item, SkippedScan) and "3 value(s) per point" in item.reason


def test_missing_label_field_lists_the_fields_the_cloud_has(tmp_path):
    write_synthetic_log(tmp_path / "log.mcap", n_scans=2, n_points=10)
    with pytest.raises(
        DatasetError,
        match=r"no 'class' label field \(--label-field\); their "
        r"fields are: x:float32, y:float32, z:float32, intensity:float32, "
        r"label:uint16",
    ):
        McapScanReader(tmp_path / "log.mcap", McapOptions(label_field="class"))
    with pytest.raises(DatasetError, match="no 'gt' ground-truth field"):
        McapScanReader(tmp_path / "log.mcap", McapOptions(gt_field="gt"))


def test_a_missing_label_field_names_the_likely_one(tmp_path):
    """Clouds whose labels are in a field 'class': the refusal of the default 'label' says
    which option would read it (it does not guess: another field could be meant)."""
    path = tmp_path / "class.mcap"
    rng = np.random.default_rng(0)
    arr = synthetic_points(10, rng)
    renamed = arr.astype(
        np.dtype(
            {
                "names": ["x", "y", "z", "intensity", "class"],
                "formats": [arr.dtype[i] for i in range(5)],
            }
        )
    )
    with Ros2McapWriter(path) as w:
        w.write_transforms([("map", "velodyne", 0, np.eye(4))], 0, static=True)
        w.write_cloud("/points", renamed, "velodyne", 5, 5)
    with pytest.raises(
        DatasetError,
        match=r"have no 'label' label field .*class:uint16 \(the labels\? --label-field class\)$",
    ):
        McapScanReader(path)
    (scan,) = list(McapScanReader(path, McapOptions(label_field="class")))
    assert np.array_equal(scan.labels, raw_to_train(arr["label"])[0])


def test_topic_choice(tmp_path):
    path = tmp_path / "two.mcap"
    rng = np.random.default_rng(0)
    with Ros2McapWriter(path) as w:
        w.write_transforms([("map", "a", 0, np.eye(4)), ("map", "b", 0, np.eye(4))], 0, static=True)
        for topic, frame in (("/front/points", "a"), ("/rear/points", "b")):
            w.write_cloud(topic, synthetic_points(10, rng), frame, 5, 5)
    with pytest.raises(
        DatasetError,
        match=r"several point-cloud topics, choose one with --topic: "
        r"/front/points \(sensor_msgs/msg/PointCloud2, 1 msgs\), /rear/points.*; "
        r"/front/points .*, /rear/points .* carry the fields asked for",
    ):
        McapScanReader(path)
    assert McapScanReader(path, McapOptions(topic="/rear/points")).frame_id == "b"
    with pytest.raises(DatasetError, match="no topic '/lidar'; point-cloud topics: /front"):
        McapScanReader(path, McapOptions(topic="/lidar"))
    with pytest.raises(DatasetError, match="carries tf2_msgs/msg/TFMessage, not a point cloud"):
        McapScanReader(path, McapOptions(topic="/tf_static"))


def test_the_one_labelled_cloud_topic_is_mapped(tmp_path, caplog):
    """The raw sensor topic beside the labelled one a segmentation node publishes: the clouds
    with the label field are mapped, and a line says which; with both labelled, --topic."""
    path = tmp_path / "two.mcap"
    rng = np.random.default_rng(0)
    labelled = synthetic_points(10, rng)
    raw = labelled[["x", "y", "z", "intensity"]]
    with Ros2McapWriter(path) as w:
        w.write_transforms([("map", "velodyne", 0, np.eye(4))], 0, static=True)
        w.write_cloud("/velodyne_points", np.ascontiguousarray(raw), "velodyne", 5, 5)
        w.write_cloud("/segmented_points", labelled, "velodyne", 5, 6)
    with caplog.at_level("INFO"):
        reader = McapScanReader(path)
    assert reader.topic == "/segmented_points"
    assert "mapping /segmented_points, the one whose clouds carry the fields" in caplog.text
    (scan,) = list(reader)
    assert np.array_equal(scan.labels, raw_to_train(labelled["label"])[0])
    with pytest.raises(DatasetError, match="several point-cloud topics"):
        McapScanReader(path, McapOptions(label_field="intensity"))


def test_no_cloud_topic(tmp_path):
    path = tmp_path / "tf_only.mcap"
    with Ros2McapWriter(path) as w:
        w.write_transforms([("map", "a", 0, np.eye(4))], 0)
    with pytest.raises(
        DatasetError,
        match=r"no point-cloud messages found; topics: /tf "
        r"\(tf2_msgs/msg/TFMessage, 1 msgs\)",
    ):
        McapScanReader(path)


def test_no_transform_path_to_the_map_frame(tmp_path):
    write_synthetic_log(tmp_path / "log.mcap", n_scans=2, n_points=10)
    with pytest.raises(
        DatasetError,
        match=r"no transform from the map frame 'world' to the "
        r"cloud frame 'velodyne'.*known frames: base_link, map, velodyne",
    ):
        McapScanReader(tmp_path / "log.mcap", McapOptions(map_frame="world"))
    # base_link works as a map frame: the static mount only
    s = scans_of(tmp_path / "log.mcap", map_frame="base_link")[0]
    assert np.allclose(s.T_world_sensor, T_BASE_LIDAR)


def test_scans_outside_the_tf_range_are_skipped_with_the_reason(tmp_path):
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=5, n_points=20, tf_end_s=0.25)
    items = scans_of(path)
    assert [type(i).__name__ for i in items] == ["Scan"] * 3 + ["SkippedScan"] * 2
    assert "map -> base_link" in items[3].reason and "after its last sample" in items[3].reason
    assert np.abs(items[2].T_world_sensor - truth["T_world_sensor"][2]).max() < 1e-9
    # a tolerance accepts a stamp just past the last sample (0.24 s; scan 3 is at 0.313 s)
    items = scans_of(path, tf_tolerance_s=0.08)
    assert [type(i).__name__ for i in items] == ["Scan"] * 4 + ["SkippedScan"]


def _odometry(T, stamp, child="base_link"):
    zeros = {"x": 0.0, "y": 0.0, "z": 0.0}
    return {
        "header": {"stamp": ros_time(stamp), "frame_id": "map"},
        "child_frame_id": child,
        "pose": {"pose": pose_msg(T), "covariance": [0.0] * 36},
        "twist": {"twist": {"linear": zeros, "angular": zeros}, "covariance": [0.0] * 36},
    }


@pytest.mark.parametrize("kind", ["odometry", "pose_stamped"])
def test_pose_topic_instead_of_tf(tmp_path, kind):
    path = tmp_path / "odom.mcap"
    rng = np.random.default_rng(0)
    stamps = [T0 + k * 20_000_000 for k in range(30)]
    with Ros2McapWriter(path) as w:
        w.write_transforms([("base_link", "velodyne", T0, T_BASE_LIDAR)], T0, static=True)
        w.write_transforms([("map", "base_link", T0, np.eye(4))], T0)  # ignored
        for t in stamps:
            T = synthetic_pose((t - T0) / 1e9)
            if kind == "odometry":
                w.write("/odom", "nav_msgs/msg/Odometry", _odometry(T, t), t)
            else:  # no child frame in the message: the top of the sensor's static mount
                w.write(
                    "/pose",
                    "geometry_msgs/msg/PoseStamped",
                    {"header": {"stamp": ros_time(t), "frame_id": "map"}, "pose": pose_msg(T)},
                    t,
                )
        w.write_cloud(
            "/points", synthetic_points(10, rng), "velodyne", T0 + 123_000_000, T0 + 150_000_000
        )
    topic = "/odom" if kind == "odometry" else "/pose"
    reader = McapScanReader(path, McapOptions(pose_topic=topic))
    (s,) = list(reader)
    assert np.abs(s.T_world_sensor - synthetic_pose(0.123) @ T_BASE_LIDAR).max() < 1e-9
    with pytest.raises(DatasetError, match="no topic '/gps'"):
        McapScanReader(path, McapOptions(pose_topic="/gps"))
    with pytest.raises(DatasetError, match="carries tf2_msgs/msg/TFMessage; supported"):
        McapScanReader(path, McapOptions(pose_topic="/tf"))


def test_foxglove_point_cloud_and_frame_transforms(tmp_path):
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
    from google.protobuf.timestamp_pb2 import Timestamp
    from mcap_protobuf.writer import Writer

    from tisem.io.pointcloud2 import array_to_foxglove_cloud
    from tisem.io.tf import matrix_to_quat

    def frame_transform(parent, child, t, T):
        q = matrix_to_quat(T[:3, :3])
        return FrameTransform(
            timestamp=Timestamp(seconds=t // 10**9, nanos=t % 10**9),
            parent_frame_id=parent,
            child_frame_id=child,
            translation=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    path = tmp_path / "fox.mcap"
    rng = np.random.default_rng(0)
    T_cloud = np.eye(4)
    T_cloud[:3, 3] = [0.0, 0.0, 0.25]  # the cloud's own `pose` field
    arr = synthetic_points(40, rng)
    with open(path, "wb") as f, Writer(f) as w:
        # the mount is logged once: no static flag in foxglove, promoted because it never changes
        w.write_message(
            "/tf",
            frame_transform("base_link", "lidar_top", T0, T_BASE_LIDAR),
            log_time=T0,
            publish_time=T0,
        )
        for k in range(20):
            t = T0 + k * 20_000_000
            w.write_message(
                "/tf",
                frame_transform("map", "base_link", t, synthetic_pose((t - T0) / 1e9)),
                log_time=t,
                publish_time=t,
            )
        t = T0 + 210_000_000
        w.write_message(
            "/lidar_top",
            array_to_foxglove_cloud(arr, "lidar_top", t, T_cloud),
            log_time=t,
            publish_time=t,
        )
    reader = McapScanReader(path)
    (s,) = list(reader)
    expect = synthetic_pose(0.21) @ T_BASE_LIDAR @ T_cloud
    assert np.abs(s.T_world_sensor - expect).max() < 1e-9
    assert np.array_equal(s.labels, raw_to_train(arr["label"])[0])
    assert any("taken as static: lidar_top" in n for n in reader.report.notes)


def test_pose_stamped_of_the_sensor_itself(tmp_path):
    """Without a static mount the PoseStamped is the cloud frame's own pose."""
    path = tmp_path / "pose.mcap"
    with Ros2McapWriter(path) as w:
        for k in range(3):
            t = T0 + k * 50_000_000
            w.write(
                "/pose",
                "geometry_msgs/msg/PoseStamped",
                {
                    "header": {"stamp": ros_time(t), "frame_id": ""},  # empty: the map
                    "pose": pose_msg(synthetic_pose(k * 0.05)),
                },
                t,
            )
        w.write_cloud(
            "/points",
            synthetic_points(10, np.random.default_rng(0)),
            "velodyne",
            T0 + 75_000_000,
            T0 + 75_000_000,
        )
    (s,) = scans_of(path, pose_topic="/pose")
    assert np.abs(s.T_world_sensor - synthetic_pose(0.075)).max() < 1e-9


@pytest.mark.parametrize("variant", [dict(), dict(indexed=False), dict(chunked=False)])
def test_stopping_early_leaves_nothing_behind(tmp_path, monkeypatch, variant):
    """A consumer may stop mid-way (an error, Ctrl-C): closing the generators must be clean."""
    import gc
    import sys

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    write_synthetic_log(tmp_path / "log.mcap", n_scans=3, n_points=20, **variant)
    reader = McapScanReader(tmp_path / "log.mcap")
    it = iter(reader)
    next(it)
    del it
    gc.collect()
    assert unraisable == []


# ---- clouds that cannot be what they say, errors that say why -------------------------------


def _hook(k, change):
    return lambda i, msg: change(msg) if i == k else msg


@pytest.mark.parametrize(
    "change,reason",
    [
        (
            lambda m: dict(m, height=0),
            "height 0 x width 30 declares no points, but the cloud carries 540 bytes of data",
        ),
        (
            lambda m: dict(m, width=29, row_step=29 * 18),
            "data has 540 bytes; height 1 x row_step 522 (width 29 x point_step 18) needs 522",
        ),
        (
            lambda m: dict(m, width=31, row_step=31 * 18),
            "data has 540 bytes; height 1 x row_step 558 (width 31 x point_step 18) needs 558",
        ),
        (lambda m: dict(m, width=0, row_step=0, data=b""), "the cloud has 0 points"),
        (
            lambda m: dict(
                m, fields=[dict(f, offset=2) if f["name"] == "x" else f for f in m["fields"]]
            ),
            "fields 'x' (bytes 2-6) and 'y' (bytes 4-8) overlap",
        ),
    ],
)
def test_clouds_whose_layout_disagrees_with_their_data_are_skipped(tmp_path, change, reason):
    """Points neither dropped nor invented: the scan is skipped, saying why."""
    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=4, n_points=30, cloud_hook=_hook(1, change))
    items = scans_of(path)
    assert isinstance(items[1], SkippedScan) and items[1].index == 1
    assert items[1].reason == reason
    for s in (items[0], items[2], items[3]):
        assert np.array_equal(s.points_sensor[:, 0], truth["points"][s.index]["x"])


def test_a_log_of_empty_clouds_skips_every_scan_with_the_reason(tmp_path):
    path = tmp_path / "log.mcap"
    write_synthetic_log(
        path, n_scans=3, n_points=10, cloud_hook=lambda i, m: dict(m, width=0, row_step=0, data=b"")
    )
    reader = McapScanReader(path)
    items = list(reader)
    assert [(type(i).__name__, i.reason) for i in items] == [
        ("SkippedScan", "the cloud has 0 points")
    ] * 3
    assert [s.index for s in reader.report.skipped] == [0, 1, 2]


def test_labels_that_are_no_labels_become_unknown_and_are_counted(tmp_path):
    """Float labels of NaN, inf, 1e300, -1 or 0.5 are no SemanticKITTI id: 0 (no evidence),
    counted once per point however often the log is read."""
    bad = [np.nan, np.inf, 1e300, -1.0, 0.5, 2.0**32]

    def labels(i, msg):
        arr = np.frombuffer(
            msg["data"],
            np.dtype(
                [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("label", "<f8")]
            ),
        ).copy()
        if i == 1:
            arr["label"][: len(bad)] = bad
        return dict(msg, data=arr.tobytes())

    path = tmp_path / "log.mcap"
    truth = write_synthetic_log(path, n_scans=2, n_points=20, label_dtype="<f8", cloud_hook=labels)
    reader = McapScanReader(path)
    for _ in range(2):  # the final pass reads the log again
        first, second = list(reader)
    assert second.labels[: len(bad)].tolist() == [0] * len(bad)
    expect = raw_to_train(truth["points"][1]["label"][len(bad) :].astype(np.uint32))[0]
    assert np.array_equal(second.labels[len(bad) :], expect)
    assert second.source.unknown_raw_ids == len(bad) and first.source.unknown_raw_ids == 0
    assert reader.report.unknown_labels == len(bad)
    assert (
        f"{len(bad)} point(s) with an unknown label id (or an invalid value) mapped to 0"
        in reader.report.lines()
    )


def test_probabilities_that_are_no_probabilities_give_no_evidence(tmp_path):
    path = tmp_path / "f.mcap"
    arrays = write_fields_log(path, (("probs", "<f4", (20,)),), frames=1)
    arr = arrays[0]
    arr["probs"] = 0.05
    arr["probs"][0, 3] = np.nan
    arr["probs"][1, 0] = 3e38
    arr["probs"][2, 5] = -0.1
    with Ros2McapWriter(path) as w:
        w.write_transforms([("map", "velodyne", 0, np.eye(4))], 0, static=True)
        w.write_cloud("/points", arr, "velodyne", 10**8, 10**8)
    reader = McapScanReader(path, McapOptions(prob_field="probs"))
    (s,) = list(reader)
    assert np.all(s.probs[:3] == 0) and np.all(s.probs[3:] == np.float32(0.05))
    assert s.source.unknown_raw_ids == 3 and reader.report.unknown_labels == 3


def test_when_no_cloud_decodes_the_error_says_why(tmp_path):
    path = tmp_path / "log.mcap"
    write_synthetic_log(
        path, n_scans=3, n_points=10, cloud_hook=lambda i, m: dict(m, point_step=0, row_step=0)
    )
    with pytest.raises(
        DatasetError,
        match=r"none of the 3 messages on /velodyne_points could "
        r"be decoded \(the first: CloudFormatError: point_step 0 is not in "
        r"1..65536\)",
    ):
        McapScanReader(path)


def test_a_missing_map_frame_names_the_transforms_that_were_ignored(tmp_path):
    path = tmp_path / "log.mcap"
    with Ros2McapWriter(path) as w:
        for k in range(16):
            w.write(
                "/tf",
                "tf2_msgs/msg/TFMessage",
                {
                    "transforms": [
                        {
                            "header": {"stamp": ros_time(T0 + k * 10**8), "frame_id": "map"},
                            "child_frame_id": "velodyne",
                            "transform": {
                                "translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                                "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0},
                            },
                        }
                    ]
                },
                T0 + k * 10**8,
            )
        w.write_cloud("/points", synthetic_points(10, np.random.default_rng(0)), "velodyne", T0, T0)
    with pytest.raises(
        DatasetError,
        match=r"frame 'map' does not appear in any transform; "
        r"known frames: none; ignored 16 transform\(s\) map -> velodyne with a "
        r"zero quaternion",
    ):
        McapScanReader(path)


def test_an_error_caused_by_damage_says_what_was_lost(tmp_path):
    """The mount (/tf_static) was in the first chunk; that chunk is lost, none of it
    inflates (its zstd frame's magic number is damaged): the error names the loss, not only
    the missing frame."""
    path = tmp_path / "log.mcap"
    write_synthetic_log(path, n_scans=4, n_points=200, chunk_size=3_000)
    data = bytearray(path.read_bytes())
    first = 8 + 9 + struct.unpack_from("<Q", data, 9)[0]  # after the header record
    # the chunk's fields: 3 x u64, u32 CRC, "zstd" with its u32 length, the u64 data length
    data[first + 9 + 44 + 1] ^= 0x40
    path.write_bytes(bytes(data))
    with pytest.raises(
        DatasetError,
        match=r"frame 'velodyne' does not appear in any "
        r"transform.*; the file is damaged: chunk at byte \d+ .*chunk skipped",
    ):
        McapScanReader(path)


@pytest.mark.parametrize(
    "options,message",
    [
        (dict(tf_tolerance_s=float("nan")), "tf_tolerance_s must be a finite number >= 0, got nan"),
        (dict(tf_tolerance_s=float("inf")), "tf_tolerance_s must be a finite number >= 0, got inf"),
        (dict(tf_tolerance_s=-1.0), "tf_tolerance_s must be a finite number >= 0, got -1.0"),
        (dict(first=-1), "first must be a whole number >= 0, got -1"),
        (dict(first=3, last=2), "last must be a whole number >= first (3) or None, got 2"),
        (dict(num_classes=1), "num_classes must be a whole number >= 2, got 1"),
        (dict(label_field=""), "label_field must be a non-empty string"),
    ],
)
def test_options_are_checked_with_the_value_and_what_is_allowed(options, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        McapOptions(**options).validate()
