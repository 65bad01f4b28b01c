"""The mapper on analytic scenes with known answers.

* a noisy road plane comes out clean; class boundaries are recovered (st, adaptive, bki);
* `csm` is exact per-voxel counting (count and unit weighting);
* the temporal decay switches a voxel's class after exactly the number of scans tau predicts,
  and without decay only after as many scans as it had;
* per-point probabilities: one-hot equals labels, split mass is split accordingly;
* `debug=True` (out-of-bounds accesses raise): the edge of the window, far from the origin.

Building a map compiles the engine's kernels for it (~1.5 s; one map per Taichi runtime), so
each map below runs several stories in regions (and at times) far enough apart not to touch
each other, in a module-scoped fixture that keeps only numpy results; the tests then check
those. Every story's scans are built from analytic shapes with known labels (tests/helpers.py).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import taichi as ti
from helpers import (
    A_CLASS,
    B_CLASS,
    BUILDING,
    POLE,
    RES,
    ROAD,
    SHIFT_M,
    SIDEWALK,
    C,
    distance_to_other_class,
    fresh_runtime,
    plane_story,
    pose,
    predicted_switch,
    probs_story,
    region,
    scan_from_world,
    small_config,
    street_scene,
    switch_story,
    voxel_keys,
    voxel_scans,
)

from tisem.mapper import Mapper
from tisem.scan import Scan

K_A = {"st": 30, "debug": 30, "adaptive": 12}  # scans of class A before the switch


# --------------------------------------------------------------------------- the maps


def _finish(result):
    ti.reset()
    return result


def street_map(seed, **cfg):
    """A fresh runtime and map in the given mode that has seen the street (plane_story at
    t = 10 s): (cfg, mapper, rng, plane result)."""
    fresh_runtime()
    cfg = small_config(min_range_m=1.0, **cfg)
    mapper = Mapper(cfg)
    rng = np.random.default_rng(seed)
    return cfg, mapper, rng, plane_story(mapper, rng, 10.0)


@pytest.fixture(scope="module")
def st_map():
    """st, tau 2 s: the street (t = 10 s), then the class switch of the probe (t = 20 s)."""
    cfg, mapper, rng, plane = street_map(2, mode="st", tau_s=2.0)
    n_star = predicted_switch(math.exp(-0.1 / cfg.tau_s), K_A["st"])
    switch = switch_story(mapper, 20.0, [0.0, -17.0, 0.5], K_A["st"], n_star + 2)
    return _finish(SimpleNamespace(cfg=cfg, plane=plane, switch=switch))


@pytest.fixture(scope="module")
def adaptive_map():
    """adaptive: the street, then the probe with as many B scans as A scans and one more."""
    cfg, mapper, rng, plane = street_map(3, mode="adaptive")
    switch = switch_story(mapper, 20.0, [0.0, -17.0, 0.5], K_A["adaptive"], K_A["adaptive"] + 1)
    return _finish(SimpleNamespace(cfg=cfg, plane=plane, switch=switch))


@pytest.fixture(scope="module")
def bki_map():
    """bki: the street, then labels vs probabilities in regions 1-3."""
    # (no evidence caps: the probability regions split mass between classes 3 and 5, and a
    # cap on motorcycle's reach would change the split; the capped bki is in test_kernels.py)
    cfg, mapper, rng, plane = street_map(4, mode="bki", thin_classes=[], vehicle_classes=[])
    probs = probs_story(mapper, rng, 20.0)
    return _finish(SimpleNamespace(cfg=cfg, plane=plane, probs=probs, snap=mapper.snapshot()))


def csm_run(weight, min_points, with_probs):
    """csm: voxel scans counted by hand (region 0), then labels vs probabilities (1-3)."""
    fresh_runtime()
    cfg = small_config(mode="csm", point_weight=weight, min_points=min_points, min_range_m=0.0)
    mapper = Mapper(cfg)
    rng = np.random.default_rng(5)
    scans = voxel_scans(rng)
    for s in scans:
        mapper.integrate(s)
    probs = probs_story(mapper, rng, 20.0) if with_probs else None
    return _finish(SimpleNamespace(cfg=cfg, scans=scans, probs=probs, snap=mapper.snapshot()))


@pytest.fixture(scope="module")
def csm_map():
    return csm_run("count", 1, with_probs=True)


@pytest.fixture(scope="module")
def csm_unit_map():
    return csm_run("unit", 3, with_probs=False)


@pytest.fixture(scope="module")
def debug_map():
    """debug=True, st with tau 0.5 s and the tightest window the config allows:
    1. a map started 5.8 km from the world origin, a jump of 2 km and back, and a pose out of
       reach of the map's keys;
    2. the probe's class switch (at home + 300 m);
    3. the edge of the window (at home + 600 m): a pitched sensor whose far points leave the
       window in z, points at max range in every direction, moves of a window half-width."""
    fresh_runtime(debug=True)
    cfg = small_config(
        mode="st", tau_s=0.5, window_xy_m=20.0 + 1.2 + 0.8, window_z_m=4.0 + 1.2 + 0.8
    )
    mapper = Mapper(cfg)
    rng = np.random.default_rng(8)
    out = SimpleNamespace(cfg=cfg)
    # 1. far from the origin
    home = np.array([5000.3, -3000.7, 50.2])
    xyz, gt = street_scene(rng)
    sub = rng.random(len(xyz)) < 0.1
    xyz, gt = xyz[sub], gt[sub]
    for i, offset in enumerate([0.0, 0.0, 2000.0, 0.0]):
        T = pose(*(home + [offset, 0, 1.7]), yaw=0.1 * i)
        mapper.integrate(
            scan_from_world(xyz + home + [offset, 0, 0], T, 1e6 + 0.1 * i, labels=gt, index=i)
        )
    out.far_gt = gt
    out.far_home = mapper.query(xyz + home)[0]
    out.far_away = mapper.query(xyz + home + [2000.0, 0, 0])[0]
    out.far_stored = mapper.stored_voxels
    far = pose(*(home + [3.0e5, 0, 0]))
    try:
        mapper.integrate(scan_from_world(xyz + far[:3, 3], far, 1e6 + 1.0, labels=gt, index=9))
        out.far_error = None
    except ValueError as exc:
        out.far_error = str(exc)
    out.far_home_after = mapper.query(xyz + home)[0]
    # 2. the class switch
    n_star = predicted_switch(math.exp(-0.1 / cfg.tau_s), K_A["debug"])
    out.switch = switch_story(mapper, 1e6 + 10.0, home + [300.0, 0, 0], K_A["debug"], n_star + 2)
    # 3. the edge of the window
    base = home + [600.0, 0, 0]
    d = rng.normal(size=(6000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.where(rng.random(6000) < 0.5, 19.999, rng.uniform(1.0, 20.5, 6000))
    sensor = d * r[:, None]
    sensor[:, 2] = np.clip(sensor[:, 2], -4.0, 4.0)  # the band's edges
    labels = rng.integers(1, C, len(sensor)).astype(np.int32)
    out.edge_range = np.linalg.norm(sensor, axis=1)
    out.edge_reports, out.edge_first_labels, out.edge_disagree = [], None, []
    for i, T in enumerate(
        [
            pose(*(base + [0, 0, 1.7])),
            pose(*(base + [0, 0, 1.7]), pitch=0.4, yaw=0.3),
            pose(*(base + [22.0, -22.0, 7.7]), pitch=-0.3),
            pose(*(base + [22.0, -22.0, 7.7]), roll=0.5),
        ]
    ):
        scan = Scan(
            points_sensor=sensor,
            T_world_sensor=T,
            stamp_s=1e6 + 20.0 + 0.1 * i,
            labels=labels,
            index=i,
        )
        out.edge_reports.append(mapper.integrate(scan))
        if i == 0:
            out.edge_first_labels = mapper.query(scan.points_world())[0]
        snap = mapper.snapshot()  # the query must see every voxel the map holds
        out.edge_disagree.append(
            int(
                np.count_nonzero(
                    mapper.query(snap.centers())[0] != snap.point_labels(snap.centers())
                )
            )
        )
    out.edge_random = mapper.query(
        base + np.random.default_rng(1).uniform([-60, -60, -20], [60, 60, 30], (20000, 3))
    )
    snap = mapper.snapshot()
    out.snap_size, out.snap_finite = len(snap), bool(np.isfinite(snap.counts).all())
    return _finish(out)


# --------------------------------------------------------------------------- plane, boundaries


@pytest.mark.parametrize(
    "mode",
    [
        "st",
        pytest.param("adaptive", marks=pytest.mark.slow),
        pytest.param("bki", marks=pytest.mark.slow),
    ],
)
def test_noisy_plane_and_boundaries(request, mode):
    """Input 80 % right: the road plane comes out >= 99 % road, and every point farther than
    the kernel's reach from another class gets its own class back (sidewalk, wall, pole)."""
    run = request.getfixturevalue(f"{mode}_map")
    pl, cfg = run.plane, run.cfg
    road = pl.gt == ROAD
    assert 0.79 < (pl.noisy[road] == ROAD).mean() < 0.81
    acc = (pl.pred[road] == ROAD).mean()
    assert acc >= 0.99, f"{mode}: {acc:.4f} of the road plane is road"
    # a voxel centre may lie half a voxel diagonal from its points, and a training point (a
    # centroid) as far from the points it stands for
    reach = cfg.reach_m + math.sqrt(3) * cfg.resolution_m
    # (the road is 2 m from every other class, farther than any reach: leave it out)
    far = np.zeros(len(pl.xyz), bool)
    far[~road] = distance_to_other_class(pl.xyz[~road], pl.gt[~road]) > reach
    for c in (SIDEWALK, BUILDING, POLE):
        sel = far & (pl.gt == c)
        assert sel.sum() > 1000, f"too few points of class {c} far from other classes"
        assert (pl.noisy[sel] == c).mean() < 0.81
        acc = (pl.pred[sel] == c).mean()
        assert acc >= 0.99, f"{mode}: class {c}: {acc:.4f} of its far points right"


