"""Checkpoints, resume (`MappingRun.resume`) and `tisem.load_map`; the apps' resume is in
test_resume_apps.py.

Every test gets its own Taichi runtime (a field of an older runtime must never be touched
again: taichi aborts the process): the fixture inits
(`tisem.init_taichi`, i.e. ti.init(arch=ti.cpu, cpu_max_num_threads=2), which also tells tisem
that a new runtime started), the fixture resets. tisem allows one map per runtime, so a test
that compares two maps keeps the first one's results as numpy arrays and starts a fresh
runtime (`fresh_runtime()`, as a resumed run in a new process would) before building the next.
Scans are small synthetic streets built here with numpy (a few thousand labelled points each).
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import fresh_runtime, small_config

import tisem
from tisem.checkpoint import checkpoint_file, load_checkpoint, save_checkpoint
from tisem.config import RunConfig
from tisem.errors import SkippedScan
from tisem.io import mapfile
from tisem.pipeline import run_pipeline
from tisem.progress import RunProgress
from tisem.run import MappingRun
from tisem.scan import Scan

ROAD, SIDEWALK, BUILDING, VEGETATION, POLE = 9, 11, 13, 15, 18


def run_config(**kw) -> RunConfig:
    return RunConfig(mapper=small_config(**kw))


# --------------------------------------------------------------------------- synthetic scans


def street_points(center_xy, rng, n=3000, reach=18.0):
    """World points of a straight street around `center_xy`: road/sidewalk ground, a building
    facade on one side, vegetation on the other, and a row of poles. Returns xyz, labels."""
    cx, cy = center_xy
    k = rng.multinomial(n, [0.5, 0.2, 0.2, 0.1])
    g = np.column_stack(
        [
            cx + rng.uniform(-reach, reach, k[0]),
            cy + rng.uniform(-7.5, 7.5, k[0]),
            rng.normal(0, 0.02, k[0]),
        ]
    )
    g_lab = np.where(np.abs(g[:, 1] - cy) < 4, ROAD, SIDEWALK)
    b = np.column_stack(
        [
            cx + rng.uniform(-reach, reach, k[1]),
            np.full(k[1], cy + 8.0) + rng.normal(0, 0.03, k[1]),
            rng.uniform(0, 3.5, k[1]),
        ]
    )
    v = np.column_stack(
        [
            cx + rng.uniform(-reach, reach, k[2]),
            cy - 8.0 + rng.uniform(-0.5, 0.5, k[2]),
            rng.uniform(0, 2.5, k[2]),
        ]
    )
    px = np.round((cx + rng.uniform(-reach, reach, k[3])) / 5.0) * 5.0
    p = np.column_stack(
        [
            px + rng.normal(0, 0.05, k[3]),
            cy + 5.0 + rng.normal(0, 0.05, k[3]),
            rng.uniform(0, 3.0, k[3]),
        ]
    )
    xyz = np.concatenate([g, b, v, p])
    labels = np.concatenate(
        [g_lab, np.full(k[1], BUILDING), np.full(k[2], VEGETATION), np.full(k[3], POLE)]
    ).astype(np.int32)
    return xyz, labels


def make_scans(n=6, step_m=1.0, seed=0, points=3000, noise=0.1):
    """`n` scans driving along +x, `step_m` apart, 0.1 s apart. Input labels are the ground
    truth with a fraction `noise` replaced by random classes (so the map has work to do)."""
    rng = np.random.default_rng(seed)
    scans = []
    for i in range(n):
        yaw = 0.05 * np.sin(i)
        c, s = np.cos(yaw), np.sin(yaw)
        T = np.eye(4)
        T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        T[:3, 3] = [i * step_m, 0.3 * np.sin(0.5 * i), 1.7]
        xyz, gt = street_points(T[:2, 3], rng, points)
        pts_sensor = (xyz - T[:3, 3]) @ T[:3, :3]
        lab = gt.copy()
        flip = rng.random(len(lab)) < noise
        lab[flip] = rng.integers(1, 20, flip.sum())
        scans.append(
            Scan(
                points_sensor=pts_sensor,
                T_world_sensor=T,
                stamp_s=100.0 + 0.1 * i,
                labels=lab,
                gt_labels=gt,
                index=i,
                name=f"synthetic {i}",
            )
        )
    return scans


# --------------------------------------------------------------------------- comparisons


def assert_same_map(a, b):
    """Same voxels, counters, times, lengths and labels, bit for bit (a map is repeatable)."""
    assert a.resolution_m == b.resolution_m
    for name in ("keys", "counts", "t_last", "ell_m"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(a.labels(), b.labels())


def query_points(scans, rng, extra=500):
    """The scans' own points plus random points around them (many in no voxel)."""
    pts = np.concatenate([s.points_world() for s in scans])
    lo, hi = pts.min(axis=0) - 2, pts.max(axis=0) + 2
    return np.concatenate([pts, rng.uniform(lo, hi, (extra, 3))])


