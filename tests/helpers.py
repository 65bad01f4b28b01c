"""Shared builders for the engine tests: runtimes, configs, poses, scans, analytic scenes with
known labels (a street, probes, mixed ground), and readers of what each step of
`Mapper.integrate` produced (from a `tisem.trace.IntegrationTrace`).

Taichi rules these follow: every test gets its own runtime (the `taichi_cpu` fixture of
conftest.py: `init_taichi("cpu", threads=2)`, one Mapper per runtime), because using a field of
an earlier runtime aborts the process; no Taichi object outlives its runtime; and the test
kernels below live in this real source file (Taichi reads kernel source from disk).
Comparisons with the numpy reference (float64 against the kernels' float32) carry named
tolerances.
"""

# (no `from __future__ import annotations`: Taichi reads the kernels' annotations)
import math
import os
from types import SimpleNamespace

import numpy as np
import taichi as ti
from scipy.spatial import cKDTree
from tisem.kernels import bki, entropy
from tisem.kernels.layout import LEAF, TOP, MapFields

from tisem.backend import init_taichi
from tisem.config import MapperConfig
from tisem.reference import voxel_histograms
from tisem.scan import Scan

C = 20
ROAD, SIDEWALK, BUILDING, VEGETATION, POLE = 9, 11, 13, 15, 18
# the analytic scenes (below, for tests/test_mapper.py)
RES = 0.2
SHIFT_M = 64.0  # region spacing: a whole number of voxels and of top cells
A_CLASS, B_CLASS = ROAD, BUILDING  # A < B: at an exact tie the map keeps A


# --------------------------------------------------------------------------- runtimes


def fresh_runtime(debug: bool = False) -> None:
    """A new Taichi runtime (every map built before it is gone: never touch it again).
    TISEM_TEST_DEBUG=1 runs every test's kernels with Taichi's bounds checks (several times
    slower; an out-of-range index raises instead of corrupting memory)."""
    debug = debug or os.environ.get("TISEM_TEST_DEBUG") == "1"
    init_taichi("cpu", threads=2, debug=debug)


def small_config(**kw) -> MapperConfig:
    """A 20 m sensor in a 30 m window (the same sizes as tests/test_checkpoint.py, so the
    offline kernel cache is shared)."""
    base = dict(max_range_m=20.0, window_xy_m=30.0, window_z_m=12.0, min_z_m=-4.0, max_z_m=4.0)
    base.update(kw)
    return MapperConfig(**base)


# --------------------------------------------------------------------------- geometry


def pose(x=0.0, y=0.0, z=0.0, yaw=0.0, pitch=0.0, roll=0.0) -> np.ndarray:
    """T_world_sensor from a position and ZYX Euler angles (radians)."""
    cz, sz, cy, sy, cx, sx = (
        math.cos(yaw),
        math.sin(yaw),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(roll),
        math.sin(roll),
    )
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = [x, y, z]
    return T


def scan_from_world(
    world_xyz, T, stamp_s, labels=None, probs=None, gt=None, index=0, name=""
) -> Scan:
    """A `Scan` whose sensor-frame points are the given world points seen from pose T."""
    world_xyz = np.asarray(world_xyz, np.float64)
    sensor = (world_xyz - T[:3, 3]) @ T[:3, :3]
    return Scan(
        points_sensor=sensor.astype(np.float32),
        T_world_sensor=T,
        stamp_s=stamp_s,
        labels=labels,
        probs=probs,
        gt_labels=gt,
        index=index,
        name=name,
    )


def away_from_faces(world_xyz, res, margin=0.02) -> np.ndarray:
    """Move points at least `margin` voxels away from every voxel face, so that float32 (tisem)
    and float64 (numpy) put each point in the same voxel."""
    v = np.asarray(world_xyz, np.float64) / res
    base = np.floor(v)
    return (base + np.clip(v - base, margin, 1 - margin)) * res


def voxel_keys(world_xyz, res) -> np.ndarray:
    return np.floor(np.asarray(world_xyz, np.float64) / res).astype(np.int64)


def grid_plane(x_range, y_range, z, spacing, rng=None) -> np.ndarray:
    """Points on the horizontal plane z on a grid (jittered by up to half a spacing)."""
    xs = np.arange(x_range[0] + spacing / 2, x_range[1], spacing)
    ys = np.arange(y_range[0] + spacing / 2, y_range[1], spacing)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, float(z))])
    if rng is not None:
        pts[:, :2] += rng.uniform(-spacing / 2, spacing / 2, (len(pts), 2))
    return pts