# --------------------------------------------------------------------------- csm


@pytest.mark.parametrize("fixture", ["csm_map", "csm_unit_map"], ids=["count", "unit-min3"])
def test_csm_is_exact_per_voxel_counting(request, fixture):
    run = request.getfixturevalue(fixture)
    cfg, snap = run.cfg, run.snap
    want: dict[tuple, np.ndarray] = {}
    for s in run.scans:
        keys, inv, npts = np.unique(
            voxel_keys(s.points_world(), RES), axis=0, return_inverse=True, return_counts=True
        )
        inv = inv.reshape(-1)
        hist = np.zeros((len(keys), C))
        lab = s.labels > 0
        np.add.at(hist, (inv[lab], s.labels[lab]), 1.0)
        total = hist.sum(axis=1)
        for k, h, n, tot in zip(map(tuple, keys), hist, npts, total):
            if n >= cfg.min_points and tot > 0:  # the filter: enough points, some evidence
                add = h if cfg.point_weight == "count" else h / tot
                want[k] = want.get(k, 0.0) + add
    r0 = region(snap, 0)
    want_keys = np.array(sorted(want))
    np.testing.assert_array_equal(snap.keys[r0], want_keys)
    want_counts = np.array([want[tuple(k)] for k in want_keys])
    got = snap.counts[r0]
    if cfg.point_weight == "count":
        np.testing.assert_array_equal(got, want_counts)  # integer sums: exact
    else:
        np.testing.assert_allclose(got, want_counts, rtol=1e-6, atol=0)
    top = np.sort(want_counts, axis=1)[:, ::-1]
    clear = top[:, 0] - top[:, 1] > 1e-5  # no tie to break
    np.testing.assert_array_equal(snap.labels()[r0][clear], want_counts.argmax(1)[clear])
    assert (got[:, 0] == 0).all(), "class 0 adds no evidence"
    if cfg.min_points > 1:
        hit = np.unique(
            np.concatenate([voxel_keys(s.points_world(), RES) for s in run.scans]), axis=0
        )
        assert len(want_keys) < len(hit), "min_points should have dropped voxels"


