"""Merging maps and tiled maps, without Ray: the merge rule against a per-voxel oracle, seeds
taken back out, transforms, lazy tiles, and `merge_maps` on files (frames refused)."""

from __future__ import annotations

import numpy as np
import pytest

from tisem.io.mapfile import save_map
from tisem.merge import contribution, merge_snapshots, transform_snapshot
from tisem.merge_files import merge_maps, parse_transform
from tisem.snapshot import MapSnapshot
from tisem.tiles import TiledMap, TileIndex, split_by_tile, tile_ids, write_index, write_tile

C = 5
RES = 0.2
CONFIG = {"mode": "st", "resolution_m": RES, "num_classes": C, "tau_s": 2.0}


def random_map(rng, n: int, spread: int = 40, t_range=(0.0, 10.0)) -> MapSnapshot:
    keys = np.unique(rng.integers(-spread, spread, (n, 3)), axis=0)
    keys = keys[MapSnapshot.sort_order(keys)]
    m = len(keys)
    return MapSnapshot(
        keys,
        rng.uniform(0, 3, (m, C)).astype(np.float32),
        rng.uniform(*t_range, m),
        rng.uniform(0.4, 1.2, m).astype(np.float32),
        RES,
    )


def oracle_merge(parts, taus):
    """Per voxel, in plain Python: decay each part to the latest t_last and sum."""
    voxels = {}
    for part, tau in zip(parts, taus):
        for k, c, t, ell in zip(map(tuple, part.keys), part.counts, part.t_last, part.ell_m):
            voxels.setdefault(k, []).append((t, c.astype(np.float64), ell, tau))
    out = {}
    for k, rows in voxels.items():
        t_max = max(r[0] for r in rows)
        total = np.zeros(C)
        for t, c, _, tau in rows:
            dt = t_max - t
            factor = 1.0 if tau == np.inf else (float(dt == 0) if tau == 0 else np.exp(-dt / tau))
            total += factor * c
        latest = max(rows, key=lambda r: r[0])
        out[k] = (total, t_max, latest[2])
    return out


@pytest.mark.parametrize("seed", range(6))
def test_merge_matches_per_voxel_oracle(seed):
    rng = np.random.default_rng(seed)
    parts = [random_map(rng, 300, spread=8) for _ in range(3)]
    taus = [[2.0] * 3, [np.inf] * 3, [0.0] * 3, [1.0, np.inf, 5.0]][seed % 4]
    merged = merge_snapshots(parts, taus)
    expected = oracle_merge(parts, taus)
    assert len(merged) == len(expected), f"seed {seed}"
    assert np.all(merged.keys[MapSnapshot.sort_order(merged.keys)] == merged.keys)
    for k, c, t, ell in zip(map(tuple, merged.keys), merged.counts, merged.t_last, merged.ell_m):
        total, t_max, ell_latest = expected[k]
        np.testing.assert_allclose(c, total, rtol=1e-5, atol=1e-6, err_msg=f"seed {seed} {k}")
        assert t == t_max and ell == ell_latest


def test_merge_of_a_split_history_is_the_serial_map():
    """A voxel's decayed sum of updates splits over any partition of the updates."""
    rng = np.random.default_rng(3)
    tau = 1.5
    times = np.sort(rng.uniform(0, 10, 40))
    deltas = rng.uniform(0, 1, (40, C))
    owner = rng.integers(0, 2, 40)

    def fold(rows):  # lazy decay, update by update, as the mapper does
        sigma, t_last = np.zeros(C), None
        for t, d in zip(times[rows], deltas[rows]):
            sigma = (np.exp(-(t - t_last) / tau) * sigma if t_last is not None else 0) + d
            t_last = t
        return MapSnapshot(
            np.zeros((1, 3), np.int64),
            sigma[None].astype(np.float32),
            np.array([t_last]),
            np.ones(1, np.float32),
            RES,
        )

    serial = fold(np.arange(40))
    merged = merge_snapshots([fold(owner == 0), fold(owner == 1)], tau)
    np.testing.assert_allclose(merged.counts, serial.counts, rtol=1e-5)
    assert merged.t_last[0] == serial.t_last[0]