def one_hot(labels, num_classes=C) -> np.ndarray:
    p = np.zeros((len(labels), num_classes), np.float32)
    p[np.arange(len(labels)), labels] = 1.0
    return p


def flip_labels(labels, fraction, rng) -> np.ndarray:
    """Replace a random `fraction` of the labels by other classes in 1..19."""
    out = np.asarray(labels, np.int32).copy()
    flip = rng.random(len(out)) < fraction
    new = rng.integers(1, C - 1, flip.sum())  # 1..18
    new = np.where(new >= out[flip], new + 1, new)  # never the point's own class
    out[flip] = new
    return out


# --------------------------------------------------------------------------- test kernels


@ti.kernel
def _sample_kernel(
    m: ti.template(),
    r2: ti.types.ndarray(dtype=ti.f32, ndim=1),
    lut: ti.types.ndarray(dtype=ti.f32, ndim=1),
    exact: ti.types.ndarray(dtype=ti.f32, ndim=1),
):
    for i in range(r2.shape[0]):
        lut[i] = bki.sparse_kernel_of_r2(m, r2[i])
        exact[i] = bki.sparse_kernel(ti.sqrt(r2[i]))


def kernel_table_fields() -> MapFields:
    """The smallest map fields (one top cell) with the sparse kernel's table filled in."""
    fields = MapFields(C, (TOP, TOP, TOP), (1, 1, 1))
    bki.fill_kernel_table(fields)
    return fields


def sample_kernel(fields, r2):
    """g(r) at r^2 through the engine's table (`sparse_kernel_of_r2`) and its closed form."""
    r2 = np.ascontiguousarray(r2, np.float32)
    lut, exact = np.zeros_like(r2), np.zeros_like(r2)
    _sample_kernel(fields, r2, lut, exact)
    return lut.astype(np.float64), exact.astype(np.float64)


@ti.kernel
def _entropy(
    p: ti.types.ndarray(dtype=ti.f32, ndim=2),
    ell_min: ti.f32,
    ell_max: ti.f32,
    common: ti.f32,
    h: ti.types.ndarray(dtype=ti.f32, ndim=1),
    ell: ti.types.ndarray(dtype=ti.f32, ndim=1),
    h_common: ti.types.ndarray(dtype=ti.f32, ndim=1),
):
    for i in range(p.shape[0]):
        v = ti.Vector([0.0] * C)
        for c in ti.static(range(C)):
            v[c] = p[i, c]
        h[i] = entropy.normalized_entropy(v, C - 1)
        ell[i] = entropy.adaptive_length(v, ell_min, ell_max, C - 1)
        h_common[i] = entropy.entropy_with_common(
            v, C - 1, common, common * entropy.fast_log(common)
        )


def engine_entropy(p, ell_min, ell_max, common=1.0):
    """(normalised entropy, adaptive length, normalised entropy with the shortcut for classes
    whose p_c equals `common`) of each row of p, by the engine's ti.funcs."""
    p = np.ascontiguousarray(p, np.float32)
    h, ell, h_common = (np.zeros(len(p), np.float32) for _ in range(3))
    _entropy(p, ell_min, ell_max, common, h, ell, h_common)
    return h.astype(np.float64), ell.astype(np.float64), h_common.astype(np.float64)


def _sorted_by_key(keys, *arrays):
    order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
    return (keys[order],) + tuple(a[order] for a in arrays)


def located_voxels(step) -> dict:
    """Step 2 of a traced scan (a `tisem.trace.ScanTrace`): every voxel a kept point fell in
    (global keys, sorted) with its point count and how many of its points carry class evidence.
    Checks on the way that the list of occupied blocks is the points' blocks, and that the block
    sort lists every kept point once, block by block."""
    kept = step.kept
    listed = step.occupied_cells
    assert np.array_equal(np.sort(listed), np.unique(step.point_cell[kept])), (
        "the list of occupied blocks differs from the points' blocks"
    )
    order = step.block_order
    assert np.array_equal(np.sort(order), np.flatnonzero(kept)), (
        "the block sort lost or repeated a point"
    )
    runs = step.point_cell[order]
    # every block's points in one run: a cell id never comes back after another
    starts = np.r_[True, runs[1:] != runs[:-1]]
    assert len(np.unique(runs)) == starts.sum(), "a block's points are split"
    keys, inv, npts = np.unique(
        step.point_voxel[kept], axis=0, return_inverse=True, return_counts=True
    )
    labelled = np.bincount(inv.reshape(-1), step.point_has_evidence[kept], len(keys))
    return dict(keys=keys, npts=npts, labelled=labelled.astype(np.int64), used=int(kept.sum()))