# --------------------------------------------------------------------------- decay


@pytest.mark.parametrize(
    "tau_s,fixture", [pytest.param(0.5, "debug_map", marks=pytest.mark.slow), (2.0, "st_map")]
)
def test_decay_switches_class_after_predicted_scans(request, tau_s, fixture):
    """st: class A for 30 scans (0.1 s apart), then class B: the map follows B exactly from
    the n*-th B scan that sigma_t = alpha sigma_{t-1} + Delta predicts, alpha = exp(-0.1/tau)."""
    run = request.getfixturevalue(fixture)
    sw = run.switch
    assert run.cfg.tau_s == tau_s
    alpha = math.exp(-0.1 / tau_s)
    n_star = predicted_switch(alpha, sw.k)
    assert sw.label_a == A_CLASS
    assert set(sw.labels) <= {A_CLASS, B_CLASS}
    switched = sw.labels.index(B_CLASS) + 1 if B_CLASS in sw.labels else None
    assert switched == n_star, (
        f"tau {tau_s} s: switched after {switched} B scans, predicted {n_star}"
    )
    assert all(lab == B_CLASS for lab in sw.labels[n_star - 1 :]), "switched back"
    # and the counters are the recursion's
    delta = sw.first[:, A_CLASS]
    assert (delta > 0).all()
    geo = (1 - alpha**sw.k) / (1 - alpha)
    np.testing.assert_allclose(sw.after_a[:, A_CLASS], delta * geo, rtol=1e-4)
    n = len(sw.labels)
    np.testing.assert_allclose(sw.end[:, A_CLASS], delta * alpha**n * geo, rtol=1e-4)
    np.testing.assert_allclose(sw.end[:, B_CLASS], delta * (1 - alpha**n) / (1 - alpha), rtol=1e-4)


