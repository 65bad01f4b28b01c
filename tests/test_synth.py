"""The synthetic sequence generator: determinism, geometry, label noise, files, the loop."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from tisem.labels import LEARNING_MAP_INV, raw_to_train
from tisem.synth import SyntheticSequence, iter_synthetic, to_scan, write_semantickitti
from tisem.synth.lidar import Lidar, ray_distances
from tisem.synth.scene import MOVING_CAR, PERSON_INSTANCE, make_rng
from tisem.synth.sequence import kitti08_tr
from tisem.synth.shapes import SHAPE_KINDS, Boxes, Cylinders, Ellipsoids, ShapeSet

SCENE_RAW_IDS = {10, 252, 30, 40, 44, 48, 50, 51, 70, 71, 72, 80, 81}


@pytest.fixture(scope="module")
def street():
    """Five full-resolution scans of the default street (shared by the content tests)."""
    return list(iter_synthetic(5, seed=0))


def _same(a, b) -> bool:
    return all(
        np.array_equal(getattr(a, k), getattr(b, k))
        for k in ("points", "remission", "gt_raw", "pred_raw", "T_world_lidar", "instance")
    )


# ----------------------------------------------------------------------------- determinism


def test_deterministic_per_seed_and_scan():
    a = SyntheticSequence(4, seed=7, points_per_ring=256)[2]
    b = list(iter_synthetic(4, seed=7, points_per_ring=256))[2]  # in order, tiles cached
    assert _same(a, b)
    # the street's scan i does not depend on how many scans the drive has
    assert _same(a, SyntheticSequence(40, seed=7, points_per_ring=256)[2])
    assert _same(a, SyntheticSequence(4, seed=7, points_per_ring=256).frame(2))
    c = SyntheticSequence(4, seed=8, points_per_ring=256)[2]
    assert len(a.points) != len(c.points) or not np.array_equal(a.gt_raw, c.gt_raw)


def test_rng_streams_are_independent_per_key():
    draw = lambda *k: make_rng(*k).random(4)  # noqa: E731
    np.testing.assert_array_equal(draw(0, "tile", 3), draw(0, "tile", 3))
    assert not np.array_equal(draw(0, "tile", 3), draw(0, "tile", -3))
    assert not np.array_equal(draw(0, "tile", 3), draw(1, "tile", 3))


def test_bad_arguments():
    with pytest.raises(ValueError, match="route"):
        SyntheticSequence(3, route="highway")
    with pytest.raises(ValueError, match="points_per_ring"):
        SyntheticSequence(3, points_per_ring=4)
    with pytest.raises(IndexError):
        SyntheticSequence(3)[3]


# ----------------------------------------------------------------------------- geometry


def test_culled_cast_matches_brute_force_intersection():
    """The azimuth/elevation culling must not lose a hit: compare with every ray against
    every primitive, on random primitives around a sensor, with the range noise off."""
    rng = np.random.default_rng(1)
    n = 40
    u = lambda lo, hi, k=n: rng.uniform(lo, hi, k)  # noqa: E731
    lab = lambda: np.full(n, 50, dtype=np.uint32)  # noqa: E731
    xy = np.column_stack([u(-40, 40), u(-40, 40)])
    shapes = ShapeSet(
        {
            Boxes: Boxes(
                label=lab(),
                instance=lab() * 0,
                center=np.column_stack([xy, u(0, 3)]),
                half=np.column_stack([u(0.05, 6), u(0.05, 3), u(0.2, 3)]),
                yaw=u(-3, 3),
            ),
            Cylinders: Cylinders(
                label=lab(),
                instance=lab() * 0,
                center=xy[::-1] * 0.7,
                radius=u(0.05, 0.6),
                z0=u(-0.5, 0.5),
                z1=u(0.6, 8),
            ),
            Ellipsoids: Ellipsoids(
                label=lab(),
                instance=lab() * 0,
                center=np.column_stack([-xy, u(0.5, 5)]),
                radii=np.column_stack([u(0.3, 3), u(0.3, 3), u(0.3, 2)]),
            ),
        }
    )
    lidar = Lidar(points_per_ring=128, range_noise_m=0.0)
    T = np.eye(4)
    T[:3, 3] = [0.3, -0.2, lidar.mount_height_m]
    yaw = 0.4
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    ret = lidar.cast(shapes, lambda p: np.full(len(p), 40, np.uint32), T, rng)

    dirs = lidar.directions @ T[:3, :3].T
    best = np.where(dirs[:, 2] < 0, -T[2, 3] / np.minimum(dirs[:, 2], -1e-12), np.inf)
    for kind in SHAPE_KINDS:
        part = shapes.parts[kind]
        ray, idx = np.divmod(np.arange(len(dirs) * len(part)), len(part))
        t = ray_distances(part, idx, T[:3, 3], dirs[ray]).reshape(len(dirs), len(part))
        best = np.minimum(best, t.min(axis=1))
    hit = np.flatnonzero(best <= lidar.max_range_m)
    np.testing.assert_array_equal(ret.ring * lidar.points_per_ring + ret.col, hit)
    np.testing.assert_allclose(ret.range_m, best[hit], atol=1e-9)
    assert (ret.label == 50).sum() > 100 and (ret.label == 40).sum() > 100


def test_primitive_distances_are_analytic():
    o = np.array([0.0, 0.0, 1.0])
    x = np.array([[1.0, 0.0, 0.0]])
    one = np.zeros(1, dtype=np.uint32)
    box = Boxes(
        label=one,
        instance=one,
        center=np.array([[10.0, 0.0, 1.0]]),
        half=np.array([[2.0, 1.0, 1.0]]),
        yaw=np.array([np.pi / 2]),
    )  # turned: 1 m deep
    cyl = Cylinders(
        label=one,
        instance=one,
        center=np.array([[6.0, 0.0]]),
        radius=np.array([0.5]),
        z0=np.array([0.0]),
        z1=np.array([3.0]),
    )
    ell = Ellipsoids(
        label=one,
        instance=one,
        center=np.array([[20.0, 0.0, 1.0]]),
        radii=np.array([[2.0, 1.0, 1.0]]),
    )
    idx = np.zeros(1, dtype=np.int64)
    assert ray_distances(box, idx, o, x)[0] == pytest.approx(9.0)
    assert ray_distances(cyl, idx, o, x)[0] == pytest.approx(5.5)
    assert ray_distances(ell, idx, o, x)[0] == pytest.approx(18.0)
    assert np.isinf(ray_distances(box, idx, o, -x)[0])  # behind the sensor
    down = np.array([[0.0, 0.0, -1.0]])  # onto a cylinder's top
    cap = Cylinders(
        label=one,
        instance=one,
        center=np.array([[0.0, 0.0]]),
        radius=np.array([0.3]),
        z0=np.array([0.0]),
        z1=np.array([0.4]),
    )
    assert ray_distances(cap, idx, o, down)[0] == pytest.approx(0.6)


# ----------------------------------------------------------------------------- scene content


def test_every_class_appears_and_points_are_sane(street):
    seen = set()
    for f in street:
        n = len(f.points)
        assert 30_000 < n < 70_000
        assert f.points.dtype == np.float32 and f.points.shape == (n, 3)
        assert f.remission.shape == (n,) and f.remission.dtype == np.float32
        assert f.gt_raw.dtype == np.uint32 and f.pred_raw.dtype == np.uint32
        assert f.gt_raw.shape == f.pred_raw.shape == f.instance.shape == (n,)
        assert np.all(np.isfinite(f.points)) and np.all((f.remission >= 0) & (f.remission <= 1))
        r = np.linalg.norm(f.points, axis=1)
        assert r.max() <= 80.0 + 1e-3 and r.min() >= 1.0 - 1e-3
        assert np.all(np.isin(f.pred_raw, LEARNING_MAP_INV[1:]))  # a network: never 0
        assert f.stamp_s == pytest.approx(0.1 * f.index)
        cars = np.isin(f.gt_raw, (10, 252))
        assert np.all(f.instance[cars] > 0) and np.all(f.instance[~cars & (f.gt_raw != 30)] == 0)
        seen |= set(np.unique(f.gt_raw).tolist())
    assert SCENE_RAW_IDS <= seen, f"missing classes: {SCENE_RAW_IDS - seen}"
    # the drive: ~1 m per scan along the road
    step = np.linalg.norm(street[4].T_world_lidar[:3, 3] - street[0].T_world_lidar[:3, 3]) / 4
    assert step == pytest.approx(1.0, abs=0.05)


def test_moving_car_and_person_move(street):
    def world_centroid(f, raw):
        p = f.points[f.gt_raw == raw].astype(np.float64)
        assert len(p) > 20
        return (p @ f.T_world_lidar[:3, :3].T + f.T_world_lidar[:3, 3]).mean(axis=0)

    # the moving car, seen in the data: it travels metres in 0.4 s
    shift = np.linalg.norm(
        world_centroid(street[4], MOVING_CAR) - world_centroid(street[0], MOVING_CAR)
    )
    assert shift > 2.0
    # the person walks (their primitives move between scan times)
    seq = SyntheticSequence(5, seed=0)
    person = [seq.world.actors(t).parts[Cylinders] for t in (0.0, 0.4)]
    c = [p.center[p.instance == PERSON_INSTANCE][0] for p in person]
    assert 0.3 < np.linalg.norm(c[1] - c[0]) < 1.0  # ~1.3 m/s walking
    # and both are left out of a static render
    static = seq.frame(0, dynamic=False)
    assert not np.isin(static.gt_raw, (MOVING_CAR, 30)).any()


@pytest.mark.slow
def test_noisy_labels_accuracy_range_and_boundaries():
    seq = SyntheticSequence(40, seed=2, points_per_ring=512)
    ok, rng_m, edge = [], [], []
    sub_rng = np.random.default_rng(0)
    for i in (0, 13, 26, 39):
        f = seq[i]
        gt, _ = raw_to_train(f.gt_raw)
        pred, _ = raw_to_train(f.pred_raw)
        assert np.count_nonzero(pred == 0) == 0
        ok.append(pred == gt)
        rng_m.append(np.linalg.norm(f.points, axis=1))
        # near a class boundary in 3D: another class within 0.5 m (brute force on a sample)
        sub = sub_rng.choice(len(gt), 300, replace=False)
        d2 = ((f.points[sub, None, :] - f.points[None, :, :]) ** 2).sum(axis=-1)
        mark = np.full(len(gt), -1)
        mark[sub] = ((d2 < 0.25) & (gt[None, :] != gt[sub, None])).any(axis=1)
        edge.append(mark)
    ok, rng_m, edge = map(np.concatenate, (ok, rng_m, edge))
    accuracy = ok.mean()
    assert 0.75 < accuracy < 0.92, accuracy
    near, far = ok[rng_m < 15].mean(), ok[rng_m > 30].mean()
    assert 1 - far > 1.5 * (1 - near), (near, far)
    interior, boundary = ok[edge == 0].mean(), ok[edge == 1].mean()
    assert 1 - boundary > 1.3 * (1 - interior), (interior, boundary)


# ----------------------------------------------------------------------------- the loop


def test_loop_goes_far_and_comes_back():
    seq = SyntheticSequence(4000, seed=0, route="loop")
    xy = seq.poses()[:, :2, 3]
    from_start = np.linalg.norm(xy - xy[0], axis=1)
    assert from_start.max() > 800.0  # a long excursion
    assert from_start[3000:].min() < 20.0  # back at the start ...
    assert from_start[-1] > 50.0  # ... and on past it
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert np.allclose(step, 1.0, atol=0.02)  # 10 m/s (a little more in the outer lane)


def test_loop_revisit_sees_the_same_scene():
    seq = SyntheticSequence(1100, seed=3, route="loop", points_per_ring=256)  # a 1 km loop
    revisit = 1000
    np.testing.assert_allclose(seq.poses([revisit])[0], seq.poses([0])[0], atol=1e-9)
    first = seq.frame(0, dynamic=False)
    for i in (250, 500, 750):  # round the loop: the start's tiles leave the cache
        seq.frame(i, dynamic=False)
    assert seq.world.tile_id(0.0) not in seq.world.cached_tile_ids
    again = seq.frame(revisit, dynamic=False)
    np.testing.assert_array_equal(again.gt_raw, first.gt_raw)
    np.testing.assert_allclose(again.points, first.points, atol=0.2)  # only range noise differs
    # fresh label noise at the revisit: errors come in coherent patches that move between scans
    gt = raw_to_train(first.gt_raw)[0]
    err = [raw_to_train(f.pred_raw)[0] != gt for f in (first, again)]
    overlap = (err[0] & err[1]).sum() / (err[0] | err[1]).sum()
    assert overlap < 0.5, overlap
    for e in err:  # points are in ring-major order: the next point is the next column
        assert e[1:][e[:-1]].mean() > 1.5 * e.mean()


# ----------------------------------------------------------------------------- outputs


def test_to_scan(street):
    f = street[3]
    s = to_scan(f)
    assert s.name == "synthetic/000003" and s.index == 3 and s.stamp_s == pytest.approx(0.3)
    np.testing.assert_array_equal(s.labels, raw_to_train(f.pred_raw)[0])
    np.testing.assert_array_equal(s.gt_labels, raw_to_train(f.gt_raw)[0])
    np.testing.assert_array_equal(s.T_world_sensor, f.T_world_lidar)
    assert s.num_points == len(f.points)


def test_write_semantickitti_round_trip(tmp_path):
    n = 3
    out = write_semantickitti(tmp_path / "08", n, seed=1, points_per_ring=128, progress=False)
    frames = list(iter_synthetic(n, seed=1, points_per_ring=128))
    calib = dict(line.split(":", 1) for line in (out / "calib.txt").read_text().splitlines())
    assert {"P0", "P1", "P2", "P3", "Tr"} <= set(calib)
    Tr = np.eye(4)
    Tr[:3] = np.array(calib["Tr"].split(), dtype=float).reshape(3, 4)
    np.testing.assert_allclose(Tr, kitti08_tr())
    assert not np.allclose(Tr, np.eye(4))
    poses = np.loadtxt(out / "poses.txt").reshape(-1, 3, 4)
    times = np.loadtxt(out / "times.txt")
    assert len(poses) == n and np.allclose(times, 0.1 * np.arange(n))
    for i, f in enumerate(frames):
        raw = (out / "velodyne" / f"{i:06d}.bin").read_bytes()
        assert len(raw) % 16 == 0
        cloud = np.frombuffer(raw, dtype="<f4").reshape(-1, 4)
        np.testing.assert_array_equal(cloud[:, :3], f.points)
        np.testing.assert_array_equal(cloud[:, 3], f.remission)
        labels = np.fromfile(out / "labels" / f"{i:06d}.label", dtype="<u4")
        preds = np.fromfile(out / "predictions" / f"{i:06d}.label", dtype="<u4")
        assert len(labels) == len(preds) == len(cloud)
        np.testing.assert_array_equal(labels & 0xFFFF, f.gt_raw)
        np.testing.assert_array_equal(labels >> 16, f.instance)
        np.testing.assert_array_equal(preds, f.pred_raw)
        P = np.eye(4)
        P[:3] = poses[i]
        np.testing.assert_allclose(np.linalg.inv(Tr) @ P @ Tr, f.T_world_lidar, atol=1e-9)


def test_make_synthetic_app(tmp_path, caplog):
    path = Path(__file__).resolve().parents[1] / "apps" / "make_synthetic.py"
    spec = importlib.util.spec_from_file_location("make_synthetic", path)
    app = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(app)
    main, parse_args = app.main, app.parse_args
    args = parse_args(["--out", str(tmp_path / "s"), "--scans", "2", "--seed", "3"])
    assert args.route == "street" and args.points_per_ring == 1024
    caplog.set_level("INFO")
    assert (
        main(
            [
                "--out",
                str(tmp_path / "s"),
                "--scans",
                "2",
                "--points-per-ring",
                "64",
                "--no-progress",
            ]
        )
        == 0
    )
    assert len(list((tmp_path / "s" / "velodyne").glob("*.bin"))) == 2
    assert "accuracy" in caplog.text
