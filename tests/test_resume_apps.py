"""Both map apps interrupted and resumed, each run in its own process (as a real resume is):
the same predictions, metrics and map as an uninterrupted run. Scans are the small synthetic
streets of test_checkpoint.py, written as a SemanticKITTI folder (and converted to MCAP)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_checkpoint import assert_same_map, comparable_metrics, make_scans

from tisem.checkpoint import load_checkpoint
from tisem.io import mapfile
from tisem.io.kitti_mcap import write_kitti_mcap

REPO = Path(__file__).resolve().parents[1]
MAPPER_YAML = "max_range_m: 20\nwindow_xy_m: 30\nwindow_z_m: 12\nmin_z_m: -4\nmax_z_m: 4\n"


def write_kitti(folder: Path, scans) -> Path:
    """A SemanticKITTI sequence folder with the given scans (identity Tr, raw ids)."""
    from tisem.labels import LEARNING_MAP_INV

    for sub in ("velodyne", "labels", "predictions"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    (folder / "calib.txt").write_text("Tr: " + " ".join(map(str, np.eye(4)[:3].ravel())) + "\n")
    poses, times = [], []
    for s in scans:
        name = f"{s.index:06d}"
        pts = np.column_stack([s.points_sensor, np.zeros(s.num_points)]).astype("<f4")
        pts.tofile(folder / "velodyne" / f"{name}.bin")
        LEARNING_MAP_INV[s.gt_labels].astype("<u4").tofile(folder / "labels" / f"{name}.label")
        LEARNING_MAP_INV[s.labels].astype("<u4").tofile(folder / "predictions" / f"{name}.label")
        poses.append(" ".join(f"{v:.12e}" for v in s.T_world_sensor[:3].ravel()))
        times.append(f"{s.stamp_s:.6e}")
    (folder / "poses.txt").write_text("\n".join(poses) + "\n")
    (folder / "times.txt").write_text("\n".join(times) + "\n")
    return folder


def run_app(name: str, *args, cwd: Path) -> subprocess.CompletedProcess:
    """`python apps/<name>.py --no-progress ARGS` in its own process; it must succeed."""
    done = subprocess.run(
        [sys.executable, str(REPO / "apps" / f"{name}.py"), "--no-progress", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    return done


def assert_same_results(part: Path, full: Path) -> None:
    """The resumed run's folder holds what the uninterrupted one's does: the same figures in
    metrics.json (timings aside; of the config, the mapper's: the resumed run was given a
    longer frame range), byte-identical predictions, the same map."""
    m_full, m_part = (json.loads((d / "metrics.json").read_text()) for d in (full, part))
    assert m_full["evaluated"]
    assert {k: v for k, v in comparable_metrics(m_part).items() if k != "config"} == {
        k: v for k, v in comparable_metrics(m_full).items() if k != "config"
    }
    assert m_part["config"]["mapper"] == m_full["config"]["mapper"]
    names = sorted(p.relative_to(full) for p in full.glob("sequences/*/predictions/*.label"))
    assert len(names) == m_full["scans"]
    assert names == sorted(p.relative_to(part) for p in part.glob("sequences/*/predictions/*"))
    for name in names:
        assert (part / name).read_bytes() == (full / name).read_bytes(), name
    assert_same_map(
        mapfile.load_map_file(part / "map.npz")[0], mapfile.load_map_file(full / "map.npz")[0]
    )


@pytest.mark.slow
def test_map_kitti_checkpoint_and_resume(tmp_path):
    data = write_kitti(tmp_path / "08", make_scans(5, points=1500, seed=6))
    (tmp_path / "mapper.yaml").write_text(MAPPER_YAML)
    common = ["--threads", 2, "--config", tmp_path / "mapper.yaml", "--data", data]
    run_app("map_kitti", *common, "--out", tmp_path / "full", cwd=tmp_path)
    # the "crashed" run got to scan 2; the resumed one is told to go on to the end
    run_app(
        "map_kitti",
        *common,
        "--out",
        tmp_path / "part",
        "--last",
        2,
        "--checkpoint-every",
        3,
        cwd=tmp_path,
    )
    assert load_checkpoint(tmp_path / "part").last_index == 2
    run_app("map_kitti", "--resume", tmp_path / "part" / "checkpoint", "--last", 4, cwd=tmp_path)
    assert_same_results(tmp_path / "part", tmp_path / "full")


@pytest.mark.slow
def test_map_mcap_checkpoint_and_resume(tmp_path):
    """The resumed run is given neither the recording nor its options: it reads them from the
    checkpoint."""
    data = write_kitti(tmp_path / "08", make_scans(5, points=1500, seed=7))
    recording = tmp_path / "drive.mcap"
    write_kitti_mcap(data, recording)
    (tmp_path / "mapper.yaml").write_text(MAPPER_YAML)
    common = [
        recording,
        "--gt-field",
        "gt_label",
        "--threads",
        2,
        "--config",
        tmp_path / "mapper.yaml",
    ]
    run_app("map_mcap", *common, "--out", tmp_path / "full", cwd=tmp_path)
    run_app(
        "map_mcap",
        *common,
        "--out",
        tmp_path / "part",
        "--last",
        2,
        "--checkpoint-every",
        3,
        cwd=tmp_path,
    )
    assert load_checkpoint(tmp_path / "part").last_index == 2
    run_app("map_mcap", "--resume", tmp_path / "part", "--last", 4, cwd=tmp_path)
    assert_same_results(tmp_path / "part", tmp_path / "full")
    assert (tmp_path / "part" / "map.mcap").stat().st_size > 1000