def test_no_decay_switches_only_after_as_many_scans(adaptive_map):
    """adaptive (alpha = 1): after k A scans, B needs k scans to tie and k + 1 to win."""
    sw = adaptive_map.switch
    k = sw.k
    assert sw.label_a == A_CLASS
    assert sw.labels[: k - 1] == [A_CLASS] * (k - 1), f"switched too early: {sw.labels}"
    np.testing.assert_allclose(sw.tie[:, B_CLASS], sw.tie[:, A_CLASS], rtol=1e-5)  # a tie
    assert sw.labels[k] == B_CLASS, f"not switched after {k + 1} B scans for {k} A scans"
    np.testing.assert_allclose(sw.end[:, A_CLASS], k * sw.first[:, A_CLASS], rtol=1e-5)
    np.testing.assert_allclose(sw.end[:, B_CLASS], (k + 1) * sw.first[:, A_CLASS], rtol=1e-5)


# --------------------------------------------------------------------------- probabilities


@pytest.mark.parametrize("mode", ["csm", pytest.param("bki", marks=pytest.mark.slow)])
def test_probabilities_one_hot_equal_labels_and_split_mass(request, mode):
    """The same scans as labels (region 1) and as one-hot probabilities (region 2: the same
    sensor-frame points, poses 64 m away) give the same voxels and counters; points whose
    mass is split between two classes (and class 0) split the evidence 70/30."""
    run = request.getfixturevalue(f"{mode}_map")
    snap, pr = run.snap, run.probs
    n_shift = int(round(SHIFT_M / RES))
    r1, r2, r3 = region(snap, 1), region(snap, 2), region(snap, 3)
    assert r1.sum() > 1000
    np.testing.assert_array_equal(snap.keys[r1] + [n_shift, 0, 0], snap.keys[r2])
    if mode == "csm":
        np.testing.assert_array_equal(snap.counts[r1], snap.counts[r2])
    else:  # float32 coordinates 64 m apart round differently (~1e-5 m): a tolerance
        np.testing.assert_allclose(snap.counts[r1], snap.counts[r2], rtol=1e-3, atol=1e-4)
    top = np.sort(snap.counts[r1], axis=1)[:, ::-1]
    clear = top[:, 0] - top[:, 1] > 1e-3 * top[:, 0]
    np.testing.assert_array_equal(snap.labels()[r1][clear], snap.labels()[r2][clear])

    assert r3.sum() > 300
    prob = snap.probabilities()[r3]
    np.testing.assert_allclose(prob[:, 3], 0.7, atol=1e-5)
    np.testing.assert_allclose(prob[:, 5], 0.3, atol=1e-5)
    assert (snap.labels()[r3] == 3).all()
    if mode == "csm":  # count weighting: the evidence is the summed probabilities, class 0 out
        keys, inv = np.unique(voxel_keys(pr.patch, RES), axis=0, return_inverse=True)
        want = np.zeros((len(keys), C))
        np.add.at(want, inv.reshape(-1), pr.p.astype(np.float64))
        want[:, 0] = 0
        np.testing.assert_array_equal(snap.keys[r3], keys)
        np.testing.assert_allclose(snap.counts[r3], want, rtol=1e-6, atol=1e-7)
    assert (pr.patch_labels == 3).all()
    np.testing.assert_allclose(
        pr.patch_probs[:, [3, 5]], np.tile([0.7, 0.3], (len(pr.patch), 1)), atol=1e-5
    )


