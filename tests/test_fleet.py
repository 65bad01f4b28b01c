"""Fleet mapping, merging and batch runs on a local Ray cluster of 2 CPUs.

The cluster is started once for the module (starting one takes 10-20 s on a 2-core machine,
longer than most of these tests) and shut down after its last test. Every merged map is
compared with the map one serial run over the same scans builds, in this process.
"""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from tisem.config import load_config
from tisem.logs import discover_logs
from tisem.map_compare import compare_snapshots, serial_snapshot
from tisem.tiles import TiledMap

ray = pytest.importorskip("ray")

pytestmark = pytest.mark.slow

# a 20 m sensor in a 30 m window: small maps, quick tasks
SMALL = ["max_range_m=20", "window_xy_m=30", "window_z_m=12", "min_z_m=-4", "max_z_m=4"]


@pytest.fixture(scope="module")
def ray_cluster():
    from tisem.cluster import ray_cluster as local_cluster

    with local_cluster(num_cpus=2):
        yield


@pytest.fixture(scope="module")
def robots(tmp_path_factory):
    """Two robots of one synthetic world, sharing half of their street, one after the other."""
    from tisem.synth.fleet_world import write_fleet

    root = tmp_path_factory.mktemp("fleet") / "robots"
    write_fleet(root, robots=2, scans=10, points_per_ring=128, progress=False)
    return root


@pytest.fixture(scope="module")
def long_log(tmp_path_factory):
    from tisem.synth.sequence import write_semantickitti

    root = tmp_path_factory.mktemp("fleet") / "long"
    write_semantickitti(root / "sequences" / "00", 24, points_per_ring=128, progress=False)
    return root


def fleet(logs, out, mode, **options):
    from tisem.fleet import FleetOptions, run_fleet

    cfg = load_config(None, [*SMALL, f"mode={mode}"])
    result = run_fleet(logs, cfg, out, FleetOptions(threads=1, **options))
    return result, cfg


