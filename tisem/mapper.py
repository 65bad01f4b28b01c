"""The mapper: the paper's steps, in order, over one live window plus a host store.

    mapper = Mapper(MapperConfig(mode="st"))
    mapper.integrate(scan)                      # a tisem.scan.Scan
    labels, probs = mapper.query(points_world)  # (N,) train ids, (N, C) probabilities

Python checks every input and every index range before a kernel sees it (Taichi does not check
indices in release mode); the kernels in `kernels/` do the per-point and per-voxel work (their
step -> module table: kernels/__init__.py). Sizes come from `tisem.geometry.MapGeometry`, the
live window and its store from `tisem.live_window.LiveWindow`.

Bad input costs the scan that carries it, never the map: a bad pose, stamp, id or probability
(`tisem.scan`, `tisem.map_clock`) is refused with a ScanError naming the scan, and a scan too
dense for the block cap is cut (`tisem.block_cap`), before the map changes; a full disk under
the store raises `tisem.spill.SpillError` with the map as it was.
"""

from __future__ import annotations

import contextlib
import time

import numpy as np
import taichi as ti

from tisem import backend
from tisem.config import MapperConfig
from tisem.errors import ScanError
from tisem.free_space import FreeSpace, class_inv_tau, without_moving
from tisem.geometry import MapGeometry, block_aligned_origin
from tisem.integration_report import IntegrationReport
from tisem.kernel_inputs import kernel_settings, scan_params, set_scan
from tisem.kernels import bki, table
from tisem.kernels.layout import CENTROID_COLS, MapFields
from tisem.live_window import LiveWindow
from tisem.map_clock import MapClock
from tisem.mapper_state import check_snapshot, parse_state, relative_arrays
from tisem.preprocess import CheckedScan, check_scan
from tisem.scan import Scan, checked_query_points, checked_stamp, scan_label
from tisem.scan_integrator import ScanIntegrator
from tisem.snapshot import MapSnapshot
from tisem.store import KEY_LIMIT, BlockStore
from tisem.trace import IntegrationTrace
from tisem.voxel_arrays import VoxelArrays, snapshot_of

# the timed stages of `integrate` (profile=True), one per step of its recipe: the checks and the
# pose; the live window; locating the points and sorting them by leaf block; sorting them by
# voxel, the filter and the training points; the kernel lengths; the kernel update and fusion
# (with the adaptive lengths' entropy, fused in its pass over the map); free space (the dynamic
# points' flags, the hits and the rays; 0 when off); resetting the table
STAGES = ("preprocess", "window", "voxelize", "filter", "length", "update", "free_space", "clear")


