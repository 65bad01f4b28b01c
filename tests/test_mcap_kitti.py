"""tisem.io.kitti_mcap (apps/kitti_to_mcap.py) and apps/map_mcap.py: a SemanticKITTI sequence
through MCAP gives the same scans (and, end to end, the same predictions and metrics) as reading
the folder."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from tisem.io.kitti_mcap import KittiMcapResult, write_kitti_mcap
from tisem.io.mcap_reader import McapOptions, McapScanReader
from tisem.io.semantickitti import SemanticKittiSequence
from tisem.io.tf import quat_to_matrix
from tisem.labels import raw_to_train

REPO = Path(__file__).resolve().parents[1]


def load_app(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "apps" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def write_tiny_sequence(root: Path, n_scans: int = 3, n_points: int = 400, seed: int = 0) -> Path:
    """A SemanticKITTI folder with exactly orthonormal poses (so MCAP's quaternions are exact)."""
    rng = np.random.default_rng(seed)
    for sub in ("velodyne", "labels", "predictions"):
        (root / sub).mkdir(parents=True)
    Tr = np.eye(4)
    Tr[:3, :3] = quat_to_matrix([0.5, -0.5, 0.5, -0.5])  # velodyne -> camera
    Tr[:3, 3] = [0.01, -0.07, -0.33]
    (root / "calib.txt").write_text("Tr: " + " ".join(f"{v:.17g}" for v in Tr[:3].ravel()) + "\n")
    poses = []
    for k in range(n_scans):
        P = np.eye(4)
        P[:3, :3] = quat_to_matrix([0.0, np.sin(0.01 * k), 0.0, np.cos(0.01 * k)])
        P[:3, 3] = [0.02 * k, 0.0, 0.9 * k]
        poses.append(" ".join(f"{v:.17g}" for v in P[:3].ravel()))
        pts = np.concatenate(
            [
                rng.uniform(-20, 20, (n_points, 2)),
                rng.uniform(-2, 3, (n_points, 1)),
                rng.random((n_points, 1)),
            ],
            1,
        )
        pts.astype("<f4").tofile(root / "velodyne" / f"{k:06d}.bin")
        raw_gt = np.where(pts[:, 2] < -1, 40, np.where(pts[:, 0] > 0, 50, 70)).astype(np.uint32)
        (raw_gt | (rng.integers(0, 3, n_points, dtype=np.uint32) << 16)).astype("<u4").tofile(
            root / "labels" / f"{k:06d}.label"
        )
        pred = np.where(rng.random(n_points) < 0.1, 10, raw_gt).astype("<u4")
        pred.tofile(root / "predictions" / f"{k:06d}.label")
    (root / "poses.txt").write_text("\n".join(poses) + "\n")
    return root


def convert(src: Path, out: Path, **options) -> KittiMcapResult:
    return write_kitti_mcap(src, out, **options)


def assert_same_scans(seq_dir: Path, mcap: Path, pose_tol: float) -> None:
    seq = SemanticKittiSequence(seq_dir)
    reader = McapScanReader(mcap, McapOptions(gt_field="gt_label"))
    assert reader.total == len(seq)
    for a, b in zip(seq, reader):
        assert b.index == a.index and b.stamp_s == pytest.approx(a.stamp_s, abs=1e-9)
        assert np.array_equal(a.points_sensor, b.points_sensor)
        assert np.array_equal(a.labels, b.labels) and np.array_equal(a.gt_labels, b.gt_labels)
        assert np.abs(a.T_world_sensor - b.T_world_sensor).max() < pose_tol


@pytest.mark.parametrize("extra", [{}, {"compression": "lz4", "label_type": "uint16"}])
def test_conversion_round_trips_through_the_reader(tmp_path, extra):
    seq = write_tiny_sequence(tmp_path / "seq")
    info = convert(seq, tmp_path / "out.mcap", **extra)
    assert info.scans == 3 and not info.skipped
    assert_same_scans(seq, tmp_path / "out.mcap", pose_tol=1e-12)
    with open(tmp_path / "out.mcap", "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {
            ch.topic: summary.statistics.channel_message_counts[cid]
            for cid, ch in summary.channels.items()
        }
        compression = {c.compression for c in summary.chunk_indexes}
    assert topics == {"/tf_static": 1, "/tf": 3, "/velodyne_points": 3}
    assert compression == {"lz4" if extra else "zstd"}
    tf = McapScanReader(tmp_path / "out.mcap").tf
    mount = tf.lookup("base_link", "velodyne", 0)
    assert np.abs(mount - np.eye(4)).max() > 0.1  # a real mount, not an identity


def test_argmax_label_files_convert_as_the_raw_ones(tmp_path):
    """Predictions saved as a network's argmax (int64 train ids) convert into a recording whose
    scans read as the uint32 raw files' do."""
    seq = write_tiny_sequence(tmp_path / "seq")
    for path in (seq / "predictions").iterdir():
        raw_to_train(np.fromfile(path, "<u4"))[0].astype(np.int64).tofile(path)
    assert convert(seq, tmp_path / "out.mcap").scans == 3
    assert_same_scans(seq, tmp_path / "out.mcap", pose_tol=1e-12)
    reference = write_tiny_sequence(tmp_path / "raw")
    for a, b in zip(SemanticKittiSequence(reference), SemanticKittiSequence(seq)):
        assert np.array_equal(a.labels, b.labels)
    # the label field holds raw ids, as documented: read as raw ids, the same scans
    as_raw = McapScanReader(tmp_path / "out.mcap", McapOptions(label_space="raw"))
    for a, b in zip(SemanticKittiSequence(reference), as_raw):
        assert np.array_equal(a.labels, b.labels)


def test_stamps_come_from_each_scan_s_entry_of_times_txt(tmp_path):
    """The stamps are times.txt's decimals, entry by entry: past a blank line, and in a
    sequence's extract (scans 1000-1002 with their own three entries)."""
    seq = write_tiny_sequence(tmp_path / "seq")
    # epoch seconds: a float64 holds them to ~0.2 us, the text to the nanosecond
    (seq / "times.txt").write_text(
        "1600000000.000000001\n\n1600000000.100000002\n1600000000.200000003\n"
    )
    for sub in ("velodyne", "labels", "predictions"):
        for k in (2, 1, 0):
            path = seq / sub / f"{k:06d}.{'bin' if sub == 'velodyne' else 'label'}"
            path.rename(path.with_name(f"{1000 + k:06d}{path.suffix}"))
    convert(seq, tmp_path / "out.mcap")
    stamps = [s.source.stamp_ns for s in McapScanReader(tmp_path / "out.mcap")]
    assert stamps == [
        1_600_000_000_000_000_001,
        1_600_000_000_100_000_002,
        1_600_000_000_200_000_003,
    ]


def test_predictions_kept_apart_convert_as_the_folder_s_own(tmp_path):
    """`--predictions DIR` (predictions=): a sequence without predictions/ whose labels lie in
    a folder of their own converts into the recording the whole folder gives."""
    seq = write_tiny_sequence(tmp_path / "seq")
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("velodyne", "labels", "poses.txt", "calib.txt"):
        (bare / name).symlink_to(seq / name)
    load_app("kitti_to_mcap").main(
        [str(bare), "--predictions", str(seq / "predictions"), "--out", str(tmp_path / "a.mcap")]
    )
    assert_same_scans(seq, tmp_path / "a.mcap", pose_tol=1e-12)


def test_app_is_the_library_conversion(tmp_path, capsys):
    seq = write_tiny_sequence(tmp_path / "seq")
    app = load_app("kitti_to_mcap")
    assert (
        app.main(
            [
                str(seq),
                str(tmp_path / "app.mcap"),
                "--compression",
                "lz4",
                "--label-type",
                "uint16",
                "--first",
                "1",
            ]
        )
        == 0
    )
    printed = capsys.readouterr()
    assert "wrote" in printed.out
    assert "kitti-to-mcap" in printed.err and "2/2" in printed.err  # the progress bar
    info = convert(seq, tmp_path / "lib.mcap", compression="lz4", label_type="uint16", first=1)
    assert info.scans == 2
    assert (tmp_path / "app.mcap").read_bytes() == (tmp_path / "lib.mcap").read_bytes()
    assert app.main([str(tmp_path / "missing"), str(tmp_path / "x.mcap")]) == 2
    # --out, as the other commands take the output, writes the same file
    argv = ["--compression", "lz4", "--label-type", "uint16", "--first", "1"]
    assert app.main([str(seq), "--out", str(tmp_path / "opt.mcap"), "--no-progress", *argv]) == 0
    assert (tmp_path / "opt.mcap").read_bytes() == (tmp_path / "lib.mcap").read_bytes()
    assert "kitti-to-mcap" not in capsys.readouterr().err
    for outputs, problem in [
        ([], "no output: give the .mcap file"),
        ([str(tmp_path / "a.mcap"), "--out", str(tmp_path / "b.mcap")], "two outputs"),
    ]:
        with pytest.raises(SystemExit) as stop:
            app.main([str(seq), *outputs])
        assert stop.value.code == 2 and problem in capsys.readouterr().err


def test_real_sequence_round_trips(tmp_path, kitti_mini):
    info = convert(kitti_mini, tmp_path / "08.mcap")
    assert info.scans == 5
    # KITTI's rotations are orthonormal only to ~1e-6; tf carries the nearest rotation
    assert_same_scans(kitti_mini, tmp_path / "08.mcap", pose_tol=2e-6)


@pytest.mark.slow
def test_map_mcap_gives_the_same_predictions_and_metrics_as_map_kitti(tmp_path):
    seq = write_tiny_sequence(tmp_path / "seq", n_scans=3, n_points=3000)
    convert(seq, tmp_path / "seq.mcap")
    # a damaged copy: cut inside the last cloud; the app must still map and say what was lost
    data = (tmp_path / "seq.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: int(len(data) * 0.8)])
    common = ["--arch", "cpu", "--threads", "1", "--no-progress"]
    runs = {
        "kitti": [REPO / "apps" / "map_kitti.py", "--data", seq],
        "mcap": [
            REPO / "apps" / "map_mcap.py",
            tmp_path / "seq.mcap",
            "--gt-field",
            "gt_label",
            "--save-scans",
        ],
        "cut": [REPO / "apps" / "map_mcap.py", tmp_path / "cut.mcap", "--gt-field", "gt_label"],
    }
    out = {}
    for name, args in runs.items():
        done = subprocess.run(
            [sys.executable, *map(str, args), *common, "--out", str(tmp_path / name)],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr[-3000:]
        assert "Traceback" not in done.stderr
        out[name] = done.stdout
    for k in range(3):
        a = np.fromfile(tmp_path / "kitti/sequences/00/predictions" / f"{k:06d}.label", "<u4")
        b = np.fromfile(tmp_path / "mcap/sequences/00/predictions" / f"{k:06d}.label", "<u4")
        assert np.mean(a == b) >= 0.999, k
    ma, mb = (json.loads((tmp_path / n / "metrics.json").read_text()) for n in ("kitti", "mcap"))
    for protocol in ("final", "online", "input"):
        assert mb[protocol]["miou"] == pytest.approx(ma[protocol]["miou"], abs=1e-3)
        assert mb[protocol]["accuracy"] == pytest.approx(ma[protocol]["accuracy"], abs=1e-3)
    assert (tmp_path / "mcap" / "map.mcap").stat().st_size > 1000
    assert "not everything could be used" in out["cut"] and "cut short" in out["cut"]
    report = json.loads((tmp_path / "cut" / "mcap_report.json").read_text())
    # one zstd chunk holds everything: what precedes the cut inflates block by block (128 KiB)
    assert report["damaged"] and 1 <= report["messages"]["/velodyne_points"] <= 2


def test_map_mcap_errors_are_one_line_not_tracebacks(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"garbage")
    done = subprocess.run(
        [
            sys.executable,
            str(REPO / "apps" / "map_mcap.py"),
            str(tmp_path / "x.mcap"),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2 and "not an MCAP file" in done.stderr
    assert "Traceback" not in done.stderr


def test_map_mcap_tells_notes_on_a_whole_recording_from_losses(tmp_path):
    """rosbag2 writes chunks without CRCs: a whole recording read with that note is not one
    that lost something, and the run's closing lines say which it is."""
    from tisem.synth.mcap_log import write_synthetic_log

    def closing(path):
        done = subprocess.run(
            [sys.executable, str(REPO / "apps" / "map_mcap.py"), str(path), "--no-progress"]
            + ["--out", str(tmp_path / path.stem)],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, done.stderr
        return done.stdout

    whole = tmp_path / "whole.mcap"
    write_synthetic_log(whole, n_scans=4, n_points=400, crcs=False, chunk_size=3_000)
    said = closing(whole)
    assert "whole.mcap: read whole, with these notes:" in said and "carry no CRC" in said
    assert "not everything could be used" not in said
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.7)])
    assert "cut.mcap: not everything could be used:" in closing(cut)
