"""The mapper: the paper's steps, in order, over one live window plus a host store.

    mapper = Mapper(MapperConfig(mode="st"))
    mapper.integrate(scan)                      # a tisem.scan.Scan
    labels, probs = mapper.query(points_world)  # (N,) train ids, (N, C) probabilities

Python checks every input and every index range before a kernel sees it (Taichi does not check
indices in release mode); the kernels in `kernels/` do the per-point and per-voxel work (their
step -> module table: kernels/__init__.py). Sizes come from `tisem.geometry.MapGeometry`, the
live window and its store from `tisem.live_window.LiveWindow`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import taichi as ti
from taichi.lang.argpack import ArgPack

from kernels import bki, entropy, fusion, rasterize, table, training
from kernels.layout import MapFields
from kernels.params import (ADAPTIVE_LENGTH, EXPONENTIAL, FIXED_LENGTH, FORGET, NO_KERNEL,
                            KernelSettings, ScanParams)
from tisem import backend
from tisem.config import MapperConfig
from tisem.geometry import MapGeometry, block_aligned_origin
from tisem.live_window import VoxelArrays, LiveWindow
from tisem.preprocess import CheckedScan, check_scan, scan_label
from tisem.scan import Scan, finite_rows
from tisem.snapshot import MapSnapshot
from tisem.store import KEY_LIMIT, BlockStore
from tisem.trace import IntegrationTrace

QUERY_CLAMP_M = 1.0e6   # query coordinates are clamped to this (int32 voxel indices at any res)

# the timed stages of `integrate` (profile=True), one per step of its recipe: the checks and the
# pose; the live window; locating the points and sorting them by leaf block; sorting them by
# voxel, the filter and the training points; the kernel lengths; the kernel update and fusion
# (with the adaptive lengths' entropy, fused in its pass over the map); resetting the table
STAGES = ("preprocess", "window", "voxelize", "filter", "length", "update", "clear")


@dataclass
class IntegrationReport:
    """What happened to one scan's points."""

    points: int = 0
    used: int = 0
    dropped_nonfinite: int = 0
    dropped_range: int = 0
    dropped_window: int = 0
    dropped_far: int = 0            # of dropped_range: implausibly far (> 1 km), corrupt data
    training_voxels: int = 0
    evicted_voxels: int = 0
    reloaded_voxels: int = 0


class ScanPoints(NamedTuple):
    """Per point: table cell, voxel code (kernels/rasterize.py), the points in block order and
    in voxel order; and the occupied cells (at most one per point)."""

    cell: np.ndarray
    code: np.ndarray
    by_block: np.ndarray
    by_voxel: np.ndarray
    blocks: np.ndarray


class TrainingRows(NamedTuple):
    """The scan's training points (kernels/training.py), one row per kept voxel."""

    xyz: np.ndarray       # (K, 3) centroid, local metres
    hist: np.ndarray      # (K, C) class evidence
    classes: np.ndarray   # (K,) bit c: evidence for class c
    single: np.ndarray    # (K,) the one class, or 0
    voxel: np.ndarray     # (K,) the voxel's index in its leaf block


@dataclass
class _Buffers:
    """Host buffers reused across scans (grown on demand) so the hot path allocates nothing."""

    per_point: np.ndarray = field(default_factory=lambda: np.zeros((5, 0), np.int32))
    rows: TrainingRows | None = None

    def points(self, n: int) -> ScanPoints:
        if self.per_point.shape[1] < n:
            cap = max(n, int(self.per_point.shape[1] * 1.5))
            self.per_point = np.zeros((5, cap), np.int32)
        # (views of exactly n, each contiguous: the kernels loop over their length)
        return ScanPoints(*(self.per_point[k, :n] for k in range(5)))

    def training(self, n: int, num_classes: int) -> TrainingRows:
        if self.rows is None or len(self.rows.xyz) < n:
            cap = max(n, int(len(self.rows.xyz) * 1.5) if self.rows is not None else n)
            self.rows = TrainingRows(np.zeros((cap, 3), np.float32),
                                     np.zeros((cap, num_classes), np.float32),
                                     *(np.zeros(cap, np.int32) for _ in range(3)))
        return self.rows


def kernel_settings(cfg: MapperConfig, per_voxel: bool) -> KernelSettings:
    """The compile-time settings of a map's kernels for its config."""
    length = ADAPTIVE_LENGTH if cfg.adaptive else FIXED_LENGTH if cfg.uses_kernel else NO_KERNEL
    return KernelSettings(kernel_length=length,
                          decay=FORGET if cfg.decay_tau_s == 0 else EXPONENTIAL,
                          unit_weight=cfg.point_weight == "unit", per_voxel=per_voxel)


