"""tisem.logs (what `tisem fleet` and `tisem batch` map): every recording `tisem map-mcap` reads
is one log, read with the recording options it was discovered with; the options come from the
same command-line group in all three commands."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the rosbags package (tisem[mcap]) is not installed")

from test_rosbag_read import make_input, recording  # noqa: E402,F401  (a fixture)

from tisem.errors import DatasetError  # noqa: E402
from tisem.io.semantickitti import SemanticKittiSequence  # noqa: E402
from tisem.logs import LogSpec, discover_logs, log_length, open_log, read_losses  # noqa: E402
from tisem.scan import Scan  # noqa: E402

READ = {"gt_field": "gt_label"}


@pytest.mark.parametrize("form", ["split mcap", "db3 folder", "humble db3 file", "ros1"])
def test_every_recording_is_one_log_read_with_its_options(recording, form):  # noqa: F811
    """A rosbag2 folder split in two is one log (its second file alone has no /tf_static: as
    two logs it was refused), a .db3 and a ROS 1 bag are logs, and the ground truth the options
    name comes with every scan."""
    seq_dir, messages, tmp = recording
    path = make_input(form, messages, tmp / ("logs_" + form.replace(" ", "_")))
    (log,) = discover_logs([path], recording=READ)
    assert log.kind == "mcap" and log.options["gt_field"] == "gt_label"
    assert log.world_frame == f"mcap:{path.resolve()}#map"
    assert log_length(log) == 4
    expected = list(SemanticKittiSequence(seq_dir))
    scans = open_log(log, first=1, last=2)
    got = list(scans)
    assert [s.index for s in got] == [1, 2] and all(isinstance(s, Scan) for s in got)
    for a, b in zip(expected[1:3], got):
        assert np.array_equal(a.points_sensor, b.points_sensor)
        assert np.array_equal(a.labels, b.labels) and np.array_equal(a.gt_labels, b.gt_labels)
        assert np.abs(a.T_world_sensor - b.T_world_sensor).max() < 1e-6
    assert scans.report.losses == []  # (notes, such as chunks without a CRC, may be there)
    # without the option, the same log has no ground truth: the options are what is read
    (plain,) = discover_logs([path])
    assert next(iter(open_log(plain))).gt_labels is None


def test_a_log_keeps_its_options_through_json(recording):  # noqa: F811
    """Ray tasks and batch cells get the log as plain JSON (LogSpec.to_dict): its static
    transforms and map frame come back and still read the recording."""
    seq_dir, messages, tmp = recording
    path = make_input("db3 folder", messages, tmp / "logs_json")
    mount = ("base_link", "velodyne", 0.5, 0.0, 1.5, 0.0, 0.0, 0.0, 1.0)
    (log,) = discover_logs([path], recording={**READ, "static_tf": (mount,), "map_frame": "/map"})
    again = LogSpec(**log.to_dict())
    assert again == log and again.options["static_tf"] == [list(mount)]
    kitti = discover_logs([seq_dir])[0]  # no options: the dict of before they existed
    assert set(kitti.to_dict()) == {"kind", "path", "name", "world_frame"}
    assert LogSpec(**kitti.to_dict()) == kitti
    (scan, *_) = list(open_log(again))
    (ref, *_) = list(SemanticKittiSequence(seq_dir))
    # the recording's own mount is replaced: the sensor sits where the option puts it
    assert not np.allclose(scan.T_world_sensor, ref.T_world_sensor, atol=1e-3)
    assert scan.gt_labels is not None


def test_what_is_no_log_is_refused_in_one_line(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("not a recording\n")
    with pytest.raises(DatasetError) as info:
        discover_logs([text])
    assert str(info.value).startswith(f"{text}: not a recording tisem reads")
    assert "\n" not in str(info.value)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match="empty: not a log .*rosbag2 folder"):
        discover_logs([empty])
    (empty / "robot1.mcap").write_bytes(b"")  # a folder of logs, not a bag: each is a log
    (empty / "robot2.mcap").write_bytes(b"")
    with pytest.raises(DatasetError, match=r"it holds robot1.mcap, robot2.mcap: give each as a"):
        discover_logs([empty])
    with pytest.raises(DatasetError, match="missing.db3: no such file or folder"):
        discover_logs([tmp_path / "missing.db3"])
    with pytest.raises(ValueError, match=r"recording options: unknown \['gt'\]"):
        discover_logs([text], recording={"gt": "gt_label"})
    with pytest.raises(ValueError, match="label_space must be one of auto, raw, train, got 'ids'"):
        discover_logs([text], recording={"label_space": "ids"})


def test_a_cut_recording_reports_what_it_lost(recording, tmp_path):  # noqa: F811
    """The reader's losses reach the fleet task and the batch cell (read_losses), the skipped
    scans apart."""
    seq_dir, messages, tmp = recording
    folder = make_input("split mcap", messages, tmp_path / "cut")
    second = sorted(folder.glob("*.mcap"))[1]
    data = second.read_bytes()
    second.write_bytes(data[: int(len(data) * 0.8)])
    (log,) = discover_logs([folder], recording=READ)
    scans = open_log(log)
    got = [s for s in scans if isinstance(s, Scan)]
    assert 2 <= len(got) < 4
    lines = read_losses(scans)
    assert lines and any(line.startswith(f"{second.name}: ") for line in lines)
    assert not any("skipped" in line for line in lines)


def test_the_three_commands_share_the_recording_options():
    """map-mcap, fleet and batch take the same recording options and build the same
    McapOptions from them."""
    from tisem.commands import batch, fleet, map_mcap
    from tisem.recording_args import recording_options

    given = [
        "--gt-field",
        "gt_label",
        "--label-space",
        "train",
        "--map-frame",
        "odom",
        "--static-tf",
        "0.8 0 1.7 0 0 0 1 base_link velodyne",
    ]
    built = [
        recording_options(fleet.parse_args(["logs", *given])),
        recording_options(batch.parse_args(["logs", *given])),
        recording_options(map_mcap.parse_args(["drive.mcap", *given])),
    ]
    assert built[0] == built[1] == dataclasses.replace(built[2], first=0, last=None)
    assert built[0].gt_field == "gt_label" and built[0].label_space == "train"
    assert built[0].static_tf == (("base_link", "velodyne", 0.8, 0.0, 1.7, 0.0, 0.0, 0.0, 1.0),)
    with pytest.raises(ValueError, match="--static-tf '1 2 3': expected X Y Z"):
        recording_options(fleet.parse_args(["logs", "--static-tf", "1 2 3"]))


def test_a_recording_is_read_for_the_maps_classes(recording):  # noqa: F811
    """open_log's num_classes (the map's, from the task's config) bounds the label values a
    recording's train-id field may hold: a value the map has no class for is reported, no
    evidence (here the raw ids, read as train ids: those from 5 up are beyond 5 classes)."""
    seq_dir, messages, tmp = recording
    path = make_input("db3 folder", messages, tmp / "logs_classes")
    (log,) = discover_logs([path], recording={"label_space": "train"})
    (scan20, *_) = list(scans20 := open_log(log))
    (scan5, *_) = list(scans5 := open_log(log, num_classes=5))
    assert np.all(scan5.labels < 5) and np.any(scan20.labels >= 5)
    assert scans5.report.unknown_labels > scans20.report.unknown_labels
