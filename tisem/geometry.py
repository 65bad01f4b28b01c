"""Map geometry: the sizing rules of a map, in plain Python (no Taichi runtime needed).

Every size the map's fields and kernels are built with follows from the config here: the live
window, how far from the sensor a kept point may lie, the scan's dense table of leaf blocks,
the kernel's reach and the toroidal storage extent. Impossible configurations are refused with
the figure that does not fit before any field exists.

The layout's constants come from kernels/layout.py when first needed, not at import: that
module imports taichi, and `import tisem` and `tisem.load_map` must stay cheap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tisem.config import MapperConfig


def block_aligned_origin(voxel: np.ndarray) -> np.ndarray:
    """The map origin (int64 global voxel index) for a map centred near `voxel`: aligned to
    a top cell of the SNode tree, so that local indices stay small and the tree's cells line
    up with the global grid."""
    from tisem.kernels.layout import TOP

    return (np.asarray(voxel, np.int64) // TOP) * TOP


@dataclass(frozen=True)
class MapGeometry:
    """The sizes of one map (voxels unless the name says otherwise).

    window_half_vox: the configured live window, |w - centre| <= half per axis;
    point_limit_vox: a scan point whose voxel is farther than this from the sensor's is
        dropped (counted as outside the window), so that no kernel reaches past the window and
        every training voxel fits the scan's table;
    kernel_radius_vox: how far from a training point's voxel its kernel can reach a voxel
        centre (0 without a kernel);
    reach_blk: the longest kernel, in leaf blocks;
    table_half_blk: half-size of the scan's dense table of leaf blocks around the sensor;
    storage_extent: the power-of-two toroidal extent of the map's fields.
    """

    resolution_m: float
    window_half_vox: np.ndarray
    point_limit_vox: np.ndarray
    kernel_radius_vox: int
    reach_blk: int
    table_half_blk: tuple[int, int, int]
    storage_extent: tuple[int, int, int]

    @classmethod
    def from_config(cls, cfg: MapperConfig) -> MapGeometry:
        """The geometry of a map with this config; ValueError if the config cannot work."""
        from tisem.kernels.layout import (
            LEAF,
            MAX_REACH_BLK,
            MAX_TABLE_CELLS,
            TABLE_BYTES_PER_CELL,
            storage_extent,
            table_half_blocks,
        )

        res = float(cfg.resolution_m)
        reach = cfg.reach_m
        radius_vox = int(math.ceil(reach / res + 0.5)) if cfg.uses_kernel else 0
        reach_blk = int(math.ceil(reach / (LEAF * res)))
        # every scan point plus its kernel reach must fit inside the window
        need_xy = cfg.max_range_m + reach + LEAF * res
        need_z = max(abs(cfg.min_z_m), abs(cfg.max_z_m)) + reach + LEAF * res
        if cfg.window_xy_m < need_xy or cfg.window_z_m < need_z:
            raise ValueError(
                f"window_xy_m={cfg.window_xy_m} / window_z_m={cfg.window_z_m} must hold the scan "
                f"(max_range + kernel reach): need >= {need_xy:.1f} m / {need_z:.1f} m"
            )
        half_vox = np.array(
            [math.ceil(cfg.window_xy_m / res)] * 2 + [math.ceil(cfg.window_z_m / res)], np.int64
        )
        if reach_blk > MAX_REACH_BLK:
            raise ValueError(
                f"kernel reach {reach} m is longer than {MAX_REACH_BLK} leaf blocks "
                f"({MAX_REACH_BLK * LEAF * res:.2f} m at {res} m voxels)"
            )
        # Any point within max_range is inside in x and y; in z the window bounds it (a tilted
        # sensor's far points can lie well above or below its own height band).
        scan_half = np.array([math.ceil(cfg.max_range_m / res) + 1] * 2 + [half_vox[2]], np.int64)
        limit = np.minimum(half_vox - radius_vox - 1, scan_half)
        table_half = table_half_blocks(limit, reach_blk)
        cells = int(np.prod([2 * h + 1 for h in table_half]))
        if cells >= MAX_TABLE_CELLS:
            raise ValueError(
                f"max_range_m={cfg.max_range_m} at resolution_m={res} needs a scan table of "
                f"{cells:,} leaf blocks ({cells * TABLE_BYTES_PER_CELL / 2**30:.0f} GiB); tisem "
                f"takes at most {MAX_TABLE_CELLS:,}: lower max_range_m or raise resolution_m"
            )
        return cls(
            res,
            half_vox,
            limit,
            radius_vox,
            reach_blk,
            table_half,
            storage_extent(tuple(int(h) for h in half_vox)),
        )

    @property
    def table_cells(self) -> int:
        return int(np.prod([2 * h + 1 for h in self.table_half_blk]))

    @property
    def scan_reach_vox(self) -> int:
        """How far from the sensor's voxel, in x and y, a scan can touch a voxel: its farthest
        kept point plus the kernel radius. The smallest live window must hold that."""
        return int(self.point_limit_vox[:2].max()) + self.kernel_radius_vox
