"""Shared builders for the engine tests: runtimes, configs, poses, scans, scenes, and readers
of what each step of `Mapper.integrate` produced (from a `tisem.trace.IntegrationTrace`).

Taichi rules these follow: every test gets its own runtime (the `taichi_cpu` fixture of
conftest.py: `init_taichi("cpu", threads=2)`, one Mapper per runtime), because using a field of
an earlier runtime aborts the process; no Taichi object outlives its runtime; and the test
kernels below live in this real source file (Taichi reads kernel source from disk). With 2
threads float atomics are not bitwise reproducible, so comparisons carry named tolerances.
"""
# (no `from __future__ import annotations`: Taichi reads the kernels' annotations)
import math

import numpy as np
import taichi as ti

from kernels import bki, entropy
from kernels.layout import TOP, MapFields
from tisem.backend import init_taichi
from tisem.config import MapperConfig
from tisem.reference import voxel_histograms
from tisem.scan import Scan

C = 20
ROAD, SIDEWALK, BUILDING, VEGETATION, POLE = 9, 11, 13, 15, 18


# --------------------------------------------------------------------------- runtimes

def fresh_runtime(debug: bool = False) -> None:
    """A new Taichi runtime (every map built before it is gone: never touch it again)."""
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
    cz, sz, cy, sy, cx, sx = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch),
                              math.cos(roll), math.sin(roll))
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = [x, y, z]
    return T


def scan_from_world(world_xyz, T, stamp_s, labels=None, probs=None, gt=None, index=0,
                    name="") -> Scan:
    """A `Scan` whose sensor-frame points are the given world points seen from pose T."""
    world_xyz = np.asarray(world_xyz, np.float64)
    sensor = (world_xyz - T[:3, 3]) @ T[:3, :3]
    return Scan(points_sensor=sensor.astype(np.float32), T_world_sensor=T, stamp_s=stamp_s,
                labels=labels, probs=probs, gt_labels=gt, index=index, name=name)


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
    new = rng.integers(1, C - 1, flip.sum())           # 1..18
    new = np.where(new >= out[flip], new + 1, new)     # never the point's own class
    out[flip] = new
    return out


# --------------------------------------------------------------------------- test kernels

@ti.kernel
def _sample_kernel(m: ti.template(), r2: ti.types.ndarray(dtype=ti.f32, ndim=1),
                   lut: ti.types.ndarray(dtype=ti.f32, ndim=1),
                   exact: ti.types.ndarray(dtype=ti.f32, ndim=1)):
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
def _entropy(p: ti.types.ndarray(dtype=ti.f32, ndim=2), ell_min: ti.f32, ell_max: ti.f32,
             common: ti.f32, h: ti.types.ndarray(dtype=ti.f32, ndim=1),
             ell: ti.types.ndarray(dtype=ti.f32, ndim=1),
             h_common: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    for i in range(p.shape[0]):
        v = ti.Vector([0.0] * C)
        for c in ti.static(range(C)):
            v[c] = p[i, c]
        h[i] = entropy.normalized_entropy(v, C - 1)
        ell[i] = entropy.adaptive_length(v, ell_min, ell_max, C - 1)
        h_common[i] = entropy.entropy_with_common(v, C - 1, common,
                                                  common * entropy.fast_log(common))


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
    assert np.array_equal(np.sort(listed), np.unique(step.point_cell[kept])), \
        "the list of occupied blocks differs from the points' blocks"
    order = step.block_order
    assert np.array_equal(np.sort(order), np.flatnonzero(kept)), \
        "the block sort lost or repeated a point"
    runs = step.point_cell[order]
    # every block's points in one run: a cell id never comes back after another
    starts = np.r_[True, runs[1:] != runs[:-1]]
    assert len(np.unique(runs)) == starts.sum(), "a block's points are split"
    keys, inv, npts = np.unique(step.point_voxel[kept], axis=0, return_inverse=True,
                                return_counts=True)
    labelled = np.bincount(inv.reshape(-1), step.point_has_evidence[kept], len(keys))
    return dict(keys=keys, npts=npts, labelled=labelled.astype(np.int64), used=int(kept.sum()))


def training_points(step) -> dict:
    """Step 3 of a traced scan: the training points found through the scan's table (global keys
    of their voxels, centroids in world metres, class evidence), sorted by key. Checks on the way
    that every slot of every block's slice is a training point, each once."""
    ends = step.layer_rows        # per cell: the rows up to the end of each z layer
    # each layer's count includes the layers below it: non-decreasing up the block
    assert np.all(np.diff(ends, axis=1) >= 0), "a block's layer ends go down"
    count = ends[:, -1]           # (the last layer's: all the block's rows)
    used = count > 0
    rows = np.concatenate([np.arange(s, s + c) for s, c in zip(step.row_start[used], count[used])]
                          or [np.zeros(0, np.int64)])
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
