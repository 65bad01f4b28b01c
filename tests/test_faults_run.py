"""The run around the map when something goes wrong: refused scans scored nowhere, one outlier
pose costing one scan, output folders, Ctrl-C, full disks, leftover temp files, checkpoints
that do not fit together, and each skipped scan reported once.

Library runs use the small synthetic streets of test_checkpoint.py; app runs the tiny
SemanticKITTI folders of test_pipeline.py, through `main(argv)` (a full disk: in a process
of its own, whose file-size limit makes writes fail as a full disk does).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import resource
import signal
import subprocess
import sys

import numpy as np
import pytest
from helpers import fresh_runtime
from test_checkpoint import comparable_metrics, make_scans, run_config
from test_faults_config import run_app_named
from test_pipeline import REPO, load_app, run_app, tiny_sequence

from tisem.checkpoint import load_checkpoint
from tisem.errors import RunInterrupted
from tisem.io import mapfile
from tisem.io.kitti_mcap import write_kitti_mcap
from tisem.run import MappingRun

FAR_M = 300e3  # a plausible place, 300 km from the drive


def moved(scan, dx_m: float):
    T = scan.T_world_sensor.copy()
    T[0, 3] += dx_m
    return dataclasses.replace(scan, T_world_sensor=T)


def predictions(out, sequence="00") -> list[int]:
    folder = out / "sequences" / sequence / "predictions"
    return sorted(int(p.stem) for p in folder.glob("*.label"))


def errors_of(rec) -> list[logging.LogRecord]:
    return [r for r in rec.records if r.levelno >= logging.ERROR]


# --------------------------------------------------------------------------- refused scans


@pytest.mark.slow
@pytest.mark.parametrize("stream", ["sequence", "iterator"])
def test_refused_scans_are_scored_in_no_row(taichi_cpu, tmp_path, stream):
    """A scan the mapper refuses (train ids out of range) and one the pose gate refuses (300
    km away): neither is scored, by any protocol, nor has a predictions file; metrics.json
    says why. The final pass reads a sequence again, or keeps an iterator's scans."""
    scans = make_scans(6, points=1500, seed=3)
    scans[2] = dataclasses.replace(scans[2], labels=np.full(scans[2].num_points, 25))
    scans[4] = moved(scans[4], FAR_M)
    source = scans if stream == "sequence" else iter(scans)
    result = MappingRun(source, run_config(), tmp_path).run(
        show_progress=False, write_map_files=False
    )
    m = result.metrics
    reasons = {s["index"]: s["reason"] for s in m["skipped"]}
    assert sorted(reasons) == [2, 4]
    assert "train ids must be whole numbers in [0, 20)" in reasons[2]
    assert reasons[4].startswith("pose outlier: the sensor is 300 km from scan ")
    mapped = [0, 1, 3, 5]
    points = sum(int((scans[i].gt_labels > 0).sum()) for i in mapped)
    assert m["input"]["points"] == m["online"]["points"] == m["final"]["points"] == points
    assert m["scans"] == len(mapped) and predictions(tmp_path) == mapped
    assert [result.is_mapped(i) for i in range(6)] == [i in mapped for i in range(6)]


# --------------------------------------------------------------------------- outlier poses


@pytest.mark.slow
@pytest.mark.parametrize("where", [0, 1, 3], ids=["first", "second", "middle"])
def test_one_outlier_pose_costs_one_scan(taichi_cpu, tmp_path, where):
    scans = make_scans(6, points=1500, seed=5)
    scans[where] = moved(scans[where], FAR_M)
    result = MappingRun(scans, run_config(), tmp_path).run(
        show_progress=False, write_map_files=False
    )
    assert [s.index for s in result.skipped] == [where]
    assert result.metrics["scans"] == 5
    # the map's origin came from the drive, not from the outlier
    assert np.abs(result.trajectory).max() < 100
    assert result.metrics["final"]["accuracy"] > 0.8


