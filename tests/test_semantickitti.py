"""tisem.io.semantickitti: pose maths, the real mini sequence, every bad input, the writer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tisem.errors import DatasetError, ScanError, SkippedScan
from tisem.io.semantickitti import (
    SemanticKittiSequence,
    camera_poses_to_lidar,
    read_calib_tr,
    read_poses,
    write_predictions,
)
from tisem.labels import LEARNING_MAP_INV, holds_train_ids, raw_to_train
from tisem.scan import Scan, finite_rows

# A KITTI-like calibration: camera x = -lidar y, camera y = -lidar z, camera z = lidar x,
# plus a small lever arm t = (0, -0.08, -0.27).
TR_ROWS = [0, -1, 0, 0.0, 0, 0, -1, -0.08, 1, 0, 0, -0.27]
IDENTITY_ROWS = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]


def _fmt(values) -> str:
    return " ".join(f"{v:.12e}" for v in values)


# ----------------------------------------------------------------------------- pose maths


def test_pose_maths_hand_example(tmp_path):
    (tmp_path / "calib.txt").write_text("P0: " + _fmt(range(12)) + "\nTr: " + _fmt(TR_ROWS) + "\n")
    # Pose: camera rotated 90 deg about its y axis, R_y = [[0,0,1],[0,1,0],[-1,0,0]],
    # and moved 2 m along camera z.
    pose_rows = [0, 0, 1, 0, 0, 1, 0, 0, -1, 0, 0, 2]
    (tmp_path / "poses.txt").write_text(_fmt(IDENTITY_ROWS) + "\n" + _fmt(pose_rows) + "\n\n")
    Tr = read_calib_tr(tmp_path / "calib.txt")
    poses = read_poses(tmp_path / "poses.txt")
    assert Tr.shape == (4, 4) and poses.shape == (2, 4, 4)
    np.testing.assert_array_equal(Tr[3], [0, 0, 0, 1])
    T = camera_poses_to_lidar(poses, Tr)
    assert T.shape == (2, 4, 4) and T.dtype == np.float64
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-12)  # identity stays identity
    # Lidar point p = (1, 2, 3), by hand:
    #   Tr p          = R p + t = (-2, -3, 1) + (0, -0.08, -0.27) = (-2, -3.08, 0.73)
    #   pose (Tr p)   = R_y q + (0,0,2) = (q_z, q_y, -q_x) + (0,0,2) = (0.73, -3.08, 4)
    #   Tr^-1 (...)   = R^T (q - t) = R^T (0.73, -3.0, 4.27) = (v_z, -v_x, -v_y) = (4.27, -0.73, 3)
    np.testing.assert_allclose(T[1] @ [1, 2, 3, 1], [4.27, -0.73, 3.0, 1.0], atol=1e-12)
    # The whole matrix: a -90 deg yaw about lidar z and (2.27, 0.27, 0) m of translation.
    np.testing.assert_allclose(
        T[1], [[0, 1, 0, 2.27], [-1, 0, 0, 0.27], [0, 0, 1, 0], [0, 0, 0, 1]], atol=1e-12
    )
    # single pose and 3x4 input work too
    np.testing.assert_allclose(camera_poses_to_lidar(poses[1, :3], Tr), T[1], atol=1e-12)


def test_pose_helper_errors(tmp_path):
    calib = tmp_path / "calib.txt"
    with pytest.raises(DatasetError, match="calib.txt: calibration file not found"):
        read_calib_tr(calib)
    calib.write_text("P0: " + _fmt(range(12)) + "\n")
    with pytest.raises(DatasetError, match=r"calib.txt: no 'Tr:' line"):
        read_calib_tr(calib)
    calib.write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(
        DatasetError,
        match=r"calib.txt:1: malformed 'Tr:' line, expected 12 numbers"
        r".*got 11",
    ):
        read_calib_tr(calib)
    calib.write_text("P0: 1\nTr: 1 0 0 0 0 1 0 0 0 0 x 0\n")
    with pytest.raises(DatasetError, match=r"calib.txt:2: malformed 'Tr:' line, non-numeric"):
        read_calib_tr(calib)
    poses = tmp_path / "poses.txt"
    poses.write_text(_fmt(IDENTITY_ROWS) + "\n" + _fmt(IDENTITY_ROWS[:9]) + "\n")
    with pytest.raises(
        DatasetError,
        match=r"poses.txt:2: malformed pose line \(pose 1\), expected "
        r"12 numbers.*got 9",
    ):
        read_poses(poses)
    poses.write_text(_fmt(IDENTITY_ROWS) + "\n1 0 0 0 0 1 0 0 0 0 1 abc\n")
    with pytest.raises(DatasetError, match=r"poses.txt:2: malformed pose line.*non-numeric"):
        read_poses(poses)
    poses.write_text("1 0 0 nan 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match=r"poses.txt:1: pose 0 has NaN/inf"):
        read_poses(poses)


# ----------------------------------------------------------------------------- real data


def test_real_mini_sequence(kitti_mini):
    seq = SemanticKittiSequence(kitti_mini)
    assert len(seq) == 5 and seq.scan_ids == [0, 1, 2, 3, 4]
    assert seq.has_ground_truth and seq.sequence_name == "00"  # folder name is not two digits
    assert seq.poses_lidar.shape == (5, 4, 4) and seq.poses_lidar.dtype == np.float64
    np.testing.assert_allclose(seq.times, [0, 0.1, 0.2, 0.3, 0.4])
    # the first pose is the identity; the car drives ~3 m forward (lidar x) over the 5 scans
    np.testing.assert_allclose(seq.poses_lidar[0], np.eye(4), atol=1e-6)
    assert 2.5 < seq.poses_lidar[4, 0, 3] < 3.5 and abs(seq.poses_lidar[4, 2, 3]) < 0.2
    scans = list(seq)
    assert all(isinstance(s, Scan) for s in scans)
    for s in scans:
        assert 122_856 <= s.num_points <= 123_433
        assert s.labels.dtype == np.int32 and s.gt_labels.shape == s.labels.shape
        assert s.labels.min() >= 1 and s.labels.max() <= 19  # predictions never 0
        assert s.source.unknown_raw_ids == 0 and finite_rows(s.points_sensor).all()
        assert Path(s.name).name == f"{s.index:06d}.bin"
    assert sum(s.num_points for s in scans) == 615_906
    # frame range and `input=labels`
    sub = SemanticKittiSequence(kitti_mini, input="labels", first=1, last=3, sequence="08")
    assert sub.scan_ids == [1, 2, 3] and len(sub) == 3 and sub.sequence_name == "08"
    assert sub[0].index == 1 and sub[-1].index == 3
    np.testing.assert_array_equal(sub[0].labels, sub[0].gt_labels)
    np.testing.assert_array_equal(sub[0].gt_labels, scans[1].gt_labels)
    np.testing.assert_array_equal(sub.poses_lidar, seq.poses_lidar[1:4])
    with pytest.raises(IndexError):
        sub[3]


# ----------------------------------------------------------------------------- synthetic


def make_sequence(
    folder: Path,
    n_scans: int = 3,
    n_points: int = 50,
    *,
    gt: bool = True,
    predictions: bool = True,
    n_poses: int | None = None,
    seed: int = 0,
) -> Path:
    """A small, valid SemanticKITTI sequence folder; tests then break one thing in it."""
    rng = np.random.default_rng(seed)
    for sub in ["velodyne"] + (["labels"] if gt else []) + (["predictions"] if predictions else []):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    (folder / "calib.txt").write_text("P0: " + _fmt(range(12)) + "\nTr: " + _fmt(TR_ROWS) + "\n")
    lines = []
    for i in range(n_scans if n_poses is None else n_poses):
        row = list(IDENTITY_ROWS)
        row[11] = float(i)  # camera z forward, 1 m per scan
        lines.append(_fmt(row))
    (folder / "poses.txt").write_text("\n".join(lines) + "\n")
    for i in range(n_scans):
        pts = np.concatenate([rng.uniform(-10, 10, (n_points, 3)), rng.random((n_points, 1))], 1)
        pts.astype("<f4").tofile(folder / "velodyne" / f"{i:06d}.bin")
        train = rng.integers(1, 20, n_points)
        raw = LEARNING_MAP_INV[train] | (np.uint32(7) << 16)  # instance bits set
        if gt:
            raw.astype("<u4").tofile(folder / "labels" / f"{i:06d}.label")
        if predictions:
            LEARNING_MAP_INV[train].astype("<u4").tofile(folder / "predictions" / f"{i:06d}.label")
    return folder


def _kinds(seq):
    return [type(s).__name__ for s in seq]


def test_synthetic_sequence_good(tmp_path):
    seq = SemanticKittiSequence(make_sequence(tmp_path / "17"))
    assert seq.sequence_name == "17" and len(seq) == 3 and seq.has_ground_truth
    s = seq[1]
    assert s.num_points == 50 and s.index == 1 and s.stamp_s == pytest.approx(0.1)
    np.testing.assert_array_equal(s.labels, s.gt_labels)  # instance bits stripped
    # pose 1: camera moved 1 m along camera z = lidar x
    np.testing.assert_allclose(s.T_world_sensor[:3, 3], [1, 0, 0], atol=1e-12)
    (tmp_path / "17" / "times.txt").write_text("5.0\n5.2\n5.4\n")
    np.testing.assert_allclose(SemanticKittiSequence(tmp_path / "17").times, [5.0, 5.2, 5.4])


def test_a_range_past_the_last_scan_says_where_it_stops(tmp_path, caplog):
    """--last 499 on a folder of three scans maps what there is, and says so."""
    folder = make_sequence(tmp_path / "17")
    with caplog.at_level("WARNING"):
        seq = SemanticKittiSequence(folder, first=1, last=499)
    assert seq.scan_ids == [1, 2]
    (line,) = [r.getMessage() for r in caplog.records if "last=" in r.getMessage()]
    assert line.endswith("last=499 is past the folder's last scan (2): scans 1..2 are mapped")
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert SemanticKittiSequence(folder, first=1, last=2).scan_ids == [1, 2]
    assert not [r for r in caplog.records if "last=" in r.getMessage()]


def test_truncated_bin_is_skipped_and_iteration_goes_on(tmp_path):
    d = make_sequence(tmp_path / "seq")
    bin1 = d / "velodyne" / "000001.bin"
    bin1.write_bytes(bin1.read_bytes()[:-5])
    seq = SemanticKittiSequence(d)
    with pytest.raises(
        ScanError,
        match=r"000001\.bin: truncated scan file \(795 bytes is not a "
        r"multiple of 16",
    ) as ei:
        seq[1]
    assert ei.value.index == 1 and ei.value.name.endswith("000001.bin")
    items = list(seq)
    assert _kinds(items) == ["Scan", "SkippedScan", "Scan"]
    assert isinstance(items[1], SkippedScan)
    assert items[1].index == 1 and "truncated" in items[1].reason
    assert items[1].name.endswith("000001.bin") and items[2].index == 2


def test_label_count_mismatch(tmp_path):
    d = make_sequence(tmp_path / "seq")
    lab = d / "predictions" / "000000.label"
    lab.write_bytes(lab.read_bytes()[:-8])
    seq = SemanticKittiSequence(d)
    with pytest.raises(
        ScanError,
        match=r"predictions/000000\.label: label count differs from "
        r"point count: 48 labels for 50 points",
    ):
        seq[0]
    # the GT file too
    gt = d / "labels" / "000002.label"
    gt.write_bytes(gt.read_bytes() + b"\0\0\0\0")
    with pytest.raises(ScanError, match=r"labels/000002\.label: label count.*51 labels for 50"):
        seq[2]
    assert _kinds(seq) == ["SkippedScan", "Scan", "SkippedScan"]
    # a label file whose size is not a multiple of 4 bytes
    lab.write_bytes(b"\0" * 10)
    with pytest.raises(ScanError, match=r"000000\.label: truncated label file \(10 bytes"):
        seq[0]


def test_int64_label_files_are_read_cut_ones_refused(tmp_path, caplog):
    """A label file of int64 labels (a network's argmax saved as it is) gives the labels uint32
    files give, with one warning per folder. Of twice the size with values past uint32's range
    (two files end to end), or of half the size (a uint32 file cut, or 16-bit labels), it is
    the count error: read so, either would give the scan garbage labels."""
    reference = list(SemanticKittiSequence(make_sequence(tmp_path / "ref")))
    d = make_sequence(tmp_path / "seq")
    for path in (d / "predictions").iterdir():
        np.fromfile(path, "<u4").astype(np.int64).tofile(path)
    with caplog.at_level("WARNING"):
        scans = list(SemanticKittiSequence(d))
    said = [
        r.getMessage() for r in caplog.records if "not SemanticKITTI's uint32" in r.getMessage()
    ]
    assert len(said) == 1 and "000000.label: this predictions file holds 64-bit integers" in said[0]
    for s, r in zip(scans, reference):
        np.testing.assert_array_equal(s.labels, r.labels)
    doubled = d / "predictions" / "000001.label"
    raw = np.fromfile(tmp_path / "ref" / "predictions" / "000001.label", "<u4")
    np.concatenate([raw, raw]).tofile(doubled)
    half = d / "predictions" / "000002.label"
    raw.astype("<u2").tofile(half)
    seq = SemanticKittiSequence(d)
    with pytest.raises(ScanError, match=r"000001\.label: label count differs.*100 labels for 50"):
        seq[1]
    with pytest.raises(ScanError, match=r"000002\.label: label count differs.*25 labels for 50"):
        seq[2]


def test_missing_label_file(tmp_path):
    d = make_sequence(tmp_path / "seq")
    (d / "predictions" / "000001.label").unlink()
    seq = SemanticKittiSequence(d)
    with pytest.raises(
        ScanError,
        match=r"predictions/000001\.label: predictions label file "
        r"missing for scan 1",
    ):
        seq[1]
    assert _kinds(seq) == ["Scan", "SkippedScan", "Scan"]
    (d / "labels" / "000002.label").unlink()
    with pytest.raises(ScanError, match=r"labels/000002\.label: ground-truth label file missing"):
        SemanticKittiSequence(d)[2]


def test_short_poses_file(tmp_path):
    d = make_sequence(tmp_path / "seq", n_scans=4, n_poses=2)
    seq = SemanticKittiSequence(d)
    assert seq.num_poses == 2 and list(seq.has_pose) == [True, True, False, False]
    assert np.isnan(seq.poses_lidar[2]).all()
    with pytest.raises(
        ScanError,
        match=r"poses\.txt: no pose for scan 2 \(000002\.bin\); "
        r"poses\.txt has 2 poses",
    ):
        seq[2]
    items = list(seq)
    assert _kinds(items) == ["Scan", "Scan", "SkippedScan", "SkippedScan"]
    assert "has 2 poses" in items[3].reason


def test_short_times_file(tmp_path):
    d = make_sequence(tmp_path / "seq")
    (d / "times.txt").write_text("0.0\n0.1\n")
    seq = SemanticKittiSequence(d)
    assert np.isnan(seq.times[2])
    with pytest.raises(
        ScanError, match=r"times\.txt: no time for scan 2; times\.txt has 2 entries"
    ):
        seq[2]
    assert _kinds(seq) == ["Scan", "Scan", "SkippedScan"]
    (d / "times.txt").write_text("0.0\nabc\n0.2\n")
    with pytest.raises(ScanError, match=r"times\.txt:2: malformed time line"):
        SemanticKittiSequence(d)[1]
    assert _kinds(SemanticKittiSequence(d)) == ["Scan", "SkippedScan", "Scan"]


def test_real_labels_are_told_from_train_ids(kitti_mini):
    """Every real scan's predictions and ground truth (instance bits) are raw ids; the same
    predictions after the learning map are train ids; so are no ids of a scan of vehicles
    (raw ids below 20, all known) or of an unlabeled one."""
    for k in range(5):
        pred = np.fromfile(kitti_mini / "predictions" / f"{k:06d}.label", "<u4")
        gt = np.fromfile(kitti_mini / "labels" / f"{k:06d}.label", "<u4")
        assert not holds_train_ids(pred) and not holds_train_ids(gt)
        assert holds_train_ids(raw_to_train(pred)[0])
    assert not holds_train_ids(np.array([0, 1, 10, 11, 13, 15, 16, 18], np.uint32))
    assert not holds_train_ids(np.zeros(100, np.uint32))
    assert not holds_train_ids(np.array([9, 40], np.uint32))  # road as raw: 40 is no train id


def test_train_id_label_files_read_as_train_ids(tmp_path, caplog):
    """Label files saved as train ids (a network's argmax without the inverse learning map)
    give the scans the raw files give, with one warning per folder; "raw" reads them as raw
    ids, most of them unknown, as before."""
    raw_seq = SemanticKittiSequence(make_sequence(tmp_path / "raw"))
    d = make_sequence(tmp_path / "train")
    for sub in ("predictions", "labels"):
        for path in (d / sub).iterdir():
            raw_to_train(np.fromfile(path, "<u4"))[0].astype("<u4").tofile(path)
    with caplog.at_level("WARNING"):
        seq = SemanticKittiSequence(d)
        scans = list(seq)
    assert seq.train_ids.sources == {"predictions": 3, "labels": 3}
    said = [r.getMessage() for r in caplog.records if "train ids, not raw" in r.getMessage()]
    assert len(said) == 2 and "train/predictions/000000.label: the predictions are" in said[0]
    for s, r in zip(scans, raw_seq):
        np.testing.assert_array_equal(s.labels, r.labels)
        np.testing.assert_array_equal(s.gt_labels, r.gt_labels)
        assert s.source.unknown_raw_ids == 0
    as_raw = SemanticKittiSequence(d, label_space="raw")[0]
    assert as_raw.source.unknown_raw_ids > 0
    assert not np.array_equal(as_raw.labels, raw_seq[0].labels)
    with pytest.raises(ValueError, match="label_space must be one of"):
        SemanticKittiSequence(d, label_space="ids")


def _write_predictions(folder: Path, files: list[list[int]]) -> None:
    for k, values in enumerate(files):
        path = folder / "predictions" / f"{k:06d}.label"
        np.resize(np.array(values, "<u4"), 50 if values else 0).tofile(path)


def test_a_scan_that_fits_both_spaces_follows_its_folder(tmp_path):
    """Train ids of a scan without any class only train ids name (car 1, sidewalk 11,
    building 13: raw ids too) are read in the space of the folder's first file that fits only
    one, whatever was read before them and whatever range is mapped; as raw ids where no file
    fits only one."""
    d = make_sequence(tmp_path / "seq")
    as_train, as_raw = [1, 11, 13], raw_to_train(np.array([1, 11, 13]))[0].tolist()
    _write_predictions(d, [[1, 11, 13], [9, 1, 11], [1, 11, 13]])  # scan 0 before the road
    seq = SemanticKittiSequence(d)
    scans = list(seq)
    assert scans[0].labels.tolist()[:3] == as_train
    assert scans[2].labels.tolist()[:3] == as_train
    assert seq.train_ids.sources == {"predictions": 3}
    assert SemanticKittiSequence(d)[2].labels.tolist()[:3] == as_train  # read first
    assert SemanticKittiSequence(d, first=2)[0].labels.tolist()[:3] == as_train  # out of range
    _write_predictions(d, [[1, 11, 13], [1, 11, 13], [40, 10, 48]])  # road as raw id 40
    assert SemanticKittiSequence(d)[0].labels.tolist()[:3] == as_raw
    _write_predictions(d, [[1, 11, 13], [1, 11, 13], [0, 1]])  # none fits one space only
    assert SemanticKittiSequence(d)[1].labels.tolist()[:3] == as_raw
    assert SemanticKittiSequence(d, label_space="train")[0].labels.tolist()[:3] == as_train
    # an empty scan (skipped) decides nothing: the next file does
    _write_predictions(d, [[], [9, 1, 11], [1, 11, 13]])
    (d / "velodyne" / "000000.bin").write_bytes(b"")
    assert SemanticKittiSequence(d)[2].labels.tolist()[:3] == as_train


def _renumber(folder: Path, ids: list[int]) -> None:
    """Give the folder's scans (000000, 000001, ...) the numbers `ids`, in order, as a
    sequence's extract keeps them."""
    for sub in ("velodyne", "labels", "predictions"):
        files = sorted((folder / sub).iterdir())
        for path, sid in zip(files, ids):
            path.rename(path.with_name(f"tmp_{sid:06d}{path.suffix}"))
        for path in (folder / sub).iterdir():
            path.rename(path.with_name(path.name[len("tmp_") :]))


def test_an_extract_pairs_its_own_poses_and_times_in_order(tmp_path, caplog):
    """Scans 1000, 1001 and 1005 of a sequence, carried with their three poses and times: every
    number lies past the files' ends, so the k-th entry is the k-th scan's, and a log line
    says so; the scans read as the same folder numbered 0-2 does."""
    whole = SemanticKittiSequence(make_sequence(tmp_path / "whole"))
    d = make_sequence(tmp_path / "extract")
    (d / "times.txt").write_text("100.0\n100.1\n100.5\n")
    _renumber(d, [1000, 1001, 1005])
    with caplog.at_level("WARNING"):
        seq = SemanticKittiSequence(d)
    assert seq.scan_ids == [1000, 1001, 1005] and list(seq.has_pose) == [True] * 3
    assert len(seq.entry_notes) == 2 and "scan 1000 takes the first entry" in caplog.text
    assert seq.reading_notes == seq.entry_notes
    assert "poses.txt: 3 entries for the 3 scans 1000..1005" in seq.entry_notes[0]
    assert "times.txt: 3 entries" in seq.entry_notes[1]
    for k in range(3):
        np.testing.assert_array_equal(seq[k].T_world_sensor, whole[k].T_world_sensor)
        np.testing.assert_array_equal(seq[k].points_sensor, whole[k].points_sensor)
    assert [seq[k].stamp_s for k in range(3)] == [100.0, 100.1, 100.5]
    # a time out of order is named by its line of the extract's file
    (d / "times.txt").write_text("100.0\n105.0\n100.5\n")
    with pytest.raises(ScanError, match=r"times\.txt:2: time 105 s is out of order"):
        SemanticKittiSequence(d)[1]
    # a selected range keeps each scan's entry: its place in the folder, not in the range
    tail = SemanticKittiSequence(d, first=1001)
    np.testing.assert_array_equal(tail[1].T_world_sensor, whole[2].T_world_sensor)
    assert tail[1].stamp_s == 100.5


@pytest.mark.parametrize(
    "ids, n_poses, skipped",
    [
        ([0, 1, 3, 4], 4, [4]),  # a scan file missing and the file a pose short
        ([3, 4, 5, 6], 4, [4, 5, 6]),  # some numbers within the file: by number
        ([1000, 1001, 1002, 1003], 3, [1000, 1001, 1002, 1003]),  # one pose short
    ],
)
def test_other_mismatches_keep_pairing_by_number(tmp_path, ids, n_poses, skipped):
    """Pairing in order only where every scan is numbered past the file's end and the file holds
    exactly one entry per scan: after a gap it would give each scan its neighbour's pose."""
    d = make_sequence(tmp_path / "seq", n_scans=len(ids), n_poses=n_poses)
    _renumber(d, ids)
    seq = SemanticKittiSequence(d)
    assert seq.entry_notes == []
    items = list(seq)
    assert [s.index for s in items if isinstance(s, SkippedScan)] == skipped
    for s in items:
        if isinstance(s, Scan):  # pose i moves 1 m along lidar x: scan i's, by its number
            np.testing.assert_allclose(s.T_world_sensor[:3, 3], [s.index, 0, 0], atol=1e-12)


def test_missing_poses_and_calib(tmp_path):
    d = make_sequence(tmp_path / "seq")
    (d / "poses.txt").unlink()
    with pytest.raises(DatasetError, match=r"seq/poses\.txt: poses file not found"):
        SemanticKittiSequence(d)
    d2 = make_sequence(tmp_path / "seq2")
    (d2 / "calib.txt").write_text("P0: " + _fmt(range(12)) + "\n")
    with pytest.raises(DatasetError, match=r"seq2/calib\.txt: no 'Tr:' line"):
        SemanticKittiSequence(d2)
    (d2 / "calib.txt").unlink()
    with pytest.raises(DatasetError, match=r"seq2/calib\.txt: calibration file not found"):
        SemanticKittiSequence(d2)
    d3 = make_sequence(tmp_path / "seq3", n_scans=4)
    lines = (d3 / "poses.txt").read_text().splitlines()
    (d3 / "poses.txt").write_text("\n".join(lines[:3] + ["1 2 3"]) + "\n")
    with pytest.raises(ScanError, match=r"poses\.txt:4: malformed pose line \(pose 3\).*got 3"):
        SemanticKittiSequence(d3)[3]
    assert _kinds(SemanticKittiSequence(d3)) == ["Scan", "Scan", "Scan", "SkippedScan"]


def test_nonfinite_points_kept_in_place_for_the_mapper(tmp_path):
    """The reader keeps every point of the file (the predictions file holds one label per
    point); which ones are non-finite is decided by one rule, `finite_rows`, that the mapper
    drops them by and the evaluation ignores them by."""
    d = make_sequence(tmp_path / "seq")
    path = d / "velodyne" / "000000.bin"
    pts = np.fromfile(path, "<f4").reshape(-1, 4)
    pts[3, 0] = np.nan
    pts[10, 2] = np.inf
    pts[11, 1] = -np.inf
    pts[20, 3] = np.nan  # NaN remission only: the point is finite
    pts.tofile(path)
    gt_as_input = SemanticKittiSequence(d, input="labels")
    s = SemanticKittiSequence(d)[0]
    keep = np.ones(50, bool)
    keep[[3, 10, 11]] = False
    assert s.num_points == 50
    np.testing.assert_array_equal(finite_rows(s.points_sensor), keep)
    raw = np.fromfile(d / "predictions" / "000000.label", "<u4")
    np.testing.assert_array_equal(s.labels, raw_to_train(raw)[0])
    np.testing.assert_array_equal(s.gt_labels, s.labels)
    np.testing.assert_array_equal(s.points_sensor[keep], pts[keep, :3])
    np.testing.assert_array_equal(finite_rows(gt_as_input[0].points_sensor), keep)
    # every point non-finite: a ScanError, the others still load
    pts[:, 1] = np.nan
    pts.tofile(path)
    seq = SemanticKittiSequence(d)
    with pytest.raises(ScanError, match=r"000000\.bin: all 50 points are non-finite"):
        seq[0]
    assert _kinds(seq) == ["SkippedScan", "Scan", "Scan"]


def test_unknown_raw_ids_map_to_zero_and_are_counted(tmp_path):
    d = make_sequence(tmp_path / "seq")
    lab = d / "predictions" / "000000.label"
    raw = np.fromfile(lab, "<u4")
    raw[:4] = [2, 999, 65535, (5 << 16) | 12345]
    raw.tofile(lab)
    s = SemanticKittiSequence(d)[0]
    assert s.source.unknown_raw_ids == 4 and s.source.unknown_gt_ids == 0
    np.testing.assert_array_equal(s.labels[:4], 0)
    assert (s.labels[4:] > 0).all()


def test_empty_scan(tmp_path):
    d = make_sequence(tmp_path / "seq")
    (d / "velodyne" / "000001.bin").write_bytes(b"")
    (d / "labels" / "000001.label").write_bytes(b"")
    (d / "predictions" / "000001.label").write_bytes(b"")
    seq = SemanticKittiSequence(d)
    with pytest.raises(ScanError, match=r"000001\.bin: empty scan \(0 points\)"):
        seq[1]
    assert _kinds(seq) == ["Scan", "SkippedScan", "Scan"]


def test_dataset_root_and_folder_errors(tmp_path):
    root = tmp_path / "kitti"
    make_sequence(root / "sequences" / "08")
    make_sequence(root / "sequences" / "11", n_scans=2)
    with pytest.raises(
        DatasetError,
        match=r"kitti: is a dataset root; choose a sequence.*found: "
        r"08, 11",
    ):
        SemanticKittiSequence(root)
    seq = SemanticKittiSequence(root, sequence=8)
    assert seq.sequence_name == "08" and seq.sequence_dir == root / "sequences" / "08"
    assert len(SemanticKittiSequence(root, sequence="11")) == 2
    with pytest.raises(DatasetError, match=r"sequences/05: no such sequence.*found: 08, 11"):
        SemanticKittiSequence(root, sequence="05")
    with pytest.raises(DatasetError, match=r"nope: folder does not exist"):
        SemanticKittiSequence(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"empty: no velodyne/ folder"):
        SemanticKittiSequence(tmp_path / "empty")
    # missing input folder
    d = make_sequence(tmp_path / "nopred", predictions=False)
    with pytest.raises(
        DatasetError,
        match=r"nopred/predictions: input label folder missing "
        r"\(input='predictions'\)",
    ):
        SemanticKittiSequence(d)
    seq = SemanticKittiSequence(d, input="labels")  # GT as input still works
    assert seq[0].labels is not None
    with pytest.raises(ValueError, match="input must be one of"):
        SemanticKittiSequence(d, input="probs")
    # no GT: gt_labels None, has_ground_truth False
    d = make_sequence(tmp_path / "nogt", gt=False)
    seq = SemanticKittiSequence(d)
    assert not seq.has_ground_truth and seq[0].gt_labels is None
    # empty frame range
    with pytest.raises(
        DatasetError,
        match=r"velodyne: empty frame range first=5 last=9; scans "
        r"present: 0\.\.2",
    ):
        SemanticKittiSequence(d, first=5, last=9)
    for f in (d / "velodyne").iterdir():
        f.unlink()
    with pytest.raises(DatasetError, match=r"velodyne: no NNNNNN\.bin scans"):
        SemanticKittiSequence(d)


# ----------------------------------------------------------------------------- writer


def test_write_predictions_round_trip(tmp_path):
    d = make_sequence(tmp_path / "in", n_scans=2)
    seq = SemanticKittiSequence(d, sequence="08")
    out = tmp_path / "out"
    for scan in seq:
        path = write_predictions(out, seq.sequence_name, scan.index, scan.labels)
        assert path == out / "sequences" / "08" / "predictions" / f"{scan.index:06d}.label"
        raw = np.fromfile(path, "<u4")
        assert raw.dtype == np.uint32 and raw.size == scan.num_points
        np.testing.assert_array_equal(raw, LEARNING_MAP_INV[scan.labels])
    # reading the written predictions back gives the same train ids
    import shutil

    for sub in ("velodyne", "labels"):
        shutil.copytree(d / sub, out / "sequences" / "08" / sub)
    shutil.copy(d / "calib.txt", out / "sequences" / "08")
    shutil.copy(d / "poses.txt", out / "sequences" / "08")
    back = SemanticKittiSequence(out, sequence="08")
    for a, b in zip(seq, back):
        np.testing.assert_array_equal(a.labels, b.labels)
    assert not list((out / "sequences" / "08" / "predictions").glob("*.tmp"))
    # train id 0 is written as raw 0; out-of-range train ids are refused
    p = write_predictions(out, 8, 7, np.array([0, 1, 19]))
    np.testing.assert_array_equal(np.fromfile(p, "<u4"), [0, 10, 81])
    with pytest.raises(ValueError, match="train ids"):
        write_predictions(out, 8, 7, np.array([20]))
