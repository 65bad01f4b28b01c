"""The multi-robot synthetic world, and fleet tasks run in this process (no Ray): a chunk's
warm-up and a seed are taken back out of what the task writes; a tiled map answers queries
as the mapper it came from does."""

from __future__ import annotations

import numpy as np
import pytest

from tisem.config import load_config, to_dict
from tisem.fleet_task import MapTask, anchor_of, map_task
from tisem.logs import discover_logs, first_pose, open_log
from tisem.map_compare import compare_snapshots, serial_snapshot
from tisem.merge import merge_snapshots
from tisem.synth.fleet_world import fleet_drives, write_fleet
from tisem.tiles import TiledMap

SMALL = ["max_range_m=20", "window_xy_m=30", "window_z_m=12", "min_z_m=-4", "max_z_m=4"]


@pytest.fixture(scope="module")
def robots(tmp_path_factory):
    root = tmp_path_factory.mktemp("world") / "robots"
    write_fleet(root, robots=2, scans=8, points_per_ring=128, progress=False)
    return root


def test_robots_share_streets_and_frame_at_different_times(robots):
    drives = fleet_drives(3, 100)
    assert [d.forward for d in drives] == [True, False, True]
    spans = [
        sorted((d.start_s_m, d.start_s_m + (1 if d.forward else -1) * d.length_m)) for d in drives
    ]
    assert spans[0][1] > spans[1][0] and spans[1][1] > spans[2][0]  # shared streets
    ends = [d.start_time_s + d.scans * 0.1 for d in drives]
    assert all(ends[k] < drives[k + 1].start_time_s for k in range(2))  # one after another
    logs = discover_logs([robots])
    assert [log.name for log in logs] == ["00", "01"]
    assert logs[0].world_frame == logs[1].world_frame == "synthetic-street-seed0"
    (T0, t0), (T1, t1) = first_pose(logs[0]), first_pose(logs[1])
    assert t1 > t0 + 0.8
    # robot 1 starts at the far end of its drive (4 m stride + 8 m), in the other lane (3.5 m
    # over), facing back towards robot 0
    assert np.linalg.norm(T1[:2, 3] - T0[:2, 3]) == pytest.approx(np.hypot(12.0, 3.5), abs=0.1)
    assert T0[:2, 0] @ T1[:2, 0] < -0.9


def run_task(task, cfg, folder):
    return map_task(task, to_dict(cfg), str(folder), threads=2)


@pytest.mark.slow
def test_chunks_with_warm_up_add_up_to_the_serial_csm_map(robots, tmp_path, taichi_cpu):
    log = discover_logs([robots])[0]
    cfg = load_config(None, [*SMALL, "mode=csm"])
    anchor = anchor_of(*first_pose(log), cfg.mapper.resolution_m)
    first = MapTask("a", log, 0, 3, anchor=anchor)
    second = MapTask("b", log, 4, 7, warmup=3, anchor=anchor)
    summaries = [run_task(t, cfg, tmp_path / t.task_id) for t in (first, second)]
    assert [s["scans"] for s in summaries] == [4, 4]
    merged = merge_snapshots([TiledMap.open(tmp_path / t).snapshot() for t in "ab"], np.inf)
    serial, _, _ = serial_snapshot([log], cfg)
    diff = compare_snapshots(merged, serial)
    assert diff.label_agreement == 1.0 and diff.max_counter_diff < 1e-5, diff


@pytest.mark.slow
def test_a_seeded_task_writes_only_its_own_bki_evidence(robots, tmp_path, taichi_cpu):
    logs = discover_logs([robots])
    cfg = load_config(None, [*SMALL, "mode=bki"])
    anchor = anchor_of(*first_pose(logs[0]), cfg.mapper.resolution_m)
    run_task(MapTask("r0", logs[0], 0, 7, anchor=anchor), cfg, tmp_path / "r0")
    r0 = TiledMap.open(tmp_path / "r0")
    seeded = map_task(
        MapTask("r1", logs[1], 0, 7, anchor=anchor, seed_from=("r0",)),
        to_dict(cfg),
        str(tmp_path / "r1"),
        threads=2,
        seed_dirs=[str(tmp_path / "r0")],
        footprint=r0.tile_keys,
    )
    assert seeded["seed_voxels"] == r0.voxels
    merged = merge_snapshots([r0.snapshot(), TiledMap.open(tmp_path / "r1").snapshot()], np.inf)
    serial, _, _ = serial_snapshot(logs, cfg)
    diff = compare_snapshots(merged, serial)
    assert diff.label_agreement == 1.0 and diff.max_counter_diff < 1e-4, diff


@pytest.mark.slow
def test_tiled_map_answers_as_the_mapper(robots, tmp_path, taichi_cpu):
    from tisem.mapper import Mapper
    from tisem.tiles import TileIndex, split_by_tile, write_index, write_tile

    log = discover_logs([robots])[0]
    # a tiled map answers from the voxels a point falls in, as the mapper does without the
    # blend of the voxels around a point in none
    cfg = load_config(None, [*SMALL, "mode=st", "query_blend=off"])
    mapper = Mapper(cfg.mapper)
    scans = list(open_log(log))
    for scan in scans:
        mapper.integrate(scan)
    snap = mapper.snapshot()
    config = to_dict(cfg)["mapper"]
    entries = [write_tile(tmp_path, t, part, config) for t, part in split_by_tile(snap, 64)]
    write_index(tmp_path, TileIndex(0.2, 20, 64, log.world_frame, config, entries, {}))
    tiled = TiledMap.open(tmp_path)
    points = scans[-1].points_world()
    labels, probs = tiled.query(points)
    expected, expected_probs = mapper.query(points)
    assert np.array_equal(labels, expected)
    np.testing.assert_allclose(probs, expected_probs, rtol=1e-5, atol=1e-6)