# --------------------------------------------------------------------------- debug=True


@pytest.mark.slow
def test_debug_pose_far_from_the_origin(debug_map):
    out = debug_map
    for name in ("far_home", "far_away", "far_home_after"):
        acc = (getattr(out, name) == out.far_gt).mean()
        assert acc > 0.97, f"{name}: {acc:.4f}"
    assert out.far_stored > 0, "the 2 km jump should have sent the first blocks to the store"
    assert out.far_error is not None and "km from the map origin" in out.far_error


def test_debug_scan_at_the_edge_of_the_window(debug_map):
    out = debug_map
    n = len(out.edge_range)
    in_range = (out.edge_range <= 20.0) & (out.edge_range >= 2.0)
    for rep in out.edge_reports:
        assert (
            rep.used
            + rep.dropped_range
            + rep.dropped_band
            + rep.dropped_window
            + rep.dropped_nonfinite
            == n
        )
        assert rep.dropped_range == np.count_nonzero(~in_range)
    first = out.edge_reports[0]
    assert first.dropped_window == 0  # a level sensor: every point in range fits
    assert (out.edge_first_labels[in_range] > 0).all()
    assert any(rep.dropped_window > 0 for rep in out.edge_reports[1:]), (
        "the tilted scans' far points leave the window in z: dropped and counted"
    )
    assert out.edge_reports[2].evicted_voxels > 0
    assert out.edge_disagree == [0] * len(out.edge_reports), (
        "query and snapshot disagree on voxels the map holds (near the window's face)"
    )
    lab, prob = out.edge_random
    assert lab.min() >= 0 and lab.max() < C and np.isfinite(prob).all()
    assert out.snap_size > 0 and out.snap_finite


def test_a_scan_with_more_points_than_training_rows_can_count_is_refused(taichi_cpu, monkeypatch):
    """Training rows pass through float32 (exact below 2^24): a scan that could need more is
    refused with its name before any kernel runs, and the map is untouched."""
    from tisem.kernels import layout

    mapper = Mapper(small_config(mode="st"))
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (50, 3))
    labels = np.full(50, ROAD, np.int32)
    monkeypatch.setattr(layout, "MAX_SCAN_POINTS", 50)
    with pytest.raises(ValueError, match="50 points; tisem takes at most 49"):
        mapper.integrate(Scan(pts, np.eye(4), 0.0, labels=labels, name="big"))
    assert mapper.live_voxels == 0
    monkeypatch.setattr(layout, "MAX_SCAN_POINTS", 51)
    mapper.integrate(Scan(pts, np.eye(4), 0.0, labels=labels, name="big"))
    assert mapper.live_voxels > 0