def training_points(step) -> dict:
    """Step 3 of a traced scan: the training points found through the scan's table (global keys
    of their voxels, centroids in world metres, class evidence), sorted by key. Checks on the way
    that every slot of every block's slice is a training point, each once."""
    ends = step.layer_rows  # per cell: the rows up to the end of each z layer
    # each layer's count includes the layers below it: non-decreasing up the block
    assert np.all(np.diff(ends, axis=1) >= 0), "a block's layer ends go down"
    count = ends[:, -1]  # (the last layer's: all the block's rows)
    used = count > 0
    rows = np.concatenate(
        [np.arange(s, s + c) for s, c in zip(step.row_start[used], count[used])]
        or [np.zeros(0, np.int64)]
    )
    n = step.training_rows
    assert len(np.unique(rows)) == len(rows), "two blocks' slices overlap"
    assert len(rows) == n, f"column_slots handed out {n} rows, the table holds {len(rows)}"
    assert rows.size == 0 or (rows.min() >= 0 and rows.max() < n), "a slice past the rows"
    xyz, hist = step.training_xyz[rows], step.training_hist[rows]
    res, origin = step.resolution_m, step.origin_vox
    centroid = xyz.astype(np.float64) + origin * res
    keys = np.floor(xyz.astype(np.float64) / res).astype(np.int64) + origin
    keys, centroid, hist = _sorted_by_key(keys, centroid, hist.copy())
    return dict(keys=keys, centroid=centroid, hist=hist)


def hand_rasterize(scan: Scan, cfg: MapperConfig):
    """Steps 1-2 by hand in float64: (keys, npts, centroid, hist) of every voxel the kept
    points hit (world frame, global keys), sorted by key. Class 0 adds no evidence."""
    from tisem.preprocess import select_points

    sel = select_points(scan, cfg)
    T = scan.T_world_sensor
    world = sel.points_sensor.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    return voxel_histograms(world, sel, cfg.resolution_m, cfg.num_classes)


# --------------------------------------------------------------------------- analytic scenes


def street_scene(rng):
    """World points and ground-truth labels: a 14 m x 14 m road plane around the sensor
    (0.05 m spacing, jittered), and 2 m beyond its edge a sidewalk with a building wall and a
    pole standing on it."""
    # (the ground at z = 0.1 m and the wall at x = 13.1 m lie mid-voxel: a point exactly on a
    # voxel face may be rasterised in float32 into the voxel below and queried into the one
    # above)
    road = grid_plane((-7, 7), (-7, 7), 0.1, 0.05, rng)
    side = grid_plane((9, 14), (-5, 5), 0.1, 0.05, rng)
    wz = np.arange(0.15, 3.5, 0.05)
    wy = np.arange(-4, 4, 0.05)
    Y, Z = np.meshgrid(wy, wz, indexing="ij")
    wall = np.column_stack([np.full(Y.size, 13.1), Y.ravel(), Z.ravel()])
    wall[:, 1:] += rng.uniform(-0.025, 0.025, (len(wall), 2))
    a = rng.uniform(0, 2 * math.pi, 2500)
    pole = np.column_stack(
        [10.5 + 0.1 * np.cos(a), 2.0 + 0.1 * np.sin(a), rng.uniform(0.15, 4.0, 2500)]
    )
    xyz = np.concatenate([road, side, wall, pole])
    gt = np.concatenate(
        [
            np.full(len(road), ROAD),
            np.full(len(side), SIDEWALK),
            np.full(len(wall), BUILDING),
            np.full(len(pole), POLE),
        ]
    ).astype(np.int32)
    return xyz, gt


def plane_story(mapper, rng, t0):
    """Three scans of the street from slightly different poses, 0.1 s apart; input labels
    80 % right (20 % flipped to random other classes, every scan afresh). Returns the query
    of every scan's points after the last one, with the ground truth and the input."""
    poses = [pose(0, 0, 1.7), pose(0.4, -0.3, 1.72, yaw=0.05), pose(-0.3, 0.5, 1.68, yaw=-0.04)]
    scans = []
    for i, T in enumerate(poses):
        xyz, gt = street_scene(rng)
        scans.append(
            scan_from_world(xyz, T, t0 + 0.1 * i, labels=flip_labels(gt, 0.2, rng), gt=gt, index=i)
        )
        mapper.integrate(scans[-1])
    xyz = np.concatenate([s.points_world() for s in scans])
    pred, _ = mapper.query(xyz, with_probs=False)
    return SimpleNamespace(
        xyz=xyz,
        pred=pred,
        gt=np.concatenate([s.gt_labels for s in scans]),
        noisy=np.concatenate([s.labels for s in scans]),
    )