def test_contribution_takes_the_seed_back_out():
    rng = np.random.default_rng(5)
    seed = random_map(rng, 400, t_range=(0, 5))
    own = random_map(rng, 400, t_range=(6, 10))
    final = merge_snapshots([seed, own], 2.0)
    back = contribution(final, seed, 2.0)
    assert np.array_equal(back.keys, own.keys)
    np.testing.assert_allclose(back.counts, own.counts, rtol=1e-4, atol=1e-4)
    assert np.array_equal(back.t_last, own.t_last)


def test_transform_by_whole_voxels_is_exact_and_a_yaw_permutes_keys():
    rng = np.random.default_rng(1)
    snap = random_map(rng, 200)
    T = parse_transform(f"{3 * RES},{-2 * RES},{RES}")
    moved = transform_snapshot(snap, T, 2.0)
    order = MapSnapshot.sort_order(snap.keys + [3, -2, 1])
    assert np.array_equal(moved.keys, (snap.keys + [3, -2, 1])[order])
    np.testing.assert_array_equal(moved.counts, snap.counts[order])
    # 90 degrees about the z axis through the origin, a voxel corner: (x, y) -> (-y - 1, x)
    turned = transform_snapshot(snap, parse_transform("0,0,0,90"), 2.0)
    expected = np.column_stack([-snap.keys[:, 1] - 1, snap.keys[:, 0], snap.keys[:, 2]])
    assert np.array_equal(turned.keys, expected[MapSnapshot.sort_order(expected)])


def write_tiled(folder, snap, frame="world-a", tile_vox=32):
    entries = [write_tile(folder, t, part, CONFIG) for t, part in split_by_tile(snap, tile_vox)]
    write_index(folder, TileIndex(RES, C, tile_vox, frame, CONFIG, entries, {}))
    return TiledMap.open(folder)


def test_tiled_map_queries_lazily_what_the_snapshot_holds(tmp_path):
    rng = np.random.default_rng(2)
    snap = random_map(rng, 3000, spread=100)
    tiled = write_tiled(tmp_path / "tiled", snap)
    assert tiled.voxels == len(snap) and len(tiled.tile_keys) > 4
    assert tiled.tiles_loaded == 0  # only the index so far
    # points inside a few voxels of one tile, and points in no voxel
    pick = rng.choice(len(snap), 50, replace=False)
    inside = snap.keys[pick]
    one_tile = tile_ids(inside, 32)
    chosen = inside[np.all(one_tile == one_tile[0], axis=1)]
    points = np.vstack(
        [(chosen + rng.uniform(0.01, 0.99, chosen.shape)) * RES, [[1e3, 1e3, 1e3], [np.nan, 0, 0]]]
    )
    labels, probs = tiled.query(points)
    assert tiled.tiles_loaded == 1
    rows = np.searchsorted(
        np.ravel_multi_index((snap.keys + 200).T, (400,) * 3),
        np.ravel_multi_index((chosen + 200).T, (400,) * 3),
    )
    assert np.array_equal(labels[: len(chosen)], snap.labels()[rows])
    np.testing.assert_allclose(probs[: len(chosen)], snap.probabilities()[rows], rtol=1e-6)
    assert np.all(labels[len(chosen) :] == 0) and np.all(probs[len(chosen) :] == 0)
    whole = tiled.snapshot()
    assert np.array_equal(whole.keys, snap.keys) and np.array_equal(whole.counts, snap.counts)
    with pytest.raises(MemoryError):
        tiled.snapshot(max_voxels=10)