def comparable_metrics(m: dict) -> dict:
    """The metrics of a run without its timings."""
    return {k: v for k, v in m.items() if not k.startswith("seconds_")}


def progress_upto(mapper, last_index: int) -> RunProgress:
    """A progress that says only how far the scans went (a checkpoint of a bare mapper)."""
    return dataclasses.replace(RunProgress.start(mapper.C), last_index=last_index)


def reference_run(scans, cfg, out, q=None):
    """An uninterrupted run, kept as numpy: (snapshot, metrics, trajectory, query result)."""
    full = run_pipeline(scans, cfg, out, progress=False, write_outputs=False)
    answer = full.mapper.query(q) if q is not None else None
    return full.mapper.snapshot(), full.metrics, full.trajectory, answer


# --------------------------------------------------------------------------- tests


@pytest.mark.slow
def test_resume_equals_uninterrupted(taichi_cpu, tmp_path):
    scans = make_scans(6)
    cfg = run_config()
    q = query_points(scans, np.random.default_rng(1))
    full_snap, full_metrics, full_traj, (full_labels, full_probs) = reference_run(
        scans, cfg, tmp_path / "full", q
    )

    fresh_runtime()
    out = tmp_path / "split"
    first = run_pipeline(
        scans[:3], cfg, out, progress=False, write_outputs=False, checkpoint_every=3
    )
    assert first.metrics["scans"] == 3
    first_snap = first.mapper.snapshot()
    ckpt = load_checkpoint(out)
    assert ckpt.path == out / "checkpoint" / mapfile.CHECKPOINT_NAME
    assert ckpt.results_dir == out
    assert ckpt.last_index == 2
    assert ckpt.meta["run_config"]["mapper"]["max_range_m"] == 20.0
    assert len(ckpt.meta["progress"]["seconds"]) == 3
    assert_same_map(ckpt.snapshot, first_snap)

    # a resumed run (a new runtime, as in a new process) is handed the whole sequence and
    # passes over what the checkpoint holds
    fresh_runtime()
    integrated = []
    resumed = run_pipeline(
        scans,
        ckpt.run_config(),
        out,
        progress=False,
        write_outputs=False,
        resume=out,
        on_scan=lambda m, s, k: integrated.append(s.index),
    )
    assert integrated == [3, 4, 5]
    assert resumed.mapper.scans == 6
    assert_same_map(resumed.mapper.snapshot(), full_snap)
    labels, probs = resumed.mapper.query(q)
    np.testing.assert_array_equal(labels, full_labels)
    np.testing.assert_array_equal(probs, full_probs)
    assert comparable_metrics(resumed.metrics) == comparable_metrics(full_metrics)
    np.testing.assert_allclose(resumed.trajectory, full_traj)
    # the final-map pass saw every scan, also the ones before the checkpoint
    pred = sorted(p.name for p in (out / "sequences" / "00" / "predictions").iterdir())
    assert pred == [f"{i:06d}.label" for i in range(6)]

    # a generator (iterable once) resumes too: early scans are kept for the final-map pass
    fresh_runtime()
    # (the library's own resume: config, sequence name and cadence from the checkpoint)
    gen = MappingRun.resume((s for s in scans), ckpt, out_dir=tmp_path / "gen").run(
        show_progress=False, write_map_files=False
    )
    assert comparable_metrics(gen.metrics) == comparable_metrics(full_metrics)


def test_progress_saves_and_restores_itself():
    """RunProgress.to_dict() is plain JSON and from_dict() gives back every accumulator."""
    from tisem.mapper import IntegrationReport

    progress = RunProgress.start(20)
    for scan in make_scans(3, points=200):
        report = IntegrationReport(points=200, dropped_nonfinite=scan.index, dropped_range=7)
        progress.add_mapped(scan, 0.01 * (scan.index + 1), report)
        progress.input.add(scan.gt_labels, scan.labels)
    progress.add_skipped(SkippedScan(3, "bad.bin", "truncated"))
    saved = json.loads(json.dumps(progress.to_dict()))
    back = RunProgress.from_dict(saved, 20)
    assert back.to_dict() == saved
    np.testing.assert_array_equal(back.input.matrix, progress.input.matrix)
    assert back.input.matrix.sum() > 0 and back.online.matrix.sum() == 0
    assert back.seconds == [0.01, 0.02, 0.03] and back.mapped == 3 and back.last_index == 2
    assert back.skipped == [SkippedScan(3, "bad.bin", "truncated")] and back.was_skipped(3)
    np.testing.assert_array_equal(back.trajectory_array(), progress.trajectory_array())
    assert back.drops.totals["dropped_nonfinite"] == 0 + 1 + 2
    assert back.drops.totals["dropped_range"] == 21
    assert [s["index"] for s in back.drops.scans] == [1, 2]  # scan 0 lost nothing odd
    with pytest.raises(ValueError, match="expected 5 classes"):
        RunProgress.from_dict(saved, 5)


