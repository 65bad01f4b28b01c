"""The mapper: the paper's steps, in order, over one live window plus a host store.

    mapper = Mapper(MapperConfig(mode="st"))
    mapper.integrate(scan)                      # a tisem.scan.Scan
    labels, probs = mapper.query(points_world)  # (N,) train ids, (N, C) probabilities

Python checks every input and every index range before a kernel sees it (Taichi does not check
indices in release mode); the kernels in `kernels/` do the per-point and per-voxel work.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from kernels import bki, query as kquery, rasterize, table, training, window
from kernels.layout import LEAF, TOP, MapFields, storage_extent
from tisem import backend
from tisem.config import MapperConfig
from tisem.geometry import block_aligned_origin
from tisem.scan import Scan, finite_rows
from tisem.snapshot import MapSnapshot
from tisem.store import KEY_LIMIT, BlockStore

log = logging.getLogger(__name__)

FAR_M = 1.0e6   # query coordinates are clamped to this (int32 voxel indices at any resolution)
# a scan's training rows travel through float32 (kernels/training.py), exact below 2^24; a scan
# has at most as many training voxels as points
MAX_POINTS = 2 ** 24
# the scan's dense table of leaf blocks around the sensor (kernels/layout.py): 16 B per cell
# (4 int32 fields; the near table adds an eighth of that), and int32 cell ids
TABLE_BYTES_PER_CELL = 18
MAX_TABLE_CELLS = 2 ** 28


def _ivec(a) -> ti.Vector:
    """An integer array (voxel or block indices) as a Taichi kernel vector argument."""
    return ti.Vector([int(x) for x in a])


# the timed stages of `integrate` (profile=True): checks and the pose; the live window; locating
# the points and sorting them by leaf block; reducing them to voxels, the filter and the training
# points; the entropy, kernel length, kernel update and fusion, fused in one pass over the map
# (kernels/bki.py); resetting the scan's table
STAGES = ("preprocess", "window", "rasterize", "training", "kernel", "clear")


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


@dataclass
class _Buffers:
    """Host buffers reused across scans (grown on demand) so the hot path allocates nothing."""

    xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    hist: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    classes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    single: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))

    # per point: table cell, voxel code (kernels/rasterize.py), the order by block and by
    # voxel; and the occupied cells (at most one per point)
    per_point: np.ndarray = field(default_factory=lambda: np.zeros((5, 0), np.int32))

    def points(self, n: int):
        if self.per_point.shape[1] < n:
            cap = max(n, int(self.per_point.shape[1] * 1.5))
            self.per_point = np.zeros((5, cap), np.int32)
        # (views of exactly n, each contiguous: the kernels loop over their length)
        return tuple(self.per_point[k, :n] for k in range(5))

    def training(self, n: int, num_classes: int):
        if self.xyz.shape[0] < n:
            cap = max(n, int(self.xyz.shape[0] * 1.5))
            self.xyz = np.zeros((cap, 3), np.float32)
            self.hist = np.zeros((cap, num_classes), np.float32)
            self.classes = np.zeros(cap, np.int32)
            self.single = np.zeros(cap, np.int32)
        return self.xyz, self.hist, self.classes, self.single


class Mapper:
    """A spatio-temporal semantic map (SPEC §1), in any of the modes of `MapperConfig`."""

    def __init__(self, config: MapperConfig | None = None, *, profile: bool = False):
        self.config = config or MapperConfig()
        self.config.validate()
        cfg = self.config
        # first: a missing store_dir is refused before the runtime's one map slot is taken
        self.store = BlockStore(cfg.num_classes, spill_dir=cfg.store_dir)
        self._generation = backend.claim_map_slot()
        self.C = cfg.num_classes
        self.res = float(cfg.resolution_m)
        reach = cfg.reach_m
        self.radius_vox = int(math.ceil(reach / self.res + 0.5)) if cfg.uses_kernel else 0
        self._reach_blk = int(math.ceil(reach / (LEAF * self.res)))
        # the live window, in voxels: every scan point plus its kernel reach must fit inside
        need_xy = cfg.max_range_m + reach + LEAF * self.res
        need_z = max(abs(cfg.min_z_m), abs(cfg.max_z_m)) + reach + LEAF * self.res
        if cfg.window_xy_m < need_xy or cfg.window_z_m < need_z:
            raise ValueError(
                f"window_xy_m={cfg.window_xy_m} / window_z_m={cfg.window_z_m} must hold the scan "
                f"(max_range + kernel reach): need >= {need_xy:.1f} m / {need_z:.1f} m")
        self.half_vox = np.array([math.ceil(cfg.window_xy_m / self.res)] * 2
                                 + [math.ceil(cfg.window_z_m / self.res)], np.int64)
        self.half_blk = self.half_vox // LEAF + 1
        if self._reach_blk > bki.MAX_REACH_BLK:
            raise ValueError(f"kernel reach {reach} m is longer than {bki.MAX_REACH_BLK} leaf blocks "
                             f"({bki.MAX_REACH_BLK * LEAF * self.res:.2f} m at {self.res} m voxels)")
        # Points whose voxel is farther than `_limit` from the sensor's are dropped (counted as
        # outside the window), so that (a) a kernel never reaches past the window and (b) every
        # training voxel fits the scan's table of leaf blocks. Any point within
        # max_range is inside in x and y; in z the window bounds it (a tilted sensor's far
        # points can lie well above or below its own height band).
        scan_half = np.array([math.ceil(cfg.max_range_m / self.res) + 1] * 2
                             + [self.half_vox[2]], np.int64)
        self._limit = np.minimum(self.half_vox - self.radius_vox - 1, scan_half)
        # the table covers every block a training voxel can fall in, plus the blocks a
        # receiving voxel's kernel can reach from there
        table_half = -(-self._limit // LEAF) + 2 * self._reach_blk + 3
        cells = int(np.prod(2 * table_half + 1))
        if cells >= MAX_TABLE_CELLS:    # (cell ids are int32, and the table is dense)
            raise ValueError(
                f"max_range_m={cfg.max_range_m} at resolution_m={self.res} needs a scan table of "
                f"{cells:,} leaf blocks ({cells * TABLE_BYTES_PER_CELL / 2 ** 30:.0f} GiB); tisem "
                f"takes at most {MAX_TABLE_CELLS:,}: lower max_range_m or raise resolution_m")
        self.fields = MapFields(self.C, storage_extent(tuple(int(h) for h in self.half_vox)),
                                tuple(int(h) for h in table_half))
        bki.fill_kernel_table(self.fields)
        # the kernel update's parallel loop: per leaf block on CPUs, per voxel on GPUs
        self._per_voxel = ti.lang.impl.current_cfg().arch == ti.cuda
        self.origin_vox: np.ndarray | None = None   # global voxel index of local voxel 0
        self.t0: float | None = None               # stamp of the first scan
        self.center_vox: np.ndarray | None = None   # window centre, local voxels
        self.scans = 0
        self.last_stamp_s: float | None = None
        self.profile = profile
        self.stage_seconds = {s: 0.0 for s in STAGES}
        self._buf = _Buffers()
        self._cap_state: dict | None = None   # _fit_cap's bookkeeping, from the first scan on
        # empty stand-ins for the kind of evidence a scan does not carry (labels or probs)
        self._no_labels = np.zeros(0, np.int32)
        self._no_probs = np.zeros((0, self.C), np.float32)
        if cfg.mode == "spatial":
            self._inv_tau = -1.0
        elif cfg.decay_tau_s == math.inf:
            self._inv_tau = 0.0
        else:
            self._inv_tau = 1.0 / cfg.decay_tau_s

    # ------------------------------------------------------------------ integrate
    def integrate(self, scan: Scan) -> IntegrationReport:
        """Fuse one scan into the map (steps 1-8 of SPEC §1)."""
        self._check_alive()
        cfg = self.config
        m = self.fields
        rep = IntegrationReport(points=scan.num_points)
        clock = self._clock()
        pts, labels, probs, R, t_local = self._prepare(scan, rep)
        t_rel = float(scan.stamp_s - self.t0)
        center = np.floor(t_local / self.res).astype(np.int64)
        clock("preprocess")
        self._move_window(center, rep)
        clock("window")
        R_ti, t_ti = ti.Matrix(R.tolist()), ti.Vector(t_local.tolist())
        evidence = (labels, self._no_probs, False) if probs is None else \
            (self._no_labels, probs, True)
        center_v = _ivec(center)
        cell, code, perm, perm2, blocks = self._buf.points(len(pts))
        stats = rasterize.locate_points(
            m, pts, *evidence, R_ti, t_ti, center_v, _ivec(self._limit),
            cfg.min_range_m ** 2, cfg.max_range_m ** 2, cfg.min_z_m, cfg.max_z_m, 1.0 / self.res,
            cell, code, blocks)
        rep.used = int(stats[rasterize.USED])
        rep.dropped_range = int(stats[rasterize.OUT_OF_RANGE]) - rep.dropped_nonfinite
        rep.dropped_window = int(stats[rasterize.OUT_OF_WINDOW])
        rep.dropped_far = int(stats[rasterize.IMPLAUSIBLY_FAR]) - rep.dropped_nonfinite
        # in table order (x, y, z), so that the per-block passes touch the map block by block
        # along columns, as the kernel update will (~1 ms less than the points' order)
        blocks = blocks[:int(stats[rasterize.BLOCKS])]
        blocks.sort()
        table.column_slots(m, table.points_in, m.p_start, True)
        rasterize.scatter_points(m, cell, perm)
        clock("rasterize")
        stamp = self.scans + 1
        training.sort_blocks(m, cfg.min_points, blocks, code, perm, perm2)
        n = table.column_slots(m, table.rows_in, m.b_start, False)
        rep.training_voxels = int(n)
        train = self._buf.training(max(n, 1), self.C)
        ell_min = cfg.ell_min_m if cfg.adaptive else cfg.ell_fixed_vox * self.res
        training.write_training(
            m, center_v, stamp, self._reach_blk, t_rel, cfg.min_points,
            int(cfg.point_weight == "unit"), ell_min, int(cfg.adaptive), int(not cfg.uses_kernel),
            pts, *evidence, R_ti, t_ti, blocks, code, perm2, *train)
        clock("training")
        if cfg.uses_kernel and n:
            bki.gather_update(m, center_v, stamp, t_rel, self._inv_tau, self.res, cfg.sigma0,
                              cfg.prior, ell_min, cfg.ell_max_m, *train, self._per_voxel)
        clock("kernel")
        table.clear_table(m)
        clock("clear")
        self._finish(scan)
        return rep

    def _check_alive(self) -> None:
        if self._generation != backend.generation():
            raise RuntimeError("this map belonged to a Taichi runtime that has since been "
                               "re-initialised (init_taichi); its fields are gone")

    def _finish(self, scan: Scan) -> None:
        self.scans += 1
        self.last_stamp_s = float(scan.stamp_s)

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

    def _prepare(self, scan: Scan, rep: IntegrationReport):
        """Check the scan's evidence and pose; the kernels do the per-point work (step 1)."""
        cfg = self.config
        where = f"scan {scan.index}" + (f" ({scan.name})" if scan.name else "")
        if scan.num_points >= MAX_POINTS:
            raise ValueError(f"{where}: {scan.num_points:,} points; tisem takes at most "
                             f"{MAX_POINTS - 1:,} per scan")
        pts = np.ascontiguousarray(scan.points_sensor, dtype=np.float32)
        finite = finite_rows(pts)
        rep.dropped_nonfinite = int(len(pts) - np.count_nonzero(finite))
        if rep.dropped_nonfinite:
            pts = pts.copy()
            # beyond any range (and counted as implausibly far, which the report corrects for):
            # the kernel drops them without a NaN test, which fast math would not honour
            pts[~finite] = (2.0 * rasterize.FAR_M, 0.0, 0.0)
        labels = probs = None
        if scan.labels is not None:
            labels = np.ascontiguousarray(scan.labels, dtype=np.int32)
            if labels.size and (labels.min() < 0 or labels.max() >= self.C):
                raise ValueError(f"{where}: train ids must lie in [0, {self.C}), got "
                                 f"[{labels.min()}, {labels.max()}]")
        else:
            probs = np.ascontiguousarray(scan.probs, dtype=np.float32)
            if probs.shape[1] != self.C:
                raise ValueError(f"{where}: {probs.shape[1]} probability columns, "
                                 f"the map has {self.C} classes")
            if not np.all(np.isfinite(probs[finite])) or (probs.size and probs.min() < 0):
                raise ValueError(f"{where}: probabilities must be finite and >= 0")
            if rep.dropped_nonfinite:
                probs = np.where(finite[:, None], probs, 0).astype(np.float32)
        T = scan.T_world_sensor
        if self.origin_vox is None:
            # the origin is block-aligned at the first sensor position, so local coordinates stay
            # small (float32 keeps mm precision within ~10 km of it)
            self.origin_vox = block_aligned_origin(np.floor(T[:3, 3] / self.res))
            self.t0 = float(scan.stamp_s)
        t_local = T[:3, 3] - self.origin_vox * self.res
        if np.any(np.abs(t_local) / self.res + self.half_vox > KEY_LIMIT):
            raise ValueError(f"{where}: the sensor is {np.abs(t_local).max() / 1000:.0f} km from "
                             f"the map origin; tisem maps within {KEY_LIMIT * self.res / 1000:.0f} km")
        return pts, labels, probs, T[:3, :3].astype(np.float32), t_local

    # ------------------------------------------------------------------ window and store
    def _move_window(self, new_center: np.ndarray, rep: IntegrationReport | None = None) -> None:
        """Move the live window to `new_center`: voxels that leave it go to the store, stored
        voxels it now covers come back, and `_fit_cap` keeps the live blocks under the cap.

        The window is the voxel box |w - center_vox| <= half_vox, the very box `query` reads
        the field in: kernels/window.py splits the blocks its face cuts, so a voxel is live
        exactly when the box holds it, and the field and the store never hold the same voxel.
        """
        m = self.fields
        new_center = np.asarray(new_center, np.int64)
        half = self._fit_cap(new_center)
        st = self._cap_state
        if self.center_vox is not None and (np.any(new_center != self.center_vox)
                                            or np.any(half != self.half_vox)):
            evicted = self._evict(new_center, half)
            if rep is not None:
                rep.evicted_voxels = evicted
        self.center_vox = new_center
        self.half_vox = half
        back = self.store.take_box(new_center, half)
        if back is not None:
            keys, counts, t_last, ell = back
            kquery.import_voxels(m, np.ascontiguousarray(keys, np.int32), counts, t_last, ell)
            if rep is not None:
                rep.reloaded_voxels = len(keys)
            st["live"] = kquery.count_active(m.blk)
        else:   # (live blocks after the move, to learn how many the scan adds)
            st["live"] = st["now"] - st["freed"]

    def _evict(self, new_center: np.ndarray, half: np.ndarray) -> int:
        """Move the live voxels outside the box |w - new_center| <= half to the store and free
        the blocks and top cells they leave empty; returns how many voxels moved."""
        m = self.fields
        st = self._cap_state
        old_blk = np.floor_divide(self.center_vox, LEAF)
        blocks = np.zeros((max(st["now"], 1), 3), np.int32)
        n = window.find_leaving_blocks(m, _ivec(old_blk), _ivec(new_center), _ivec(half), blocks)
        if n == 0:
            return 0
        if n > len(blocks):   # (st["now"] is exact; this is a guard)
            blocks = np.zeros((n, 3), np.int32)
            n = window.find_leaving_blocks(m, _ivec(old_blk), _ivec(new_center), _ivec(half), blocks)
        cap = n * LEAF ** 3
        keys = np.zeros((cap, 3), np.int32)
        counts = np.zeros((cap, self.C), np.float32)
        t_last = np.zeros(cap, np.float32)
        ell = np.zeros(cap, np.float32)
        left = np.zeros(n, np.int32)
        nv = window.export_leaving(m, _ivec(self.center_vox), _ivec(new_center), _ivec(half),
                                   blocks, n, keys, counts, t_last, ell, left)
        self.store.put(keys[:nv], counts[:nv], t_last[:nv], ell[:nv], box=(new_center, half))
        st["freed"] = window.free_empty_blocks(m, blocks, n, left)
        # a top cell can only fall wholly outside when the box's range of top cells changes
        tops = np.r_[np.floor_divide(new_center - half, TOP), np.floor_divide(new_center + half, TOP)]
        if st.get("tops") is None or np.any(tops != st["tops"]):
            window.free_far_top_cells(m, _ivec(np.floor_divide(self.center_vox, TOP)),
                                      _ivec(new_center), _ivec(half))
            st["tops"] = tops
        return int(nv)

    def _fit_cap(self, center: np.ndarray) -> np.ndarray:
        """Half-size (voxels) of the live window for a scan at `center`, under the block cap.

        The configured window, unless its blocks (live and stored) would leave less room under
        `max_live_blocks` than the most blocks one scan has added so far: then the largest
        smaller x/y box that does, so the farthest blocks go to the store first (they come back
        once the map around the sensor thins out). Raises ValueError, with the map untouched
        (the pipeline skips the scan), when even the smallest box that holds a scan and its
        kernel reach does not fit.
        """
        m = self.fields
        st = self._cap_state
        if st is None:   # the configured window; headroom: the most blocks a scan has added
            st = self._cap_state = {"full": self.half_vox.copy(), "headroom": 0, "live": None,
                                    "shrunk": False}
        full = st["full"]
        live = st["now"] = kquery.count_active(m.blk)
        st["freed"] = 0
        if st["live"] is not None:
            st["headroom"] = max(st["headroom"], live - st["live"])
        cap = int(self.config.max_live_blocks)
        budget = cap - st["headroom"]
        center_blk = np.floor_divide(center, LEAF)
        full_blk = -(-full // LEAF)             # rings of blocks the full box can touch
        stored = self.store.count_blocks_by_ring(center_blk, full_blk)
        if live + int(stored.sum()) <= budget:
            if st["shrunk"]:
                log.info("live window back to its full size (%d live blocks)", live)
                st["shrunk"] = False
            return full
        rings = np.zeros(int(full_blk[0]) + 1, np.int32)
        if self.center_vox is not None:
            window.blocks_by_ring(m, _ivec(np.floor_divide(self.center_vox, LEAF)),
                                  _ivec(center_blk), _ivec(full_blk), rings)
        within = np.cumsum(rings + stored)      # blocks within ring r: the box of half 4r holds
        fits = np.flatnonzero(within <= budget)
        r = int(fits.max()) if len(fits) else -1
        if r >= full_blk[0]:
            return full
        # every voxel a scan touches lies within _limit + kernel radius of its centre voxel
        reach = int(self._limit[:2].max()) + self.radius_vox
        r_min = -(-reach // LEAF)
        if r < r_min:
            raise ValueError(
                f"the live map cannot stay under max_live_blocks={cap}: the smallest window that "
                f"holds a scan (+-{reach * self.res:.0f} m) has "
                f"{int(within[min(r_min, len(within) - 1)])} blocks here, and a scan adds up to "
                f"{st['headroom']}; raise max_live_blocks (~5.7 KB each) or lower max_range_m")
        if not st["shrunk"]:
            log.warning("the map around the sensor needs more than max_live_blocks=%d blocks: "
                        "live window shrunk to +-%.0f m (farthest blocks go to the store)",
                        cap, r * LEAF * self.res)
            st["shrunk"] = True
        half = full.copy()
        half[:2] = r * LEAF                     # a box of half 4r voxels touches rings <= r
        return half

    # ------------------------------------------------------------------ query and export
    def query(self, points_world: np.ndarray, with_probs: bool = True):
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
        local = pts - self.origin_vox * self.res
        if not finite.all():
            local[~finite] = 0.0
        local = np.clip(local, -FAR_M, FAR_M, out=local).astype(np.float32)
        inside = np.zeros(n, np.int32)
        out_prob = probs if with_probs else np.zeros((0, self.C), np.float32)
        kquery.query(self.fields, local, _ivec(self.center_vox), _ivec(self.half_vox),
                     1.0 / self.res, labels, inside, out_prob, int(with_probs))
        rest = finite & (inside == 0)
        if len(self.store) and rest.any():
            # the voxel index exactly as the kernel computes it (float32 local * 1/res), so a
            # point on a voxel face finds the same voxel live or stored
            vox = np.floor(local[rest] * np.float32(1.0 / self.res)).astype(np.int64)
            ok = np.all(np.abs(vox) <= KEY_LIMIT, axis=1)
            counts = np.zeros((len(vox), self.C), np.float32)
            counts[ok], _ = self.store.lookup(vox[ok])
            snap = MapSnapshot(np.zeros((len(counts), 3), np.int64), counts,
                               np.zeros(len(counts)), np.zeros(len(counts), np.float32), self.res)
            labels[rest] = snap.labels()
            if with_probs:
                probs[rest] = snap.probabilities()
        return labels, probs

    def _live_arrays(self):
        self._check_alive()
        m = self.fields
        n = kquery.count_active(m.t_last)
        keys = np.zeros((n, 3), np.int32)
        counts = np.zeros((n, self.C), np.float32)
        t_last = np.zeros(n, np.float32)
        ell = np.zeros(n, np.float32)
        if n:
            center = _ivec(self.center_vox)
            got = kquery.export_voxels(m, center, keys, counts, t_last, ell)
            assert got == n, f"export found {got} voxels, count found {n}"
        return keys, counts, t_last, ell

    @property
    def live_voxels(self) -> int:
        return int(kquery.count_active(self.fields.t_last))

    @property
    def live_blocks(self) -> int:
        return int(kquery.count_active(self.fields.blk))

    @property
    def stored_voxels(self) -> int:
        return len(self.store)

    def snapshot(self) -> MapSnapshot:
        """The whole map (live window and store) as host arrays, sorted by key."""
        if self.origin_vox is None:
            C = self.C
            return MapSnapshot(np.zeros((0, 3), np.int64), np.zeros((0, C), np.float32),
                               np.zeros(0), np.zeros(0, np.float32), self.res)
        parts = [self._live_arrays(), self.store.arrays()]
        keys = np.concatenate([p[0] for p in parts]).astype(np.int64) + self.origin_vox
        counts = np.concatenate([p[1] for p in parts])
        t_last = np.concatenate([p[2] for p in parts]).astype(np.float64) + self.t0
        ell = np.concatenate([p[3] for p in parts])
        order = MapSnapshot.sort_order(keys)
        return MapSnapshot(keys[order], counts[order], t_last[order], ell[order], self.res)

    def state(self) -> dict:
        """Scalars that, with `snapshot()`, rebuild this mapper exactly (for checkpoints)."""
        return {"origin_vox": None if self.origin_vox is None else self.origin_vox.tolist(),
                "t0": self.t0, "center_vox": None if self.center_vox is None else self.center_vox.tolist(),
                "scans": self.scans, "last_stamp_s": self.last_stamp_s}

    def restore(self, snapshot: MapSnapshot, state: dict) -> None:
        """Load a snapshot written by `snapshot()` (with `state()`), into an empty mapper."""
        if self.origin_vox is not None:
            raise RuntimeError("restore() needs a fresh mapper")
        if abs(snapshot.resolution_m - self.res) > 1e-9:
            raise ValueError(f"snapshot resolution {snapshot.resolution_m} m != mapper {self.res} m")
        if snapshot.counts.shape[1] != self.C:
            raise ValueError(f"snapshot has {snapshot.counts.shape[1]} classes, mapper {self.C}")
        if state.get("origin_vox") is None:
            return
        self.origin_vox = np.asarray(state["origin_vox"], np.int64)
        self.t0 = float(state["t0"])
        self.scans = int(state.get("scans", 0))
        self.last_stamp_s = state.get("last_stamp_s")
        keys = snapshot.keys - self.origin_vox
        # everything goes to the store first; the window then pulls in what it covers
        self.store.put(keys, snapshot.counts.astype(np.float32),
                       (snapshot.t_last - self.t0).astype(np.float32), snapshot.ell_m.astype(np.float32))
        center = state.get("center_vox")
        self._move_window(np.asarray(center if center is not None else [0, 0, 0], np.int64))
