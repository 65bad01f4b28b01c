"""Steps 2-8 of one scan on the scan table: voxelize, filter, kernel length, kernel update.

The mapper decides what a scan is (its checks, pose, time and the live window); this integrator
runs the kernels that turn its checked points into evidence on the live voxels, in the order of
the method, and keeps the scan-sized buffers they share between scans. It holds no map state of
its own: the fields, the scan constants and the window are the mapper's.
"""

from __future__ import annotations

import logging

import numpy as np

from tisem import backend
from tisem.block_cap import cut_to_nearest, new_blocks_beyond
from tisem.config import MapperConfig
from tisem.geometry import MapGeometry
from tisem.integration_report import IntegrationReport
from tisem.kernel_inputs import KernelSettings
from tisem.kernels import bki, entropy, fusion, rasterize, table, training
from tisem.kernels.layout import MapFields
from tisem.live_window import LiveWindow
from tisem.preprocess import CheckedScan
from tisem.scan import Scan, scan_label
from tisem.scan_buffers import ScanBuffers, ScanPoints, TrainingRows
from tisem.trace import IntegrationTrace

log = logging.getLogger(__name__)


class ScanIntegrator:
    """The kernel steps of `Mapper.integrate`, for one map's fields and settings."""

    def __init__(
        self,
        fields: MapFields,
        params,
        settings: KernelSettings,
        config: MapperConfig,
        geometry: MapGeometry,
        window: LiveWindow,
    ) -> None:
        self._fields = fields
        self._params = params  # the scan constants: the mapper writes them before each scan
        self._settings = settings
        # (a CPU lists each block's points in the scan's order, in one thread: kernels/rasterize.py)
        self._points_in_order = backend.on_cpu()
        self._min_points = config.min_points
        self._num_classes = config.num_classes
        self._resolution_m = geometry.resolution_m
        self._window = window
        self._cap_inv2 = bki.evidence_cap_table(config.evidence_caps_m)
        self._buf = ScanBuffers()

    def voxelize(
        self,
        checked: CheckedScan,
        report: IntegrationReport,
        trace: IntegrationTrace | None,
        origin_vox: np.ndarray,
    ) -> ScanPoints:
        """Step 2: locate every point in the scan's table of leaf blocks and list each block's
        points together (`origin_vox` only places the trace's voxels in the world)."""
        m = self._fields
        pts = self._buf.points(len(checked.points_sensor))
        stats = rasterize.locate_kernel(checked.use_probs)(
            m, self._params, checked.kernel_points, checked.evidence, pts.cell, pts.code, pts.blocks
        )
        report.used = int(stats[rasterize.USED])
        report.dropped_range = int(stats[rasterize.OUT_OF_RANGE]) - report.dropped_nonfinite
        report.dropped_band = int(stats[rasterize.OUT_OF_BAND])
        report.dropped_window = int(stats[rasterize.OUT_OF_WINDOW])
        report.dropped_far = int(stats[rasterize.IMPLAUSIBLY_FAR]) - report.dropped_nonfinite
        # in table order (x, y, z), so that the per-block passes touch the map block by block
        # along columns, as the kernel update will (~1 ms less than the points' order)
        pts = pts._replace(blocks=pts.blocks[: int(stats[rasterize.BLOCKS])])
        pts.blocks.sort()
        table.column_slots(m, table.points_in, m.p_start, True)
        rasterize.scatter_kernel(self._points_in_order)(m, pts.cell, pts.by_block)
        if trace is not None:
            trace.points_located(
                pts.cell,
                pts.code,
                pts.blocks,
                pts.by_block[: report.used],
                m.table_half,
                self._window.center_vox,
                origin_vox,
                self._resolution_m,
            )
        return pts

    def training_points(
        self,
        checked: CheckedScan,
        pts: ScanPoints,
        report: IntegrationReport,
        trace: IntegrationTrace | None,
    ) -> TrainingRows:
        """Step 3: sort each block's points by voxel, filter the voxels, write the kept ones'
        training rows."""
        m = self._fields
        training.sort_blocks(m, self._min_points, pts.blocks, pts.code, pts.by_block, pts.by_voxel)
        n = table.column_slots(m, table.rows_in, m.b_start, False)
        report.training_voxels = int(n)
        rows = self._buf.training(max(n, 1), self._num_classes)
        training.training_kernel(self._settings.unit_weight, checked.use_probs, m.class_centroids)(
            m,
            self._params,
            checked.kernel_points,
            checked.evidence,
            pts.blocks,
            pts.code,
            pts.by_voxel,
            *rows,
        )
        if trace is not None:
            trace.training_written(
                n, m.b_start.to_numpy(), m.b_layers.to_numpy(), rows.xyz, rows.hist
            )
        return rows

    def hold_block_cap(
        self,
        scan: Scan,
        checked: CheckedScan,
        pts: ScanPoints,
        rows: TrainingRows,
        report: IntegrationReport,
        trace: IntegrationTrace | None,
        origin_vox: np.ndarray,
    ) -> tuple[ScanPoints, TrainingRows]:
        """Keep the live blocks under max_live_blocks (tisem/block_cap.py): a scan whose
        training rows would make more blocks live than there is room for keeps only its points
        in live blocks and in the nearest new blocks (steps 2-3 again on those), or is refused
        when that leaves none. The common case costs one comparison: the occupied blocks fit."""
        free = self._window.free_blocks
        new = new_blocks_beyond(self._fields, self._params, pts.blocks, free)
        if new is None:
            return pts, rows
        m, where = self._fields, scan_label(scan.index, scan.name)
        cut = cut_to_nearest(
            pts.cell, pts.blocks, new, m.table_shape, m.table_half, free, self._resolution_m
        )
        table.clear_table(m)
        cap = self._window.cap
        if not cut.keep.any():
            raise ValueError(cut.refusal(where, cap, report.used))
        log.warning(cut.describe(where, cap, report.used))
        kept = checked.subset(cut.keep)
        again = IntegrationReport(points=len(kept.points_sensor))
        if trace is not None:
            trace.scans.pop()  # the trace records the points the scan kept
        pts = self.voxelize(kept, again, trace, origin_vox)
        rows = self.training_points(kept, pts, again, trace)
        if trace is not None:
            trace.scans[-1].cut_points = np.flatnonzero(cut.keep)
        report.dropped_dense = report.used - again.used
        report.used, report.training_voxels = again.used, again.training_voxels
        return pts, rows

    def assign_lengths(self, pts: ScanPoints, rows: TrainingRows) -> None:
        """Steps 4-5: the semantic uncertainty and kernel length of the voxels the training
        points hit (and, with class centroids, where in them each class's points lie)."""
        entropy.assign_lengths(
            self._fields,
            self._params,
            pts.blocks,
            rows.voxel,
            rows.cent,
            self._settings.kernel_length,
            self._settings.decay,
        )

    def update(self, pts: ScanPoints, rows: TrainingRows, n_rows: int) -> None:
        """Steps 6-8: the kernel update of every live voxel within reach of the n_rows training
        points and its fusion; csm (no kernel) adds each training voxel's own histogram."""
        m, p, settings = self._fields, self._params, self._settings
        if not settings.uses_kernel:
            fusion.fuse_histograms(m, p, pts.blocks, rows.voxel, rows.hist)
        elif n_rows:
            bki.update_kernel(settings)(
                m, p, rows.xyz, rows.hist, rows.classes, rows.single, self._cap_inv2
            )
