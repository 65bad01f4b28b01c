"""The mapping run and `apps/map_kitti.py` on small SemanticKITTI folders.

A tiny synthetic sequence (`write_semantickitti(..., points_per_ring=128)`) is damaged in
every way a real one can be, one scan per problem, and mapped once through the app's `main`;
the tests then read what came out: exit code, log, metrics.json, predictions.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest
import taichi as ti

from tisem.labels import LEARNING_MAP_INV, raw_to_train
from tisem.report import results_table
from tisem.synth.sequence import write_semantickitti

REPO = Path(__file__).resolve().parents[1]
SUMMARY_KEYS = {"miou", "miou_all", "accuracy", "wiou", "oa_paper", "per_class_iou"}
FAR_POINT = 7  # the point of scan 5 moved 10 km away


def load_app(name: str = "map_kitti"):
    spec = importlib.util.spec_from_file_location(f"{name}_app", REPO / "apps" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class Records(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record):
        self.records.append(record)

    def text(self, min_level=logging.INFO) -> list[str]:
        return [r.getMessage() for r in self.records if r.levelno >= min_level]


def run_app(argv) -> tuple[int, Records]:
    """`apps/map_kitti.py main(argv)` with every log record kept."""
    rec = Records()
    root = logging.getLogger()
    old = root.level
    root.addHandler(rec)
    root.setLevel(logging.INFO)
    try:
        rc = load_app().main([str(a) for a in argv])
    finally:
        root.removeHandler(rec)
        root.setLevel(old)
        ti.reset()  # leave no map behind in the runtime main() started
    return rc, rec


def tiny_sequence(folder: Path, n: int) -> Path:
    write_semantickitti(folder, n, points_per_ring=128, progress=False)
    return folder


def bin_points(seq: Path, i: int) -> int:
    return (seq / "velodyne" / f"{i:06d}.bin").stat().st_size // 16


# --------------------------------------------------------------------------- bad inputs


@pytest.fixture(scope="module")
def damaged(tmp_path_factory):
    """Nine scans, seven of them damaged, mapped once: (seq, out, rc, log records, metrics)."""
    root = tmp_path_factory.mktemp("damaged")
    seq = tiny_sequence(root / "08", 9)
    vel, pred, gt = seq / "velodyne", seq / "predictions", seq / "labels"
    # 1: a .bin whose size is not a multiple of 16
    b = vel / "000001.bin"
    b.write_bytes(b.read_bytes()[:-5])
    # 2: a label file with fewer labels than points
    p = pred / "000002.label"
    p.write_bytes(p.read_bytes()[:-8])
    # 3: NaN / inf coordinates
    pts = np.fromfile(vel / "000003.bin", "<f4").reshape(-1, 4)
    pts[[3, 4, 5], 0] = np.nan
    pts[6, 2] = np.inf
    pts[7, 1] = -np.inf
    pts.tofile(vel / "000003.bin")
    # 4: unknown raw ids in the predictions and the ground truth
    raw = np.fromfile(pred / "000004.label", "<u4")
    raw[:40] = 999
    raw.tofile(pred / "000004.label")
    raw = np.fromfile(gt / "000004.label", "<u4")
    raw[40:50] = 12345
    raw.tofile(gt / "000004.label")
    # 5: a point 10 km away, far outside the map's window (and index range at 0.2 m: 5e4 voxels)
    pts = np.fromfile(vel / "000005.bin", "<f4").reshape(-1, 4)
    pts[FAR_POINT, :3] = [1.0e4, -3.0, 1.0]
    pts.tofile(vel / "000005.bin")
    # 6: an empty scan
    for f in (vel / "000006.bin", pred / "000006.label", gt / "000006.label"):
        f.write_bytes(b"")
    # 8: no pose (poses.txt one line short)
    lines = (seq / "poses.txt").read_text().splitlines()
    (seq / "poses.txt").write_text("\n".join(lines[:8]) + "\n")

    out = root / "out"
    rc, rec = run_app(
        ["--data", seq, "--out", out, "--no-progress", "--arch", "cpu", "--threads", 2]
    )
    metrics = json.loads((out / "metrics.json").read_text()) if rc == 0 else None
    return seq, out, rc, rec, metrics


SKIPPED = {
    1: ("000001.bin", "not a multiple of 16"),
    2: ("000002.label", "label count differs from point count"),
    6: ("000006.bin", "empty scan"),
    8: ("poses.txt", "no pose for scan 8"),
}
MAPPED = [0, 3, 4, 5, 7]


@pytest.mark.slow
def test_bad_scans_are_skipped_and_reported_the_rest_mapped(damaged):
    seq, out, rc, rec, metrics = damaged
    assert rc == 0, rec.text()
    assert metrics["scans"] == len(MAPPED)
    skipped = {s["index"]: s for s in metrics["skipped"]}
    assert sorted(skipped) == sorted(SKIPPED)
    warnings = rec.text(logging.WARNING)
    for i, (fname, problem) in SKIPPED.items():
        reason = skipped[i]["reason"]
        assert fname in reason and problem in reason, reason
        about = [w for w in warnings if re.match(rf"skipped scan {i}\b", w)]
        assert len(about) == 1, f"scan {i} should be reported once, not {len(about)} times"
        assert fname in about[0] and problem in about[0], (
            f"the warning does not name {fname} and '{problem}': {about[0]}"
        )
    # the others are mapped: a predictions file each, raw ids, one label per point
    pred_dir = out / "sequences" / "08" / "predictions"
    assert sorted(p.name for p in pred_dir.iterdir()) == [f"{i:06d}.label" for i in MAPPED]
    for i in MAPPED:
        labels = np.fromfile(pred_dir / f"{i:06d}.label", "<u4")
        assert labels.size == bin_points(seq, i), f"scan {i}: {labels.size} predictions"
        assert np.isin(labels, LEARNING_MAP_INV).all()
        assert (labels > 0).mean() > 0.8, f"scan {i}: too few points in the map"
    far = np.fromfile(pred_dir / "000005.label", "<u4")[FAR_POINT]
    assert far == 0, "the point 10 km away is in no voxel: unlabeled"
    nonfinite = np.fromfile(pred_dir / "000003.label", "<u4")[[3, 4, 5, 6, 7]]
    assert (nonfinite == 0).all(), "the NaN/inf points keep their place, unlabeled"


@pytest.mark.slow
def test_metrics_json_has_every_protocol_and_figure(damaged):
    _, out, rc, _, metrics = damaged
    assert rc == 0
    assert metrics["mode"] == "st"
    assert metrics["seconds_per_scan"] > 0
    assert metrics["active_voxels"] > 1000
    for protocol in ("final", "online", "input"):
        summary = metrics[protocol]
        assert SUMMARY_KEYS <= set(summary), f"{protocol}: {sorted(summary)}"
        for key in SUMMARY_KEYS - {"per_class_iou"}:
            assert 0.0 <= summary[key] <= 1.0, (protocol, key, summary[key])
        assert len(summary["per_class_iou"]) == 19
    assert metrics["final"]["accuracy"] > 0.5


@pytest.mark.slow
def test_relabelled_points_are_counted_from_the_files(damaged):
    """metrics.json says at how many finite points of the mapped scans the final map answers
    another class than the network's labels; recounted here from the written predictions,
    the input's labels and the .bin files (scan 3's NaN points are no measurement)."""
    seq, out, rc, _, metrics = damaged
    assert rc == 0
    points = changed = 0
    for k in MAPPED:
        xyz = np.fromfile(seq / "velodyne" / f"{k:06d}.bin", "<f4").reshape(-1, 4)[:, :3]
        finite = np.isfinite(xyz).all(axis=1)
        net, _ = raw_to_train(np.fromfile(seq / "predictions" / f"{k:06d}.label", "<u4"))
        ours, _ = raw_to_train(
            np.fromfile(out / "sequences" / "08" / "predictions" / f"{k:06d}.label", "<u4")
        )
        points += int(finite.sum())
        changed += int(((net != ours) & finite).sum())
    assert 0 < changed < points
    assert metrics["relabelled"] == {
        "points": points,
        "changed": changed,
        "share": pytest.approx(changed / points),
    }
    assert f"changed the input's label at {changed:,} of {points:,} points" in results_table(
        metrics
    )
    # scan 4's 40 predictions of raw id 999, which the label space has no class for, among
    # every point of the mapped scans (scan 3's 5 non-finite ones too)
    assert metrics["dropped"]["unknown_raw_ids"] == 40
    assert metrics["dropped"]["dropped_nonfinite"] == 5
    share = 100 * 40 / (points + 5)
    assert (
        f"input labels with no class: 40 ({share:.2f} % of the points), no evidence"
        in results_table(metrics)
    )


@pytest.mark.slow
def test_dropped_points_are_reported_with_their_file(damaged):
    """Points dropped from a scan that is still mapped: a message names the scan's file
    (its .bin or .label) and the problem."""
    _, _, rc, rec, _ = damaged
    assert rc == 0
    text = [t.lower() for t in rec.text(logging.INFO)]
    for i, words in (
        (3, ("non-finite", "nan")),
        (4, ("unknown",)),
        (5, ("range", "window", "far", "outside")),
    ):
        assert any(f"{i:06d}." in t and any(w in t for w in words) for t in text), (
            f"nothing in the log says what was dropped from scan {i}"
        )


@pytest.mark.parametrize(
    "damage,fname,problem",
    [
        ("calib_without_tr", "calib.txt", "no 'Tr:' line"),
        ("no_poses", "poses.txt", "poses file not found"),
        ("bad_pose_line", "poses.txt", "malformed pose line"),
    ],
)
def test_whole_sequence_problems_exit_2_with_one_line(tmp_path, damage, fname, problem):
    seq = tiny_sequence(tmp_path / "08", 1)
    if damage == "calib_without_tr":
        text = (seq / "calib.txt").read_text()
        (seq / "calib.txt").write_text(
            "".join(line + "\n" for line in text.splitlines() if not line.startswith("Tr:"))
        )
    elif damage == "no_poses":
        (seq / "poses.txt").unlink()
    else:
        (seq / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    rc, rec = run_app(["--data", seq, "--out", tmp_path / "out", "--no-progress"])
    assert rc == 2
    errors = [r for r in rec.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1, [r.getMessage() for r in errors]
    msg = errors[0].getMessage()
    assert "\n" not in msg and fname in msg and problem in msg, msg
    assert errors[0].exc_info is None, "a one-line error, not a traceback"
    assert not (tmp_path / "out" / "metrics.json").exists()


@pytest.mark.parametrize(
    "app,argv,flag",
    [
        ("map_kitti", ["--resume", "r", "--input", "labels"], "--input"),
        ("map_kitti", ["--resume", "r", "--label-space", "raw"], "--label-space"),
        ("map_kitti", ["--resume", "r", "--predictions", "p"], "--predictions"),
        ("map_kitti", ["--resume", "r", "--set", "tau_s=1"], "--set"),
        ("map_mcap", ["--resume", "r", "--topic", "/points"], "--topic"),
        ("map_mcap", ["--resume", "r", "--mode", "csm", "--label-space", "train"], "--label-space"),
    ],
)
def test_resume_refuses_options_the_checkpoint_holds(app, argv, flag, capsys):
    """A resumed run goes on with the config and input it started with: overriding them is a
    usage error (exit status 2) that names the option, before anything is read."""
    with pytest.raises(SystemExit) as exit_:
        load_app(app).parse_args(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "--resume" in err and flag in err


# --------------------------------------------------------------------------- embedded default


@pytest.mark.slow
def test_embedded_default_beats_the_network_input(tmp_path, monkeypatch):
    """`python apps/map_kitti.py --arch cpu --synthetic-scans 6 --out DIR --no-progress`."""
    out = tmp_path / "run"
    monkeypatch.setenv("TISEM_CACHE_DIR", str(tmp_path / "cache"))
    rc, rec = run_app(["--arch", "cpu", "--synthetic-scans", 6, "--out", out, "--no-progress"])
    assert rc == 0, rec.text()
    m = json.loads((out / "metrics.json").read_text())
    assert m["mode"] == "st" and m["scans"] == 6 and m["skipped"] == []
    # the synthetic labels err like the real network's (persistent, coherent patches), so a
    # few scans gain about what the five real frames do (+1.3 pp), not more
    assert m["final"]["accuracy"] > m["input"]["accuracy"] + 0.01, (m["final"], m["input"])
    assert m["final"]["miou"] > m["input"]["miou"]
    assert m["online"]["accuracy"] > m["input"]["accuracy"]
    seq = Path(json.loads((out / "run.json").read_text())["data"])
    assert seq.parent == tmp_path / "cache"  # the street is cached, not in the results
    pred = out / "sequences" / "00" / "predictions"
    for i in range(6):
        labels = np.fromfile(pred / f"{i:06d}.label", "<u4")
        assert labels.size == bin_points(seq, i)
    assert (out / "map.npz").is_file() and (out / "config.yaml").is_file()