class Mapper:
    """A spatio-temporal semantic map, in any of the modes of `MapperConfig`.

    `parallel_loop`: the kernel update's parallel loop, "block" (one task per leaf block: CPUs)
    or "voxel" (one thread per voxel: GPUs); None picks by the running arch.
    """

    def __init__(
        self,
        config: MapperConfig | None = None,
        *,
        profile: bool = False,
        parallel_loop: str | None = None,
    ):
        self.config = config or MapperConfig()
        self.config.validate()
        cfg = self.config
        if parallel_loop not in (None, "block", "voxel"):
            raise ValueError(
                f"parallel_loop must be 'block', 'voxel' or None, got {parallel_loop!r}"
            )
        self.geometry = MapGeometry.from_config(cfg)
        # before the runtime's one map slot is taken: a bad config or a missing store_dir is
        # refused with the runtime still free for another map
        # (with free space the occupancy evidence is the store's last counter column)
        self.store = BlockStore(
            cfg.num_classes + int(cfg.free_space) + CENTROID_COLS * int(cfg.class_centroids),
            spill_dir=cfg.store_dir,
        )
        self._generation = backend.claim_map_slot()
        self.C = cfg.num_classes
        if parallel_loop is None:
            parallel_loop = "block" if backend.on_cpu() else "voxel"
        self._settings = kernel_settings(cfg, per_voxel=parallel_loop == "voxel")
        self._fields = MapFields(
            self.C,
            self.geometry.storage_extent,
            self.geometry.table_half_blk,
            cfg.free_space,
            cfg.empty_evidence,
            cfg.occupancy_cap,
            class_centroids=cfg.class_centroids,
            compact_counters=cfg.compact_counters,
            seen_empty_s=cfg.seen_empty_s,
            spare_beside_unseen=cfg.spare_beside_unseen,
            spare_static_beside_own=cfg.spare_static_beside_own,
            spare_thin_static=cfg.spare_thin_static,
            thin_static_hold_s=cfg.thin_static_hold_s,
            thin_static_crossings=cfg.thin_static_crossings,
        )
        bki.fill_kernel_table(self._fields)
        self._fields.class_inv_tau.from_numpy(class_inv_tau(cfg))
        self._free = None
        if cfg.free_space:
            self._free = FreeSpace(
                self._fields, cfg, self._settings.decay, self.geometry.window_half_vox
            )
        self.window = LiveWindow(self._fields, self.store, self.geometry, cfg.max_live_blocks)
        self._params = scan_params(cfg, self.geometry)
        self._steps = ScanIntegrator(
            self._fields, self._params, self._settings, cfg, self.geometry, self.window
        )
        self.origin_vox: np.ndarray | None = None  # global voxel index of local voxel 0
        self.clock = MapClock(cfg.decay_tau_s)  # map time: seconds since the first scan
        self.scans = 0
        self.last_stamp_s: float | None = None
        self.profile = profile
        self.stage_seconds = {s: 0.0 for s in STAGES}

    @property
    def t0(self) -> float | None:
        """Stamp of the first scan: map time 0 (None before it)."""
        return self.clock.state.t0

    # ------------------------------------------------------------------ integrate
    def integrate(self, scan: Scan, trace: IntegrationTrace | None = None) -> IntegrationReport:
        """Fuse one scan into the map (steps 1-8 of the method); `trace` records each step.

        A scan that cannot be mapped (a bad pose or stamp, evidence out of range, too far from
        the map origin, too dense for the block cap with nothing left) raises a ScanError (a
        ValueError) naming it, and a full disk under the store SpillError, before the map
        changes."""
        self._check_alive()
        steps = self._steps
        report = IntegrationReport(points=scan.num_points)
        timer = self._timer()
        with self._one_scan(scan):
            # 1. preprocess: check everything, drop non-finite points, the pose and the time
            # in map coordinates
            checked, center_vox, map_time = self._preprocess(scan, report)
            timer("preprocess")
            # the live window follows the sensor: what it leaves goes to the store, what it
            # reaches comes back from there
            moved = self.window.follow(center_vox)
            report.evicted_voxels = moved.evicted_voxels
            report.reloaded_voxels = moved.reloaded_voxels
            timer("window")
            if self._free is not None:
                # what lands in space seen empty is dynamic; moving points add no evidence
                self._free.forget_if_wrapped(map_time, center_vox)
                checked = self._flag_dynamic(scan, checked, report)
                timer("free_space")
            # 2. downsample / voxelize: range and window checks, the points sorted by leaf block
            points = steps.voxelize(checked, report, trace, self.origin_vox)
            timer("voxelize")
            # 3. redundant-voxel filter, then per kept voxel a training point: its centroid and
            # class histogram, sorted by leaf block; a scan that would make more blocks live
            # than the cap has room for is cut to its nearest blocks (nothing is live yet)
            rows = steps.training_points(checked, points, report, trace)
            points, rows = steps.hold_block_cap(
                scan, checked, points, rows, report, trace, self.origin_vox
            )
            timer("filter")
            # 4-5. semantic uncertainty and kernel length of the voxels the training points hit
            steps.assign_lengths(points, rows)
            timer("length")
            # 6-8. sparse kernel, Bayesian kernel update and temporal fusion of every live
            # voxel within reach of a training point
            steps.update(points, rows, report.training_voxels)
            timer("update")
            if self._free is not None:
                # hits, then rays from the sensor to the training points clear what they cross
                report.freed_voxels = self._free.integrate(
                    self._params, rows, report.training_voxels
                )
                report.seen_empty_blocks = self._free.forget(map_time)
                timer("free_space")
            table.clear_table(self._fields)  # the scan's table, empty again for the next scan
            timer("clear")
        self.clock.advance(scan.stamp_s, map_time)
        self.scans += 1
        self.last_stamp_s = float(scan.stamp_s)
        return report

    @contextlib.contextmanager
    def _one_scan(self, scan: Scan):
        """Whatever stops a scan (a refusal, an interrupt), its table is emptied again and a
        first scan leaves no origin behind; a refusal leaves as a ScanError naming the scan
        (the run reports it as a skipped scan)."""
        first = self.origin_vox is None
        try:
            yield
        except BaseException as e:
            table.clear_table(self._fields)
            if first:
                self.origin_vox = None
            if not isinstance(e, ValueError) or isinstance(e, ScanError):
                raise
            where = scan_label(scan.index, scan.name)
            message = str(e) if str(e).startswith(where + ":") else f"{where}: {e}"
            raise ScanError(message, scan.index, scan.name) from e

    def _origin_of(self, scan: Scan) -> np.ndarray:
        """The map origin a first scan gives: block-aligned at the sensor's position, so that
        local coordinates stay small (float32 keeps mm precision within ~10 km of it)."""
        return block_aligned_origin(
            np.floor(scan.T_world_sensor[:3, 3] / self.geometry.resolution_m)
        )

    def _preprocess(
        self, scan: Scan, report: IntegrationReport
    ) -> tuple[CheckedScan, np.ndarray, float]:
        """Check the scan (its pose, stamp and evidence) and put its pose and time in map
        coordinates (the kernels do the per-point work); returns the checked
        scan, the sensor's voxel and the scan's map time. The first scan fixes the map's origin
        and clock only if it is mapped, so a bad first scan costs that scan alone."""
        checked = check_scan(scan, self.C)
        where = scan_label(scan.index, scan.name)
        stamp = checked_stamp(scan.stamp_s, where)
        report.dropped_nonfinite = checked.dropped_nonfinite
        res = self.geometry.resolution_m
        T = scan.T_world_sensor
        origin = self.origin_vox if self.origin_vox is not None else self._origin_of(scan)
        translation = T[:3, 3] - origin * res
        if np.any(np.abs(translation) / res + self.window.half_vox > KEY_LIMIT):
            raise ValueError(
                f"{where}: the sensor is "
                f"{np.abs(translation).max() / 1000:.0f} km from the map origin; "
                f"tisem maps within {KEY_LIMIT * res / 1000:.0f} km"
            )
        map_time = self.clock.time_of(stamp, where)
        self.origin_vox = origin  # (integrate takes a first scan's back if it fails)
        center_vox = np.floor(translation / res).astype(np.int64)
        set_scan(self._params, T[:3, :3], translation, center_vox, map_time, self.scans + 1)
        return checked, center_vox, map_time

    def _flag_dynamic(
        self, scan: Scan, checked: CheckedScan, report: IntegrationReport
    ) -> CheckedScan:
        """The free-space flags of the scan's points (before it changes the map), and the scan
        without the evidence of the points flagged dynamic."""
        to_local = (scan.T_world_sensor, self.origin_vox * self.geometry.resolution_m)
        report.dynamic = self._free.flag_points(
            self._params, checked, self.window.half_vox, scan.moving, to_local
        )
        report.dynamic_points = int(report.dynamic.sum())
        return without_moving(checked, report.dynamic)

    def _check_alive(self) -> None:
        if self._generation != backend.generation():
            raise RuntimeError(
                "this map belonged to a Taichi runtime that has since been "
                "re-initialised (init_taichi); its fields are gone"
            )

    def _timer(self):
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
    def query(
        self, points_world: np.ndarray, with_probs: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Labels (N,) int32 train ids and probabilities (N, C) float32 of world points.

        A point whose voxel holds no evidence gets, with query_blend `missing`, the
        kernel-weighted posterior of the voxels within query_radius_m (in the live window,
        of the live ones; outside it, of the live and stored ones); otherwise (none there, or
        query_blend `off`) label 0 and all-zero probabilities.
        """
        self._check_alive()
        pts = checked_query_points(points_world)
        n = len(pts)
        labels = np.zeros(n, np.int32)
        probs = np.zeros((n, self.C), np.float32) if with_probs else None
        if self.origin_vox is None or n == 0:
            return labels, probs
        blend = self.config.query_radius_m if self.config.query_blend == "missing" else 0.0
        self.window.lookup_world(
            pts, self.origin_vox, labels, probs, blend, self.config.centroid_ratio
        )
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
        cfg = self.config
        return snapshot_of(
            parts,
            self.origin_vox,
            self.t0,
            self.geometry.resolution_m,
            self.C,
            cfg.empty_evidence if self._free is not None else None,
            cfg.centroid_ratio if cfg.class_centroids else None,
        )

    def state(self) -> dict:
        """Scalars that, with `snapshot()`, rebuild this mapper exactly (for checkpoints)."""
        center = self.window.center_vox
        return {
            "origin_vox": None if self.origin_vox is None else self.origin_vox.tolist(),
            "t0": self.t0,
            "center_vox": None if center is None else center.tolist(),
            "scans": self.scans,
            "last_stamp_s": self.last_stamp_s,
            "clock": self.clock.to_dict(),
        }

    def restore(self, snapshot: MapSnapshot, state: dict) -> None:
        """Load a snapshot written by `snapshot()` (with `state()`), into an empty mapper.
        ValueError, with the mapper left empty, when a value does not fit (mapper_state.py)."""
        res = self.geometry.resolution_m
        if self.origin_vox is not None or self.scans:
            raise RuntimeError("restore() needs a fresh mapper")
        check_snapshot(snapshot, self.C, res)
        saved = parse_state(state, res, self.config.decay_tau_s)
        if saved.origin_vox is None:
            return
        # everything goes to the store first; the window then pulls in what it covers
        occupancy = None
        if self._free is not None:  # (a map saved without free space starts with none)
            occupancy = (
                np.zeros(len(snapshot), np.float32)
                if snapshot.occupancy is None
                else np.asarray(snapshot.occupancy, np.float32)
            )
        centroids = None
        if self.config.class_centroids:  # (a map saved without them starts with none)
            centroids = (
                np.zeros((len(snapshot), CENTROID_COLS), np.float32)
                if snapshot.centroids is None
                else np.asarray(snapshot.centroids, np.float32)
            )
        segments = self.store.put(
            *VoxelArrays(*relative_arrays(snapshot, saved), occupancy, centroids).arrays()
        )
        try:
            self.window.follow(saved.center_vox)
        except BaseException:  # (the map does not fit the cap): the mapper stays empty
            self.store.forget_last(segments)
            raise
        self.origin_vox = saved.origin_vox
        self.clock = saved.clock
        self.scans = saved.scans
        self.last_stamp_s = saved.last_stamp_s