@pytest.mark.slow
def test_an_outlier_first_pose_through_the_app(tmp_path):
    seq = tiny_sequence(tmp_path / "08", 4)
    lines = (seq / "poses.txt").read_text().splitlines()
    row = np.array(lines[0].split(), float)
    row[11] += FAR_M  # camera z: the drive's forward axis
    lines[0] = " ".join(f"{v:.12e}" for v in row)
    (seq / "poses.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    rc, rec = run_app(["--data", seq, "--out", out, "--no-progress"])
    assert rc == 0, rec.text()
    metrics = json.loads((out / "metrics.json").read_text())
    assert [s["index"] for s in metrics["skipped"]] == [0]
    assert "pose outlier" in metrics["skipped"][0]["reason"]
    assert metrics["scans"] == 3 and predictions(out, "08") == [1, 2, 3]


# --------------------------------------------------------------------------- output folders


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "results" / "old").mkdir(parents=True)
    os.symlink("old", tmp_path / "results" / "latest")
    return tmp_path


@pytest.mark.slow
def test_a_failed_run_creates_nothing_and_a_good_one_repoints_latest(workdir):
    rc, rec = run_app(["--data", workdir / "no-such-folder", "--no-progress"])
    assert rc == 2 and len(errors_of(rec)) == 1
    assert sorted(p.name for p in (workdir / "results").iterdir()) == ["latest", "old"]
    assert os.readlink(workdir / "results" / "latest") == "old"
    # every scan skipped: nothing to map, nothing written, latest untouched
    seq = tiny_sequence(workdir / "seq", 2)
    (seq / "poses.txt").write_text("1 0 0\n1 0 0\n")
    rc, rec = run_app(["--data", seq, "--no-progress"])
    assert rc == 2
    assert "no scan could be mapped: all 2 were skipped" in errors_of(rec)[0].getMessage()
    assert sorted(p.name for p in (workdir / "results").iterdir()) == ["latest", "old"]
    seq = tiny_sequence(workdir / "good", 1)
    rc, rec = run_app(["--data", seq, "--no-progress"])
    assert rc == 0, rec.text()
    new = [p for p in (workdir / "results").iterdir() if p.name not in ("latest", "old")]
    assert len(new) == 1 and os.readlink(workdir / "results" / "latest") == new[0].name
    assert (new[0] / "metrics.json").is_file()


@pytest.mark.slow
def test_a_non_empty_out_is_refused_unless_overwrite_clears_a_previous_run(tmp_path):
    seq = tiny_sequence(tmp_path / "00", 2)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    rc, rec = run_app(["--data", seq, "--out", out, "--no-progress"])
    assert rc == 2 and "the folder is not empty (notes.txt)" in errors_of(rec)[0].getMessage()
    rc, rec = run_app(["--data", seq, "--out", out, "--no-progress", "--overwrite"])
    assert rc == 2 and "holds no tisem results" in errors_of(rec)[0].getMessage()
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    # a previous run's folder, with an old sequence's predictions beside it
    (out / "notes.txt").unlink()
    rc, _ = run_app(["--data", seq, "--out", out, "--no-progress", "--checkpoint-every", "1"])
    assert rc == 0
    stale = out / "sequences" / "08" / "predictions"
    stale.mkdir(parents=True)
    (stale / "000000.label").write_bytes(b"\0" * 8)
    (out / "notes.txt").write_text("mine")
    rc, rec = run_app(["--data", seq, "--out", out, "--no-progress"])
    assert rc == 2 and "--overwrite" in errors_of(rec)[0].getMessage()
    rc, rec = run_app(["--data", seq, "--out", out, "--no-progress", "--overwrite"])
    assert rc == 0, rec.text()
    assert not (out / "sequences" / "08").exists() and not (out / "checkpoint").exists()
    assert (out / "notes.txt").read_text() == "mine"
    assert predictions(out) == [0, 1]