def probe_scan(cls, t, origin, index=0) -> Scan:
    """Six isolated voxels, 3 m apart (farther than any kernel reach), 10 points each at the
    voxel's centre. A voxel's only training point is then its own centroid at distance ~0,
    so every scan brings it the same evidence Delta = 10 sigma0 g(0) whatever its kernel
    length: the fixed geometry of the decay derivation, with the adaptive length left on."""
    keys = np.array([[15 * j, 0, 0] for j in range(6)]) + voxel_keys(origin, RES)
    world = np.repeat((keys + 0.5) * RES, 10, axis=0)
    T = pose(*(np.asarray(origin, float) + [7.5, 3.0, 1.7]))
    return scan_from_world(world, T, t, labels=np.full(len(world), cls, np.int32), index=index)


def probe_labels(mapper, origin) -> int:
    centres = (np.array([[15 * j, 0, 0] for j in range(6)]) + voxel_keys(origin, RES) + 0.5) * RES
    lab, _ = mapper.query(centres, with_probs=False)
    values = np.unique(lab)
    assert len(values) == 1, f"the probe voxels disagree: {lab}"
    return int(values[0])


def switch_story(mapper, t0, origin, k, n_b):
    """k scans of class A, then n_b of class B, 0.1 s apart; the probe's label after each B
    scan, and its counters after the first scan, after the A scans and at the end."""
    mapper.integrate(probe_scan(A_CLASS, t0, origin))
    keys = voxel_keys(probe_scan(A_CLASS, t0, origin).points_world()[::10], RES)

    def counters():
        snap = mapper.snapshot()
        pos = [np.flatnonzero((snap.keys == k_).all(axis=1))[0] for k_ in keys]
        return snap.counts[pos].astype(np.float64)

    first = counters()
    for i in range(1, k):
        mapper.integrate(probe_scan(A_CLASS, t0 + 0.1 * i, origin, i))
    after_a = counters()
    label_a = probe_labels(mapper, origin)
    labels, tie = [], None
    for n in range(1, n_b + 1):
        mapper.integrate(probe_scan(B_CLASS, t0 + 0.1 * (k + n - 1), origin, k + n - 1))
        labels.append(probe_labels(mapper, origin))
        if n == k:
            tie = counters()
    return SimpleNamespace(
        first=first, after_a=after_a, label_a=label_a, labels=labels, tie=tie, end=counters(), k=k
    )


def mixed_scene(rng):
    """Ground stripes of three classes, a wall and a blob, 30 % label noise, some unlabeled:
    many voxels with several classes. Returns world points, labels."""
    ground = grid_plane((-8, 8), (-8, 8), 0.0, 0.1, rng)
    lab = np.where(ground[:, 1] < -2, ROAD, np.where(ground[:, 1] < 3, SIDEWALK, 17))
    wall = np.column_stack([np.full(3000, 6.0), rng.uniform(-6, 6, 3000), rng.uniform(0, 3, 3000)])
    blob = rng.normal([-3, 4, 1], 0.5, (1500, 3))
    xyz = np.concatenate([ground, wall, blob])
    labels = np.concatenate([lab, np.full(3000, BUILDING), np.full(1500, 15)]).astype(np.int32)
    labels = flip_labels(labels, 0.3, rng)
    labels[rng.random(len(labels)) < 0.05] = 0
    return away_from_faces(xyz, RES), labels


def probs_story(mapper, rng, t0):
    """Region 1 (x = 64 m): three scans given as labels. Region 2 (128 m): the same
    sensor-frame points and poses 64 m farther, given as one-hot probabilities. Region 3
    (192 m): a patch whose every point says 70 % class 3, 30 % class 5 (half of them with
    half their mass on class 0, which adds no evidence)."""
    shift = np.array([SHIFT_M, 0, 0])
    scenes = [mixed_scene(rng) for _ in range(3)]
    poses = [pose(0.1 * i, -0.2 * i, 1.7, yaw=0.1 * i) for i in range(3)]
    for region, as_probs in ((1, False), (2, True)):
        for i, ((xyz, lab), T) in enumerate(zip(scenes, poses)):
            T2 = T.copy()
            T2[:3, 3] += region * shift
            kw = dict(probs=one_hot(lab)) if as_probs else dict(labels=lab)
            mapper.integrate(scan_from_world(xyz + region * shift, T2, t0 + region + 0.1 * i, **kw))
    patch = away_from_faces(grid_plane((-2, 2), (-2, 2), 0.0, 0.05, rng), RES) + 3 * shift
    p = np.zeros((len(patch), C), np.float32)
    p[:, 3], p[:, 5] = 0.7, 0.3
    half = rng.random(len(patch)) < 0.5
    p[half] = 0.5 * p[half]
    p[half, 0] = 0.5
    mapper.integrate(scan_from_world(patch, pose(*(3 * shift + [0, 0, 1.7])), t0 + 3.0, probs=p))
    lab, prob = mapper.query(patch)
    return SimpleNamespace(patch=patch, p=p, patch_labels=lab, patch_probs=prob)