def test_merge_maps_refuses_other_frames_unless_transformed(tmp_path):
    rng = np.random.default_rng(4)
    a, b = random_map(rng, 500), random_map(rng, 500)
    save_map(tmp_path / "a.npz", a, CONFIG, {"world_frame": "world-a"})
    save_map(tmp_path / "b.npz", b, CONFIG, {"world_frame": "world-b"})
    write_tiled(tmp_path / "c", random_map(rng, 500), frame="world-a")
    with pytest.raises(ValueError, match="--transform 1="):
        merge_maps([tmp_path / "a.npz", tmp_path / "b.npz"], tmp_path / "out")
    result = merge_maps([tmp_path / "a.npz", tmp_path / "c"], tmp_path / "same")
    merged = TiledMap.open(tmp_path / "same")
    expected = merge_snapshots([a, TiledMap.open(tmp_path / "c").snapshot()], 2.0)
    assert result.voxels == len(expected) == merged.voxels
    np.testing.assert_allclose(merged.snapshot().counts, expected.counts, rtol=1e-6)
    assert (tmp_path / "same" / "map.npz").is_file() and merged.world_frame == "world-a"
    moved = merge_maps(
        [tmp_path / "a.npz", tmp_path / "b.npz"],
        tmp_path / "moved",
        transforms={1: parse_transform(f"{10 * RES},0,0")},
    )
    assert moved.voxels == len(
        merge_snapshots([a, transform_snapshot(b, parse_transform(f"{10 * RES},0,0"))], 2.0)
    )


def test_merge_maps_refuses_other_resolutions(tmp_path):
    rng = np.random.default_rng(6)
    a = random_map(rng, 50)
    coarse = MapSnapshot(a.keys, a.counts, a.t_last, a.ell_m, 0.4)
    save_map(tmp_path / "a.npz", a, CONFIG, {"world_frame": "w"})
    save_map(tmp_path / "b.npz", coarse, dict(CONFIG, resolution_m=0.4), {"world_frame": "w"})
    with pytest.raises(ValueError, match="resolution"):
        merge_maps([tmp_path / "a.npz", tmp_path / "b.npz"], tmp_path / "out")


def test_load_map_gives_a_tiled_map_read_lazily(tmp_path):
    import tisem

    rng = np.random.default_rng(7)
    snap = random_map(rng, 2000, spread=100)
    write_tiled(tmp_path / "tiled", snap)
    loaded = tisem.load_map(tmp_path / "tiled")
    assert isinstance(loaded, TiledMap) and loaded.tiles_loaded == 0
    points = (snap.keys[:20] + 0.5) * RES
    labels, probs = loaded.query(points)
    assert np.array_equal(labels, snap.labels()[:20])
    np.testing.assert_allclose(probs, snap.probabilities()[:20], rtol=1e-6)
    assert 0 < loaded.tiles_loaded < len(loaded.tile_keys)


def test_merge_app_refuses_other_frames_in_one_line(tmp_path, capsys, caplog):
    from test_pipeline import load_app

    module = load_app("merge_maps")
    rng = np.random.default_rng(8)
    save_map(tmp_path / "a.npz", random_map(rng, 50), CONFIG, {"world_frame": "world-a"})
    save_map(tmp_path / "b.npz", random_map(rng, 50), CONFIG, {"world_frame": "world-b"})
    argv = [str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "m")]
    assert module.main(argv) == 2
    assert module.main([*argv, "--transform", "1=1,2"]) == 2
    capsys.readouterr()
    assert module.main([*argv, "--transform", "1=0.4,0,0"]) == 0
    merged = TiledMap.open(tmp_path / "m")
    assert merged.voxels > 0
    # the tiles merged, counted by the progress bar (and none with --no-progress)
    tiles = len(merged.tile_keys)
    assert "merging tiles: 100%" in (bar := capsys.readouterr().err) and f" {tiles}/{tiles} " in bar
    assert module.main([*argv, "--transform", "1=0.4,0,0", "--no-progress"]) == 2  # not empty
    assert "give --overwrite" in caplog.text
    again = [*argv, "--transform", "1=0.4,0,0", "--no-progress", "--overwrite"]
    assert module.main(again) == 0
    assert "merging tiles" not in capsys.readouterr().err
    assert TiledMap.open(tmp_path / "m").voxels == merged.voxels


