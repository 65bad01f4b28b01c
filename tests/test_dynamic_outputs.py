"""What free space writes and what the synthetic movers know: the static map and the dynamic
layer of a snapshot, the occupancy in map files, the per-point flag files, the movers' ground
truth, and the benchmark end to end."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tisem.io.kitti_predictions import read_dynamic_flags, write_dynamic_flags
from tisem.io.mapfile import load_map_file, save_map
from tisem.snapshot import MapSnapshot
from tisem.synth.movers import FIRST_INSTANCE, STILL_M, Mover, StreetMovers, street_movers

ROOT = Path(__file__).resolve().parents[1]
CAR, ROAD = 1, 9


def snapshot_with_a_trail() -> MapSnapshot:
    """Three voxels: road (hit), a car seen through (empty) and a car still there."""
    counts = np.zeros((3, 20), np.float32)
    counts[0, ROAD] = 5.0
    counts[1, CAR] = 3.0
    counts[2, CAR] = 4.0
    return MapSnapshot(
        np.array([[0, 0, 0], [0, 0, 1], [5, 0, 1]]),
        counts,
        np.zeros(3),
        np.full(3, 0.4, np.float32),
        0.2,
        occupancy=np.array([4.0, -2.5, 1.0], np.float32),
        empty_evidence=2.0,
    )


def test_empty_voxels_leave_labels_probabilities_and_the_static_map():
    snap = snapshot_with_a_trail()
    assert snap.empty().tolist() == [False, True, False]
    assert snap.labels().tolist() == [ROAD, 0, CAR]
    assert not snap.probabilities()[1].any()
    assert snap.static_map().keys.tolist() == [[0, 0, 0], [5, 0, 1]]
    trail = snap.dynamic_layer()
    assert trail.keys.tolist() == [[0, 0, 1]] and trail.labels().tolist() == [CAR]


def test_map_files_keep_the_occupancy(tmp_path):
    snap = snapshot_with_a_trail()
    save_map(tmp_path / "map.npz", snap, {"free_space": True})
    back, _, _ = load_map_file(tmp_path / "map.npz")
    assert np.array_equal(back.occupancy, snap.occupancy)
    assert back.empty_evidence == 2.0 and back.labels().tolist() == [ROAD, 0, CAR]
    plain = MapSnapshot(snap.keys, snap.counts, snap.t_last, snap.ell_m, 0.2)
    save_map(tmp_path / "plain.npz", plain, {})
    assert load_map_file(tmp_path / "plain.npz")[0].occupancy is None


def test_dynamic_flags_are_their_own_file_beside_the_labels(tmp_path):
    flags = np.array([0, 1, 1, 0, 0], bool)
    path = write_dynamic_flags(tmp_path, 8, 3, flags)
    assert path == tmp_path / "sequences" / "08" / "predictions" / "000003.dynamic"
    assert np.array_equal(np.fromfile(path, np.uint8), flags.astype(np.uint8))
    assert np.array_equal(read_dynamic_flags(tmp_path, 8, 3, 5), flags)
    assert read_dynamic_flags(tmp_path, 8, 4, 5) is None  # no file: free space was off
    with pytest.raises(ValueError, match=r"000003\.dynamic: 5 flags for a scan of 6 points"):
        read_dynamic_flags(tmp_path, 8, 3, 6)


def test_movers_ground_truth_knows_who_is_where_at_the_end():
    parks = Mover("car", -5.25, 5.0, 7.0, t_start=0.0, t_stop=5.0)
    leaves = Mover("car", -5.25, 28.0, 6.0, t_start=3.0)
    t_end = 12.0
    assert abs(parks.s(6.0) - parks.s(t_end)) <= STILL_M  # parked: static from then on
    assert abs(parks.s(1.0) - parks.s(t_end)) > STILL_M  # still driving in
    assert abs(leaves.s(0.0) - leaves.s(t_end)) > STILL_M  # parked, but gone by the end
    assert parks.moving(1.0) and not parks.moving(6.0) and leaves.moving(t_end)
    movers = StreetMovers(None, (parks, leaves))
    instance = np.array([0, FIRST_INSTANCE, FIRST_INSTANCE + 1])
    # on the last scan: the parked car is static, the one still under way dynamic
    assert movers.dynamic(instance, t_end, t_end).tolist() == [False, False, True]
    assert movers.dynamic(instance, 1.0, t_end).tolist() == [False, True, True]
    kinds = {m.kind for m in street_movers()}
    speeds = [m.speed for m in street_movers() if m.kind == "car"]
    assert kinds == {"car", "cyclist", "person"} and min(speeds) < 0 < max(speeds)


@pytest.mark.slow
def test_no_mover_drives_through_the_street():
    """A dynamic point of a mover never shares a 0.2 m voxel with a static point of anything
    but the ground it stands on (or the parking car's own body, which it drove into): the cars
    that park and leave use the right parking lane, which then holds no parked car."""
    from benchmarks.dynamic import pack
    from tisem.synth.scene import PARKING, ROAD, SIDEWALK, TERRAIN
    from tisem.synth.sequence import SyntheticSequence

    static, dynamic = [], []
    for f in SyntheticSequence(40, seed=0, movers=True):
        world = f.points @ f.T_world_lidar[:3, :3].T + f.T_world_lidar[:3, 3]
        key = pack(np.floor(world / 0.2))
        ground = np.isin(f.gt_raw & 0xFFFF, [ROAD, PARKING, SIDEWALK, TERRAIN])
        mover = f.instance >= FIRST_INSTANCE
        static.append(key[~f.dynamic & ~ground & ~mover])
        dynamic.append(key[f.dynamic & mover])
    static, dynamic = np.concatenate(static), np.concatenate(dynamic)
    assert len(static) > 100_000 and len(dynamic) > 100_000
    assert not np.isin(dynamic, static).any()


@pytest.mark.slow
def test_the_benchmark_scores_free_space_on_the_synthetic_street(tmp_path):
    out = tmp_path / "dynamic.json"
    subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "dynamic.py"),
            "--synthetic",
            "--scans",
            "12",
            "--methods",
            "tisem,tisem+free_space",
            "--json",
            str(out),
        ],
        check=True,
        cwd=ROOT,
        capture_output=True,
    )
    rows = {r["method"]: r for r in json.loads(out.read_text())["rows"]}
    plain, free = rows["tisem"], rows["tisem+free_space"]
    assert plain["da"] < free["da"] and free["trail_voxels"] < plain["trail_voxels"]
    assert free["sa"] > 0.98 and free["stages_ms"]["free_space"] > 0
    assert plain["stages_ms"]["free_space"] == 0


class _Points:
    """What the DA bound reads of a scan: its world points and their motion ground truth."""

    def __init__(self, world: np.ndarray, moving: np.ndarray):
        self._world, self.gt_moving = world, moving

    def points_world(self) -> np.ndarray:
        return self._world


def test_the_da_bound_counts_dynamic_points_that_share_a_voxel_with_a_static_one():
    from benchmarks.dynamic import da_bound

    # scan 0: road at the origin voxel, a car passing two voxels away; scan 1: the car parks
    # at the road's voxel (static from then on) and the car's first place is empty
    first = _Points(np.array([[0.05, 0.05, 0.05], [0.45, 0.05, 0.05]]), np.array([False, True]))
    second = _Points(np.array([[0.15, 0.15, 0.15], [0.11, 0.01, 0.02]]), np.array([True, False]))
    # dynamic points: (0.45, .) alone in its voxel, (0.15, .) in the static points' voxel
    assert da_bound([first, second], 0.2) == pytest.approx(0.5)
    assert da_bound([first, second], 0.1) == pytest.approx(1.0)  # finer voxels share none
    assert da_bound([_Points(np.zeros((1, 3)), np.array([False]))], 0.2) == 1.0


def test_the_da_bound_with_static_points_to_spare_gives_up_the_most_dynamic_voxels_first():
    from benchmarks.dynamic import da_bound

    def voxel(ix: int, n: int) -> np.ndarray:  # n points in voxel (ix, 0, 0) of 0.2 m
        return np.tile([[0.2 * ix + 0.1, 0.1, 0.1]], (n, 1))

    # voxel 0: 1 static, 3 dynamic points; voxel 1: 10 static, 1 dynamic; voxel 2: 2 dynamic
    world = np.concatenate([voxel(0, 1), voxel(1, 10), voxel(0, 3), voxel(1, 1), voxel(2, 2)])
    moving = np.repeat([False, True], [11, 6])
    scans = [_Points(world, moving)]
    assert da_bound(scans, 0.2) == pytest.approx(2 / 6)  # only voxel 2 can go
    # 1.1 static points to spare: voxel 0 (3 dynamic for 1 static) goes, not voxel 1
    assert da_bound(scans, 0.2, min_sa=0.9) == pytest.approx(5 / 6)
    assert da_bound(scans, 0.2, min_sa=0.95) == pytest.approx(2 / 6)  # half a point: none
    assert da_bound(scans, 0.2, min_sa=0.0) == pytest.approx(1.0)


def test_the_first_dynamic_flags_of_a_run_come_with_its_config_and_run_json(tmp_path):
    from tisem.config import RunConfig
    from tisem.run_writer import RunWriter

    out = tmp_path / "run"
    writer = RunWriter(out, RunConfig(), {"data": "synthetic"}, "00", out / "checkpoint")
    writer.write_dynamic_flags(0, np.array([True, False, True]))
    assert (out / "config.yaml").is_file()
    assert json.loads((out / "run.json").read_text()) == {"data": "synthetic"}
    np.testing.assert_array_equal(read_dynamic_flags(out, "00", 0, 3), [True, False, True])