def test_make_synthetic_refuses_or_replaces_an_existing_sequence(tmp_path):
    app = load_app("make_synthetic")
    out = tmp_path / "seq"
    common = ["--out", str(out), "--points-per-ring", "32", "--no-progress"]
    assert app.main(common + ["--scans", "3"]) == 0
    assert app.main(common + ["--scans", "2"]) == 2
    assert len(list((out / "velodyne").iterdir())) == 3
    (out / "notes.txt").write_text("mine")
    assert app.main(common + ["--scans", "2", "--overwrite"]) == 0
    for sub in ("velodyne", "labels", "predictions"):
        assert sorted(p.stem for p in (out / sub).iterdir()) == ["000000", "000001"]
    assert len((out / "poses.txt").read_text().splitlines()) == 2
    assert (out / "notes.txt").read_text() == "mine"


# --------------------------------------------------------------------------- Ctrl-C


def ctrl_c_after(position: int):
    """An on_scan that presses Ctrl-C (a real SIGINT) once scan `position` is mapped."""

    def press(mapper, scan, k):
        if k == position:
            os.kill(os.getpid(), signal.SIGINT)

    return press


@pytest.mark.slow
def test_ctrl_c_stops_at_a_scan_boundary_and_the_run_resumes(taichi_cpu, tmp_path):
    scans = make_scans(5, points=1500, seed=8)
    cfg = run_config()
    full = MappingRun(scans, cfg, tmp_path / "full").run(show_progress=False, write_map_files=False)
    full_metrics = comparable_metrics(full.metrics)

    fresh_runtime()
    out = tmp_path / "run"
    handler = signal.getsignal(signal.SIGINT)
    with pytest.raises(RunInterrupted) as stop:
        MappingRun(scans, cfg, out, checkpoint_every=10).run(
            show_progress=False, on_scan=ctrl_c_after(1)
        )
    assert str(stop.value) == f"interrupted after scan 1; continue with --resume {out}"
    assert signal.getsignal(signal.SIGINT) is handler  # the handler is given back
    assert load_checkpoint(out).last_index == 1  # saved on the way out
    assert not (out / "metrics.json").exists()

    fresh_runtime()
    resumed = MappingRun.resume(scans, out).run(show_progress=False, write_map_files=False)
    assert comparable_metrics(resumed.metrics) == full_metrics
    assert predictions(out) == [0, 1, 2, 3, 4]


@pytest.mark.slow
def test_ctrl_c_in_the_app_exits_130_with_one_line(tmp_path, monkeypatch):
    seq = tiny_sequence(tmp_path / "00", 3)
    run = MappingRun.run

    def run_with_ctrl_c(self, **options):
        return run(self, **{**options, "on_scan": ctrl_c_after(0)})

    monkeypatch.setattr(MappingRun, "run", run_with_ctrl_c)
    for extra, said in (
        (["--checkpoint-every", "5"], "continue with --resume"),
        ([], "nothing to resume from"),
    ):
        out = tmp_path / f"out{len(extra)}"
        rc, rec = run_app(["--data", seq, "--out", out, "--no-progress", *extra])
        assert rc == 130
        errors = errors_of(rec)
        assert len(errors) == 1 and errors[0].exc_info is None
        assert errors[0].getMessage().startswith("interrupted after scan 0; ")
        assert said in errors[0].getMessage()
    monkeypatch.undo()
    rc, rec = run_app(["--resume", tmp_path / "out2", "--no-progress"])
    assert rc == 0, rec.text()
    assert predictions(tmp_path / "out2") == [0, 1, 2]


# --------------------------------------------------------------------------- full disks


