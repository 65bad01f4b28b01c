"""Own data in: the KITTI odometry layout, --poses trajectories (KITTI and TUM), a label space
from a YAML file, and what a missing predictions/ folder suggests."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest
import taichi as ti
import yaml

from tisem.errors import DatasetError
from tisem.io.kitti_files import read_trajectory
from tisem.io.semantickitti import SemanticKittiSequence
from tisem.io.tf import matrix_to_quat
from tisem.label_space import load_label_space
from tisem.labels import (
    CLASS_COLORS_RGB,
    CLASS_NAMES,
    LEARNING_MAP,
    LEARNING_MAP_INV,
    raw_to_train,
    train_to_raw,
    use_label_space,
)
from tisem.synth.sequence import write_semantickitti

REPO = Path(__file__).resolve().parents[1]
# five classes: the synthetic street's cars, road, buildings and vegetation, the rest unlabeled
FIVE = {
    "labels": {0: "unlabeled", 10: "car", 40: "road", 50: "building", 70: "vegetation"},
    "color_map": {
        0: [0, 0, 0],
        10: [245, 150, 100],
        40: [255, 0, 255],
        50: [0, 200, 255],
        70: [0, 175, 0],
    },
    "learning_map": {**{raw: 0 for raw in LEARNING_MAP}, 10: 1, 40: 2, 50: 3, 70: 4},
}


def map_kitti():
    spec = importlib.util.spec_from_file_location("map_kitti_app", REPO / "apps" / "map_kitti.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_map_kitti(argv) -> int:
    try:
        return map_kitti().main([str(a) for a in argv])
    finally:
        ti.reset()


def lidar_trajectory(path: Path, poses: np.ndarray, fmt: str, stamps=None) -> Path:
    if fmt == "kitti":
        path.write_text("".join(" ".join(f"{v:.17g}" for v in T[:3].ravel()) + "\n" for T in poses))
    else:
        lines = ["# timestamp tx ty tz qx qy qz qw"]
        for t, T in zip(stamps, poses):
            values = [t, *T[:3, 3], *matrix_to_quat(T[:3, :3])]
            lines.append(" ".join(f"{v:.17g}" for v in values))
        path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def street(tmp_path_factory) -> Path:
    return write_semantickitti(
        tmp_path_factory.mktemp("street") / "seq", 3, points_per_ring=128, progress=False
    )


# --------------------------------------------------------------------------- poses


def test_odometry_layout_reads_dataset_poses(kitti_mini, tmp_path):
    """dataset/poses/08.txt beside dataset/sequences/08/ (no poses.txt) gives the poses."""
    seq_dir = tmp_path / "dataset" / "sequences" / "08"
    seq_dir.mkdir(parents=True)
    for name in ("velodyne", "labels", "predictions", "calib.txt"):
        (seq_dir / name).symlink_to(kitti_mini / name)
    (tmp_path / "dataset" / "poses").mkdir()
    (tmp_path / "dataset" / "poses" / "08.txt").write_text((kitti_mini / "poses.txt").read_text())
    ours = SemanticKittiSequence(tmp_path / "dataset", sequence="08")
    theirs = SemanticKittiSequence(kitti_mini)
    assert ours.poses_file == tmp_path / "dataset" / "poses" / "08.txt"
    np.testing.assert_array_equal(ours.poses_lidar, theirs.poses_lidar)


def test_missing_poses_name_both_places_and_the_option(street, tmp_path):
    seq_dir = tmp_path / "dataset" / "sequences" / "00"
    seq_dir.mkdir(parents=True)
    for name in ("velodyne", "labels", "predictions", "calib.txt"):
        (seq_dir / name).symlink_to(street / name)
    with pytest.raises(DatasetError, match=r"poses/00\.txt.*--poses FILE"):
        SemanticKittiSequence(tmp_path / "dataset", sequence="00")


@pytest.mark.parametrize("fmt", ["kitti", "tum"])
def test_lidar_trajectory_replaces_poses_and_calibration(street, tmp_path, fmt):
    """--poses: LiDAR poses as given (calib.txt not needed); TUM stamps become the times."""
    reference = SemanticKittiSequence(street)
    seq_dir = tmp_path / "seq"
    seq_dir.mkdir()
    for name in ("velodyne", "labels", "predictions"):
        (seq_dir / name).symlink_to(street / name)
    stamps = 1.7e9 + 0.1 * np.arange(len(reference))
    path = lidar_trajectory(tmp_path / f"traj.{fmt}", reference.poses_lidar, fmt, stamps)
    seq = SemanticKittiSequence(seq_dir, poses=path)
    np.testing.assert_allclose(seq.poses_lidar, reference.poses_lidar, atol=1e-9)
    if fmt == "tum":
        np.testing.assert_array_equal(seq.times, stamps)
    np.testing.assert_array_equal(seq[1].points_sensor, reference[1].points_sensor)


@pytest.mark.parametrize(
    "text, problem",
    [
        ("1 2 3\n", r"traj\.txt:1: 3 numbers"),
        ("0 1 2 3 0 0 0 0\n", r"traj\.txt:1: expected 8 finite numbers"),
        ("0 1 2 3 0 0 0 1\n0 1 nan 3 0 0 0 1\n", r"traj\.txt:2: expected 8 finite"),
    ],
)
def test_bad_trajectory_lines_name_file_and_line(tmp_path, text, problem):
    path = tmp_path / "traj.txt"
    path.write_text(text)
    try:
        _, _, problems = read_trajectory(path)
    except DatasetError as exc:
        message = str(exc)
    else:
        message = problems[min(problems)]
    assert re.search(problem, message), message


def test_missing_predictions_suggest_input_labels(street, tmp_path):
    seq_dir = tmp_path / "seq"
    seq_dir.mkdir()
    for name in ("velodyne", "labels", "poses.txt", "calib.txt"):
        (seq_dir / name).symlink_to(street / name)
    with pytest.raises(
        DatasetError,
        match=r"predictions: input label folder missing.*--predictions DIR.*--input "
        r"labels",
    ):
        SemanticKittiSequence(seq_dir)


def _without_predictions(street: Path, folder: Path) -> Path:
    folder.mkdir(parents=True)
    for name in ("velodyne", "labels", "poses.txt", "calib.txt"):
        (folder / name).symlink_to(street / name)
    return folder


def test_predictions_from_another_folder_or_a_prediction_root(street, tmp_path):
    """`predictions=`: a folder of .label files, or a semantic-kitti-api style root holding
    sequences/NN/predictions: the scans are the ones the sequence's own predictions/ give."""
    own = list(SemanticKittiSequence(street))
    seq_dir = _without_predictions(street, tmp_path / "data" / "17")
    flat = tmp_path / "flat"
    flat.symlink_to(street / "predictions")
    root = tmp_path / "run"
    (root / "sequences" / "17").mkdir(parents=True)
    (root / "sequences" / "17" / "predictions").symlink_to(street / "predictions")
    for given in (flat, root):
        seq = SemanticKittiSequence(seq_dir, predictions=given)
        assert seq.input_dir.samefile(street / "predictions")
        for a, b in zip(seq, own):
            np.testing.assert_array_equal(a.labels, b.labels)
            np.testing.assert_array_equal(a.gt_labels, b.gt_labels)
    with pytest.raises(
        DatasetError,
        match=r"sequences/18/predictions: no predictions of "
        r"sequence 18 under this prediction root; it has 17",
    ):
        SemanticKittiSequence(seq_dir, sequence="18", predictions=root)
    with pytest.raises(DatasetError, match=r"nowhere: predictions folder does not exist"):
        SemanticKittiSequence(seq_dir, predictions=tmp_path / "nowhere")