def test_resume_refuses_another_mapper_config(taichi_cpu, tmp_path):
    scans = make_scans(2, points=1000)
    run_pipeline(
        scans, run_config(), tmp_path, progress=False, write_outputs=False, checkpoint_every=1
    )
    with pytest.raises(ValueError, match="tau_s"):  # refused before any map is built
        run_pipeline(
            scans,
            run_config(tau_s=1.0),
            tmp_path,
            progress=False,
            write_outputs=False,
            resume=tmp_path,
        )
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        load_checkpoint(tmp_path / "nowhere")


@pytest.mark.slow
def test_interrupted_checkpoint_write_keeps_the_previous_one(taichi_cpu, tmp_path, monkeypatch):
    scans = make_scans(6, seed=3)
    cfg = run_config()
    full_snap, full_metrics, _, _ = reference_run(scans, cfg, tmp_path / "full")

    fresh_runtime()
    out = tmp_path / "run"
    real_savez = np.savez
    calls = []

    def dying_savez(f, **arrays):
        """The second checkpoint dies half-way through writing its file."""
        calls.append(1)
        if len(calls) < 2:
            return real_savez(f, **arrays)
        import io

        buf = io.BytesIO()
        real_savez(buf, **arrays)
        f.write(buf.getvalue()[: buf.tell() // 2])
        raise KeyboardInterrupt("killed mid-checkpoint")

    monkeypatch.setattr(np, "savez", dying_savez)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(scans, cfg, out, progress=False, write_outputs=False, checkpoint_every=2)
    monkeypatch.undo()
    assert len(calls) == 2
    ckdir = out / "checkpoint"
    assert sorted(os.listdir(ckdir)) == [mapfile.CHECKPOINT_NAME]  # no torn temp file left
    ckpt = load_checkpoint(ckdir)  # the first one, intact
    assert ckpt.last_index == 1 and len(ckpt.meta["progress"]["seconds"]) == 2

    fresh_runtime()
    resumed = run_pipeline(
        scans,
        ckpt.run_config(),
        out,
        progress=False,
        write_outputs=False,
        resume=ckdir,
        checkpoint_every=2,
    )
    assert_same_map(resumed.mapper.snapshot(), full_snap)
    assert comparable_metrics(resumed.metrics) == comparable_metrics(full_metrics)
    assert load_checkpoint(out).last_index == 5  # checkpoints went on


@pytest.mark.slow
def test_skipped_scans_survive_a_resume(taichi_cpu, tmp_path):
    scans = make_scans(5, points=1500, seed=4)
    far = scans[3]
    T = far.T_world_sensor.copy()
    T[:3, 3] += 1e6  # the mapper refuses a pose this far from the origin
    items = (
        scans[:1]
        + [SkippedScan(1, "bad.bin", "truncated")]
        + scans[2:3]
        + [Scan(far.points_sensor, T, far.stamp_s, labels=far.labels, index=3, name="far")]
        + scans[4:]
    )
    cfg = run_config()
    full_snap, full_metrics, _, _ = reference_run(items, cfg, tmp_path / "full")
    assert [s["index"] for s in full_metrics["skipped"]] == [1, 3]

    fresh_runtime()
    out = tmp_path / "split"
    run_pipeline(items[:3], cfg, out, progress=False, write_outputs=False, checkpoint_every=2)
    ckpt = load_checkpoint(out)
    assert ckpt.last_index == 2 and [s["index"] for s in ckpt.meta["progress"]["skipped"]] == [1]
    fresh_runtime()
    resumed = run_pipeline(items, cfg, out, progress=False, write_outputs=False, resume=ckpt)
    assert [s.index for s in resumed.skipped] == [1, 3]
    assert comparable_metrics(resumed.metrics) == comparable_metrics(full_metrics)
    assert_same_map(resumed.mapper.snapshot(), full_snap)


@pytest.mark.slow
def test_load_map_round_trip(taichi_cpu, tmp_path):
    scans = make_scans(4, seed=1)
    result = run_pipeline(scans, run_config(), tmp_path, progress=False)  # writes map.npz
    q = query_points(scans, np.random.default_rng(2))
    want_labels, want_probs = result.mapper.query(q)
    want_snap, want_config = result.mapper.snapshot(), result.mapper.config
    assert (want_labels > 0).mean() > 0.5
    save_checkpoint(tmp_path / "ck", result.mapper, progress_upto(result.mapper, 3))
    del result

    for path in (tmp_path / "map.npz", tmp_path, tmp_path / "ck" / mapfile.CHECKPOINT_NAME):
        fresh_runtime()
        loaded = tisem.load_map(path)
        assert isinstance(loaded, tisem.Mapper)
        assert loaded.config == want_config
        labels, probs = loaded.query(q)
        np.testing.assert_array_equal(labels, want_labels)
        np.testing.assert_allclose(probs, want_probs, rtol=0, atol=1e-6)
        assert_same_map(loaded.snapshot(), want_snap)


def test_load_map_initialises_taichi(tmp_path):
    """In a fresh process, load_map needs no ti.init beforehand (and a map without a stored
    mapper state still loads: the state is rebuilt from the voxels)."""
    code = f"""
import numpy as np, taichi as ti, tisem
from tisem.backend import is_initialized
from tisem.io.mapfile import save_map
from tisem.snapshot import MapSnapshot
from tisem.config import MapperConfig
keys = np.array([[0, 0, 0], [0, 0, 1], [5000, -3000, 7]], np.int64)
counts = np.zeros((3, 20), np.float32); counts[0, 9] = 2; counts[1, 13] = 1; counts[2, 15] = 3
cfg = MapperConfig(max_range_m=20, window_xy_m=30, window_z_m=12, min_z_m=-4, max_z_m=4)
snap = MapSnapshot(keys, counts, np.zeros(3), np.full(3, 0.4, np.float32), 0.2)
save_map(r"{tmp_path}/bare.npz", snap, cfg, {{}})
assert not is_initialized()
m = tisem.load_map(r"{tmp_path}/bare.npz")
assert is_initialized()
labels, probs = m.query((keys + 0.5) * 0.2)
assert labels.tolist() == [9, 13, 15], labels
np.testing.assert_allclose(probs[:, [9, 13, 15]], np.eye(3), atol=1e-6)
"""
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300, cwd=tmp_path)


@pytest.mark.slow
def test_checkpoint_restores_evicted_blocks(taichi_cpu, tmp_path):
    # 60 m steps with a 30 m window: each scan evicts the previous one's blocks to the store
    scans = make_scans(6, step_m=60.0, seed=5, points=2000)
    q = query_points(scans[:5], np.random.default_rng(4))
    mapper = tisem.Mapper(small_config())
    for s in scans[:5]:
        mapper.integrate(s)
    assert mapper.stored_voxels > 0 and mapper.live_voxels > 0
    stored, live = mapper.stored_voxels, mapper.live_voxels
    snap, answer = mapper.snapshot(), mapper.query(q)
    path = save_checkpoint(tmp_path / "checkpoint", mapper, progress_upto(mapper, 4))
    mapper.integrate(scans[5])
    snap_after = mapper.snapshot()
    del mapper

    fresh_runtime()
    restored = load_checkpoint(tmp_path).build_mapper()
    assert path == checkpoint_file(tmp_path / "checkpoint")
    assert (restored.stored_voxels, restored.live_voxels) == (stored, live)
    assert_same_map(restored.snapshot(), snap)
    for a, b in zip(restored.query(q), answer):
        np.testing.assert_array_equal(a, b)
    far_behind = scans[0].points_world()  # 240 m behind: answered by the store
    assert (restored.query(far_behind)[0] > 0).mean() > 0.5
    # and it goes on as the original did
    restored.integrate(scans[5])
    assert_same_map(restored.snapshot(), snap_after)


def test_import_tisem_is_cheap():
    code = (
        "import sys, tisem; assert 'taichi' not in sys.modules; "
        "tisem.MapperConfig, tisem.RunConfig, tisem.load_config, tisem.Scan, "
        "tisem.MapSnapshot, tisem.load_map; assert 'taichi' not in sys.modules; "
        "tisem.init_taichi, tisem.Mapper; assert 'taichi' in sys.modules; "
        "assert set(tisem.__all__) >= {'Mapper', 'load_map', 'init_taichi'}"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
