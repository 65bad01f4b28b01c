"""An optional record of what each step of `Mapper.integrate` produced, for tests and debugging.

    trace = IntegrationTrace()
    mapper.integrate(scan, trace=trace)
    step = trace.scans[-1]          # a ScanTrace: numpy copies, global voxel keys

The mapper fills it only when one is passed (copying the arrays a step produced, and the scan's
table after step 3), so integrating without a trace costs nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tisem.kernels.layout import LAYER_BITS, LEAF
from tisem.kernels.rasterize import DROPPED, EVIDENCE


@dataclass
class ScanTrace:
    """One scan, step by step.

    Step 2, where the points landed (N: the scan's points):
      point_cell (N,) int32: each point's cell in the scan's table of leaf blocks (-1: dropped);
      point_voxel (N, 3) int64: each kept point's global voxel key (zeros where dropped);
      point_has_evidence (N,) bool: the kept point carries class evidence;
      occupied_cells (B,) int32: the table cells the step listed as holding points;
      block_order (P,) int32: the kept points (indices into the scan) sorted by leaf block.
    Step 3, the training points (one row per voxel the filter kept):
      training_rows: how many rows the scan's table handed out;
      row_start (T,) int32 and layer_rows (T, LEAF) int32: per table cell (T cells, flattened
        in the table's order), its first row and its rows up to the end of each z layer;
      training_xyz (K, 3) float32: the rows' centroids in local map metres (K = training_rows);
      training_hist (K, C) float32: the rows' class evidence (weighted per point_weight);
      origin_vox (3,) int64, resolution_m: to turn local coordinates into world ones.
    A scan too dense for the block cap (tisem/block_cap.py) is traced as cut:
      cut_points (N,) int64: the indices into the scan of the points it kept, which the
        per-point arrays above then cover (None: nothing was cut).
    """

    point_cell: np.ndarray
    point_voxel: np.ndarray
    point_has_evidence: np.ndarray
    occupied_cells: np.ndarray
    block_order: np.ndarray
    origin_vox: np.ndarray
    resolution_m: float
    training_rows: int = 0
    row_start: np.ndarray | None = None
    layer_rows: np.ndarray | None = None
    training_xyz: np.ndarray | None = None
    training_hist: np.ndarray | None = None
    cut_points: np.ndarray | None = None

    @property
    def kept(self) -> np.ndarray:
        """(N,) bool: the points the scan uses."""
        return self.point_cell != DROPPED


@dataclass
class IntegrationTrace:
    """The ScanTrace of every scan integrated with this trace, in order."""

    scans: list[ScanTrace] = field(default_factory=list)

    def points_located(
        self,
        cell: np.ndarray,
        code: np.ndarray,
        occupied: np.ndarray,
        block_order: np.ndarray,
        table_half: tuple,
        center_vox: np.ndarray,
        origin_vox: np.ndarray,
        resolution_m: float,
    ) -> None:
        """Step 2 of a new scan: the kernels' per-point cells and voxel codes, the list of
        occupied cells and the block sort, decoded with the table's geometry."""
        kept = cell != DROPPED
        table_shape = tuple(2 * h + 1 for h in table_half)
        cells = np.stack(np.unravel_index(cell[kept], table_shape), axis=1)
        world_blk = cells - np.array(table_half) + np.floor_divide(center_vox, LEAF)
        q = code[kept] % EVIDENCE
        local = np.stack([q % LEAF, (q // LEAF) % LEAF, q // (LEAF * LEAF)], axis=1)
        voxel = np.zeros((len(cell), 3), np.int64)
        voxel[kept] = world_blk * LEAF + local + origin_vox
        evidence = np.zeros(len(cell), bool)
        evidence[kept] = code[kept] // EVIDENCE > 0
        self.scans.append(
            ScanTrace(
                cell.copy(),
                voxel,
                evidence,
                occupied.copy(),
                block_order.copy(),
                np.array(origin_vox, np.int64),
                float(resolution_m),
            )
        )

    def training_written(
        self,
        rows: int,
        row_start: np.ndarray,
        layers: np.ndarray,
        xyz: np.ndarray,
        hist: np.ndarray,
    ) -> None:
        """Step 3 of the current scan: the row count, the table's packed slices (b_start,
        b_layers) and the training arrays."""
        s = self.scans[-1]
        s.training_rows = int(rows)
        s.row_start = row_start.ravel().copy()
        packed = layers.ravel()
        s.layer_rows = np.stack(
            [(packed >> (LAYER_BITS * k)) & ((1 << LAYER_BITS) - 1) for k in range(LEAF)], axis=1
        )
        s.training_xyz = xyz[:rows].copy()
        s.training_hist = hist[:rows].copy()