def test_a_run_records_how_it_read_the_labels(street, tmp_path):
    """Predictions saved as a network's argmax (int64 train ids): the run maps them as the
    raw files, and metrics.json says how they were read (the warning lines); --label-space
    raw reads them as raw ids (most unknown), and run.json keeps it."""
    seq_dir = _without_predictions(street, tmp_path / "17")
    (seq_dir / "predictions").mkdir()
    for path in (street / "predictions").iterdir():
        train = raw_to_train(np.fromfile(path, "<u4"))[0]
        train.astype(np.int64).tofile(seq_dir / "predictions" / path.name)
    runs = {}
    for name, data, extra in (
        ("raw", street, []),
        ("argmax", seq_dir, []),
        ("as_raw", seq_dir, ["--label-space", "raw"]),
    ):
        argv = ["--data", data, "--no-progress", "--out", tmp_path / name, *extra]
        assert run_map_kitti(argv) == 0
        runs[name] = json.loads((tmp_path / name / "metrics.json").read_text())
    assert runs["argmax"]["final"] == runs["raw"]["final"] and "input_read" not in runs["raw"]
    read = runs["argmax"]["input_read"]
    assert len(read) == 2 and "holds 64-bit integers" in read[0] and "are train ids" in read[1]
    assert len(runs["as_raw"]["input_read"]) == 1 and runs["as_raw"]["dropped"]["unknown_raw_ids"]
    assert runs["as_raw"]["final"]["accuracy"] < runs["raw"]["final"]["accuracy"]
    assert json.loads((tmp_path / "as_raw" / "run.json").read_text())["label_space"] == "raw"