def voxel_scans(rng, n_scans=3, n_voxels=300):
    """Scans of points placed inside known voxels (away from their faces, so float32 and
    float64 agree on the voxel), 1-8 points per voxel, labels 0..19 (0 = unlabeled)."""
    keys = np.unique(rng.integers([-40, -40, -8], [40, 40, 8], (n_voxels, 3)), axis=0)
    scans = []
    for i in range(n_scans):
        sub = keys[rng.random(len(keys)) < 0.7]
        per = rng.integers(1, 9, len(sub))
        k = np.repeat(sub, per, axis=0)
        world = (k + rng.uniform(0.05, 0.95, (len(k), 3))) * RES
        labels = rng.integers(0, C, len(k)).astype(np.int32)
        main = rng.integers(1, C, len(sub))  # most voxels lean to one class
        lean = rng.random(len(k)) < 0.6
        labels[lean] = np.repeat(main, per)[lean]
        T = pose(rng.uniform(-1, 1), rng.uniform(-1, 1), 0.0, yaw=rng.uniform(-3, 3))
        scans.append(scan_from_world(world, T, 5.0 + 0.1 * i, labels=labels, index=i))
    return scans


def region(snap, i):
    """The snapshot rows of region i (x around i * 64 m)."""
    n = int(round(SHIFT_M / RES))
    x = snap.keys[:, 0]
    return (x >= (i - 0.5) * n) & (x < (i + 0.5) * n)


def predicted_switch(alpha: float, k: int) -> int:
    """Smallest n with sigma_B(n) > sigma_A(n), for sigma_t = alpha sigma_{t-1} + Delta:
    after k A scans sigma_A = Delta (1 - alpha^k) / (1 - alpha); n B scans later
    sigma_A = alpha^n that, sigma_B = Delta (1 - alpha^n) / (1 - alpha)."""
    before = (1 - alpha**k) / (1 - alpha)
    n = 1
    while (1 - alpha**n) / (1 - alpha) <= alpha**n * before:
        n += 1
    # the test would be meaningless if float32 rounding could move the switch: keep a margin
    for m in (n - 1, n):
        b, a = (1 - alpha**m) / (1 - alpha), alpha**m * before
        assert abs(b - a) > 0.01 * a, f"switch too close to call at n = {m}"
    return n


def distance_to_other_class(xyz, gt):
    """Per point, the distance to the nearest point of another ground-truth class."""
    d = np.full(len(xyz), np.inf)
    for c in np.unique(gt):
        tree = cKDTree(xyz[gt == c])
        other = gt != c
        d[other] = np.minimum(d[other], tree.query(xyz[other], k=1)[0])
    return d


def check_scan_orders(step, where: str = "") -> None:
    """The scan's two sorted orders are fixed by the scan alone: its points by table cell (in
    table order), a cell's points in the scan's order; its training rows cell after cell in
    table order. (Handed out first come first served, they changed with the threads' timing,
    and free space's rays, every stride-th row, with them.)"""
    kept = np.flatnonzero(step.kept)
    by_cell = kept[np.argsort(step.point_cell[kept], kind="stable")]
    np.testing.assert_array_equal(step.block_order, by_cell, err_msg=f"{where}: points by block")
    rows = step.layer_rows[:, -1]
    used = rows > 0
    np.testing.assert_array_equal(
        step.row_start[used],
        (np.cumsum(rows) - rows)[used],
        err_msg=f"{where}: training rows in table order",
    )


@ti.kernel
def counters_without_voxel(m: ti.template()) -> ti.i32:
    """Cells of the live blocks whose counters are allocated where no voxel is live
    (compact_counters keeps a live voxel's counters behind a pointer of its own)."""
    apart = 0
    for b0, b1, b2 in m.blk:
        for i, j, k in ti.ndrange(LEAF, LEAF, LEAF):
            u = ti.Vector([b0 * LEAF + i, b1 * LEAF + j, b2 * LEAF + k])
            if ti.is_active(m.vox_counts, u) and not ti.is_active(m.vox, u):
                apart += 1
    return apart
