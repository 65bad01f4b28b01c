"""`--static-tf` / `McapOptions.static_tf`: a transform the recording lacks (a bag recorded
without /tf_static, so without the sensor's mount) or gets wrong, given by the user."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tisem.errors import DatasetError
from tisem.io.mcap_reader import McapOptions, McapScanReader
from tisem.io.mcap_writer import Ros2McapWriter
from tisem.io.tf import matrix_to_quat
from tisem.synth.mcap_log import T_BASE_LIDAR, synthetic_points, synthetic_pose

REPO = Path(__file__).resolve().parents[1]
T0 = 100_000_000_000
CLOUD_AT = [T0 + 113_000_000 + k * 100_000_000 for k in range(3)]


def mount_of(T: np.ndarray) -> tuple:
    """T_parent_child as the numbers of a static_tf item: x y z qx qy qz qw."""
    return (*T[:3, 3], *matrix_to_quat(T[:3, :3]))


def write_recording(path: Path, mount: np.ndarray | None) -> Path:
    """map -> base_link at 50 Hz on /tf, the clouds in frame velodyne, and the mount
    base_link -> velodyne on /tf_static only where `mount` is given."""
    rng = np.random.default_rng(0)
    with Ros2McapWriter(path) as w:
        if mount is not None:
            w.write_transforms([("base_link", "velodyne", T0, mount)], T0, static=True)
        for k in range(20):
            t = T0 + k * 20_000_000
            w.write_transforms([("map", "base_link", t, synthetic_pose((t - T0) / 1e9))], t)
        for t in CLOUD_AT:
            w.write_cloud("/points", synthetic_points(50, rng), "velodyne", t, t + 30_000_000)
    return path


def expected_pose(t_ns: int) -> np.ndarray:
    return synthetic_pose((t_ns - T0) / 1e9) @ T_BASE_LIDAR


def test_a_mount_the_recording_lacks_comes_from_static_tf(tmp_path):
    path = write_recording(tmp_path / "no_mount.mcap", None)
    with pytest.raises(DatasetError) as info:
        McapScanReader(path)
    assert "cloud frame 'velodyne'" in str(info.value) and "--static-tf" in str(info.value)
    given = ("base_link", "velodyne", *mount_of(T_BASE_LIDAR))
    reader = McapScanReader(path, McapOptions(static_tf=(given,)))
    scans = list(reader)
    assert len(scans) == 3
    for s, t in zip(scans, CLOUD_AT):
        assert np.abs(s.T_world_sensor - expected_pose(t)).max() < 1e-9
    assert reader.report.lines() == []  # (nothing of the recording was replaced)


def test_static_tf_replaces_a_wrong_mount_and_says_so(tmp_path):
    path = write_recording(tmp_path / "wrong_mount.mcap", np.eye(4))
    (first, *_) = list(McapScanReader(path))
    assert np.abs(first.T_world_sensor - expected_pose(CLOUD_AT[0])).max() > 0.1
    given = ("/base_link", "/velodyne", *mount_of(T_BASE_LIDAR))  # (ROS 1 names work too)
    reader = McapScanReader(path, McapOptions(static_tf=(given,)))
    for s, t in zip(reader, CLOUD_AT):
        assert np.abs(s.T_world_sensor - expected_pose(t)).max() < 1e-9
    assert reader.report.notes == [
        "tf: base_link -> velodyne from --static-tf, in place of the recording's 1 "
        "transform(s) of velodyne"
    ]


ROTATION = (0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize(
    "static_tf,message",
    [
        ((("a", "b", 1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 2.0),), "the quaternion qx qy qz qw has norm 2"),
        ((("a", "b", 0.0, 0.0, 0.0, 0.1, 0.2, 1.57),), "each transform is (parent, child, x, y, z"),
        ((("a", "a", 0.0, 0.0, 0.0, *ROTATION),), "needs two different, non-empty frame names"),
        ((("a", "b", float("nan"), 0.0, 0.0, *ROTATION),), "x y z qx qy qz qw must be finite"),
        ((("a", "b", "1", 0.0, 0.0, *ROTATION),), "x y z qx qy qz qw must be numbers"),
        (
            (("a", "b", 0.0, 0.0, 0.0, *ROTATION), ("c", "/b", 0.0, 0.0, 0.0, *ROTATION)),
            "frame 'b' is given a transform twice",
        ),
    ],
)
def test_a_static_tf_that_is_no_transform_is_refused_with_what_is_wrong(static_tf, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        McapOptions(static_tf=static_tf).validate()


def test_a_quaternion_typed_to_a_few_digits_is_normalised():
    (item,) = McapOptions(
        static_tf=(("a", "b", 0, 0, 0, 0.0, 0.0, 0.7071, 0.7071),)
    ).static_transforms()
    assert np.isclose(np.linalg.norm(item[3]), 1.0)


def run_map_mcap(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(REPO / "apps" / "map_mcap.py"), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_map_mcap_takes_the_mount_in_quotes_and_refuses_other_text_in_one_line(tmp_path):
    path = write_recording(tmp_path / "no_mount.mcap", None)
    mount = " ".join(repr(float(v)) for v in mount_of(T_BASE_LIDAR)) + " base_link velodyne"
    done = run_map_mcap(path, "--out", tmp_path / "out", "--no-progress", "--static-tf", mount)
    assert done.returncode == 0, done.stderr
    assert "3 scans mapped, 0 skipped" in done.stdout
    bad = run_map_mcap(path, "--out", tmp_path / "bad", "--static-tf", "0 0 0 base_link velodyne")
    assert bad.returncode == 2
    (line,) = [x for x in bad.stderr.splitlines() if "--static-tf" in x]
    assert "expected X Y Z QX QY QZ QW (numbers), then PARENT CHILD" in line
    assert "Traceback" not in bad.stderr and not (tmp_path / "bad").exists()


def test_a_bag_without_a_mount_is_refused_for_that_alone(tmp_path):
    """rosbags reads the `.db3` and refuses it for what it holds (no mount); the row reader,
    tried next, refuses it alike: the refusal is that one line, without a note blaming the
    file's pages. With --static-tf the bag maps."""
    pytest.importorskip("rosbags", reason="the rosbags package (tisem[mcap]) is not installed")
    from tisem.io.bag_open import open_scan_reader
    from tisem.testing.bag_damage import recorded_messages, write_db3

    messages = recorded_messages(write_recording(tmp_path / "no_mount.mcap", None))
    db3 = write_db3(tmp_path / "no_mount_bag", messages)
    with pytest.raises(DatasetError) as info:
        open_scan_reader(db3.parent)
    assert "cloud frame 'velodyne'" in str(info.value)
    assert "rosbags cannot read" not in str(info.value) and "\n" not in str(info.value)
    given = ("base_link", "velodyne", *mount_of(T_BASE_LIDAR))
    scans = list(open_scan_reader(db3.parent, McapOptions(static_tf=(given,))))
    for s, t in zip(scans, CLOUD_AT, strict=True):
        assert np.abs(s.T_world_sensor - expected_pose(t)).max() < 1e-9