def test_map_kitti_predictions_option(street, tmp_path, caplog):
    """--predictions feeds the map from another folder, which run.json keeps for render;
    with --input labels or without --data it is refused in one line."""
    seq_dir = _without_predictions(street, tmp_path / "17")
    out = tmp_path / "out"
    preds = street / "predictions"
    argv = ["--data", seq_dir, "--predictions", preds, "--no-progress", "--out"]
    assert run_map_kitti([*argv, out]) == 0
    run = json.loads((out / "run.json").read_text())
    assert Path(run["predictions"]) == preds.resolve()
    assert len(list((out / "sequences" / "17" / "predictions").iterdir())) == 3
    # render finds the network's labels where the run took them (the data folder has none)
    from tisem.viz.compare import render_comparison

    drawn = render_comparison(out)
    assert drawn["accuracy"]["network"] is not None and drawn["scans"] == [0, 1, 2]
    for extra, problem in (
        (["--input", "labels"], "the map is fed the ground truth"),
        ([], None),
    ):
        caplog.clear()
        if problem is None:  # no --data: the synthetic street
            rc = run_map_kitti(["--predictions", preds, "--out", tmp_path / "o2"])
            problem = "give the sequence they belong to with --data"
        else:
            rc = run_map_kitti([*argv, tmp_path / "o1", *extra])
        assert rc != 0
        errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
        assert len(errors) == 1 and f"--predictions {preds}: {problem}" in errors[0]


# --------------------------------------------------------------------------- label space


def test_label_space_from_yaml(tmp_path):
    path = tmp_path / "five.yaml"
    path.write_text(yaml.safe_dump(FIVE))
    space = load_label_space(path)
    assert space.num_classes == 5
    assert space.names == ("unlabeled", "car", "road", "building", "vegetation")
    np.testing.assert_array_equal(space.colors_rgb[1], [100, 150, 245])  # BGR -> RGB
    np.testing.assert_array_equal(space.learning_map_inv, [0, 10, 40, 50, 70])
    use_label_space(space)
    try:
        train, unknown = raw_to_train(np.array([10, 40, 48, 70 | (3 << 16), 7]))
        np.testing.assert_array_equal(train, [1, 2, 0, 4, 0])
        assert unknown == 1  # raw id 7 is in no map
        np.testing.assert_array_equal(train_to_raw(np.array([4, 1])), [70, 10])
    finally:
        use_label_space(None)
    assert raw_to_train(np.array([40]))[0][0] == 9  # SemanticKITTI's again


# semantic-kitti.yaml's `color_map` (BGR) for the raw id of each train id, as published
KITTI_COLOR_MAP_BGR = {
    0: [0, 0, 0],
    10: [245, 150, 100],
    11: [245, 230, 100],
    15: [150, 60, 30],
    18: [180, 30, 80],
    20: [255, 0, 0],
    30: [30, 30, 255],
    31: [200, 40, 255],
    32: [90, 30, 150],
    40: [255, 0, 255],
    44: [255, 150, 255],
    48: [75, 0, 75],
    49: [75, 0, 175],
    50: [0, 200, 255],
    51: [50, 120, 255],
    70: [0, 175, 0],
    71: [0, 60, 135],
    72: [80, 240, 150],
    80: [150, 240, 255],
    81: [0, 0, 255],
}