def run_with_file_limit(limit_bytes: int, *args) -> subprocess.CompletedProcess:
    """`apps/map_kitti.py ARGS` in a process that may write no file beyond `limit_bytes`:
    a write past it fails (EFBIG) as a write to a full disk does (ENOSPC)."""

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return subprocess.run(
        [sys.executable, str(REPO / "apps" / "map_kitti.py"), "--no-progress", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=600,
        preexec_fn=limit,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
    )


def error_lines(done: subprocess.CompletedProcess) -> list[str]:
    assert "Traceback" not in done.stderr, done.stderr
    return [line for line in done.stderr.splitlines() if line.startswith("ERROR")]


@pytest.mark.slow
def test_a_full_disk_while_checkpointing_keeps_the_previous_checkpoint(tmp_path):
    """The first checkpoint (~1.6 MB) fits, the second (~2.7 MB) does not."""
    seq = tiny_sequence(tmp_path / "00", 4)
    out = tmp_path / "out"
    done = run_with_file_limit(2_100_000, "--data", seq, "--out", out, "--checkpoint-every", 2)
    assert done.returncode == 1, done.stderr
    lines = error_lines(done)
    assert len(lines) == 1 and f"cannot write the checkpoint in {out}" in lines[0], lines
    assert f"the checkpoint of scan 1 is kept: continue with --resume {out}" in lines[0]
    assert load_checkpoint(out).last_index == 1
    assert sorted(p.name for p in (out / "checkpoint").iterdir()) == ["checkpoint.npz"]
    rc, rec = run_app(["--resume", out, "--no-progress"])
    assert rc == 0, rec.text()
    assert predictions(out) == [0, 1, 2, 3]


@pytest.mark.slow
def test_a_full_spill_folder_ends_the_run_with_what_could_be_written(tmp_path):
    """A small live window makes the store spill; its file outgrows the limit mid-run."""
    seq = tiny_sequence(tmp_path / "00", 40)
    spill = tmp_path / "spill"
    spill.mkdir()
    out = tmp_path / "out"
    done = run_with_file_limit(
        300_000,
        "--data",
        seq,
        "--out",
        out,
        "--set",
        "max_range_m=20",
        "--set",
        "window_xy_m=24",
        "--set",
        "window_z_m=12",
        "--set",  # (a band the 12 m window holds with the kernel's reach)
        "min_z_m=-4",
        "--set",
        "max_z_m=8",
        "--set",
        f"store_dir={spill}",
    )
    assert done.returncode == 1, done.stderr
    lines = error_lines(done)
    assert len(lines) == 1, lines
    assert "mapping had stopped at scan" in lines[0] or "mapping stopped at scan" in lines[0]
    assert f"could not write its spill file in {spill}" in lines[0]
    metrics = json.loads((out / "metrics.json").read_text())
    assert "spill file" in metrics["stopped"]
    assert 0 < metrics["scans"] < 40 and predictions(out) == list(range(metrics["scans"]))


# --------------------------------------------------------------------------- checkpoints


@pytest.fixture(scope="module")
def good_checkpoint(tmp_path_factory):
    """A checkpoint of 3 small scans, and a way to write a changed copy of it."""
    fresh_runtime()
    out = tmp_path_factory.mktemp("ckpt")
    MappingRun(make_scans(3, points=1000, seed=9), run_config(), out, checkpoint_every=3).run(
        show_progress=False, write_map_files=False
    )
    return out / "checkpoint" / mapfile.CHECKPOINT_NAME


def damaged_copy(good, folder, meta=None, **arrays):
    """The checkpoint with some arrays replaced and `meta(dict)` applied to its meta; its
    CRCs are right (np.savez writes them), its contents are not."""
    with np.load(good) as npz:
        data = {k: npz[k] for k in npz.files}
    data.update(arrays)
    if meta is not None:
        m = json.loads(str(data["meta_json"]))
        meta(m)
        data["meta_json"] = np.array(json.dumps(m))
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / mapfile.CHECKPOINT_NAME, **data)
    return folder


def set_in(path, value):
    def change(meta):
        d = meta
        for key in path[:-1]:
            d = d[key]
        d[path[-1]] = value

    return change


