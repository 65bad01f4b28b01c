"""Impossible geometry and times in a SemanticKITTI folder: refused with file and line.

A bad calibration or two files for one scan number refuse the whole sequence (DatasetError);
a pose line that is not a pose, or a time that is not plausible, costs its own scan only
(ScanError naming poses.txt:LINE / times.txt:LINE), and the others are read as before.
Folders are the small generated ones of test_semantickitti.py.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from test_pipeline import run_app, tiny_sequence
from test_semantickitti import IDENTITY_ROWS, TR_ROWS, _fmt, _kinds, make_sequence

from tisem.errors import DatasetError, ScanError
from tisem.io.semantickitti import MAX_TIME_S, SemanticKittiSequence, read_calib_tr


def pose_row(rotation: np.ndarray, t=(0.0, 0.0, 0.0)) -> list[float]:
    return np.column_stack([rotation, t]).ravel().tolist()


BAD_ROTATIONS = {
    "singular": (np.diag([1.0, 1.0, 0.0]), "singular"),
    "scaled x1000": (np.eye(3) * 1000.0, "scaled by 1000"),
    "mirrored": (np.diag([1.0, -1.0, 1.0]), "mirrored"),
    "sheared": (np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "not a rotation"),
}


@pytest.mark.parametrize("kind", sorted(BAD_ROTATIONS))
def test_a_pose_that_is_not_a_rotation_costs_its_scan(tmp_path, kind):
    d = make_sequence(tmp_path / "seq", n_scans=4)
    rotation, words = BAD_ROTATIONS[kind]
    lines = (d / "poses.txt").read_text().splitlines()
    lines[2] = _fmt(pose_row(rotation, (0.0, 0.0, 2.0)))
    (d / "poses.txt").write_text("\n".join(lines) + "\n")
    seq = SemanticKittiSequence(d)
    with pytest.raises(ScanError) as err:
        seq[2]
    message = str(err.value)
    assert "\n" not in message
    assert f"{d / 'poses.txt'}:3: pose 2 is not a pose" in message and words in message, message
    items = list(seq)
    assert _kinds(items) == ["Scan", "Scan", "SkippedScan", "Scan"]
    assert items[2].reason == message
    assert np.allclose(
        items[3].T_world_sensor[:3, :3] @ items[3].T_world_sensor[:3, :3].T, np.eye(3)
    )


@pytest.mark.parametrize(
    "calib,problem",
    [
        ("Tr: " + _fmt(np.multiply(TR_ROWS, 0.5)) + "\n", "scaled by 0.5"),
        (
            "Tr: " + _fmt(TR_ROWS) + "\nTr: " + _fmt(IDENTITY_ROWS) + "\n",
            "calib.txt:3: a second 'Tr:' line (the first velodyne -> camera line is line 2)",
        ),
        (
            "Tr: " + _fmt(TR_ROWS) + "\nTr_velo_to_cam: " + _fmt(TR_ROWS) + "\n",
            "calib.txt:3: a second 'Tr_velo_to_cam:' line (the first velodyne -> camera line",
        ),
        ("Tr: " + _fmt(pose_row(np.diag([1.0, 1.0, -1.0]))) + "\n", "mirrored"),
    ],
    ids=["scaled by 0.5", "two Tr lines", "Tr and Tr_velo_to_cam", "mirrored"],
)
def test_a_bad_calibration_refuses_the_sequence(tmp_path, calib, problem):
    d = make_sequence(tmp_path / "seq")
    (d / "calib.txt").write_text("P0: " + _fmt(range(12)) + "\n" + calib)
    with pytest.raises(DatasetError) as err:
        SemanticKittiSequence(d)
    message = str(err.value)
    assert "\n" not in message and problem in message, message
    assert f"{d / 'calib.txt'}:" in message
    with pytest.raises(DatasetError):
        read_calib_tr(d / "calib.txt")


@pytest.mark.parametrize("key", ["Tr_velo_to_cam", "Tr_velo_cam"])
def test_the_object_and_tracking_calibration_keys_are_read(tmp_path, key):
    """KITTI's 3D object and tracking calibrations name the velodyne -> camera line otherwise:
    the same transform, the same scans."""
    reference = list(SemanticKittiSequence(make_sequence(tmp_path / "ref")))
    d = make_sequence(tmp_path / "seq")
    (d / "calib.txt").write_text(f"P0: {_fmt(range(12))}\n{key}: {_fmt(TR_ROWS)}\n")
    for a, b in zip(SemanticKittiSequence(d), reference):
        np.testing.assert_array_equal(a.T_world_sensor, b.T_world_sensor)


def test_two_files_for_one_scan_number_refuse_the_sequence(tmp_path):
    d = make_sequence(tmp_path / "seq")
    (d / "velodyne" / "000001.bin").rename(d / "velodyne" / "1.bin")
    assert len(SemanticKittiSequence(d)) == 3  # a short name alone is scan 1
    make_sequence(tmp_path / "again")
    (tmp_path / "again" / "velodyne" / "000001.bin").replace(d / "velodyne" / "000001.bin")
    with pytest.raises(DatasetError, match=r"velodyne: 000001\.bin and 1\.bin are both scan 1"):
        SemanticKittiSequence(d)


@pytest.mark.parametrize(
    "times,bad,words",
    [
        (["0.0", "0.1", "1e300", "0.3", "0.4"], 2, "time 1e+300 s is not a plausible time"),
        (["0.0", "0.1", "nan", "0.3", "0.4"], 2, "time nan s is not a plausible time"),
        (["0.0", "0.1", "-5", "0.3", "0.4"], 2, "time -5 s is not a plausible time"),
        # one wild but finite time: the map's clock would jump ahead and run back
        (
            ["0.0", "0.1", "1e5", "0.3", "0.4"],
            2,
            "time 100000 s is out of order (scan 1 at 0.1 s and scan 3 at 0.3 s)",
        ),
        # a time earlier than the scans around it
        (["0.0", "0.1", "0.2", "0.05", "0.4"], 3, "time 0.05 s is out of order"),
    ],
    ids=["1e300", "nan", "negative", "wild", "backwards"],
)
def test_a_bad_time_costs_its_scan(tmp_path, times, bad, words):
    d = make_sequence(tmp_path / "seq", n_scans=5)
    (d / "times.txt").write_text("\n".join(times) + "\n")
    seq = SemanticKittiSequence(d)
    with pytest.raises(ScanError) as err:
        seq[bad]
    message = str(err.value)
    assert message.startswith(f"{d / 'times.txt'}:{bad + 1}: ") and words in message, message
    kinds = ["Scan"] * 5
    kinds[bad] = "SkippedScan"
    assert _kinds(seq) == kinds
    stamps = [s.stamp_s for s in seq if not hasattr(s, "reason")]
    assert stamps == sorted(stamps) and max(stamps) <= MAX_TIME_S


@pytest.mark.slow
def test_bad_poses_and_times_through_the_app_cost_their_scans(tmp_path):
    """map_kitti.py on a folder with a scaled pose (scan 1) and a wild time (scan 3): both
    are skipped with their file and line, the rest is mapped, nothing has NaN or inf."""
    seq = tiny_sequence(tmp_path / "08", 5)
    lines = (seq / "poses.txt").read_text().splitlines()
    row = np.array(lines[1].split(), float).reshape(3, 4)
    row[:, :3] *= 1000.0
    lines[1] = _fmt(row.ravel())
    (seq / "poses.txt").write_text("\n".join(lines) + "\n")
    times = (seq / "times.txt").read_text().splitlines()
    times[3] = "1e300"
    (seq / "times.txt").write_text("\n".join(times) + "\n")
    out = tmp_path / "out"
    rc, rec = run_app(["--data", seq, "--out", out, "--no-progress"])
    assert rc == 0, rec.text()
    metrics = json.loads((out / "metrics.json").read_text())
    reasons = {s["index"]: s["reason"] for s in metrics["skipped"]}
    assert sorted(reasons) == [1, 3]
    assert "poses.txt:2: pose 1 is not a pose" in reasons[1] and "scaled by 1000" in reasons[1]
    assert "times.txt:4: time 1e+300 s is not a plausible time" in reasons[3]
    assert metrics["scans"] == 3
    predictions = sorted(p.name for p in (out / "sequences" / "08" / "predictions").iterdir())
    assert predictions == ["000000.label", "000002.label", "000004.label"]
    from tisem.io.mapfile import load_map_file

    snapshot, _, _ = load_map_file(out / "map.npz")
    assert np.isfinite(snapshot.t_last).all() and snapshot.t_last.max() < 10.0
    assert not [r for r in rec.records if r.levelno >= logging.ERROR]


def test_a_blank_line_among_the_poses_is_skipped_and_later_lines_keep_their_numbers(tmp_path):
    """An editor's stray newline is not a pose: the poses after it stay with their own scans,
    and a bad line after it is still named by its place in the file."""
    from tisem.io.kitti_files import read_pose_lines

    row = "1 0 0 0 0 1 0 0 0 0 1 0\n"
    (tmp_path / "poses.txt").write_text(row + "\n" + row.replace(" 0\n", " 5\n") + "x\n")
    poses, problems = read_pose_lines(tmp_path / "poses.txt")
    assert len(poses) == 3
    assert poses[1][0, 3] == 0.0 and poses[1][2, 3] == 5.0
    assert list(problems) == [2] and f"{tmp_path / 'poses.txt'}:4:" in problems[2]