class Mapper:
    """A spatio-temporal semantic map, in any of the modes of `MapperConfig`.

    `parallel_loop`: the kernel update's parallel loop, "block" (one task per leaf block: CPUs)
    or "voxel" (one thread per voxel: GPUs); None picks by the running arch.
    """

    def __init__(self, config: MapperConfig | None = None, *, profile: bool = False,
                 parallel_loop: str | None = None):
        self.config = config or MapperConfig()
        self.config.validate()
        cfg = self.config
        if parallel_loop not in (None, "block", "voxel"):
            raise ValueError(f"parallel_loop must be 'block', 'voxel' or None, "
                             f"got {parallel_loop!r}")
        self.geometry = MapGeometry.from_config(cfg)
        # before the runtime's one map slot is taken: a bad config or a missing store_dir is
        # refused with the runtime still free for another map
        self.store = BlockStore(cfg.num_classes, spill_dir=cfg.store_dir)
        self._generation = backend.claim_map_slot()
        self.C = cfg.num_classes
        if parallel_loop is None:
            parallel_loop = "voxel" if ti.lang.impl.current_cfg().arch == ti.cuda else "block"
        self._settings = kernel_settings(cfg, per_voxel=parallel_loop == "voxel")
        self._fields = MapFields(self.C, self.geometry.storage_extent,
                                 self.geometry.table_half_blk)
        bki.fill_kernel_table(self._fields)
        self.window = LiveWindow(self._fields, self.store, self.geometry, cfg.max_live_blocks)
        self._params = self._scan_params()
        self.origin_vox: np.ndarray | None = None   # global voxel index of local voxel 0
        self.t0: float | None = None               # stamp of the first scan: map time 0
        self.scans = 0
        self.last_stamp_s: float | None = None
        self.profile = profile
        self.stage_seconds = {s: 0.0 for s in STAGES}
        self._buf = _Buffers()

    def _scan_params(self) -> ArgPack:
        """The map's ScanParams; `_preprocess` refreshes the pose, time and stamp per scan."""
        cfg, geo = self.config, self.geometry
        res = geo.resolution_m
        tau = cfg.decay_tau_s
        return ScanParams(
            rotation=np.eye(3, dtype=np.float32), translation_m=np.zeros(3),
            center_vox=np.zeros(3, np.int64), limit_vox=geo.point_limit_vox,
            min_range2_m2=cfg.min_range_m ** 2, max_range2_m2=cfg.max_range_m ** 2,
            min_z_m=cfg.min_z_m, max_z_m=cfg.max_z_m, resolution_m=res, inv_resolution=1.0 / res,
            time_rel_s=0.0, stamp=0, min_points=cfg.min_points, reach_blk=geo.reach_blk,
            fixed_length_m=cfg.ell_fixed_vox * res, length_min_m=cfg.ell_min_m,
            length_max_m=cfg.ell_max_m, prior=cfg.prior, sigma0=cfg.sigma0,
            inv_tau=0.0 if tau in (0.0, float("inf")) else 1.0 / tau)

    # ------------------------------------------------------------------ integrate
    def integrate(self, scan: Scan, trace: IntegrationTrace | None = None) -> IntegrationReport:
        """Fuse one scan into the map (steps 1-8 of the method); `trace` records each step."""
        self._check_alive()
        m, p, settings = self._fields, self._params, self._settings
        report = IntegrationReport(points=scan.num_points)
        clock = self._clock()
        # 1. preprocess: check the evidence, drop non-finite points, the pose in map coordinates
        checked, center_vox = self._preprocess(scan, report)
        clock("preprocess")
        # the live window follows the sensor: what it leaves goes to the store, what it reaches
        # comes back from there
        moved = self.window.follow(center_vox)
        report.evicted_voxels, report.reloaded_voxels = moved.evicted_voxels, moved.reloaded_voxels
        clock("window")
        # 2. downsample / voxelize: range and window checks, the points sorted by leaf block
        points = self._voxelize(checked, report, trace)
        clock("voxelize")
        # 3. redundant-voxel filter, then per kept voxel a training point: its centroid and
        # class histogram, sorted by leaf block
        rows = self._training_points(checked, points, report, trace)
        clock("filter")
        # 4-5. semantic uncertainty and kernel length of the voxels the training points hit
        entropy.assign_lengths(m, p, points.blocks, rows.voxel, rows.hist, settings.kernel_length)
        clock("length")
        # 6-8. sparse kernel, Bayesian kernel update and temporal fusion of every live voxel
        # within reach of a training point
        self._update(points, rows, report.training_voxels)
        clock("update")
        table.clear_table(m)              # the scan's table, empty again for the next scan
        clock("clear")
        self.scans += 1
        self.last_stamp_s = float(scan.stamp_s)
        return report

    def _preprocess(self, scan: Scan, report: IntegrationReport) -> tuple[CheckedScan, np.ndarray]:
        """Check the scan, put its pose in map coordinates (the kernels do the per-point work);
        returns the checked scan and the sensor's voxel."""
        checked = check_scan(scan, self.C)
        report.dropped_nonfinite = checked.dropped_nonfinite
        res = self.geometry.resolution_m
        T = scan.T_world_sensor
        if self.origin_vox is None:
            # the origin is block-aligned at the first sensor position, so local coordinates stay
            # small (float32 keeps mm precision within ~10 km of it)
            self.origin_vox = block_aligned_origin(np.floor(T[:3, 3] / res))
            self.t0 = float(scan.stamp_s)
        translation = T[:3, 3] - self.origin_vox * res
        if np.any(np.abs(translation) / res + self.window.half_vox > KEY_LIMIT):
            raise ValueError(f"{scan_label(scan)}: the sensor is "
                             f"{np.abs(translation).max() / 1000:.0f} km from the map origin; "
                             f"tisem maps within {KEY_LIMIT * res / 1000:.0f} km")
        center_vox = np.floor(translation / res).astype(np.int64)
        p = self._params
        p.rotation = T[:3, :3].astype(np.float32)
        p.translation_m = translation
        p.center_vox = center_vox
        p.time_rel_s = float(scan.stamp_s - self.t0)
        p.stamp = self.scans + 1
        return checked, center_vox

    def _voxelize(self, checked: CheckedScan, report: IntegrationReport,
                  trace: IntegrationTrace | None) -> ScanPoints:
        """Step 2: locate every point in the scan's table of leaf blocks and list each block's
        points together."""
        m = self._fields
        pts = self._buf.points(len(checked.points_sensor))
        stats = rasterize.locate_kernel(checked.use_probs)(
            m, self._params, checked.points_sensor, checked.evidence, pts.cell, pts.code,
            pts.blocks)
        report.used = int(stats[rasterize.USED])
        report.dropped_range = int(stats[rasterize.OUT_OF_RANGE]) - report.dropped_nonfinite
        report.dropped_window = int(stats[rasterize.OUT_OF_WINDOW])
        report.dropped_far = int(stats[rasterize.IMPLAUSIBLY_FAR]) - report.dropped_nonfinite
        # in table order (x, y, z), so that the per-block passes touch the map block by block
        # along columns, as the kernel update will (~1 ms less than the points' order)
        pts = pts._replace(blocks=pts.blocks[:int(stats[rasterize.BLOCKS])])
        pts.blocks.sort()
        table.column_slots(m, table.points_in, m.p_start, True)
        rasterize.scatter_points(m, pts.cell, pts.by_block)
        if trace is not None:
            trace.points_located(pts.cell, pts.code, pts.blocks, pts.by_block[:report.used],
                                 m.table_half, self.window.center_vox, self.origin_vox,
                                 self.geometry.resolution_m)
        return pts

    def _training_points(self, checked: CheckedScan, pts: ScanPoints, report: IntegrationReport,
                         trace: IntegrationTrace | None) -> TrainingRows:
        """Step 3: sort each block's points by voxel, filter the voxels, write the kept ones'
        training rows."""
        m = self._fields
        training.sort_blocks(m, self.config.min_points, pts.blocks, pts.code, pts.by_block,
                             pts.by_voxel)
        n = table.column_slots(m, table.rows_in, m.b_start, False)
        report.training_voxels = int(n)
        rows = self._buf.training(max(n, 1), self.C)
        training.training_kernel(self._settings.unit_weight, checked.use_probs)(
            m, self._params, checked.points_sensor, checked.evidence, pts.blocks, pts.code,
            pts.by_voxel, *rows)
        if trace is not None:
            trace.training_written(n, m.b_start.to_numpy(), m.b_layers.to_numpy(), rows.xyz,
                                   rows.hist)
        return rows

    def _update(self, pts: ScanPoints, rows: TrainingRows, n_rows: int) -> None:
        """Steps 6-8: the kernel update of every voxel within reach of the n_rows training
        points and its fusion; csm (no kernel) adds each training voxel's own histogram."""
        m, p, settings = self._fields, self._params, self._settings
        if not settings.uses_kernel:
            fusion.fuse_histograms(m, p, pts.blocks, rows.voxel, rows.hist)
        elif n_rows:
            bki.update_kernel(settings)(m, p, rows.xyz, rows.hist, rows.classes, rows.single)

    def _check_alive(self) -> None:
        if self._generation != backend.generation():
            raise RuntimeError("this map belonged to a Taichi runtime that has since been "
                               "re-initialised (init_taichi); its fields are gone")

    def _clock(self):
        if not self.profile:
            return lambda stage: None
        last = [time.perf_counter()]

        def tick(stage: str) -> None:
            ti.sync()
            now = time.perf_counter()
            self.stage_seconds[stage] += now - last[0]
            last[0] = now
        return tick

    # ------------------------------------------------------------------ query and export
    def query(self, points_world: np.ndarray,
              with_probs: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Labels (N,) int32 train ids and probabilities (N, C) float32 of world points.

        A point in no voxel gets label 0 and all-zero probabilities.
        """
        self._check_alive()
        pts = np.asarray(points_world, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"query points must be (N, 3), got {pts.shape}")
        n = len(pts)
        labels = np.zeros(n, np.int32)
        probs = np.zeros((n, self.C), np.float32) if with_probs else None
        if self.origin_vox is None or n == 0:
            return labels, probs
        finite = finite_rows(pts)
        # local coordinates; far or non-finite points are clamped so their voxel index still fits
        # an int32 in the kernel (they land outside the window either way)
        local = pts - self.origin_vox * self.geometry.resolution_m
        if not finite.all():
            local[~finite] = 0.0
        local = np.clip(local, -QUERY_CLAMP_M, QUERY_CLAMP_M, out=local).astype(np.float32)
        self.window.lookup(local, finite, labels, probs)
        return labels, probs

    @property
    def live_voxels(self) -> int:
        return self.window.live_voxels

    @property
    def live_blocks(self) -> int:
        return self.window.live_blocks

    @property
    def stored_voxels(self) -> int:
        return len(self.store)

    def snapshot(self) -> MapSnapshot:
        """The whole map (live window and store) as host arrays, sorted by key."""
        self._check_alive()
        if self.origin_vox is None:
            return self._snapshot_of([])
        return self._snapshot_of([self.window.live_arrays(), self.window.stored_arrays()])

    def live_snapshot(self) -> MapSnapshot:
        """Only the voxels live in the Taichi field, as `snapshot()` gives them."""
        self._check_alive()
        parts = [] if self.origin_vox is None else [self.window.live_arrays()]
        return self._snapshot_of(parts)

    def _snapshot_of(self, parts: list[VoxelArrays]) -> MapSnapshot:
        res = self.geometry.resolution_m
        if not parts:
            return MapSnapshot(np.zeros((0, 3), np.int64), np.zeros((0, self.C), np.float32),
                               np.zeros(0), np.zeros(0, np.float32), res)
        keys = np.concatenate([p.keys for p in parts]).astype(np.int64) + self.origin_vox
        counts = np.concatenate([p.counts for p in parts])
        t_last = np.concatenate([p.t_last_rel for p in parts]).astype(np.float64) + self.t0
        length_m = np.concatenate([p.length_m for p in parts])
        order = MapSnapshot.sort_order(keys)
        return MapSnapshot(keys[order], counts[order], t_last[order], length_m[order], res)

    def state(self) -> dict:
        """Scalars that, with `snapshot()`, rebuild this mapper exactly (for checkpoints)."""
        center = self.window.center_vox
        return {"origin_vox": None if self.origin_vox is None else self.origin_vox.tolist(),
                "t0": self.t0, "center_vox": None if center is None else center.tolist(),
                "scans": self.scans, "last_stamp_s": self.last_stamp_s}

    def restore(self, snapshot: MapSnapshot, state: dict) -> None:
        """Load a snapshot written by `snapshot()` (with `state()`), into an empty mapper."""
        res = self.geometry.resolution_m
        if self.origin_vox is not None:
            raise RuntimeError("restore() needs a fresh mapper")
        if abs(snapshot.resolution_m - res) > 1e-9:
            raise ValueError(f"snapshot resolution {snapshot.resolution_m} m != mapper {res} m")
        if snapshot.counts.shape[1] != self.C:
            raise ValueError(f"snapshot has {snapshot.counts.shape[1]} classes, mapper {self.C}")
        if state.get("origin_vox") is None:
            return
        self.origin_vox = np.asarray(state["origin_vox"], np.int64)
        self.t0 = float(state["t0"])
        self.scans = int(state.get("scans", 0))
        self.last_stamp_s = state.get("last_stamp_s")
        # everything goes to the store first; the window then pulls in what it covers
        self.store.put(snapshot.keys - self.origin_vox, snapshot.counts.astype(np.float32),
                       (snapshot.t_last - self.t0).astype(np.float32),
                       snapshot.ell_m.astype(np.float32))
        center = state.get("center_vox")
        self.window.follow(np.asarray(center if center is not None else [0, 0, 0], np.int64))