def test_builtin_classes_are_semantic_kitti_yaml(tmp_path):
    """The built-in names and colours (maps, PLY, MCAP, pictures) are what semantic-kitti.yaml
    gives, read through the same loader as a user's class file: a colour converted by hand
    from BGR once gave other-vehicle traffic-sign's red."""
    path = tmp_path / "semantic-kitti.yaml"
    raw_ids = [int(r) for r in LEARNING_MAP_INV]
    path.write_text(
        yaml.safe_dump(
            {
                "labels": dict(zip(raw_ids, CLASS_NAMES)),
                "color_map": KITTI_COLOR_MAP_BGR,
                "learning_map": dict(LEARNING_MAP),
                "learning_map_inv": dict(enumerate(raw_ids)),
            }
        )
    )
    space = load_label_space(path)
    assert space.names == CLASS_NAMES
    for train, name in enumerate(CLASS_NAMES):
        assert tuple(CLASS_COLORS_RGB[train]) == tuple(space.colors_rgb[train]), name


@pytest.mark.parametrize(
    "change, problem",
    [
        ({"learning_map": {0: 0, 10: 2}}, r"maps no raw id to train ids \[1\]"),
        ({"labels": {0: "unlabeled"}}, r"'labels' has no name for raw id 10"),
        ({"color_map": {0: [0, 0, 0], 10: [1, 2]}}, r"colour of raw id 10"),
        ({"learning_map": "car"}, r"'learning_map' must be a mapping"),
    ],
)
def test_bad_label_space_is_one_line_naming_the_key(tmp_path, change, problem):
    data = {
        "labels": {0: "unlabeled", 10: "car"},
        "color_map": {0: [0, 0, 0], 10: [1, 2, 3]},
        "learning_map": {0: 0, 10: 1},
        **change,
    }
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match=problem):
        load_label_space(path)


@pytest.mark.slow
def test_map_kitti_with_own_classes_and_poses(street, tmp_path, capsys):
    """A five-class label space, the ground truth as input, a TUM trajectory: the run scores
    five classes, writes raw ids of the YAML and says 'labels (input)'."""
    classes = tmp_path / "five.yaml"
    classes.write_text(yaml.safe_dump(FIVE))
    reference = SemanticKittiSequence(street)
    poses = lidar_trajectory(
        tmp_path / "traj.tum", reference.poses_lidar, "tum", 0.1 * np.arange(len(reference))
    )
    out = tmp_path / "run"
    assert (
        run_map_kitti(
            [
                "--data",
                street,
                "--classes",
                classes,
                "--poses",
                poses,
                "--input",
                "labels",
                "--out",
                out,
                "--no-progress",
                "--per-class",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "| labels (input) " in printed and "IoU per class" in printed
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["final"]["per_class_iou"]) == {"car", "road", "building", "vegetation"}
    assert metrics["config"]["mapper"]["num_classes"] == 5
    raw = np.fromfile(out / "sequences" / "00" / "predictions" / "000001.label", "<u4")
    assert set(np.unique(raw)) <= {0, 10, 40, 50, 70}
    run = json.loads((out / "run.json").read_text())
    assert Path(run["classes"]) == classes.resolve() and Path(run["poses"]) == poses.resolve()
    assert raw_to_train(np.array([40]))[0][0] == 9  # the run's space is undone


def test_num_classes_that_disagrees_with_classes_is_refused(street, tmp_path, caplog):
    classes = tmp_path / "five.yaml"
    classes.write_text(yaml.safe_dump(FIVE))
    rc = run_map_kitti(
        [
            "--data",
            street,
            "--classes",
            classes,
            "--set",
            "num_classes=20",
            "--out",
            tmp_path / "run",
            "--no-progress",
        ]
    )
    assert rc == 2 and "defines 5 classes" in caplog.text
    assert not (tmp_path / "run").exists()