DAMAGES = {
    "last_index abc": (
        dict(meta=set_in(["last_index"], "abc")),
        "last_index 'abc' is not a scan number",
    ),
    "keys out of range": (dict(keys=lambda a: a + 2**22), "voxel keys reach"),
    "another resolution": (
        dict(resolution_m=lambda a: np.array(0.3)),
        "its voxels are 0.3 m but its mapper config says resolution_m = 0.2",
    ),
    "nan counts": (dict(counts=lambda a: np.where(a > 0, np.nan, a)), "counts holds NaN/inf"),
    "negative counts": (dict(counts=lambda a: a - 1.0), "counts holds negative values"),
    "nan t_last": (dict(t_last=lambda a: a * np.inf), "t_last holds NaN/inf"),
    "nan seconds": (
        dict(meta=set_in(["progress", "seconds", 0], float("nan"))),
        "progress seconds: nan is not a finite number",
    ),
    "negative confusion": (
        dict(meta=set_in(["progress", "input", 1, 1], -5)),
        "progress input confusion",
    ),
    "origin abc": (
        dict(meta=set_in(["mapper_state", "origin_vox"], "abc")),
        "origin_vox 'abc' is not three integers",
    ),
    "t0 nan": (
        dict(meta=set_in(["mapper_state", "t0"], float("nan"))),
        "t0 nan is not a finite time",
    ),
    "skipped record": (
        dict(meta=set_in(["progress", "skipped"], [{"index": "x"}])),
        "is not an index / name / reason record",
    ),
    "run config": (dict(meta=set_in(["run_config", "first"], "abc")), "first = 'abc'"),
}


@pytest.mark.parametrize("damage", sorted(DAMAGES))
def test_a_checkpoint_that_does_not_fit_together_is_refused(good_checkpoint, tmp_path, damage):
    change, words = DAMAGES[damage]
    with np.load(good_checkpoint) as npz:
        arrays = {k: fn(npz[k]) for k, fn in change.items() if k != "meta"}
    folder = damaged_copy(good_checkpoint, tmp_path / "ck", change.get("meta"), **arrays)
    with pytest.raises(mapfile.MapFileError) as err:
        load_checkpoint(folder)
    message = str(err.value)
    assert "\n" not in message and words in message and str(folder) in message, message


def test_resume_of_a_damaged_checkpoint_is_one_line(good_checkpoint, tmp_path):
    folder = damaged_copy(
        good_checkpoint, tmp_path / "run" / "checkpoint", set_in(["last_index"], "abc")
    )
    rc, rec = run_app(["--resume", folder.parent, "--no-progress"])
    assert rc == 2
    errors = errors_of(rec)
    assert len(errors) == 1 and "last_index 'abc'" in errors[0].getMessage()


@pytest.mark.slow
def test_temp_files_of_a_killed_save_are_removed(good_checkpoint, tmp_path):
    folder = damaged_copy(good_checkpoint, tmp_path / "run" / "checkpoint")
    left = folder / f".{mapfile.CHECKPOINT_NAME}.k1ll3d.tmp"
    left.write_bytes(b"\0" * 1000)
    fresh_runtime()
    scans = make_scans(3, points=1000, seed=9)
    MappingRun.resume(scans, folder.parent)
    assert not left.exists()  # removed by the resume
    left.write_bytes(b"\0" * 1000)
    fresh_runtime()
    MappingRun(scans, run_config(), tmp_path / "run", checkpoint_every=1).run(
        show_progress=False, write_map_files=False
    )
    assert sorted(p.name for p in folder.iterdir()) == [mapfile.CHECKPOINT_NAME]


# --------------------------------------------------------------------------- reported once


@pytest.mark.slow
def test_each_skipped_scan_is_reported_once_by_both_apps(tmp_path, capsys):
    """The reason of a skipped scan appears once in all the apps say (log and stdout), and the
    summary counts it."""
    seq = tiny_sequence(tmp_path / "00", 4)
    lines = (seq / "poses.txt").read_text().splitlines()
    row = np.array(lines[2].split(), float)
    row[11] += FAR_M
    lines[2] = " ".join(f"{v:.12e}" for v in row)
    (seq / "poses.txt").write_text("\n".join(lines) + "\n")
    recording = tmp_path / "drive.mcap"
    write_kitti_mcap(seq, recording)
    capsys.readouterr()
    for name, argv in (
        ("map_kitti", ["--data", seq]),
        ("map_mcap", [recording, "--gt-field", "gt_label"]),
    ):
        rc, rec = run_app_named(name, [*argv, "--out", tmp_path / name, "--no-progress"])
        assert rc == 0, rec.text()
        said = "\n".join(rec.text(logging.DEBUG)) + "\n" + capsys.readouterr().out
        assert said.count("pose outlier") == 1, said
        assert "3 scans mapped, 1 skipped" in said