def assert_same_map(merged, serial):
    diff = compare_snapshots(merged, serial)
    assert diff.voxels_a == diff.voxels_b == diff.common, diff
    assert diff.label_agreement == 1.0, diff
    np.testing.assert_allclose(merged.counts, serial.counts, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(merged.t_last, serial.t_last, atol=1e-5)


@pytest.mark.parametrize("mode", ["csm", "bki"])
def test_merged_fleet_map_is_the_serial_map(ray_cluster, robots, tmp_path, mode, taichi_cpu):
    result, cfg = fleet([robots], tmp_path / "fleet", mode, evaluate=mode == "bki")
    assert not result.failed and list(result.maps) == ["synthetic-street-seed0"]
    folder = result.maps["synthetic-street-seed0"]
    merged = TiledMap.open(folder)
    serial, _, scans = serial_snapshot(discover_logs([robots]), cfg)
    assert scans == 20
    assert_same_map(merged.snapshot(), serial)
    assert (folder / "map.npz").is_file() and (folder / "map_bev.png").is_file()
    report = json.loads((tmp_path / "fleet" / "fleet.json").read_text())
    assert set(report["tasks"]) == {"00", "01"} and report["missing"] == []
    # the two reducers split the tiles between them
    assert len(report["reduction"]["synthetic-street-seed0"]) == 2
    if mode == "bki":  # robot 1 drove after robot 0 through its streets: refined
        assert report["tasks"]["01"]["task"]["seed_from"] == ["00"]
        metrics = json.loads((folder / "metrics.json").read_text())
        assert metrics["scans"] == 20 and metrics["final"]["accuracy"] > 0.5


def test_chunked_long_log_gives_the_serial_labels(ray_cluster, long_log, tmp_path, taichi_cpu):
    result, cfg = fleet(
        [long_log], tmp_path / "chunks", "bki", chunks=2, overlap_scans=4, evaluate=False
    )
    assert not result.failed
    assert set(result.report["tasks"]) == {"00#chunk0", "00#chunk1"}
    chunk = result.report["tasks"]["00#chunk1"]["task"]
    assert (chunk["first"], chunk["last"], chunk["warmup"]) == (12, 23, 0)  # seeded instead
    merged = TiledMap.open(result.maps["00"]).snapshot()
    serial, _, _ = serial_snapshot(discover_logs([long_log]), cfg)
    diff = compare_snapshots(merged, serial)
    assert diff.label_agreement >= 0.999, diff


def test_a_failing_task_is_reported_and_the_rest_merged(ray_cluster, robots, tmp_path, capsys):
    root = tmp_path / "robots"
    shutil.copytree(robots, root)
    broken = root / "sequences" / "02"
    shutil.copytree(root / "sequences" / "01", broken)
    (broken / "poses.txt").write_text("not a pose\n")
    result, _ = fleet([root], tmp_path / "fleet", "csm", evaluate=False)
    assert list(result.failed) == ["02"] and "malformed" in result.failed["02"]
    # each step's bar counts its tasks as they end, the failed one among them
    bars = capsys.readouterr().err
    assert re.search(r"mapping: 100%.* 3/3 .*failed=1", bars), bars
    assert re.search(r"merging tiles: 100%.* 2/2 ", bars), bars
    report = json.loads((tmp_path / "fleet" / "fleet.json").read_text())
    assert report["missing"][0]["task"] == "02" and set(report["tasks"]) == {"00", "01"}
    metrics = json.loads((result.maps["synthetic-street-seed0"] / "metrics.json").read_text())
    assert metrics["tasks"] == ["00", "01"] and metrics["missing"][0]["task"] == "02"
    merged = TiledMap.open(result.maps["synthetic-street-seed0"])
    ours = [TiledMap.open(tmp_path / "fleet" / "tasks" / t).voxels for t in ("00", "01")]
    assert max(ours) < merged.voxels <= sum(ours)


def test_a_finished_batch_runs_nothing_again(ray_cluster, robots, tmp_path, capsys):
    from tisem.batch import batch_table, run_batch

    logs = discover_logs([robots / "sequences" / "00"])
    first = run_batch(logs, tmp_path / "batch", overrides=SMALL, sweeps=["mode=csm,bki"])
    assert (first.ran, first.kept, first.failed) == (2, 0, {})
    assert re.search(r"cells: 100%.* 2/2 ", capsys.readouterr().err)
    assert [r["cell"] for r in first.rows] == ["mode=csm", "mode=bki"]
    stamps = {
        p: p.stat().st_mtime_ns
        for p in (tmp_path / "batch").rglob("*")
        if p.is_file() and p.name != "batch.json"
    }
    again = run_batch(logs, tmp_path / "batch", overrides=SMALL, sweeps=["mode=csm,bki"])
    assert (again.ran, again.kept) == (0, 2)
    assert "cells" not in capsys.readouterr().err  # nothing ran: no bar
    assert stamps == {p: p.stat().st_mtime_ns for p in stamps}
    assert [r["miou"] for r in again.rows] == [r["miou"] for r in first.rows]
    table = batch_table(again.rows)
    assert "| 00 | mode=bki |" in table and "kept" in table
    saved = json.loads((tmp_path / "batch" / "batch.json").read_text())
    assert saved["ran"] == 0 and saved["kept"] == 2


def test_fleet_benchmark_runs(ray_cluster, tmp_path, capsys):
    """benchmarks/fleet.py with tiny arguments (so it never rots); no timing is checked."""
    from benchmarks import fleet as bench

    out = tmp_path / "f.json"
    assert (
        bench.main(
            [
                "--robots",
                "2",
                "--scans",
                "4",
                "--points-per-ring",
                "64",
                "--modes",
                "bki",
                "--refine",
                "both",
                *sum([["--set", s] for s in SMALL], []),
                "--out",
                str(tmp_path / "runs"),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    rows = json.loads(out.read_text())["rows"]
    assert [r["row"] for r in rows] == ["serial", "fleet (apart)", "fleet (refined)"]
    assert rows[2]["label_agreement"] == 1.0 and rows[1]["peak_reducer_mb"] > 0
    assert "| bki | fleet (refined) |" in capsys.readouterr().out


def test_recordings_are_mapped_and_scored_with_their_options(ray_cluster, tmp_path):
    """A .db3 bag and a ROS 1 bag of the same drive, read with --gt-field's option: a batch
    cell scores the .db3 as map-mcap would, and its run names the options (so `tisem render`
    reads the recording again); a fleet maps both into one frame and scores the merged map."""
    pytest.importorskip("rosbags")
    from test_mcap_kitti import write_tiny_sequence
    from test_rosbag_read import make_input, recorded_messages

    from tisem.batch import run_batch
    from tisem.fleet import FleetOptions, run_fleet
    from tisem.viz.sources import open_run_scans

    seq = write_tiny_sequence(tmp_path / "seq", n_scans=4, n_points=500)
    messages = recorded_messages(seq, tmp_path)
    db3 = make_input("db3 folder", messages, tmp_path / "bags")
    ros1 = make_input("ros1", messages, tmp_path / "bags")
    read = {"gt_field": "gt_label"}
    logs = discover_logs([db3, ros1], recording=read)
    assert [log.options for log in logs] == [read, read]

    batch = run_batch(logs[:1], tmp_path / "batch", overrides=["mode=bki"])
    (row,) = batch.rows
    assert row["scans"] == 4 and row["evaluated"] > 0 and row["miou"] > 0
    assert row["read_losses"] == []
    (run_json,) = (tmp_path / "batch").rglob("run.json")
    run = json.loads(run_json.read_text())
    assert run["options"] == read
    scans = open_run_scans(run, {}, run_json.parent, run_json)
    assert len(scans.scan_ids) == 4 and scans.has_ground_truth

    cfg = load_config(None, ["mode=bki"])
    result = run_fleet(logs, cfg, tmp_path / "fleet", FleetOptions(threads=1, world_frame="map"))
    assert not result.failed and list(result.maps) == ["map"]
    metrics = json.loads((result.maps["map"] / "metrics.json").read_text())
    assert metrics["scans"] == 8 and metrics["final"]["miou"] > 0


def test_a_log_that_cannot_be_read_is_one_failing_task_when_logs_are_chunked(tmp_path):
    """--chunks N needs each log's length; a log that cannot be read is not cut (its one task
    fails with the reason, as any failed task) instead of ending the fleet before it maps the
    others."""
    from test_mcap_kitti import write_tiny_sequence

    from tisem.fleet import FleetOptions, plan_tasks

    good = write_tiny_sequence(tmp_path / "good", n_scans=4, n_points=100)
    broken = tmp_path / "broken.mcap"  # an MCAP header, then nothing a reader can use
    broken.write_bytes(b"\x89MCAP0\r\n" + b"x" * 100)
    logs = discover_logs([good, broken])
    tasks = plan_tasks({"g": logs}, FleetOptions(chunks=2))
    assert [(t.task_id, t.first, t.last) for t in tasks] == [
        ("good#chunk0", 0, 1),
        ("good#chunk1", 2, 3),
        ("broken", 0, 1 << 62),
    ]