def test_merge_app_never_writes_over_an_input_or_a_folder_of_the_users(tmp_path, caplog):
    """--out is a new or empty folder, or (--overwrite) a previous merge, whose own files
    alone are replaced; never the folder of a map being merged."""
    from test_pipeline import load_app

    module = load_app("merge_maps")
    rng = np.random.default_rng(9)
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        save_map(tmp_path / name / "map.npz", random_map(rng, 50), CONFIG, {"world_frame": "w"})
    before = (tmp_path / "a" / "map.npz").read_bytes()
    maps = [str(tmp_path / "a"), str(tmp_path / "b" / "map.npz")]
    for out in ("a", "b"):
        caplog.clear()
        assert module.main([*maps, "--out", str(tmp_path / out), "--overwrite"]) == 2
        assert "holds the map" in caplog.text
    assert (tmp_path / "a" / "map.npz").read_bytes() == before
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    assert module.main([*maps, "--out", str(mine), "--overwrite"]) == 2
    assert "holds no merged map" in caplog.text
    merged = tmp_path / "merged"
    assert module.main([*maps, "--out", str(merged), "--no-progress"]) == 0
    (merged / "notes.txt").write_text("mine")
    assert module.main([*maps, "--out", str(merged), "--no-progress", "--overwrite"]) == 0
    assert (merged / "notes.txt").read_text() == "mine" and TiledMap.open(merged).voxels > 0


def test_merge_cost_benchmark_runs():
    """benchmarks/merge_cost.py with a tiny map (so it never rots); no timing is checked."""
    from benchmarks import merge_cost

    result = merge_cost.run(merge_cost.parse_args(["--voxels", "3000"]))
    assert result["rows"] > result["voxels"] > 0.9 * result["rows"]  # half the area shared
    assert result["bytes_per_voxel"] > 0


@pytest.mark.parametrize("blend", ["missing", "off"])
def test_a_tiled_map_answers_between_its_voxels_as_the_mapper_does(tmp_path, taichi_cpu, blend):
    """A point in no voxel gets the blend of the voxels within query_radius_m, across tile
    borders, as `Mapper.query` gives it (query_blend missing), or 0 (off); points in voxels
    get their voxel's answer either way."""
    import tisem
    from tisem.config import to_dict

    cfg = tisem.MapperConfig(query_blend=blend)
    mapper = tisem.Mapper(cfg)
    rng = np.random.default_rng(3)
    for k in range(4):
        xy = rng.uniform(-8, 8, (4000, 2))
        points = np.c_[xy, np.full(4000, -1.7)]
        labels = np.where(xy[:, 0] < 0, 9, 11)  # road | sidewalk, split at x = 0
        labels[rng.random(4000) < 0.1] = 15  # noise: vegetation
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * k, 0.0, 1.7]
        mapper.integrate(tisem.Scan(points, pose, stamp_s=0.1 * k, labels=labels))
    snap = mapper.snapshot()
    folder = tmp_path / "tiled"
    mapper_config = to_dict(cfg)
    entries = [write_tile(folder, t, p, mapper_config) for t, p in split_by_tile(snap, 32)]
    write_index(
        folder, TileIndex(cfg.resolution_m, cfg.num_classes, 32, "w", mapper_config, entries, {})
    )
    tiled = TiledMap.open(folder)
    assert len(tiled.tile_keys) >= 4
    # above the ground (in no voxel, 0.1-0.35 m above a voxel centre), across the tile borders
    # at x, y = 0 and +-6.4 m, and in voxels
    centres = (snap.keys + 0.5) * cfg.resolution_m
    pick = rng.choice(len(snap), 400, replace=False)
    above = centres[pick] + np.c_[rng.uniform(-0.1, 0.1, (400, 2)), rng.uniform(0.1, 0.35, 400)]
    points = np.concatenate([above, centres[pick[:100]], [[200.0, 0.0, 0.0]]])
    want_labels, want_probs = mapper.query(points)
    labels, probs = tiled.query(points)
    assert np.array_equal(labels, want_labels)
    # (the kernels sample g from a table, in float32)
    np.testing.assert_allclose(probs, want_probs, atol=1e-4)
    blended = (want_labels[:400] != 0).mean()
    assert blended > 0.5 if blend == "missing" else blended == 0
    assert labels[-1] == 0 and not probs[-1].any()