def test_a_range_that_needs_too_big_a_scan_table_is_refused(taichi_cpu):
    """The scan's table is dense (every leaf block within max_range of the sensor): a range and
    resolution that need more cells than int32 ids and memory allow are refused up front."""
    cfg = small_config(
        max_range_m=900.0, resolution_m=0.02, window_xy_m=910.0, ell_min_m=0.04, ell_max_m=0.16
    )
    with pytest.raises(ValueError, match=r"needs a scan table of [\d,]+ leaf blocks"):
        Mapper(cfg)


def test_points_given_as_the_first_columns_of_wider_rows_map_as_their_copy():
    """The KITTI reader's points are a view of its x y z intensity rows; the kernels read them
    in place (`kernel_rows`), not copied. The map is bitwise the one of the same points given
    as their own (N, 3) array, with free space too (its kernel reads the points), for a scan
    with a non-finite point (copied, to move it away) and one whose rows end the memory."""
    from tisem.preprocess import check_scan, kernel_rows

    rng = np.random.default_rng(7)
    world, gt = street_scene(rng)
    T = pose(0.3, -0.2, 1.7, yaw=0.4)
    base = scan_from_world(world, T, 0.0, labels=gt)
    n = len(gt)
    rows = np.concatenate([base.points_sensor, rng.random((n, 1), np.float32)], axis=1)
    view = rows[:, :3]
    assert np.shares_memory(kernel_rows(view), rows) and kernel_rows(view).shape == (n, 4)
    checked = check_scan(Scan(view, T, 0.0, labels=gt), C)  # (the mapper's own check)
    assert np.shares_memory(checked.kernel_points, rows)
    shifted = np.concatenate([rng.random((n, 1), np.float32), base.points_sensor], axis=1)
    assert kernel_rows(shifted[:, 1:]).shape == (n, 3)  # (the fourth column would pass the end)
    broken = view.copy()
    broken[5] = np.nan

    def snapshot(points: list[np.ndarray]):
        fresh_runtime()
        mapper = Mapper(small_config(mode="st", free_space=True))
        for k, p in enumerate(points):
            mapper.integrate(Scan(p, T, 0.1 * k, labels=gt, index=k))
        return _finish(mapper.snapshot())

    wide = snapshot([view, shifted[:, 1:], np.concatenate([broken, rows[:, 3:]], axis=1)[:, :3]])
    own = snapshot([np.ascontiguousarray(view), shifted[:, 1:].copy(), broken])
    assert len(wide.keys) > 1000
    for name in ("keys", "counts", "t_last", "ell_m", "occupancy"):
        assert np.array_equal(getattr(wide, name), getattr(own, name)), name


def test_points_and_labels_in_read_only_memory_reach_the_kernels_as_copies():
    """A CUDA launch copies every host array back after the kernel: arrays in read-only memory
    (a read-only mmap, bytes) reach the kernels as writeable copies, wider rows and all, and so
    do unaligned ones; writeable, aligned ones are not copied."""
    from tisem.preprocess import check_scan

    rows = np.arange(40, dtype=np.float32).reshape(10, 4)
    labels = np.full(10, ROAD, np.int32)
    frozen = np.frombuffer(rows.tobytes(), np.float32).reshape(10, 4)  # (bytes: read-only)
    frozen_labels = np.frombuffer(labels.tobytes(), np.int32)
    shifted = np.r_[np.zeros(2, np.uint8), rows.view(np.uint8).ravel()]  # rows at byte 2
    unaligned = np.frombuffer(shifted.data, np.float32, offset=2).reshape(10, 4)
    cases = [
        (rows[:, :3], labels, True),
        (frozen[:, :3], frozen_labels, False),
        (frozen[:, :3].copy(), labels, True),
        (unaligned[:, :3], labels, False),
    ]
    for points, ids, in_place in cases:
        checked = check_scan(Scan(points, np.eye(4), 0.0, labels=ids), C)
        for a in (checked.kernel_points, checked.evidence):
            assert a.flags.c_contiguous and a.flags.aligned
        assert checked.evidence.flags.writeable
        assert np.array_equal(checked.kernel_points[:, :3], rows[:, :3])
        assert np.shares_memory(checked.kernel_points, points) == in_place
        if not in_place:
            assert checked.kernel_points.flags.writeable
